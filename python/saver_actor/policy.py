"""The behaviour policies of a SAVER run in numpy, over the learner's published
weights (safetensors): one forward pass for a batch of observations (one per env).
They follow the `architecture` text each weights file carries and are held to the
Rust actors' policies by tests/python/test_saver_actor.py (through `saver act`).

gaussian-mlp (A2C, SAVER, PPO): mu = MLP(x) with x = obs, or
clip((obs - agent.obs_mean) / agent.obs_std, -b, b) when the weights carry that
observation normaliser (PPO's ppo.obs_norm, SAVER's saver.obs_norm), b = 10, or each
entry's agent.obs_clip where the weights hold it (inf: the entry is not clipped). The
MLP has the run's hidden widths (256-128-64 by
default, ReLU; as many agent.l{i} layers as the weights hold), bounded by
mu_bound * tanh when mu_bound is finite; log_std = clamp(agent.log_std); continuous
action = mu + exp(log_std) * N(0, 1); a choice ~ softmax(logits) as a one-hot.
Payload per step: mu then log_std.

quantile-mlp (QRRL): tau_j ~ U(0, 1) per action dim, action_j = Q_j(tau_j, obs) +
spread * (2 tau_j - 1) with the PCPN-shaped implicit quantile network agent.q.*.
Payload per step: tau.
"""
from __future__ import annotations

import json
import math
import os
import struct
from types import SimpleNamespace
from typing import Any, Optional, Tuple, Union

import numpy as np

MAX_HIDDEN_LAYERS = 8  # the most hidden layers a run may have (the Rust actor's limit)
EMBED = 128  # cosine embedding size of the quantile network


class Gaussian:
    family = "gaussian-mlp"

    def __init__(self, tensors: dict, layout, params: dict):
        self.c, self.ch = layout.continuous, layout.choices
        self.layers: list[tuple[np.ndarray, np.ndarray]] = []
        while f"agent.l{len(self.layers)}.w" in tensors:
            if len(self.layers) == MAX_HIDDEN_LAYERS:
                raise ValueError(f"the weights have more than {MAX_HIDDEN_LAYERS} hidden layers")
            i = len(self.layers)
            w, b = tensors[f"agent.l{i}.w"], tensors[f"agent.l{i}.b"]
            self.layers.append((w.astype(np.float32), b.astype(np.float32)))
        self.hidden = len(self.layers)
        if self.hidden == 0:
            raise ValueError("the weights lack agent.l0.w")
        self.layers.append((tensors["agent.mu.w"].astype(np.float32), tensors["agent.mu.b"].astype(np.float32)))
        fan_in = layout.obs_dim
        for w, b in self.layers:
            if w.ndim != 2 or w.shape[0] != fan_in or b.shape != (w.shape[1],):
                raise ValueError("the weights do not fit the env layout")
            fan_in = w.shape[1]
        if fan_in != self.c + self.ch:
            raise ValueError("the weights do not fit the env layout")
        bound = params.get("mu_bound", math.inf)
        self.mu_bound = None if not math.isfinite(bound) else np.float32(bound)
        lo, hi = params.get("log_std_min", -math.inf), params.get("log_std_max", math.inf)
        log_std = tensors["agent.log_std"].astype(np.float32)
        bounded = math.isfinite(lo) or math.isfinite(hi)
        self.log_std = np.clip(log_std, np.float32(lo), np.float32(hi)) if bounded else log_std
        self.sigma = np.exp(self.log_std)
        self.payload_width = 2 * self.c + self.ch
        self.obs_norm: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None
        if ("agent.obs_mean" in tensors) != ("agent.obs_std" in tensors):
            raise ValueError("the weights hold one of agent.obs_mean and agent.obs_std without the other")
        if "agent.obs_clip" in tensors and "agent.obs_mean" not in tensors:
            raise ValueError("the weights hold agent.obs_clip without agent.obs_mean and agent.obs_std")
        if "agent.obs_mean" in tensors:
            mean = tensors["agent.obs_mean"].astype(np.float32)
            std = tensors["agent.obs_std"].astype(np.float32)
            if mean.shape != (layout.obs_dim,) or std.shape != (layout.obs_dim,):
                raise ValueError("the observation normaliser does not fit the env layout")
            if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std)) and np.all(std > 0)):
                raise ValueError("agent.obs_mean must be finite and agent.obs_std finite and > 0")
            bound = np.full(layout.obs_dim, 10.0, dtype=np.float32)
            if "agent.obs_clip" in tensors:
                bound = tensors["agent.obs_clip"].astype(np.float32)
                if bound.shape != (layout.obs_dim,):
                    raise ValueError("agent.obs_clip does not fit the env layout")
                if not np.all(bound > 0):
                    raise ValueError("agent.obs_clip must be > 0 in every entry (inf: not clipped)")
            self.obs_norm = (mean, std, bound)

    def mean(self, obs: np.ndarray) -> np.ndarray:
        h = np.asarray(obs, dtype=np.float32)
        if self.obs_norm is not None:
            m, s, b = self.obs_norm
            h = np.clip((h - m) / s, -b, b)
        for i, (w, b) in enumerate(self.layers):
            h = h @ w + b
            if i < self.hidden:
                np.maximum(h, 0.0, out=h)
        if self.mu_bound is not None:
            h = self.mu_bound * np.tanh(h)
        return h

    def act(self, obs: np.ndarray, rng: np.random.Generator):
        """Actions [E, c + ch] and payloads [E, mu_dim + c] for observations [E, obs_dim]."""
        mu = self.mean(obs)
        e = mu.shape[0]
        c = self.c
        actions = np.empty((e, c + self.ch), dtype=np.float32)
        actions[:, :c] = mu[:, :c] + self.sigma * rng.standard_normal((e, c), dtype=np.float32)
        if self.ch:
            pick = sample_choices(mu[:, c:], rng)
            actions[:, c:] = 0.0
            actions[np.arange(e), c + pick] = 1.0
        payload = np.concatenate([mu, np.broadcast_to(self.log_std, (e, c))], axis=1)
        return actions, payload

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        mu = self.mean(obs)
        if self.ch:
            pick = np.argmax(mu[:, self.c:], axis=1)
            mu[:, self.c:] = 0.0
            mu[np.arange(mu.shape[0]), self.c + pick] = 1.0
        return mu


