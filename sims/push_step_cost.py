"""CPU per rollout of a pushing selector at a 10 ms plant step and at PRIMITIVE_PUSH_TIME_STEP
(5 ms, the step the pushing selectors use) on the same heaps: what the 5 ms push costs the search.

    .venv/bin/python sims/push_step_cost.py --heap-dir HEAPS --seed-start 1100 --heaps 10 \\
        --heap-engine bullet --out docs/data/push_step_cost.jsonl
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ms_drake.execution import PRIMITIVE_PUSH_TIME_STEP
from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.rollout import rollout

KEYS = ("seed", "policy", "push_policy", "success", "actions", "action_kinds", "failure", "cpu_seconds", "sim_seconds")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--heap-dir", required=True, help="cached heaps (read; a missing heap is generated there)")
    ap.add_argument("--seed-start", type=int, default=1100)
    ap.add_argument("--heaps", type=int, default=10)
    ap.add_argument("--objects", type=int, default=15)
    ap.add_argument("--heap-engine", default="bullet")
    ap.add_argument("--policy", default="largest_push")
    ap.add_argument("--push-policy", default="quasi_random")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    rows = []
    for seed in range(a.seed_start, a.seed_start + a.heaps):
        heap = cached_heap(a.objects, seed, a.heap_dir, "ch7", a.heap_engine)
        for ts in (0.01, PRIMITIVE_PUSH_TIME_STEP):
            r = rollout(a.policy, a.objects, seed, heap=heap, time_step=ts, push_policy=a.push_policy).record()
            rows.append({**{k: r[k] for k in KEYS}, "time_step": ts})
            print(json.dumps(rows[-1]), flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("".join(json.dumps(r) + "\n" for r in rows))
    cpu = {ts: np.array([r["cpu_seconds"] for r in rows if r["time_step"] == ts]) for ts in (0.01, PRIMITIVE_PUSH_TIME_STEP)}
    same = sum(x["action_kinds"] == y["action_kinds"] for x, y in zip(rows[::2], rows[1::2]))
    print(f"{a.heaps} heaps: CPU s per rollout {cpu[0.01].mean():.2f} at 10 ms, {cpu[PRIMITIVE_PUSH_TIME_STEP].mean():.2f} at "
          f"{1000 * PRIMITIVE_PUSH_TIME_STEP:.0f} ms ({cpu[PRIMITIVE_PUSH_TIME_STEP].sum() / cpu[0.01].sum():.2f}x); "
          f"the same actions on {same} heaps")


if __name__ == "__main__":
    main()
