#!/usr/bin/env python3
"""Tuned peers on a custom env in its own reward (issue 55), Reacher-v5 by default:
Stable-Baselines3 PPO with
RL Zoo's Optuna-tuned Reacher hyperparameters (rl_zoo3/hyperparams/ppo.yml, key
Reacher-v2: VecNormalize on observations and rewards, 1 env, n_steps 512, batch 32,
5 epochs, gamma 0.9, GAE lambda 1.0, lr 1.04e-4, clip 0.3, ent 7.5e-8, vf 0.95,
max_grad_norm 0.9) and SB3 SAC at its defaults. The env is gym.make("Reacher-v5")
with saver_actor.examples:reacher's observation (joint velocities x 0.1, as SAVER's
runs see it; VecNormalize rescales it anyway), 50 steps, never ended at success.
`--factory module:function` runs another env of the same kind (saver_actor.examples:
pointmass: RL Zoo has no entry for it, so it gets the Reacher entry, the zoo's tuned
settings for the nearest task, a goal reached by continuous force), with episodes of
`--max-steps` steps, evaluated as SAVER's runs of that env are.

Every --eval-every env steps, 50 deterministic episodes (env seeds 0-49) as
bench/custom_env_results.py evaluates SAVER: success (fingertip within 0.02 of the
target in both coordinates at some step), the return up to success, and "env_return",
the env's own return over all 50 steps. One JSON line per evaluation on stdout, then
one with "final": true.

    SB3 venv: pip install stable-baselines3==2.9.2 rl_zoo3 "gymnasium[mujoco]" ./python
    python bench/sb3_tuned.py {ppo-zoo|sac} --steps 1000000 --seed 0 [--eval-every 50000]
        [--factory saver_actor.examples:pointmass --max-steps 200] [--lr-decay]
"""
import argparse
import json
import time

import torch
from gymnasium.wrappers import TimeLimit
from saver_actor import factory_function
from saver_actor.evaluate import scored_episodes
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

torch.set_num_threads(1)
ap = argparse.ArgumentParser()
ap.add_argument("algo", choices=["ppo-zoo", "sac"])
ap.add_argument("--steps", type=int, required=True)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--eval-every", type=int, default=50_000)
ap.add_argument("--episodes", type=int, default=50)
ap.add_argument("--factory", default="saver_actor.examples:reacher",
                help="module:function returning (make_env, EnvDecl), as saver-actor's --factory")
ap.add_argument("--max-steps", type=int, default=50, help="steps per episode, in training and evaluation")
ap.add_argument("--lr-decay", action="store_true",
                help="PPO's rate falls linearly to 0 over --steps, as SAVER's does on a custom env "
                "(the zoo's is constant)")
opts = ap.parse_args()
if opts.lr_decay and opts.algo != "ppo-zoo":
    ap.error("--lr-decay is PPO's (SAC keeps SB3's constant rate)")
make_env, decl = factory_function(opts.factory)()


def train_env():
    """The env for training, its episodes cut at --max-steps as the evaluation's are."""
    return TimeLimit(make_env(), opts.max_steps)


def evaluate(model, norm):
    """Deterministic episodes (seeds 0..episodes-1) scored as SAVER's runs are
    (saver_actor.evaluate.scored_episodes), through VecNormalize's observation scaling."""
    def act(o):
        x = norm.normalize_obs(o[None]) if norm is not None else o[None]
        return model.predict(x, deterministic=True)[0][0]
    r = scored_episodes(make_env, decl, act, opts.episodes, opts.max_steps)
    return {"success": r["success"], "return": r["return"], "env_return": r["env_return"]}


class Every(BaseCallback):
    """Evaluates every --eval-every steps and prints a JSON line."""

    def __init__(self, norm):
        super().__init__()
        self.norm, self.next, self.t0 = norm, opts.eval_every, time.time()

    def _on_step(self):
        if self.num_timesteps >= self.next:
            self.next += opts.eval_every
            line = {"algo": name, "env": opts.factory, "seed": opts.seed, "steps": self.num_timesteps,
                    "wall_s": round(time.time() - self.t0, 1), **evaluate(self.model, self.norm)}
            print(json.dumps(line), flush=True)
        return True


if opts.algo == "ppo-zoo":
    venv = VecNormalize(make_vec_env(train_env, n_envs=1, seed=opts.seed), norm_obs=True, norm_reward=True,
                        gamma=0.9)
    lr = 0.000104019
    model = PPO("MlpPolicy", venv, n_steps=512, batch_size=32, gamma=0.9,
                learning_rate=(lambda left: lr * left) if opts.lr_decay else lr,
                ent_coef=7.52585e-08, clip_range=0.3, n_epochs=5, gae_lambda=1.0, max_grad_norm=0.9,
                vf_coef=0.950368, seed=opts.seed, device="cpu")
    norm = venv
else:
    venv = make_vec_env(train_env, n_envs=1, seed=opts.seed)
    model = SAC("MlpPolicy", venv, seed=opts.seed, device="cpu")
    norm = None
name = opts.algo + ("-lr-decay" if opts.lr_decay else "")
t0 = time.time()
model.learn(total_timesteps=opts.steps, callback=Every(norm))
if isinstance(norm, VecNormalize):
    norm.training = False
print(json.dumps({"algo": name, "env": opts.factory, "seed": opts.seed, "steps": opts.steps,
                  "wall_s": round(time.time() - t0, 1),
                  "final": True, **evaluate(model, norm)}), flush=True)
