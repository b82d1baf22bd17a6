"""MAPEX Algorithm 1's outer loop as a run, shaped like the other algorithms' runs.

`ExtractionRun` holds the population Pi (its members: every starting policy, then every
child), the specialists' buffers D_k and critics Q^(k)_m (none for the warm-up-only variant,
epochs = 0, which reads no critics), and the history of the run.
`start()` evaluates the starting policies; each `step()` is one iteration of Algorithm 1's while
loop: the whole population's returns choose parents and target weights, each of
`children_per_iteration` children is trained on its own hybrid buffer
(pipeline.extraction.children.make_children) and evaluated, and joins the population.
`state_dict()` / `load_state_dict()` save and restore the run between iterations (the members as
an append-only log, see pipeline.core.resume), so a resumed run ends bitwise as an uninterrupted
one on the same machine.

Random streams: member i is evaluated on evaluation stream i (seed, EVAL_STREAM, i); child c
(counted from 1 over the run) draws from derive_seeds(seed, EXTRACT_TAG, c), so with one
child per iteration child c has the streams iteration c always had.

Not in the paper, each off by default (pipeline/params/extract.py EXTENSION_KEYS):
- `seed_interpolation` > 0: `start()` also mixes and evaluates the interpolation baseline's grid
  of policies between the specialists (pipeline.core.mixing; origin "interpolated", iteration
  0), so the first gaps drawn are those interpolation leaves. Member i of the grid is evaluated
  on the episodes the baseline evaluates its member i on, so the two are the same policies with
  the same returns.
- `init: interpolate`: children start from their parents' mixed weights
  (pipeline.extraction.mapex.start_child); each one's record says whether it did or fell back.
- `stop_patience` > 0: the run stops once `stop_hypervolume` has risen by at most
  `stop_min_gain` (a fraction) over `stop_patience` iterations (`should_stop`); `stopped_at`.
Every iteration's wall and CPU seconds of training and of evaluating are kept in `costs`
(pipeline.core.cost, rows of COST_FIELDS; part of the checkpointed state, so a resumed run keeps
them), for the stage's provenance record: never in an artifact.
"""

from __future__ import annotations

import copy
from dataclasses import asdict
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.alignment import MixOptions, buffer_states, mixer
from pipeline.core.artifacts import csv_text
from pipeline.core.cost import Stopwatch, cost_row
from pipeline.core.drive import fmt_vec
from pipeline.core.finite import TrainingDiverged
from pipeline.core.mixing import chosen_specialists, mixing_weights, starts_problem
from pipeline.core.nets import CriticEnsemble
from pipeline.core.pareto import hypervolume, normalised_hypervolume, pareto_mask
from pipeline.core.population import Member, actor_state, member_actor
from pipeline.core.precision import frozen, resolve
from pipeline.core.seeding import derive_seeds
from pipeline.core.specialist import Slot, StartingPolicy
from pipeline.evaluation.episodes import EvalResult, eval_seeds, evaluate_policies, evaluate_policy
from pipeline.extraction.children import make_children
from pipeline.extraction.mapex import AdvantageConfig, ChildConfig, ChildSeeds
from pipeline.params.extract import AWR_KEYS, EXTENSION_KEYS, ExtractParams

EXTRACT_TAG = 0xE87AC7
EVAL_STREAM = 0  # evaluation seeds of extraction; the evaluate stage uses fresh streams
HISTORY_FIELDS = ["iteration", "population", "front_size", "env_samples"]
SEED_ORIGIN = "interpolated"  # the origin of a policy seeded by extract.seed_interpolation (as the baseline's)


def child_seeds(seed: int, first: int, k: int) -> list[ChildSeeds]:
    """Streams of the run's children first .. first + k - 1 (counted from 1): child c's depend on
    (seed, c) alone, so with K = 1 child c has the streams iteration c always had."""
    return [ChildSeeds(*derive_seeds(seed, EXTRACT_TAG, c, n=3)) for c in range(first, first + k)]


