"""The MORL/D baseline: morl-baselines' MORLD run exchange by exchange, checkpointed, and exported.

morl-baselines is an optional dependency (the `baselines` extra): nothing here imports it at
module level; `require_morl_baselines` imports it when a run is built and names the install
command when it is missing.

What the run is. `MorldRun` builds the library's `MORLD` (MOSAC agents, weighted sums) on our
env (pipeline.core.envs.make_env, so every training and evaluation episode is capped at
env.max_episode_steps) and repeats the body of `MORLD.train` itself, one exchange per `step`:
the next agent in turn collects `exchange_every` frames (one SAC update per frame), the others
make `update_passes` updates, every agent is scored by MORL/D's own evaluation and offered to
its Pareto archive, then the weights are adapted (PSA). Driving the loop ourselves (through
MORLD's private methods, hence the exact version pin) gives a progress callback, a frame count
and checkpoints between exchanges; `MORLD.train` offers none of them that we could resume from.

What we change, and why:
- The archive. MORL/D's `ParetoArchive` deep-copies the whole agent, replay buffer included
  (with a shared 1M-row buffer that is 170 MB per entry on HalfCheetah, 880 MB on Ant).
  `ActorArchive` replaces it with the same keep-the-first-non-dominated rule but stores only
  the actor's weights, the agent's weight vector, and when it was archived.
- Seeding. MORLD seeds only its weight vectors; the networks draw from torch's global RNG,
  minibatches from numpy's global RNG and env resets from the envs' own unseeded RNGs. A run
  seeds all of them from (seed, MORLD_TAG), so a run is reproducible on one machine type.
- Logging. wandb is off (log=False); the library's prints are silenced.
MORL/D's archive scores are discounted returns of *stochastic* actions; they only decide what
the archive keeps. Every exported actor is re-scored here with deterministic actions
(`export_members`), and downstream stages evaluate again on fresh episodes.

Actors. MOSAC's actor is latent_pi = (Linear, ReLU) x n, then a mean head and a log-std head;
its deterministic action is tanh(mean) * action_scale + action_bias. Our `pipeline.core.nets.Actor`
computes centre + scale * tanh(net(obs)) with net = (Linear, ReLU) x n + Linear: the same
function once the latent layers and the mean head are copied into `net` and action_scale /
action_bias into scale / centre (`actor_from_mosac`). The log-std head only shapes
exploration and is dropped.

Resuming. `MorldRun.state_dict` holds everything a run continues from at an exchange
boundary: every agent's networks, optimisers and entropy temperature, the replay buffer(s),
the archive, MORLD's counters and weights, and the global and env RNG states. MOSAC restarts
its env episode at the start of every turn, so no env state is needed. A run resumed from a
checkpoint ends bit for bit as an uninterrupted one on the same device, thread count and
libraries. (MORLD's own save/load is not used: it keeps neither the counters (frames, whose
turn it is) nor any RNG state, the checkpoints `MORLD.train` writes (to ./weights/) leave the
replay buffer out, and its load replaces the temperature tensor, so the temperature optimiser
goes on updating the old one and the temperature freezes after a resume.)
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import asdict, dataclass
from importlib import metadata
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from pipeline.core.envs import EnvSpec, make_env
from pipeline.core.finite import check_finite, weights
from pipeline.core.nets import Actor, hidden_sizes_of
from pipeline.core.population import Member, actor_state
from pipeline.core.seeding import derive_seeds
from pipeline.evaluation.episodes import EvalResult, eval_seeds, evaluate_policies
from pipeline.params.morld import MorldParams

MORL_BASELINES_VERSION = "1.3.0"
INSTALL_HINT = 'pip install -e ".[baselines]"'
MORLD_TAG = 0x4D4F524C  # "MORL": separates the baseline's streams from every other use of a run seed
EVAL_STREAM = 0  # eval_seeds stream of the export evaluation; the evaluate stage uses fresh streams
STATE_VERSION = 1
_STREAMS = ("torch", "numpy", "train_env", "train_actions", "eval_env")
_NETS = ("actor", "qf1", "qf2", "qf1_target", "qf2_target")
_NET_NAMES = dict(zip(_NETS, ("actor", "critic 1", "critic 2", "target critic 1", "target critic 2")))


class BaselinesMissing(ImportError):
    """morl-baselines (the optional `baselines` extra) is not importable, or not the pinned version."""


def require_morl_baselines() -> tuple[type, Callable]:
    """Import what a run needs from morl-baselines: (the MORLD class, filter_pareto_dominated).

    Raises BaselinesMissing, naming the install command, when it is not installed or is
    another version than the one this driver was written against.
    """
    try:
        from morl_baselines.common.pareto import filter_pareto_dominated
        from morl_baselines.multi_policy.morld.morld import MORLD
    except ImportError as exc:
        raise BaselinesMissing(
            f"the MORL/D baseline needs morl-baselines=={MORL_BASELINES_VERSION}, which cannot be imported ({exc}); "
            f"install the optional extra: {INSTALL_HINT}"
        ) from None
    try:
        version = metadata.version("morl-baselines")
    except metadata.PackageNotFoundError:
        version = None
    if version != MORL_BASELINES_VERSION:
        raise BaselinesMissing(
            f"the MORL/D baseline drives morl-baselines=={MORL_BASELINES_VERSION} through its private methods, but "
            f"version {version} is installed; install the pinned one: {INSTALL_HINT}"
        )
    return MORLD, filter_pareto_dominated


@contextlib.contextmanager
def _quiet():
    """Silence the library's prints (weights, the whole archive after every exchange, ...)."""
    with open(os.devnull, "w") as sink, contextlib.redirect_stdout(sink):
        yield


