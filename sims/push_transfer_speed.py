"""The push study's primitive push with fast transfers: does it change what a push does?

The primitive jaw's push (PrimitiveBackend) spends most of its simulated time on the two transfers
between its park pose beside the bin and the point above the push, in free space above the walls
(0.5 m/s by default). `StudyParams.transfer_speed` runs those two legs faster; everything near the
objects (down to the start, along the segment, up) is unchanged. For every push of an improvable
heap record (the data step's push of each policy), this executes the same push from the record's
state at the recorded setting and at the fast one, and compares:
  * the objects' motion, with the agreement test of the push-fidelity benchmark
    (ms_drake.experiments.push_fidelity.agreement: 2 cm + 25 % of the displacement);
  * the overall gain (Q*_o after - before, the study's GraspSets seeded by the heap's seed);
  * CPU seconds of the push's simulation.

    .venv/bin/python sims/push_transfer_speed.py --heap-dir DIR --heaps 30 --speed 2.0 \
        --out docs/data/push_transfer_speed.jsonl --json docs/data/push_transfer_speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ms_drake.experiments.push_fidelity import _centres, agreement, object_motion, wilson
from ms_drake.experiments.push_study import (
    GraspSets,
    PushWorld,
    StudyParams,
    _append,
    improvable_records,
    read_jsonl,
    state_metrics,
)
from ms_drake.pushing.policies import POLICIES
from ms_drake.scenes.heaps import heap_from_dict
from ms_drake.types import Push


def compare_heap(rec: dict, speed: float, done: set) -> list[dict]:
    heap = heap_from_dict(rec["heap"])
    params = StudyParams(object_set=rec.get("object_set", ""))
    sides = {"recorded": params, "fast": replace(params, transfer_speed=speed)}
    worlds = {}
    for name, p in sides.items():
        w = PushWorld(heap, p)
        w.set_state(rec["state"])
        worlds[name] = (w, w.snapshot())
    w0 = worlds["recorded"][0]
    ids = w0.present()
    c0 = _centres(w0, ids)
    R0 = {oid: w0.pose(oid)[:3, :3] for oid in ids}
    before = state_metrics(w0, GraspSets(params, int(rec["seed"])))
    rows = []
    for policy in POLICIES:
        r = rec["policies"].get(policy) or {}
        if not r.get("push") or (int(rec["seed"]), policy) in done:
            continue
        push = Push(tuple(r["push"]["start"]), tuple(r["push"]["end"]), r["push"]["object"])
        row = {"seed": int(rec["seed"]), "policy": policy, "speed": speed}
        for name, (w, snap) in worlds.items():
            w.restore(snap)
            c = time.process_time()
            try:
                sim_s = w.execute_push(push)
            except RuntimeError as e:
                row[name] = {"status": "error", "error": str(e).splitlines()[0] if str(e) else "RuntimeError"}
                continue
            cpu = time.process_time() - c
            after = state_metrics(w, GraspSets(params, int(rec["seed"])))
            row[name] = {"status": "ok", "sim_s": float(sim_s), "cpu_s": cpu,
                         "overall_gain": after["overall"] - before["overall"],
                         "motion": object_motion(w, ids, c0, R0)}
        if all(row.get(n, {}).get("status") == "ok" for n in sides):
            ok, per = agreement(row["recorded"]["motion"], row["fast"]["motion"])
            row.update(agree=ok, max_gap=max(v["gap"] for v in per.values()),
                       gain_equal=abs(row["recorded"]["overall_gain"] - row["fast"]["overall_gain"]) < 1e-9)
        rows.append(row)
    return rows


def summarize(rows: list[dict]) -> dict:
    ok = [r for r in rows if "agree" in r]
    k = sum(r["agree"] for r in ok)
    g = sum(r["gain_equal"] for r in ok)
    cpu = {n: [r[n]["cpu_s"] for r in ok] for n in ("recorded", "fast")}
    sim = {n: [r[n]["sim_s"] for r in ok] for n in ("recorded", "fast")}
    gains = {n: [r[n]["overall_gain"] for r in ok] for n in ("recorded", "fast")}
    return {
        "pushes": len(rows), "compared": len(ok),
        "agree": {"k": k, "n": len(ok), "ci95": list(wilson(k, len(ok)))},
        "gain_equal": {"k": g, "n": len(ok), "ci95": list(wilson(g, len(ok)))},
        "mean_overall_gain": {n: float(np.mean(v)) if v else 0.0 for n, v in gains.items()},
        "cpu_s_per_push": {n: {"median": float(np.median(v)), "mean": float(np.mean(v))} if v else {}
                           for n, v in cpu.items()},
        "sim_s_per_push": {n: float(np.mean(v)) if v else 0.0 for n, v in sim.items()},
        "max_gap_m": {"median": float(np.median([r["max_gap"] for r in ok])) if ok else 0.0,
                      "max": float(max([r["max_gap"] for r in ok], default=0.0))},
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heap-dir", type=Path, required=True)
    ap.add_argument("--heaps", type=int, default=30)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--speed", type=float, default=2.0, help="transfer speed of the fast side [m/s]")
    ap.add_argument("--out", type=Path, required=True, help="JSONL (appended to; resumes)")
    ap.add_argument("--json", type=Path, default=None, help="write the summary here")
    a = ap.parse_args()
    if a.speed <= 0:
        ap.error(f"--speed must be > 0 m/s, got {a.speed}")
    recs = improvable_records(a.heap_dir, a.heaps, a.seed_start)
    if not recs:
        ap.error(f"no improvable heap records in {a.heap_dir} (run `ms-drake data push-heaps` first)")
    done = {(int(r["seed"]), r["policy"]) for r in read_jsonl(a.out)} if a.out.exists() else set()
    for rec in tqdm(recs, desc="heaps", unit="heap"):
        for row in compare_heap(rec, a.speed, done):
            _append(a.out, row)
    s = summarize([r for r in read_jsonl(a.out) if r["speed"] == a.speed])
    print(json.dumps(s, indent=1))
    if a.json:
        a.json.write_text(json.dumps(s, indent=1) + "\n")


if __name__ == "__main__":
    main()
