"""The push study's full fidelity on recorded stuck states with the pushes planned again by the
current policies (push_height's minimum height) instead of the record's pushes: each policy's
push from the record's state on the YuMi and in the primitive mode (FidelityPair.compare, the
rows of `ms-drake bench push-fidelity`). For heap records made before the push height changed.

    .venv/bin/python sims/push_fidelity_replan.py --heap-dir docs/data/push_heaps --heaps 27 \\
        --out docs/data/push_fidelity_replan.jsonl --json docs/data/push_fidelity_replan.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ms_drake.experiments.push_fidelity import FidelityPair, format_fidelity, pushed_records, summarize_fidelity
from ms_drake.experiments.push_study import _append, read_jsonl
from ms_drake.pushing.policies import POLICIES, PolicyParams, plan_policy_push, state_scene


def replanned_rows(rec: dict) -> list[dict]:
    """One row per policy that finds a push on the record's state (the study's policy seeds)."""
    pair = FidelityPair(rec)
    w = pair.worlds["primitive"][0]
    w.restore(pair.worlds["primitive"][1])
    scene = state_scene(w.geometry(pair.ids), w.workspace)
    rows = []
    for p in POLICIES:
        push = plan_policy_push(p, scene, PolicyParams(), seed=[pair.seed, POLICIES.index(p)])
        if push is not None:
            rows.append(pair.compare(p, {"start": list(push.start), "end": list(push.end), "object": push.object_id}))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--heap-dir", type=Path, action="append", required=True)
    ap.add_argument("--heaps", type=int, default=27)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    done = {int(r["seed"]) for r in read_jsonl(a.out)}
    for rec, _ in pushed_records(a.heap_dir, a.heaps, a.seed_start):
        if int(rec["seed"]) in done:
            continue
        for row in replanned_rows(rec):
            _append(a.out, row)
        print(f"heap {rec['seed']} done", flush=True)
    seeds = {int(r["seed"]) for r, _ in pushed_records(a.heap_dir, a.heaps, a.seed_start)}
    s = summarize_fidelity([r for r in read_jsonl(a.out) if int(r["seed"]) in seeds])
    print(format_fidelity(s))
    if a.json:
        a.json.write_text(json.dumps(s, indent=1) + "\n")


if __name__ == "__main__":
    main()
