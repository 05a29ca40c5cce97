"""Declarations of environments SAVER has been run on, for `--factory` and the tests."""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from .env import EnvDecl


def reacher(success_radius: float = 0.02, velocity_scale: float = 0.1):
    """Gymnasium's MuJoCo Reacher-v5 (50 steps): obs = cos q (2), sin q (2), target xy
    (2), joint velocities (2), fingertip - target xy (2). The aligned position is
    obs[8:10], already relative to the target (g = 0); the fingertip reaches 0.21 from
    the centre and the target lies within 0.2 of it, so each entry stays within 0.41.
    Joint velocities stay within +-200 rad/s and one step moves the fingertip by less
    than 0.5 (measured: 40 rad/s and 0.15 under random actions). Success: the
    fingertip within `success_radius` of the target in both coordinates. The joint
    velocities are multiplied by `velocity_scale` (so that no input dwarfs the others;
    SB3's Reacher settings normalise every input for the same reason)."""
    def make_env():
        env = gym.make("Reacher-v5")
        if velocity_scale == 1.0:
            return env
        scale = np.ones(10)
        scale[6:8] = velocity_scale
        space = gym.spaces.Box(-np.inf, np.inf, (10,), np.float64)
        return gym.wrappers.TransformObservation(env, lambda o: o * scale, space)

    v = 200.0 * velocity_scale
    low = [-1.0] * 4 + [-0.2, -0.2] + [-v, -v] + [-0.5, -0.5]
    high = [1.0] * 4 + [0.2, 0.2] + [v, v] + [0.5, 0.5]
    decl = EnvDecl(name="reacher", obs_low=low, obs_high=high, aligned=slice(8, 10), max_change=0.5,
                   continuous=2, success_radius=success_radius)
    return make_env, decl
