"""The push study's cost: the five policies on improvable heaps from their stored states.

Issue 14's speed goal is the study's 400 heaps x 5 policies in <= 60 min on 2 cores. This runs,
per heap, what the study does once the improvable states exist (ms_drake.experiments.push_study.
policies_from_state: the world, Q*_o before, each policy's plan, its push in physics, Q*_o after)
with a local pool, and reports the wall time, the CPU per heap and the 400-heap projection.
Algorithm 1 itself (dropping heaps and grasping until stuck, to find the improvable states) is the
data step (`ms-drake data push-heaps`) and is not part of this.

    .venv/bin/python sims/push_study_speed.py --heap-dir DIR --heaps 40 --workers 2 \
        --transfer-speed 2.0 --out docs/data/push_study_speed.jsonl --json docs/data/push_study_speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ms_drake.experiments.push_study import (
    METRICS,
    StudyParams,
    _append,
    improvable_records,
    read_jsonl,
    state_job,
)
from ms_drake.parallel import run_jobs
from ms_drake.pushing.policies import POLICIES


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heap-dir", type=Path, required=True)
    ap.add_argument("--heaps", type=int, default=40)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--transfer-speed", type=float, default=None, help="m/s (default: the push's travel speed)")
    ap.add_argument("--out", type=Path, required=True, help="JSONL, one line per heap (appended to; resumes)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    if a.transfer_speed is not None and a.transfer_speed <= 0:
        ap.error(f"--transfer-speed must be > 0 m/s, got {a.transfer_speed}")
    recs = improvable_records(a.heap_dir, a.heaps, a.seed_start)
    if not recs:
        ap.error(f"no improvable heap records in {a.heap_dir} (run `ms-drake data push-heaps` first)")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    done = {int(r["seed"]) for r in read_jsonl(a.out) if r.get("transfer_speed") == a.transfer_speed} \
        if a.out.exists() else set()
    params = asdict(StudyParams(transfer_speed=a.transfer_speed))
    jobs = [(r, POLICIES, params) for r in recs if int(r["seed"]) not in done]
    t0 = time.perf_counter()
    with tqdm(total=len(jobs), desc="heaps x 5 policies", unit="heap") as bar:
        for r in run_jobs(state_job, jobs, workers=a.workers):
            bar.update(1)
            if not r.ok:
                tqdm.write(f"seed {r.job[0]['seed']}: {r.error.strip().splitlines()[-1] if r.error else 'failed'}")
                continue
            _append(a.out, {"seed": int(r.job[0]["seed"]), "transfer_speed": a.transfer_speed,
                            "cpu_s": r.value["cpu_s"], "before": r.value["before"],
                            "policies": {p: {k: v.get(k) for k in (*METRICS, "pushed", "plan_ms", "sim_cpu_s")}
                                         for p, v in r.value["policies"].items()}})
    wall = time.perf_counter() - t0
    rows = [r for r in read_jsonl(a.out) if r.get("transfer_speed") == a.transfer_speed]
    cpu = [r["cpu_s"] for r in rows]
    s = {"heaps": len(rows), "workers": a.workers, "transfer_speed": a.transfer_speed,
         "wall_s_this_run": wall, "heaps_this_run": len(jobs),
         "cpu_s_per_heap": {"median": float(np.median(cpu)), "mean": float(np.mean(cpu))} if cpu else {},
         "projected_400_heaps_min_on_2_cores": float(400 * np.mean(cpu) / 2 / 60) if cpu else None,
         "mean_overall_gain": {p: float(np.mean([r["policies"][p]["overall_gain"] for r in rows])) for p in POLICIES}
         if rows else {}}
    print(json.dumps(s, indent=1))
    if a.json:
        a.json.write_text(json.dumps(s, indent=1) + "\n")


if __name__ == "__main__":
    main()
