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


class PointMass(gym.Env):
    """A point mass with inertia in the plane, pushed by a bounded force towards a goal
    that moves each episode: the second inertial goal-reaching env SAVER is measured on
    (results/README.md), numpy only.

    obs = position p (2), velocity v (2), goal g (2). Each step (dt = 0.1):
    v' = (1 - drag)·v + accel·dt·a, p' = p + dt·v', with a in [-1, 1]^2; a wall at
    +-1 stops the coordinate that hits it (p clipped, that v entry set to 0). Reset:
    p, g ~ U(-0.9, 0.9)^2 at least 0.5 apart (L-inf), v = 0. The episode ends at 200
    steps, or as a success when |p - g| < radius in both coordinates. From rest one
    step's action moves p by accel·dt² = 0.01 per unit, while a moving mass drifts by up
    to dt·v_max = 0.2: as in Reacher, one step's position change is mostly velocity."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, drag: float = 0.05, accel: float = 1.0, radius: float = 0.05, max_steps: int = 200,
                 render_mode=None):
        self.drag, self.accel, self.radius, self.max_steps = drag, accel, radius, max_steps
        self.render_mode = render_mode
        self.v_max = accel * 0.1 / drag  # the terminal speed of a constant push of 1: 2
        high = np.array([1.0, 1.0, self.v_max, self.v_max, 1.0, 1.0])
        self.observation_space = gym.spaces.Box(-high, high, dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self._state = np.zeros(6)
        self._t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        while True:
            p, g = self.np_random.uniform(-0.9, 0.9, 2), self.np_random.uniform(-0.9, 0.9, 2)
            if np.max(np.abs(p - g)) >= 0.5:
                break
        self._state = np.concatenate([p, np.zeros(2), g])
        self._t = 0
        return self._state.copy(), {}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        p, v, g = self._state[0:2], self._state[2:4], self._state[4:6]
        v = (1.0 - self.drag) * v + self.accel * 0.1 * a
        p = p + 0.1 * v
        wall = np.abs(p) > 1.0
        p = np.clip(p, -1.0, 1.0)
        v = np.where(wall, 0.0, v)
        self._state = np.concatenate([p, v, g])
        self._t += 1
        dist = np.abs(p - g)
        success = bool(np.max(dist) < self.radius)
        reward = -float(np.sum(dist))
        return self._state.copy(), reward, success, self._t >= self.max_steps and not success, {}

    def render(self, size: int = 128):
        """A size x size RGB frame: the goal's success square in green, the mass in white."""
        frame = np.zeros((size, size, 3), dtype=np.uint8)

        def pixel(x):
            return np.clip(((np.asarray(x) + 1.0) * 0.5 * (size - 1)).round().astype(int), 0, size - 1)

        g, r = self._state[4:6], max(self.radius, 2.0 / size)
        (x0, y0), (x1, y1) = pixel(g - r), pixel(g + r)
        frame[y0:y1 + 1, x0:x1 + 1] = (40, 160, 60)
        x, y = pixel(self._state[0:2])
        frame[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3] = 255
        return frame


def pointmass(radius: float = 0.05):
    """The inertial point mass (PointMass): p = obs[0:2], goal g = obs[4:6], success
    within `radius` of g in both coordinates. Velocities stay within the terminal
    speed accel·dt/drag = 2, so one step moves p by at most dt·2 = 0.2."""
    def make_env(render_mode=None):
        return PointMass(radius=radius, render_mode=render_mode)

    env = PointMass(radius=radius)
    v = env.v_max
    decl = EnvDecl(name="pointmass", obs_low=[-1, -1, -v, -v, -1, -1], obs_high=[1, 1, v, v, 1, 1],
                   aligned=slice(0, 2), goal=slice(4, 6), max_change=0.1 * v, continuous=2,
                   success_radius=radius)
    return make_env, decl
