"""Training single-objective TD3 specialists, with secondary critics (paper: "Secondary Critics").

`train_specialists` trains S specialists in lockstep in one process: the specialists of every
objective of a seed, or of several seeds. Each keeps its own env, replay buffer, RNG streams
and minibatch draws, so each is exactly the TD3 specialist it would be alone; only the
networks are stacked, so one batched update serves all of them (see pipeline/specialists/td3.py). S = 1
is one specialist on its own (`train_specialist`).

The loop prints nothing; progress goes through the `on_step` callback.

Devices: on a CPU the buffers are CPU tensors and minibatch rows are drawn with each
specialist's numpy generator (the same stream as its exploration noise). On CUDA the buffers
live on the GPU, rows are drawn on the GPU from a per-specialist torch generator, and the
update runs as captured CUDA graphs (`train_specialist.cuda_graphs`); the only per-step host
sync is reading the actions to step the envs. The two devices therefore draw different
(each reproducible) minibatches.

Checkpoints: `SpecialistsRun.state_dict` holds every piece of a run's state (networks,
optimizers, replay buffers, RNG streams, counters, the episode history and each env's
mid-episode state, `env_state`), so a run restored after any step goes on bitwise as the
uninterrupted one on a CPU. Only MuJoCo envs (behind gymnasium's standard wrappers) can be
saved mid-episode; `env_checkpoint_problem` says why another cannot. On CUDA the state is
saved as CPU tensors and restored onto the device (untested here: no GPU).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.buffer import StackedReplay
from pipeline.core.envs import EnvSpec
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.core.seeding import derive_seeds, torch_generator
from pipeline.specialists.td3 import GraphedUpdate, StackedTD3, TD3State, stacked_update


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


def covered_objectives(objective: int, n_objectives: int, secondary: bool) -> tuple[list[int], int]:
    """Objectives the critic ensemble covers, in member order, and the index of the primary in that list.

    With secondary critics the ensemble covers every objective 0..n-1; without, only `objective`.
    """
    if secondary:
        return list(range(n_objectives)), objective
    return [objective], 0


def init_td3(spec: EnvSpec, cfg: TrainSpecialistParams, objective: int, device: torch.device) -> TD3State:
    """One specialist's networks unstacked: the reference form that `td3.td3_update` trains
    (the tests check the stacked update against it)."""
    objectives, primary = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
    actor = Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high).to(device)
    critic = CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)).to(device)
    return TD3State(
        actor=actor,
        actor_target=copy.deepcopy(actor).requires_grad_(False),
        critic=critic,
        critic_target=copy.deepcopy(critic).requires_grad_(False),
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, fused=True),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, fused=True),
        objectives=objectives,
        primary=primary,
    )


def run_seeds(seed: int, objective: int) -> dict[str, int]:
    """The independent seeds of specialist (seed, objective): the same however many are stacked."""
    names = ("torch", "env", "space", "numpy", "noise", "cuda_rows")
    return dict(zip(names, derive_seeds(seed, objective, n=len(names))))


def init_stacked(spec: EnvSpec, cfg: TrainSpecialistParams, jobs: Sequence[tuple[int, int]], device: torch.device) -> StackedTD3:
    """Stacked networks of specialists `jobs` = [(seed, objective), ...], each initialised as it
    would be alone (torch seeded with its own seed, actor first, then its critics)."""
    actors, critics, covered, primary = [], [], [], []
    for seed, objective in jobs:
        objectives, j = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
        torch.manual_seed(run_seeds(seed, objective)["torch"])
        actors.append(Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high))
        critics.append(CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)))
        covered.append(objectives)
        primary.append(j)
    return stack_td3(cfg, actors, critics, covered, primary, device)


def stack_td3(
    cfg: TrainSpecialistParams,
    actors: Sequence[Actor],
    critics: Sequence[CriticEnsemble],
    covered: Sequence[Sequence[int]],
    primary: Sequence[int],
    device: torch.device,
    actor_targets: Sequence[Actor] | None = None,
    critic_targets: Sequence[CriticEnsemble] | None = None,
) -> StackedTD3:
    """S specialists' networks stacked (copies; targets copies of the online nets unless given)
    with fresh optimizers. covered[s]: the objectives specialist s's ensemble covers, in member
    order; primary[s]: the index of its own objective in that list."""
    actor = StackedActor(actors).to(device)
    critic = CriticEnsemble.stack(critics).to(device)
    actor_target = copy.deepcopy(actor) if actor_targets is None else StackedActor(actor_targets).to(device)
    critic_target = copy.deepcopy(critic) if critic_targets is None else CriticEnsemble.stack(critic_targets).to(device)
    sizes = {2 * len(c) for c in covered}
    if len(sizes) != 1 or [c.n_members for c in critics] != [2 * len(c) for c in covered]:
        raise ValueError(f"stacked specialists need critic ensembles of one size, 2 members per covered objective: {list(covered)}")
    e = sizes.pop()
    # fused Adam: one kernel per parameter tensor (same update as the plain one). Captured CUDA
    # graphs need the optimizer's step counters on the device (capturable).
    graphs = device.type == "cuda" and cfg.cuda_graphs
    opt = dict(fused=True, capturable=True) if graphs else dict(fused=True)
    return StackedTD3(
        actor=actor,
        actor_target=actor_target.requires_grad_(False),
        critic=critic,
        critic_target=critic_target.requires_grad_(False),
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, **opt),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, **opt),
        reward_index=torch.tensor([list(c) for c in covered], dtype=torch.long, device=device),
        primary_members=torch.tensor([s * e + 2 * j for s, j in enumerate(primary)], dtype=torch.long, device=device),
    )


def exploration_actions(actor: StackedActor, obs: np.ndarray, noise_std: float, rngs: Sequence[np.random.Generator]) -> np.ndarray:
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


class _Updater:
    """Draws each specialist's minibatch rows and smoothing noise and runs one stacked update."""

    def __init__(self, state: StackedTD3, buffer: StackedReplay, cfg: TrainSpecialistParams, seeds: list[dict[str, int]], rngs, device):
        self.state, self.buffer, self.cfg, self.rngs = state, buffer, cfg, rngs
        self.device = device
        s, b, act = state.n, cfg.batch_size, state.actor.scale.shape[-1]
        self.noise_gens = [torch_generator(x["noise"], device) for x in seeds]
        self.noise = torch.zeros(s, b, act, device=device)
        self.on_cuda = device.type == "cuda"
        if self.on_cuda:
            self.row_gens = [torch_generator(x["cuda_rows"], device) for x in seeds]
            self.idx = torch.zeros(s, b, dtype=torch.long, device=device)
        self.graphs = self.on_cuda and cfg.cuda_graphs
        self.graphed: GraphedUpdate | None = None
        self.args = dict(gamma=cfg.gamma, tau=cfg.tau, policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip)

    def graph(self) -> GraphedUpdate:
        """The captured update (CUDA graphs), captured on first use: it needs fresh optimizers."""
        if self.graphed is None:
            self.graphed = GraphedUpdate(self.state, self.buffer.gather, self.idx, self.noise, **self.args)
        return self.graphed

    def __call__(self, update_actor: bool) -> None:
        for s, g in enumerate(self.noise_gens):
            self.noise[s].normal_(generator=g)
        if self.on_cuda:
            for s, g in enumerate(self.row_gens):
                self.idx[s].random_(0, self.buffer.size, generator=g)
            idx = self.idx
        else:
            idx = torch.from_numpy(np.stack([rng.integers(0, self.buffer.size, size=self.cfg.batch_size) for rng in self.rngs]))
        if self.graphs:
            self.graph()(update_actor)
        else:
            stacked_update(self.state, self.buffer.gather(idx), self.noise, update_actor, **self.args)


