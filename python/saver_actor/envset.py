"""The E envs an actor steps: in its own process, one after another (`LocalEnvs`), or
spread over worker processes that step their shares at the same time
(`ProcessEnvs`, `saver-actor act --env-processes N`), for envs whose step costs more
than the actor's own work per step. Both step every env with one call and reset the
envs the caller names; neither resets on its own (the actor decides when an episode
ends: at its goal or at the run's step limit).
"""
from __future__ import annotations

import multiprocessing as mp
import pickle
import traceback
from typing import Any, Callable, List, Optional, Sequence

import numpy as np

from .env import ActionMap


def _own_limit(env) -> Optional[int]:
    return getattr(getattr(env, "spec", None), "max_episode_steps", None)


def _step_all(envs, actions, obs, rewards, terminated, truncated) -> list:
    """Steps envs[i] with actions[i], writing its outcome into row i of obs [k, obs_dim],
    rewards, terminated and truncated [k]; the infos."""
    infos = [None] * len(envs)
    for i, (env, a) in enumerate(zip(envs, actions)):
        o, rewards[i], terminated[i], truncated[i], infos[i] = env.step(a)
        obs[i] = np.asarray(o).reshape(-1)
    return infos


def _reset(env, seed: Optional[int]) -> np.ndarray:
    o, _ = env.reset() if seed is None else env.reset(seed=int(seed))
    return np.asarray(o, dtype=np.float64).reshape(-1)


class LocalEnvs:
    """n instances of make_env() in this process, taking the agent's actions of
    `continuous` values then `action_dim - continuous` one-hot choice entries."""

    def __init__(self, make_env: Callable, n: int, obs_dim: int, continuous: int, action_dim: int):
        self.envs = [make_env() for _ in range(n)]
        self.action_space = self.envs[0].action_space
        self.limits = [_own_limit(e) for e in self.envs]
        self._map = ActionMap(continuous, action_dim, self.action_space)
        self._out = (np.empty((n, obs_dim)), np.empty(n), np.empty(n, dtype=bool), np.empty(n, dtype=bool))

    def step(self, actions: np.ndarray):
        """Steps every env with the agent's actions [E, action_dim] (as the env takes
        them: ActionMap): (next obs [E, obs_dim], rewards, terminated, truncated, infos);
        the arrays are reused by the next call."""
        return (*self._out, _step_all(self.envs, self._map(np.asarray(actions)), *self._out))

    def reset(self, indices: Sequence[int], seeds: Sequence[Optional[int]]) -> List[np.ndarray]:
        """Resets the envs at `indices` (each with its seed, or none); their observations."""
        return [_reset(self.envs[i], s) for i, s in zip(indices, seeds)]

    def close(self):
        for e in self.envs:
            e.close()


def _layout(n: int, obs_dim: int, action_dim: int) -> dict:
    """The step's arrays that the actor and its workers share: name -> (shape, dtype)."""
    return {"act": ((n, action_dim), np.float32), "obs": ((n, obs_dim), np.float64), "rew": ((n,), np.float64),
            "term": ((n,), np.bool_), "trunc": ((n,), np.bool_)}


def _views(buffers: dict, layout: dict) -> dict:
    return {k: np.frombuffer(buffers[k], dtype=dtype).reshape(shape) for k, (shape, dtype) in layout.items()}


# Worker messages, raw bytes: b"s" step (the actions are in the shared array), b"r" +
# pickled [(env, seed)] reset, b"c" close. Answers: b"k" + the pickled result (a
# step's infos, when asked for, else nothing), or b"e" + a traceback.
def _worker(conn, make_env: Callable, lo: int, hi: int, buffers: dict, layout: dict, continuous: int,
            want_infos: bool):
    """A worker process: envs lo..hi, stepped and reset on the actor's word."""
    try:
        envs = [make_env() for _ in range(hi - lo)]
        conn.send((envs[0].action_space, [_own_limit(e) for e in envs]))
        to_env = ActionMap(continuous, layout["act"][0][1], envs[0].action_space)
        v = {k: a[lo:hi] for k, a in _views(buffers, layout).items()}
    except BaseException:
        conn.send(traceback.format_exc())
        return
    while True:
        try:
            msg = conn.recv_bytes()
        except (EOFError, KeyboardInterrupt):
            return
        try:
            reply = b""
            if msg == b"s":
                infos = _step_all(envs, to_env(v["act"]), v["obs"], v["rew"], v["term"], v["trunc"])
                reply = pickle.dumps(infos) if want_infos else b""
            elif msg[:1] == b"r":
                reply = pickle.dumps([_reset(envs[i], s) for i, s in pickle.loads(msg[1:])])
            else:
                for e in envs:
                    e.close()
                conn.send_bytes(b"k")
                return
            conn.send_bytes(b"k" + reply)
        except BaseException:
            conn.send_bytes(b"e" + traceback.format_exc().encode())


