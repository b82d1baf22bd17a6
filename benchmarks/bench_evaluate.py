"""The evaluate stage with its members in 1 and in P worker processes (`evaluate.processes`): wall
and CPU seconds of the whole `mapex evaluate` command, and a check that every process count wrote
the same bytes.

    python benchmarks/bench_evaluate.py                       # the quickstart's shape: 14 members, 10 episodes
    python benchmarks/bench_evaluate.py --processes 1 2 --rounds 3 --population data/fronts/mapex_td3/seed0/population.pt

Without --population it writes a population of the quickstart's shape: 2 specialists and 12
children, 64-64 actors with random weights, mo-halfcheetah-v5 (every episode runs its 750 steps
whatever the weights, so the episodes cost what a trained population's cost). Each round runs
the command once per process count, alternately; the table gives the median of the rounds.
"CPU s" is the command's user + system time with its workers (`resource.RUSAGE_CHILDREN`);
"episodes, CPU s" is the in-process time of the members' episodes alone (the stage's own loop,
timed here by `time.process_time`), so CPU s minus it is what the command pays besides
(interpreter, imports, env construction, the population's load, the writes). Timings only:
nothing here is asserted.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from speed_floor import load  # noqa: E402

from pipeline.core.envs import make_env  # noqa: E402
from pipeline.core.nets import Actor  # noqa: E402
from pipeline.core.population import Member, actor_state, load_population, member_actor, save_population  # noqa: E402
from pipeline.core.provenance import cpu_model  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy  # noqa: E402

ENV_ID, CAP, OBS, ACT = "mo-halfcheetah-v5", 750, 17, 6
META_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives", "action_low", "action_high", "seed", "method")


def write_population(path: Path, children: int, hidden: list[int]) -> None:
    """2 specialists and `children` children of random weights, seed 0."""
    low, high = [-1.0] * ACT, [1.0] * ACT
    members = []
    for i in range(2 + children):
        torch.manual_seed(i)
        specialist = i < 2
        members.append(
            Member(
                origin="specialist" if specialist else "child",
                objective=i if specialist else None,
                iteration=0 if specialist else i - 1,
                parents=[] if specialist else [0, 1],
                target_weight=None if specialist else [0.6, 0.8],
                returns=[0.0, 0.0],
                returns_std=[0.0, 0.0],
                eval_episodes=5,
                env_samples=3750 * (i + 1),
                hidden_sizes=hidden,
                actor=actor_state(Actor(OBS, ACT, hidden, low, high)),
                policy_name="policy" if specialist else None,
            )
        )
    meta = dict(
        env_id=ENV_ID, obs_dim=OBS, act_dim=ACT, n_objectives=2, action_low=low, action_high=high, seed=0,
        params={}, method="mapex_td3",
    )  # fmt: skip
    save_population(path, members, meta)


def run_command(population: Path, out: Path, params: Path, seed: int) -> tuple[float, float]:
    """(wall s, CPU s) of one `mapex evaluate`, its workers' CPU included."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "stages.cli", "evaluate", "--population", str(population), "--out", str(out)]
    cmd += ["--seed", str(seed), "--params", str(params)]
    env = {
        **os.environ,
        "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
        "MAPEX_TORCH_THREADS": "1",
    }
    subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def episodes_cpu(population: Path, episodes: int, seed: int) -> float:
    """CPU seconds of the members' episodes alone, in this process, as the stage's loop runs them."""
    torch.set_num_threads(1)
    members, meta = load_population(population, META_KEYS)
    envs = [make_env(ENV_ID, CAP) for _ in range(episodes)]
    t0 = time.process_time()
    for i, member in enumerate(members):
        evaluate_policy(member_actor(member, meta), envs, eval_seeds(seed, 1, i, episodes))
    spent = time.process_time() - t0
    for env in envs:
        env.close()
    return spent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--population", type=Path, help="a population.pt on mo-halfcheetah-v5 (default: write one)")
    ap.add_argument("--seed", type=int, default=0, help="the population's run seed")
    ap.add_argument("--children", type=int, default=12, help="children of the written population (quickstart: 12)")
    ap.add_argument("--hidden", type=int, nargs="+", default=[64, 64], help="its actors' widths (quickstart: 64 64)")
    ap.add_argument("--episodes", type=int, default=10, help="evaluate.episodes (quickstart: 10)")
    ap.add_argument("--processes", type=int, nargs="+", default=[1, 2], help="evaluate.processes to compare")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-evaluate-"))
    population = args.population
    if population is None:
        population = work / "population.pt"
        write_population(population, args.children, args.hidden)
    n_members = len(load_population(population, META_KEYS)[0])
    params = {}
    for p in args.processes:
        params[p] = work / f"params{p}.yaml"
        body = {
            "env": {"id": ENV_ID, "max_episode_steps": CAP},
            "evaluate": {"episodes": args.episodes, "processes": p},
        }
        params[p].write_text(yaml.safe_dump(body))
    print(f"cpu: {cpu_model()}; {os.cpu_count()} cores; torch {torch.__version__}, 1 thread per process; {load()}")
    print(f"population: {n_members} members ({population}), {args.episodes} episodes of {CAP} steps each, {ENV_ID}")
    times: dict[int, list[tuple[float, float]]] = {p: [] for p in args.processes}
    for _ in range(args.rounds):
        for p in args.processes:
            times[p].append(run_command(population, work / f"out{p}", params[p], args.seed))
    same = all(
        (work / f"out{p}" / name).read_bytes() == (work / f"out{args.processes[0]}" / name).read_bytes()
        for p in args.processes
        for name in ("evaluated.csv", "evaluation.json")
    )
    work_cpu = episodes_cpu(population, args.episodes, args.seed)
    print(f"episodes alone, in process: {work_cpu:.2f} CPU s; {load()}")
    print(f"outputs byte-identical across process counts: {'yes' if same else 'NO'}\n")
    print("| `evaluate.processes` | wall s (median of rounds) | CPU s (median) | every round's wall s |")
    print("|---:|---:|---:|---|")
    for p in args.processes:
        wall = statistics.median(w for w, _ in times[p])
        cpu = statistics.median(c for _, c in times[p])
        print(f"| {p} | {wall:.2f} | {cpu:.2f} | {', '.join(f'{w:.2f}' for w, _ in times[p])} |")
    if not same:
        sys.exit("the process counts wrote different outputs")


if __name__ == "__main__":
    main()
