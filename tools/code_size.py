#!/usr/bin/env python3
"""Files over 800 lines and functions over 150 lines, tests left out.

    python3 tools/code_size.py [DIR ...]     (default: crates trainer xtask)

A file's size counts its lines outside `#[cfg(test)]` modules; a directory named `tests`
is left out. A function's size is the lines from its `fn` to its closing brace. Prints
each offender; exits 1 when there is one.
"""
import os
import re
import sys

MAX_FILE, MAX_FN = 800, 150
roots = sys.argv[1:] or ['crates', 'trainer', 'xtask']


def strip(src):
    """Source with comments, strings and chars blanked (newlines kept)."""
    out, i, n = [], 0, len(src)
    while i < n:
        c = src[i]
        if src.startswith('//', i):
            j = src.find('\n', i)
            j = n if j < 0 else j
            out.append(' ' * (j - i))
            i = j
        elif src.startswith('/*', i):
            j, depth = i + 2, 1
            while j < n and depth:
                if src.startswith('/*', j):
                    depth, j = depth + 1, j + 2
                elif src.startswith('*/', j):
                    depth, j = depth - 1, j + 2
                else:
                    j += 1
            out.append(re.sub(r'[^\n]', ' ', src[i:j]))
            i = j
        elif c == 'r' and re.match(r'r#*"', src[i:i + 10]) and (i == 0 or not (src[i - 1].isalnum() or src[i - 1] == '_')):
            hashes = re.match(r'r(#*)"', src[i:]).group(1)
            end = src.find('"' + hashes, i + len(hashes) + 2)
            j = n if end < 0 else end + 1 + len(hashes)
            out.append(re.sub(r'[^\n]', ' ', src[i:j]))
            i = j
        elif c == '"':
            j = i + 1
            while j < n and src[j] != '"':
                j += 2 if src[j] == '\\' else 1
            out.append(re.sub(r'[^\n]', ' ', src[i:j + 1]))
            i = j + 1
        elif c == "'" and re.match(r"'(\\.|[^\\'])'", src[i:i + 4]) or src.startswith("'\\", i):
            m = re.match(r"'(\\u\{[0-9a-fA-F]+\}|\\x..|\\.|[^\\'])'", src[i:])
            j = i + (len(m.group(0)) if m else 1)
            out.append(' ' * (j - i))
            i = j
        else:
            out.append(c)
            i += 1
    return ''.join(out)


def block_end(code, open_at):
    depth = 0
    for k in range(open_at, len(code)):
        if code[k] == '{':
            depth += 1
        elif code[k] == '}':
            depth -= 1
            if depth == 0:
                return k
    return len(code) - 1


def line_of(code, pos):
    return code.count('\n', 0, pos) + 1


bad = 0
for root in roots:
    for d, dirs, fs in os.walk(root):
        dirs[:] = [x for x in dirs if x not in ('tests', 'target', 'node_modules')]
        for f in sorted(fs):
            if not f.endswith('.rs'):
                continue
            p = os.path.join(d, f)
            code = strip(open(p).read())
            tests = []
            for m in re.finditer(r'#\[cfg\(test\)\]\s*(pub(\([^)]*\))?\s+)?mod\s+\w+\s*\{', code):
                start = m.end() - 1
                tests.append((m.start(), block_end(code, start)))
            test_lines = sum(line_of(code, b) - line_of(code, a) + 1 for a, b in tests)
            lines = code.count('\n') + (0 if code.endswith('\n') else 1) - test_lines
            if lines > MAX_FILE:
                print(f'{p}: {lines} lines outside tests (> {MAX_FILE})')
                bad += 1
            for m in re.finditer(r'\bfn\s+(\w+)', code):
                if any(a <= m.start() <= b for a, b in tests):
                    continue
                k = m.end()
                while k < len(code) and code[k] not in '{;':
                    k += 1
                if k >= len(code) or code[k] == ';':
                    continue
                length = line_of(code, block_end(code, k)) - line_of(code, m.start()) + 1
                if length > MAX_FN:
                    print(f'{p}:{line_of(code, m.start())}: fn {m.group(1)} is {length} lines (> {MAX_FN})')
                    bad += 1
print(f'{bad} over the limits (files {MAX_FILE} lines, functions {MAX_FN} lines, tests left out)')
sys.exit(1 if bad else 0)
