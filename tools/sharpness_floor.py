#!/usr/bin/env python3
"""The RGB L1 between two renderings of the same scans under the same cameras: what a
perfect generator would score in `trainer eval --subject-codes` when its images are sampled
one way and the data another. The labels are those `trainer eval --count N` picks (N spread
evenly over the sorted entries), so the figure sits beside the eval's.

    # the data (2×2 supersampled, prepare's default) and the scans at one sample per pixel:
    trainer prepare --scans data/scans16 --views 24 --res 64 --out data/ds64_16
    trainer prepare --scans data/scans16 --views 24 --res 64 --ss 1 --out /tmp/ds64_16_ss1
    python3 tools/sharpness_floor.py data/ds64_16 /tmp/ds64_16_ss1 4

At 64² the scans themselves, sampled once per pixel, differ from their own 2×2-supersampled
views by 0.0085 on v1's grid (the model card's sharpness row): point-sampled renders alias
where the data averages. Images are compared as `trainer eval` reads them (the PNG's RGB, which
`prepare` composites on white; [0, 1] units). Needs numpy and Pillow.
"""
import json
import os
import sys

import numpy as np
from PIL import Image


def rgb(path):
    return np.asarray(Image.open(path).convert("RGBA"), dtype=np.float64)[..., :3] / 255.0


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    data, other, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
    with open(os.path.join(data, "dataset.json")) as f:
        entries = sorted(json.load(f)["labels"])
    if count < 1:
        sys.exit("count must be at least 1")
    count = min(count, len(entries))
    picked = [entries[k * len(entries) // count] for k in range(count)]
    l1 = [np.abs(rgb(os.path.join(data, e)) - rgb(os.path.join(other, e))).mean() for e in picked]
    for e, v in zip(picked, l1):
        print(f"{e}: {v:.4f}")
    print(f"mean RGB L1 over {count} labels: {np.mean(l1):.4f}")


if __name__ == "__main__":
    main()