STATE_FORMAT = "mapex.specialists_state"
STATE_VERSION = 1


def _cpu(obj: Any) -> Any:
    """A copy of a (nested) state dict with every tensor detached and cloned on the CPU."""
    if torch.is_tensor(obj):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: _cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_cpu(v) for v in obj)
    return obj


def _copy_optimizer_state_(opt: torch.optim.Optimizer, saved: dict[str, Any]) -> None:
    """Copy a saved optimizer state into `opt`'s existing state tensors, in place (captured
    CUDA graphs read those very tensors, so load_state_dict, which replaces them, cannot be used)."""
    params = [p for group in opt.param_groups for p in group["params"]]
    if sorted(saved["state"]) != list(range(len(params))):
        raise ValueError(f"optimizer state for {len(saved['state'])} parameters, the optimizer has {len(params)}")
    with torch.no_grad():
        for i, p in enumerate(params):
            for key, value in saved["state"][i].items():
                opt.state[p][key].copy_(value)


def nets_state(st: StackedTD3) -> dict[str, Any]:
    """The networks and optimizers of a stacked set, as CPU tensors."""
    return _cpu({
        "actor": st.actor.state_dict(), "actor_target": st.actor_target.state_dict(),
        "critic": st.critic.state_dict(), "critic_target": st.critic_target.state_dict(),
        "actor_opt": st.actor_opt.state_dict(), "critic_opt": st.critic_opt.state_dict(),
    })


