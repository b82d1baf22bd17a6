"""PDERL specialists: Proximal Distilled Evolutionary RL with our TD3 as the RL agent.

The paper trains its specialists with PDERL (one run per objective: the warm-up stage of
MOPDERL). A run keeps a population of deterministic actors and one TD3 agent (with
secondary critics, pipeline/specialists/td3.py) that learns from every transition anyone collects.
One generation:

1. Evaluate: every individual runs `eval_episodes` episodes with its deterministic actions;
   its fitness is the mean undiscounted return of the run's objective. Every transition goes
   into the RL agent's shared replay buffer, and the states into the individual's own ring
   ("mini buffer").
2. Evolve (`evolve`): elites stay unchanged; tournament selection picks survivors; the other
   slots get children by distillation crossover of survivor pairs; non-elites are mutated by
   proximal mutation with probability `mutation_prob`.
3. One exploration episode of the RL actor (plus Gaussian action noise) into the shared buffer.
4. As many TD3 updates as env frames were collected this generation (frames before TD3's
   `learning_starts` give none, so a run makes total_frames - learning_starts updates, as TD3
   would).
5. Every `rl_sync_period` generations the RL actor is copied over the worst individual of
   this generation's evaluation (never an elite), whose mini buffer is refilled with the
   latest states of the shared buffer.

Frames count every env step: evaluations, the RL episode and the final evaluation. Once the
budget is spent, a final evaluation (`finish`) scores every population actor and the RL actor
as they end, so the policy set's fitness describes the actors it holds.

Choices where PDERL (paper, public code) is ambiguous or differs from what we run:
- The RL agent is TD3 with the paper's TD3 table (not the public MOPDERL code's DDPG with
  small LayerNorm nets); the population actors have the RL actor's architecture.
- TD3's start timesteps gate the updates only; the RL episode always uses the actor plus
  noise (PDERL's population already explores with diverse random actors from the start).
- Distillation crossover compares the parents' actions with the RL agent's primary critic,
  head 0 (Q1): the head TD3's actor ascends, as PDERL compares with its critic's Q1. The
  child starts as a copy of the less fit parent, as PDERL's code does.
- Mini buffers hold states only: crossover, mutation and the RL sync read nothing else.
- Proximal mutation perturbs weight matrices only (biases untouched), as PDERL's code does.
- Survivors, elites and children are arranged slot by slot as in `evolve`'s docstring.

Randomness is drawn from streams seeded by (seed, objective, PDERL_TAG) (`pderl_seeds`); env
episode e is reset with a seed derived from its index alone. `PderlRun.state_dict` holds
every piece of state, RNG states included, so a run checkpointed after any generation and
resumed ends bitwise as an uninterrupted one on a CPU (same thread count and libraries).

The RL agent is a `TD3Learner`: the specialists' stacked TD3 path with one specialist, so on
CUDA its replay buffer lives on the GPU and a generation's updates replay as captured CUDA
graphs with no host sync but the finiteness check every 100 updates (td3.cuda_graphs). Earlier versions used the plain
`td3_update` with a numpy buffer. On a CPU the two gave bitwise-identical runs: a small run
hashed before and after, and the PDERL-vs-TD3 comparison of docs/results.md, re-run, reproduced
every figure. The tests check agreement up to float rounding only.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass
from itertools import combinations
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.checkpoint import cpu_copy
from pipeline.core.drive import run_to_end
from pipeline.core.envs import EnvSpec, make_env
from pipeline.core.finite import TrainingDiverged, check_finite
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.precision import resolve
from pipeline.core.seeding import derive_seeds, torch_generator
from pipeline.params.td3 import TD3Params
from pipeline.params.train_pderl import TrainPderlParams, n_elites
from pipeline.specialists.td3 import covered_objectives, stack_td3
from pipeline.specialists.td3_learner import TD3Learner

PDERL_TAG = 0x50444552  # "PDER": separates PDERL's streams from every other use of (seed, objective)
STATE_FORMAT = "mapex.pderl_state"
STATE_VERSION = 2  # 2: the RL agent is a TD3Learner (stacked networks, device buffer)
_STREAMS = ("torch_init", "episodes", "evolution", "rows", "noise", "smoothing", "mutation", "cuda_rows")

QFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (obs (B, o), action (B, a)) -> (B,)


def pderl_seeds(seed: int, objective: int) -> dict[str, int]:
    """Independent seeds of every random stream of PDERL run (seed, objective)."""
    return dict(zip(_STREAMS, derive_seeds(seed, objective, PDERL_TAG, n=len(_STREAMS))))


def episode_seed(base: int, episode: int) -> int:
    """Env reset seed of the run's episode number `episode` (counted over all its episodes)."""
    return derive_seeds(base, episode, n=1)[0]


