#!/usr/bin/env python3
"""Import circles between the top-level modules of each crate (issue 34): every
`crate::M` (and `super::M` from a crate-root file) a file of module A names is an
arrow A -> M; a strongly connected set of two or more modules is a circle. Prints
each crate's circles and the arrows inside them, with the files that draw them.

    python3 bench/import_circles.py            # exit 1 if any circle
"""
import os
import re
import sys
from collections import defaultdict

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CRATES = ["core", "learner", "actor", "pcpn-trainer", "proto", "run"]


def module_of(src: str, path: str) -> str:
    rel = os.path.relpath(path, src)
    first = rel.split(os.sep)[0]
    return first[:-3] if first.endswith(".rs") else first


def arrows(src: str):
    """(from module, to module) -> files, for one crate's src folder."""
    found = defaultdict(set)
    mods = {module_of(src, os.path.join(src, f)) for f in os.listdir(src)} - {"lib", "main"}
    for dirpath, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs") or f.endswith("tests.rs"):
                continue
            path = os.path.join(dirpath, f)
            a = module_of(src, path)
            if a in ("lib", "main"):
                continue
            text = open(path).read()
            text = text.split("#[cfg(test)]")[0]  # test modules may reach anywhere
            # Code only: a doc link is no import.
            text = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//"))
            names = set(re.findall(r"\bcrate::([a-z_][a-z0-9_]*)", text))
            if dirpath == src:  # a root file's super:: is the crate root
                names |= set(re.findall(r"\bsuper::([a-z_][a-z0-9_]*)", text))
            for b in names:
                if b in mods and b != a:
                    found[(a, b)].add(os.path.relpath(path, ROOT))
    return found


def circles(edges):
    graph = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def main():
    total = 0
    for crate in CRATES:
        src = os.path.join(ROOT, crate, "src")
        edges = arrows(src)
        found = circles(edges)
        total += len(found)
        print(f"{crate}: {len(found)} circle(s)")
        for comp in found:
            print(f"  {sorted(comp)}")
            for (a, b), files in sorted(edges.items()):
                if a in comp and b in comp:
                    print(f"    {a} -> {b}: {', '.join(sorted(files))}")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
