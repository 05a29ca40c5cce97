"""What the Python actor benches (python_actor_speed.py, python_actor_profile.py,
python_actor_ceiling.py) share: a sync A2C `saver learner` on Reacher-v5 (its config in
a fresh folder, a free loopback port, the process and the URL actors connect to), and
the bare env's step rate they are measured against."""
import os
import socket
import subprocess
import tempfile
import time

import numpy as np


def bare_rate(make_env, n_envs, steps, draw):
    """Steps/s of n_envs envs stepped in a loop in this process, reset at the end of
    each episode, with actions draw(rng, (n_envs, 2)) (Reacher's two torques)."""
    envs = [make_env() for _ in range(n_envs)]
    for i, e in enumerate(envs):
        e.reset(seed=i)
    rng = np.random.default_rng(0)
    n = steps // n_envs
    t = time.perf_counter()
    for _ in range(n):
        acts = draw(rng, (n_envs, 2)).astype(np.float32)
        for e, a in zip(envs, acts):
            _, _, term, trunc, _ = e.step(a)
            if term or trunc:
                e.reset()
    return n * n_envs / (time.perf_counter() - t)


def policy_actions(rng, shape):
    """The untrained policy's actions: N(0, 1) clipped to [-1, 1] (the actors' Gaussian
    at mu ~ 0, log sigma 0)."""
    return np.clip(rng.standard_normal(shape), -1, 1)


def start(saver, decl, actors, steps, prefix):
    """(learner process, URL) of a learner that waits for `actors` actors and exits
    after `steps` env steps."""
    tmp = tempfile.mkdtemp(prefix=prefix)
    cfg = os.path.join(tmp, "reacher.toml")
    with open(cfg, "w") as f:
        f.write("max_episode_steps = 50\n" + decl.toml())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    learner = subprocess.Popen([saver, "learner", "--config", cfg, "--actors", str(actors), "--steps", str(steps),
                                "--out", os.path.join(tmp, "run"), "--exit-when-done", "--listen",
                                f"127.0.0.1:{port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return learner, f"http://127.0.0.1:{port}"
