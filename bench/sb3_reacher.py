#!/usr/bin/env python3
"""Stable-Baselines3 A2C and PPO (their default settings) on Reacher-v5 with the reward
SAVER's runs see: the scalar sum of the state aligned vector reward |p| - |p'| (p =
fingertip - target, obs[8:10]), an episode that ends when the fingertip is within 0.02
of the target in both coordinates (success) or after 50 steps, joint velocities scaled
by 0.1 (saver_actor.examples.reacher). Prints a JSON line: steps, wall seconds, and the
mean final |fingertip - target| (L1) of 50 deterministic episodes, untrained and
trained, as tests/python/test_saver_actor.py measures SAVER's.

    SB3 venv: pip install stable-baselines3==2.9.2 "gymnasium[mujoco]"
    python bench/sb3_reacher.py {a2c|ppo} STEPS SEED
"""
import json
import sys
import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.env_util import make_vec_env

torch.set_num_threads(1)
RADIUS = 0.02


class AlignedReward(gym.Wrapper):
    def __init__(self, env):
        super().__init__(env)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (10,), np.float64)

    def _scale(self, o):
        o = np.array(o, dtype=np.float64)
        o[6:8] *= 0.1
        return o

    def reset(self, **kw):
        o, info = self.env.reset(**kw)
        self.p = o[8:10].copy()
        return self._scale(o), info

    def step(self, a):
        o, _, term, trunc, info = self.env.step(a)
        q = o[8:10]
        r = float(np.sum(np.abs(self.p) - np.abs(q)))
        self.p = q.copy()
        success = bool(np.max(np.abs(q)) < RADIUS)
        return self._scale(o), r, term or success, trunc and not success, info


def final_distance(model, episodes=50):
    env = AlignedReward(gym.make("Reacher-v5"))
    dist = []
    for ep in range(episodes):
        o, _ = env.reset(seed=ep)
        for _ in range(50):
            a, _ = model.predict(o, deterministic=True)
            o, _, term, trunc, _ = env.step(a)
            if term or trunc:
                break
        dist.append(float(np.abs(env.p).sum()))
    return float(np.mean(dist))


algo, steps, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
venv = make_vec_env(lambda: AlignedReward(gym.make("Reacher-v5")), n_envs=8, seed=seed)
model = {"a2c": A2C, "ppo": PPO}[algo]("MlpPolicy", venv, seed=seed, device="cpu", verbose=0)
before = final_distance(model)
t = time.time()
model.learn(total_timesteps=steps)
wall = time.time() - t
print(json.dumps({"algo": f"sb3-{algo}", "seed": seed, "steps": steps, "wall_s": round(wall, 1),
                  "untrained": round(before, 4), "trained": round(final_distance(model), 4)}), flush=True)