class EnvWorkerError(RuntimeError):
    """An env raised in a worker process (the message holds its traceback)."""


class ProcessEnvs:
    """n instances of make_env() in `processes` worker processes (env i in worker
    i * processes // n), each stepping its share of one call's actions at the same time.
    The agent's actions (as LocalEnvs takes them; each worker maps its own rows to the
    env's), observations, rewards and flags go through shared memory (a step's messages
    are a byte each way); a step's infos come back (pickled) only when `infos` is true
    (the actor asks for them when the env's declaration computes its vector reward from
    them). On Linux the workers are forked, so make_env may be any
    callable; elsewhere it must pickle (a module-level function)."""

    def __init__(self, make_env: Callable, n: int, obs_dim: int, processes: int, continuous: int,
                 action_dim: int, infos: bool = True):
        if not 1 <= processes <= n:
            raise ValueError(f"env processes must be in 1..={n} (the envs); got {processes}")
        methods = mp.get_all_start_methods()
        ctx: Any = mp.get_context("fork" if "fork" in methods else "spawn")
        layout = _layout(n, obs_dim, action_dim)
        buffers = {k: ctx.RawArray("b", int(np.prod(shape)) * np.dtype(dtype).itemsize)
                   for k, (shape, dtype) in layout.items()}
        self._v = _views(buffers, layout)
        self.n = n
        bounds = [w * n // processes for w in range(processes + 1)]
        self.slices = [slice(bounds[w], bounds[w + 1]) for w in range(processes)]
        self.conns, self.procs = [], []
        for s in self.slices:
            mine, theirs = ctx.Pipe()
            p = ctx.Process(target=_worker, daemon=True,
                            args=(theirs, make_env, s.start, s.stop, buffers, layout, continuous, infos))
            p.start()
            theirs.close()
            self.conns.append(mine)
            self.procs.append(p)
        self.limits: List[Optional[int]] = []
        for c in self.conns:
            try:
                ready = c.recv()
            except EOFError:
                raise EnvWorkerError("an env worker process ended while starting its envs") from None
            if isinstance(ready, str):
                raise EnvWorkerError(f"an env worker process failed while starting its envs:\n{ready}")
            self.action_space, limits = ready
            self.limits.extend(limits)

    def _answers(self, conns, what: str) -> list:
        """Each worker's answer (None for an empty one), read from all of them before a
        failure is raised, so that no answer is left behind for the next call."""
        msgs: List[Optional[bytes]] = []
        for c in conns:
            try:
                msgs.append(c.recv_bytes())
            except EOFError:
                msgs.append(None)
        for m in msgs:
            if m is None:
                raise EnvWorkerError(f"an env worker process ended while {what}")
            if m[:1] == b"e":
                raise EnvWorkerError(f"an env worker process failed while {what}:\n{m[1:].decode()}")
        return [pickle.loads(m[1:]) if m and len(m) > 1 else None for m in msgs]

    def step(self, actions: np.ndarray):
        """As LocalEnvs.step (infos are None unless asked for at construction)."""
        v = self._v
        v["act"][:] = actions
        for c in self.conns:
            c.send_bytes(b"s")
        infos: list = []
        for inf, s in zip(self._answers(self.conns, "stepping"), self.slices):
            infos.extend(inf if inf is not None else [None] * (s.stop - s.start))
        return v["obs"], v["rew"], v["term"], v["trunc"], infos

    def reset(self, indices: Sequence[int], seeds: Sequence[Optional[int]]) -> List[np.ndarray]:
        """As LocalEnvs.reset, one message to each worker that holds one of the envs."""
        asked = []
        for c, s in zip(self.conns, self.slices):
            mine = [(i, seed) for i, seed in zip(indices, seeds) if s.start <= i < s.stop]
            if mine:
                c.send_bytes(b"r" + pickle.dumps([(i - s.start, seed) for i, seed in mine]))
                asked.append((c, mine))
        out: dict = {}
        for (_, mine), obs in zip(asked, self._answers([c for c, _ in asked], "resetting")):
            out.update(zip((i for i, _ in mine), obs))
        return [out[i] for i in indices]

    def close(self):
        for c in self.conns:
            try:
                c.send_bytes(b"c")
            except (BrokenPipeError, OSError):
                pass
        for p in self.procs:
            p.join(5)
            if p.is_alive():
                p.terminate()
