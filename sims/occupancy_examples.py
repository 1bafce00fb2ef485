"""Predicted against ground-truth occupancy on test images with the target partly seen.

    .venv/bin/python sims/occupancy_examples.py DATA OUT.png WEIGHTS... [--rows 6] [--seed 0]

DATA: a folder of `ms-drake data occupancy`; per row (a random test image whose target is partly
seen, the same rows for every run with the same seed): the depth, the target's seen (modal) mask,
the ground truth, then each network's estimator output (input scaling by the target's size),
all at the working resolution in a 40 x 40 window about the seen part (the whole image in the
first column, the window drawn on it), the maps in a colour scale with the seen mask outlined.
"""
import argparse
from pathlib import Path

import cv2
import numpy as np

from ms_drake.experiments.occupancy_data import load_dataset
from ms_drake.experiments.occupancy_learning import diagonals, predict, target_scales
from ms_drake.perception.occupancy_net import load_model

SCALE = 4  # display pixels per working pixel
WINDOW = 40  # working pixels


def tile(a: np.ndarray, seen: np.ndarray | None, gray: bool = False) -> np.ndarray:
    a = np.clip(np.asarray(a, np.float32), 0.0, 1.0)
    img = (a * 255).astype(np.uint8)
    img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if gray else cv2.applyColorMap(img, cv2.COLORMAP_INFERNO)
    img = cv2.resize(img, (a.shape[1] * SCALE, a.shape[0] * SCALE), interpolation=cv2.INTER_NEAREST)
    if seen is not None:
        m = cv2.resize(seen.astype(np.uint8), (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, contours, -1, (255, 255, 0), 1)
    return cv2.copyMakeBorder(img, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("data", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("weights", nargs="+", type=Path)
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    d = load_dataset(args.data, "test")
    seen_idx = np.flatnonzero(d["visible"] > 0)
    rows = np.sort(np.random.default_rng(args.seed).choice(seen_idx, min(args.rows, len(seen_idx)), replace=False))
    x, y = d["x"][rows].astype(np.float32), d["y"][rows].astype(np.float32)
    preds = [predict(load_model(w)[0], x, d["ratio"][rows], target_scales(d["size"][rows]),
                     diag=diagonals(d["size"][rows])) for w in args.weights]
    lines = []
    for i in range(len(rows)):
        seen = x[i, 0] > 0
        r, c = np.argwhere(seen).mean(axis=0).astype(int)
        r0 = int(np.clip(r - WINDOW // 2, 0, seen.shape[0] - WINDOW))
        c0 = int(np.clip(c - WINDOW // 2, 0, seen.shape[1] - WINDOW))
        win = (slice(r0, r0 + WINDOW), slice(c0, c0 + WINDOW))
        dep = x[i, 1]
        dep = 1.0 - (dep - dep.min()) / max(float(np.ptp(dep)), 1e-6)  # near is bright
        whole = cv2.cvtColor((dep * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        cv2.rectangle(whole, (c0, r0), (c0 + WINDOW - 1, r0 + WINDOW - 1), (0, 0, 255), 1)
        whole = cv2.resize(whole, (WINDOW * SCALE * seen.shape[1] // seen.shape[0], WINDOW * SCALE),
                           interpolation=cv2.INTER_AREA)
        whole = cv2.copyMakeBorder(whole, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
        tiles = [whole, tile(dep[win], seen[win], gray=True), tile(x[i, 0][win], None, gray=True),
                 tile(y[i][win], seen[win])]
        tiles += [tile(p[i][win], seen[win]) for p in preds]
        lines.append(np.hstack(tiles))
    header = np.full((22, lines[0].shape[1], 3), 255, np.uint8)
    names = ["depth (window)", "seen mask", "ground truth"] + [w.stem for w in args.weights]
    w = WINDOW * SCALE + 4
    x0 = lines[0].shape[1] - w * len(names)  # the width of the whole-image column
    cv2.putText(header, "depth", (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for k, name in enumerate(names):
        cv2.putText(header, name, (x0 + k * w + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.vstack([header] + lines))
    print(f"wrote {args.out}: test images {rows.tolist()} of {args.data}")


if __name__ == "__main__":
    main()
