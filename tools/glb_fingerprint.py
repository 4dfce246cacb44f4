#!/usr/bin/env python3
"""The figures of the demo model's fingerprint test (tests/tests/generator.rs,
`demo_checkpoint_reproduces_its_cli_avatars`) from the .glb files the CLI exports.

    trainer sample --seed-geo 1 --seed-tex 2 --pose walking --res 64 --out /tmp/fp_walking
    trainer sample --seed-geo 1 --seed-tex 2 --pose arms_up --res 64 --out /tmp/fp_arms_up
    python3 tools/glb_fingerprint.py /tmp/fp_walking/avatar.glb /tmp/fp_arms_up/avatar.glb

Prints, per file: vertices, triangles, and the sums of x + 2y + 3z over the first mesh's
POSITION, NORMAL and COLOR_0 (RGB) accessors in f64 (normalised integer colours as [0, 1]).
Needs numpy.
"""
import json
import struct
import sys

import numpy as np


def fingerprint(path):
    b = open(path, 'rb').read()
    if b[:4] != b'glTF':
        raise SystemExit(f'{path}: not a binary glTF')
    json_len = struct.unpack('<I', b[12:16])[0]
    gltf = json.loads(b[20:20 + json_len])
    off = 20 + json_len
    bin_len = struct.unpack('<I', b[off:off + 4])[0]
    blob = b[off + 8:off + 8 + bin_len]
    prim = gltf['meshes'][0]['primitives'][0]

    def accessor(i):
        a = gltf['accessors'][i]
        view = gltf['bufferViews'][a['bufferView']]
        n = {'SCALAR': 1, 'VEC2': 2, 'VEC3': 3, 'VEC4': 4}[a['type']]
        dt = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[a['componentType']]
        start = view.get('byteOffset', 0) + a.get('byteOffset', 0)
        stride = view.get('byteStride', 0)
        if stride:
            raw = np.frombuffer(blob[start:start + stride * a['count']], dtype=np.uint8).reshape(a['count'], stride)
            arr = raw[:, :n * np.dtype(dt).itemsize].copy().view(dt)
        else:
            arr = np.frombuffer(blob, dtype=dt, count=a['count'] * n, offset=start)
        arr = arr.reshape(a['count'], n).astype(np.float64)
        if a.get('normalized'):
            arr /= np.iinfo(dt).max
        return arr

    at = prim['attributes']
    w = np.array([1.0, 2.0, 3.0])
    pos, nrm = accessor(at['POSITION']), accessor(at['NORMAL'])
    sums = [float((pos * w).sum()), float((nrm * w).sum())]
    if 'COLOR_0' in at:
        sums.append(float((accessor(at['COLOR_0'])[:, :3] * w).sum()))
    return len(pos), len(accessor(prim['indices'])) // 3, sums


for p in sys.argv[1:]:
    v, t, s = fingerprint(p)
    print(f'{p}: ({v}, {t}, [{", ".join(repr(x) for x in s)}])')
