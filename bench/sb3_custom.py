#!/usr/bin/env python3
"""Stable-Baselines3 A2C and PPO (their default settings, 8 envs) on a custom env as
SAVER's runs see it (saver_actor.examples:NAME): the reward is the scalar sum of the
state aligned vector reward |p - g| - |p' - g| (what our A2C sees), an episode ends at
success (the declaration's radius) or at --max-steps. Evaluated as
bench/custom_env_results.py evaluates our runs: 50 deterministic episodes (seeds
0-49), mean return in the env's own reward, success rate and mean final L1 |p - g|.
One JSON line.

    SB3 venv: pip install stable-baselines3==2.9.2 "gymnasium[mujoco]" ./python
    python bench/sb3_custom.py {a2c|ppo} --factory saver_actor.examples:pointmass --steps STEPS --seed SEED \\
        [--max-steps 200] [--save MODEL.zip]
"""
import argparse
import importlib
import json
import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import A2C, PPO
from stable_baselines3.common.env_util import make_vec_env

torch.set_num_threads(1)
ap = argparse.ArgumentParser()
ap.add_argument("algo", choices=["a2c", "ppo"])
ap.add_argument("--factory", required=True)
ap.add_argument("--steps", type=int, required=True)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--max-steps", type=int, default=200)
ap.add_argument("--save", help="write the trained model here (SB3's zip), for bench/approach_profile.py")
opts = ap.parse_args()
mod, _, fn = opts.factory.partition(":")
make_env, decl = getattr(importlib.import_module(mod), fn)()


class Aligned(gym.Wrapper):
    """The env with SAVER's scalar reward and success; `env_return` keeps its own."""

    def reset(self, **kw):
        o, info = self.env.reset(**kw)
        self.obs, self.t, self.env_return, self.success = np.asarray(o), 0, 0.0, False
        return o, info

    def step(self, a):
        o, r, term, trunc, info = self.env.step(decl.env_actions(np.asarray(a)[None], self.env.action_space)[0])
        _, vec, success = decl.outcome(self.obs[None], np.asarray(o)[None], [r], [term], [info], check=False)
        self.obs, self.t, self.success = np.asarray(o), self.t + 1, bool(success[0])
        self.env_return += float(r)
        return o, float(vec.sum()), term or self.success, (trunc or self.t >= opts.max_steps) and not self.success, info


def evaluate(model, episodes=50):
    env = Aligned(make_env())
    returns, successes, dist = [], 0, []
    for ep in range(episodes):
        o, _ = env.reset(seed=ep)
        while True:
            a, _ = model.predict(o, deterministic=True)
            o, _, term, trunc, _ = env.step(a)
            if term or trunc:
                break
        g = 0.0 if decl.goal is None else env.obs[decl.goal]
        returns.append(env.env_return)
        successes += env.success
        dist.append(float(np.abs(env.obs[decl.aligned] - g).sum()))
    return {"return": round(float(np.mean(returns)), 3), "success": successes / episodes,
            "distance": round(float(np.mean(dist)), 4)}


venv = make_vec_env(lambda: Aligned(make_env()), n_envs=8, seed=opts.seed)
model = {"a2c": A2C, "ppo": PPO}[opts.algo]("MlpPolicy", venv, seed=opts.seed, device="cpu", verbose=0)
before = evaluate(model)
start = time.time()
model.learn(total_timesteps=opts.steps)
wall = time.time() - start
if opts.save:
    model.save(opts.save)
log_std = float(model.policy.log_std.mean()) if hasattr(model.policy, "log_std") else None
print(json.dumps({"env": decl.name, "algo": f"sb3-{opts.algo}", "seed": opts.seed, "steps": opts.steps,
                  "wall_s": round(wall, 1), "log_std_mean": log_std, "untrained": before,
                  "trained": evaluate(model)}), flush=True)