def load_nets_state(update: "_Updater", nets: dict[str, Any], n_updates: int) -> None:
    """Restore `nets_state` into the networks `update` trains (fresh, never updated)."""
    st = update.state
    for name in ("actor", "actor_target", "critic", "critic_target"):
        getattr(st, name).load_state_dict(nets[name])
    if update.graphs and n_updates > 0:
        # The captured graphs read the optimizers' own state tensors: capture them now (on
        # fresh optimizers, with the restored networks and buffer), then fill those tensors in
        # place.
        update.graph()
        _copy_optimizer_state_(st.actor_opt, nets["actor_opt"])
        _copy_optimizer_state_(st.critic_opt, nets["critic_opt"])
    else:
        for opt, saved in ((st.actor_opt, nets["actor_opt"]), (st.critic_opt, nets["critic_opt"])):
            # load_state_dict also takes the saved param-group flags: keep this optimizer's
            # capturable/fused (a state saved eagerly may be resumed under CUDA graphs)
            flags = [{k: g[k] for k in ("capturable", "fused") if k in g} for g in opt.param_groups]
            opt.load_state_dict(saved)
            for g, f in zip(opt.param_groups, flags):
                g.update(f)


def buffer_state(b: StackedReplay) -> dict[str, Any]:
    """A StackedReplay's rows and pointers as CPU tensors. The rows are not copied when a full
    ring already lies on the CPU: they are the live ring, so save (or copy) the state before
    the next row is added."""
    size = b.size
    if size == b.capacity and b.rows.device.type == "cpu":
        rows, host = b.rows.detach(), {k: torch.from_numpy(v) for k, v in b.host.items()}
    else:  # the rows written so far, copied to the CPU
        rows = b.rows[:, :size].to("cpu", copy=True)
        host = {k: torch.from_numpy(v[:, :size].copy()) for k, v in b.host.items()}
    return {"capacity": b.capacity, "ptr": b.ptr, "size": size, "rows": rows, **host}


def check_buffer_state(b: StackedReplay, saved: dict[str, Any]) -> None:
    """ValueError unless `saved` (a `buffer_state`) fits buffer `b`."""
    if saved["capacity"] != b.capacity:
        raise ValueError(f"state's buffer capacity {saved['capacity']} != {b.capacity}")
    size = saved["size"]
    if tuple(saved["rows"].shape) != (b.n, size, b.rows.shape[2]) or not 0 <= saved["ptr"] < b.capacity:
        raise ValueError(f"state's buffer rows {tuple(saved['rows'].shape)} do not fit ({b.n}, {size}, {b.rows.shape[2]})")


def load_buffer_state(b: StackedReplay, saved: dict[str, Any]) -> None:
    """Restore a `buffer_state` (checked by `check_buffer_state`) into `b`."""
    size = int(saved["size"])
    with torch.no_grad():
        b.rows[:, :size].copy_(saved["rows"])
    for k, v in b.host.items():
        v[:, :size] = saved[k].numpy()
    b.ptr, b.size = int(saved["ptr"]), size


