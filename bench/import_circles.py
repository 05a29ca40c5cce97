#!/usr/bin/env python3
"""Import circles between the modules of each crate (issues 34 and 57).

Every source file is a module (`algo/saver/step.rs` is `algo::saver::step`). Every path
a file's code names is an arrow to the module that defines the item:

- `use` trees (braces and globs expanded) and paths written inline in code;
- paths from `crate::`, `super::` (any number), `self::`, and from a child or
  sibling module's own name where the file brings it into scope;
- a path that ends at a re-export (`pub use x::Y` in module M) goes on to the module
  that defines Y, so a facade such as `algo::Saver` is an arrow to `algo::saver`;
- a re-export (`pub use`) is naming, not depending: it is no arrow of its own, and
  neither is a `mod x;` declaration. So a parent may re-export its children while
  they use what it defines, as long as its own code uses none of theirs.

A strongly connected set of two or more modules is a circle. Test code (files named
`*tests.rs` and everything from a file's first `#[cfg(test)]` on) may reach anywhere.
Prints each crate's circles and the arrows inside them, with the files that draw
them; `--arrows` prints every arrow.

    python3 bench/import_circles.py            # exit 1 if any circle
"""
import os
import re
import sys
from collections import defaultdict

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CRATES = [".", "core", "learner", "actor", "pcpn-trainer", "proto", "run"]
IDENT = r"[A-Za-z_][A-Za-z0-9_]*"
PUB_USE = r"\bpub(?:\([^)]*\))?\s+use\s+([^;]+);"  # a re-export, with its use tree


def module_files(src: str):
    """Module path (tuple) -> file, for one crate's src folder."""
    out = {}
    for dirpath, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs"):
                continue
            path = os.path.join(dirpath, f)
            parts = os.path.relpath(path, src)[:-3].split(os.sep)
            if parts[-1] == "mod" or (len(parts) == 1 and parts[0] in ("lib", "main")):
                parts = parts[:-1]
            if parts and parts[0] == "bin":
                continue  # each binary is a crate of its own
            out[tuple(parts)] = path
    return out


def code_of(path: str) -> str:
    """The non-test code of a file, without comments and string literals."""
    if os.path.basename(path).endswith("tests.rs"):
        return ""
    text = open(path).read().split("#[cfg(test)]")[0]
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = "\n".join(line.split("//")[0] for line in text.splitlines())
    return re.sub(r'"(\\.|[^"\\])*"', '""', text)


def split_top(s: str):
    """Splits a use-tree list at its top-level commas."""
    parts, depth, cur = [], 0, ""
    for ch in s:
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    parts.append(cur)
    return [p.strip() for p in parts if p.strip()]


def expand(tree: str, prefix=()):
    """The flat paths (tuples of segments) of a use tree."""
    tree = re.sub(r"\s+as\s+" + IDENT, "", tree.strip())
    m = re.match(r"^((?:" + IDENT + r"::)*)\{(.*)\}$", tree, flags=re.S)
    if m:
        head = tuple(s for s in m.group(1).split("::") if s)
        out = []
        for part in split_top(m.group(2)):
            out.extend(expand(part, prefix + head))
        return out
    segs = tuple(s for s in tree.split("::") if s and s != "*")
    segs = tuple(s for s in segs if s != "self")
    return [prefix + segs]


class Crate:
    def __init__(self, src: str):
        self.src = src
        self.files = module_files(src)
        self.code = {m: code_of(p) for m, p in self.files.items()}
        self.uses = {m: self.use_paths(m) for m in self.files}
        # Re-exports: module -> item name -> flat path as written.
        self.reexports = defaultdict(dict)
        for m, text in self.code.items():
            for tree in re.findall(PUB_USE, text):
                for path in expand(tree):
                    if path:
                        self.reexports[m][path[-1]] = path

    def use_paths(self, m):
        # Private `use`s only: a `pub use` is a re-export (no arrow).
        text = re.sub(PUB_USE, "", self.code[m])
        return [p for tree in re.findall(r"\buse\s+([^;]+);", text) for p in expand(tree)]

    def is_module(self, m):
        return m in self.files

    def base(self, m, path):
        """Where `path` (written in module m) starts, and the segments after that."""
        path = list(path)
        if not path:
            return None, []
        if path[0] == "crate":
            return (), path[1:]
        if path[0] == "self":
            return m, path[1:]
        if path[0] == "super":
            cur = m
            while path and path[0] == "super":
                cur = cur[:-1]
                path = path[1:]
            return cur, path
        if self.is_module(m + (path[0],)):
            return m, path  # a child module by name
        return None, []

    def resolve(self, m, path, seen=None):
        """The module that defines what `path` (written in module m) names."""
        start, rest = self.base(m, path)
        if start is None:
            return None
        cur = start
        while rest and self.is_module(cur + (rest[0],)):
            cur = cur + (rest[0],)
            rest = rest[1:]
        if rest and rest[0] in self.reexports.get(cur, {}):
            seen = seen or set()
            key = (cur, rest[0])
            if key not in seen:
                seen.add(key)
                target = self.resolve(cur, self.reexports[cur][rest[0]], seen)
                if target is not None:
                    return target
        return cur

    def arrows(self):
        """(from module, to module) -> files."""
        found = defaultdict(set)
        for m, text in self.code.items():
            paths = list(self.uses[m])
            text = re.sub(r"\buse\s+[^;]+;", "", text)  # counted above (or a re-export)
            # Names a `use` brought into scope, so `step::run()` after `use super::step;`.
            local = {p[-1]: p for p in paths if p}
            for hit in re.finditer(r"\b(" + IDENT + r")((?:::" + IDENT + r")+)", text):
                head, tail = hit.group(1), hit.group(2).split("::")[1:]
                if head in local and head not in ("crate", "super", "self"):
                    paths.append(tuple(local[head]) + tuple(tail))
                else:
                    paths.append((head,) + tuple(tail))
            for path in paths:
                target = self.resolve(m, path)
                if target is not None and target != m:
                    found[(m, target)].add(os.path.relpath(self.files[m], ROOT))
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

    sys.setrecursionlimit(10000)
    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def name(m):
    return "::".join(m) or "(crate root)"


def main():
    show_all = "--arrows" in sys.argv
    total = 0
    for crate in CRATES:
        src = os.path.join(ROOT, crate, "src")
        c = Crate(src)
        edges = c.arrows()
        found = circles(edges)
        total += len(found)
        label = "saver (top level)" if crate == "." else crate
        print(f"{label}: {len(c.files)} modules, {len(edges)} arrows, {len(found)} circle(s)")
        if show_all:
            for (a, b), _files in sorted(edges.items()):
                print(f"    {name(a)} -> {name(b)}")
        for comp in found:
            print(f"  {sorted(name(x) for x in comp)}")
            for (a, b), files in sorted(edges.items()):
                if a in comp and b in comp:
                    print(f"    {name(a)} -> {name(b)}: {', '.join(sorted(files))}")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
