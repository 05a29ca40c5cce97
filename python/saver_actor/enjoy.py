"""Watches a trained policy act in the user's env: deterministic (or sampled) episodes
with `Policy.predict`, each episode's return, length and success, and optionally a
video of them (imageio; mp4 needs imageio-ffmpeg, a .gif needs only pillow:
`pip install "saver-actor[video]"`).

    saver-actor enjoy --factory mymodule:make --weights runs/.../best.safetensors --video out.mp4
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, List, Optional

import numpy as np

from .env import EnvDecl, EnvError
from .policy import Policy


@dataclass
class EpisodeResult:
    ret: float
    length: int
    success: bool


@dataclass
class EnjoyReport:
    episodes: List[EpisodeResult] = field(default_factory=list)
    frames: int = 0

    @property
    def mean_return(self) -> float:
        return float(np.mean([e.ret for e in self.episodes])) if self.episodes else float("nan")

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else float("nan")


def _make(make_env: Callable, render: bool) -> Any:
    """An env, asked for rgb_array frames when `render` (a factory that takes
    render_mode gets it; otherwise the env must already render them)."""
    if not render:
        return make_env()
    try:
        takes = "render_mode" in inspect.signature(make_env).parameters
    except (TypeError, ValueError):
        takes = False
    env = make_env(render_mode="rgb_array") if takes else make_env()
    if getattr(env, "render_mode", None) != "rgb_array":
        raise EnvError("the env renders no rgb_array frames: let the factory's make_env take render_mode "
                       "(make_env(render_mode='rgb_array')) and pass it to the env or gym.make")
    return env


def enjoy(make_env: Callable, decl: EnvDecl, policy: Policy, episodes: int = 5, deterministic: bool = True,
          seed: int = 0, max_steps: int = 1000, video: Optional[str] = None, fps: int = 30) -> EnjoyReport:
    """Runs `episodes` episodes (env seeds seed, seed + 1, ...) of `policy` in a fresh
    env and, with `video`, writes their frames there. Success is the declaration's
    (success_radius, or the env's terminated)."""
    if policy.layout.obs_dim != decl.obs_dim or policy.layout.continuous != decl.continuous \
            or policy.layout.choices != decl.choices:
        raise EnvError(f"the policy acts in a layout ({policy.layout.obs_dim} observation entries, "
                       f"{policy.layout.continuous} continuous, {policy.layout.choices} choices) that is not the "
                       f"env's {decl.name}")
    writer = None
    if video is not None:
        try:
            import imageio.v2 as imageio
        except ImportError:
            raise EnvError('a video needs imageio: pip install "saver-actor[video]"') from None
        kw = {"fps": fps} if not video.endswith(".gif") else {"duration": 1.0 / fps}
        writer = imageio.get_writer(video, **kw)
    env = _make(make_env, writer is not None)
    rng = np.random.default_rng(seed)
    report = EnjoyReport()
    try:
        for k in range(episodes):
            o, _ = env.reset(seed=seed + k)
            total, success, steps = 0.0, False, 0
            while True:
                if writer is not None:
                    writer.append_data(np.asarray(env.render()))
                    report.frames += 1
                a, _ = policy.predict(np.asarray(o, dtype=np.float32), deterministic=deterministic, rng=rng)
                prev = o
                o, r, term, trunc, info = env.step(decl.env_actions(a[None], env.action_space)[0])
                total += float(r)
                steps += 1
                success = bool(decl.outcome(np.asarray(prev, dtype=np.float64)[None],
                                            np.asarray(o, dtype=np.float64)[None], [r], [term], [info],
                                            check=False)[2][0])
                if success or term or trunc or steps >= max_steps:
                    break
            if writer is not None:
                writer.append_data(np.asarray(env.render()))
                report.frames += 1
            report.episodes.append(EpisodeResult(total, steps, success))
    finally:
        env.close()
        if writer is not None:
            writer.close()
    return report
