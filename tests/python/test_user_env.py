#!/usr/bin/env python3
"""A new user's own env, as docs/GUIDE.md "Bring your own environment" tells it:

1. the guide's shell recipes run as written (its `slider.py`, A2C and then SAVER with a
   pcpn-trainer fed by the actors' walks), end to end, into the run folders it names;
   `saver eval` on that custom run points to `saver-actor enjoy`;
2. every waiting state stops on Ctrl-C or SIGTERM, and nothing ends in a Python
   traceback: a learner waiting for a store that has no samples says within 30 s that
   no actor streams them; an actor waits for such a learner past its --connect-timeout;
   an actor given a wrong port, or whose learner exits, ends with one line;
3. a third real env, a goal-reaching arm with a flattened dict observation
   (saver_actor.examples:reach3, the goal in the observation), passes `saver-actor
   check` and trains with SAVER and A2C.

    python3 tests/python/test_user_env.py target/release/saver [NAME FILTER]
"""
import glob
import os
import re
import signal
import subprocess
import sys
import threading
import time

import test_saver_actor as t

GUIDE = os.path.join(t.ROOT, "docs", "GUIDE.md")


def guide_blocks():
    """The code blocks of the guide's "Bring your own environment": [(language, text)]."""
    text = open(GUIDE).read()
    start = text.index("### Bring your own environment")
    section = text[start:text.index("\n### ", start + 1)]
    return re.findall(r"```(\w+)\n(.*?)```", section, re.S)


def user_env():
    """PATH and environment of a user who installed `saver` and `saver-actor`."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([os.path.dirname(t.SAVER), os.path.dirname(sys.executable), env["PATH"]])
    env.pop("PYTHONPATH", None)
    return env


def sh(script, cwd, timeout):
    """Runs a guide block with bash -e in its own process group (killed whole on a
    timeout); returns (exit status, output), the output also in guide-N.log. A block
    that succeeds is read to the end of its output (its background processes included);
    one that fails ends when bash does, its background processes killed (actors that
    wait up to 600 s for a learner that never started would hold the output open)."""
    p = subprocess.Popen(["bash", "-e", "-c", script], cwd=cwd, env=user_env(), stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, start_new_session=True)
    def kill_group():
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    chunks = []
    reader = threading.Thread(target=lambda: chunks.extend(p.stdout), daemon=True)
    reader.start()
    start = time.monotonic()
    try:
        p.wait(timeout=timeout)
        if p.returncode != 0:
            kill_group()
        reader.join(max(timeout - (time.monotonic() - start), 1.0))
        if reader.is_alive():
            raise subprocess.TimeoutExpired(script, timeout)
    except subprocess.TimeoutExpired:
        kill_group()
        reader.join()
        out = "".join(chunks)
        raise AssertionError(f"the block did not end in {timeout} s:\n{script}\n{out[-4000:]}") from None
    finally:
        kill_group()  # what a block left running in the background
    out = "".join(chunks)
    log = os.path.join(cwd, f"guide-{len(glob.glob(os.path.join(cwd, 'guide-*.log')))}.log")
    with open(log, "w") as f:
        f.write(out)
    print(f"  output in {log}")
    return p.returncode, out


def no_traceback(out):
    assert "Traceback" not in out, out[-4000:]


def test_the_guide_recipes_run_as_written():
    blocks = guide_blocks()
    langs = [lang for lang, _ in blocks]
    assert langs[:3] == ["python", "sh", "sh"], langs
    work = os.path.join(t.TMP, "guide")
    os.makedirs(work)
    with open(os.path.join(work, "slider.py"), "w") as f:
        f.write(blocks[0][1])
    # The harness installed the package (.ci/run: pip install ./python) beforehand.
    a2c = "\n".join(line for line in blocks[1][1].splitlines() if not line.startswith("pip install"))
    rc, out = sh(a2c, work, 1200)
    print(out[-1500:])
    assert rc == 0, out[-4000:]
    no_traceback(out)
    runs = glob.glob(os.path.join(work, "runs", "slider-d2-a2c-seed0-*"))
    assert len(runs) == 1, (runs, out[-3000:])
    assert f"Outputs in runs/{os.path.basename(runs[0])}" in out, out[-3000:]
    assert "saver-actor enjoy --factory MODULE:FUNCTION --weights" in out, out[-3000:]
    # enjoy's lines: one per deterministic episode, then the mean.
    assert len(re.findall(r"episode \d+", out)) >= 5, out[-3000:]
    # `saver eval` steps built-in envs only, and says where to go for this one.
    e = subprocess.run([t.SAVER, "eval", runs[0]], capture_output=True, text=True, timeout=60)
    assert e.returncode != 0, e.stdout
    assert "slider-d2 is a custom env" in e.stderr and "saver-actor enjoy --factory" in e.stderr, e.stderr
    assert os.path.join(runs[0], "policy.safetensors") in e.stderr, e.stderr

    rc, out = sh(blocks[2][1], work, 1800)
    print(out[-1500:])
    # The store ends on the recipe's kill (SIGTERM), the rest on their own.
    assert rc == 0, out[-4000:]
    no_traceback(out)
    runs = glob.glob(os.path.join(work, "runs", "slider-d2-saver-seed0-*"))
    assert len(runs) == 1 and os.path.exists(os.path.join(runs[0], "policy.safetensors")), (runs, out[-3000:])
    assert glob.glob(os.path.join(work, "pcpn-cache", "pcpn-slider-d2-*.safetensors")), os.listdir(work)
    # 65,536 walk transitions and 16 held-out batches of 128 (the slider's 8 envs walk
    # them in about a second), then SAVER's 2,500 batches at K 16 on a custom env
    # (a few seconds on 2 cores): the learner names them first, and where the wait passes
    # 10 s the learner's and the store's progress every 10 s says how far they are.
    pcpn = glob.glob(os.path.join(work, "pcpn-cache", "pcpn-slider-d2-*.safetensors"))
    with t.safe_open(pcpn[0], framework="numpy") as f:
        assert f.metadata()["samples"].startswith("67584 transitions streamed by actors"), f.metadata()
    assert re.search(r"waiting for the PCPN of slider-d2 from http://127.0.0.1:50052 \(the store pretrains it "
                     r"first if it has none: 2500 batches x 128, K 16, ", out), out[-4000:]
    if "still waiting for the PCPN" in out:
        assert re.search(r"still waiting for the PCPN from http://127.0.0.1:50052: pretraining slider-d2: "
                         r"(batch \d+ of 2500 \(\d+ %\), \d+ batches/s|\d+ of 67584 samples)", out), out[-4000:]
    assert re.search(r"py-actor-\w+: the learner at http://127.0.0.1:50051 waits before it serves", out), out[-4000:]


def wait_for(path, pattern, timeout, proc=None):
    """Waits until the file at `path` matches `pattern`; returns the text."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        text = open(path).read() if os.path.exists(path) else ""
        if re.search(pattern, text):
            return text
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.5)
    raise AssertionError(f"no {pattern!r} in {path} after {timeout} s:\n{open(path).read()[-3000:]}")