class SpecialistsRun:
    """S specialists jobs = [(seed, objective), ...] in training, in lockstep, specialist s on
    envs[s]: every piece of their state and one env step at a time (`step`).

    `state_dict` holds all of it (networks, optimizers, replay buffers, every RNG, the envs'
    mid-episode state, counters and episode history), so a run restored from it after any
    step (`load_state_dict`) goes on exactly as the uninterrupted run: bitwise on a CPU with
    the same thread count and library versions.
    """

    def __init__(self, envs: Sequence[gym.Env], spec: EnvSpec, cfg: TrainSpecialistParams, jobs: Sequence[tuple[int, int]], device: torch.device):
        for seed, objective in jobs:
            if not 0 <= objective < spec.n_objectives:
                raise ValueError(f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives")
        if len(envs) != len(jobs):
            raise ValueError(f"{len(jobs)} specialists need as many envs, got {len(envs)}")
        self.envs, self.spec, self.cfg = list(envs), spec, cfg
        self.jobs = [(int(seed), int(objective)) for seed, objective in jobs]
        self.device = torch.device(device)
        n = len(jobs)
        self.seeds = [run_seeds(seed, objective) for seed, objective in self.jobs]
        self.state = init_stacked(spec, cfg, self.jobs, self.device)
        self.rngs = [np.random.default_rng(x["numpy"]) for x in self.seeds]
        for env, x in zip(self.envs, self.seeds):
            env.action_space.seed(x["space"])
        self.buffer = StackedReplay(n, cfg.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives, self.device)
        self.update = _Updater(self.state, self.buffer, cfg, self.seeds, self.rngs, self.device)
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
        self.n_updates = 0

    @property
    def done(self) -> bool:
        return self.t >= self.cfg.total_steps

    def step(self) -> list[EpisodeRecord | None]:
        """One env step of every specialist (and one update once learning has started);
        returns, per specialist, the record of the episode this step ended, else None."""
        cfg, envs, t = self.cfg, self.envs, self.t
        if t < cfg.learning_starts:
            actions = np.stack([np.asarray(env.action_space.sample(), dtype=np.float32) for env in envs])
        else:
            actions = exploration_actions(self.state.actor, self.obs, cfg.exploration_noise, self.rngs)
        next_obs, reward, terminated, truncated = self._next_obs, self._reward, self._terminated, self._truncated
        for s, env in enumerate(envs):
            o, r, terminated[s], truncated[s], _ = env.step(actions[s])
            next_obs[s], reward[s] = o, r
        self.buffer.add(self.obs, actions, reward, next_obs, terminated, truncated, self.episode, self.ep_step)
        self.ep_return += reward
        self.ep_step += 1
        self.obs = next_obs.copy()
        records: list[EpisodeRecord | None] = [None] * len(envs)
        for s in np.flatnonzero(terminated | truncated):
            records[s] = EpisodeRecord(int(self.episode[s]), t + 1, int(self.ep_step[s]), self.ep_return[s].copy(), bool(terminated[s]))
            self.episodes[s].append(records[s])
            self.obs[s] = envs[s].reset()[0]
            self.episode[s] += 1
            self.ep_step[s] = 0
            self.ep_return[s] = 0.0
        if t >= cfg.learning_starts:
            self.n_updates += 1
            self.update(update_actor=self.n_updates % cfg.policy_freq == 0)
        self.t = t + 1
        return records

    def results(self) -> list[SpecialistResult]:
        state, n = self.state, len(self.jobs)
        e = state.critic.n_members // n
        return [
            SpecialistResult(
                seed=seed,
                objective=objective,
                actor=state.actor.unstack(s),
                actor_target=state.actor_target.unstack(s),
                critic=state.critic.subset(s * e, (s + 1) * e).cpu(),
                critic_target=state.critic_target.subset(s * e, (s + 1) * e).cpu().requires_grad_(False),
                objectives=state.reward_index[s].tolist(),
                buffer=self.buffer.chronological(s),
                episodes=self.episodes[s],
            )
            for s, (seed, objective) in enumerate(self.jobs)
        ]

    # -- checkpoints ----------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything the run depends on from here, as CPU tensors and plain Python values
        (torch.load(weights_only=True) reads it back).

        The buffer rows are not copied when a full ring already lies on the CPU: they are the
        live ring, so save (or copy) the state before the next `step`."""
        cuda = self.device.type == "cuda"
        return {
            "format": STATE_FORMAT,
            "format_version": STATE_VERSION,
            "jobs": [list(j) for j in self.jobs],
            "counters": {"t": self.t, "n_updates": self.n_updates},
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
                    "returns": torch.from_numpy(np.stack([r.returns for r in eps]) if eps else np.zeros((0, self.spec.n_objectives))),
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
                        eps["episode"].tolist(), eps["end_step"].tolist(), eps["length"].tolist(),
                        eps["terminated"].tolist(), eps["returns"].numpy(), strict=True,
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
        except (RuntimeError, KeyError, TypeError) as exc:
            raise ValueError(f"state does not fit this run ({type(exc).__name__}: {exc})") from None
        if len(self.episodes) != len(self.jobs):
            raise ValueError(f"state holds the episodes of {len(self.episodes)} specialists, the run trains {len(self.jobs)}")
        c = state["counters"]
        self.t, self.n_updates = int(c["t"]), int(c["n_updates"])


def continue_training(
    run: SpecialistsRun,
    on_step: Callable[[int, list[EpisodeRecord | None]], None] | None = None,
    on_checkpoint: Callable[[SpecialistsRun], None] | None = None,
) -> list[SpecialistResult]:
    """Step `run` (fresh or restored) to cfg.total_steps and return its results.

    `on_step(t, records)` after every step; `on_checkpoint(run)` after every
    cfg.checkpoint_every-th step but the last (none when it is 0): save `run.state_dict()`
    there. An exception raised in a callback stops the run."""
    every = run.cfg.checkpoint_every
    while not run.done:
        records = run.step()
        if on_step is not None:
            on_step(run.t, records)
        if on_checkpoint is not None and every and run.t % every == 0 and not run.done:
            on_checkpoint(run)
    return run.results()


def train_specialists(
    envs: Sequence[gym.Env],
    spec: EnvSpec,
    cfg: TrainSpecialistParams,
    jobs: Sequence[tuple[int, int]],
    device: torch.device,
    on_step: Callable[[int, list[EpisodeRecord | None]], None] | None = None,
    state: dict[str, Any] | None = None,
    on_checkpoint: Callable[[SpecialistsRun], None] | None = None,
) -> list[SpecialistResult]:
    """Train specialists jobs = [(seed, objective), ...] with TD3 for cfg.total_steps env steps
    each, in lockstep, specialist s on envs[s]; resume from `state` (a
    `SpecialistsRun.state_dict()`, ValueError if it does not fit) if given. The callbacks are
    those of `continue_training`.

    Randomness: torch init, env resets, the start-up action sampler, exploration noise, batch
    rows and target smoothing noise are all seeded from (seed, objective) alone, so a
    specialist draws the same whatever else is stacked with it, and the same inputs give
    bitwise-identical results on a CPU (same thread count and library versions).
    """
    run = SpecialistsRun(envs, spec, cfg, jobs, device)
    if state is not None:
        run.load_state_dict(state)
    return continue_training(run, on_step, on_checkpoint)


def train_specialist(
    env: gym.Env,
    spec: EnvSpec,
    cfg: TrainSpecialistParams,
    objective: int,
    seed: int,
    device: torch.device,
    on_step: Callable[[int, EpisodeRecord | None], None] | None = None,
) -> SpecialistResult:
    """One specialist alone: `train_specialists` with S = 1."""
    step = None if on_step is None else (lambda t, records: on_step(t, records[0]))
    return train_specialists([env], spec, cfg, [(seed, objective)], device, step)[0]


# --------------------------------------------------------------- a TD3 agent fed from outside


class TD3Learner:
    """One TD3 agent with secondary critics that learns from transitions handed to it: the RL
    agent inside PDERL and MOPDERL, whose episodes are run by the population's loop.

    It is the specialists' machinery with S = 1 (a stacked network set, a `StackedReplay` on
    the training device and `_Updater`), so it gets the same device path: on CUDA the buffer
    lives on the GPU, minibatch rows are drawn there from `cuda_rows_seed`, and with
    cfg.cuda_graphs each update replays two captured CUDA graphs; `train(n)` makes n updates
    with no host sync. On a CPU, rows are drawn with `rows_rng` (numpy).
    """

    def __init__(self, spec: EnvSpec, cfg: TrainSpecialistParams, state: StackedTD3, rows_rng: np.random.Generator,
                 noise_seed: int, cuda_rows_seed: int, device: torch.device | str):
        if state.n != 1:
            raise ValueError(f"a TD3Learner trains one specialist, got a stacked set of {state.n}")
        self.cfg, self.state, self.device = cfg, state, torch.device(device)
        self.rows_rng = rows_rng
        self.buffer = StackedReplay(1, cfg.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives, self.device)
        self.update = _Updater(state, self.buffer, cfg, [{"noise": noise_seed, "cuda_rows": cuda_rows_seed}], [rows_rng], self.device)
        self.objectives: list[int] = state.reward_index[0].tolist()
        self.primary_member = int(state.primary_members[0])  # head 0 of its own objective
        self.updates = 0

    def add(self, obs, action, reward, next_obs, terminated: bool, truncated: bool, episode: int, step: int) -> None:
        """Append one transition to the replay buffer."""
        self.buffer.add(obs[None], action[None], np.asarray(reward)[None], next_obs[None],
                        np.array([terminated]), np.array([truncated]), np.array([episode]), np.array([step]))

    def train(self, n: int) -> None:
        """n TD3 updates (the actor and targets on every policy_freq-th, counted over the run)."""
        for _ in range(n):
            self.updates += 1
            self.update(update_actor=self.updates % self.cfg.policy_freq == 0)

    def actor(self) -> Actor:
        """A copy of the current actor, on the training device (to act with or copy from)."""
        with torch.random.fork_rng(devices=[]):  # building an Actor draws an init we overwrite
            return self.state.actor.unstack(0).to(self.device)

    def q_primary(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The primary critic's head 0 (Q1, the head the actor ascends) at (obs (B, o), action (B, a)) -> (B,)."""
        return self.state.critic.member(obs, action, self.primary_member)

    def networks(self) -> tuple[Actor, Actor, CriticEnsemble, CriticEnsemble]:
        """CPU copies of (actor, actor_target, critic, critic_target): the artifact formats."""
        st = self.state
        e = st.critic.n_members
        with torch.random.fork_rng(devices=[]):
            return (st.actor.unstack(0), st.actor_target.unstack(0).requires_grad_(False), st.critic.subset(0, e).cpu(),
                    st.critic_target.subset(0, e).cpu().requires_grad_(False))

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimizers, buffer, RNG streams and the update count, as CPU tensors."""
        u = self.update
        return {
            "updates": self.updates,
            "nets": nets_state(self.state),
            "buffer": buffer_state(self.buffer),
            "rng": {"rows": copy.deepcopy(self.rows_rng.bit_generator.state), "noise": u.noise_gens[0].get_state(),
                    "cuda_rows": u.row_gens[0].get_state() if u.on_cuda else None},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` into a fresh learner (ValueError if it does not fit)."""
        if self.updates:
            raise ValueError("load_state_dict needs a fresh learner")
        check_buffer_state(self.buffer, state["buffer"])
        load_buffer_state(self.buffer, state["buffer"])
        load_nets_state(self.update, state["nets"], state["updates"])
        rng = state["rng"]
        self.rows_rng.bit_generator.state = rng["rows"]
        self.update.noise_gens[0].set_state(rng["noise"])
        if self.update.on_cuda and rng["cuda_rows"] is not None:
            self.update.row_gens[0].set_state(rng["cuda_rows"])
        self.updates = int(state["updates"])