def child_config(cfg: ExtractParams, precision: str = "fp32") -> ChildConfig:
    """The `extract` params that shape one child's training; `precision` the resolved
    extract.precision (pipeline.core.precision)."""
    return ChildConfig(
        precision=precision,
        hidden_sizes=tuple(cfg.hidden_sizes),
        child_buffer_size=cfg.child_buffer_size,
        weight_norm=cfg.weight_norm,
        warmup_steps=cfg.warmup_steps,
        warmup_lr=cfg.warmup_lr,
        warmup_batch_size=cfg.warmup_batch_size,
        adv=AdvantageConfig(
            epochs=cfg.epochs,
            beta=cfg.beta,
            omega_max=cfg.omega_max,
            lr=cfg.lr,
            batch_size=cfg.batch_size,
            max_grad_norm=cfg.max_grad_norm,
            recompute=cfg.advantage_recompute,
            norm=cfg.advantage_norm,
        ),
        facet_bridge_ratio=cfg.facet_bridge_ratio,
        init=cfg.init,
        warmup_after_interpolate=cfg.warmup_after_interpolate,
        mixing=mix_options(cfg),
        mix_states=cfg.mix_states,
    )


def mix_options(cfg: ExtractParams) -> MixOptions:
    """extract.align, repair, mix and regmean_alpha as the interpolation stage's MixOptions."""
    return MixOptions(align=cfg.align, repair=cfg.repair, mix=cfg.mix, regmean_alpha=cfg.regmean_alpha)


def stop_hypervolume(returns: np.ndarray, lo: np.ndarray, span: np.ndarray) -> float:
    """The hypervolume the early-stopping rule watches: of `returns` (n, m) scaled as
    (returns - lo) / span, reference point at 0. The extraction passes the starting policies'
    per-objective minimum and range (fixed for the run, so the curve never falls as members
    join), since the report's reference point (env.reference_point) is not an input of
    extraction; a member below the starting policies' minimum on an objective adds nothing."""
    return hypervolume((returns - lo) / span, np.zeros(returns.shape[1]))


def should_stop(curve: Sequence[float], patience: int, min_gain: float) -> bool:
    """The early-stopping rule (not in the paper) after the last entry of `curve` (its
    hypervolume after iterations 0, 1, ..., t): stop when patience > 0, t >= patience and
    curve[t] - curve[t - patience] <= min_gain * curve[t - patience], i.e. it has not risen by
    more than the fraction `min_gain` over the last `patience` iterations (a curve still at 0
    then stops too)."""
    t = len(curve) - 1
    if patience <= 0 or t < patience:
        return False
    before = curve[t - patience]
    return curve[t] - before <= min_gain * before


def history_row(iteration: int, members: Sequence[Member]) -> dict[str, int]:
    returns = np.array([m.returns for m in members])
    return {
        "iteration": iteration,
        "population": len(members),
        "front_size": int(pareto_mask(returns).sum()),
        "env_samples": members[-1].env_samples,
    }


def history_csv(rows: Sequence[dict]) -> str:
    """history.csv: population, front size and env samples after each iteration (0 = the start)."""
    return csv_text(HISTORY_FIELDS, rows)


