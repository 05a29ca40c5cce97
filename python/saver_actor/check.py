"""Checks an env against its declaration before a long run (as SB3's env_checker):
a few hundred steps of random actions, each one held to what the actor and the
learner will hold it to, with a report of what the declaration leaves loose.

    saver-actor check --factory mymodule:make [--steps 500]
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, List

import numpy as np

from .env import EnvDecl, EnvError


@dataclass
class CheckReport:
    """What a check saw: the steps and episodes it ran, the largest one-step change
    of each aligned entry, the range and spread (standard deviation) of each
    observation entry (under random actions: where entries differ much in scale,
    docs/GUIDE.md says when `--saver-obs-norm aligned` or `running` helps), warnings
    (things that will not stop a run but probably are not what was meant) and notes
    (options the spreads suggest)."""

    steps: int = 0
    episodes: int = 0
    successes: int = 0
    largest_change: Any = None  # [d]
    obs_min: Any = None  # [obs_dim]
    obs_max: Any = None
    obs_std: Any = None  # [obs_dim], over every observation seen (resets included)
    warnings: List[str] = field(default_factory=list)
    notes: List[str] = field(default_factory=list)

    def text(self, decl: EnvDecl) -> str:
        lines = [f"{decl.name}: {self.steps} random steps, {self.episodes} episodes ended "
                 f"({self.successes} successes); every check passed"]
        change = ", ".join(f"{v:.3g}" for v in self.largest_change)
        lines.append(f"  largest one-step change of p: [{change}] (declared max_change {decl.max_change:g})")
        spread = ", ".join(f"{v:.3g}" for v in self.obs_std)
        lines.append(f"  spread (std) of each observation entry: [{spread}]")
        lines += [f"  warning: {w}" for w in self.warnings]
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def _spaces(env, decl: EnvDecl) -> None:
    import gymnasium as gym

    a, o = env.action_space, env.observation_space
    if isinstance(a, gym.spaces.Box):
        if decl.choices or int(np.prod(a.shape)) != decl.continuous:
            raise EnvError(f"{decl.name}: the action space {a} has {int(np.prod(a.shape))} values; the declaration "
                           f"says {decl.continuous} continuous and {decl.choices} choices")
    elif isinstance(a, gym.spaces.Discrete):
        if decl.continuous or int(a.n) != decl.choices:
            raise EnvError(f"{decl.name}: the action space {a} has {int(a.n)} choices; the declaration says "
                           f"{decl.continuous} continuous and {decl.choices} choices")
    else:
        raise EnvError(f"{decl.name}: action space {a} is neither a Box nor a Discrete")
    if not isinstance(o, gym.spaces.Box) or int(np.prod(o.shape)) != decl.obs_dim:
        raise EnvError(f"{decl.name}: the observation space {o} is not a flat Box of the {decl.obs_dim} "
                       f"declared entries")


def check_env(make_env: Callable, decl: EnvDecl, steps: int = 500, seed: int = 0) -> CheckReport:
    """Steps a fresh env from `make_env` with uniformly random actions for `steps`
    steps, raising EnvError at the first thing the actor or the learner would refuse:
    spaces that are not the declared layout, an observation outside its bounds, a
    change of p or a vector reward beyond max_change, an episode that ends before its
    step limit without success. Returns what it saw (CheckReport)."""
    if steps < 1:
        raise ValueError(f"steps {steps} must be >= 1")
    env = make_env()
    rng = np.random.default_rng(seed)
    _spaces(env, decl)
    r = CheckReport(largest_change=np.zeros(decl.dim), obs_min=np.full(decl.obs_dim, np.inf),
                    obs_max=np.full(decl.obs_dim, -np.inf))
    c, ch = decl.continuous, decl.choices
    seen = []  # every observation, for the entries' spreads
    try:
        o, _ = env.reset(seed=seed)
        obs = np.asarray(o, dtype=np.float64).reshape(-1)
        decl.check_obs(obs, "reset")
        seen.append(obs)
        for _ in range(steps):
            action = np.zeros(c + ch, dtype=np.float32)
            action[:c] = rng.uniform(-1.0, 1.0, c)
            if ch:
                action[c + rng.integers(ch)] = 1.0
            nxt, reward, terminated, truncated, info = env.step(decl.env_actions(action[None], env.action_space)[0])
            nxt = np.asarray(nxt, dtype=np.float64).reshape(-1)
            where = f"step {r.steps} (episode {r.episodes})"
            decl.check_obs(nxt, where)
            delta, vr, success = decl.outcome(obs[None], nxt[None], [reward], [terminated], [info], check=False)
            decl.check_steps(delta, vr, where)
            r.steps += 1
            r.largest_change = np.maximum(r.largest_change, np.abs(delta[0]))
            r.obs_min, r.obs_max = np.minimum(r.obs_min, nxt), np.maximum(r.obs_max, nxt)
            seen.append(nxt)
            if terminated and not success[0]:
                raise EnvError(f"{decl.name}: {where}: the env ended the episode (terminated) without success; a "
                               f"SAVER episode ends at the goal or at the step limit: declare success_radius so that "
                               f"this end is a success, or drop the termination")
            if success[0] or terminated or truncated:
                r.episodes += 1
                r.successes += int(success[0])
                o, _ = env.reset()
                obs = np.asarray(o, dtype=np.float64).reshape(-1)
                decl.check_obs(obs, "reset")
                seen.append(obs)
            else:
                obs = nxt
    finally:
        env.close()
    r.obs_std = np.std(np.array(seen), axis=0)
    _loose(decl, r)
    _narrow_position(decl, r)
    return r


# p spreads less than this share of the widest other entry: the note on
# `--saver-obs-norm aligned` (the learner's `auto` uses the same share, NARROW_POSITION in
# core/src/algo/saver/obs_scale.rs; results/env-return/README.md, "where the observation
# scale acts").
NARROW_POSITION = 1 / 3


def _narrow_position(decl: EnvDecl, r: CheckReport) -> None:
    """A note when the aligned position p spreads much less than some entry outside p
    and the goal: the agent then reads p, what it has to steer, at a fraction of its
    other inputs' scale. Measured with this check's 500 steps (seeds 0-2): Reacher-v5's
    fingertip offset 0.18-0.22 of its joint cosines (`aligned` took its 200 k-step
    success from 0.76 to 0.94), the point masses 2.5-3.3 and reach3 1.0 (`aligned`
    cost them)."""
    p = list(range(decl.aligned.start, decl.aligned.stop))
    g = list(range(decl.goal.start, decl.goal.stop)) if decl.goal is not None else []
    other = [k for k in range(decl.obs_dim) if k not in p and k not in g]
    if not other:
        return
    widest = max(other, key=lambda k: r.obs_std[k])
    ratio = float(np.max(r.obs_std[p])) / max(float(r.obs_std[widest]), 1e-12)
    if ratio < NARROW_POSITION:
        r.notes.append(f"p spreads {float(np.max(r.obs_std[p])):.3g} at most, {ratio:.2f} of entry {widest}'s "
                       f"{float(r.obs_std[widest]):.3g}: SAVER's default (`--saver-obs-norm auto`) reads p (and g) "
                       f"at unit spread where its first batch finds the same, `--saver-obs-norm aligned` always "
                       f"(docs/GUIDE.md, 'Bring your own environment')")


def _loose(decl: EnvDecl, r: CheckReport) -> None:
    """Warnings: a max_change far above what the steps showed (the PCPN's targets and
    the learner's checks are scaled by it), observation entries that never moved."""
    seen = float(np.max(r.largest_change))
    if seen < 0.1 * decl.max_change:
        r.warnings.append(f"p never changed by more than {seen:.3g} in a step, under a tenth of the declared "
                          f"max_change {decl.max_change:g}: a tighter max_change lets the learner check more")
    still = [k for k in range(decl.obs_dim) if r.obs_max[k] == r.obs_min[k]]
    moving_aligned = [k for k in range(decl.aligned.start, decl.aligned.stop) if k in still]
    if moving_aligned:
        r.warnings.append(f"aligned entries {moving_aligned} never changed under random actions")
