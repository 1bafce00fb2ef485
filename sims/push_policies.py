"""Ch. 4 push policies: planning speed per policy and source, and before/after pictures of heaps.

    .venv/bin/python sims/push_policies.py speed --heaps 20 --objects 8 --out docs/data/push_planning_speed.json
    .venv/bin/python sims/push_policies.py example --seed 3 --out docs/figures/push_example_3.png
    .venv/bin/python sims/push_policies.py example --seed 12 --object-set ycb --out docs/figures/push_example_ycb_12.png

speed: CPU ms to plan one push (ms_drake.experiments.push_study.planning_speed) on dropped
BinHeap15 heaps, from full state (coal) and from the depth image with ground-truth masks.
example: Algorithm 1 replayed on heap `seed`, then every policy's push drawn before and after
(push_study.push_example_figure, the Fig. 4.4 / 4.5 layout).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ms_drake.experiments.push_study import StudyParams, planning_speed, push_example_figure


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("speed", "example"))
    ap.add_argument("--heaps", type=int, default=20)
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--object-set", default="", help="example: the heaps' object set (as `ms-drake data push-heaps`)")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    if a.what == "speed":
        r = planning_speed(a.heaps, a.seed_start, a.objects)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(r, indent=1))
        print(json.dumps(r, indent=1))
    else:
        print(json.dumps(push_example_figure(a.seed, a.out, StudyParams(object_set=a.object_set)), indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
