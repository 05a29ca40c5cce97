"""A pretraining-sample provider (saver.proto PcpnStore.ProvideSamples): a custom env's
PCPN is pretrained from transitions its actors draw. Each sample is one step of a
random walk from the env's reset: mu ~ U(-1, 1) per action output (choice logits
included), sigma ~ U(0, 1) per continuous dim, a ~ N(mu, sigma^2) (a choice ~
softmax(logits)), recording (obs, mu, log(sigma + 1e-10), p' - p); the walk goes on
from where it lands until the env ends the episode (success, its own end, or the
declaration's `walk_steps`), then resets. The store asks for chunks; this answers
them for as long as the call stays open.
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Callable, Optional

import grpc
import numpy as np

from ._proto import saver_pb2 as pb
from ._proto import saver_pb2_grpc as pb_grpc
from .actor import Connection
from .env import EnvDecl
from .envset import LocalEnvs
from .policy import sample_choices

BATCH = 1024  # samples per SampleBatch message


class Walker:
    """Draws walk samples from `n_envs` instances of the env, stepped together (one
    step of every env per row block: E walks at once, for the Python work of a step is
    shared by all E)."""

    def __init__(self, make_env: Callable, decl: EnvDecl, seed: int, walk_steps: int, n_envs: int = 1):
        if n_envs < 1:
            raise ValueError("n_envs must be >= 1")
        self.decl, self.walk_steps, self.n = decl, walk_steps, n_envs
        self.envs = LocalEnvs(make_env, n_envs, decl.obs_dim, decl.continuous, decl.action_dim)
        self.rng = np.random.default_rng(seed)
        self.obs = np.empty((n_envs, decl.obs_dim), dtype=np.float64)
        self.steps = np.zeros(n_envs, dtype=np.int64)
        self._left: Optional[tuple] = None  # rows drawn beyond the last call's n
        self._reset(range(n_envs))

    def _reset(self, indices):
        indices = list(indices)
        seeds = [int(s) for s in self.rng.integers(1 << 62, size=len(indices))]
        for i, o in zip(indices, self.envs.reset(indices, seeds)):
            self.decl.check_obs(o, "reset")
            self.obs[i] = o
            self.steps[i] = 0

    def _step(self):
        """One step of every env: (obs, mu, log_std, delta) rows [E, ...]."""
        d, e = self.decl, self.n
        c, ch = d.continuous, d.choices
        mu = self.rng.uniform(-1.0, 1.0, (e, c + ch)).astype(np.float32)
        sigma = self.rng.random((e, c)).astype(np.float32)
        log_std = np.log(sigma + np.float32(1e-10)).astype(np.float32)
        action = np.zeros((e, c + ch), dtype=np.float32)
        action[:, :c] = mu[:, :c] + sigma * self.rng.standard_normal((e, c))
        if ch:
            action[np.arange(e), c + sample_choices(mu[:, c:].astype(np.float64), self.rng)] = 1.0
        nxt, rewards, terminated, truncated, infos = self.envs.step(action)
        d.check_obs(nxt, "a sample step")
        obs = self.obs.astype(np.float32)
        delta, _, success = d.outcome(self.obs, nxt, rewards, terminated, infos)
        self.obs[:] = nxt
        self.steps += 1
        ended = np.flatnonzero(success | terminated | truncated | (self.steps >= self.walk_steps))
        if ended.size:
            self._reset(ended)
        return obs, mu, log_std, delta.astype(np.float32)

    def draw(self, n: int):
        """n samples: (obs [n, obs_dim], mu [n, continuous + choices], log_std [n,
        continuous], delta [n, dim]), float32; the walks go on from where the last call
        left them."""
        parts, have = [], 0
        if self._left is not None:
            parts.append(self._left)
            have = len(self._left[0])
        while have < n:
            parts.append(self._step())
            have += self.n
        rows = tuple(np.concatenate(p) for p in zip(*parts))
        self._left = tuple(r[n:] for r in rows) if have > n else None
        return tuple(r[:n] for r in rows)

    def close(self):
        self.envs.close()


class _Progress:
    """The store's count of samples (from its demands), said every `every` seconds
    with the rate and the time left."""

    def __init__(self, log: Callable, name: str, every: float = 10.0):
        self.log, self.name, self.every = log, name, every
        self.first: Optional[tuple] = None  # (time, samples at the store)
        self.said = time.monotonic()

    def demand(self, received: int, total: int, sent: int) -> None:
        now = time.monotonic()
        if self.first is None or received < self.first[1]:
            self.first = (now, received)
        if now - self.said < self.every or total == 0:
            return
        self.said = now
        t0, r0 = self.first
        rate = (received - r0) / max(now - t0, 1e-9)
        eta = f", about {(total - received) / rate:.0f} s left" if rate > 0 else ""
        self.log(f"{self.name}: PCPN samples: {received:,} of {total:,} at the store "
                 f"({100 * received / total:.0f} %, {rate:,.0f}/s{eta}); {sent:,} sent by this actor")


def provide_samples(make_env: Callable, decl: EnvDecl, conn: Connection, seed: int = 0,
                    walk_steps: int = 1000, stop: Optional[threading.Event] = None,
                    log: Callable = print, n_envs: int = 1, name: str = "sample provider",
                    give_up: Optional[float] = None) -> int:
    """Answers the store's demands for samples of `decl`'s env from `n_envs` walks at
    once until the store closes the call or `stop` is set (reconnecting while the
    store is unreachable, for at most `give_up` seconds since it last answered when
    given; saying the store's progress every 10 s); returns the number of samples sent."""
    stop = stop or threading.Event()
    walker = Walker(make_env, decl, seed, walk_steps, n_envs)
    progress = _Progress(log, name)
    sent, said_down, last_contact = 0, False, time.monotonic()
    try:
        while not stop.is_set():
            out: "queue.Queue" = queue.Queue()
            out.put(pb.SampleBatch(env=decl.spec(), n=0))

            def requests(out=out):
                while True:
                    m = out.get()
                    if m is None:
                        return
                    yield m

            try:
                with conn.channel() as channel:
                    call = pb_grpc.PcpnStoreStub(channel).ProvideSamples(requests(), metadata=conn.metadata())
                    for demand in call:
                        said_down, last_contact = False, time.monotonic()
                        progress.demand(demand.samples_received, demand.samples_total, sent)
                        left = demand.count
                        while left > 0:
                            k = min(left, BATCH)
                            o, m, s, dl = walker.draw(k)
                            out.put(pb.SampleBatch(n=k, obs=o.ravel().tolist(), mu=m.ravel().tolist(),
                                                   log_std=s.ravel().tolist(), delta=dl.ravel().tolist()))
                            left -= k
                            sent += k
                        if stop.is_set():
                            break
                    out.put(None)
                    return sent
            except grpc.RpcError as e:
                out.put(None)
                if e.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.UNAUTHENTICATED):
                    raise RuntimeError(f"the PCPN store {conn.url} refused this env's samples: {e.details()}") from None
                if e.code() == grpc.StatusCode.CANCELLED and stop.is_set():
                    return sent
                if give_up is not None and time.monotonic() - last_contact > give_up:
                    why = f"{e.code().name}: {e.details()}"
                    raise RuntimeError(f"no PCPN store answers at {conn.url} for {give_up:.0f} s ({why}; "
                                       "start one with `saver pcpn-trainer`)") from None
                if not said_down:
                    limit = f" for up to {give_up:.0f} s" if give_up is not None else ""
                    log(f"{name}: the PCPN store {conn.url} does not answer ({e.code().name}: {e.details()}); "
                        f"retrying every second{limit} (start it with `saver pcpn-trainer`)")
                    said_down = True
                stop.wait(1.0)
        return sent
    finally:
        walker.close()