# --------------------------------------------------------------------------- env state


class EnvStateError(ValueError):
    """An env whose whole state cannot be saved and restored (so it cannot be checkpointed)."""


# Wrappers the env state knows: TimeLimit (its step count is saved), OrderEnforcing (its
# has-reset flag is saved) and PassiveEnvChecker (its flags only decide which one-off checks
# run; they change nothing the env returns). Any other wrapper may hold state we cannot see.
_KNOWN_WRAPPERS = (gym.wrappers.TimeLimit, gym.wrappers.OrderEnforcing, gym.wrappers.PassiveEnvChecker)

# Quantities MuJoCo derives from the state during a step (positions, frames, velocities and
# forces of bodies, geoms and sites). mj_step recomputes all of them before it uses them, so
# they are not part of the integration state, but env code may read them before stepping:
# Ant-v5 takes the torso's xpos before the step to compute its velocity, and after a step
# xpos still belongs to the last substep's start, not to the current qpos. So they are saved
# as they are, not recomputed on restore.
_MJ_DERIVED = (
    "xpos", "xquat", "xmat", "xipos", "ximat", "xanchor", "xaxis", "geom_xpos", "geom_xmat",
    "site_xpos", "site_xmat", "subtree_com", "cinert", "cdof", "cvel", "cacc", "cfrc_int",
    "cfrc_ext", "qacc", "qfrc_actuator", "actuator_force", "sensordata",
)


