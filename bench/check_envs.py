"""Goal-reaching envs that no default was chosen on, for checking a custom-env default
beyond the envs it was tuned on (results/README.md, issue 31). Factories for
`--factory check_envs:NAME` with bench/ on PYTHONPATH:

    PYTHONPATH=bench python3 bench/custom_env_results.py target/release/saver --factory check_envs:heavy ...

heavy: the point mass in the plane with a fifth of the drag and half the force
  (terminal speed 2.5; a push of 1 takes ~40 steps to stop the mass from full speed).
pointmass4: the point mass in four coordinates (drag 0.05, force 1).
lagged: a body in the plane whose velocity follows the commanded one with a lag
  (v' = v + 0.2 (2a - v), p' = p + 0.1 v'): the action sets where the velocity goes,
  not the acceleration.
"""
import gymnasium as gym
import numpy as np
from saver_actor.env import EnvDecl
from saver_actor.examples import PointMass, _pointmass_decl


def heavy(radius: float = 0.05):
    def make(render_mode=None):
        return PointMass(drag=0.02, accel=0.5, radius=radius, render_mode=render_mode)

    return make, _pointmass_decl("heavy", make())


def pointmass4(radius: float = 0.05):
    def make(render_mode=None):
        return PointMass(radius=radius, render_mode=render_mode, n=4)

    return make, _pointmass_decl("pointmass4", make())


class Lagged(gym.Env):
    """obs = p (2), v (2), g (2); a in [-1, 1]^2 commands the velocity 2a; 200 steps;
    success within `radius` of g in both coordinates; walls at +-1 as the point mass."""

    def __init__(self, radius: float = 0.05, max_steps: int = 200):
        self.radius, self.max_steps = radius, max_steps
        high = np.array([1, 1, 2, 2, 1, 1], dtype=np.float64)
        self.observation_space = gym.spaces.Box(-high, high, dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self._s, self._t = np.zeros(6), 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        while True:
            p, g = self.np_random.uniform(-0.9, 0.9, 2), self.np_random.uniform(-0.9, 0.9, 2)
            if np.max(np.abs(p - g)) >= 0.5:
                break
        self._s, self._t = np.concatenate([p, np.zeros(2), g]), 0
        return self._s.copy(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        p, v, g = self._s[0:2], self._s[2:4], self._s[4:6]
        v = v + 0.2 * (2.0 * a - v)
        p = p + 0.1 * v
        wall = np.abs(p) > 1.0
        p, v = np.clip(p, -1.0, 1.0), np.where(wall, 0.0, v)
        self._s, self._t = np.concatenate([p, v, g]), self._t + 1
        dist = np.abs(p - g)
        success = bool(np.max(dist) < self.radius)
        return self._s.copy(), -float(dist.sum()), success, self._t >= self.max_steps and not success, {}


def lagged(radius: float = 0.05):
    def make(render_mode=None):
        return Lagged(radius=radius)

    decl = EnvDecl(name="lagged", obs_low=[-1, -1, -2, -2, -1, -1], obs_high=[1, 1, 2, 2, 1, 1], aligned=slice(0, 2),
                   goal=slice(4, 6), max_change=0.2, continuous=2, success_radius=radius)
    return make, decl
