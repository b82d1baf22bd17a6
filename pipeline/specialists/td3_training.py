"""Training single-objective TD3 specialists, with secondary critics (paper: "Secondary Critics").

`train_specialists` trains S specialists in lockstep in one process: the specialists of every
objective of a seed, or of several seeds. Each keeps its own env, replay buffer, RNG streams
and minibatch draws, so each is exactly the TD3 specialist it would be alone; only the
networks are stacked, so one batched update serves all of them (see pipeline/specialists/td3.py). S = 1
is one specialist on its own (`train_specialist`).

`SpecialistsRun` is a pipeline.core.drive.Run (the stage drives it: checkpoints, SIGTERM,
progress); the run prints nothing.

Devices: on a CPU the buffers are CPU tensors and minibatch rows are drawn with each
specialist's numpy generator (the same stream as its exploration noise). On CUDA the buffers
live on the GPU, rows are drawn on the GPU from a per-specialist torch generator, and the
update runs as captured CUDA graphs (`td3.cuda_graphs`); the only per-step host
sync is reading the actions to step the envs (and, every CHECK_EVERY updates, the check that
the losses and weights are finite: pipeline.core.finite). The two devices therefore draw
different (each reproducible) minibatches.

Checkpoints: `SpecialistsRun.state_dict` holds every piece of a run's state (networks,
optimizers, replay buffers, RNG streams, counters, the episode history and each env's
mid-episode state, `env_state`), so a run restored after any step goes on bitwise as the
uninterrupted one on a CPU. Only MuJoCo envs (behind gymnasium's standard wrappers) can be
saved mid-episode; `env_checkpoint_problem` says why another cannot. On CUDA the state is
saved as CPU tensors and restored onto the device (untested here: no GPU).

Keep-best (train_specialist.keep_best_every > 0) is a hook on the loop that steps the run
(pipeline/specialists/keep_best.py, `keep_best_hook`); its records live in the run's state so
they are checkpointed with it.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.buffer import StackedReplay
from pipeline.core.checkpoint import cpu_copy
from pipeline.core.drive import fmt_vec, run_to_end
from pipeline.core.envs import EnvSpec
from pipeline.core.envstate import env_state, restore_env_state
from pipeline.core.finite import TrainingDiverged, due, first_nonfinite
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.core.precision import resolve
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.keep_best import KeepBest, keep_best_hook, keep_best_steps
from pipeline.specialists.td3 import Updater, init_stacked, run_seeds, unstack_actor
from pipeline.specialists.td3_state import (
    buffer_state,
    check_buffer_state,
    diverged_specialist,
    finite_named,
    load_buffer_state,
    load_nets_state,
    nets_state,
)


@dataclass
class EpisodeRecord:
    episode: int
    end_step: int  # global env step at which the episode ended (1-based count)
    length: int
    returns: np.ndarray  # (n_objectives,) undiscounted
    terminated: bool


@dataclass
class SpecialistResult:
    """What one trained specialist leaves behind (CPU modules, buffer rows oldest first)."""

    seed: int
    objective: int
    actor: Actor
    actor_target: Actor
    critic: CriticEnsemble
    critic_target: CriticEnsemble
    objectives: list[int]  # objectives its critic ensemble covers, in member order
    buffer: dict[str, np.ndarray]
    episodes: list[EpisodeRecord] = field(default_factory=list)
    keep_best: KeepBest | None = None  # None: keep-best off, `actor` is the final one


def exploration_actions(
    actor: StackedActor, obs: np.ndarray, noise_std: float, rngs: Sequence[np.random.Generator]
) -> np.ndarray:
    """pi_s(s_s) plus Gaussian noise (std noise_std times the action half-range) per specialist,
    clipped to the bounds: obs (S, o) -> (S, a). Reading the actions is the step's one host sync."""
    device = actor.scale.device
    with torch.no_grad():
        a = actor(torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(1))[:, 0].cpu().numpy()
    scale = actor.scale[:, 0].cpu().numpy()
    centre = actor.centre[:, 0].cpu().numpy()
    for s, rng in enumerate(rngs):
        a[s] += rng.normal(0.0, noise_std, size=a.shape[1]).astype(np.float32) * scale[s]
    return np.clip(a, centre - scale, centre + scale).astype(np.float32)