class ExtractionRun:
    """Algorithm 1 over one seed's specialists (see the module docstring).

    cfg: the resolved `extract` params (a variant's changes already applied, e.g. epochs 0 for
    warmup_only). critics: Q^(k) per specialist, or None when cfg.epochs == 0 (warm-up only:
    no child reads a critic, so specialists without critics, e.g. imported ones, will do).
    meta: env_id, obs_dim, act_dim, n_objectives, action_low, action_high (what a child's actor
    is rebuilt from). envs: cfg.eval_episodes * cfg.children_per_iteration envs.
    cfg.precision is resolved on `device` at the child's widest hidden layer; with bf16 the
    critics are cast to bfloat16 once, here, and every child trains in bf16 (its evaluation
    episodes stay fp32).
    """

    def __init__(
        self,
        starts: Sequence[StartingPolicy],
        buffers: Sequence[dict[str, np.ndarray]],
        critics: Sequence[CriticEnsemble] | None,
        cfg: ExtractParams,
        meta: dict[str, Any],
        seed: int,
        envs: Sequence[gym.Env],
        device: torch.device,
    ) -> None:
        self.starts, self.buffers, self.cfg, self.meta, self.seed = list(starts), list(buffers), cfg, meta, seed
        if critics is None and cfg.epochs > 0:
            raise ValueError(f"extract.epochs = {cfg.epochs} trains with the critics, but none were given")
        self.precision = resolve(cfg.precision, device, max(cfg.hidden_sizes))
        self.critics = None if critics is None else [frozen(c.to(device), self.precision) for c in critics]
        self.envs, self.device = list(envs), device
        self.child_cfg = child_config(cfg, self.precision)
        self.k = cfg.children_per_iteration
        self.actors = [s.actor.to(device) for s in self.starts]  # the population's actors, member by member
        self.members: list[Member] = []
        self.history: list[dict[str, int]] = []
        self.last: list[EvalResult] = []  # the last iteration's children's evaluations
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run
        # extract.seed_interpolation: the grid's mixing weights, or why the specialists cannot be mixed
        self.seed_problem = starts_problem(self.starts) if cfg.seed_interpolation else None
        self.seed_weights = (
            mixing_weights(int(meta["n_objectives"]), cfg.seed_interpolation)
            if cfg.seed_interpolation and self.seed_problem is None
            else []
        )
        self.seed_mixing_fallback: str | None = None  # why extract.align/repair/mix could not apply to the seeds
        self._fallbacks: dict[str, int] = {}  # init interpolate: why children fell back, reason -> count
        self.costs: list[dict] = []  # per-iteration cost rows (pipeline.core.cost.COST_FIELDS)
        self.stop_curve: list[float] = []  # stop_hypervolume after iterations 0, 1, ... (stop_patience > 0)
        self.stopped_at: int | None = None  # the iteration after which the early-stopping rule stopped the run

    @classmethod
    def from_slots(
        cls,
        slots: Sequence[Slot],
        cfg: ExtractParams,
        meta: dict[str, Any],
        seed: int,
        envs: Sequence[gym.Env],
        device: torch.device,
    ) -> "ExtractionRun":
        """A run over the specialists' slots (pipeline.core.specialist.load_slots): every policy
        of every slot's set starts the population; slot k gives D_k and Q^(k) (slots read
        without critics give none: cfg.epochs must be 0 then)."""
        starts = [p for s in slots for p in s.starts]
        critics = [s.critic for s in slots]
        if any(c is None for c in critics):
            if any(c is not None for c in critics):
                raise ValueError("some slots were read with critics and some without")
            critics = None
        return cls(starts, [s.buffer for s in slots], critics, cfg, meta, seed, envs, device)

    @property
    def n_start(self) -> int:
        return len(self.starts)

    @property
    def n_initial(self) -> int:
        """Members before the first child: the starting policies and the interpolated seeds."""
        return len(self.starts) + len(self.seed_weights)

    @property
    def iteration(self) -> int:
        """Iterations done (0 before the first child)."""
        return max(len(self.members) - self.n_initial, 0) // self.k

    @property
    def done(self) -> bool:
        return self.iteration >= self.cfg.iterations or self.stopped_at is not None

    @property
    def samples(self) -> int:
        """Env frames spent on evaluation so far (the only env interaction of extraction)."""
        return self.members[-1].env_samples if self.members else 0

    def _seeds(self, member: int) -> list[int]:
        return eval_seeds(self.seed, EVAL_STREAM, member, self.cfg.eval_episodes)

    def _member(self, res: EvalResult, actor, **origin) -> Member:
        return Member(
            **origin,
            returns=res.mean.tolist(),
            returns_std=res.std.tolist(),
            eval_episodes=self.cfg.eval_episodes,
            env_samples=self.samples + res.env_samples,
            actor=actor_state(actor),
        )

    def start(self) -> None:
        """Evaluate the starting policies: they become members 0 .. n_start - 1 (a TD3
        specialist's single policy is member k); then, with extract.seed_interpolation, the
        interpolated seeds (`add_seeds`)."""
        if self.members:
            raise RuntimeError("start runs once, before any iteration")
        with Stopwatch() as ev:
            for i, (s, actor) in enumerate(zip(self.starts, self.actors)):
                res = evaluate_policy(actor, self.envs, self._seeds(i))
                self.members.append(
                    self._member(
                        res,
                        actor,
                        origin="specialist",
                        objective=s.objective,
                        iteration=0,
                        parents=[],
                        target_weight=None,
                        hidden_sizes=s.hidden_sizes,
                        policy_name=s.name,
                    )
                )
        self.costs.append(cost_row(0, "start", self.n_start, None, ev))
        if self.seed_weights:
            self.add_seeds()
        self.history.append(history_row(0, self.members))
        self._watch()

    def add_seeds(self) -> None:
        """extract.seed_interpolation (not in the paper): the interpolation baseline's grid
        (pipeline.core.mixing.mixing_weights, at most seed_interpolation points) of policies
        mixed from the chosen specialists (per objective the starting policy best on it), each
        evaluated and added as a member of origin "interpolated", iteration 0: the population
        Algorithm 1 starts from. Recorded like the baseline's members (target_weight: the mixing
        weights; parents: the specialists mixed with a weight > 0)."""
        n_obj = len(self.seed_weights[0])
        chosen = chosen_specialists(self.starts, [m.returns for m in self.members], n_obj)
        # on the CPU (a copy where the run trains on a GPU: the population's actors stay put)
        mixed = [self.starts[i].actor for i in chosen]
        mixed = [copy.deepcopy(a).cpu() if next(a.parameters()).is_cuda else a for a in mixed]
        spent = np.zeros(4)  # wall and CPU seconds of mixing, then of evaluating
        options = mix_options(self.cfg)
        with Stopwatch() as setup:  # extract.align, repair, mix: the interpolation stage's mixer
            obs = buffer_states(self.buffers, self.cfg.mix_states, self.seed) if options.needs_states else None
            make, self.seed_mixing_fallback = mixer(mixed, options, obs)
        spent += (setup.wall, setup.cpu, 0, 0)
        for w in self.seed_weights:
            with Stopwatch() as mix:
                actor = make(w).to(self.device)
            with Stopwatch() as ev:
                res = evaluate_policy(actor, self.envs, self._seeds(len(self.members)))
            spent += (mix.wall, mix.cpu, ev.wall, ev.cpu)
            self.members.append(
                self._member(
                    res,
                    actor,
                    origin=SEED_ORIGIN,
                    objective=None,
                    iteration=0,
                    parents=[chosen[i] for i, x in enumerate(w) if x > 0],
                    target_weight=list(w),
                    hidden_sizes=[m.out_features for m in actor.net if isinstance(m, torch.nn.Linear)][:-1],
                    policy_name=None,
                )
            )
            self.actors.append(actor)
        row = cost_row(0, "seeds", len(self.seed_weights), None, None)
        for key, value in zip(("train_wall_s", "train_cpu_s", "eval_wall_s", "eval_cpu_s"), spent):
            row[key] = round(float(value), 4)
        self.costs.append(row)

    def _watch(self) -> None:
        """The early-stopping rule (extract.stop_patience > 0) after the iteration just ended."""
        if self.cfg.stop_patience <= 0:
            return
        returns = np.array([m.returns for m in self.members])
        start = returns[: self.n_start]
        lo = start.min(axis=0)
        span = np.where(start.max(axis=0) > lo, start.max(axis=0) - lo, 1.0)
        self.stop_curve.append(stop_hypervolume(returns, lo, span))
        if should_stop(self.stop_curve, self.cfg.stop_patience, self.cfg.stop_min_gain):
            self.stopped_at = self.iteration

    def step(self, on_step: Callable[[], None] | None = None) -> None:
        """One iteration: parents and target weights from the whole population, k children
        trained and evaluated, each joining the population. Raises TrainingDiverged (naming
        the seed and iteration) if a child's training diverges: nothing joins then."""
        it = self.iteration + 1
        returns = np.array([m.returns for m in self.members])
        seeds = child_seeds(self.seed, len(self.members) - self.n_initial + 1, self.k)
        try:
            with Stopwatch() as train:
                children = make_children(
                    returns, self.actors, self.buffers, self.critics, self.child_cfg, seeds, self.device
                )
        except TrainingDiverged as exc:
            raise exc.about(seed=self.seed, during=f"iteration {it}")
        ids = range(len(self.members), len(self.members) + self.k)
        with Stopwatch() as ev:
            self.last = evaluate_policies([a for a, _ in children], self.envs, [self._seeds(i) for i in ids])
        for (child, rec), res in zip(children, self.last):
            self.members.append(
                self._member(
                    res,
                    child,
                    origin="child",
                    objective=None,
                    iteration=it,
                    parents=list(rec.parents),
                    target_weight=rec.weight.tolist(),
                    hidden_sizes=list(self.cfg.hidden_sizes),
                    policy_name=None,
                    init=rec.init,
                )
            )
            self.actors.append(child)
            if rec.fallback is not None:
                self._fallbacks[rec.fallback] = self._fallbacks.get(rec.fallback, 0) + 1
        self.costs.append(cost_row(it, "children", self.k, train, ev))
        self.history.append(history_row(it, self.members))
        self._watch()

    def normalised_hypervolume(self) -> float:
        return normalised_hypervolume(np.array([m.returns for m in self.members]))

    # -- the verbs of pipeline.core.drive.Run ---------------------------------------------

    def finish(self) -> None:
        """Nothing follows the last iteration: the members are the output."""

    def progress(self) -> tuple[int, str]:
        """Children made so far; the front, its normalised hypervolume and the last child's returns."""
        if not self.last:
            return self.iteration * self.k, ""
        return self.iteration * self.k, (
            f"front {self.history[-1]['front_size']} HV(norm) {self.normalised_hypervolume():.3f} "
            f"child {fmt_vec(self.last[-1].mean)}"
        )

    def checkpoint_due(self) -> bool:
        """Every iteration (and the start) is checkpointed."""
        return True

    def where(self) -> str:
        return f"iteration {self.iteration}" if self.iteration else "the start (the specialists' policies evaluated)"

    def close(self) -> None:
        """The envs belong to the caller."""

    def state_dict(self) -> dict[str, Any]:
        """The members (as an append-only log), the history, the per-iteration costs, the
        early-stopping curve and the fallbacks: everything the run continues from."""
        return {
            "log": [asdict(m) for m in self.members],
            "history": list(self.history),
            "costs": list(self.costs),
            "stop_curve": list(self.stop_curve),
            "stopped_at": self.stopped_at,
            "fallbacks": dict(self._fallbacks),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a run of the same starting policies and params; raises
        ValueError if it is not the starting policies (and seeds) plus whole iterations."""
        members = [Member(**m) for m in state["log"]]
        if len(members) < self.n_initial or (len(members) - self.n_initial) % self.k:
            raise ValueError(
                f"{len(members)} members are not the {self.n_initial} starting policies and seeds plus whole "
                f"iterations of {self.k}"
            )
        self.members, self.history = members, list(state["history"])
        self.costs, self.stop_curve = list(state.get("costs", [])), list(state.get("stop_curve", []))
        self.stopped_at, self._fallbacks = state.get("stopped_at"), dict(state.get("fallbacks", {}))
        self.actors = self.actors[: self.n_start] + [
            member_actor(m, self.meta).to(self.device) for m in members[self.n_start :]
        ]

    def record(self) -> dict[str, Any]:
        """What population.pt's meta says of the extensions that ran (EXTENSION_KEYS; {} when
        none did, so a paper run's meta is what it always was): with init interpolate, the
        children that fell back to the paper's warm-up ("init_fallbacks": reason -> count);
        with seed_interpolation, the seeds added or why none were ("seed_interpolation");
        with stop_patience, the iteration it stopped after, or None ("stopped_at")."""
        out: dict[str, Any] = {}
        if self.cfg.init == "interpolate":
            out["init_fallbacks"] = dict(self._fallbacks)
        if self.cfg.seed_interpolation:
            out["seed_interpolation"] = {"policies": len(self.seed_weights), "problem": self.seed_problem}
            if not mix_options(self.cfg).plain:
                out["seed_interpolation"]["mixing"] = mix_options(self.cfg).describe()
                if self.seed_mixing_fallback:
                    out["seed_interpolation"]["mixing_fallback"] = self.seed_mixing_fallback
        if self.cfg.stop_patience:
            out["stopped_at"] = self.stopped_at
        return out


def variant_config(cfg: ExtractParams, variant: str) -> ExtractParams:
    """The `extract` params as variant `variant` runs them: warmup_only is Algorithm 1 with
    epochs = 0 (regression onto the mean parent action only), its advantage-weighted keys
    (AWR_KEYS) and the hybrid extraction's and early stopping's (EXTENSION_KEYS: the ablation is
    the paper's) set to their defaults, so that nothing it records or fingerprints depends on
    keys it does not read; mapex and mapex_posthoc change nothing here (they differ in the
    critics they read)."""
    if variant != "warmup_only":
        return cfg
    fields = ExtractParams.model_fields
    return cfg.model_copy(update={k: fields[k].default for k in AWR_KEYS + EXTENSION_KEYS} | {"epochs": 0})
