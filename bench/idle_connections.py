#!/usr/bin/env python3
"""Idle connections against a learner with a token under a 256-fd limit: how many it
closes after 13 s, and whether it still answers.

    python3 bench/idle_connections.py target/release/saver [CONNECTIONS]
"""
import socket, subprocess, sys, time, tempfile, threading
b = sys.argv[1]
p = subprocess.Popen(["bash", "-c", f"ulimit -n 256; exec {b} learner --listen 127.0.0.1:0 --algo a2c --env angle --dim 4 --actors 1 --steps 100000000 --out {tempfile.mkdtemp()} --weights-dir none --token s3cret"], stderr=subprocess.PIPE, text=True)
for line in p.stderr:
    if " on " in line:
        addr = line.split(" on ")[1].split()[0].rstrip(";"); break
threading.Thread(target=lambda: [None for _ in p.stderr], daemon=True).start()
host, port = addr.rsplit(":", 1)
socks = []
for i in range(int(sys.argv[2]) if len(sys.argv) > 2 else 374):
    try:
        s = socket.create_connection((host, int(port)), timeout=2); socks.append(s)
    except OSError as e:
        print("connect", i, "failed:", e); break
print("held", len(socks), "idle connections")
time.sleep(13)
closed = 0
for s in socks:
    s.settimeout(0.5)
    try:
        while True:
            data = s.recv(4096)  # the server's SETTINGS frame, then EOF if it closed
            if data == b"":
                closed += 1
                break
    except socket.timeout: pass
    except OSError: closed += 1
print("closed by the learner after 13 s:", closed, "of", len(socks))
r = subprocess.run([b, "status", "--learner", f"http://{addr}", "--token", "s3cret"], capture_output=True, text=True, timeout=20)
print("status afterwards:", "ok" if r.returncode == 0 else r.stderr.strip()[-200:])
p.kill()