def play_episode(
    env: gym.Env,
    actor: Actor,
    reset_seed: int,
    add: Callable[..., None],
    n_objectives: int,
    device: torch.device | str,
    ring: "StateRing | None" = None,
    noise_rng: np.random.Generator | None = None,
    noise_std: float = 0.0,
) -> "EpisodeResult":
    """One episode of `actor` from `env.reset(seed=reset_seed)`: each transition goes to
    `add(obs, action, reward, next_obs, terminated, truncated, step)` and each state into `ring`;
    with `noise_rng`, Gaussian noise of `noise_std` times the action scale is added to every
    action, clipped to the bounds (TD3's exploration noise). The one episode loop of PDERL and
    MOPDERL (whose `add` feeds several agents' buffers)."""
    obs, _ = env.reset(seed=reset_seed)
    obs = np.asarray(obs, np.float32)
    scale = actor.scale.cpu().numpy()
    low, high = (actor.centre - actor.scale).cpu().numpy(), (actor.centre + actor.scale).cpu().numpy()
    returns = np.zeros(n_objectives)
    step = 0
    while True:
        a = actor(torch.as_tensor(obs, device=device).unsqueeze(0))[0].cpu().numpy()
        if noise_rng is not None:
            a = a + noise_rng.normal(0.0, noise_std, size=a.shape).astype(np.float32) * scale
            a = np.clip(a, low, high).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(a)
        next_obs = np.asarray(next_obs, np.float32)
        add(obs, a, reward, next_obs, bool(terminated), bool(truncated), step)
        if ring is not None:
            ring.add(obs)
        returns += reward
        step += 1
        obs = next_obs
        if terminated or truncated:
            break
    return EpisodeResult(step, returns)


# ----------------------------------------------------------------------------- mini buffer


