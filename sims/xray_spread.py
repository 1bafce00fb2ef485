"""Does a wider heap widen X-Ray's margin? The `xray_occluded` heaps with another offset spread.

The reference gives, as one case of X-Ray's margin over Largest, heaps with "many large objects,
but some lying to the side" (lines 1518-1520); its text does not give the spread of its truncated
Gaussian offsets. This runs X-Ray, Largest and the oracle on `xray_occluded` heaps whose offsets
have another sigma (the protocol's: 8 cm), with the lid target, H = 10, the image grasp planners:

    .venv/bin/python sims/xray_spread.py --sigma 0.14 --seed-start 7000 --heaps 60 --heap-dir DIR \
        --out FILE.jsonl

Resumable (one line per rollout in FILE; heaps cached in DIR, one file per seed); prints the
success of each policy on the heaps all three searched and the heaps only one of X-Ray and Largest
solved.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
from pathlib import Path

from ms_drake.experiments.rollout import rollout
from ms_drake.experiments.xray import XRAY_HORIZON, XRAY_OBJECTS, XRAY_OCCLUDED_HEAPS, _names, xray_heap_settings
from ms_drake.paths import code_version
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import generate_heap, heap_digest, heap_to_dict, load_heap

POLICIES = ("xray", "largest", "oracle")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sigma", type=float, required=True, help="offset sigma (m); xray_occluded: 0.08")
    ap.add_argument("--seed-start", type=int, default=7000)
    ap.add_argument("--heaps", type=int, default=60)
    ap.add_argument("--heap-dir", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    params = dataclasses.replace(XRAY_OCCLUDED_HEAPS, offset_sigma=args.sigma)
    _, pool = xray_heap_settings("xray_occluded")
    args.heap_dir.mkdir(parents=True, exist_ok=True)
    done = {(r["seed"], r["policy"]) for r in map(json.loads, args.out.open())} if args.out.exists() else set()
    for seed in range(args.seed_start, args.seed_start + args.heaps):
        path = args.heap_dir / f"heap_sigma{args.sigma}_s{seed}.json"
        if path.exists():
            heap = load_heap(path)
        else:
            heap = generate_heap(load_scenario(None, "BinHeap15"), XRAY_OBJECTS + 1, seed, params=params,
                                 names_fn=functools.partial(_names, occluders=XRAY_OBJECTS, pool=pool),
                                 target_first=True)
            path.write_text(json.dumps(heap_to_dict(heap)))
        for policy in POLICIES:
            if (seed, policy) in done:
                continue
            rec = rollout(policy, XRAY_OBJECTS, seed, "primitive", XRAY_HORIZON, heap=heap,
                          grasp_planner="image").record()
            rec.update(sigma=args.sigma, heap_digest=heap_digest(heap), code=code_version())
            with args.out.open("a") as f:
                f.write(json.dumps(rec) + "\n")
            print(f"seed {seed} {policy}: {'success' if rec['success'] else rec['failure']} after "
                  f"{rec['actions']} actions", flush=True)
    recs = [json.loads(line) for line in args.out.open()]
    by = {}
    for r in recs:
        by.setdefault(r["seed"], {})[r["policy"]] = r["success"]
    common = sorted(s for s, v in by.items() if all(p in v for p in POLICIES))
    for p in POLICIES:
        print(f"{p}: {sum(by[s][p] for s in common)} / {len(common)}")
    print(f"X-Ray only {sum(by[s]['xray'] and not by[s]['largest'] for s in common)}, "
          f"Largest only {sum(by[s]['largest'] and not by[s]['xray'] for s in common)}")


if __name__ == "__main__":
    main()