def stops(proc, sig, within=20):
    """Sends `sig`; the process must end within `within` s. Returns its status."""
    proc.send_signal(sig)
    try:
        return proc.wait(within)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f"{proc.args[:3]} still running {within} s after signal {sig}") from None


def actor(log, *args):
    return subprocess.Popen([sys.executable, "-m", "saver_actor", "act", "--factory", "saver_actor.examples:reach3",
                             *args], stdout=open(log, "w"), stderr=subprocess.STDOUT)


def test_waiting_states_stop_on_signals_and_say_what_they_wait_for():
    # A store with no samples, and a learner that waits on it.
    store = t.Server("store-wait", ["pcpn-trainer", "--store", os.path.join(t.TMP, "store-wait")]).wait_ready()
    lrn = t.learner("learner-wait", "--config", write_reach3_config(), "--algo", "saver", "--pcpn", store.url)
    lrn.wait_ready()
    # An actor that does not feed the store: the learner says so within 30 s (it polls
    # the store every 10 s), and the actor waits past its 3 s --connect-timeout.
    alog = os.path.join(t.TMP, "actor-wait.log")
    a = actor(alog, "--learner", lrn.url, "--connect-timeout", "3")
    try:
        started = time.time()
        wait_for(lrn.log, r"no actor streams samples of it: start its actors with --pcpn-samples", 30, lrn.proc)
        print(f"  the learner named the missing samples after {time.time() - started:.0f} s")
        wait_for(alog, r"waits before it serves", 40, a)
        time.sleep(5)
        assert a.poll() is None, open(alog).read()
        # `saver status` says what the learner waits for.
        st = subprocess.run([t.SAVER, "status", "--learner", lrn.url], capture_output=True, text=True, timeout=30)
        assert st.returncode == 0 and "waiting" in st.stdout and "reach3-d3" in st.stdout, (st.stdout, st.stderr)
        # Ctrl-C stops the waiting learner; its actor, the learner gone, ends with one line.
        assert stops(lrn.proc, signal.SIGINT) is not None
        assert a.wait(60) == 2, open(alog).read()
        text = open(alog).read()
        no_traceback(text)
        assert text.rstrip().splitlines()[-1].startswith("error: "), text[-2000:]
        # SIGTERM stops the store that waits for samples.
        assert stops(store.proc, signal.SIGTERM) is not None
        no_traceback(open(store.log).read())
    finally:
        for p in (a, lrn.proc, store.proc):
            if p.poll() is None:
                p.kill()


