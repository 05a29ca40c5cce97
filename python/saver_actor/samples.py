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
from typing import Callable, Optional

import grpc
import numpy as np

from ._proto import saver_pb2 as pb
from ._proto import saver_pb2_grpc as pb_grpc
from .actor import Connection
from .env import EnvDecl

BATCH = 1024  # samples per SampleBatch message


class Walker:
    """Draws walk samples from one env."""

    def __init__(self, env, decl: EnvDecl, seed: int, walk_steps: int):
        self.env, self.decl, self.walk_steps = env, decl, walk_steps
        self.rng = np.random.default_rng(seed)
        self.obs: Optional[np.ndarray] = None
        self.steps = 0

    def _reset(self):
        o, _ = self.env.reset(seed=int(self.rng.integers(1 << 62)))
        self.obs = np.asarray(o, dtype=np.float64).reshape(-1)
        self.decl.check_obs(self.obs, "reset")
        self.steps = 0

    def draw(self, n: int):
        d = self.decl
        c, ch = d.continuous, d.choices
        obs = np.empty((n, d.obs_dim), dtype=np.float32)
        mu = self.rng.uniform(-1.0, 1.0, (n, c + ch)).astype(np.float32)
        sigma = self.rng.random((n, c)).astype(np.float32)
        log_std = np.log(sigma + np.float32(1e-10)).astype(np.float32)
        delta = np.empty((n, d.dim), dtype=np.float32)
        for k in range(n):
            if self.obs is None:
                self._reset()
            action = np.zeros(c + ch, dtype=np.float32)
            action[:c] = mu[k, :c] + sigma[k] * self.rng.standard_normal(c)
            if ch:
                logits = mu[k, c:]
                p = np.exp(logits - logits.max())
                action[c + self.rng.choice(ch, p=p / p.sum())] = 1.0
            nxt, reward, terminated, truncated, info = self.env.step(
                d.env_actions(action[None], self.env.action_space)[0])
            nxt = np.asarray(nxt, dtype=np.float64).reshape(-1)
            d.check_obs(nxt, "a sample step")
            assert self.obs is not None
            dl, _, success = d.outcome(self.obs[None], nxt[None], [reward], [terminated], [info])
            obs[k], delta[k] = self.obs, dl[0]
            self.steps += 1
            self.obs = nxt
            if success[0] or terminated or truncated or self.steps >= self.walk_steps:
                self.obs = None
        return obs, mu, log_std, delta


def provide_samples(make_env: Callable, decl: EnvDecl, conn: Connection, seed: int = 0,
                    walk_steps: int = 1000, stop: Optional[threading.Event] = None,
                    log: Callable = print) -> int:
    """Answers the store's demands for samples of `decl`'s env until the store closes
    the call or `stop` is set (reconnecting while the store is unreachable); returns
    the number of samples sent."""
    stop = stop or threading.Event()
    walker = Walker(make_env(), decl, seed, walk_steps)
    sent = 0
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
            log(f"sample provider: {e.code().name}: {e.details()}; retrying in 1 s")
            stop.wait(1.0)
    return sent
