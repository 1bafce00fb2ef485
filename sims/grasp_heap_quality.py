"""Jaw GraspPlanner on bin heaps: the fraction of visible objects with a grasp above t = 0.15.

    OMP_NUM_THREADS=1 .venv/bin/python sims/grasp_heap_quality.py --heaps 10 --objects 15
    (--diagnose prints each object's candidate outcome reasons; --out FILE writes JSON lines)

Same planner settings as the bin-search pilot (ms_drake/experiments/rollout.py): model
soft_point, 8 candidates per mask, 4 robust trials, default GraspEvaluator parameters.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--heaps", type=int, default=10)
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--model", default="soft_point")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--robust", type=int, default=4)
    ap.add_argument("--threshold", type=float, default=0.15)
    ap.add_argument("--closing-force", type=float, default=None, help="GraspEvaluator closing_force [N]")
    ap.add_argument("--jaw-margin", type=float, default=None, help="GraspPlanner jaw_margin [m]")
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--out", default="")
    ap.add_argument("--heap-dir", default="", help="cache the generated heaps here (JSON) and reuse them")
    args = ap.parse_args()

    from ms_drake.experiments.heap_grasps import heap_grasp_inputs, heap_grasp_report
    from ms_drake.grasping.planner import GraspPlanner
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import generate_heap, load_heap, save_heap

    s = load_scenario(None, "BinHeap15")
    params = {} if args.closing_force is None else {"closing_force": args.closing_force}
    kw = {} if args.jaw_margin is None else {"jaw_margin": args.jaw_margin}
    all_rows, reasons = [], Counter()
    t_plan = 0.0
    for h in range(args.heaps):
        seed = args.seed0 + h
        path = Path(args.heap_dir) / f"heap_{args.objects}_{seed}.json" if args.heap_dir else None
        if path is not None and path.is_file():
            heap = load_heap(path)
        else:
            heap = generate_heap(s, args.objects, seed)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                save_heap(heap, path)
        inputs = heap_grasp_inputs(s, heap)
        planner = GraspPlanner(inputs.camera_info, inputs.X_WC, model=args.model, num_samples=args.samples,
                               robust_samples=args.robust, seed=seed, evaluator_params=params, **kw)
        c0 = time.process_time()
        rows = heap_grasp_report(inputs, planner, diagnose=args.diagnose, scenario=s)
        t_plan += time.process_time() - c0
        for r in rows:
            r["heap"] = seed
            reasons.update(r.get("reasons", {}))
            g = r.pop("grasp")
            r["width"] = float(g.width) if g is not None else None
            if args.diagnose:
                print(f"  heap {seed} {r['name']:28s} vis {r['visible']:.2f} px {r['pixels']:6d} "
                      f"size_ok {int(r['graspable_size'])} q {r['quality']:.2f} cands {r.get('candidates')} "
                      f"{r.get('reasons')} collides {r['collides']}")
        all_rows.extend(rows)
        above = [r["quality"] > args.threshold for r in rows]
        free = [r["quality"] > args.threshold and not r["collides"] for r in rows]
        print(f"heap {seed}: {sum(above)} / {len(rows)} visible objects with q > {args.threshold} "
              f"({sum(free)} of them with a collision-free jaw)", flush=True)
    q = np.array([r["quality"] for r in all_rows])
    sized = np.array([r["graspable_size"] for r in all_rows])
    vis = np.array([r["visible"] for r in all_rows]) >= 0.5
    sel = sized & vis
    print(f"\n{args.heaps} heaps x {args.objects} objects, model {args.model}, {args.samples} candidates, "
          f"{args.robust} robust trials; {len(all_rows)} visible objects")
    print(f"fraction with q > {args.threshold}: all visible {np.mean(q > args.threshold):.2f}; "
          f"graspable-sized and >= 50 % visible ({sel.sum()}): {np.mean(q[sel] > args.threshold):.2f}")
    ok = np.array([r["quality"] > args.threshold and not r["collides"] for r in all_rows])
    coll = np.array([bool(r["collides"]) for r in all_rows if r["width"] is not None])
    print(f"fraction with q > {args.threshold} and a collision-free jaw: all visible {np.mean(ok):.2f}; "
          f"graspable-sized and >= 50 % visible: {np.mean(ok[sel]):.2f}; chosen grasps whose jaw collides: "
          f"{np.mean(coll) if len(coll) else 0:.2f} of {len(coll)}")
    print(f"planner CPU: {1e3 * t_plan / max(len(all_rows), 1):.0f} ms per object")
    if args.diagnose:
        print("candidate outcomes (nominal):", dict(reasons))
    if args.out:
        with open(args.out, "w") as f:
            for r in all_rows:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