class StateRing:
    """An individual's mini buffer: a ring of the latest `capacity` states it visited."""

    def __init__(self, capacity: int, obs_dim: int):
        self.data = np.zeros((capacity, obs_dim), np.float32)
        self.ptr = 0
        self.size = 0

    @property
    def capacity(self) -> int:
        return self.data.shape[0]

    def add(self, obs: np.ndarray) -> None:
        self.data[self.ptr] = obs
        self.ptr = (self.ptr + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def extend(self, rows: np.ndarray) -> None:
        """Append rows (oldest first); only the last `capacity` of them can stay."""
        rows = np.asarray(rows, np.float32)[-self.capacity :]
        n = len(rows)
        first = min(n, self.capacity - self.ptr)
        self.data[self.ptr : self.ptr + first] = rows[:first]
        self.data[: n - first] = rows[first:]
        self.ptr = (self.ptr + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def clear(self) -> None:
        self.ptr = 0
        self.size = 0

    def chronological(self) -> np.ndarray:
        if self.size < self.capacity:
            return self.data[: self.size]
        return np.concatenate([self.data[self.ptr :], self.data[: self.ptr]])

    def latest(self, n: int) -> np.ndarray:
        """The last min(n, size) states, oldest first."""
        n = min(n, self.size)
        idx = (self.ptr - n + np.arange(n)) % self.capacity
        return self.data[idx]

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """min(n, size) distinct stored states, drawn uniformly (positions in the stored array)."""
        idx = rng.choice(self.size, size=min(n, self.size), replace=False)
        return self.data[np.sort(idx)]

    def copy(self) -> "StateRing":
        out = StateRing.__new__(StateRing)
        out.data, out.ptr, out.size = self.data.copy(), self.ptr, self.size
        return out

    def state_dict(self) -> dict[str, Any]:
        # rows 0..size-1 of the array (the whole ring once full): exactly the stored state
        return {"rows": torch.from_numpy(self.data[: self.size].copy()), "ptr": self.ptr, "capacity": self.capacity}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        rows = state["rows"].numpy()
        if (
            state["capacity"] != self.capacity
            or rows.ndim != 2
            or rows.shape[1] != self.data.shape[1]
            or len(rows) > self.capacity
        ):
            raise ValueError(
                f"mini buffer state of shape {tuple(rows.shape)} (capacity {state['capacity']}) does not fit {self.data.shape}"
            )
        self.data[: len(rows)] = rows
        self.size, self.ptr = len(rows), int(state["ptr"])


# ------------------------------------------------------------------------ genetic operators


def action_sensitivity(actor: Actor, states: torch.Tensor) -> list[torch.Tensor]:
    """Per weight of each weight matrix of `actor` (parameter order): sqrt(sum_j g_j^2), where
    g_j is the gradient of action dimension j summed over `states` (N, o) with respect to it."""
    weights = [p for p in actor.parameters() if p.dim() == 2]
    if len(states) == 0:
        return [torch.zeros_like(w) for w in weights]
    with torch.enable_grad():
        out = actor(states)  # (N, a)
        sq = [torch.zeros_like(w) for w in weights]
        n_act = out.shape[1]
        for j in range(n_act):
            grads = torch.autograd.grad(out[:, j].sum(), weights, retain_graph=j < n_act - 1)
            for s, g in zip(sq, grads):
                s.add_(g * g)
    return [s.sqrt_() for s in sq]


@torch.no_grad()
def proximal_mutation(
    actor: Actor, states: torch.Tensor, std: float, generator: torch.Generator, min_sensitivity: float = 0.01
) -> list[torch.Tensor]:
    """Proximal (safe) mutation in place: w += N(0, std^2) / sensitivity(w), per weight.

    Only weight matrices are perturbed (biases are not). The sensitivity is
    `action_sensitivity` on `states`; exact zeros (a weight no state moves, e.g. into a dead
    ReLU) divide by 1, anything else below `min_sensitivity` by `min_sensitivity`. The noise
    is drawn on the CPU from `generator`, one `torch.randn(w.shape)` per weight matrix in
    parameter order (so it is the same on every device). Returns the added deltas.
    """
    weights = [p for p in actor.parameters() if p.dim() == 2]
    sens = action_sensitivity(actor, states)
    deltas = []
    for w, s in zip(weights, sens):
        s = torch.where(s == 0, torch.ones_like(s), s.clamp_min(min_sensitivity))
        noise = torch.randn(w.shape, generator=generator, dtype=w.dtype).to(w.device)
        delta = noise * std / s
        w.add_(delta)
        deltas.append(delta)
    return deltas


def distillation_crossover(
    parent_a: Actor,
    parent_b: Actor,
    buf_a: StateRing,
    buf_b: StateRing,
    critic: QFunction,
    cfg: TrainPderlParams,
    rng: np.random.Generator,
) -> tuple[Actor, np.ndarray]:
    """A child that acts, at each state, like whichever parent `critic` values higher there.

    The child starts as a copy of `parent_b` (PDERL passes the less fit parent here) and is
    trained on the latest `cfg.crossover_transitions` states of each parent's mini buffer,
    for `cfg.crossover_epochs` shuffled passes (minibatches of `cfg.crossover_batch_size`, a
    last partial one dropped unless it is the only one; Adam, `cfg.crossover_lr`). Target at
    state s: a_A = parent_a(s) where critic(s, a_A) >= critic(s, a_B), else a_B. Loss, with
    actions measured in half-ranges of the action bounds: the squared error summed over action
    dims, mean over rows, plus `cfg.crossover_action_penalty` * mean(a^2).

    Returns the child (on the parents' device) and the states it was distilled on (A's, then
    B's, oldest first), which become its mini buffer.
    """
    states = np.concatenate([buf_a.latest(cfg.crossover_transitions), buf_b.latest(cfg.crossover_transitions)])
    child = copy.deepcopy(parent_b)
    if len(states) == 0:
        return child, states
    device = parent_a.scale.device
    obs = torch.as_tensor(states, device=device)
    with torch.no_grad():
        a_a, a_b = parent_a(obs), parent_b(obs)
        better_a = critic(obs, a_a) >= critic(obs, a_b)
        target = torch.where(better_a.unsqueeze(-1), a_a, a_b)
    child.requires_grad_(True)
    opt = torch.optim.Adam(child.parameters(), lr=cfg.crossover_lr)
    scale, centre = child.scale, child.centre
    n = len(states)
    bs = min(cfg.crossover_batch_size, n)
    for _ in range(cfg.crossover_epochs):
        order = torch.from_numpy(rng.permutation(n)).to(device)
        for start in range(0, n - bs + 1, bs):
            idx = order[start : start + bs]
            pred = child(obs[idx])
            err = (((pred - target[idx]) / scale) ** 2).sum(dim=1).mean()
            loss = err + cfg.crossover_action_penalty * (((pred - centre) / scale) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    child.zero_grad(set_to_none=True)
    return child, states


def tournament(ranked: Sequence[int], n: int, size: int, rng: np.random.Generator) -> list[int]:
    """Winners of `n` tournaments: each draws `size` entrants (with replacement) from `ranked`
    (slot indices, best first) and the best-ranked entrant wins. Unique, in order of first win."""
    winners = [int(ranked[int(rng.integers(0, len(ranked), size=size).min())]) for _ in range(n)]
    return list(dict.fromkeys(winners))


# ------------------------------------------------------------------------------ population


@dataclass
class Individual:
    actor: Actor
    ring: StateRing
    fitness: float | None = None  # mean return when last evaluated; None once changed since


@dataclass
class EvolutionReport:
    elites: list[int]  # slots kept unchanged
    selected: list[int]  # tournament winners (slots, unique)
    copies: dict[int, int]  # slot -> elite slot it received a (mutable) copy of
    children: dict[int, tuple[int, int]]  # slot -> (fitter parent, other parent) slots
    mutated: list[int]


def evolve(
    population: list[Individual],
    critic: QFunction,
    cfg: TrainPderlParams,
    rng: np.random.Generator,
    generator: torch.Generator,
) -> EvolutionReport:
    """One PDERL evolution step of `population` (all evaluated), in place.

    - Elites: the floor(elite_fraction * P) (at least 1) fittest keep their slots, unchanged.
    - Selection: P - n_elites tournaments of `tournament_size` over the whole population;
      the unique winners survive in their slots. An elite that also wins gets a second,
      mutable copy in a free slot (PDERL keeps an untouched elite clone beside it).
    - The remaining free slots (in slot order) get distillation-crossover children of
      survivor pairs (elites and winners), pairs taken in order of decreasing summed fitness
      (cycling if there are more free slots than pairs); the fitter parent is parent_a.
      With a single survivor, a child is a plain copy of it.
    - Every slot but the elites' is mutated (`proximal_mutation` on up to `mutation_states`
      states of its own mini buffer) with probability `mutation_prob`, in slot order.
    A child's mini buffer is the states it was distilled on; a copy's is a copy of its
    original's. Changed individuals lose their fitness (None) until evaluated again.
    """
    p = len(population)
    fitness = np.array([ind.fitness for ind in population], dtype=np.float64)
    if np.isnan(fitness).any():
        raise ValueError("evolve needs every individual evaluated")
    ranked = [int(i) for i in np.argsort(-fitness, kind="stable")]  # best first, ties by slot
    elites = ranked[: n_elites(cfg.elite_fraction, p)]
    selected = tournament(ranked, p - len(elites), cfg.tournament_size, rng)
    survivors = elites + [s for s in selected if s not in elites]
    free = [i for i in range(p) if i not in survivors]

    copies = {free.pop(0): e for e in elites if e in selected}
    pairs = sorted(combinations(survivors, 2), key=lambda ab: -(fitness[ab[0]] + fitness[ab[1]]))
    new: dict[int, Individual] = {
        slot: Individual(copy.deepcopy(population[e].actor), population[e].ring.copy()) for slot, e in copies.items()
    }
    children: dict[int, tuple[int, int]] = {}
    for j, slot in enumerate(free):
        if not pairs:
            s = survivors[0]
            new[slot] = Individual(copy.deepcopy(population[s].actor), population[s].ring.copy())
            children[slot] = (s, s)
            continue
        a, b = pairs[j % len(pairs)]
        if fitness[b] > fitness[a]:
            a, b = b, a
        child, states = distillation_crossover(
            population[a].actor, population[b].actor, population[a].ring, population[b].ring, critic, cfg, rng
        )
        ring = StateRing(population[slot].ring.capacity, population[slot].ring.data.shape[1])
        ring.extend(states)
        new[slot] = Individual(child, ring)
        children[slot] = (a, b)
    for slot, ind in new.items():  # only after every child is made: parents are never overwritten
        population[slot] = ind

    mutated = []
    for slot in range(p):
        if slot in elites:
            continue
        if rng.random() < cfg.mutation_prob:
            ind = population[slot]
            device = ind.actor.scale.device
            states = torch.as_tensor(ind.ring.sample(cfg.mutation_states, rng), device=device)
            proximal_mutation(ind.actor, states, cfg.mutation_std, generator, cfg.mutation_min_sensitivity)
            ind.fitness = None
            mutated.append(slot)
    return EvolutionReport(elites, selected, copies, children, mutated)


# ------------------------------------------------------------------------------------- run


@dataclass
class GenerationRecord:
    generation: int  # 1-based
    frames: int  # env frames so far, this generation included
    updates: int  # TD3 updates so far
    best: float  # best fitness of this generation's evaluation
    mean: float  # mean fitness of this generation's evaluation
    rl_fitness: float  # return (run's objective) of this generation's noisy RL episode
    crossovers: int
    mutations: int
    rl_slot: int | None  # slot the RL actor was copied into, if synced this generation


@dataclass
class EpisodeResult:
    length: int
    returns: np.ndarray  # (n_objectives,) undiscounted


@dataclass
class PderlResult:
    """What a finished PDERL run leaves behind (CPU modules, buffer rows oldest first)."""

    seed: int
    objective: int
    actors: list[Actor]  # the population, slot order
    fitness: list[float]  # their final-evaluation fitness
    rl_fitness: float  # final-evaluation fitness of the RL actor
    actor: Actor  # RL actor
    actor_target: Actor
    critic: CriticEnsemble
    critic_target: CriticEnsemble
    objectives: list[int]
    buffer: dict[str, np.ndarray]
    history: list[GenerationRecord]
    frames: int
    updates: int


class PderlRun:
    """The whole state of one PDERL run (seed, objective) and its generation loop: a
    pipeline.core.drive.Run on `env` (the env its episodes run in; default: one of its own,
    closed by `close`), one generation a `step` until `done`, then `finish` (the final
    evaluation) and `result`."""

    def __init__(
        self,
        spec: EnvSpec,
        td3_cfg: TD3Params,
        cfg: TrainPderlParams,
        objective: int,
        seed: int,
        device: torch.device | str = "cpu",
        env: gym.Env | None = None,
    ):
        if not 0 <= objective < spec.n_objectives:
            raise ValueError(
                f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives"
            )
        self.spec, self.td3_cfg, self.cfg = spec, td3_cfg, cfg
        self.objective, self.seed = objective, seed
        self.device = torch.device(device)
        self.seeds = pderl_seeds(seed, objective)
        # Networks are initialised on the CPU from their own seed (the same on every device),
        # without disturbing the caller's global torch RNG.
        objectives, primary = covered_objectives(objective, spec.n_objectives, td3_cfg.secondary_critics)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seeds["torch_init"])
            rl_actor = self._new_actor()
            rl_critic = CriticEnsemble(spec.obs_dim, spec.act_dim, td3_cfg.hidden_sizes, 2 * len(objectives))
            actors = [self._new_actor() for _ in range(cfg.population_size)]
        self.population = [Individual(a.to(self.device), StateRing(cfg.mini_buffer_size, spec.obs_dim)) for a in actors]
        # The RL agent: the specialists' TD3 machinery with S = 1 (so on CUDA its buffer lives on
        # the GPU and its updates replay as CUDA graphs), holding the shared replay buffer.
        self.agent = TD3Learner(
            spec,
            td3_cfg,
            stack_td3(td3_cfg, [rl_actor], [rl_critic], [objectives], [primary], self.device),
            np.random.default_rng(self.seeds["rows"]),
            self.seeds["smoothing"],
            self.seeds["cuda_rows"],
            self.device,
            # its updates' arithmetic (train_pderl.precision); the population's episodes stay fp32
            resolve(cfg.precision, self.device, max(td3_cfg.hidden_sizes)),
        )
        self.buffer = self.agent.buffer
        self.evo_rng = np.random.default_rng(self.seeds["evolution"])
        self.noise_rng = np.random.default_rng(self.seeds["noise"])
        self.mutation_gen = torch_generator(self.seeds["mutation"], "cpu")
        self.generation = 0
        self.frames = 0
        self.episodes = 0
        self.history: list[GenerationRecord] = []
        self.own_env = env is None
        self.env = make_env(spec.env_id, spec.max_episode_steps, spec.reward_terms) if env is None else env
        self.rl_fitness: float | None = None  # the RL actor's final-evaluation fitness, once finished
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run

    @property
    def updates(self) -> int:
        """TD3 updates made so far."""
        return self.agent.updates

    def _new_actor(self) -> Actor:
        s = self.spec
        return Actor(s.obs_dim, s.act_dim, self.td3_cfg.hidden_sizes, s.action_low, s.action_high)

    # -- acting ---------------------------------------------------------------------------

    def q_primary(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The RL agent's primary critic, head 0 (Q1): what crossover compares parents with."""
        return self.agent.q_primary(obs, action)

    @torch.no_grad()
    def run_episode(self, env: gym.Env, actor: Actor, noise: bool, ring: StateRing | None) -> EpisodeResult:
        """One episode of `actor` (plus exploration noise if `noise`) into the shared buffer
        (and its states into `ring`); counts its frames."""
        episode = self.episodes

        def add(obs, a, reward, next_obs, terminated, truncated, step):
            self.agent.add(obs, a, reward, next_obs, terminated, truncated, episode, step)

        result = play_episode(
            env,
            actor,
            episode_seed(self.seeds["episodes"], episode),
            add,
            self.spec.n_objectives,
            self.device,
            ring,
            self.noise_rng if noise else None,
            self.td3_cfg.exploration_noise,
        )
        self.episodes += 1
        self.frames += result.length
        return result

    def evaluate(self, env: gym.Env, actor: Actor, ring: StateRing | None, on_episode=None) -> float:
        """Mean return of the run's objective over `eval_episodes` deterministic episodes."""
        total = 0.0
        for _ in range(self.cfg.eval_episodes):
            ep = self.run_episode(env, actor, noise=False, ring=ring)
            total += float(ep.returns[self.objective])
            if on_episode is not None:
                on_episode(ep)
        return total / self.cfg.eval_episodes

    # -- the loop -------------------------------------------------------------------------

    @property
    def done(self) -> bool:
        """Whether the frame budget is spent (the last generation runs to its end)."""
        return self.frames >= self.cfg.total_frames

    def step_generation(
        self, env: gym.Env, on_episode: Callable[[EpisodeResult], None] | None = None
    ) -> GenerationRecord:
        """Run one generation (see the module docstring); returns its record."""
        start = self.frames
        for ind in self.population:
            ind.fitness = self.evaluate(env, ind.actor, ind.ring, on_episode)
        fitness = np.array([ind.fitness for ind in self.population])
        report = evolve(self.population, self.q_primary, self.cfg, self.evo_rng, self.mutation_gen)
        rl = self.run_episode(env, self.agent.actor(), noise=True, ring=None)
        if on_episode is not None:
            on_episode(rl)
        try:
            self.agent.train(max(0, self.frames - max(start, self.td3_cfg.learning_starts)))
        except TrainingDiverged as exc:
            raise exc.about(self.seed, self.objective, f"generation {self.generation + 1}")
        self.generation += 1
        rl_slot = None
        if self.generation % self.cfg.rl_sync_period == 0:
            rl_slot = self.sync_rl(fitness, report.elites)
        rec = GenerationRecord(
            generation=self.generation,
            frames=self.frames,
            updates=self.updates,
            best=float(fitness.max()),
            mean=float(fitness.mean()),
            rl_fitness=float(rl.returns[self.objective]),
            crossovers=sum(1 for a, b in report.children.values() if a != b),
            mutations=len(report.mutated),
            rl_slot=rl_slot,
        )
        self.history.append(rec)
        self.check_finite()
        return rec

    def check_finite(self) -> None:
        """Raise TrainingDiverged (pipeline.core.finite) if the RL agent's latest losses,
        networks, optimizer moments or replay buffer, or a weight of a population actor (the
        crossover and mutation outputs among them) is not finite. Run after every generation,
        so before every checkpoint, and before the result."""
        try:
            self.agent.check_finite(full=True)
        except TrainingDiverged as exc:
            raise exc.about(self.seed, self.objective, f"generation {self.generation}")
        named = [
            (f"a weight of population actor {i}", p)
            for i, ind in enumerate(self.population)
            for p in ind.actor.parameters()
        ]
        check_finite(named, self.generation, "generation", seed=self.seed, objective=self.objective)

    def sync_rl(self, fitness: np.ndarray, elites: list[int]) -> int:
        """Copy the RL actor over the worst non-elite slot of `fitness`; refill its mini buffer
        with the latest states of the shared buffer. Returns the slot."""
        slots = [i for i in range(len(fitness)) if i not in elites]
        worst = min(slots, key=lambda i: (fitness[i], i))
        ind = self.population[worst]
        ind.actor.load_state_dict(self.agent.actor().state_dict())
        ind.ring.clear()
        ind.ring.extend(self.buffer.latest(0, ind.ring.capacity))
        ind.fitness = None
        return worst

    def evaluate_final(self, env: gym.Env, on_episode: Callable[[EpisodeResult], None] | None = None) -> float:
        """Final evaluation of every population actor and of the RL actor, as they end (their
        frames count too). Returns the RL actor's fitness."""
        for ind in self.population:
            ind.fitness = self.evaluate(env, ind.actor, ind.ring, on_episode)
        return self.evaluate(env, self.agent.actor(), None, on_episode)

    # -- the verbs of pipeline.core.drive.Run ---------------------------------------------

    def _episode(self, ep: EpisodeResult) -> None:
        if self.on_progress is not None:
            self.on_progress()

    def start(self) -> None:
        """Nothing before the first generation (it evaluates the population first)."""

    def step(self) -> GenerationRecord:
        """One generation on `env` (`step_generation`)."""
        return self.step_generation(self.env, self._episode)

    def finish(self) -> None:
        """The final evaluation (`evaluate_final`), then `check_finite`: the result holds no
        diverged network."""
        self.rl_fitness = self.evaluate_final(self.env, self._episode)
        self.check_finite()

    def progress(self) -> tuple[int, str]:
        """Frames spent; the generation's best and mean fitness and its RL episode's return."""
        if not self.history:
            return self.frames, ""
        rec = self.history[-1]
        return self.frames, f"gen {rec.generation} best {rec.best:.1f} mean {rec.mean:.1f} rl {rec.rl_fitness:.1f}"

    def checkpoint_due(self) -> bool:
        """Every train_pderl.checkpoint_every generations (not before the first)."""
        return self.generation > 0 and self.generation % self.cfg.checkpoint_every == 0

    def where(self) -> str:
        return f"generation {self.generation}"

    def close(self) -> None:
        """Close the env if the run made it."""
        if self.own_env:
            self.env.close()

    def result(self) -> PderlResult:
        """The finished run's networks, population, buffer and history (after `finish`)."""
        if self.rl_fitness is None:
            raise RuntimeError("finish the run first")
        rl_fitness = self.rl_fitness
        actor, actor_target, critic, critic_target = self.agent.networks()
        return PderlResult(
            seed=self.seed,
            objective=self.objective,
            actors=[copy.deepcopy(ind.actor).cpu() for ind in self.population],
            fitness=[ind.fitness for ind in self.population],
            rl_fitness=rl_fitness,
            actor=actor,
            actor_target=actor_target,
            critic=critic,
            critic_target=critic_target,
            objectives=list(self.agent.objectives),
            buffer=self.buffer.chronological(0),
            history=list(self.history),
            frames=self.frames,
            updates=self.updates,
        )

    # -- checkpoints ----------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything the run depends on from here, as CPU tensors and plain Python values. On
        a CPU a full replay buffer is not copied (see `buffer_state`): save the state before
        the next generation."""
        return {
            "format": STATE_FORMAT,
            "format_version": STATE_VERSION,
            "seed": self.seed,
            "objective": self.objective,
            "counters": {"generation": self.generation, "frames": self.frames, "episodes": self.episodes},
            "history": [asdict(r) for r in self.history],
            "td3": self.agent.state_dict(),
            "population": [
                {"actor": cpu_copy(ind.actor.state_dict()), "ring": ind.ring.state_dict(), "fitness": ind.fitness}
                for ind in self.population
            ],
            "rng": {
                "evolution": copy.deepcopy(self.evo_rng.bit_generator.state),
                "noise": copy.deepcopy(self.noise_rng.bit_generator.state),
                "mutation": self.mutation_gen.get_state(),
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a run with the same spec, params, seed and objective.

        Raises ValueError if it cannot be of this run (format, seed, objective, sizes, shapes).
        """
        if state.get("format") != STATE_FORMAT or state.get("format_version") != STATE_VERSION:
            raise ValueError(f"not a {STATE_FORMAT} v{STATE_VERSION} state")
        if (state["seed"], state["objective"]) != (self.seed, self.objective):
            raise ValueError(
                f"state of seed {state['seed']}, objective {state['objective']}; this run is seed {self.seed}, objective {self.objective}"
            )
        if len(state["population"]) != len(self.population):
            raise ValueError(f"state holds {len(state['population'])} individuals, the run {len(self.population)}")
        try:
            self.agent.load_state_dict(state["td3"])
            for ind, saved in zip(self.population, state["population"]):
                ind.actor.load_state_dict(saved["actor"])
                ind.ring.load_state_dict(saved["ring"])
                ind.fitness = saved["fitness"]
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            raise ValueError(f"state does not fit this run ({type(exc).__name__}: {exc})") from None
        self.evo_rng.bit_generator.state = state["rng"]["evolution"]
        self.noise_rng.bit_generator.state = state["rng"]["noise"]
        self.mutation_gen.set_state(state["rng"]["mutation"])
        c = state["counters"]
        self.generation, self.frames, self.episodes = c["generation"], c["frames"], c["episodes"]
        self.history = [GenerationRecord(**r) for r in state["history"]]


def train_pderl(
    env: gym.Env,
    spec: EnvSpec,
    td3_cfg: TD3Params,
    cfg: TrainPderlParams,
    objective: int,
    seed: int,
    device: torch.device | str = "cpu",
    state: dict[str, Any] | None = None,
    on_generation: Callable[[PderlRun, GenerationRecord], None] | None = None,
) -> PderlResult:
    """Run PDERL for objective `objective` on `env` until `cfg.total_frames` frames, then
    evaluate the final actors; resume from `state` (a `PderlRun.state_dict()`) if given
    (ValueError if it does not fit). No checkpoints, no progress: the stage drives its runs
    with pipeline.core.drive.

    `on_generation(run, record)` is called after every generation (an exception raised in
    it stops the run). Raises TrainingDiverged when a generation ends with a loss or weight
    that is not finite (`PderlRun.check_finite`)."""
    run = PderlRun(spec, td3_cfg, cfg, objective, seed, device, env)
    if state is not None:
        run.load_state_dict(state)
    hooks = [] if on_generation is None else [lambda run: on_generation(run, run.history[-1])]
    return run_to_end(run, hooks, fresh=state is None).result()