def test_actor_failures_end_in_one_line():
    # A learner told of a store that is not there retries it for 60 s, then says how
    # to start one.
    lrn = t.learner("learner-nostore", "--config", write_reach3_config(), "--algo", "saver", "--pcpn",
                    f"http://127.0.0.1:{t.port()}")
    # A wrong port: the actor gives up after its --connect-timeout with one line.
    log = os.path.join(t.TMP, "actor-noport.log")
    a = actor(log, "--learner", f"http://127.0.0.1:{t.port()}", "--connect-timeout", "2")
    assert a.wait(60) == 2, open(log).read()
    text = open(log).read()
    no_traceback(text)
    assert "no learner at" in text.splitlines()[-1], text
    # Ctrl-C and SIGTERM while feeding a store that waits for samples (and its learner).
    store = t.Server("store-feed", ["pcpn-trainer", "--store", os.path.join(t.TMP, "store-feed")]).wait_ready()
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            log = os.path.join(t.TMP, f"actor-feed-{sig}.log")
            a = actor(log, "--learner", f"http://127.0.0.1:{t.port()}", "--pcpn-samples", store.url)
            wait_for(log, r"no learner serving", 60, a)
            assert stops(a, sig) == 130, open(log).read()
            text = open(log).read()
            no_traceback(text)
            assert text.rstrip().splitlines()[-1] == "saver-actor: stopped (Ctrl-C or SIGTERM)", text[-2000:]
        # `saver-actor samples` to a store that is not there: one line.
        s = subprocess.run([sys.executable, "-m", "saver_actor", "samples", "--factory", "saver_actor.examples:reach3",
                            "--pcpn", f"http://127.0.0.1:{t.port()}", "--connect-timeout", "2"],
                           capture_output=True, text=True, timeout=120)
        assert s.returncode == 2, (s.stdout, s.stderr)
        no_traceback(s.stderr)
        assert s.stderr.rstrip().splitlines()[-1].startswith("error: "), s.stderr
    finally:
        store.stop()
    assert lrn.proc.wait(120) == 1
    text = open(lrn.log).read()
    assert "retrying for up to 60 s" in text and "Start one with `saver pcpn-trainer" in text, text[-2000:]


def write_reach3_config():
    cfg = os.path.join(t.TMP, "reach3.toml")
    _, decl = t.custom_env("saver_actor.examples:reach3")
    with open(cfg, "w") as f:
        f.write("max_episode_steps = 50\n" + decl.toml())
    return cfg


def test_reach3_checks_and_trains_with_saver_and_a2c():
    c = subprocess.run([sys.executable, "-m", "saver_actor", "check", "--factory", "saver_actor.examples:reach3"],
                       capture_output=True, text=True, timeout=300)
    assert c.returncode == 0, (c.stdout, c.stderr)
    for algo in ("a2c", "saver"):
        store = None
        if algo == "saver":
            store = t.Server("store-reach3", ["pcpn-trainer", "--store", os.path.join(t.TMP, "store-reach3")])
            store.wait_ready()
        try:
            before, after, _, wall = t.custom_run("saver_actor.examples:reach3", algo, 100_000, pcpn=store,
                                                  name=f"reach3-{algo}")
        finally:
            if store is not None:
                store.stop()
        print(f"  reach3 {algo}: {before} -> {after} in {wall:.0f} s")
        # Measured (seed 0, 100 k steps, 50 deterministic episodes): untrained mean
        # final L1 distance 0.223, success 0 %; A2C 0.044, 100 %; SAVER 0.033, 100 %.
        assert after["distance"] < 0.5 * before["distance"], (algo, before, after)
        assert after["success"] >= 0.9, (algo, before, after)


if __name__ == "__main__":
    t.run_tests(globals())
