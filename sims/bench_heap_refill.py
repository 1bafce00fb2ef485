"""Heaps that hold N objects (issue #15): objects leaving the bin dropped again (HeapParams.refill_rounds)
vs removed (refill_rounds = 0), paired on the same seeds.

    .venv/bin/python sims/bench_heap_refill.py --engine bullet --objects 15 --heaps 50 --seed-start 1000 \\
        --workers 1 --out /tmp/refill_bullet.jsonl
    .venv/bin/python sims/bench_heap_refill.py --report /tmp/refill_bullet.jsonl

One JSON line per (seed, mode): objects in the heap, attempts, re-drop rounds and objects re-dropped
(of the accepted attempt), CPU seconds of generate_heap. Resumable (seeds already in --out are kept).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from ms_drake.parallel import run_jobs
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, HeapParams, generate_heap

ENGINES = {"bullet": HeapParams(), "drake": SEARCH_HEAPS}


def job(j):
    engine, objects, seed, mode = j
    params = dataclasses.replace(ENGINES[engine], refill_rounds=0 if mode == "remove" else ENGINES[engine].refill_rounds)
    t = time.process_time()
    heap, d = generate_heap(load_scenario(None, "BinHeap15"), objects, seed, params=params, return_diagnostics=True)
    return dict(engine=engine, objects=objects, seed=seed, mode=mode, present=len(heap.objects), attempts=d.attempts,
                refills=d.refills, redropped=d.redropped, cpu_s=time.process_time() - t,
                rejected=d.rejected_reasons)


def report(path):
    recs = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    for mode in ("remove", "refill"):
        r = [x for x in recs if x["mode"] == mode]
        if not r:
            continue
        pres = np.array([x["present"] for x in r])
        att = np.array([x["attempts"] for x in r])
        ref = np.array([x["refills"] for x in r])
        red = np.array([x["redropped"] for x in r])
        cpu = np.array([x["cpu_s"] for x in r])
        print(f"{r[0]['engine']} N={r[0]['objects']} {mode}: {len(r)} heaps; objects in the heap mean {pres.mean():.2f} "
              f"(min {pres.min()}), all N in {np.mean(pres == r[0]['objects']) * 100:.0f} %; attempts mean {att.mean():.2f} "
              f"max {att.max()}; re-drop rounds mean {ref.mean():.2f} max {ref.max()}; objects re-dropped mean "
              f"{red.mean():.2f} max {red.max()}; CPU s per heap median {np.median(cpu):.2f} mean {cpu.mean():.2f} "
              f"max {cpu.max():.2f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--engine", choices=list(ENGINES), default="bullet")
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--heaps", type=int, default=50)
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", default="/tmp/refill.jsonl")
    ap.add_argument("--report", default=None)
    a = ap.parse_args()
    if a.report:
        return report(a.report)
    out = Path(a.out)
    done = set()
    if out.exists():
        done = {(r["engine"], r["objects"], r["seed"], r["mode"]) for r in map(json.loads, out.read_text().splitlines())}
    jobs = [(a.engine, a.objects, s, m) for s in range(a.seed_start, a.seed_start + a.heaps) for m in ("remove", "refill")
            if (a.engine, a.objects, s, m) not in done]
    with open(out, "a") as f:
        for r in run_jobs(job, jobs, workers=a.workers):
            if r.ok:
                f.write(json.dumps(r.value) + "\n")
                f.flush()
            else:
                print("failed", r.job, r.error.strip().splitlines()[-1:])
    report(out)


if __name__ == "__main__":
    main()
