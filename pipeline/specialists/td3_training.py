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
sync is reading the actions to step the envs (and, every CHECK_EVERY updates, the check that
the losses and weights are finite: pipeline.core.finite). The two devices therefore draw
different (each reproducible) minibatches.

Checkpoints: `SpecialistsRun.state_dict` holds every piece of a run's state (networks,
optimizers, replay buffers, RNG streams, counters, the episode history and each env's
mid-episode state, `env_state`), so a run restored after any step goes on bitwise as the
uninterrupted one on a CPU. Only MuJoCo envs (behind gymnasium's standard wrappers) can be
saved mid-episode; `env_checkpoint_problem` says why another cannot. On CUDA the state is
saved as CPU tensors and restored onto the device (untested here: no GPU).

Keep-best (train_specialist.keep_best_every > 0; off by default, as in the paper and plain
TD3): after every env step t that is a multiple of keep_best_every and past learning_starts,
and after the last step (`keep_best_steps`), each specialist's actor is scored by
keep_best_episodes deterministic episodes (no exploration noise) on an evaluation env of its
own, reset with seeds derived from (seed, objective, check index) alone: the mean undiscounted
return on its own objective. A CPU copy of the best-scoring actor and its target actor (the
earlier on ties; never a non-finite score) is kept, and `results` returns them instead of the
final ones; critics and buffer stay final. The checks draw from no training stream (the
training envs, numpy generators, torch generators and torch's global RNG are untouched), so
the training itself is bitwise the same with keep-best on or off; the snapshots and every
check's (step, score) are part of `state_dict`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.buffer import StackedReplay
from pipeline.core.envs import EnvSpec, make_env
from pipeline.core.envstate import env_state, restore_env_state
from pipeline.core.finite import TrainingDiverged, due, first_nonfinite, optimizer_state, weights
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.core.seeding import derive_seeds, torch_generator
from pipeline.evaluation.episodes import evaluate_policy
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.td3 import GraphedUpdate, StackedTD3, TD3State, stacked_update


@dataclass
class EpisodeRecord:
    episode: int
    end_step: int  # global env step at which the episode ended (1-based count)
    length: int
    returns: np.ndarray  # (n_objectives,) undiscounted
    terminated: bool


@dataclass
class KeepBest:
    """What keep-best selection (train_specialist.keep_best_every > 0) did for one specialist."""

    every: int  # keep_best_every
    episodes: int  # keep_best_episodes
    checks: list[tuple[int, float]]  # (env step, score) of every check, in order; the last is the final actor's
    step: int | None  # env step of the kept actor; None: no check scored finite, the final actor is kept
    score: float | None  # its score (mean deterministic return on the specialist's own objective)


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


def init_stacked(
    spec: EnvSpec, cfg: TrainSpecialistParams, jobs: Sequence[tuple[int, int]], device: torch.device
) -> StackedTD3:
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
        raise ValueError(
            f"stacked specialists need critic ensembles of one size, 2 members per covered objective: {list(covered)}"
        )
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


KEEP_BEST_TAG = 0x6B33_B357  # separates keep-best evaluation seeds from a specialist's training streams


def keep_best_due(cfg: TrainSpecialistParams, t: int) -> bool:
    """Whether a keep-best check follows env step t (t steps taken): t a multiple of
    keep_best_every past learning_starts, or the last step; never when keep-best is off."""
    every = cfg.keep_best_every
    return every > 0 and cfg.learning_starts < t <= cfg.total_steps and (t % every == 0 or t == cfg.total_steps)


def keep_best_steps(cfg: TrainSpecialistParams) -> list[int]:
    """Every env step a keep-best check follows, in order ([] when keep-best is off)."""
    return [t for t in range(cfg.learning_starts + 1, cfg.total_steps + 1) if keep_best_due(cfg, t)]


def keep_best_seeds(seed: int, objective: int, check: int, episodes: int) -> list[int]:
    """Env reset seeds of keep-best check number `check` (0-based) of specialist (seed, objective)."""
    return derive_seeds(seed, objective, KEEP_BEST_TAG, check, n=episodes)


def keep_best_score(actor: Actor, env: gym.Env, objective: int, seeds: Sequence[int]) -> float:
    """Mean undiscounted return on `objective` of deterministic episodes of `actor` (CPU), one
    per seed, one after another on `env`. NaN, without running any episode, if a weight is not
    finite (MuJoCo would be stepped with NaN actions)."""
    if not all(bool(torch.isfinite(v).all()) for v in actor.state_dict().values()):
        return math.nan
    returns = [evaluate_policy(actor, [env], [int(s)]).returns[0, objective] for s in seeds]
    return float(np.mean(returns))


def unstack_actor(actor: StackedActor, s: int) -> Actor:
    """Actor s of a stacked set as a CPU `Actor`, leaving torch's global RNG as it was (building
    an `Actor` draws its throwaway initial weights from it)."""
    with torch.random.fork_rng(devices=[]):
        return actor.unstack(s)


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


class _Updater:
    """Draws each specialist's minibatch rows and smoothing noise and runs one stacked update."""

    def __init__(
        self,
        state: StackedTD3,
        buffer: StackedReplay,
        cfg: TrainSpecialistParams,
        seeds: list[dict[str, int]],
        rngs,
        device,
    ):
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
        # the latest critic and actor losses (eager updates only: a captured graph keeps its own)
        self.metrics: dict[str, torch.Tensor] = {}

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
            idx = torch.from_numpy(
                np.stack([rng.integers(0, self.buffer.size, size=self.cfg.batch_size) for rng in self.rngs])
            )
        if self.graphs:
            self.graph()(update_actor)
        else:
            self.metrics.update(
                stacked_update(self.state, self.buffer.gather(idx), self.noise, update_actor, **self.args)
            )


STATE_FORMAT = "mapex.specialists_state"
STATE_VERSION = 2  # 2: keep-best checks and snapshots


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
    return _cpu(
        {
            "actor": st.actor.state_dict(),
            "actor_target": st.actor_target.state_dict(),
            "critic": st.critic.state_dict(),
            "critic_target": st.critic_target.state_dict(),
            "actor_opt": st.actor_opt.state_dict(),
            "critic_opt": st.critic_opt.state_dict(),
        }
    )


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
        raise ValueError(
            f"state's buffer rows {tuple(saved['rows'].shape)} do not fit ({b.n}, {size}, {b.rows.shape[2]})"
        )


def load_buffer_state(b: StackedReplay, saved: dict[str, Any]) -> None:
    """Restore a `buffer_state` (checked by `check_buffer_state`) into `b`."""
    size = int(saved["size"])
    with torch.no_grad():
        b.rows[:, :size].copy_(saved["rows"])
    for k, v in b.host.items():
        v[:, :size] = saved[k].numpy()
    b.ptr, b.size = int(saved["ptr"]), size


def finite_named(update: _Updater, full: bool) -> list[tuple[str, torch.Tensor]]:
    """What `check_finite` looks at in stacked networks under training: the latest losses
    (eager updates; Q-values enter both, so a non-finite Q-value shows there) and the online
    weights; with `full` (before a checkpoint or the results) also the target networks, the
    optimizers' moments and the replay buffer rows."""
    st, b = update.state, update.buffer
    named = [(name.replace("_", " "), v) for name, v in update.metrics.items()]  # "critic loss", "actor loss"
    named += weights("a critic weight", st.critic) + weights("an actor weight", st.actor)
    if full:
        named += weights("a target critic weight", st.critic_target)
        named += weights("a target actor weight", st.actor_target)
        named += optimizer_state("a critic optimizer moment", st.critic_opt)
        named += optimizer_state("an actor optimizer moment", st.actor_opt)
        named.append(("a replay buffer value", b.rows[:, : b.size]))
    return named


def diverged_specialist(update: _Updater) -> int | None:
    """The first specialist s of a stacked set whose networks, optimizer moments or replay
    buffer hold a non-finite value, else None (only called once a check has failed)."""
    st, b = update.state, update.buffer
    e = st.critic.n_members // st.n

    def moments(opt) -> list[torch.Tensor]:
        return [v for state in opt.state.values() for v in state.values() if torch.is_tensor(v) and v.dim() > 0]

    for s in range(st.n):
        parts = [p[s * e : (s + 1) * e] for m in (st.critic, st.critic_target) for p in m.parameters()]
        parts += [v[s * e : (s + 1) * e] for v in moments(st.critic_opt)]
        parts += [p[s] for m in (st.actor, st.actor_target) for p in m.parameters()]
        parts += [v[s] for v in moments(st.actor_opt)]
        parts.append(b.rows[s, : b.size])
        if first_nonfinite([("", t) for t in parts]) is not None:
            return s
    return None


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
        cfg: TrainSpecialistParams,
        jobs: Sequence[tuple[int, int]],
        device: torch.device,
    ):
        for seed, objective in jobs:
            if not 0 <= objective < spec.n_objectives:
                raise ValueError(
                    f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives"
                )
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
        # keep-best: every check's (step, score) and the best snapshot ({step, score, actor,
        # actor_target}, CPU state dicts) per specialist; the evaluation envs are built at the first check
        self.checks: list[list[tuple[int, float]]] = [[] for _ in range(n)]
        self.best: list[dict[str, Any] | None] = [None] * n
        self.eval_envs: list[gym.Env] | None = None

    @property
    def done(self) -> bool:
        return self.t >= self.cfg.total_steps

    def step(self) -> list[EpisodeRecord | None]:
        """One env step of every specialist (and one update once learning has started, and a
        keep-best check where `keep_best_due`); returns, per specialist, the record of the
        episode this step ended, else None."""
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
            records[s] = EpisodeRecord(
                int(self.episode[s]), t + 1, int(self.ep_step[s]), self.ep_return[s].copy(), bool(terminated[s])
            )
            self.episodes[s].append(records[s])
            self.obs[s] = envs[s].reset()[0]
            self.episode[s] += 1
            self.ep_step[s] = 0
            self.ep_return[s] = 0.0
        if t >= cfg.learning_starts:
            self.n_updates += 1
            self.update(update_actor=self.n_updates % cfg.policy_freq == 0)
        self.t = t + 1
        if t >= cfg.learning_starts and due(self.n_updates):
            self.check_finite()
        if keep_best_due(cfg, self.t):
            self.keep_best_check()
        return records

    def keep_best_check(self) -> None:
        """Score every specialist's current actor (`keep_best_score`, on its own evaluation env,
        seeds from (seed, objective, check index)); record (step, score) and keep a CPU copy of
        the actor and its target actor if the score is finite and beats the best so far."""
        if self.eval_envs is None:
            self.eval_envs = [make_env(self.spec.env_id, self.spec.max_episode_steps) for _ in self.jobs]
        for s, ((seed, objective), env) in enumerate(zip(self.jobs, self.eval_envs)):
            seeds = keep_best_seeds(seed, objective, len(self.checks[s]), self.cfg.keep_best_episodes)
            actor = unstack_actor(self.state.actor, s)
            score = keep_best_score(actor, env, objective, seeds)
            self.checks[s].append((self.t, score))
            best = self.best[s]
            if math.isfinite(score) and (best is None or score > best["score"]):
                self.best[s] = {
                    "step": self.t,
                    "score": score,
                    "actor": actor.state_dict(),
                    "actor_target": unstack_actor(self.state.actor_target, s).state_dict(),
                }

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
                    "best": None if best is None else _cpu(best),
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
        self.t, self.n_updates = int(c["t"]), int(c["n_updates"])

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
                    name: _cpu(b[name])
                    for name in ("actor", "actor_target")  # copies: the state may be memory-mapped
                }
            best.append(b)
        self.checks, self.best = checks, best


def continue_training(
    run: SpecialistsRun,
    on_step: Callable[[int, list[EpisodeRecord | None]], None] | None = None,
    on_checkpoint: Callable[[SpecialistsRun], None] | None = None,
) -> list[SpecialistResult]:
    """Step `run` (fresh or restored) to cfg.total_steps and return its results.

    `on_step(t, records)` after every step; `on_checkpoint(run)` after every
    cfg.checkpoint_every-th step but the last (none when it is 0): save `run.state_dict()`
    there. An exception raised in a callback stops the run.

    Raises TrainingDiverged (pipeline.core.finite) when a loss, weight or buffer value is not
    finite: checked every CHECK_EVERY updates, before every checkpoint and before the results,
    so no checkpoint and no result holds a diverged state."""
    every = run.cfg.checkpoint_every
    while not run.done:
        records = run.step()
        if on_step is not None:
            on_step(run.t, records)
        if on_checkpoint is not None and every and run.t % every == 0 and not run.done:
            run.check_finite(full=True)
            on_checkpoint(run)
    run.check_finite(full=True)
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
