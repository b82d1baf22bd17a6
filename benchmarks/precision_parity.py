"""Parity of bf16 against fp32 (issue 30, item 4): the same runs in each precision, one table.

    python benchmarks/precision_parity.py WORKDIR                     # quickstart scale, 4 + 3 seeds
    python benchmarks/precision_parity.py WORKDIR --set td3.hidden_sizes=[256,256] --set extract.hidden_sizes=[256,256]
    python benchmarks/precision_parity.py /tmp/parity-tiny --tiny     # minutes: checks that it runs, no evidence

1. Specialists: for each precision P (--precisions) and seed S (--seeds), `mapex
   train-specialist` with the params file (--params, default the repository's params.yaml: the
   quickstart, mo-halfcheetah-v5) and train_specialist.precision = P; both objectives' TD3
   specialists, the speed one (objective 0) being the one the issue asks about.
2. Each specialist: deterministic returns (the mean over --eval-episodes fresh episodes in fp32,
   so policies are compared, not evaluation arithmetic) and critic fidelity (`mapex
   critic-fidelity`: the joint critics against Monte-Carlo returns of their own buffer; the
   normalised error and Pearson r on the specialist's own objective).
3. Children: from the same specialists (those trained in --children-from, default fp32), for
   each precision P and seed S of --child-seeds, `mapex extract` (variant mapex) with
   extract.precision = P, then `mapex evaluate` (in fp32 for all) and `mapex score`: the front's
   hypervolume and distinct points.
4. The table: mean +- SEM over seeds per precision, and the difference bf16 - fp32 in units of
   the pooled SEM (|d| < 2: within the seed noise).

Every stage runs as a subprocess of this Python (`python -m stages.cli`, MAPEX_TORCH_THREADS=1)
writing under WORKDIR; what is already there (a specialist's policy.pt, a front's metrics.json) is not run
again, so a rerun continues an interrupted one. --set KEY=VALUE (YAML value, dotted key) changes
the params of every run. Timings are not the point here: see bench_extract.py and
bench_specialist.py.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.core.checkpoint import load_policy  # noqa: E402
from pipeline.core.envs import make_env  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy  # noqa: E402
from pipeline.params import RunParams  # noqa: E402
from pipeline.params.tracked import tidied_text  # noqa: E402

EVAL_STREAM = 7  # fresh episodes: neither extraction's stream 0 nor evaluate's 1

# --tiny: a budget that runs in minutes, to check the script (its numbers mean nothing)
TINY = {
    "td3": {"learning_starts": 300, "buffer_size": 2000, "batch_size": 64, "hidden_sizes": [32, 32]},
    "train_specialist": {"total_steps": 800, "processes": 1, "keep_best_every": 0, "checkpoint_every": 0},
    "extract": {"iterations": 2, "child_buffer_size": 600, "eval_episodes": 2, "warmup_steps": 30, "epochs": 1},
    "evaluate": {"episodes": 2},
    "env": {"max_episode_steps": 120},
    "critic_fidelity": {"episodes": 3, "tail_tolerance": 0.5},  # 120-step episodes: a shorter horizon
}


def merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def dotted(pairs: list[str]) -> dict:
    """--set a.b=VALUE ... as a nested dict (values parsed as YAML)."""
    out: dict = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"--set {pair!r}: expected KEY=VALUE")
        *path, last = key.split(".")
        node = out
        for p in path:
            node = node.setdefault(p, {})
        node[last] = yaml.safe_load(value)
    return out


def mapex(work: Path, label: str, *args: str) -> None:
    """One stage command; its output goes to WORKDIR/log.txt, a failure stops here."""
    env = {**os.environ, "MAPEX_TORCH_THREADS": "1", "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    with open(work / "log.txt", "a") as log:
        log.write(f"\n$ mapex {' '.join(args)}\n")
        log.flush()
        # in the repository (score reads presets/envs.yaml); every path given is absolute
        proc = subprocess.run([sys.executable, "-m", "stages.cli", *args], cwd=ROOT, env=env, stdout=log, stderr=log)
    if proc.returncode:
        raise SystemExit(f"mapex {args[0]} failed (exit {proc.returncode}); see {work / 'log.txt'}")
    print(f"  {args[0]} {label}: {time.perf_counter() - t0:.0f} s", flush=True)


def mean_sem(values: list[float]) -> tuple[float, float]:
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return math.nan, math.nan
    m = float(np.mean(v))
    return m, float(np.std(v, ddof=1) / math.sqrt(len(v))) if len(v) > 1 else math.nan


def cell(values: list[float], digits: int = 1) -> str:
    m, s = mean_sem(values)
    if math.isnan(m):
        return "n/a"
    return f"{m:.{digits}f}" + ("" if math.isnan(s) else f" ± {s:.{digits}f}") + f" (n={len(values)})"


def gap(a: list[float], b: list[float]) -> str:
    """(mean b - mean a) over the pooled SEM, sqrt(SEM_a^2 + SEM_b^2)."""
    (ma, sa), (mb, sb) = mean_sem(a), mean_sem(b)
    pooled = math.hypot(sa, sb)
    return "n/a" if not pooled or math.isnan(pooled) else f"{(mb - ma) / pooled:+.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--params", type=Path, default=ROOT / "params.yaml", help="base params (default: the quickstart)")
    ap.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3], help="specialist seeds (issue: >= 4)")
    ap.add_argument("--child-seeds", type=int, nargs="+", default=[0, 1, 2], help="extraction seeds (issue: 3)")
    ap.add_argument("--children-from", default="fp32", choices=["fp32", "bf16"], help="whose specialists")
    ap.add_argument("--eval-episodes", type=int, default=10, help="deterministic episodes per specialist")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="params override (repeatable)")
    ap.add_argument("--tiny", action="store_true", help="a tiny budget, to check that everything runs")
    args = ap.parse_args()
    if not set(args.child_seeds) <= set(args.seeds):
        ap.error("--child-seeds must be among --seeds (children come from those seeds' specialists)")
    if args.children_from not in args.precisions:
        ap.error(f"--children-from {args.children_from} is not among --precisions")
    work = args.workdir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    base = yaml.safe_load(args.params.read_text())
    base = merge(base, TINY) if args.tiny else base
    base = merge(base, dotted(args.set))
    base |= {"seeds": sorted(set(args.seeds)), "methods": ["mapex_td3"]}
    for key in RunParams.model_fields:  # the derived lists: derived again where read
        if key not in ("seeds", "objectives", "methods"):
            base.pop(key, None)
    files = {}
    for p in args.precisions:
        params = merge(base, {"train_specialist": {"precision": p}, "extract": {"precision": p}})
        files[p] = work / f"params_{p}.yaml"
        files[p].write_text(tidied_text(yaml.safe_dump(params, sort_keys=False), str(files[p])))
    objectives = list(base.get("objectives", [0, 1]))
    env_id, cap = base["env"]["id"], base["env"]["max_episode_steps"]
    print(
        f"parity in {work}: {env_id}, precisions {args.precisions}, seeds {args.seeds}, children seeds "
        f"{args.child_seeds} from the {args.children_from} specialists",
        flush=True,
    )

    returns = {p: {k: [] for k in objectives} for p in args.precisions}
    fidelity = {p: {k: [] for k in objectives} for p in args.precisions}
    pearson = {p: {k: [] for k in objectives} for p in args.precisions}
    envs = [make_env(env_id, cap) for _ in range(args.eval_episodes)]
    for p in args.precisions:
        for s in args.seeds:
            out = work / f"specialists_{p}" / f"seed{s}"
            if not all((out / f"obj{k}" / "policy.pt").exists() for k in objectives):
                mapex(
                    work,
                    f"{p} seed {s}",
                    "train-specialist",
                    "--seed",
                    str(s),
                    "--out",
                    str(out),
                    "--params",
                    str(files[p]),
                )
            for k in objectives:
                spec = out / f"obj{k}"
                fid = work / f"fidelity_{p}" / f"seed{s}" / f"obj{k}.json"
                if not fid.exists():
                    mapex(
                        work,
                        f"{p} seed {s} obj {k}",
                        "critic-fidelity",
                        "--objective",
                        str(k),
                        "--specialist",
                        str(spec),
                        "--out",
                        str(fid),
                        "--params",
                        str(files[p]),
                    )
                own = json.loads(fid.read_text())[f"obj{k}"]
                fidelity[p][k].append(own["rel_error"])
                pearson[p][k].append(own["pearson"])
                actor, _ = load_policy(spec / "policy.pt")
                res = evaluate_policy(actor, envs, eval_seeds(s, EVAL_STREAM, k, args.eval_episodes))
                returns[p][k].append(float(res.mean[k]))
    for env in envs:
        env.close()

    hv = {p: [] for p in args.precisions}
    distinct = {p: [] for p in args.precisions}
    for p in args.precisions:
        for s in args.child_seeds:
            front, ev, sc = (work / f"{d}_{p}" / f"seed{s}" for d in ("fronts", "evaluate", "score"))
            if not (sc / "metrics.json").exists():
                specialists = work / f"specialists_{args.children_from}" / f"seed{s}"
                mapex(
                    work,
                    f"{p} seed {s}",
                    "extract",
                    "--seed",
                    str(s),
                    "--specialists",
                    str(specialists),
                    "--out",
                    str(front),
                    "--resume-dir",
                    str(work / "resume" / p),
                    "--params",
                    str(files[p]),
                )
                mapex(
                    work,
                    f"{p} seed {s}",
                    "evaluate",
                    "--seed",
                    str(s),
                    "--population",
                    str(front / "population.pt"),
                    "--out",
                    str(ev),
                    "--params",
                    str(files[p]),
                )
                mapex(
                    work,
                    f"{p} seed {s}",
                    "score",
                    "--population",
                    str(front / "population.pt"),
                    "--evaluated",
                    str(ev),
                    "--out",
                    str(sc),
                    "--params",
                    str(files[p]),
                )
            metrics = json.loads((sc / "metrics.json").read_text())["front"]
            hv[p].append(metrics["hypervolume"])
            distinct[p].append(metrics["distinct_count"])

    a, b = (args.precisions + args.precisions)[:2]
    print(
        f"\nSpecialists ({env_id}, seeds {args.seeds}; returns: {args.eval_episodes} deterministic episodes, fp32):\n"
    )
    print(f"| objective | what | {' | '.join(args.precisions)} | {b} - {a} in pooled SEMs |")
    print("|---|---|" + "---|" * len(args.precisions) + "---|")
    for k in objectives:
        for what, table, digits in (
            ("return", returns, 1),
            ("critic rel. error", fidelity, 3),
            ("critic Pearson r", pearson, 3),
        ):
            row = [cell(table[p][k], digits) for p in args.precisions]
            print(f"| {k} | {what} | {' | '.join(row)} | {gap(table[a][k], table[b][k])} |")
    print(
        f"\nChildren (extract.precision; from the {args.children_from} specialists, seeds {args.child_seeds}; "
        "fronts re-evaluated in fp32):\n"
    )
    print(f"| what | {' | '.join(args.precisions)} | {b} - {a} in pooled SEMs |")
    print("|---|" + "---|" * len(args.precisions) + "---|")
    for what, table, digits in (("hypervolume", hv, 0), ("distinct points", distinct, 1)):
        row = [cell(table[p], digits) for p in args.precisions]
        print(f"| {what} | {' | '.join(row)} | {gap(table[a], table[b])} |")


if __name__ == "__main__":
    main()