STATE_FORMAT = "mapex.specialists_state"
STATE_VERSION = 2  # 2: keep-best checks and snapshots


class SpecialistsRun:
    """S specialists jobs = [(seed, objective), ...] in training, in lockstep, specialist s on
    envs[s]: every piece of their state and one env step at a time (`step`).

    `state_dict` holds all of it (networks, optimizers, replay buffers, every RNG, the envs'
    mid-episode state, counters and episode history), so a run restored from it after any
    step (`load_state_dict`) goes on exactly as the uninterrupted run: bitwise on a CPU with
    the same thread count and library versions.
    """

    def __init__(
        self,
        envs: Sequence[gym.Env],
        spec: EnvSpec,
        td3: TD3Params,
        cfg: TrainSpecialistParams,
        jobs: Sequence[tuple[int, int]],
        device: torch.device,
        mix: Sequence[float] | None = None,
        fork_from: Callable[[], dict[str, Any]] | None = None,
    ):
        # `mix`: the run trains on the env's rewards plus one more, their weighted sum (the shared
        # prefix, td3.shared_prefix_steps): its buffer, critics and returns have n + 1 objectives,
        # objective n being the mixed one, which is what its jobs train
        self.mix = None if mix is None else np.asarray(mix, np.float64)
        if self.mix is not None:
            if self.mix.shape != (spec.n_objectives,):
                raise ValueError(
                    f"mix: {len(self.mix)} weights for the {spec.n_objectives} objectives of {spec.env_id}"
                )
            spec = dataclasses.replace(spec, n_objectives=spec.n_objectives + 1)
        # `fork_from`: the specialists start (in `start`) from that shared-prefix run's final
        # state (a `state_dict` of a run with `mix`), forked by `fork_state`
        self.fork_from = fork_from
        for seed, objective in jobs:
            if not 0 <= objective < spec.n_objectives:
                raise ValueError(
                    f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives"
                )
        if len(envs) != len(jobs):
            raise ValueError(f"{len(jobs)} specialists need as many envs, got {len(envs)}")
        self.envs, self.spec, self.td3, self.cfg = list(envs), spec, td3, cfg
        self.jobs = [(int(seed), int(objective)) for seed, objective in jobs]
        self.device = torch.device(device)
        n = len(jobs)
        self.seeds = [run_seeds(seed, objective) for seed, objective in self.jobs]
        self.state = init_stacked(spec, td3, self.jobs, self.device)
        # the updates' arithmetic (train_specialist.precision); acting in the env stays fp32
        self.precision = resolve(cfg.precision, self.device, max(td3.hidden_sizes))
        self.rngs = [np.random.default_rng(x["numpy"]) for x in self.seeds]
        for env, x in zip(self.envs, self.seeds):
            env.action_space.seed(x["space"])
        self.buffer = StackedReplay(n, td3.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives, self.device)
        self.update = Updater(self.state, self.buffer, td3, self.seeds, self.rngs, self.device, self.precision)
        self.episodes: list[list[EpisodeRecord]] = [[] for _ in range(n)]
        self.obs = np.stack([env.reset(seed=x["env"])[0] for env, x in zip(self.envs, self.seeds)]).astype(np.float32)
        self.episode = np.zeros(n, np.int64)
        self.ep_step = np.zeros(n, np.int64)
        self.ep_return = np.zeros((n, spec.n_objectives))
        # scratch rows, overwritten by every step
        self._next_obs = np.zeros_like(self.obs)
        self._reward = np.zeros((n, spec.n_objectives), np.float32)
        self._terminated = np.zeros(n, bool)
        self._truncated = np.zeros(n, bool)
        self.t = 0  # env steps taken by each specialist
        self.start_step = 0  # the step it started from: a forked run's shared prefix (its steps are not its own)
        self.full_check_at = -1  # the step of the last full finiteness check that passed
        self.n_updates = 0
        # keep-best: every check's (step, score) and the best snapshot ({step, score, actor,
        # actor_target}, CPU state dicts) per specialist; the evaluation envs are built at the first check
        self.checks: list[list[tuple[int, float]]] = [[] for _ in range(n)]
        self.best: list[dict[str, Any] | None] = [None] * n
        self.eval_envs: list[gym.Env] | None = None
        self.last: list[EpisodeRecord | None] = [None] * n  # per specialist, the episode the last step ended
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run (a step is short: unused)

    @property
    def done(self) -> bool:
        return self.t >= self.cfg.total_steps

    def step(self) -> list[EpisodeRecord | None]:
        """One env step of every specialist (and one update once learning has started, and a
        keep-best check where `keep_best_due`); returns, per specialist, the record of the
        episode this step ended, else None."""
        td3, envs, t = self.td3, self.envs, self.t
        if t < td3.learning_starts:
            actions = np.stack([np.asarray(env.action_space.sample(), dtype=np.float32) for env in envs])
        else:
            actions = exploration_actions(self.state.actor, self.obs, td3.exploration_noise, self.rngs)
        next_obs, reward, terminated, truncated = self._next_obs, self._reward, self._terminated, self._truncated
        for s, env in enumerate(envs):
            o, r, terminated[s], truncated[s], _ = env.step(actions[s])
            if self.mix is None:
                next_obs[s], reward[s] = o, r
            else:  # the shared prefix: the env's rewards, then their weighted sum
                next_obs[s], reward[s, :-1], reward[s, -1] = o, r, float(np.dot(self.mix, r))
        self.buffer.add(self.obs, actions, reward, next_obs, terminated, truncated, self.episode, self.ep_step)
        self.ep_return += reward
        self.ep_step += 1
        self.obs = next_obs.copy()
        records: list[EpisodeRecord | None] = [None] * len(envs)
        for s in np.flatnonzero(terminated | truncated):
            records[s] = EpisodeRecord(
                int(self.episode[s]), t + 1, int(self.ep_step[s]), self.ep_return[s].copy(), bool(terminated[s])
            )
            self.episodes[s].append(records[s])
            self.obs[s] = envs[s].reset()[0]
            self.episode[s] += 1
            self.ep_step[s] = 0
            self.ep_return[s] = 0.0
        if t >= td3.learning_starts:
            self.n_updates += 1
            self.update(update_actor=self.n_updates % td3.policy_freq == 0)
        self.t = t + 1
        if t >= td3.learning_starts and due(self.n_updates):
            self.check_finite()
        if self.checkpoint_due():
            self.check_finite(full=True)  # no checkpoint holds a diverged state
        self.last = records
        return records

    # -- the verbs of pipeline.core.drive.Run ---------------------------------------------

    def start(self) -> None:
        """Before the first step of a fresh run: a run with `fork_from` takes the shared prefix's
        state (`fork_state`); any other, nothing."""
        if self.fork_from is not None:
            self.load_state_dict(fork_state(self.fork_from(), self.state_dict(), self.spec))

    def finish(self) -> None:
        """The final `check_finite(full=True)`: no result holds a diverged state."""
        self.check_finite(full=True)

    def progress(self) -> tuple[int, str]:
        """Env steps of all specialists; the returns of the episodes the last step ended ("" if none)."""
        ended = [f"obj {k} {fmt_vec(r.returns)}" for (_, k), r in zip(self.jobs, self.last) if r is not None]
        return (self.t - self.start_step) * len(self.jobs), "; ".join(ended)

    def checkpoint_due(self) -> bool:
        """After every train_specialist.checkpoint_every-th env step but the last (none when it is 0)."""
        every = self.cfg.checkpoint_every
        return bool(every) and self.t > 0 and self.t % every == 0 and not self.done

    def where(self) -> str:
        return f"step {self.t}"

    def keep_best_record(self, s: int) -> KeepBest | None:
        """Specialist s's keep-best record so far (None when keep-best is off)."""
        if not self.cfg.keep_best_every:
            return None
        best = self.best[s]
        return KeepBest(
            every=self.cfg.keep_best_every,
            episodes=self.cfg.keep_best_episodes,
            checks=list(self.checks[s]),
            step=None if best is None else best["step"],
            score=None if best is None else best["score"],
        )

    def close(self) -> None:
        """Close the training envs and the evaluation envs."""
        for env in [*self.envs, *(self.eval_envs or [])]:
            env.close()

    def check_finite(self, full: bool = False) -> None:
        """Raise TrainingDiverged, naming the specialist (seed, objective) it found it in, if
        the latest losses or any weight is not finite (`finite_named`: with `full`, before a
        checkpoint or the results, also targets, optimizer moments and buffers). The step
        is the env step of the check."""
        bad = first_nonfinite(finite_named(self.update, full))
        if bad is None:
            if full:
                self.full_check_at = self.t
            return
        s = diverged_specialist(self.update)
        if s is not None:
            seed, objective = self.jobs[s]
        else:  # not to be told apart: name them all
            seeds = {seed for seed, _ in self.jobs}
            seed = seeds.pop() if len(seeds) == 1 else None
            objective = [k for _, k in self.jobs] if len(self.jobs) > 1 else self.jobs[0][1]
        raise TrainingDiverged(*bad, self.t, seed=seed, objective=objective)

    def results(self) -> list[SpecialistResult]:
        """Each specialist's networks (the final ones; with keep-best, the kept actor and its
        target actor), buffer rows and episode history."""
        state, n = self.state, len(self.jobs)
        e = state.critic.n_members // n
        out = []
        # a forked run makes the checks after its shared prefix only (the prefix made none)
        due_steps = [t for t in keep_best_steps(self.cfg, self.td3.learning_starts) if t > self.start_step]
        missing = due_steps[len(self.checks[0]) :] if n else []
        if missing and missing[0] <= self.t:
            raise RuntimeError(
                f"keep-best is on (train_specialist.keep_best_every = {self.cfg.keep_best_every}) but no check ran "
                f"at step {missing[0]}: step the run with keep_best_hook among its hooks (pipeline.core.drive)"
            )
        for s, (seed, objective) in enumerate(self.jobs):
            actor, actor_target = state.actor.unstack(s), state.actor_target.unstack(s)
            best = self.best[s] if self.cfg.keep_best_every else None
            if best is not None:
                actor.load_state_dict(best["actor"])
                actor_target.load_state_dict(best["actor_target"])
            out.append(
                SpecialistResult(
                    seed=seed,
                    objective=objective,
                    actor=actor,
                    actor_target=actor_target,
                    critic=state.critic.subset(s * e, (s + 1) * e).cpu(),
                    critic_target=state.critic_target.subset(s * e, (s + 1) * e).cpu().requires_grad_(False),
                    objectives=state.reward_index[s].tolist(),
                    buffer=self.buffer.chronological(s),
                    episodes=self.episodes[s],
                    keep_best=self.keep_best_record(s),
                )
            )
        return out

    # -- checkpoints ----------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything the run depends on from here, as CPU tensors and plain Python values
        (torch.load(weights_only=True) reads it back).

        The buffer rows are not copied when a full ring already lies on the CPU: they are the
        live ring, so save (or copy) the state before the next `step`.

        Every state passes `check_finite(full=True)` first (TrainingDiverged otherwise), the
        one a periodic checkpoint's step already ran or, for a checkpoint that is not due (on
        SIGTERM), one run here: no saved state is a diverged one."""
        if self.full_check_at != self.t:
            self.check_finite(full=True)
        cuda = self.device.type == "cuda"
        return {
            "format": STATE_FORMAT,
            "format_version": STATE_VERSION,
            "jobs": [list(j) for j in self.jobs],
            "counters": {"t": self.t, "n_updates": self.n_updates, "start": self.start_step},
            "nets": nets_state(self.state),
            "buffer": buffer_state(self.buffer),
            "loop": {
                "obs": torch.from_numpy(self.obs.copy()),
                "episode": torch.from_numpy(self.episode.copy()),
                "ep_step": torch.from_numpy(self.ep_step.copy()),
                "ep_return": torch.from_numpy(self.ep_return.copy()),
            },
            "episodes": [
                {
                    "episode": torch.tensor([r.episode for r in eps], dtype=torch.int64),
                    "end_step": torch.tensor([r.end_step for r in eps], dtype=torch.int64),
                    "length": torch.tensor([r.length for r in eps], dtype=torch.int64),
                    "terminated": torch.tensor([r.terminated for r in eps], dtype=torch.bool),
                    "returns": torch.from_numpy(
                        np.stack([r.returns for r in eps]) if eps else np.zeros((0, self.spec.n_objectives))
                    ),
                }
                for eps in self.episodes
            ],
            "rng": {
                "numpy": [copy.deepcopy(r.bit_generator.state) for r in self.rngs],
                "noise": [g.get_state() for g in self.update.noise_gens],
                "rows": [g.get_state() for g in self.update.row_gens] if self.update.on_cuda else [],
                "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state(self.device) if cuda else None,
            },
            "envs": [env_state(env) for env in self.envs],
            # the evaluation envs hold nothing between checks: every episode starts with a seeded reset
            "keep_best": [
                {
                    "check_step": torch.tensor([t for t, _ in checks], dtype=torch.int64),
                    "check_score": torch.tensor([x for _, x in checks], dtype=torch.float64),
                    "best": None if best is None else cpu_copy(best),
                }
                for checks, best in zip(self.checks, self.best)
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a run with the same envs, spec, params, jobs and device
        (call it on a fresh run, before any `step`). Raises ValueError if the state cannot be
        of this run; the run is then unusable (build a fresh one)."""
        if state.get("format") != STATE_FORMAT or state.get("format_version") != STATE_VERSION:
            raise ValueError(f"not a {STATE_FORMAT} v{STATE_VERSION} state")
        if [tuple(j) for j in state["jobs"]] != self.jobs:
            raise ValueError(f"state of specialists {state['jobs']}; this run trains {[list(j) for j in self.jobs]}")
        check_buffer_state(self.buffer, state["buffer"])
        if self.t or self.n_updates:
            raise ValueError("load_state_dict needs a fresh run")
        try:
            load_buffer_state(self.buffer, state["buffer"])
            load_nets_state(self.update, state["nets"], state["counters"]["n_updates"])
            for env, saved in zip(self.envs, state["envs"], strict=True):
                restore_env_state(env, saved)
            loop = state["loop"]
            for name in ("obs", "episode", "ep_step", "ep_return"):
                value = loop[name].numpy()
                if value.shape != getattr(self, name).shape:
                    raise ValueError(f"saved {name} has shape {value.shape}, expected {getattr(self, name).shape}")
                setattr(self, name, value.astype(getattr(self, name).dtype, copy=True))
            self.episodes = [
                [
                    EpisodeRecord(int(e), int(end), int(length), ret.copy(), bool(term))
                    for e, end, length, term, ret in zip(
                        eps["episode"].tolist(),
                        eps["end_step"].tolist(),
                        eps["length"].tolist(),
                        eps["terminated"].tolist(),
                        eps["returns"].numpy(),
                        strict=True,
                    )
                ]
                for eps in state["episodes"]
            ]
            rng = state["rng"]
            for r, saved in zip(self.rngs, rng["numpy"], strict=True):
                r.bit_generator.state = saved
            for g, saved in zip(self.update.noise_gens, rng["noise"], strict=True):
                g.set_state(saved)
            if self.update.on_cuda:
                for g, saved in zip(self.update.row_gens, rng["rows"], strict=True):
                    g.set_state(saved)
                if rng["cuda"] is not None:
                    torch.cuda.set_rng_state(rng["cuda"], self.device)
            torch.set_rng_state(rng["torch"])
            self._load_keep_best(state["keep_best"])
        except (RuntimeError, KeyError, TypeError) as exc:
            raise ValueError(f"state does not fit this run ({type(exc).__name__}: {exc})") from None
        if len(self.episodes) != len(self.jobs):
            raise ValueError(
                f"state holds the episodes of {len(self.episodes)} specialists, the run trains {len(self.jobs)}"
            )
        c = state["counters"]
        self.t, self.n_updates, self.start_step = int(c["t"]), int(c["n_updates"]), int(c.get("start", 0))

    def _load_keep_best(self, saved: list[dict[str, Any]]) -> None:
        """Restore the keep-best checks and snapshots of `state_dict` (each snapshot tried on an
        actor of this run's architecture)."""
        if len(saved) != len(self.jobs):
            raise ValueError(
                f"state holds the keep-best checks of {len(saved)} specialists, the run trains {len(self.jobs)}"
            )
        checks, best = [], []
        for s, item in enumerate(saved):
            steps, scores = item["check_step"].tolist(), item["check_score"].tolist()
            if len(steps) != len(scores):
                raise ValueError(f"keep-best checks of specialist {s}: {len(steps)} steps, {len(scores)} scores")
            checks.append([(int(t), float(x)) for t, x in zip(steps, scores)])
            b = item["best"]
            if b is not None:
                for name, stacked in (("actor", self.state.actor), ("actor_target", self.state.actor_target)):
                    unstack_actor(stacked, s).load_state_dict(b[name])
                b = {"step": int(b["step"]), "score": float(b["score"])} | {
                    name: cpu_copy(b[name])
                    for name in ("actor", "actor_target")  # copies: the state may be memory-mapped
                }
            best.append(b)
        self.checks, self.best = checks, best


