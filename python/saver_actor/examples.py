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
    """A point mass with inertia, pushed by a bounded force towards a goal that moves
    each episode: the second inertial goal-reaching env SAVER is measured on
    (results/README.md), numpy only; `n` coordinates (2 by default, the plane).

    obs = position p (n), velocity v (n), goal g (n). Each step (dt = 0.1):
    v' = (1 - drag)·v + accel·dt·a, p' = p + dt·v', with a in [-1, 1]^n; a wall at
    +-1 stops the coordinate that hits it (p clipped, that v entry set to 0). Reset:
    p, g ~ U(-0.9, 0.9)^n at least 0.5 apart (L-inf), v = 0. The episode ends at 200
    steps, or as a success when |p - g| < radius in every coordinate. From rest one
    step's action moves p by accel·dt² = 0.01 per unit, while a moving mass drifts by up
    to dt·v_max = 0.2: as in Reacher, one step's position change is mostly velocity."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, drag: float = 0.05, accel: float = 1.0, radius: float = 0.05, max_steps: int = 200,
                 render_mode=None, n: int = 2):
        self.drag, self.accel, self.radius, self.max_steps, self.n = drag, accel, radius, max_steps, n
        self.render_mode = render_mode
        self.v_max = accel * 0.1 / drag  # the terminal speed of a constant push of 1 (2 by default)
        high = np.concatenate([np.ones(n), np.full(n, self.v_max), np.ones(n)])
        self.observation_space = gym.spaces.Box(-high, high, dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n,), dtype=np.float32)
        self._state = np.zeros(3 * n)
        self._t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        n = self.n
        while True:
            p, g = self.np_random.uniform(-0.9, 0.9, n), self.np_random.uniform(-0.9, 0.9, n)
            if np.max(np.abs(p - g)) >= 0.5:
                break
        self._state = np.concatenate([p, np.zeros(n), g])
        self._t = 0
        return self._state.copy(), {}

    def step(self, action):
        n = self.n
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        p, v, g = self._state[0:n], self._state[n:2 * n], self._state[2 * n:3 * n]
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

        n = self.n  # the first two coordinates, seen from above
        g, r = self._state[2 * n:2 * n + 2], max(self.radius, 2.0 / size)
        (x0, y0), (x1, y1) = pixel(g - r), pixel(g + r)
        frame[y0:y1 + 1, x0:x1 + 1] = (40, 160, 60)
        x, y = pixel(self._state[0:2])
        frame[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3] = 255
        return frame


def _pointmass_decl(name: str, env: PointMass):
    n, v = env.n, env.v_max
    return EnvDecl(name=name, obs_low=[-1] * n + [-v] * n + [-1] * n, obs_high=[1] * n + [v] * n + [1] * n,
                   aligned=slice(0, n), goal=slice(2 * n, 3 * n), max_change=0.1 * v, continuous=n,
                   success_radius=env.radius)


def pointmass(radius: float = 0.05):
    """The inertial point mass (PointMass) in the plane: p = obs[0:2], goal g = obs[4:6],
    success within `radius` of g in both coordinates. Velocities stay within the
    terminal speed accel·dt/drag = 2, so one step moves p by at most dt·2 = 0.2."""
    def make_env(render_mode=None):
        return PointMass(radius=radius, render_mode=render_mode)

    return make_env, _pointmass_decl("pointmass", PointMass(radius=radius))


def pointmass3(radius: float = 0.05):
    """A check env that no default was tuned on: the point mass in three coordinates
    with twice the drag and 1.5 times the force (terminal speed 1.5, so the mass stops
    within ~10 steps of letting go, where the plane's takes ~20). p = obs[0:3], goal
    g = obs[6:9], success within `radius` in every coordinate."""
    def make(render_mode=None):
        return PointMass(drag=0.1, accel=1.5, radius=radius, render_mode=render_mode, n=3)

    return make, _pointmass_decl("pointmass3", make())


class Reach3(gym.Env):
    """A gripper reaching for a goal in 3-D, shaped as Gymnasium-Robotics' goal envs
    (FetchReach): a Dict observation {"achieved_goal": gripper position (3),
    "desired_goal": goal (3), "observation": gripper position (3) and velocity (3)},
    a 4-D action of which the last entry (the gripper's fingers) does nothing, and a
    sparse reward -1 until the gripper is within 0.05 (Euclidean) of the goal, with
    info["is_success"]. Never terminates; 50 steps an episode (TimeLimit).

    Each step the action moves a target point by 0.05·a[:3] (clipped to the box
    +-0.3), and the gripper follows it with a lag: v' = 0.5·(target - p), p' = p + v'.
    The gap target - p' is half the gap before the step plus the target's move, so it
    stays within 0.05 and one step moves the gripper by at most 0.5·(0.05 + 0.05) = 0.05
    per coordinate (the velocity's bound).
    Reset: p = target = 0, v = 0, goal ~ U(-0.15, 0.15)^3 at least 0.05 from p."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(self, render_mode=None):
        self.render_mode = render_mode
        box = gym.spaces.Box(-0.3, 0.3, (3,), dtype=np.float64)
        self.observation_space = gym.spaces.Dict({
            "achieved_goal": box, "desired_goal": box,
            "observation": gym.spaces.Box(np.r_[[-0.3] * 3, [-0.05] * 3], np.r_[[0.3] * 3, [0.05] * 3],
                                          dtype=np.float64)})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self._p, self._v, self._target, self._goal = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)

    def _obs(self):
        return {"achieved_goal": self._p.copy(), "desired_goal": self._goal.copy(),
                "observation": np.concatenate([self._p, self._v])}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._p, self._v, self._target = np.zeros(3), np.zeros(3), np.zeros(3)
        while True:
            self._goal = self.np_random.uniform(-0.15, 0.15, 3)
            if np.linalg.norm(self._goal) >= 0.05:
                break
        return self._obs(), {"is_success": 0.0}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self._target = np.clip(self._target + 0.05 * a[:3], -0.3, 0.3)
        self._v = 0.5 * (self._target - self._p)
        self._p = self._p + self._v
        success = float(np.linalg.norm(self._p - self._goal) < 0.05)
        return self._obs(), success - 1.0, False, False, {"is_success": success}

    def render(self, size: int = 128):
        """A size x size RGB frame seen from above (x, y): the goal green, the gripper
        white, larger the higher it is (z)."""
        frame = np.zeros((size, size, 3), dtype=np.uint8)

        def pixel(x):
            return np.clip(((np.asarray(x) / 0.3 + 1.0) * 0.5 * (size - 1)).round().astype(int), 0, size - 1)

        for point, colour, r in ((self._goal, (40, 160, 60), 3), (self._p, (255, 255, 255), 2)):
            x, y = pixel(point[:2])
            r = r + int(round(2 * point[2] / 0.3))
            frame[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1] = colour
        return frame


def reach3(radius: float = 0.03):
    """Reach3 as a user brings a goal env: FlattenObservation of its Dict observation
    (keys in sorted order: achieved_goal obs[0:3], desired_goal obs[3:6], then the
    gripper's position and velocity obs[6:12]); p = obs[0:3], g = obs[3:6], success
    within `radius` of g in every coordinate (0.03 lies inside the env's own 0.05
    Euclidean ball). One step moves the gripper by at most 0.05 (Reach3)."""
    def make_env(render_mode=None):
        return gym.wrappers.TimeLimit(gym.wrappers.FlattenObservation(Reach3(render_mode=render_mode)), 50)

    decl = EnvDecl.for_env(make_env(), name="reach3", aligned="0:3", goal="3:6", max_change=0.05,
                           success_radius=radius)
    return make_env, decl
