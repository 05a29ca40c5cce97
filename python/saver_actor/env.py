"""What a user declares of an environment: which observation entries are the
state-aligned position p (and, optionally, the goal g), the bounds of every
observation entry and of one step's change of p, and when an episode succeeds.

From it come the vector reward r_j = |p_j - g_j| - |p'_j - g_j| (or the user's own),
the state change p' - p that SAVER's PCPN predicts, and the env spec the learner checks
the actor against (saver.proto EnvSpec).
"""
from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence, Union

import numpy as np

from ._proto import saver_pb2 as pb


# Values this close past a bound still pass (the learner's rounding slack).
def _slack(b: float) -> float:
    return abs(b) * 1e-5 + 1e-6


class EnvError(ValueError):
    """An environment does not do what its declaration says."""


def factory_function(spec: str) -> Callable[[], tuple]:
    """The function named by a factory "module:function" (`--factory`), which returns
    (make_env, EnvDecl) when called; a ValueError says what is wrong with the name. The
    module is imported as Python finds it (sys.path)."""
    mod, _, fn = spec.partition(":")
    if not mod or not fn:
        raise ValueError(f"--factory {spec!r}: expected module:function")
    try:
        module = importlib.import_module(mod)
    except ModuleNotFoundError as e:
        raise ValueError(f"--factory {spec!r}: {e} (run from the folder that holds it, or set PYTHONPATH)") from e
    if not hasattr(module, fn):
        raise ValueError(f"--factory {spec!r}: {mod} has no {fn}")
    return getattr(module, fn)


# The largest env reward per step a learner takes (core/src/limits.rs MAX_ENV_REWARD).
MAX_ENV_REWARD = 1e9


def check_env_rewards(name: str, rewards: np.ndarray) -> None:
    """Refuses env rewards (any shape) that are not finite or beyond MAX_ENV_REWARD:
    the learner would refuse the rollout."""
    bad = ~(np.abs(rewards) <= MAX_ENV_REWARD)
    if bad.any():
        v = float(rewards.reshape(-1)[int(np.argmax(bad.reshape(-1)))])
        raise EnvError(f"{name}: the env's reward {v!r} is not finite or beyond +-{MAX_ENV_REWARD:g}")


def _as_slice(s, what: str) -> slice:
    if isinstance(s, slice):
        return s
    if isinstance(s, str) and ":" in s:
        a, b = s.split(":")
        return slice(int(a), int(b))
    if isinstance(s, (tuple, list)) and len(s) == 2:
        return slice(int(s[0]), int(s[1]))
    raise EnvError(f"{what}: {s!r} is not a slice of observation entries (e.g. slice(8, 10) or '8:10')")


