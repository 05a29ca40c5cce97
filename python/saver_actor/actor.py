"""A SAVER actor over any Gymnasium environment: registers with a learner, steps its
envs with the newest published weights, and streams rollouts (saver.proto), as the
Rust `saver actor` does. Several envs per process (one batched forward pass per
step), sync and async runs, token and TLS, and reconnection with jittered backoff
when the learner is lost.
"""
from __future__ import annotations

import queue
import random
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Callable, List, Optional

import grpc
import numpy as np
from safetensors.numpy import load as load_safetensors
from threadpoolctl import threadpool_limits

from ._proto import saver_pb2 as pb
from ._proto import saver_pb2_grpc as pb_grpc
from .env import EnvDecl, EnvError, check_env_rewards
from .envset import LocalEnvs, ProcessEnvs
from .policy import policy_for

MAX_MESSAGE = 64 << 20


class RunFinished(Exception):
    """The learner's run is over."""


class LinkLost(Exception):
    """The learner went away or forgot this actor: register again."""


class Waiting(Exception):
    """The learner is up but not serving yet: it waits for its PCPN (the message says
    how far that is)."""


class Refused(Exception):
    """The learner refused what this actor sent, for a reason reconnecting does not mend."""


@dataclass
class Connection:
    """Where the learner is and how to reach it: URL (http://host:port, or https://
    with `ca`, the PEM of its CA), and the token its calls need, if any."""

    url: str = "http://127.0.0.1:50051"
    token: Optional[str] = None
    ca: Optional[bytes] = None

    def channel(self) -> grpc.Channel:
        opts = [("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)]
        if self.url.startswith("https://"):
            creds = grpc.ssl_channel_credentials(root_certificates=self.ca)
            return grpc.secure_channel(self.url[len("https://"):], creds, options=opts)
        if self.url.startswith("http://"):
            return grpc.insecure_channel(self.url[len("http://"):], options=opts)
        raise ValueError(f"{self.url!r}: a learner URL starts with http:// or https://")

    def metadata(self, *extra) -> list:
        md = list(extra)
        if self.token:
            md.append(("authorization", f"Bearer {self.token}"))
        return md


@dataclass
class Summary:
    rollouts: int = 0
    steps: int = 0
    episodes: int = 0
    successes: int = 0
    registrations: int = 0
    seconds: float = 0.0
    env_seconds: float = 0.0  # time inside env.step / env.reset
    wait_seconds: float = 0.0  # time waiting for the learner's next weights


WAITING_KEY = "x-saver-waiting"  # trailing metadata of a learner that waits for its PCPN


def _status_error(e: grpc.RpcError, what: str) -> Exception:
    code, msg = e.code(), e.details()
    if code == grpc.StatusCode.UNAVAILABLE:
        try:
            trailers = getattr(e, "trailing_metadata", lambda: ())() or ()
        except Exception:
            trailers = ()
        if any(k == WAITING_KEY for k, _ in trailers):
            return Waiting(msg)
    if code == grpc.StatusCode.OUT_OF_RANGE:
        return RunFinished(msg)
    if code in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.UNAUTHENTICATED,
                grpc.StatusCode.PERMISSION_DENIED, grpc.StatusCode.RESOURCE_EXHAUSTED):
        return Refused(f"{what}: {code.name}: {msg}")
    return LinkLost(f"{what}: {code.name}: {msg}")


class _Weights:
    """The newest weights from WatchWeights, on a thread of its own. It keeps the bytes;
    the actor decodes the version it acts with (a fast learner publishes far more
    versions than an actor uses, and decoding each on this thread would hold the GIL
    the env steps need)."""

    def __init__(self, stub, conn: Connection):
        self.cond = threading.Condition()
        self.latest = None  # (version, safetensors bytes)
        self.error: Optional[Exception] = None
        self.call = stub.WatchWeights(pb.WatchRequest(by_file=False), metadata=conn.metadata())
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            for w in self.call:
                with self.cond:
                    self.latest = (w.version, w.safetensors)
                    self.cond.notify_all()
            err: Exception = LinkLost("the weights stream ended")
        except grpc.RpcError as e:
            err = _status_error(e, "WatchWeights")
        with self.cond:
            self.error = err
            self.cond.notify_all()

    def wait(self, min_version: int, timeout: Optional[float]):
        """The newest weights once their version is >= min_version (or, after `timeout`
        seconds, whatever is newest)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self.cond:
            while self.latest is None or self.latest[0] < min_version:
                if self.error is not None:
                    raise self.error
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    if self.latest is not None:
                        break
                    left = 1.0
                self.cond.wait(left if left is not None else 1.0)
            return self.latest

    def close(self):
        _end(self.call, self.thread)


# Seconds _end waits for a cancelled stream's reader thread to end.
READER_JOIN_S = 10.0


def _end(call, thread: threading.Thread) -> None:
    """Cancels a streaming call and waits for the thread that reads it to see the end.
    A reader left running is a daemon thread that interpreter exit freezes wherever it
    is, possibly inside the call's lock; the call's finaliser then waits on that lock
    forever and the process never exits (seen once in ~30 runs: an actor that had said
    its run finished, hung in grpc's _Rendezvous.__del__)."""
    call.cancel()
    if thread is not threading.current_thread():
        # Bounded, so that a reader grpc never wakes cannot hang the actor.
        thread.join(timeout=READER_JOIN_S)
        if thread.is_alive():
            warnings.warn(f"{thread.name}: the stream's reader is still running {READER_JOIN_S:.0f} s after its "
                          "call was cancelled", RuntimeWarning, stacklevel=2)


class _Rollouts:
    """The StreamRollouts call: rollouts go into a queue its request iterator drains;
    refusals (the only acks asked for) come back on a thread."""

    def __init__(self, stub, conn: Connection, actor_id: int, session: int):
        self.q: "queue.Queue" = queue.Queue(maxsize=4)
        self.error: Optional[Exception] = None
        md = conn.metadata(("x-saver-actor-id", str(actor_id)), ("x-saver-session", str(session)),
                           ("x-saver-acks", "refusals"))
        self.call = stub.StreamRollouts(self._requests(), metadata=md)
        self.thread = threading.Thread(target=self._acks, daemon=True)
        self.thread.start()

    def _requests(self):
        while True:
            r = self.q.get()
            if r is None:
                return
            yield r

    def _acks(self):
        try:
            for ack in self.call:
                if not ack.accepted:
                    code = grpc.StatusCode.INVALID_ARGUMENT
                    for c in grpc.StatusCode:
                        if c.value[0] == ack.code:
                            code = c
                    if code == grpc.StatusCode.FAILED_PRECONDITION:
                        self.error = LinkLost(f"rollout {ack.seq} refused: {ack.error}")
                    elif code == grpc.StatusCode.OUT_OF_RANGE:
                        self.error = RunFinished(ack.error)
                    elif code == grpc.StatusCode.UNAVAILABLE:
                        self.error = LinkLost(f"rollout {ack.seq}: {ack.error}")
                    else:
                        self.error = Refused(f"the learner refused rollout {ack.seq} ({code.name}): {ack.error}")
                    return
            self.error = self.error or LinkLost("the rollout stream ended")
        except grpc.RpcError as e:
            self.error = _status_error(e, "StreamRollouts")

    def send(self, r: "pb.Rollout"):
        while True:
            if self.error is not None:
                raise self.error
            try:
                self.q.put(r, timeout=0.5)
                return
            except queue.Full:
                continue

    def close(self):
        # The end marker must reach grpc's request thread, which may be waiting in
        # _requests for the next rollout: a full queue (the learner stopped reading)
        # gives up its unsent rollouts for it, else that thread would wait forever.
        while True:
            try:
                self.q.put_nowait(None)
                break
            except queue.Full:
                try:
                    self.q.get_nowait()
                except queue.Empty:
                    pass
        _end(self.call, self.thread)


class Actor:
    """Acts for a learner with `n_envs` instances of `make_env()` declared by `decl`.

    `run()` registers, acts until the run finishes (or `stop` is set), reconnecting
    when the learner is lost for up to `give_up` seconds, and returns a Summary.
    """

    def __init__(self, make_env: Callable, decl: EnvDecl, conn: Connection, n_envs: int = 1,
                 name: Optional[str] = None, give_up: float = 600.0, log: Callable = print,
                 env_processes: int = 0):
        if n_envs < 1:
            raise ValueError("n_envs must be >= 1")
        self.make_env, self.decl, self.conn = make_env, decl, conn
        self.n_envs = n_envs
        self.name = name or f"py-actor-{random.getrandbits(24):06x}"
        self.give_up, self.log = give_up, log
        # env_processes > 0: the envs step in that many worker processes at once.
        # (A step's infos cross to the actor only when the declaration's vector reward reads them.)
        self.envs = (ProcessEnvs(make_env, n_envs, decl.obs_dim, env_processes, decl.continuous, decl.action_dim,
                                 infos=decl.vector_reward is not None) if env_processes > 0
                     else LocalEnvs(make_env, n_envs, decl.obs_dim, decl.continuous, decl.action_dim))
        self.stop = threading.Event()
        # Set while this process feeds the PCPN store (the learner waits for that PCPN):
        # the actor does not give up on the learner meanwhile.
        self.feeding = threading.Event()
        self.summary = Summary()

    # ---- one registration ----------------------------------------------------------
    def _register(self, stub):
        reply = stub.Register(pb.RegisterRequest(name=self.name, session=random.getrandbits(63),
                                                 n_envs=self.n_envs, env=self.decl.spec()),
                              metadata=self.conn.metadata(), timeout=30)
        s = reply.settings
        self.decl.check_run(s.env)
        limit = s.max_episode_steps
        for own in self.envs.limits:
            if own is not None and own < limit:
                raise EnvError(
                    f"{self.decl.name}: the env ends its episodes at {own} steps (its TimeLimit) but the run's "
                    f"step limit is {limit}; set max_episode_steps = {own} in the learner's config")
        return reply

    def _session(self, stub) -> None:
        reply = self._register(stub)
        s = reply.settings
        self.summary.registrations += 1
        n, e = s.rollout, self.n_envs
        params = dict(s.policy.params)
        rng = np.random.default_rng([s.seed, 1000 + reply.actor_id])
        complete = self.decl.completes(s.complete_at_success)
        if s.complete_at_success and not complete and self.summary.registrations == 1:
            why = ("sets complete_at_success=False" if self.decl.can_complete
                   else "has no success_radius or a vector_reward of its own")
            self.log(f"{self.name}: the run completes the progress reward at success, but {self.decl.name} {why}: "
                     f"its rewards stay as they are")
        weights = _Weights(stub, self.conn)
        rollouts: Optional[_Rollouts] = None
        try:
            rollouts = _Rollouts(stub, self.conn, reply.actor_id, reply.session)
            # Fresh envs for every registration: the learner counts episodes from seq 0.
            obs = np.stack(self._reset(range(e), s.seed, reply.actor_id))
            running = np.zeros(e, dtype=np.int64)
            returns = np.zeros(e, dtype=np.float32)
            entered = np.zeros(e, dtype=bool)
            want, seq, interval, last = 0, 0, 0.01, None
            policy, policy_version = None, -1
            while not self.stop.is_set():
                timeout = None if s.mode == "sync" or seq == 0 else min(max(2 * interval, 0.002), 0.5)
                t0 = time.monotonic()
                version, raw = weights.wait(want, timeout)
                self.summary.wait_seconds += time.monotonic() - t0
                now = time.monotonic()
                if last is not None and version > last[0]:
                    interval = 0.8 * interval + 0.2 * (now - last[1]) / (version - last[0])
                if last is None or version > last[0]:
                    last = (version, now)
                if policy_version != version:
                    try:
                        tensors = load_safetensors(raw)
                    except Exception as e:
                        raise Refused(f"weights version {version} do not decode: {e}") from None
                    policy = policy_for(s.policy.family, tensors, s.env.layout, params)
                    policy_version = version
                msg, obs = self._collect(policy, rng, obs, running, returns, n, s.max_episode_steps, complete,
                                         entered if s.continue_past_success else None)
                msg.actor_id, msg.session, msg.seq, msg.policy_version = reply.actor_id, reply.session, seq, version
                rollouts.send(msg)
                self.summary.rollouts += 1
                seq += 1
                want = version + 1
        finally:
            if rollouts is not None:
                rollouts.close()
            weights.close()

    def _reset(self, indices, seed: Optional[int] = None, actor_id: int = 0) -> List[np.ndarray]:
        """Resets the envs at `indices`: seeded from (run seed, actor id, i) at a
        registration, from their own streams after that (Gymnasium's way: seed once)."""
        t = time.perf_counter()
        seeds = [None if seed is None else int(np.random.SeedSequence([seed, actor_id, i]).generate_state(1)[0])
                 for i in indices]
        obs = self.envs.reset(indices, seeds)
        self.summary.env_seconds += time.perf_counter() - t
        for o in obs:
            self.decl.check_obs(o, "reset")
        return obs

    def close(self):
        """Closes the envs (and ends their worker processes, if any)."""
        self.envs.close()

    def _collect(self, policy, rng, obs, running, returns, n, limit, complete=False, entered=None):
        """n steps of every env; the rollout message (env-major) and the new observations
        (`complete`: the progress completed at success, EnvDecl.completes; `entered`: in
        a run that goes on past success, RunSettings.continue_past_success, whether each
        env's episode has entered the success box yet, updated here)."""
        past = entered is not None
        d = self.decl
        e = self.n_envs
        o_all = np.empty((e, n + 1, d.obs_dim), dtype=np.float32)
        act_all = np.empty((e, n, d.action_dim), dtype=np.float32)
        pay_all = np.empty((e, n, policy.payload_width), dtype=np.float32)
        delta_all = np.empty((e, n, d.dim), dtype=np.float32)
        rew_all = np.empty((e, n, d.dim), dtype=np.float32)
        env_rew_all = np.empty((e, n), dtype=np.float32)
        done_all = np.zeros((e, n), dtype=bool)
        episodes = [[] for _ in range(e)]
        timeouts = [[] for _ in range(e)]
        env_time = 0.0
        for t in range(n):
            o_all[:, t] = obs
            actions, payload = policy.act(o_all[:, t], rng)
            act_all[:, t], pay_all[:, t] = actions, payload
            t0 = time.perf_counter()
            nxt, rewards, terminated, truncated, infos = self.envs.step(actions)
            env_time += time.perf_counter() - t0
            # Bounds are checked for the whole rollout below (before anything is sent).
            # Past success an episode ends where the env ends it (inside the box) or at the
            # limit, and the progress is completed on its first entry into the box (or
            # where the env ends it there).
            terminated = np.asarray(terminated, dtype=bool)
            delta, r, success = d.outcome(obs, nxt, rewards, terminated, infos, check=False,
                                          complete=complete & (terminated | ~entered) if past else complete)
            ends = success & terminated if past else success
            if past:
                entered |= success
            delta_all[:, t], rew_all[:, t] = delta, r
            env_rew_all[:, t] = rewards
            running += 1
            returns += r.astype(np.float32).sum(axis=1)
            timeout = ~ends & (running >= limit)
            if terminated.any() and (terminated & ~success).any():
                i = int(np.argmax(terminated & ~success))
                raise EnvError(f"{d.name}: the env ended an episode at step {running[i]} without success; SAVER "
                               f"episodes end at the goal or at the step limit (declare success_radius, or make "
                               f"the env terminate only at its goal)")
            if truncated.any() and (truncated & ~ends & ~timeout).any():
                i = int(np.argmax(truncated & ~ends & ~timeout))
                raise EnvError(f"{d.name}: the env truncated its episode at step {running[i]}, before the run's "
                               f"step limit {limit}; set max_episode_steps = {running[i]} in the learner's config")
            done = ends | timeout
            done_all[:, t] = done
            obs[:] = nxt
            if done.any():
                ended = np.flatnonzero(done)
                for i in ended:
                    episodes[i].append(pb.Episode(length=int(running[i]), success=bool(success[i]),
                                                  ret=float(returns[i])))
                    if timeout[i]:
                        d.check_obs(nxt[i], f"step {running[i]} of an episode")
                        timeouts[i].append((i * n + t, nxt[i].astype(np.float32).tolist()))
                    self.summary.episodes += 1
                    self.summary.successes += int(success[i])
                    running[i], returns[i] = 0, 0.0
                    if past:
                        entered[i] = False
                obs[ended] = self._reset(ended)
        o_all[:, n] = obs
        d.check_obs(o_all, "a step")
        d.check_steps(delta_all, rew_all, "a step")
        check_env_rewards(d.name, env_rew_all)
        self.summary.steps += e * n
        self.summary.env_seconds += env_time
        msg = pb.Rollout(
            n_envs=e, n_steps=n, obs=o_all.ravel().tolist(), actions=act_all.ravel().tolist(),
            state_delta=delta_all.ravel().tolist(), vector_reward=rew_all.ravel().tolist(),
            env_reward=env_rew_all.ravel().tolist(),
            done=done_all.ravel().tolist(), payload=pay_all.ravel().tolist(),
            episodes=[ep for eps in episodes for ep in eps],
            timeouts=[k for ts in timeouts for k, _ in ts],
            timeout_obs=[v for ts in timeouts for _, o in ts for v in o])
        return msg, obs

    # ---- the reconnect loop ----------------------------------------------------------
    def run(self) -> Summary:
        # One BLAS thread: the policy's forward pass has E rows, and BLAS's own threads
        # would spin on the cores the envs (and their worker processes) need.
        with threadpool_limits(limits=1, user_api="blas"):
            return self._run()

    def _run(self) -> Summary:
        start = time.monotonic()
        attempt, last_contact, said_waiting = 0, time.monotonic(), 0.0
        try:
            while not self.stop.is_set():
                before = self.summary.rollouts
                try:
                    with self.conn.channel() as channel:
                        self._session(pb_grpc.LearnerStub(channel))
                    return self.summary
                except RunFinished:
                    return self.summary
                except grpc.RpcError as e:
                    err = _status_error(e, "Register")
                    if isinstance(err, RunFinished):
                        return self.summary
                    if isinstance(err, Refused):
                        raise err from None
                    if isinstance(err, Waiting):
                        # The learner answers and waits for its PCPN: no deadline, its
                        # progress said every 10 s.
                        last_contact, attempt = time.monotonic(), 0
                        if last_contact - said_waiting >= 10.0:
                            self.log(f"{self.name}: the learner at {self.conn.url} {err}")
                            said_waiting = last_contact
                        self.stop.wait(2.0)
                        continue
                    why = str(err)
                except LinkLost as e:
                    why = str(e)
                if self.summary.rollouts > before or self.feeding.is_set():
                    attempt, last_contact = 0, time.monotonic()
                if time.monotonic() - last_contact > self.give_up:
                    raise LinkLost(f"{self.name}: no learner at {self.conn.url} for {self.give_up:.0f} s ({why})")
                wait = min(0.1 * 2 ** min(attempt, 6), 5.0) * random.uniform(0.5, 1.0)
                attempt += 1
                if self.summary.registrations == 0 and "UNAVAILABLE" in why:
                    if attempt == 1:
                        gone = "no longer answers" if said_waiting else "serving yet"
                        self.log(f"{self.name}: no learner {gone} at {self.conn.url}; retrying for up to "
                                 f"{self.give_up:.0f} s" + (" (no limit while this actor feeds the PCPN store)"
                                                            if self.feeding.is_set() else ""))
                else:
                    self.log(f"{self.name}: {why}; reconnecting in {wait:.2f} s")
                self.stop.wait(wait)
            return self.summary
        finally:
            self.summary.seconds = time.monotonic() - start
