#!/usr/bin/env python3
"""Import circles between a crate's source files (tests excluded).

    python3 tools/import_cycles.py [crates/core/src]

Every `crate::a::b…` and `super::…` path in a file's code (comments and `#[cfg(test)]`
modules left out) is an edge to the file that defines the module it names: `a/b.rs`,
`a/b/mod.rs`, or the nearest enclosing module's file. Prints each circle (a strongly
connected set of files) with its edges; exits 1 when there is one.
"""
import os
import re
import sys

root = sys.argv[1] if len(sys.argv) > 1 else 'crates/core/src'


def module_path(path):
    rel = os.path.relpath(path, root)[:-3].split(os.sep)
    if rel[-1] in ('mod', 'lib'):
        rel = rel[:-1]
    return rel


files = {}
for d, _, fs in os.walk(root):
    for f in fs:
        if f.endswith('.rs'):
            p = os.path.join(d, f)
            files[tuple(module_path(p))] = p


def file_of(segments):
    """The file defining the longest prefix of `segments` that is a module."""
    for k in range(len(segments), -1, -1):
        if tuple(segments[:k]) in files:
            return files[tuple(segments[:k])]
    return None


def expand(code, i):
    """The module paths of the use tree starting at `code[i]` (`a::b`, `a::{b, c::{d}}`)."""
    segs = []
    while True:
        m = re.match(r'\s*([A-Za-z_][A-Za-z_0-9]*)', code[i:])
        if m:
            segs.append(m.group(1))
            i += m.end()
            n = re.match(r'\s*::', code[i:])
            if not n:
                return [segs]
            i += n.end()
            continue
        if re.match(r'\s*\{', code[i:]):
            i = code.index('{', i) + 1
            out, depth, start = [], 0, i
            while i < len(code):
                c = code[i]
                if c == '{':
                    depth += 1
                elif c == '}' and depth:
                    depth -= 1
                elif (c == ',' or c == '}') and depth == 0:
                    out += [segs + sub for sub in expand(code[start:i] + ' ', 0)]
                    start = i + 1
                    if c == '}':
                        break
                i += 1
            return out or [segs]
        return [segs]


edges = {}
for mod, p in files.items():
    src = open(p).read()
    i = src.find('#[cfg(test)]')
    if i >= 0:
        src = src[:i]
    code = '\n'.join(line.split('//')[0] for line in src.split('\n'))
    targets = set()
    is_mod_file = os.path.basename(p) in ('mod.rs', 'lib.rs')
    parent = list(mod) if is_mod_file else list(mod[:-1])
    for m in re.finditer(r'\b(crate|(?:super::)*super)::', code):
        if m.group(1) == 'crate':
            base = []
        else:
            ups = m.group(1).count('super')
            base = parent[: len(parent) - (ups - 1)] if is_mod_file else list(mod[: len(mod) - ups])
        for path in expand(code, m.end()):
            targets.add(file_of(base + path))
    edges[p] = {t for t in targets if t and t != p and not t.endswith(('lib.rs', 'mod.rs'))}

index, low, stack, on, sccs, counter = {}, {}, [], set(), [], [0]
sys.setrecursionlimit(100000)


def visit(v):
    index[v] = low[v] = counter[0]
    counter[0] += 1
    stack.append(v)
    on.add(v)
    for w in edges.get(v, ()):
        if w not in index:
            visit(w)
            low[v] = min(low[v], low[w])
        elif w in on:
            low[v] = min(low[v], index[w])
    if low[v] == index[v]:
        s = []
        while True:
            w = stack.pop()
            on.discard(w)
            s.append(w)
            if w == v:
                break
        if len(s) > 1:
            sccs.append(sorted(s))


for v in list(edges):
    if v not in index:
        visit(v)
for s in sccs:
    print('circle:', ' '.join(os.path.relpath(f, root) for f in s))
    for a in s:
        for b in sorted(edges[a] & set(s)):
            print(f'  {os.path.relpath(a, root)} -> {os.path.relpath(b, root)}')
print(f'{len(files)} files, {len(sccs)} import circles')
sys.exit(1 if sccs else 0)