@dataclass
class EnvDecl:
    """A custom environment as SAVER sees it.

    name: the env's name in the run (letters, digits, '_', '.', '-'; not a preset's).
    obs_low, obs_high: every observation entry's range (finite); an observation
        outside them stops the actor with an error naming the entry.
    aligned: the observation entries that are the state-aligned position p
        (slice or "start:stop"); d = their number = the vector reward's length.
    max_change: the largest |p'_j - p_j| of one step (bounds the vector reward).
    continuous: continuous action dims (agent outputs in [-1, 1] are scaled to the
        env's Box); choices: size of a categorical choice (Discrete), 0 for none.
    goal: the observation entries of the goal g (same length as `aligned`); None when
        p is already relative to the goal (g = 0), as Reacher's fingertip - target.
    success_radius: the episode succeeds (and ends) when every |p'_j - g_j| is below
        it; None: the env's own `terminated` is the success.
    vector_reward: optional f(obs, next_obs, env_reward, info) -> array of d, used
        instead of |p - g| - |p' - g| (e.g. MO-Gymnasium's array reward).
    complete_at_success: on the step that ends an episode inside the success box,
        each coordinate's progress reward also gets the rest of its distance,
        |p'_j - g_j| (capped at max_change), so a successful episode is credited the
        whole way to the goal and stopping short of the box costs the whole remainder
        (docs/ALGORITHM.md §7.1); in a run that goes on past success
        (RunSettings.continue_past_success), on the episode's first step into the box
        and where the env itself ends it. None (the default): as the learner's run says
        (RunSettings.complete_at_success; on for SAVER on a custom env), where the env
        declares a success_radius and keeps the default progress reward. True needs
        both; False: never.
    """

    name: str
    obs_low: Union[Sequence[float], np.ndarray]  # an array of float64 after construction
    obs_high: Union[Sequence[float], np.ndarray]
    aligned: slice
    max_change: float
    continuous: int
    choices: int = 0
    goal: Optional[slice] = None
    success_radius: Optional[float] = None
    vector_reward: Optional[Callable] = field(default=None, repr=False)
    complete_at_success: Optional[bool] = None

    def __post_init__(self):
        self.obs_low = np.asarray(self.obs_low, dtype=np.float64)
        self.obs_high = np.asarray(self.obs_high, dtype=np.float64)
        self.aligned = _as_slice(self.aligned, "aligned")
        if self.goal is not None:
            self.goal = _as_slice(self.goal, "goal")
        n = len(self.obs_low)
        if len(self.obs_high) != n or n == 0:
            raise EnvError(f"{self.name}: obs_low has {n} entries and obs_high {len(self.obs_high)}")
        bad = [k for k in range(n) if not (math.isfinite(self.obs_low[k]) and math.isfinite(self.obs_high[k])
                                           and self.obs_low[k] <= self.obs_high[k])]
        if bad:
            k = bad[0]
            raise EnvError(
                f"{self.name}: observation entries {bad} have no finite bounds (entry {k}: "
                f"[{self.obs_low[k]}, {self.obs_high[k]}]); declare the range each can take")
        a = self.aligned
        if a.step not in (None, 1) or a.start is None or a.stop is None or not (0 <= a.start < a.stop <= n):
            raise EnvError(f"{self.name}: aligned entries {a.start}:{a.stop} are not a non-empty range inside the "
                           f"{n} observation entries")
        if self.goal is not None:
            g = self.goal
            if g.start is None or g.stop is None or g.stop - g.start != self.dim or not (0 <= g.start and g.stop <= n):
                raise EnvError(f"{self.name}: goal entries {g.start}:{g.stop} must be {self.dim} entries inside the "
                               f"observation, as many as the aligned ones")
        if self.success_radius is not None and not (math.isfinite(self.success_radius) and self.success_radius > 0):
            raise EnvError(f"{self.name}: success_radius {self.success_radius} must be finite and > 0")
        if self.complete_at_success and not self.can_complete:
            raise EnvError(f"{self.name}: complete_at_success needs a success_radius and the default progress "
                           f"reward (no vector_reward)")
        if not (math.isfinite(self.max_change) and self.max_change > 0):
            raise EnvError(f"{self.name}: max_change {self.max_change} must be finite and > 0")
        if self.continuous < 0 or self.choices < 0 or self.continuous + self.choices == 0:
            raise EnvError(f"{self.name}: the env needs at least one action dim")

    @property
    def can_complete(self) -> bool:
        """Whether the progress reward can be completed at success: a success_radius
        and the default progress reward."""
        return self.success_radius is not None and self.vector_reward is None

    def completes(self, run_asks: bool) -> bool:
        """Whether this env's steps complete the progress at success in a run whose
        settings ask `run_asks` (complete_at_success None follows the run)."""
        if self.complete_at_success is None:
            return run_asks and self.can_complete
        return self.complete_at_success

    @property
    def obs_dim(self) -> int:
        return len(self.obs_low)

    @property
    def dim(self) -> int:
        return self.aligned.stop - self.aligned.start

    @property
    def action_dim(self) -> int:
        return self.continuous + self.choices

    @classmethod
    def for_env(cls, env, name: str, aligned, max_change: float, obs_low=None, obs_high=None, **kw) -> "EnvDecl":
        """A declaration with the action layout and (where finite) the observation bounds
        read from a Gymnasium env's spaces; `obs_low`/`obs_high` override them (needed
        wherever the space is unbounded)."""
        import gymnasium as gym

        space = env.action_space
        if isinstance(space, gym.spaces.Box):
            continuous, choices = int(np.prod(space.shape)), 0
        elif isinstance(space, gym.spaces.Discrete):
            continuous, choices = 0, int(space.n)
        else:
            raise EnvError(f"{name}: action space {space} is neither a Box nor a Discrete")
        ospace = env.observation_space
        if not isinstance(ospace, gym.spaces.Box) or len(ospace.shape) != 1:
            raise EnvError(f"{name}: the observation space {ospace} is not a flat Box")
        low = np.asarray(ospace.low if obs_low is None else obs_low, dtype=np.float64)
        high = np.asarray(ospace.high if obs_high is None else obs_high, dtype=np.float64)
        return cls(name=name, obs_low=low, obs_high=high, aligned=aligned, max_change=max_change,
                   continuous=continuous, choices=choices, **kw)

    # ---- the wire form -------------------------------------------------------------
    def spec(self) -> "pb.EnvSpec":
        """The env as saver.proto's EnvSpec; with a success radius, the success rule the
        learner checks each success flag by."""
        a = self.aligned
        spec = pb.EnvSpec(
            kind=self.name, dim=self.dim,
            layout=pb.EnvLayout(obs_dim=self.obs_dim, continuous=self.continuous, choices=self.choices,
                                aligned_start=a.start, aligned_dim=self.dim),
            bounds=pb.EnvBounds(obs_low=np.asarray(self.obs_low, dtype=np.float32).tolist(),
                                obs_high=np.asarray(self.obs_high, dtype=np.float32).tolist(),
                                max_change=float(np.float32(self.max_change))))
        if self.success_radius is not None:
            spec.success_radius = float(np.float32(self.success_radius))
            if self.goal is not None:
                spec.goal_start = self.goal.start
        return spec

    def check_run(self, run: "pb.EnvSpec") -> None:
        """Refuses a learner whose env is not this one, saying what differs."""
        mine = self.spec()
        if run.kind != mine.kind:
            raise EnvError(f"the learner trains env {run.kind!r}, this actor brings {mine.kind!r}")
        if run.layout != mine.layout:
            raise EnvError(f"env {mine.kind}: the learner's layout {_text(run.layout)} is not this actor's "
                           f"{_text(mine.layout)}")
        if run.bounds != mine.bounds:
            raise EnvError(f"env {mine.kind}: the learner's bounds are not this actor's; copy the actor's "
                           f"declaration (python -m saver_actor describe ...) into the learner's config")
        # A rule only one side declares is no conflict (the learner checks by its own).
        if run.success_radius and mine.success_radius and (
                run.success_radius != mine.success_radius or run.HasField("goal_start") != mine.HasField("goal_start")
                or run.goal_start != mine.goal_start):
            raise EnvError(f"env {mine.kind}: the learner's success rule (radius {run.success_radius}) is not this "
                           f"actor's (radius {mine.success_radius}); copy the actor's declaration into the "
                           f"learner's config")

    def toml(self) -> str:
        """The learner's `[env]` section for this env (saver learner --config FILE)."""
        f = lambda v: np.format_float_positional(np.float32(v), unique=True, trim="0")  # noqa: E731
        low = ", ".join(f(v) for v in self.obs_low)
        high = ", ".join(f(v) for v in self.obs_high)
        return (f'[env]\nname = "{self.name}"\n\n[env.layout]\nobs_dim = {self.obs_dim}\n'
                f"continuous = {self.continuous}\nchoices = {self.choices}\n"
                f"aligned_start = {self.aligned.start}\naligned_dim = {self.dim}\n\n"
                f"[env.bounds]\nobs_low = [{low}]\nobs_high = [{high}]\nmax_change = {f(self.max_change)}\n"
                + self._success_toml(f))

    def _success_toml(self, f) -> str:
        if self.success_radius is None:
            return ""
        goal = "" if self.goal is None else f"goal_start = {self.goal.start}\n"
        return f"\n[env.success]\nradius = {f(self.success_radius)}\n{goal}"

    # ---- steps (batched over envs: arrays [E, ...]) -----------------------------------
    def check_obs(self, obs: np.ndarray, where: str) -> None:
        """Refuses observations [E, obs_dim] (or one [obs_dim]) outside the declared bounds."""
        obs = np.asarray(obs)
        if obs.shape[-1:] != (self.obs_dim,):
            raise EnvError(f"{self.name}: {where}: an observation of shape {obs.shape[-1:]}, "
                           f"declared ({self.obs_dim},)")
        lo, hi = self.obs_low, self.obs_high
        out = ~((obs >= lo - np.abs(lo) * 1e-5 - 1e-6) & (obs <= hi + np.abs(hi) * 1e-5 + 1e-6))
        if out.any():
            row = obs.reshape(-1, self.obs_dim)[int(np.argmax(out.reshape(-1, self.obs_dim).any(axis=1)))]
            k = int(np.argmax(out.reshape(-1, self.obs_dim).any(axis=0)))
            raise EnvError(
                f"{self.name}: {where}: observation entry {k} = {float(row[k])!r} is outside its declared bounds "
                f"[{lo[k]}, {hi[k]}]; widen obs_low/obs_high (the learner's config too)")

    def env_actions(self, actions: np.ndarray, space) -> list:
        """The env's action for each of the agent's [E, action_dim] (env_actions)."""
        return env_actions(actions, self.continuous, space)

    def outcome(self, obs, next_obs, rewards, terminated, infos, check=True, complete=None):
        """(state_delta, vector_reward, success) of one step of every env, [E, d] and
        [E]; checked against max_change unless `check` is false (the actor checks a
        whole rollout at once: check_steps). `complete`: whether to complete the
        progress at success, for every env or per env ([E] booleans), None: as
        `completes` says outside a run."""
        a = self.aligned
        p, q = obs[:, a], next_obs[:, a]
        g = 0.0 if self.goal is None else obs[:, self.goal]
        delta = q - p
        left = np.abs(q - g)  # |p' - g|: the progress, the success and the completion
        if self.vector_reward is not None:
            r = np.stack([np.asarray(self.vector_reward(o, n, rw, info), dtype=np.float64).reshape(-1)
                          for o, n, rw, info in zip(obs, next_obs, rewards, infos)])
            if r.shape[1] != self.dim:
                raise EnvError(f"{self.name}: vector_reward gave {r.shape[1]} values for d = {self.dim}")
        else:
            r = np.abs(p - g) - left
        if self.success_radius is not None:
            success = np.max(left, axis=1) < self.success_radius
        else:
            success = np.asarray(terminated, dtype=bool)
        c = self.completes(False) if complete is None else complete
        if np.any(c):
            at = success & np.asarray(c, dtype=bool)
            r = np.where(at[:, None], np.minimum(r + left, self.max_change), r)
        if check:
            self.check_steps(delta, r, "a step")
        return delta, r, success

    def check_steps(self, delta: np.ndarray, r: np.ndarray, where: str) -> None:
        """Refuses state changes or vector rewards (any shape [..., d]) beyond max_change."""
        lim = self.max_change + _slack(self.max_change)
        for what, v in (("moved by", delta), ("has a vector reward of", r)):
            if not np.all(np.abs(v) <= lim):
                flat = np.abs(v).reshape(-1, self.dim)
                k, j = np.unravel_index(int(np.argmax(flat)), flat.shape)
                raise EnvError(f"{self.name}: {where}: aligned entry {self.aligned.start + j} {what} "
                               f"{float(v.reshape(-1, self.dim)[k, j])!r} in one step, beyond the declared "
                               f"max_change {self.max_change}")


