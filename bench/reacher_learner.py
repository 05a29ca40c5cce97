"""A sync A2C `saver learner` on Reacher-v5 for the Python actor benches
(python_actor_speed.py, python_actor_profile.py): its config in a fresh folder, a free
loopback port, the process and the URL actors connect to."""
import os
import socket
import subprocess
import tempfile


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
