"""The fidelity benchmark's suction attempts re-scored: would a primitive outcome with another
suction model agree with the YuMi's cup more often? For each suction attempt of a
`ms-drake bench fidelity` file, the grasp-set quality (the SuctionEvaluator's defaults, gravity
along the approach, as stored in the grasp sets) is recomputed (a) with gravity where it is in the
heap (the grasp's real tilt), (b) also with the station's cup (SuctionCup: 40 N, lip friction 1.0,
moment up to f r = 0.6 N m), (c) also with the other objects' load on it (full_load < 0: their
downward force added to the weight). Prints the agreement with the YuMi's outcome of a draw with
p = quality (expected) and of "quality >= 0.5", per model.

    .venv/bin/python sims/fidelity_suction_models.py docs/data/fidelity_reach_v4_N10.jsonl --heap-dir HEAPS [--samples 16]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from ms_drake.experiments.harness import cached_heap
from ms_drake.grasping.grasp import SuctionGrasp
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.grasping.meshes import object_mesh
from ms_drake.objects import get_object

G = 9.81


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("records")
    ap.add_argument("--heap-dir", required=True)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--samples", type=int, default=16, help="robust samples per quality")
    a = ap.parse_args()
    recs = [r for r in map(json.loads, open(a.records)) if r.get("kind") == "attempt" and r["grasp"] == "suction"]
    kappa = 0.6 / (np.pi * 0.015)  # pi r kappa = f r at 40 N
    models = {"grasp sets (gravity along the approach)": None,
              "(a) real tilt": SuctionEvaluator(),
              "(b) real tilt, station cup": SuctionEvaluator(vacuum_force=40.0, friction=1.0, stiffness=kappa),
              "(c) real tilt, station cup, heap load": SuctionEvaluator(vacuum_force=40.0, friction=1.0, stiffness=kappa)}
    rows = {m: [] for m in models}
    for r in recs:
        heap = cached_heap(a.objects, r["seed"], a.heap_dir)
        k = int(r["object"][3:5])
        o = heap.objects[k]
        X, name = np.asarray(o.matrix(), float), o.name
        spec = get_object(name)
        mesh, mass, com = object_mesh(name), spec.mass, np.asarray(spec.inertia.com, float)
        g = SuctionGrasp(r["center"], r["approach"])
        load = max(0.0, -float(r.get("full_load", 0.0)))
        full = bool(r["full_lifted"])
        for m, ev in models.items():
            if ev is None:
                qual = float(r["quality"])
            else:
                extra = load / G if m.startswith("(c)") else 0.0
                qual = ev.quality(mesh, X, g, mass + extra, a.samples, seed=r["seed"], com=com)
            rows[m].append((qual, full))
        print(r["seed"], name, "full", int(full), " ".join(f"{rows[m][-1][0]:.2f}" for m in models), flush=True)
    print(f"\n{len(recs)} suction attempts; agreement with the YuMi:")
    for m, v in rows.items():
        qs, fs = np.array([x[0] for x in v]), np.array([x[1] for x in v])
        draw = np.mean(np.where(fs, qs, 1 - qs))
        det = np.mean((qs >= 0.5) == fs)
        print(f"  {m}: mean quality {qs.mean():.2f}; draw (expected) {100 * draw:.0f} %, quality >= 0.5 {100 * det:.0f} %")


if __name__ == "__main__":
    main()
