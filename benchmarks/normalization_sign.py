"""Does the import's warning tell SB3 models trained on normalised observations from raw ones?

Trains SB3 TD3 and SAC (64x64 nets) for --steps steps on one objective of an MO env, each under
VecNormalize(norm_obs=True) and on raw observations, and prints, for each, the two spreads the
import compares (pipeline.interop.readers.input_scale_warning): of the log input scales its
critic's first layer saw in training ("flat"), and of the same relative to the raw scales of
1,000 env steps under random actions ("vs_raw"), and whether the warning fires (flat < 0.5 vs_raw).
Needs stable-baselines3 (a test extra). About 15-120 s per model on 2 busy cores.

    python benchmarks/normalization_sign.py --env mo-halfcheetah-v5 --steps 5000
    python benchmarks/normalization_sign.py --env mo-hopper-v5 --steps 1500
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.core.envs import env_spec, make_env  # noqa: E402
from pipeline.interop.readers import FLATTER, input_scale_warning, read_policy  # noqa: E402


def raw_observations(env_id: str, n: int = 1000) -> np.ndarray:
    env = make_env(env_id, 200)
    env.action_space.seed(0)
    env.reset(seed=0)
    rows = []
    for _ in range(n):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows.append(obs)
        if terminated or truncated:
            env.reset()
    env.close()
    return np.asarray(rows, np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env", default="mo-halfcheetah-v5")
    ap.add_argument("--steps", type=int, default=1500)
    args = ap.parse_args()
    torch.set_num_threads(1)
    import mo_gymnasium as mo
    import stable_baselines3 as sb3
    from mo_gymnasium.wrappers import LinearReward
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    spec = env_spec(make_env(args.env, 200), args.env, 200)
    weight = np.eye(spec.n_objectives, dtype=np.float32)[0]
    obs = raw_observations(args.env)
    raw = np.sqrt(np.mean(np.square(obs.astype(np.float64)), axis=0))
    with tempfile.TemporaryDirectory() as tmp:
        for cls in (sb3.TD3, sb3.SAC):
            for normalised in (True, False):
                start = time.time()
                venv = DummyVecEnv([lambda: LinearReward(mo.make(args.env, max_episode_steps=200), weight=weight)])
                env = VecNormalize(venv) if normalised else venv
                kwargs = {"net_arch": [64, 64]}
                model = cls("MlpPolicy", env, learning_starts=100, policy_kwargs=kwargs, seed=0, device="cpu")
                model.learn(args.steps)
                path = Path(tmp) / "model.zip"
                model.save(path)
                scales = read_policy(path, "sb3", spec).input_scales
                keep = (scales > 0) & (raw > 0)
                seen = np.log(scales[keep])
                flat, versus = float(np.std(seen)), float(np.std(seen - np.log(raw[keep])))
                warns = input_scale_warning(path, scales, obs, normalized=False) is not None
                trained = "VecNormalize" if normalised else "raw"
                print(
                    f"{args.env} {cls.__name__} {args.steps} steps, {trained:12s} flat {flat:.2f} vs_raw {versus:.2f} "
                    f"(warns below {FLATTER} x vs_raw): warns={warns}  [{time.time() - start:.0f} s]",
                    flush=True,
                )


if __name__ == "__main__":
    main()