def _wrapper_chain(env: gym.Env) -> list[gym.Env]:
    chain = []
    while isinstance(env, gym.Wrapper):
        chain.append(env)
        env = env.env
    return chain


def env_checkpoint_problem(env: gym.Env) -> str | None:
    """Why the mid-episode state of `env` cannot be saved, or None if `env_state` can save it."""
    unknown = [type(w).__name__ for w in _wrapper_chain(env) if not isinstance(w, _KNOWN_WRAPPERS)]
    if unknown:
        return f"wrapper(s) {unknown} may hold state the checkpoint cannot see"
    u = env.unwrapped
    try:
        import mujoco
    except ImportError:  # pragma: no cover - mujoco comes with the MuJoCo envs
        return "mujoco is not installed"
    if not isinstance(getattr(u, "model", None), mujoco.MjModel) or not isinstance(getattr(u, "data", None), mujoco.MjData):
        return f"{type(u).__name__} is not a MuJoCo env (only MuJoCo physics state is saved)"
    return None


def env_state(env: gym.Env) -> dict[str, Any]:
    """The whole mid-episode state of a MuJoCo env built by `make_env`: the physics
    (mjSTATE_INTEGRATION: time, qpos, qvel, act, warm start of the constraint solver, controls,
    ...), the derived quantities env code may read before the next step (`_MJ_DERIVED`), the
    wrappers' counters and the env's and its action space's RNG states.

    qpos and qvel alone are not enough: without the solver's warm start a step with contacts
    (Hopper, Walker2d, Ant) differs in the last bits. Raises EnvStateError if the env is not
    one whose state this knows (see `env_checkpoint_problem`)."""
    problem = env_checkpoint_problem(env)
    if problem is not None:
        raise EnvStateError(problem)
    import mujoco

    u = env.unwrapped
    sig = mujoco.mjtState.mjSTATE_INTEGRATION
    physics = np.empty(mujoco.mj_stateSize(u.model, sig), np.float64)
    mujoco.mj_getState(u.model, u.data, physics, sig)
    wrappers = []
    for w in _wrapper_chain(env):
        entry: dict[str, Any] = {"type": type(w).__name__}
        if isinstance(w, gym.wrappers.TimeLimit):
            entry["elapsed_steps"] = w._elapsed_steps
        if isinstance(w, gym.wrappers.OrderEnforcing):
            entry["has_reset"] = w._has_reset
        wrappers.append(entry)
    return {
        "physics": torch.from_numpy(physics),
        "derived": {k: torch.from_numpy(np.array(getattr(u.data, k))) for k in _MJ_DERIVED if hasattr(u.data, k)},
        "wrappers": wrappers,
        "np_random": copy.deepcopy(u.np_random.bit_generator.state),
        "action_space": copy.deepcopy(env.action_space.np_random.bit_generator.state),
    }


