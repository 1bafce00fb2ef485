"""Pictures of the heaps where two policies of the Table 8.2 runs differ (docs/BENCHMARKS.md, X-Ray).

    .venv/bin/python sims/xray_differences.py --a FILE_A.jsonl --b FILE_B.jsonl --heap-dir DIR --out DIR [--max 4] [--seed S ...]

For each heap one policy solves and the other does not (ms_drake.experiments.harness.paired_comparison),
both rollouts are rerun with their frames (the same seeds, heap protocol and search options as the
records, ms_drake.experiments.harness.OPTION_DEFAULTS: bit-identical searches) and every step's
panels (masks and target, X-Ray's occupancy, the action; ms_drake.experiments.demo.frame_image)
are stacked into <out>/<policy>_s<seed>.png; a line per rollout lists its actions. `--seed` (repeatable)
draws those heaps instead, whichever policy solves them.
"""

import argparse
from pathlib import Path

import cv2
import numpy as np

from ms_drake.experiments.demo import frame_image
from ms_drake.experiments.harness import OPTION_DEFAULTS, cached_heap, paired_comparison, read_records
from ms_drake.experiments.rollout import rollout
from ms_drake.experiments.xray import XRAY_HORIZON, XRAY_OBJECTS
from ms_drake.geometry import PinholeCamera
from ms_drake.scenario import load_scenario


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--a", type=Path, required=True)
    ap.add_argument("--b", type=Path, required=True)
    ap.add_argument("--heap-dir", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--max", type=int, default=4, help="heaps per direction")
    ap.add_argument("--seed", type=int, action="append", default=[], help="draw these heaps (repeatable)")
    args = ap.parse_args()
    ra, rb = read_records(args.a), read_records(args.b)
    pa, pb = ra[0]["policy"], rb[0]["policy"]
    protocol = ra[0].get("protocol", "xray")

    def options(rec):  # the record's search options (a record without grasp_planner: image planners)
        opts = {k: rec.get(k, default) for k, default in OPTION_DEFAULTS if k != "heap_engine"}
        opts["grasp_planner"] = rec.get("grasp_planner", "image")
        return opts

    cmp = paired_comparison(ra, rb)
    camera = PinholeCamera.from_config(load_scenario(None, "FloatingGripperBin").cameras["overhead"])
    args.out.mkdir(parents=True, exist_ok=True)
    groups = (cmp["only_a"][:args.max], cmp["only_b"][:args.max])
    if args.seed:
        known = {r["seed"] for r in ra} & {r["seed"] for r in rb}
        missing = sorted(set(args.seed) - known)
        if missing:
            ap.error(f"--seed {missing}: not in both {args.a} and {args.b} (their common seeds: "
                     f"{min(known)}-{max(known)})" if known else f"--seed: {args.a} and {args.b} share no seed")
        groups = (args.seed,)
    for seeds in groups:
        for seed in seeds:
            heap = cached_heap(XRAY_OBJECTS, seed, args.heap_dir, protocol)
            for policy, rec in ((pa, ra[0]), (pb, rb[0])):
                r = rollout(policy, XRAY_OBJECTS, seed, horizon=XRAY_HORIZON, heap=heap, keep_frames=True,
                            **options(rec))
                pic = np.concatenate([frame_image(f, camera) for f in r.frames], axis=0)
                path = args.out / f"{policy}_s{seed}.png"
                cv2.imwrite(str(path), cv2.resize(pic, None, fx=0.5, fy=0.5)[:, :, ::-1])
                print(f"seed {seed} {policy}: {'success' if r.success else r.failure} after {r.actions}; "
                      + "; ".join(f"{f.step}: {f.action.reason}" for f in r.frames) + f" -> {path}")


if __name__ == "__main__":
    main()
