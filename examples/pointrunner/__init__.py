"""PointRunner: a small continuous-control env that is not MuJoCo, for trying mapex on your own env.

A point on a ring track is pushed by a 2-D action in [-1, 1]^2: the first component accelerates
it, the second only costs energy (a distraction a policy must learn to leave at 0). Like
Gymnasium's MuJoCo envs, it returns ONE scalar reward, the sum of its terms, and reports each
term in the info dict of every step:

    reward_forward  the point's velocity (up to about 5 per step at full throttle)
    reward_ctrl     -sum(action^2) (0 at rest, -2 at most)

so that mapex makes it a two-objective env from params alone:

    env:
      id: examples.pointrunner:PointRunner-v0     # importing the module registers the id
      reward_terms:
        - {info: reward_forward, name: speed}
        - {info: reward_ctrl, name: energy efficiency}
      reference_point: [-10.0, -100.0]             # for 50-step episodes; see docs/manual.md

Observation: (velocity, sin(position), cos(position)). It draws itself for `render_mode="rgb_array"`
(a 64 x 128 image: the track and the point), so stage render films it without MuJoCo.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np


class PointRunner(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, render_mode: str | None = None):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.render_mode = render_mode
        self._x = 0.0
        self._v = 0.0

    def _obs(self) -> np.ndarray:
        return np.array([self._v, np.sin(self._x), np.cos(self._x)], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._x = float(self.np_random.uniform(-np.pi, np.pi))
        self._v = float(self.np_random.uniform(-0.1, 0.1))
        return self._obs(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self._v = 0.9 * self._v + 0.5 * a[0]
        self._x = (self._x + 0.1 * self._v + np.pi) % (2 * np.pi) - np.pi
        forward, ctrl = self._v, -float(np.sum(a**2))
        info = {"reward_forward": forward, "reward_ctrl": ctrl, "x_velocity": self._v}
        return self._obs(), forward + ctrl, False, False, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        img = np.full((64, 128, 3), 235, dtype=np.uint8)
        img[30:34, 4:124] = 150  # the track, unrolled
        col = int(4 + (self._x + np.pi) / (2 * np.pi) * 119)
        img[24:40, max(col - 3, 0) : col + 4] = (200, 40, 40)
        return img


gym.register("PointRunner-v0", entry_point=PointRunner, max_episode_steps=200)
