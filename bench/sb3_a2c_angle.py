"""Stable-Baselines3 A2C on a Python transcription of SAVER's `angle` env, with the
paper's settings (16 envs x 8 steps, net 256-128-64, RMSProp, lr 3e-4, gamma 0.99, no
gradient clipping, n-step returns). Prints one line: `sb3_a2c STEPS WALL_S STEPS_PER_S
MEAN_LEN_LAST_100`. Run by bench/sb3_compare.sh; alone:

    python bench/sb3_a2c_angle.py --steps 200000 --dim 4
"""

import argparse
import math
import time
from collections import deque

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import A2C
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

SUCCESS_RADIUS = 0.1


class AngleEnv(gym.Env):
    """core/src/env/angle.rs: for each pair k = 0, 2, ...: step s = 0.1 a[k], angle
    phi = (a[k+1] + 1) pi / 2; dp[k] = s sin phi, dp[k+1] = s cos phi; p' = clip(p + dp).
    Reward: the sum of the vector reward |p - g| - |p' - g| (A2C's scalar reward); the
    episode ends on strict L-inf success (< 0.1) or at 1000 steps (terminal, as in the
    paper's code)."""

    def __init__(self, dim=4, max_steps=1000):
        assert dim % 2 == 0
        self.dim, self.max_steps = dim, max_steps
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (dim,), np.float32)
        self.goal = np.zeros(dim, np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-1.0, 1.0, self.dim).astype(np.float32)
        self.steps = 0
        return self.pos.copy(), {}

    def step(self, action):
        a = np.clip(action, -1.0, 1.0)
        s = 0.1 * a[0::2]
        phi = (a[1::2] + 1.0) * math.pi / 2.0
        delta = np.empty(self.dim, np.float32)
        delta[0::2] = s * np.sin(phi)
        delta[1::2] = s * np.cos(phi)
        before = self.pos
        self.pos = np.clip(before + delta, -1.0, 1.0).astype(np.float32)
        self.steps += 1
        reward = float(np.sum(np.abs(before - self.goal) - np.abs(self.pos - self.goal)))
        success = bool(np.max(np.abs(self.pos - self.goal)) < SUCCESS_RADIUS)
        done = success or self.steps >= self.max_steps
        return self.pos.copy(), reward, done, False, {}


class EpisodeLengths(BaseCallback):
    """Lengths of finished episodes (the paper's metric: mean of the last 100)."""

    def __init__(self):
        super().__init__()
        self.lengths = deque(maxlen=100)
        self.running = None

    def _on_step(self):
        dones = self.locals["dones"]
        if self.running is None:
            self.running = np.zeros(len(dones), np.int64)
        self.running += 1
        for i, d in enumerate(dones):
            if d:
                self.lengths.append(int(self.running[i]))
                self.running[i] = 0
        return True


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--steps", type=int, default=200_000)
    p.add_argument("--dim", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    env = make_vec_env(AngleEnv, n_envs=16, seed=args.seed, env_kwargs={"dim": args.dim})
    model = A2C(
        "MlpPolicy",
        env,
        learning_rate=3e-4,
        n_steps=8,
        gamma=0.99,
        gae_lambda=1.0,
        ent_coef=0.0,
        vf_coef=0.5,
        max_grad_norm=1e10,  # the paper clips nothing
        use_rms_prop=True,
        policy_kwargs={"net_arch": [256, 128, 64]},
        seed=args.seed,
        device="cpu",
    )
    cb = EpisodeLengths()
    start = time.perf_counter()
    model.learn(total_timesteps=args.steps, callback=cb)
    wall = time.perf_counter() - start
    mean = sum(cb.lengths) / len(cb.lengths) if cb.lengths else float("nan")
    print(f"sb3_a2c {args.steps} {wall:.2f} {args.steps / wall:.1f} {mean:.1f} torch_threads={torch.get_num_threads()}")


if __name__ == "__main__":
    main()