def fork_state(prefix: dict[str, Any], fresh: dict[str, Any], spec: EnvSpec) -> dict[str, Any]:
    """The state of S specialists forked from a shared prefix (td3.shared_prefix_steps).

    `prefix`: the final `state_dict` of a run with `mix` (one job: the mixed reward, objective
    n of n + 1); `fresh`: the `state_dict` of the fresh run of S specialists to start (its jobs,
    RNG streams and empty keep-best records are kept: each specialist explores with its own
    noise from the fork on). Every specialist gets the prefix's actor, its critics of the n env
    objectives (the mixed objective's pair is dropped; needs td3.secondary_critics, so that the
    prefix has a critic for each), target networks, the optimizers' moments of those
    parameters, the replay buffer with the env's reward columns, the env mid-episode, the step
    and update counters and the episode history: exactly where the prefix stopped, as if each
    specialist had trained those steps itself. It then ascends its own objective's critic."""
    S, m = len(fresh["jobs"]), spec.n_objectives
    e = 2 * m  # critic members of one specialist: a pair per objective, in objective order

    def copies(t: torch.Tensor) -> torch.Tensor:  # a (1, ...) stacked tensor -> (S, ...)
        return t.repeat(S, *([1] * (t.dim() - 1)))

    def critic_part(t: torch.Tensor) -> torch.Tensor:  # (2(m + 1), ...) members -> (S * 2m, ...)
        return t[:e].repeat(S, *([1] * (t.dim() - 1)))

    def opt_state(saved: dict[str, Any], part: Callable[[torch.Tensor], torch.Tensor]) -> dict[str, Any]:
        state = {
            i: {k: (part(v) if torch.is_tensor(v) and v.dim() > 0 else v.clone()) for k, v in moments.items()}
            for i, moments in saved["state"].items()
        }
        return {"state": state, "param_groups": copy.deepcopy(saved["param_groups"])}

    nets = prefix["nets"]
    buf = prefix["buffer"]
    col = spec.obs_dim + spec.act_dim + m  # the mixed reward's column of a packed row
    rows = torch.cat([buf["rows"][..., :col], buf["rows"][..., col + 1 :]], dim=-1)
    loop = prefix["loop"]
    history = prefix["episodes"][0]
    return {
        **fresh,
        "counters": {**prefix["counters"], "start": int(prefix["counters"]["t"])},
        "nets": {
            "actor": {k: copies(v) for k, v in nets["actor"].items()},
            "actor_target": {k: copies(v) for k, v in nets["actor_target"].items()},
            "critic": {k: critic_part(v) for k, v in nets["critic"].items()},
            "critic_target": {k: critic_part(v) for k, v in nets["critic_target"].items()},
            "actor_opt": opt_state(nets["actor_opt"], copies),
            "critic_opt": opt_state(nets["critic_opt"], critic_part),
        },
        "buffer": {
            **{k: buf[k] for k in ("capacity", "ptr", "size")},
            "rows": copies(rows),
            **{k: copies(buf[k]) for k in ("truncated", "episode", "episode_step")},
        },
        "loop": {
            "obs": copies(loop["obs"]),
            "episode": copies(loop["episode"]),
            "ep_step": copies(loop["ep_step"]),
            "ep_return": copies(loop["ep_return"][:, :m]),
        },
        "episodes": [{**history, "returns": history["returns"][:, :m].clone()} for _ in range(S)],
        "envs": [copy.deepcopy(prefix["envs"][0]) for _ in range(S)],
    }