def restore_env_state(env: gym.Env, state: dict[str, Any]) -> None:
    """Put `env` (built like the one `state` was taken from) into `state` (an `env_state`):
    its next steps and resets give exactly what the saved env's would have. ValueError if the
    state does not fit the env."""
    problem = env_checkpoint_problem(env)
    if problem is not None:
        raise EnvStateError(problem)
    import mujoco

    u = env.unwrapped
    sig = mujoco.mjtState.mjSTATE_INTEGRATION
    physics = state["physics"].numpy()
    if physics.shape != (mujoco.mj_stateSize(u.model, sig),):
        raise ValueError(f"physics state of shape {tuple(physics.shape)} does not fit this env's model")
    chain = _wrapper_chain(env)
    if [type(w).__name__ for w in chain] != [w["type"] for w in state["wrappers"]]:
        raise ValueError(f"env wrappers {[w['type'] for w in state['wrappers']]} were saved, this env has {[type(w).__name__ for w in chain]}")
    mujoco.mj_setState(u.model, u.data, physics, sig)
    mujoco.mj_forward(u.model, u.data)  # derived quantities not saved: consistent with the state
    for k, v in state["derived"].items():
        target = getattr(u.data, k, None)
        if target is None:
            raise ValueError(f"saved mjData.{k}, which this MuJoCo version lacks")
        if target.shape != tuple(v.shape):
            raise ValueError(f"saved mjData.{k} has shape {tuple(v.shape)}, this env's {target.shape}")
        target[...] = v.numpy()
    mujoco.mj_setState(u.model, u.data, physics, sig)  # in case mj_forward touched any of it
    for w, saved in zip(chain, state["wrappers"]):
        if "elapsed_steps" in saved:
            w._elapsed_steps = saved["elapsed_steps"]
        if "has_reset" in saved:
            w._has_reset = saved["has_reset"]
    u.np_random.bit_generator.state = state["np_random"]
    env.action_space.np_random.bit_generator.state = state["action_space"]
