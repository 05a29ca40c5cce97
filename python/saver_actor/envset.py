"""The E envs an actor steps: in its own process, one after another (`LocalEnvs`), or
spread over worker processes that step their shares at the same time
(`ProcessEnvs`, `saver-actor act --env-processes N`), for envs whose step costs more
than the actor's own work per step. Both step every env with one call and reset the
envs the caller names; neither resets on its own (the actor decides when an episode
ends: at its goal or at the run's step limit).
"""
from __future__ import annotations

import multiprocessing as mp
import traceback
from typing import Any, Callable, List, Optional, Sequence

import numpy as np


def _own_limit(env) -> Optional[int]:
    return getattr(getattr(env, "spec", None), "max_episode_steps", None)


def _step_all(envs, actions, obs_out):
    """Steps envs[i] with actions[i]; observations go into obs_out [k, obs_dim]."""
    k = len(envs)
    rewards = np.empty(k)
    terminated = np.empty(k, dtype=bool)
    truncated = np.empty(k, dtype=bool)
    infos = [None] * k
    for i, (env, a) in enumerate(zip(envs, actions)):
        o, rewards[i], terminated[i], truncated[i], infos[i] = env.step(a)
        obs_out[i] = np.asarray(o).reshape(-1)
    return rewards, terminated, truncated, infos


def _reset(env, seed: Optional[int]) -> np.ndarray:
    o, _ = env.reset() if seed is None else env.reset(seed=int(seed))
    return np.asarray(o, dtype=np.float64).reshape(-1)


class LocalEnvs:
    """n instances of make_env() in this process."""

    def __init__(self, make_env: Callable, n: int, obs_dim: int):
        self.envs = [make_env() for _ in range(n)]
        self.action_space = self.envs[0].action_space
        self.limits = [_own_limit(e) for e in self.envs]
        self._obs = np.empty((n, obs_dim))

    def step(self, actions: Sequence):
        """Steps every env: (next obs [E, obs_dim] (reused by the next call), rewards,
        terminated, truncated, infos)."""
        return (self._obs, *_step_all(self.envs, actions, self._obs))

    def reset(self, indices: Sequence[int], seeds: Sequence[Optional[int]]) -> List[np.ndarray]:
        """Resets the envs at `indices` (each with its seed, or none); their observations."""
        return [_reset(self.envs[i], s) for i, s in zip(indices, seeds)]

    def close(self):
        for e in self.envs:
            e.close()


def _worker(conn, make_env: Callable, n: int, obs_dim: int):
    """A worker process: n envs, stepped and reset on the actor's word."""
    try:
        envs = [make_env() for _ in range(n)]
        conn.send(("ready", envs[0].action_space, [_own_limit(e) for e in envs]))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
        return
    obs = np.empty((n, obs_dim))
    while True:
        try:
            cmd, arg = conn.recv()
        except (EOFError, KeyboardInterrupt):
            return
        try:
            reply: object
            if cmd == "step":
                reply = (obs, *_step_all(envs, arg, obs))
            elif cmd == "reset":
                reply = [_reset(envs[i], s) for i, s in arg]
            else:
                for e in envs:
                    e.close()
                conn.send(("ok", None))
                return
            conn.send(("ok", reply))
        except BaseException:
            conn.send(("error", traceback.format_exc()))


class EnvWorkerError(RuntimeError):
    """An env raised in a worker process (the message holds its traceback)."""


class ProcessEnvs:
    """n instances of make_env() in `processes` worker processes (env i in worker
    i * processes // n), each stepping its share of one call's actions at the same time.
    On Linux the workers are forked, so make_env may be any callable; elsewhere it must
    pickle (a module-level function)."""

    def __init__(self, make_env: Callable, n: int, obs_dim: int, processes: int):
        if not 1 <= processes <= n:
            raise ValueError(f"env processes must be in 1..={n} (the envs); got {processes}")
        methods = mp.get_all_start_methods()
        ctx: Any = mp.get_context("fork" if "fork" in methods else "spawn")
        bounds = [w * n // processes for w in range(processes + 1)]
        self.slices = [slice(bounds[w], bounds[w + 1]) for w in range(processes)]
        self.conns, self.procs = [], []
        for s in self.slices:
            mine, theirs = ctx.Pipe()
            p = ctx.Process(target=_worker, args=(theirs, make_env, s.stop - s.start, obs_dim), daemon=True)
            p.start()
            theirs.close()
            self.conns.append(mine)
            self.procs.append(p)
        self.limits: List[Optional[int]] = []
        for c in self.conns:
            _, space, limits = self._answer(c, "starting its envs")
            self.action_space = space
            self.limits.extend(limits)
        self._obs = np.empty((n, obs_dim))
        self._rewards = np.empty(n)
        self._terminated = np.empty(n, dtype=bool)
        self._truncated = np.empty(n, dtype=bool)

    def _answer(self, conn, what: str):
        try:
            msg = conn.recv()
        except EOFError:
            raise EnvWorkerError(f"an env worker process ended while {what}") from None
        if msg[0] == "error":
            raise EnvWorkerError(f"an env worker process failed while {what}:\n{msg[1]}")
        return msg

    def step(self, actions: Sequence):
        for c, s in zip(self.conns, self.slices):
            c.send(("step", list(actions[s])))
        infos: list = []
        for c, s in zip(self.conns, self.slices):
            obs, rewards, terminated, truncated, inf = self._answer(c, "stepping")[1]
            self._obs[s], self._rewards[s], self._terminated[s], self._truncated[s] = (
                obs, rewards, terminated, truncated)
            infos.extend(inf)
        return self._obs, self._rewards, self._terminated, self._truncated, infos

    def reset(self, indices: Sequence[int], seeds: Sequence[Optional[int]]) -> List[np.ndarray]:
        """As LocalEnvs.reset, one message to each worker that holds one of the envs."""
        asked = []
        for c, s in zip(self.conns, self.slices):
            mine = [(i, seed) for i, seed in zip(indices, seeds) if s.start <= i < s.stop]
            if mine:
                c.send(("reset", [(i - s.start, seed) for i, seed in mine]))
                asked.append((c, mine))
        out: dict = {}
        for c, mine in asked:
            out.update(zip((i for i, _ in mine), self._answer(c, "resetting")[1]))
        return [out[i] for i in indices]

    def close(self):
        for c in self.conns:
            try:
                c.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for p in self.procs:
            p.join(5)
            if p.is_alive():
                p.terminate()
