"""IndexedGraspPlanner on bin heaps (issue #15): CPU of indexing and checking every visible object of a
heap (one core), and per visible object the best grasp quality it finds vs the image-based planners.

    OMP_NUM_THREADS=1 .venv/bin/python sims/bench_indexed_grasps.py --objects 15 --heaps 20 --seed-start 1000 \\
        --workers 1 --out /tmp/indexed.jsonl [--image]

One JSON line per heap: visible objects, CPU ms of the whole heap (scene build + every object; the
median of 5 repeats), objects with a grasp >= 0.15 (indexed; with --image also the image planners'
jaw + suction, the search's settings). Resumable.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.heap_grasps import heap_grasp_inputs
from ms_drake.geometry import Workspace
from ms_drake.grasping.grasp_sets import load_grasp_sets
from ms_drake.grasping.indexed import IndexedGraspPlanner, environment_parts
from ms_drake.grasping.planner import GraspPlanner, LazyGraspPlanner
from ms_drake.parallel import run_jobs
from ms_drake.scenario import load_scenario

THRESHOLD = 0.15


def job(j):
    objects, seed, heap_dir, image = j
    s = load_scenario(None, "BinHeap15")
    heap = cached_heap(objects, seed, heap_dir)
    inp = heap_grasp_inputs(s, heap)
    sets = load_grasp_sets(inp.names.values())
    gsets = {oid: sets[n] for oid, n in inp.names.items() if n in sets}
    planner = IndexedGraspPlanner(inp.names, gsets, environment_parts(s), Workspace.from_scenario(s), 640, 480)
    geoms = {o.id: o for o in inp.objects}
    planner.scene(inp.objects)  # warm the per-object shape cache (once per process and object)
    times, best = [], {}
    for _ in range(5):
        t = time.process_time()
        scene = planner.scene(inp.objects)
        res = {oid: planner.plan_object(oid, geoms, scene) for oid in inp.masks.ids}
        times.append(time.process_time() - t)
    for oid, gs in res.items():
        best[oid] = max([g.quality for g in gs], default=0.0)
    rec = dict(objects=objects, seed=seed, present=len(heap.objects), visible=len(inp.masks.ids),
               with_set=sum(oid in gsets for oid in inp.masks.ids), cpu_ms=1000 * float(np.median(times)),
               cpu_ms_max=1000 * float(np.max(times)),
               indexed_above=sum(q >= THRESHOLD for q in best.values()),
               indexed_kinds={k: sum(1 for gs in res.values() for g in gs if g.kind == k and g.quality >= THRESHOLD)
                              for k in ("parallel_jaw", "suction")})
    if image:
        planners = [GraspPlanner(inp.camera_info, inp.X_WC, model=m, num_samples=8, robust_samples=4, seed=seed)
                    for m in ("soft_point", "suction")]
        lazy = LazyGraspPlanner(planners, 640, 480, seed=seed)
        t = time.process_time()
        ib = {oid: max([g.quality for g in lazy.plan_object(inp.depth, inp.masks, geoms, oid)], default=0.0)
              for oid in inp.masks.ids}
        rec["image_cpu_ms"] = 1000 * (time.process_time() - t)
        rec["image_above"] = sum(q >= THRESHOLD for q in ib.values())
    return rec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--heaps", type=int, default=20)
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--heap-dir", default=None)
    ap.add_argument("--image", action="store_true")
    ap.add_argument("--out", default="/tmp/indexed.jsonl")
    a = ap.parse_args()
    out = Path(a.out)
    done = {r["seed"] for r in map(json.loads, out.read_text().splitlines())} if out.exists() else set()
    jobs = [(a.objects, s, a.heap_dir, a.image) for s in range(a.seed_start, a.seed_start + a.heaps) if s not in done]
    with open(out, "a") as f:
        for r in run_jobs(job, jobs, workers=a.workers):
            if r.ok:
                f.write(json.dumps(r.value) + "\n")
                f.flush()
            else:
                print("failed", r.job, r.error.strip().splitlines()[-1:])
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    cpu = np.array([r["cpu_ms"] for r in recs])
    vis = sum(r["visible"] for r in recs)
    print(f"{len(recs)} heaps of N={a.objects}: present mean {np.mean([r['present'] for r in recs]):.2f}, visible "
          f"mean {vis / len(recs):.1f}; indexing + checking all visible objects: CPU ms median {np.median(cpu):.1f} "
          f"mean {cpu.mean():.1f} max {cpu.max():.1f}; objects with a grasp >= {THRESHOLD}: indexed "
          f"{sum(r['indexed_above'] for r in recs)} / {vis}")
    if all("image_above" in r for r in recs):
        print(f"image planners: {sum(r['image_above'] for r in recs)} / {vis}; CPU ms per heap mean "
              f"{np.mean([r['image_cpu_ms'] for r in recs]):.0f}")


if __name__ == "__main__":
    main()