def train_specialists(
    envs: Sequence[gym.Env],
    spec: EnvSpec,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    jobs: Sequence[tuple[int, int]],
    device: torch.device,
    on_step: Callable[[int, list[EpisodeRecord | None]], None] | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[SpecialistsRun], None] | None = None,
) -> list[SpecialistResult]:
    """Train specialists jobs = [(seed, objective), ...] with TD3 for cfg.total_steps env steps
    each, in lockstep, specialist s on envs[s]; resume from `state` (a
    `SpecialistsRun.state_dict()`, ValueError if it does not fit) if given. No checkpoints: the
    stage drives its runs with pipeline.core.drive.

    `on_step(t, records)` is called after every step; `on_checkpoint(run)` after every step
    where `run.checkpoint_due()` (save `run.state_dict()` there). An exception raised in a
    callback stops the run. Raises TrainingDiverged (pipeline.core.finite) when a loss, weight
    or buffer value is not finite: checked every CHECK_EVERY updates, before every checkpoint
    and before the results, so no checkpoint and no result holds a diverged state.

    Randomness: torch init, env resets, the start-up action sampler, exploration noise, batch
    rows and target smoothing noise are all seeded from (seed, objective) alone, so a
    specialist draws the same whatever else is stacked with it, and the same inputs give
    bitwise-identical results on a CPU (same thread count and library versions).
    """
    run = SpecialistsRun(envs, spec, td3, cfg, jobs, device)
    if state is not None:
        run.load_state_dict(state)
    hooks = [keep_best_hook] + ([] if on_step is None else [lambda run: on_step(run.t, run.last)])
    if on_checkpoint is not None:
        hooks.append(lambda run: on_checkpoint(run) if run.checkpoint_due() else None)
    return run_to_end(run, hooks, fresh=state is None).results()


def train_specialist(
    env: gym.Env,
    spec: EnvSpec,
    td3: TD3Params,
    cfg: TrainSpecialistParams,
    objective: int,
    seed: int,
    device: torch.device,
    on_step: Callable[[int, EpisodeRecord | None], None] | None = None,
) -> SpecialistResult:
    """One specialist alone: `train_specialists` with S = 1."""
    step = None if on_step is None else (lambda t, records: on_step(t, records[0]))
    return train_specialists([env], spec, td3, cfg, [(seed, objective)], device, step)[0]
