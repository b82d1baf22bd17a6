"""MOPDERL phase 2: NSGA-II evolution of the merged PDERL populations beside their RL agents.

MOPDERL (the paper's baseline) first trains one PDERL run per objective (phase 1: our PDERL
specialists, pipeline/specialists/pderl.py), then merges the populations and evolves them towards a
Pareto front. This module is phase 2. State: a population of deterministic actors, each with
a fitness vector (mean undiscounted return of every objective), a mini buffer of states
(`StateRing`) and a type (the objective it descends from: a starting actor's specialist, a
child's crossover critic); one TD3 agent per objective (with secondary critics,
pipeline/specialists/td3.py), restored from its specialist; and the all-time archive of non-dominated
fitness vectors.

Start (`MopderlRun.initialize`, generation 0): every starting actor is evaluated; its
transitions fill its mini buffer and every RL agent's replay buffer; the archive is the
non-dominated set of their fitness.

One generation (`MopderlRun.step_generation`; the NSGA-II tools are pipeline/baselines/nsga2.py's):

1. Rank the population by NSGA-II: Pareto rank (`nondominated_ranks`), then crowding
   distance within its front (`crowding_distance`); `preference_positions` is the total order.
2. `children` distillation-crossover children: each from a size-`tournament_size` tournament
   (`tournament_pair`): the two best-placed distinct entrants not paired before this
   generation. The child starts as a copy of the better parent and is distilled on the
   latest states of both parents towards, per state, whichever parent action the primary
   critic (Q1) of the objective chosen by `crossover_critic` values more.
3. One child per RL agent: the RL actor distilled with the winner of one tournament
   (`tournament_winner`), on the latest states of the winner's mini buffer and of the RL
   replay buffer, judged by that agent's critic; the child starts as a copy of the RL actor.
4. Mutated clones: each individual of the population and each child of this generation gets,
   with probability `mutation_prob`, a clone proximally mutated on states of its mini
   buffer; each RL actor gets one mutated clone always (sensitivity states drawn from its
   replay buffer; its mini buffer: the buffer's latest states).
5. Every new individual is evaluated (`eval_episodes` deterministic episodes); its
   transitions go to its own mini buffer and to every RL agent's replay buffer. Survivors are
   not evaluated again: their fitness is the one they were first evaluated with.
6. The archive takes every new individual that no archived or new fitness dominates and drops
   what they dominate (`archive_update`).
7. NSGA-II survivor selection (`nsga2_select`) back to `population_size` over the population
   and the new individuals.
8. Each RL agent runs one exploration episode (its actor plus Gaussian noise) into its own
   buffer, then makes floor(rl_updates_per_frame x frames added to its buffer so far) minus
   the updates it has made, TD3 updates (so with 1.0: one update per frame it received).

Frames count every env step: the starting population's evaluation, every new individual's
evaluation and both exploration episodes; the run stops at the first generation boundary at
or past `total_frames`.

Choices where MOPDERL (paper, the authors' public code) is ambiguous, or where we differ:
- The RL agents are our TD3 (with secondary critics), not the public code's DDPG. They are
  restored from the specialists' artifacts (actor and target actor, critic ensemble and its
  target, replay buffer) with fresh Adam optimizers: the artifacts hold no optimizer state.
  Their hyperparameters are the td3 section's. TD3's start timesteps do not apply here (the
  buffers are full). Each is a `TD3Learner` (pipeline/specialists/td3_learner.py), as
  PDERL's agent: on CUDA its buffer lives on the GPU and its updates replay as CUDA graphs.
- The critic of a crossover (`crossover_critic`) follows the authors' code: when the parents'
  types differ, the worse-placed parent's type (the child starts from the better parent and
  is pulled towards the other one where that one's objective says so); when they share a
  type and differ in rank, that type; when they share type and rank, another objective
  (the other one with two objectives; drawn uniformly among the others with more). The child
  takes the critic's objective as its type. The critic compared is the agent's primary head 0
  (Q1), as in our PDERL.
- Tournaments: entrants drawn with replacement and ordered by (rank, crowding, then
  position in the population). The authors' code may pair the best entrant with itself (its
  pair loop starts at the diagonal); we always pair two distinct individuals, and as there
  each pair at most once per generation (until every pair has been used).
- Crowding distance is Deb's: boundary points of each objective infinite, interior points
  the sum over objectives of the neighbours' gap over the front's range (an objective with
  zero range adds nothing). Ties in (rank, crowding) go to the earlier individual in the
  population (survivors before this generation's new individuals), as do ties in sorting
  an objective. The authors' code gives boundaries 1e6 and breaks ties the other way.
- Starting actors are the specialists' population actors (not their "rl" actors, which are
  the RL agents) with empty mini buffers, evaluated before generation 1 as in the authors'
  code (those frames count towards the budget and towards generation 1's TD3 updates).
- The RL agents' test episodes of the authors' code (not stored, a logging metric) are not
  run. Every frame counts against one shared budget (the code keeps one counter per agent,
  each missing the other agent's exploration episode).
- Mini buffers hold states only, as in our PDERL; the child's mini buffer is the states it
  was distilled on.

Randomness comes from streams seeded by (seed, MOPDERL_TAG) (`mopderl_seeds`, and per agent
`agent_seeds`); env episode e is reset with a seed derived from its index. `MopderlRun
.state_dict` holds every piece of state (the archive's members aside, which the caller keeps),
so a run checkpointed after any generation and resumed ends bitwise as an uninterrupted one
on a CPU (same thread count and libraries).
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.baselines.nsga2 import (
    archive_update,
    nondominated_ranks,
    nsga2_scores,
    nsga2_select,
    preference_positions,
    tournament_pair,
    tournament_winner,
)
from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import StackedReplay
from pipeline.core.checkpoint import cpu_copy
from pipeline.core.drive import fmt_vec
from pipeline.core.envs import EnvSpec
from pipeline.core.finite import TrainingDiverged, check_finite
from pipeline.core.nets import Actor, CriticEnsemble, hidden_sizes_of
from pipeline.core.pareto import normalised_hypervolume
from pipeline.core.population import Member, actor_state
from pipeline.core.precision import resolve
from pipeline.core.seeding import derive_seeds, torch_generator
from pipeline.core.specialist import Slot
from pipeline.params.mopderl import MopderlParams
from pipeline.params.td3 import TD3Params
from pipeline.specialists.pderl import (
    EpisodeResult,
    StateRing,
    distillation_crossover,
    episode_seed,
    play_episode,
    proximal_mutation,
)
from pipeline.specialists.td3 import stack_td3
from pipeline.specialists.td3_learner import TD3Learner

MOPDERL_TAG = 0x4D4F5044  # "MOPD": separates MOPDERL's streams from every other use of a seed
STATE_FORMAT = "mapex.mopderl_state"
STATE_VERSION = 2  # 2: the RL agents are TD3Learners (stacked networks, device buffers)
_STREAMS = ("episodes", "evolution", "mutation", "noise")
_AGENT_STREAMS = ("rows", "smoothing", "cuda_rows")


def mopderl_seeds(seed: int) -> dict[str, int]:
    """Independent seeds of the run-wide random streams of MOPDERL run `seed`."""
    return dict(zip(_STREAMS, derive_seeds(seed, MOPDERL_TAG, n=len(_STREAMS))))


def agent_seeds(seed: int, objective: int) -> dict[str, int]:
    """Seeds of RL agent `objective`'s own streams (minibatch rows on a CPU, target smoothing
    noise, minibatch rows on CUDA)."""
    return dict(zip(_AGENT_STREAMS, derive_seeds(seed, MOPDERL_TAG, 1 + objective, n=len(_AGENT_STREAMS))))


def crossover_critic(
    better: int, worse: int, ranks: np.ndarray, kinds: Sequence[int], n_objectives: int, rng: np.random.Generator
) -> int:
    """The objective whose RL critic judges the crossover of `better` and `worse` (the rule of
    the authors' code, see the module docstring): the worse parent's type if the types
    differ; else their shared type if the ranks differ; else another objective (drawn
    uniformly from the others when there are more than one; no draw otherwise)."""
    kb, kw = int(kinds[better]), int(kinds[worse])
    if kb != kw:
        return kw
    if ranks[better] != ranks[worse]:
        return kb
    others = [k for k in range(n_objectives) if k != kb]
    if not others:
        return kb
    return others[0] if len(others) == 1 else others[int(rng.integers(len(others)))]


# ------------------------------------------------------------------------- individuals


class StartingActor(NamedTuple):
    """One starting policy: a population actor of specialist `objective` ("pop3", ...)."""

    objective: int
    name: str
    actor: Actor


class AgentInit(NamedTuple):
    """A phase-1 RL agent as its artifacts hold it (CPU modules, buffer rows oldest first)."""

    objective: int
    actor: Actor
    actor_target: Actor
    critic: CriticEnsemble
    critic_target: CriticEnsemble
    objectives: list[int]  # objectives the critic ensemble covers, in member order
    buffer: dict[str, np.ndarray]


def starts_from_slots(slots: Sequence[Slot], where: Path) -> tuple[list[StartingActor], list[AgentInit]]:
    """MOPDERL's phase-2 start from one seed's PDERL specialists (their slots under `where`):
    every population actor of every policy set (not the RL actors), and each slot's RL agent.
    Raises ArtifactError naming the file when the slots are not PDERL specialists'."""
    population = [StartingActor(p.objective, p.name, p.actor) for s in slots for p in s.starts if p.name != "rl"]
    if len(population) < 2:
        raise ArtifactError(
            f"{where}: {len(population)} population actor(s) in the policy sets; MOPDERL starts from "
            "PDERL specialists' populations (policies.pt of stage train_pderl)"
        )
    for s in slots:
        if s.actor_target is None:
            raise ArtifactError(
                f"{where / f'obj{s.objective}' / 'policy.pt'}: no 'actor_target': not an RL agent's policy "
                "(stage train_pderl writes one)"
            )
    agents = [
        AgentInit(
            s.objective,
            s.actor,
            s.actor_target,
            s.critic,
            s.critic_target,
            list(s.critics_meta["objectives"]),
            s.buffer,
        )
        for s in slots
    ]
    return population, agents


@dataclass
class Individual:
    uid: int  # unique over the run, in order of creation
    actor: Actor
    ring: StateRing
    kind: int  # objective it descends from (see the module docstring)
    parents: list[int]  # uids
    generation: int  # 0 for the starting actors
    name: str | None = None  # policy name of a starting actor
    fitness: np.ndarray | None = None  # (m,) mean returns once evaluated
    fitness_std: np.ndarray | None = None
    env_samples: int = 0  # run frames once it was evaluated


@dataclass
class RLAgent:
    objective: int
    learner: TD3Learner  # its TD3 networks, optimizers, replay buffer and update RNG streams
    added: int = 0  # transitions added to its buffer in phase 2
    next_episode: int = 0  # episode id its buffer gives the next episode it stores

    @property
    def buffer(self) -> StackedReplay:
        return self.learner.buffer

    @property
    def updates(self) -> int:
        """TD3 updates made in phase 2."""
        return self.learner.updates

    def q(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The agent's primary critic, head 0 (Q1): what its crossovers compare actions with."""
        return self.learner.q_primary(obs, action)


@dataclass
class GenerationRecord:
    generation: int  # 0: the starting population's evaluation
    frames: int  # run frames so far
    new_individuals: int
    entered: int  # new individuals that joined the archive
    archive_size: int
    front_size: int  # rank-0 individuals of the population after selection
    updates: list[int] = field(default_factory=list)  # TD3 updates so far, per agent
    rl_returns: list[list[float]] = field(default_factory=list)  # this generation's exploration episodes
    # hypervolume of the archive's training-time fitness scaled to [0, 1] by its own range (reference 0)
    archive_hv_norm: float = 0.0


# ---------------------------------------------------------------------------------- run


class MopderlRun:
    """The whole state of one MOPDERL phase-2 run and its generation loop.

    `members` is the run's output so far (pipeline.core.population.Member): the starting actors
    (ids 0..n-1, in the order given), then every new individual that entered the archive, in
    order of entry. It is a pipeline.core.drive.Run on `env` (the env its episodes run in):
    `start` (generation 0: `initialize`), then `step` (`step_generation`) until `done` (the
    frame budget spent); or `load_state_dict` a checkpoint instead of `start`.
    """

    def __init__(
        self,
        spec: EnvSpec,
        td3_cfg: TD3Params,
        cfg: MopderlParams,
        seed: int,
        starts: Sequence[StartingActor],
        agents: Sequence[AgentInit],
        device: torch.device | str = "cpu",
        env: gym.Env | None = None,
    ):
        if cfg.total_frames is None or cfg.eval_episodes is None:
            raise ValueError("MopderlParams must be resolved (total_frames, eval_episodes set) before a run")
        if len(starts) < 2:
            raise ValueError(f"MOPDERL needs at least two starting actors, got {len(starts)}")
        if sorted(a.objective for a in agents) != list(range(spec.n_objectives)):
            raise ValueError(
                f"one RL agent per objective 0..{spec.n_objectives - 1} needed, got {[a.objective for a in agents]}"
            )
        self.spec, self.td3_cfg, self.cfg, self.seed = spec, td3_cfg, cfg, seed
        self.device = torch.device(device)
        self.seeds = mopderl_seeds(seed)
        self.evo_rng = np.random.default_rng(self.seeds["evolution"])
        self.noise_rng = np.random.default_rng(self.seeds["noise"])
        self.mutation_gen = torch_generator(self.seeds["mutation"], "cpu")
        self.agents = [self._agent(a) for a in sorted(agents, key=lambda a: a.objective)]
        self.population: list[Individual] = []
        for uid, s in enumerate(starts):
            actor = copy.deepcopy(s.actor).to(self.device)
            self.population.append(Individual(uid, actor, self._ring(), s.objective, [], 0, name=s.name))
        self.next_uid = len(starts)
        self.n_starts = len(starts)
        self.archive: list[tuple[int, np.ndarray]] = []  # (uid, fitness) of the archived individuals
        self.members: list[Member] = []
        self.member_of: dict[int, int] = {}  # uid -> member id
        self.generation = -1  # 0 once initialized
        self.frames = 0
        self.episodes = 0
        self.history: list[GenerationRecord] = []
        self.env = env  # where `start` and `step` run their episodes (the caller's: it closes it)
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run

    def _ring(self) -> StateRing:
        return StateRing(self.cfg.mini_buffer_size, self.spec.obs_dim)

    def _agent(self, a: AgentInit) -> RLAgent:
        c, d = self.td3_cfg, self.device
        if a.objective not in a.objectives:
            raise ValueError(f"agent {a.objective}: its critics cover {a.objectives}, not its own objective")
        # The specialists' TD3 machinery with S = 1 (on CUDA: device buffer, CUDA graphs), with
        # fresh optimizers: the specialists' artifacts hold no optimizer state.
        state = stack_td3(
            c,
            [a.actor],
            [a.critic],
            [list(a.objectives)],
            [list(a.objectives).index(a.objective)],
            d,
            actor_targets=[a.actor_target],
            critic_targets=[a.critic_target],
        )
        seeds = agent_seeds(self.seed, a.objective)
        learner = TD3Learner(
            self.spec,
            c,
            state,
            np.random.default_rng(seeds["rows"]),
            seeds["smoothing"],
            seeds["cuda_rows"],
            d,
            resolve(self.cfg.precision, d, max(c.hidden_sizes)),  # mopderl.precision: the updates' arithmetic
        )
        if len(a.buffer["obs"]):
            learner.buffer.fill(a.buffer)
        next_episode = int(np.asarray(a.buffer["episode"])[-1]) + 1 if len(a.buffer["obs"]) else 0
        return RLAgent(a.objective, learner, next_episode=next_episode)

    # -- acting ---------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        """Whether the frame budget is spent (the last generation runs to its end)."""
        return self.frames >= self.cfg.total_frames

    @torch.no_grad()
    def run_episode(
        self, env: gym.Env, actor: Actor, ring: StateRing | None, agents: Sequence[RLAgent], noise: bool
    ) -> EpisodeResult:
        """One episode of `actor` (plus exploration noise if `noise`); its transitions go into
        each of `agents`' buffers (and its states into `ring`). Counts its frames."""
        ids = [ag.next_episode for ag in agents]

        def add(obs, a, reward, next_obs, terminated, truncated, step):
            for ag, ep in zip(agents, ids):
                ag.learner.add(obs, a, reward, next_obs, terminated, truncated, ep, step)

        result = play_episode(
            env,
            actor,
            episode_seed(self.seeds["episodes"], self.episodes),
            add,
            self.spec.n_objectives,
            self.device,
            ring,
            self.noise_rng if noise else None,
            self.td3_cfg.exploration_noise,
        )
        for ag in agents:
            ag.next_episode += 1
            ag.added += result.length
        self.episodes += 1
        self.frames += result.length
        return result

    def evaluate(
        self, env: gym.Env, ind: Individual, on_episode: Callable[[EpisodeResult], None] | None = None
    ) -> None:
        """Fitness of `ind`: mean (and std) return vector over `eval_episodes` deterministic
        episodes, whose transitions go to its mini buffer and every agent's buffer."""
        rets = []
        for _ in range(self.cfg.eval_episodes):
            ep = self.run_episode(env, ind.actor, ind.ring, self.agents, noise=False)
            rets.append(ep.returns)
            if on_episode is not None:
                on_episode(ep)
        r = np.stack(rets)
        ind.fitness, ind.fitness_std, ind.env_samples = r.mean(axis=0), r.std(axis=0), self.frames

    def train_agents(self) -> None:
        """Bring each agent to floor(rl_updates_per_frame x frames it received) updates."""
        for ag in self.agents:
            try:
                ag.learner.train(max(0, math.floor(self.cfg.rl_updates_per_frame * ag.added) - ag.updates))
            except TrainingDiverged as exc:
                raise exc.about(self.seed, ag.objective, f"generation {self.generation}")

    def check_agents(self) -> None:
        """Raise TrainingDiverged (pipeline.core.finite) if an RL agent's latest losses,
        networks, optimizer moments or replay buffer are not finite."""
        for ag in self.agents:
            try:
                ag.learner.check_finite(full=True)
            except TrainingDiverged as exc:
                raise exc.about(self.seed, ag.objective, f"generation {self.generation}")

    def check_offspring(self, new: Sequence[Individual]) -> None:
        """Raise TrainingDiverged if a weight of a new individual (a crossover child or a
        mutated clone) is not finite, before it is evaluated or archived."""
        named = [(f"a weight of new individual {ind.uid}", p) for ind in new for p in ind.actor.parameters()]
        check_finite(named, self.generation, "generation", seed=self.seed)

    # -- members and archive --------------------------------------------------------------

    def _member(self, ind: Individual) -> Member:
        start = ind.generation == 0
        return Member(
            origin="specialist" if start else "mopderl",
            objective=ind.kind if start else None,
            iteration=ind.generation,
            parents=[self.member_of[u] for u in ind.parents if u in self.member_of],
            target_weight=None,
            returns=[float(x) for x in ind.fitness],
            returns_std=[float(x) for x in ind.fitness_std],
            eval_episodes=self.cfg.eval_episodes,
            env_samples=ind.env_samples,
            hidden_sizes=hidden_sizes_of(ind.actor),
            actor=actor_state(ind.actor),
            policy_name=ind.name,
        )

    def _enter(self, ind: Individual) -> None:
        self.member_of[ind.uid] = len(self.members)
        self.members.append(self._member(ind))

    def _update_archive(self, new: list[Individual]) -> int:
        old = np.array([f for _, f in self.archive]).reshape(-1, self.spec.n_objectives)
        keep, enter = archive_update(old, np.stack([ind.fitness for ind in new]))
        self.archive = [entry for entry, k in zip(self.archive, keep) if k]
        for ind, e in zip(new, enter):
            if e:
                self.archive.append((ind.uid, ind.fitness.copy()))
                if ind.uid not in self.member_of:
                    self._enter(ind)
        return int(enter.sum())

    def _front_size(self) -> int:
        return int((nondominated_ranks(np.stack([ind.fitness for ind in self.population])) == 0).sum())

    def archive_returns(self) -> np.ndarray:
        return np.array([f for _, f in self.archive]).reshape(-1, self.spec.n_objectives)

    # -- the loop -------------------------------------------------------------------------

    def initialize(self, env: gym.Env, on_episode: Callable[[EpisodeResult], None] | None = None) -> GenerationRecord:
        """Generation 0: evaluate the starting actors; they all become members, the
        non-dominated ones form the archive."""
        if self.generation != -1:
            raise RuntimeError("initialize runs once, before any generation")
        for ind in self.population:
            self.evaluate(env, ind, on_episode)
        for ind in self.population:
            self._enter(ind)
        self._update_archive(self.population)
        self.generation = 0
        rec = GenerationRecord(
            0,
            self.frames,
            len(self.population),
            len(self.archive),
            len(self.archive),
            self._front_size(),
            [ag.updates for ag in self.agents],
            [],
            normalised_hypervolume(self.archive_returns()),
        )
        self.history.append(rec)
        return rec

    def _new(self, actor: Actor, ring: StateRing, kind: int, parents: list[int]) -> Individual:
        ind = Individual(self.next_uid, actor, ring, kind, parents, self.generation)
        self.next_uid += 1
        return ind

    def _mutated_clone(
        self, actor: Actor, ring: StateRing, states: np.ndarray, kind: int, parents: list[int]
    ) -> Individual:
        clone = copy.deepcopy(actor)
        clone.zero_grad(set_to_none=True)
        c = self.cfg
        proximal_mutation(
            clone,
            torch.as_tensor(states, device=self.device),
            c.mutation_std,
            self.mutation_gen,
            c.mutation_min_sensitivity,
        )
        return self._new(clone, ring, kind, parents)

    def make_offspring(self) -> list[Individual]:
        """Steps 1-4 of a generation: the crossover children, the RL children and the mutated
        clones, in that order (not yet evaluated). Advances the generation counter."""
        if self.generation < 0:
            raise RuntimeError("initialize the run first")
        self.generation += 1
        c, rng, pop = self.cfg, self.evo_rng, self.population
        fit = np.stack([ind.fitness for ind in pop])
        ranks, crowd = nsga2_scores(fit)
        pos = preference_positions(ranks, crowd)
        kinds = [ind.kind for ind in pop]
        new: list[Individual] = []
        used: set[tuple[int, int]] = set()
        for _ in range(c.children):
            better, worse = tournament_pair(pos, c.tournament_size, used, rng)
            k = crossover_critic(better, worse, ranks, kinds, self.spec.n_objectives, rng)
            pb, pw = pop[better], pop[worse]
            # MopderlParams carries distillation_crossover's crossover_* settings under PDERL's names
            child, states = distillation_crossover(pw.actor, pb.actor, pw.ring, pb.ring, self.agents[k].q, c, rng)  # type: ignore[arg-type]
            ring = self._ring()
            ring.extend(states)
            new.append(self._new(child, ring, k, [pb.uid, pw.uid]))
        for ag in self.agents:
            w = pop[tournament_winner(pos, c.tournament_size, rng)]
            rl_ring = StateRing(c.crossover_transitions, self.spec.obs_dim)
            rl_ring.extend(ag.buffer.latest(0, c.crossover_transitions))
            child, states = distillation_crossover(w.actor, ag.learner.actor(), w.ring, rl_ring, ag.q, c, rng)  # type: ignore[arg-type]
            child.zero_grad(set_to_none=True)
            ring = self._ring()
            ring.extend(states)
            new.append(self._new(child, ring, ag.objective, [w.uid]))
        for ind in pop + new:  # a snapshot: clones are not cloned again
            if rng.random() < c.mutation_prob:
                ring = ind.ring.copy()
                new.append(
                    self._mutated_clone(ind.actor, ring, ring.sample(c.mutation_states, rng), ind.kind, [ind.uid])
                )
        for ag in self.agents:
            b = ag.buffer
            rows = np.sort(rng.choice(b.size, size=min(c.mutation_states, b.size), replace=False))
            ring = self._ring()
            ring.extend(b.latest(0, c.mini_buffer_size))
            new.append(self._mutated_clone(ag.learner.actor(), ring, b.take(0, rows), ag.objective, []))
        self.check_offspring(new)
        return new

    def step_generation(
        self, env: gym.Env, on_episode: Callable[[EpisodeResult], None] | None = None
    ) -> GenerationRecord:
        """Run one generation (see the module docstring); returns its record."""
        new = self.make_offspring()
        for ind in new:
            self.evaluate(env, ind, on_episode)
        entered = self._update_archive(new)
        candidates = self.population + new
        keep = nsga2_select(np.stack([ind.fitness for ind in candidates]), self.cfg.population_size)
        self.population = [candidates[i] for i in keep]
        rl_returns = []
        for ag in self.agents:
            ep = self.run_episode(env, ag.learner.actor(), None, [ag], noise=True)
            rl_returns.append([float(x) for x in ep.returns])
            if on_episode is not None:
                on_episode(ep)
        self.train_agents()
        rec = GenerationRecord(
            self.generation,
            self.frames,
            len(new),
            entered,
            len(self.archive),
            self._front_size(),
            [ag.updates for ag in self.agents],
            rl_returns,
            normalised_hypervolume(self.archive_returns()),
        )
        self.history.append(rec)
        self.check_agents()  # so before every checkpoint and the members' export
        return rec

    # -- the verbs of pipeline.core.drive.Run ---------------------------------------------

    def _episode(self, ep: EpisodeResult) -> None:
        if self.on_progress is not None:
            self.on_progress()

    def start(self) -> None:
        """Generation 0 on `env` (`initialize`)."""
        self.initialize(self.env, self._episode)

    def step(self) -> GenerationRecord:
        """One generation on `env` (`step_generation`)."""
        return self.step_generation(self.env, self._episode)

    def finish(self) -> None:
        """Nothing follows the last generation: the members are the output."""

    def progress(self) -> tuple[int, str]:
        """Frames spent; the generation, the archive, its normalised hypervolume and each objective's best."""
        if self.generation < 1:
            return self.frames, ""
        rec, best = self.history[-1], self.archive_returns().max(axis=0)
        return self.frames, (
            f"gen {rec.generation} archive {rec.archive_size} HV(norm) {rec.archive_hv_norm:.6g} best {fmt_vec(best)}"
        )

    def checkpoint_due(self) -> bool:
        """Every mopderl.checkpoint_every generations, generation 0 (the start) included."""
        return self.generation % self.cfg.checkpoint_every == 0

    def where(self) -> str:
        return f"generation {self.generation}" + (" (the starting actors evaluated)" if self.generation == 0 else "")

    def close(self) -> None:
        """The env belongs to the caller."""

    # -- checkpoints ----------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything the run depends on from here, as CPU tensors and plain values; the members
        as an append-only "log" (pipeline.core.resume writes each entry once). On a CPU the
        agents' full replay buffers are not copied (see `buffer_state`): save the state before
        the next generation."""

        def ind_state(ind: Individual) -> dict[str, Any]:
            return {
                "uid": ind.uid,
                "actor": cpu_copy(ind.actor.state_dict()),
                "ring": ind.ring.state_dict(),
                "kind": ind.kind,
                "parents": list(ind.parents),
                "generation": ind.generation,
                "name": ind.name,
                "fitness": [float(x) for x in ind.fitness],
                "fitness_std": [float(x) for x in ind.fitness_std],
                "env_samples": ind.env_samples,
            }

        def agent_state(ag: RLAgent) -> dict[str, Any]:
            return {
                "objective": ag.objective,
                "learner": ag.learner.state_dict(),
                "added": ag.added,
                "next_episode": ag.next_episode,
            }

        return {
            "format": STATE_FORMAT,
            "format_version": STATE_VERSION,
            "seed": self.seed,
            "counters": {
                "generation": self.generation,
                "frames": self.frames,
                "episodes": self.episodes,
                "next_uid": self.next_uid,
            },
            "population": [ind_state(ind) for ind in self.population],
            "archive": [{"uid": u, "fitness": [float(x) for x in f]} for u, f in self.archive],
            "member_of": [[u, m] for u, m in self.member_of.items()],
            "n_members": len(self.members),
            "agents": [agent_state(ag) for ag in self.agents],
            "rng": {
                "evolution": copy.deepcopy(self.evo_rng.bit_generator.state),
                "noise": copy.deepcopy(self.noise_rng.bit_generator.state),
                "mutation": self.mutation_gen.get_state(),
            },
            "history": [asdict(r) for r in self.history],
            "log": [asdict(m) for m in self.members],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a run of the same spec, params and seed. Raises ValueError
        if it cannot be of this run."""
        if state.get("format") != STATE_FORMAT or state.get("format_version") != STATE_VERSION:
            raise ValueError(f"not a {STATE_FORMAT} v{STATE_VERSION} state")
        if state["seed"] != self.seed:
            raise ValueError(f"state of seed {state['seed']}; this run is seed {self.seed}")
        members = [Member(**m) for m in state["log"]]
        if state["n_members"] != len(members):
            raise ValueError(f"state counts {state['n_members']} members, {len(members)} given")
        if [a["objective"] for a in state["agents"]] != [ag.objective for ag in self.agents]:
            raise ValueError("state's RL agents do not match this run's")
        template = self.population[0].actor
        try:
            population = []
            for s in state["population"]:
                actor = copy.deepcopy(template)
                actor.load_state_dict(s["actor"])
                ring = self._ring()
                ring.load_state_dict(s["ring"])
                population.append(
                    Individual(
                        s["uid"],
                        actor,
                        ring,
                        s["kind"],
                        list(s["parents"]),
                        s["generation"],
                        s["name"],
                        np.array(s["fitness"], dtype=float),
                        np.array(s["fitness_std"], dtype=float),
                        s["env_samples"],
                    )
                )
            for ag, s in zip(self.agents, state["agents"]):
                ag.learner.load_state_dict(s["learner"])
                ag.added, ag.next_episode = s["added"], s["next_episode"]
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"state does not fit this run ({type(exc).__name__}: {exc})") from None
        self.population = population
        self.archive = [(a["uid"], np.array(a["fitness"], dtype=float)) for a in state["archive"]]
        self.member_of = {int(u): int(m) for u, m in state["member_of"]}
        self.members = list(members)
        self.evo_rng.bit_generator.state = state["rng"]["evolution"]
        self.noise_rng.bit_generator.state = state["rng"]["noise"]
        self.mutation_gen.set_state(state["rng"]["mutation"])
        c = state["counters"]
        self.generation, self.frames, self.episodes, self.next_uid = (
            c["generation"],
            c["frames"],
            c["episodes"],
            c["next_uid"],
        )
        self.history = [GenerationRecord(**r) for r in state["history"]]
