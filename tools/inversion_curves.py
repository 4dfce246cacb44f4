#!/usr/bin/env python3
"""Quality against steps of `trainer invert` runs: the curves the presets' step counts come from.

Each run's `steps.jsonl` holds every step's terms, measured on the render *before* that step's
update: the mask IoU at the photo's camera and the masked RGB MSE (sRGB in [0, 1] inside the
person mask), printed here as masked PSNR = -10 log10(MSE), the figure metrics.json gives.

    python3 tools/inversion_curves.py runs/curves/enc_w_0001_000 runs/curves/search_w_0001_000 ...

Prints, per run, IoU / PSNR at a fixed list of steps of each phase (W+ then PTI), and a
Markdown table for docs/benchmarks.md with `--markdown`. Stdlib only.
"""

import json
import math
import sys
from pathlib import Path

AT = [0, 5, 10, 20, 30, 45, 60, 90, 120, 150, 199]


def load(run: Path):
    phases = {}
    with open(run / "steps.jsonl") as f:
        for line in f:
            r = json.loads(line)
            t = r["terms"]
            psnr = -10.0 * math.log10(max(t["rgb_mse"], 1e-12))
            phases.setdefault(r["phase"], []).append((r["step"], t["mask_iou"], psnr))
    return phases


def main(argv):
    markdown = "--markdown" in argv
    runs = [Path(a) for a in argv if not a.startswith("--")]
    if not runs:
        sys.exit(__doc__)
    rows = []
    for run in runs:
        if not (run / "steps.jsonl").is_file():
            sys.exit(f"{run}: no steps.jsonl (not a `trainer invert` output folder)")
        for phase, steps in load(run).items():
            by_step = {s: (iou, p) for s, iou, p in steps}
            cells = [f"{by_step[s][0]:.3f} / {by_step[s][1]:.2f}" if s in by_step else "" for s in AT]
            rows.append((run.name, phase, len(steps), cells))
    if markdown:
        print("| run | phase | steps | " + " | ".join(f"step {s}" for s in AT) + " |")
        print("|---|---|---|" + "---|" * len(AT))
        for name, phase, n, cells in rows:
            print(f"| {name} | {phase} | {n} | " + " | ".join(cells) + " |")
    else:
        print("mask IoU / masked PSNR dB at step " + ", ".join(map(str, AT)))
        for name, phase, n, cells in rows:
            print(f"{name} {phase} ({n} steps): " + "  ".join(c or "-" for c in cells))


if __name__ == "__main__":
    main(sys.argv[1:])
