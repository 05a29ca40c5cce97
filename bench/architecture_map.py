#!/usr/bin/env python3
"""docs/ARCHITECTURE.md's module map names every source file (issue 57): each crate's
`src/**/*.rs` and the Python package's `*.py` must have a row `| path | ... |` under its
crate's heading, and no row may name a file that is gone.

    python3 bench/architecture_map.py      # exit 1 on a missing or stale row
"""
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Heading fragment of each crate's table -> its source folder and file suffix.
CRATES = {
    "(the root package, `src/`)": ("src", ".rs"),
    "(`run/src/`)": ("run/src", ".rs"),
    "(`proto/src/`": ("proto/src", ".rs"),
    "(`core/src/`)": ("core/src", ".rs"),
    "(`learner/src/`)": ("learner/src", ".rs"),
    "(`actor/src/`)": ("actor/src", ".rs"),
    "(`pcpn-trainer/src/`)": ("pcpn-trainer/src", ".rs"),
    "(`python/saver_actor/`": ("python/saver_actor", ".py"),
}


def files(folder, suffix):
    out = set()
    base = os.path.join(ROOT, folder)
    for dirpath, dirs, names in os.walk(base):
        dirs[:] = [d for d in dirs if not d.startswith("_")]  # generated stubs
        out |= {os.path.relpath(os.path.join(dirpath, n), base) for n in names if n.endswith(suffix)}
    return out


def main():
    text = open(os.path.join(ROOT, "docs", "ARCHITECTURE.md")).read()
    section = text.split("## Module map", 1)[1].split("\n## ", 1)[0]
    problems = 0
    parts = re.split(r"\n(?=\*\*)", section)
    for key, (folder, suffix) in CRATES.items():
        part = next((p for p in parts if p.startswith("**") and key in p.split("\n", 1)[0]), None)
        if part is None:
            print(f"no table for {folder}")
            problems += 1
            continue
        # Markdown escapes a dunder name's underscores (\_\_init\_\_.py).
        rows = set(re.findall(r"^\| ([\w./\\-]+\.(?:rs|py)) \|", part, flags=re.M))
        rows = {r.replace("\\_", "_") for r in rows}
        have = files(folder, suffix)
        for f in sorted(have - rows):
            print(f"{folder}/{f}: no row in ARCHITECTURE.md's module map")
        for f in sorted(rows - have):
            print(f"{folder}/{f}: a row for a file that is not there")
        problems += len(have ^ rows)
    print(f"module map: {problems} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