# -- actors ---------------------------------------------------------------------------------


def check_mosac_actor(module: nn.Module) -> None:
    """Raise ValueError unless `module` is MOSAC's actor as morl-baselines 1.3.0 builds it:
    latent_pi = (Linear, ReLU) x n, heads fc_mean and fc_logstd, buffers action_scale and
    action_bias. Anything else (dropout, layer norm, another activation) has no exact
    `pipeline.core.nets.Actor` counterpart."""
    latent = getattr(module, "latent_pi", None)
    missing = [a for a in ("fc_mean", "action_scale", "action_bias") if not hasattr(module, a)]
    if not isinstance(latent, nn.Sequential) or missing:
        raise ValueError(
            f"{type(module).__name__} is not a MOSAC actor (latent_pi: {type(latent).__name__}, missing {missing})"
        )
    layers = list(latent)
    pattern_ok = (
        len(layers) >= 2
        and len(layers) % 2 == 0
        and all(isinstance(m, nn.Linear) for m in layers[0::2])
        and all(type(m) is nn.ReLU for m in layers[1::2])
        and isinstance(module.fc_mean, nn.Linear)
    )
    if not pattern_ok:
        raise ValueError(
            f"MOSAC actor with latent layers {[type(m).__name__ for m in layers]}: only (Linear, ReLU) x n converts "
            "exactly into pipeline.core.nets.Actor"
        )


def mosac_state(module: nn.Module) -> dict[str, torch.Tensor]:
    """The actor's state dict, detached and cloned onto the CPU."""
    return {k: v.detach().cpu().clone() for k, v in module.state_dict().items()}