def env_actions(actions: np.ndarray, continuous: int, space) -> list:
    """The env's action for each of the agent's actions [E, continuous + choices]: the
    continuous values clipped to [-1, 1] and scaled to the Box; a choice's one-hot (the
    entries after the continuous ones) as its index."""
    actions = np.asarray(actions)
    return ActionMap(continuous, actions.shape[1], space)(actions)


class ActionMap:
    """`env_actions` for one action space, with what the space asks worked out once (an
    actor maps every step's actions with it)."""

    def __init__(self, continuous: int, action_dim: int, space):
        self.c, self.choice = continuous, action_dim > continuous
        if not self.choice:
            self.low, high = space.low.reshape(-1), space.high.reshape(-1)
            self.unit = bool(np.all(self.low == -1.0) and np.all(high == 1.0))
            self.span = high - self.low
            self.dtype, self.shape = space.dtype, space.shape
            self.flat = space.shape == (continuous,)

    def __call__(self, actions: np.ndarray) -> list:
        if self.choice:
            return np.argmax(actions[:, self.c:], axis=1).tolist()
        a = np.clip(actions[:, :self.c], -1.0, 1.0)
        if not self.unit:
            a = self.low + (a + 1.0) * 0.5 * self.span
        a = a.astype(self.dtype, copy=False)
        return list(a) if self.flat else [row.reshape(self.shape) for row in a]


def _text(layout) -> str:
    return (f"(obs_dim {layout.obs_dim}, continuous {layout.continuous}, choices {layout.choices}, "
            f"aligned {layout.aligned_start}:{layout.aligned_start + layout.aligned_dim})")
