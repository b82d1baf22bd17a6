"""Stage render's cost for a front of N policies: the real `mapex render` command on a synthetic
front of random 64-64 actors (every one non-dominated, so every one is filmed), timed whole.

    MUJOCO_GL=egl python benchmarks/bench_render.py --clips 30 --frames 200 --width 320 --height 240 --processes 2

prints the stage's wall time, seconds per clip and milliseconds per frame, and the CPU time of
the stage and its workers (less sensitive to what else the machine runs; docs/benchmarks.md,
"Rendering clips"). The quickstart films seed 0's fronts of its three methods: about 30 clips.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.core.envs import env_spec, make_env  # noqa: E402
from pipeline.core.nets import Actor  # noqa: E402
from pipeline.core.population import Member, save_population  # noqa: E402
from pipeline.evaluation.episodes import EvalResult  # noqa: E402

ENV, STEPS = "mo-halfcheetah-v5", 750


def synthetic_front(root: Path, n: int, seed: int = 0) -> None:
    """n random 64-64 actors as one population whose evaluated returns all lie on one front."""
    from stages.evaluate import evaluated_csv

    env = make_env(ENV, STEPS)
    spec = env_spec(env, ENV, STEPS)
    env.close()
    torch.manual_seed(seed)
    meta = {"env_id": ENV, "n_objectives": 2, "seed": seed, "method": "mapex_td3", "params": {}}
    meta |= {"obs_dim": spec.obs_dim, "act_dim": spec.act_dim}
    meta |= {"action_low": list(spec.action_low), "action_high": list(spec.action_high)}
    members = []
    for i in range(n):
        actor = Actor(spec.obs_dim, spec.act_dim, [64, 64], spec.action_low, spec.action_high)
        ret = [float(i), float(n - i)]
        members.append(
            Member(
                origin="child", objective=None, iteration=i, parents=[], target_weight=[0.5, 0.5], returns=ret,
                returns_std=[0.0, 0.0], eval_episodes=1, env_samples=0, hidden_sizes=[64, 64],
                actor={k: v.clone() for k, v in actor.state_dict().items()}, policy_name=None,
            )
        )  # fmt: skip
    pop = root / "fronts" / "mapex_td3" / f"seed{seed}" / "population.pt"
    pop.parent.mkdir(parents=True)
    save_population(pop, members, meta)
    ev = root / "evaluate" / "mapex_td3" / f"seed{seed}"
    ev.mkdir(parents=True)
    results = [EvalResult(np.array([m.returns, m.returns]), 0) for m in members]
    (ev / "evaluated.csv").write_text(evaluated_csv(members, results))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=30)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--shadow-size", type=int, default=1024)
    ap.add_argument("--samples", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        synthetic_front(root, args.clips)
        render = {"methods": ["mapex_td3"], "frames": args.frames, "width": args.width, "height": args.height}
        render |= {"processes": args.processes, "shadow_size": args.shadow_size, "samples": args.samples}
        params = {
            "env": {"id": ENV, "max_episode_steps": STEPS},
            "seeds": [0],
            "methods": ["mapex_td3"],
            "export_methods": [],
            "render": render,
        }
        (root / "params.yaml").write_text(yaml.safe_dump(params))
        cmd = [sys.executable, "-m", "stages.cli", "render", "--fronts", root / "fronts", "--evaluated"]
        cmd += [root / "evaluate", "--out", root / "render", "--export", root / "export", "--params"]
        cmd += [root / "params.yaml"]
        load0 = f"{os.getloadavg()[0]:.1f}"
        cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        done = subprocess.run([str(c) for c in cmd], cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the stage and its workers, all waited for
        cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
        if done.returncode != 0:
            sys.exit(done.stderr[-2000:])
        frames = sum(json.loads(p.read_text())["frames"] for p in (root / "render" / "clips").rglob("*.json"))
        print(
            f"{args.clips} clips x {args.frames} frames at {args.width}x{args.height}, {args.processes} process(es), "
            f"shadow map {args.shadow_size}, {args.samples} samples: {wall:.1f} s stage wall time "
            f"({wall / args.clips:.2f} s/clip, {1000 * wall / frames:.1f} ms/frame all in); {cpu:.1f} CPU s "
            f"({1000 * cpu / frames:.1f} CPU ms/frame); load average before {load0}, after {os.getloadavg()[0]:.1f}"
        )


if __name__ == "__main__":
    main()