def sample_choices(logits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw from softmax(logits) per row [E, K]: the indices [E] (the first whose
    cumulative probability passes a uniform u; one rng.random((E, 1)) call)."""
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    p /= p.sum(axis=1, keepdims=True)
    u = rng.random((logits.shape[0], 1))
    return np.minimum((np.cumsum(p, axis=1) < u).sum(axis=1), logits.shape[1] - 1)


def cosine_embedding(tau: np.ndarray) -> np.ndarray:
    """cos(pi * i * tau) for i = 1..128, [..., 128] (computed in f64, as the Rust side)."""
    i = np.arange(1, EMBED + 1, dtype=np.float64)
    return np.cos(np.pi * i * np.asarray(tau, dtype=np.float64)[..., None]).astype(np.float32)


class Quantile:
    family = "quantile-mlp"

    def __init__(self, tensors: dict, layout, params: dict):
        if layout.choices:
            raise ValueError("the quantile policy acts in continuous dims only")
        self.c = layout.continuous
        t = {k[len("agent.q."):]: v.astype(np.float32) for k, v in tensors.items() if k.startswith("agent.q.")}
        self.w0, self.b0, self.w1, self.b1 = t["l0.w"], t["l0.b"], t["l1.w"], t["l1.b"]
        self.hw0, self.hb0, self.hw1, self.hb1 = t["head.w0"], t["head.b0"], t["head.w1"], t["head.b1"]
        if self.w0.shape[0] != layout.obs_dim or self.hw0.shape[0] != self.c:
            raise ValueError("the weights do not fit the env layout")
        self.spread = np.float32(params.get("spread", 0.0))
        self.payload_width = self.c

    def quantiles(self, obs: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Q_j(tau_j, obs) + spread (2 tau_j - 1): [E, c] for obs [E, obs_dim], tau [E, c]."""
        obs = np.asarray(obs, dtype=np.float32)
        tau = np.asarray(tau, dtype=np.float32)
        h = np.maximum(obs @ self.w0 + self.b0, 0.0)
        z = np.maximum(h @ self.w1 + self.b1, 0.0).reshape(obs.shape[0], self.c, EMBED)
        e = z * cosine_embedding(tau)  # [E, c, 128]
        u = np.maximum(np.einsum("ecm,cmh->ech", e, self.hw0) + self.hb0[:, 0, :], 0.0)  # [E, c, 64]
        q = np.einsum("ech,ch->ec", u, self.hw1[:, :, 0]) + self.hb1[:, 0, 0]
        return (q + self.spread * (2.0 * tau - 1.0)).astype(np.float32)

    def act(self, obs: np.ndarray, rng: np.random.Generator):
        tau = rng.random((np.asarray(obs).shape[0], self.c), dtype=np.float32)
        return self.quantiles(obs, tau), tau

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        return self.quantiles(obs, np.full((np.asarray(obs).shape[0], self.c), 0.5, dtype=np.float32))


FAMILIES = {Gaussian.family: Gaussian, Quantile.family: Quantile}


def policy_for(family: str, tensors: dict, layout, params: dict):
    """The policy of `family` over `tensors` (saver.proto PolicySpec names it)."""
    try:
        cls = FAMILIES[family]
    except KeyError:
        raise ValueError(f"policy family {family!r} is not known to this saver-actor ({', '.join(FAMILIES)})") from None
    return cls(tensors, layout, params)


def _metadata(raw: bytes) -> dict:
    """The `__metadata__` of safetensors bytes (an 8-byte little-endian header length,
    then the JSON header)."""
    if len(raw) < 8:
        raise ValueError("not a safetensors file: shorter than its 8-byte header length")
    (n,) = struct.unpack("<Q", raw[:8])
    if n > len(raw) - 8:
        raise ValueError(f"not a safetensors file: a header of {n} bytes in {len(raw)}")
    try:
        header = json.loads(raw[8:8 + n])
    except ValueError as e:
        raise ValueError(f"not a safetensors file: its header is not JSON ({e})") from None
    return dict(header.get("__metadata__") or {})


class Policy:
    """A trained policy of any SAVER run (A2C, SAVER or QRRL; continuous actions, a
    choice, or both), loaded from the learner's weights and evaluated in numpy.

        policy = Policy.load("runs/.../weights.safetensors")   # or the bytes
        action, _ = policy.predict(obs, deterministic=True)

    The weights file describes itself (format saver-policy/1: the env layout, the
    policy family and its parameters), so nothing else is needed. Actions come in the
    agent's layout: the continuous values clipped to [-1, 1] as the env applies them,
    then the choice as a one-hot; `env_action(action, space)` maps them to a
    Gymnasium env's Box (scaled) or Discrete (an index).
    """

    FORMAT = "saver-policy/1"

    def __init__(self, net: Any, metadata: dict, version: Optional[int] = None):
        self.net = net
        self.metadata = metadata
        self.version = version
        self.layout = SimpleNamespace(**json.loads(metadata["layout"]))

    @classmethod
    def load(cls, source: Union[str, "os.PathLike[str]", bytes]) -> "Policy":
        """A policy from a weights file's path or its bytes (`saver weights --out`,
        a run folder's weights, GetWeights' `safetensors`)."""
        from safetensors.numpy import load as load_safetensors

        if isinstance(source, (bytes, bytearray, memoryview)):
            raw, where = bytes(source), "the weights bytes"
        else:
            where = os.fspath(source)
            with open(where, "rb") as f:
                raw = f.read()
        meta = _metadata(raw)
        if meta.get("format") != cls.FORMAT:
            raise ValueError(f"{where}: not a SAVER policy (format {meta.get('format')!r}, expected {cls.FORMAT!r}); "
                             f"a PCPN or checkpoint file is no policy")
        missing = [k for k in ("layout", "policy_family", "policy_params") if k not in meta]
        if missing:
            raise ValueError(f"{where}: the metadata lacks {', '.join(missing)}")
        layout = SimpleNamespace(**json.loads(meta["layout"]))
        # JSON has no infinity: an unbounded parameter (mu_bound, a log sigma clamp) is null.
        params = {k: (-math.inf if k.endswith("_min") else math.inf) if v is None else v
                  for k, v in json.loads(meta["policy_params"]).items()}
        net = policy_for(meta["policy_family"], load_safetensors(raw), layout, params)
        version = int(meta["version"]) if str(meta.get("version", "")).isdigit() else None
        return cls(net, meta, version)

    @property
    def family(self) -> str:
        return str(self.net.family)

    def predict(self, obs: np.ndarray, deterministic: bool = True,
                rng: Optional[np.random.Generator] = None) -> Tuple[np.ndarray, None]:
        """(actions, None) for one observation [obs_dim] or a batch [N, obs_dim], as
        Stable-Baselines3's predict: deterministic is the policy's mean (a Gaussian's
        mu, the quantile network's median, the most likely choice); otherwise a draw
        from `rng` (default: a fresh generator)."""
        o = np.asarray(obs, dtype=np.float32)
        single = o.ndim == 1
        batch = o[None] if single else o
        if batch.ndim != 2 or batch.shape[1] != self.layout.obs_dim:
            raise ValueError(f"observations of shape {o.shape}; this policy takes [{self.layout.obs_dim}] or "
                             f"[N, {self.layout.obs_dim}]")
        if deterministic:
            a = self.net.deterministic(batch)
        else:
            a, _ = self.net.act(batch, rng if rng is not None else np.random.default_rng())
        a = np.array(a, dtype=np.float32)
        c = self.layout.continuous
        a[:, :c] = np.clip(a[:, :c], -1.0, 1.0)
        return (a[0] if single else a), None

    def env_action(self, action: np.ndarray, space) -> Any:
        """`action` (one, from predict) as a Gymnasium env takes it: a Box's values
        scaled from [-1, 1] to its bounds, a Discrete's index (env.env_actions)."""
        from .env import env_actions

        return env_actions(np.asarray(action, dtype=np.float32)[None], self.layout.continuous, space)[0]
