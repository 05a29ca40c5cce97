"""Periodic evaluation of a running learner's policy on the user's own env, keeping
the best weights (what the learner does itself for the preset envs, which it can step):

    saver-actor evaluate --factory mymodule:make --learner URL --out best.safetensors

Every `every` seconds it takes the learner's newest weights (GetWeights), runs
`episodes` deterministic episodes from the same env seeds, appends a row to eval.csv
beside `out`, and writes the weights to `out` (atomically, self-describing, with the
evaluation in nothing but eval.csv) when they returned more than every version before.
It ends after evaluating the final version once the run has finished.
"""
from __future__ import annotations

import os
import time
from typing import Callable, Optional

import grpc
import numpy as np

from ._proto import saver_pb2 as pb
from ._proto import saver_pb2_grpc as pb_grpc
from .actor import Connection
from .enjoy import enjoy
from .env import EnvDecl
from .policy import Policy


def scored_episodes(make_env: Callable, decl: EnvDecl, act: Callable[[np.ndarray], np.ndarray], episodes: int = 50,
                    max_steps: int = 1000) -> dict:
    """Episodes (env seeds 0..episodes-1) of `act` (an observation -> the agent's action,
    before `decl.env_actions`): mean return (the env's own reward) up to success, success
    rate, mean L1 distance |p - g| where the episode ended (at success or its last step),
    and mean "env_return": the env's own return over the whole episode, which goes on
    past success until the env ends it or max_steps (Reacher-v5's 50 steps: the return
    its peers report). Shared by the tests and the benchmarks, for our policies and
    other libraries' alike."""
    env = make_env()
    returns, full, successes, dist = [], [], 0, []
    for ep in range(episodes):
        o, _ = env.reset(seed=ep)
        total, whole, success, end = 0.0, 0.0, False, None
        for _ in range(max_steps):
            a = act(np.asarray(o, dtype=np.float32))
            prev = o
            o, r, term, trunc, info = env.step(decl.env_actions(np.asarray(a)[None], env.action_space)[0])
            whole += float(r)
            if end is None:
                total += float(r)
                success = bool(decl.outcome(np.asarray(prev)[None], np.asarray(o)[None], [r], [term], [info],
                                            check=False)[2][0])
                if success:
                    end = o
            if term or trunc:
                break
        successes += success
        end = o if end is None else end
        g = 0.0 if decl.goal is None else np.asarray(end)[decl.goal]
        dist.append(float(np.abs(np.asarray(end)[decl.aligned] - g).sum()))
        returns.append(total)
        full.append(whole)
    env.close()
    return {"return": float(np.mean(returns)), "success": successes / episodes, "distance": float(np.mean(dist)),
            "env_return": float(np.mean(full))}


def keep_best(make_env: Callable, decl: EnvDecl, conn: Connection, out: str, every: float = 60.0,
              episodes: int = 10, max_steps: int = 1000, seed: int = 0,
              log: Callable[[str], None] = print) -> Optional[float]:
    """Evaluates the learner's newest weights every `every` seconds until its run has
    finished; returns the best mean return (None if no version was evaluated)."""
    csv_path = os.path.join(os.path.dirname(os.path.abspath(out)), "eval.csv")
    best: Optional[float] = None
    last = -1
    with conn.channel() as ch:
        stub = pb_grpc.LearnerStub(ch)
        while True:
            status = stub.Status(pb.StatusRequest(), metadata=conn.metadata(), timeout=30)
            try:
                w = stub.GetWeights(pb.WeightsRequest(min_version=0), metadata=conn.metadata(), timeout=60)
            except grpc.RpcError as e:
                raise RuntimeError(f"the learner at {conn.url}: {e.details()}") from None
            if w.version != last:
                last = w.version
                r = enjoy(make_env, decl, Policy.load(w.safetensors), episodes=episodes, max_steps=max_steps,
                          seed=seed)
                better = best is None or r.mean_return > best
                if better:
                    best = r.mean_return
                    tmp = f"{out}.tmp"
                    with open(tmp, "wb") as f:
                        f.write(w.safetensors)
                    os.replace(tmp, out)
                new = not os.path.exists(csv_path)
                with open(csv_path, "a") as f:
                    if new:
                        f.write("steps,version,episodes,mean_return,success_rate,best\n")
                    f.write(f"{status.steps},{w.version},{episodes},{r.mean_return},{r.success_rate},{int(better)}\n")
                log(f"version {w.version} ({status.steps} steps): mean return {r.mean_return:.3f}, success rate "
                    f"{r.success_rate:.2f}{' (best so far: ' + out + ')' if better else ''}")
            if status.finished:
                return best
            time.sleep(every)
