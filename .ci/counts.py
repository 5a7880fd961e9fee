#!/usr/bin/env python3
"""The house's counts, redone from the tree (issue 50): functions over 120 lines, files over
800 lines of code, and modules that import each other.

    python3 .ci/counts.py          # prints every offender, exits 1 if there is one

Lines of code are lines that are neither blank nor only a comment. A function's length runs
from its `fn` (or `function`) line to its closing brace. Rust files, the page's HTML and
script, and the deploy scripts' Python are counted. Tests count for a file's lines, but a test
function (under tests/ or in a test module) is not held to the 120 lines: a test reads best as
one story.
Module imports are `use crate::...`, `use super::...` and `crate::a::b` paths inside one
crate, at the granularity of files (a `mod.rs` is its folder).
"""
import os
import re
import subprocess
import sys

MAX_FN = 120
MAX_LOC = 800


def tracked(root):
    out = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True)
    return [p for p in out.stdout.splitlines() if not p.startswith("results/")]


def strip_strings(line):
    """The line without the contents of its string literals (so braces in them don't count)."""
    return re.sub(r'"(\\.|[^"\\])*"', '""', re.sub(r"'(\\.|[^'\\])'", "''", line))


def code_lines(lines, comment="//"):
    n, in_block = 0, False
    for raw in lines:
        s = raw.strip()
        if in_block:
            if "*/" in s:
                in_block = False
                s = s.split("*/", 1)[1].strip()
            else:
                continue
        if not s:
            continue
        if comment == "//" and s.startswith("/*"):
            if "*/" not in s:
                in_block = True
            continue
        if s.startswith(comment):
            continue
        if comment == "//" and s.startswith("<!--"):
            continue
        n += 1
    return n


FN_RUST = re.compile(r"^\s*(pub(\([^)]*\))?\s+)?(const\s+)?(async\s+)?(unsafe\s+)?(extern\s+\"C\"\s+)?fn\s+(\w+)")
FN_JS = re.compile(r"^\s*(async\s+)?function\s*\*?\s*(\w+)|^\s*(const|let)\s+(\w+)\s*=\s*(async\s*)?\([^)]*\)\s*=>\s*\{")


def long_functions(path, lines, rust):
    """(name, first line, length) for each function over MAX_FN lines."""
    found = []
    test_depth = None  # brace depth at which a #[cfg(test)] module opened
    depth = 0
    pending_test = False
    stack = []  # (name, start line, depth at open) of open functions
    waiting = None  # a function whose body brace has not come yet
    nest = 0  # open parentheses and brackets (a `;` inside them ends nothing)
    for i, raw in enumerate(lines, 1):
        line = strip_strings(raw.split("//", 1)[0]) if rust else strip_strings(raw)
        if rust and "#[cfg(test)]" in line:
            pending_test = True
        m = (FN_RUST.match(line) if rust else FN_JS.match(line))
        if m and waiting is None:
            name = m.group(7) if rust else (m.group(2) or m.group(4))
            waiting = (name, i)
        for ch in line:
            if ch == "{":
                if waiting is not None:
                    stack.append((waiting[0], waiting[1], depth))
                    waiting = None
                if pending_test and test_depth is None and rust:
                    test_depth = depth
                    pending_test = False
                depth += 1
            elif ch == "}":
                depth -= 1
                if stack and stack[-1][2] == depth:
                    name, start, _ = stack.pop()
                    length = i - start + 1
                    if length > MAX_FN and test_depth is None:
                        found.append((name, start, length))
                if test_depth is not None and depth == test_depth:
                    test_depth = None
            elif ch in "([":
                nest += 1
            elif ch in ")]":
                nest -= 1
            elif ch == ";" and waiting is not None and rust and nest == 0:
                waiting = None  # a declaration without a body
        if pending_test and rust and re.match(r"^\s*(mod|fn)\b", line) and "{" not in line:
            pending_test = False
    return found


def module_of(path):
    """(crate folder, module path) of a Rust source file."""
    parts = path.split("/")
    if "src" not in parts:
        return None
    i = parts.index("src")
    crate = "/".join(parts[:i]) or "."
    mod = parts[i + 1 :]
    mod[-1] = mod[-1][:-3]
    if mod[-1] in ("mod", "lib", "main"):
        mod = mod[:-1]
    return crate, tuple(mod)


USE = re.compile(r"\b(crate|super)((::\w+)+)")


def imports(path, text, files):
    """The modules (files) of the same crate that a file names."""
    me = module_of(path)
    if me is None:
        return set()
    crate, mod = me
    is_dir_mod = path.endswith("/mod.rs") or path.endswith("/lib.rs") or path.endswith("/main.rs")
    here = mod if is_dir_mod else mod[:-1]
    out = set()
    body = re.split(r"#\[cfg\(test\)\]\s*mod\s+tests", text)[0]
    body = "\n".join(line.split("//", 1)[0] for line in body.splitlines())
    for m in USE.finditer(body):
        segs = m.group(2).split("::")[1:]
        base = () if m.group(1) == "crate" else here[:-1]
        if m.group(1) == "super":
            while segs and segs[0] == "super":
                base, segs = base[:-1], segs[1:]
        target = base + tuple(segs)
        # the longest prefix that is a file of this crate
        while target and (crate, target) not in files:
            target = target[:-1]
        if target and target != mod and not (mod[: len(target)] == target):
            out.add(target)
    return out


def cycles(edges):
    """Pairs of modules that reach each other (strongly connected components over 1)."""
    index, low, on, stack, comps, n = {}, {}, set(), [], [], [0]
    sys.setrecursionlimit(10000)

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return comps


def main():
    root = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True).stdout.strip()
    paths = [p for p in tracked(root) if p.endswith((".rs", ".js", ".html", ".py"))]
    big, long_fns, texts = [], [], {}
    for p in paths:
        with open(os.path.join(root, p), encoding="utf-8") as f:
            text = f.read()
        texts[p] = text
        lines = text.splitlines()
        loc = code_lines(lines, "#" if p.endswith(".py") else "//")
        if loc > MAX_LOC:
            big.append((p, loc))
        if p.startswith("tests/"):
            pass  # a test reads best as one story
        elif p.endswith(".rs"):
            long_fns += [(p,) + f for f in long_functions(p, lines, True)]
        elif p.endswith((".js", ".html")):
            long_fns += [(p,) + f for f in long_functions(p, lines, False)]
    files = {module_of(p) for p in paths if p.endswith(".rs") and module_of(p)}
    edges = {}
    for p in paths:
        me = module_of(p) if p.endswith(".rs") else None
        if me:
            edges.setdefault(me, set()).update((me[0], t) for t in imports(p, texts[p], files))
    circles = cycles(edges)
    print(f"functions over {MAX_FN} lines: {len(long_fns)}")
    for p, name, start, length in sorted(long_fns, key=lambda f: -f[3]):
        print(f"  {p}:{start} {name} {length}")
    print(f"files over {MAX_LOC} lines of code: {len(big)}")
    for p, loc in sorted(big, key=lambda b: -b[1]):
        print(f"  {p} {loc}")
    print(f"modules that import each other: {len(circles)}")
    for comp in circles:
        print("  " + " <-> ".join(f"{c}/{'::'.join(m) or '(root)'}" for c, m in comp))
    return 1 if (long_fns or big or circles) else 0


if __name__ == "__main__":
    sys.exit(main())
