#!/usr/bin/env python3
"""How much of a dataset's normal maps lies in detail finer than a given scale: the mean
angle between each normal map and itself low-passed by a Gaussian of σ pixels, over the
pixels at least 2 px inside the mask (the interior figure of `trainer eval`).

A generator whose normal field cannot hold detail below some scale (the 3.6 cm texels of
64² geometry planes over the 2.29 m canonical box) scores about this angle there even where
its coarse shape is exact, so it is a floor for `trainer eval`'s interior normal error.

    trainer prepare --scans data/scans64 --views 4 --res 256 --seed 1 --out data/train256_64
    python3 tools/normal_detail_floor.py data/train256_64 1 2 3 4

At 256² (2.3 m camera distance, 49.13° fov) one pixel is about 0.85 cm on the subject.
Needs numpy and Pillow.
"""
import glob
import os
import sys

import numpy as np
from PIL import Image


def blur(a, sigma):
    r = int(3 * sigma)
    x = np.arange(-r, r + 1)
    k = np.exp(-(x**2) / (2 * sigma * sigma))
    k /= k.sum()
    a = np.apply_along_axis(lambda v: np.convolve(v, k, "same"), 0, a)
    return np.apply_along_axis(lambda v: np.convolve(v, k, "same"), 1, a)


def erode(mask, band):
    out = mask.copy()
    h, w = mask.shape
    padded = np.zeros((h + 2 * band, w + 2 * band), bool)
    padded[band : band + h, band : band + w] = mask
    for dy in range(-band, band + 1):
        for dx in range(-band, band + 1):
            out &= padded[band + dy : band + dy + h, band + dx : band + dx + w]
    return out


def floor(dataset, sigma, every=4):
    files = sorted(glob.glob(os.path.join(dataset, "*", "*_normal.png")))[::every]
    if not files:
        sys.exit(f"no */*_normal.png under {dataset}")
    total, count = 0.0, 0
    for f in files:
        n = np.asarray(Image.open(f).convert("RGB")).astype(float) / 255 * 2 - 1
        rgba = np.asarray(Image.open(f.replace("_normal.png", ".png")).convert("RGBA"))
        valid = (rgba[..., 3] > 127) & (np.linalg.norm(n, axis=-1) > 0.5)
        w = valid.astype(float)
        b = np.stack([blur(n[..., c] * w, sigma) for c in range(3)], -1)
        b /= np.linalg.norm(b, axis=-1, keepdims=True) + 1e-9
        a = n / (np.linalg.norm(n, axis=-1, keepdims=True) + 1e-9)
        angle = np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))
        inner = erode(valid, 2)
        total += angle[inner].sum()
        count += inner.sum()
    return total / count, count, len(files)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    for s in sys.argv[2:]:
        deg, px, n = floor(sys.argv[1], float(s))
        print(f"σ {s} px: {deg:.2f}° between the normal maps and their blur, over {px} interior pixels of {n} views")