def actor_from_mosac_state(state: dict[str, torch.Tensor]) -> Actor:
    """Our deterministic `Actor` computing MOSAC's deterministic action from a MOSAC actor's
    state dict: latent layers latent_pi.0, .2, ... and the mean head become net.0, .2, ...,
    the last; action_scale and action_bias become scale and centre (copied, not recomputed,
    so the arithmetic is the same to the bit)."""
    idx = sorted(int(k.split(".")[1]) for k in state if k.startswith("latent_pi.") and k.endswith(".weight"))
    if not idx or idx != list(range(0, 2 * len(idx), 2)) or "fc_mean.weight" not in state:
        raise ValueError(f"not a MOSAC actor state dict (keys {sorted(state)})")
    weights = [state[f"latent_pi.{i}.weight"] for i in idx] + [state["fc_mean.weight"]]
    biases = [state[f"latent_pi.{i}.bias"] for i in idx] + [state["fc_mean.bias"]]
    for a, b in zip(weights, weights[1:]):
        if b.shape[1] != a.shape[0]:
            raise ValueError(f"MOSAC actor layers do not chain: {[tuple(w.shape) for w in weights]}")
    scale = state["action_scale"].reshape(-1).float()
    centre = state["action_bias"].reshape(-1).float()
    obs_dim, act_dim = weights[0].shape[1], weights[-1].shape[0]
    if scale.numel() != act_dim or centre.numel() != act_dim:
        raise ValueError(
            f"action_scale {tuple(scale.shape)} / action_bias {tuple(centre.shape)} do not match {act_dim} actions"
        )
    actor = Actor(
        obs_dim, act_dim, [w.shape[0] for w in weights[:-1]], (centre - scale).tolist(), (centre + scale).tolist()
    )
    linears = [m for m in actor.net if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for lin, w, b in zip(linears, weights, biases):
            lin.weight.copy_(w)
            lin.bias.copy_(b)
        actor.scale.copy_(scale)
        actor.centre.copy_(centre)
    return actor.eval()


def actor_from_mosac(module: nn.Module) -> Actor:
    """`actor_from_mosac_state` of a live MOSAC actor, its structure checked first."""
    check_mosac_actor(module)
    return actor_from_mosac_state(mosac_state(module))


# -- the run --------------------------------------------------------------------------------


class FrameCounter(gym.Wrapper):
    """Counts env steps (and the longest episode) and calls `on_step` after each step."""

    def __init__(self, env: gym.Env, on_step: Callable[[], None] | None = None):
        super().__init__(env)
        self.frames = 0
        self.episode_steps = 0
        self.longest_episode = 0
        self.on_step = on_step

    def reset(self, **kwargs):
        self.episode_steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        out = self.env.step(action)
        self.frames += 1
        self.episode_steps += 1
        self.longest_episode = max(self.longest_episode, self.episode_steps)
        if self.on_step is not None:
            self.on_step()
        return out


@dataclass
class ArchivedActor:
    """One entry of `ActorArchive`: what the run keeps of an archived agent."""

    policy: int  # population index of the agent it is a copy of
    weights: np.ndarray  # the agent's weight vector when it was archived (float64)
    actor: dict[str, torch.Tensor]  # its MOSAC actor's state dict (CPU)
    exchange: int  # exchanges done when it was archived (0: the untrained agents' first evaluation)
    frames: int  # training frames spent when it was archived


class ActorArchive:
    """Stands in for morl-baselines' ParetoArchive (same `add`, `individuals`, `evaluations`):
    the same rule (append, keep the first entry of each non-dominated evaluation, in order)
    but each entry is an `ArchivedActor`, not a deep copy of the agent and its replay buffer.
    MORLD reads only `evaluations` (weight adaptation) and passes individuals around unread."""

    def __init__(self, filter_fn: Callable, clock: Callable[[], tuple[int, int]]):
        self.individuals: list[ArchivedActor] = []
        self.evaluations: list[np.ndarray] = []
        self._filter = filter_fn
        self._clock = clock  # -> (exchange, frames) now

    def add(self, candidate, evaluation: np.ndarray) -> None:
        check_mosac_actor(candidate.wrapped.actor)
        exchange, frames = self._clock()
        record = ArchivedActor(
            int(candidate.id),
            np.array(candidate.weights, dtype=np.float64),
            mosac_state(candidate.wrapped.actor),
            exchange,
            frames,
        )
        self.individuals.append(record)
        self.evaluations.append(evaluation)
        keep = {tuple(x) for x in self._filter(self.evaluations)}
        seen: set[tuple] = set()
        evaluations, individuals = [], []
        for e, ind in zip(self.evaluations, self.individuals):
            key = tuple(e)
            if key in keep and key not in seen:
                seen.add(key)
                evaluations.append(e)
                individuals.append(ind)
        self.evaluations, self.individuals = evaluations, individuals


@dataclass(frozen=True)
class ExchangeRecord:
    """One row of history.csv: the state after `exchange` exchanges (0: before training)."""

    exchange: int
    frames: int  # training frames spent
    front_eval_frames: int  # frames of MORL/D's own archive evaluations so far (not in `frames`)
    trained_policy: int  # the agent that collected this exchange's frames (-1 for exchange 0)
    archive_size: int


@dataclass
class ExportedActor:
    """An actor the run hands over: a final agent ("pop3") or an archive entry ("archive7")."""

    name: str
    actor: Actor
    weights: list[float]  # the MORL/D weight vector (L1 norm 1) it was last trained for
    exchange: int
    frames: int
    morld_estimate: list[float]  # MORL/D's discounted return of stochastic actions (not comparable to ours)


def morld_seeds(seed: int) -> dict[str, int]:
    return dict(zip(_STREAMS, derive_seeds(seed, MORLD_TAG, n=len(_STREAMS))))


def _json_state(state: Any) -> str:
    """A numpy bit generator state (ints, nested dicts, maybe an array) as JSON."""
    return json.dumps(state, default=lambda x: x.tolist())


class MorldRun:
    """One MORL/D run of seed `seed` with params `cfg` on the env `spec` describes.

    A pipeline.core.drive.Run: `start` seeds the envs and makes MORL/D's first archive
    evaluation (exchange 0); `step` does one exchange; `done` once cfg.total_frames training
    frames are spent (whole exchanges). Building a run seeds torch's and numpy's global RNGs
    (MORLD draws from them).
    """

    def __init__(
        self,
        spec: EnvSpec,
        cfg: MorldParams,
        seed: int,
        device: torch.device | str = "cpu",
    ):
        MORLD, filter_fn = require_morl_baselines()
        self.spec, self.cfg, self.seed = spec, cfg, seed
        self.device = torch.device(device)
        self.seeds = morld_seeds(seed)
        torch.manual_seed(self.seeds["torch"])
        np.random.seed(self.seeds["numpy"])
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run: after every training frame
        self.env = FrameCounter(make_env(spec.env_id, spec.max_episode_steps, spec.reward_terms), self._frame)
        self.eval_env = FrameCounter(make_env(spec.env_id, spec.max_episode_steps, spec.reward_terms))
        policy_args = {
            "net_arch": list(cfg.hidden_sizes),
            "batch_size": cfg.batch_size,
            "learning_starts": cfg.learning_starts,
            "buffer_size": cfg.buffer_size,
            "policy_lr": cfg.policy_lr,
            "q_lr": cfg.q_lr,
            "tau": cfg.tau,
            "policy_freq": cfg.policy_freq,
            "target_net_freq": cfg.target_net_freq,
            "alpha": cfg.alpha,
            "autotune": cfg.autotune,
            "device": self.device,  # MORLD passes no device on to its agents
        }
        with _quiet():
            self.algo = MORLD(
                self.env,
                scalarization_method=cfg.scalarization,
                evaluation_mode=cfg.evaluation_mode,
                policy_name="MOSAC",
                policy_args=policy_args,
                gamma=cfg.gamma,
                pop_size=cfg.pop_size,
                seed=seed,
                exchange_every=cfg.exchange_every,
                neighborhood_size=cfg.neighborhood_size,
                shared_buffer=cfg.shared_buffer,
                update_passes=cfg.update_passes,
                weight_init_method=cfg.weight_init,
                weight_adaptation_method=cfg.weight_adaptation,
                log=False,
                device=self.device,
            )
        self.algo.archive = ActorArchive(filter_fn, lambda: (self.exchange, int(self.algo.global_step)))
        self.started = False
        self.exchange = 0
        self.history: list[ExchangeRecord] = []
        self.eval_weights = [np.array(p.weights, dtype=np.float64) for p in self.algo.population]
        self.last_evals = [np.zeros(spec.n_objectives) for _ in self.algo.population]

    # -- the loop ---------------------------------------------------------------------------

    def _private(self, name: str) -> Callable:
        return getattr(self.algo, f"_MORLD__{name}")

    @property
    def frames(self) -> int:
        return int(self.algo.global_step)

    @property
    def done(self) -> bool:
        return self.started and self.frames >= self.cfg.total_frames

    def _evaluate(self) -> list[np.ndarray]:
        """MORL/D's evaluation of every agent, each offered to the archive; remembers the
        weights they were evaluated under (the ones they were trained for)."""
        ref = np.zeros(self.spec.n_objectives)  # read only by wandb logging, which is off
        evals = self._private("eval_all_policies")(self.eval_env, self.cfg.front_eval_episodes, 1, ref, None)
        self.eval_weights = [np.array(p.weights, dtype=np.float64) for p in self.algo.population]
        self.last_evals = [np.asarray(e, dtype=np.float64) for e in evals]
        return evals

    def _record(self, trained: int) -> ExchangeRecord:
        rec = ExchangeRecord(
            self.exchange, self.frames, self.eval_env.frames, trained, len(self.algo.archive.individuals)
        )
        self.history.append(rec)
        return rec

    def _frame(self) -> None:
        if self.on_progress is not None:
            self.on_progress()

    def start(self) -> None:
        """Seed the envs (MORLD resets them unseeded) and evaluate the untrained agents (exchange 0)."""
        if self.started:
            return
        self.env.reset(seed=self.seeds["train_env"])
        self.env.action_space.seed(self.seeds["train_actions"])
        self.eval_env.reset(seed=self.seeds["eval_env"])
        with _quiet():
            self._evaluate()
        self.started = True
        self._record(-1)

    def step(self) -> ExchangeRecord:
        """One exchange: the body of MORLD.train's loop (morl-baselines 1.3.0), in its order."""
        self.start()
        algo = self.algo
        with _quiet():
            policy = self._private("select_candidate")()
            policy.wrapped.train(algo.exchange_every, eval_env=self.eval_env)
            algo.global_step += algo.exchange_every
            for p in algo.population:
                p.wrapped.global_step = algo.global_step
            self._private("update_others")(policy)
            self.exchange += 1
            evals = self._evaluate()
            self._private("share")(policy)
            self._private("adapt_weights")(evals)
        rec = self._record(int(policy.id))
        self.check_finite()
        return rec

    def check_finite(self) -> None:
        """Raise TrainingDiverged (pipeline.core.finite, unit "exchange") if a weight of an
        agent's networks (actor, twin critics and their targets), its entropy temperature or
        a replay buffer value is not finite. MOSAC's losses stay inside morl-baselines (it
        logs them to wandb only), so the weights they train are what is checked, after every
        exchange: before its checkpoint and the export, at most one exchange late."""
        named = []
        for i, p in enumerate(self.algo.population):
            w = p.wrapped
            for net in _NETS:
                named += weights(f"a weight of agent {i}'s {_NET_NAMES[net]}", getattr(w, net))
            if w.autotune:
                named.append((f"agent {i}'s entropy temperature", w.log_alpha))
        for b in self._buffers()[0]:
            for k in ("obs", "actions", "rewards", "next_obs"):
                named.append(("a replay buffer value", torch.from_numpy(np.asarray(getattr(b, k)[: b.size]))))
        check_finite(named, self.exchange, "exchange", seed=self.seed)

    # -- the rest of pipeline.core.drive.Run ----------------------------------------------

    def finish(self) -> None:
        """Nothing follows the last exchange here (the export is `export_members`)."""

    def progress(self) -> tuple[int, str]:
        """Training frames so far (counted frame by frame, mid-exchange too); the exchange, its
        agent and the archive's size."""
        if not self.history or self.exchange == 0:
            return int(self.env.frames), ""
        rec = self.history[-1]
        return int(self.env.frames), f"exchange {rec.exchange} agent {rec.trained_policy} archive {rec.archive_size}"

    def checkpoint_due(self) -> bool:
        """Every morld.checkpoint_every exchanges, and the last one (a run killed while its
        actors are exported need not train again)."""
        return self.exchange > 0 and (self.exchange % self.cfg.checkpoint_every == 0 or self.done)

    def where(self) -> str:
        return f"exchange {self.exchange}"

    def close(self) -> None:
        """Close the training and evaluation envs."""
        self.env.close()
        self.eval_env.close()

    # -- export -----------------------------------------------------------------------------

    def exported_actors(self) -> list[ExportedActor]:
        """The final agents ("pop{i}"), then the archive's entries ("archive{j}", j its position
        in the archive) except exact copies of a final agent (an entry archived at the last
        evaluation is the agent itself)."""
        out, finals = [], []
        for i, p in enumerate(self.algo.population):
            state = mosac_state(p.wrapped.actor)
            finals.append(state)
            out.append(
                ExportedActor(
                    f"pop{i}",
                    actor_from_mosac(p.wrapped.actor),
                    self.eval_weights[i].tolist(),
                    self.exchange,
                    self.frames,
                    self.last_evals[i].tolist(),
                )
            )
        archive = self.algo.archive
        for j, (rec, ev) in enumerate(zip(archive.individuals, archive.evaluations)):
            if any(
                state.keys() == rec.actor.keys() and all(torch.equal(state[k], rec.actor[k]) for k in state)
                for state in finals
            ):
                continue
            out.append(
                ExportedActor(
                    f"archive{j}",
                    actor_from_mosac_state(rec.actor),
                    rec.weights.tolist(),
                    rec.exchange,
                    rec.frames,
                    np.asarray(ev, dtype=np.float64).tolist(),
                )
            )
        return out

    # -- checkpoint -------------------------------------------------------------------------

    def _buffers(self) -> tuple[list, list[int]]:
        """The distinct replay buffers (one when shared) and each agent's index into them."""
        unique, index = [], []
        for p in self.algo.population:
            b = p.wrapped.get_buffer()
            for j, u in enumerate(unique):
                if u is b:
                    index.append(j)
                    break
            else:
                unique.append(b)
                index.append(len(unique) - 1)
        return unique, index

    def state_dict(self) -> dict[str, Any]:
        """Everything the run continues from (at an exchange boundary), weights_only-loadable."""
        if not self.started:
            raise ValueError("state_dict before start(): nothing to save")
        algo = self.algo
        buffers, index = self._buffers()
        agents = []
        for p, b in zip(algo.population, index):
            w = p.wrapped
            agent = {
                name: {k: v.detach().cpu().clone() for k, v in getattr(w, name).state_dict().items()} for name in _NETS
            }
            agent |= {
                "actor_optimizer": w.actor_optimizer.state_dict(),
                "q_optimizer": w.q_optimizer.state_dict(),
                "alpha": float(w.alpha),
                "global_step": int(w.global_step),
                "buffer": b,
                "weights": torch.from_numpy(np.array(p.weights, dtype=np.float64)),
            }
            if w.autotune:
                agent |= {"log_alpha": w.log_alpha.detach().cpu().clone(), "a_optimizer": w.a_optimizer.state_dict()}
            agents.append(agent)

        def rows(a: np.ndarray, n: int) -> torch.Tensor:
            # a full buffer is saved as it is; a partial one as a copy of its filled rows (a
            # view would drag the whole preallocated array into the file)
            return torch.from_numpy(a if n == len(a) else a[:n].copy())

        bufs = [
            {
                "ptr": int(b.ptr),
                "size": int(b.size),
                "max_size": int(b.max_size),
                **{k: rows(getattr(b, k), b.size) for k in ("obs", "next_obs", "actions", "rewards", "dones")},
            }
            for b in buffers
        ]
        archive = [
            {
                "policy": r.policy,
                "weights": torch.from_numpy(r.weights.copy()),
                "actor": r.actor,
                "exchange": r.exchange,
                "frames": r.frames,
                "evaluation": torch.from_numpy(np.array(e, dtype=np.float64)),
            }
            for r, e in zip(algo.archive.individuals, algo.archive.evaluations)
        ]
        np_state = np.random.get_state(legacy=False)
        rng = {
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if self.device.type == "cuda" else [],
            "numpy": _json_state(np_state),
            "morld": _json_state(algo.np_random.bit_generator.state),
            "train_env": _json_state(self.env.unwrapped.np_random.bit_generator.state),
            "train_actions": _json_state(self.env.action_space.np_random.bit_generator.state),
            "eval_env": _json_state(self.eval_env.unwrapped.np_random.bit_generator.state),
        }
        return {
            "version": STATE_VERSION,
            "agents": agents,
            "buffers": bufs,
            "archive": archive,
            "rng": rng,
            "global_step": int(algo.global_step),
            "iteration": int(algo.iteration),
            "current_policy": int(algo.current_policy),
            "exchange": self.exchange,
            "history": [asdict(r) for r in self.history],
            "eval_weights": [torch.from_numpy(w.copy()) for w in self.eval_weights],
            "last_evals": [torch.from_numpy(e.copy()) for e in self.last_evals],
            "frames_eval": int(self.eval_env.frames),
            "frames_train": int(self.env.frames),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from `state_dict()` of a run of the same spec, params and seed (ValueError if it cannot be)."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"state version {state.get('version')!r}, expected {STATE_VERSION}")
        algo = self.algo
        buffers, index = self._buffers()
        if len(state["agents"]) != len(algo.population) or [a["buffer"] for a in state["agents"]] != index:
            raise ValueError(
                f"{len(state['agents'])} agents / buffer layout {[a['buffer'] for a in state['agents']]} saved, "
                f"the run has {len(algo.population)} / {index}"
            )
        for b, saved in zip(buffers, state["buffers"]):
            n = saved["size"]
            if saved["max_size"] != b.max_size or saved["obs"].shape[1:] != b.obs.shape[1:]:
                raise ValueError(
                    f"replay buffer of {saved['max_size']} rows x {tuple(saved['obs'].shape[1:])} saved, "
                    f"the run's has {b.max_size} x {b.obs.shape[1:]}"
                )
            for k in ("obs", "next_obs", "actions", "rewards", "dones"):
                getattr(b, k)[:n] = saved[k][:n].numpy()
            b.ptr, b.size = saved["ptr"], n
        for p, saved in zip(algo.population, state["agents"]):
            w = p.wrapped
            for name in _NETS:
                getattr(w, name).load_state_dict(saved[name])
            w.actor_optimizer.load_state_dict(saved["actor_optimizer"])
            w.q_optimizer.load_state_dict(saved["q_optimizer"])
            if w.autotune:
                with torch.no_grad():
                    w.log_alpha.copy_(saved["log_alpha"])  # in place: the temperature optimiser keeps its tensor
                w.a_optimizer.load_state_dict(saved["a_optimizer"])
                w.alpha_tensor = w.log_alpha.detach().exp()
            w.alpha = saved["alpha"]
            w.global_step = saved["global_step"]
            weights = saved["weights"].numpy().copy()
            p.weights = weights
            w.set_weights(weights)
        archive = algo.archive
        archive.individuals = [
            ArchivedActor(r["policy"], r["weights"].numpy().copy(), r["actor"], r["exchange"], r["frames"])
            for r in state["archive"]
        ]
        archive.evaluations = [r["evaluation"].numpy().copy() for r in state["archive"]]
        algo.global_step, algo.iteration, algo.current_policy = (
            state["global_step"],
            state["iteration"],
            state["current_policy"],
        )
        self.exchange = state["exchange"]
        self.history = [ExchangeRecord(**r) for r in state["history"]]
        self.eval_weights = [w.numpy().copy() for w in state["eval_weights"]]
        self.last_evals = [e.numpy().copy() for e in state["last_evals"]]
        self.eval_env.frames, self.env.frames = state["frames_eval"], state["frames_train"]
        rng = state["rng"]
        if not self.started:  # make the envs' and the action space's generators exist (seeded below)
            self.env.reset(seed=self.seeds["train_env"])
            self.env.action_space.seed(self.seeds["train_actions"])
            self.eval_env.reset(seed=self.seeds["eval_env"])
        self.env.unwrapped.np_random.bit_generator.state = json.loads(rng["train_env"])
        self.env.action_space.np_random.bit_generator.state = json.loads(rng["train_actions"])
        self.eval_env.unwrapped.np_random.bit_generator.state = json.loads(rng["eval_env"])
        algo.np_random.bit_generator.state = json.loads(rng["morld"])
        np_state = json.loads(rng["numpy"])
        np_state["state"]["key"] = np.asarray(np_state["state"]["key"], dtype=np.uint32)
        np.random.set_state(np_state)
        torch.set_rng_state(rng["torch"])
        if self.device.type == "cuda" and rng["cuda"]:
            torch.cuda.set_rng_state_all(rng["cuda"])
        self.started = True


# -- export ---------------------------------------------------------------------------------


def evaluate_exported(
    actors: Sequence[Actor], spec: EnvSpec, seed: int, episodes: int, chunk: int = 8
) -> list[EvalResult]:
    """Deterministic evaluation of each actor for `episodes` episodes; actor i on
    eval_seeds(seed, EVAL_STREAM, i, episodes), `chunk` actors at a time in one batch."""
    width = min(chunk, len(actors))
    envs = [make_env(spec.env_id, spec.max_episode_steps, spec.reward_terms) for _ in range(episodes * width)]
    try:
        results: list[EvalResult] = []
        for start in range(0, len(actors), chunk):
            group = list(actors[start : start + chunk])
            seeds = [eval_seeds(seed, EVAL_STREAM, i, episodes) for i in range(start, start + len(group))]
            results += evaluate_policies(group, envs, seeds)
        return results
    finally:
        for env in envs:
            env.close()


def export_members(run: MorldRun, episodes: int) -> tuple[list[Member], dict[str, Any]]:
    """The run's actors as population members, each scored by our own deterministic evaluation.

    Member fields: origin "morld", objective None, policy_name "pop{i}" / "archive{j}",
    iteration = the exchange after which it was taken (the final agents: the last exchange;
    an archive entry: when it was archived, 0 = an untrained agent), parents [],
    target_weight = its MORL/D weight vector (L1 norm 1, not MAPEX's L2-normalised weights),
    returns / returns_std = mean / std of `episodes` deterministic undiscounted episodes,
    env_samples = training frames spent when it was taken (the final agents: all of them).
    Also returns extra metadata: the frame counts and MORL/D's own (discounted, stochastic)
    archive scores by policy name, kept for reference only.
    """
    exported = run.exported_actors()
    check_finite(
        [(f"a weight of exported actor {e.name}", p) for e in exported for p in e.actor.parameters()],
        run.exchange,
        "exchange",
        seed=run.seed,
    )
    results = evaluate_exported([e.actor for e in exported], run.spec, run.seed, episodes)
    members = [
        Member(
            origin="morld",
            objective=None,
            iteration=e.exchange,
            parents=[],
            target_weight=e.weights,
            returns=r.mean.tolist(),
            returns_std=r.std.tolist(),
            eval_episodes=episodes,
            env_samples=e.frames,
            hidden_sizes=hidden_sizes_of(e.actor),
            actor=actor_state(e.actor),
            policy_name=e.name,
        )
        for e, r in zip(exported, results)
    ]
    extra = {
        "training_frames": run.frames,
        "exchanges": run.exchange,
        "front_eval_frames": int(run.eval_env.frames),
        "export_eval_frames": int(sum(r.env_samples for r in results)),
        "morld_estimates": {e.name: e.morld_estimate for e in exported},
        "morl_baselines_version": MORL_BASELINES_VERSION,
    }
    return members, extra


def history_csv_rows(history: Sequence[ExchangeRecord]) -> list[dict[str, int]]:
    return [asdict(r) for r in history]
