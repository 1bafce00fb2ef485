"""The fidelity benchmark's suction attempts re-scored: would a primitive outcome with another
suction model agree with the YuMi's cup more often? For each suction attempt of a
`ms-drake bench fidelity` file, the grasp-set quality (the SuctionEvaluator's defaults, gravity
along the approach, as stored in the grasp sets) is recomputed (a) with gravity where it is in the
heap (the grasp's real tilt), (b) also with the station's cup (SuctionCup: 40 N, lip friction 1.0,
moment up to f r = 0.6 N m), (c) also with the other objects' load on it (full_load < 0: their
downward force added to the weight), (d) as (b) with the lip's springs allowed to stretch by
`--stretch` (the evaluator's max_stretch; default 0.1), (e) the grasp sets' convention (gravity
along the approach) with the station's cup and that stretch: the qualities the grasp sets would
hold if re-made with it (these attempts are the current model's choices; the same model choosing
its own grasps: sims/suction_model_station.py). Prints the agreement with the YuMi's outcome of a draw with p = quality (expected)
and of "quality >= 0.5", per model, over the suction attempts and over all attempts (the jaw
attempts keep their recorded quality).

    .venv/bin/python sims/fidelity_suction_models.py docs/data/fidelity_reach_v4_N10.jsonl --heap-dir HEAPS \
        [--samples 16] [--stretch 0.2]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from ms_drake.experiments.harness import cached_heap
from ms_drake.grasping.grasp import SuctionGrasp
from ms_drake.grasping.grasp_sets import _down
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
    ap.add_argument("--stretch", type=float, default=0.1, help="the lip springs' stretch limit of models (d), (e)")
    a = ap.parse_args()
    attempts = [r for r in map(json.loads, open(a.records)) if r.get("kind") == "attempt"]
    jaw = [r for r in attempts if r["grasp"] != "suction"]
    recs = [r for r in attempts if r["grasp"] == "suction"]
    kappa = 0.6 / (np.pi * 0.015)  # pi r kappa = f r at 40 N
    cup = dict(vacuum_force=40.0, friction=1.0, stiffness=kappa)
    models = {"grasp sets (gravity along the approach)": None,
              "(a) real tilt": SuctionEvaluator(),
              "(b) real tilt, station cup": SuctionEvaluator(**cup),
              "(c) real tilt, station cup, heap load": SuctionEvaluator(**cup),
              f"(d) real tilt, station cup, stretch {a.stretch:g}": SuctionEvaluator(**cup, max_stretch=a.stretch),
              f"(e) gravity along the approach, station cup, stretch {a.stretch:g}":
                  SuctionEvaluator(**cup, max_stretch=a.stretch)}
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
                if m.startswith("(e)"):  # the grasp sets' frame: the object turned so the approach is -z
                    R, t = X[:3, :3], X[:3, 3]
                    g_O = SuctionGrasp(R.T @ (np.asarray(r["center"], float) - t), R.T @ np.asarray(r["approach"], float))
                    Xd = _down(g_O.approach)
                    qual = ev.quality(mesh, Xd, g_O.transformed(Xd), mass, a.samples, seed=r["seed"], com=com)
                else:
                    qual = ev.quality(mesh, X, g, mass + extra, a.samples, seed=r["seed"], com=com)
            rows[m].append((qual, full))
        print(r["seed"], name, "full", int(full), " ".join(f"{rows[m][-1][0]:.2f}" for m in models), flush=True)
    jq = np.array([float(r["quality"]) for r in jaw])
    jf = np.array([bool(r["full_lifted"]) for r in jaw])
    print(f"\n{len(recs)} suction attempts ({len(jaw)} jaw attempts, their recorded quality); agreement with the YuMi:")
    for m, v in rows.items():
        qs, fs = np.array([x[0] for x in v]), np.array([x[1] for x in v])
        draw = np.sum(np.where(fs, qs, 1 - qs))
        det = np.sum((qs >= 0.5) == fs)
        jdraw, jdet = np.sum(np.where(jf, jq, 1 - jq)), np.sum((jq >= 0.5) == jf)
        n = len(qs) + len(jq)
        print(f"  {m}: mean quality {qs.mean():.2f}; suction: draw (expected) {100 * draw / len(qs):.0f} %, "
              f"quality >= 0.5 {det} / {len(qs)}; all attempts: draw {100 * (draw + jdraw) / n:.1f} %, "
              f"quality >= 0.5 {det + jdet} / {n} ({100 * (det + jdet) / n:.1f} %)")


if __name__ == "__main__":
    main()
