"""Ch. 4 push policies: planning speed per policy and source, and before/after pictures of heaps.

    .venv/bin/python sims/push_policies.py speed --heaps 20 --objects 8 --out docs/data/push_planning_speed.json
    .venv/bin/python sims/push_policies.py example --seed 3 --out docs/figures/push_example_3.png
    .venv/bin/python sims/push_policies.py example --seed 12 --object-set ycb --out docs/figures/push_example_ycb_12.png
    .venv/bin/python sims/push_policies.py example --seed 368 --object-set ycb --sampling object --transfer-speed 2.0 \
        --with-checked --out docs/figures/push_ycb_crn/push_example_368.png

speed: CPU ms to plan one push (ms_drake.experiments.push_study.planning_speed) on dropped
BinHeap15 heaps, from full state (coal) and from the depth image with ground-truth masks.
example: Algorithm 1 replayed on heap `seed`, then every policy's push drawn before and after
(push_study.push_example_figure, the Fig. 4.4 / 4.5 layout); --with-checked adds the collision-checked
quasi-random (PolicyParams.quasi_random_checked, the ablation of sims/push_ablation.py); --sampling and
--transfer-speed as `ms-drake data push-heaps` (the heaps' own settings replay their stuck state).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ms_drake.experiments.push_study import StudyParams, planning_speed, push_example_figure
from ms_drake.pushing import POLICIES, PolicyParams


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("speed", "example"))
    ap.add_argument("--heaps", type=int, default=20)
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--object-set", default="", help="example: the heaps' object set (as `ms-drake data push-heaps`)")
    ap.add_argument("--sampling", default="tilt_bin", help="example: the heaps' grasp sampling")
    ap.add_argument("--transfer-speed", type=float, default=None, help="example: the heaps' transfer speed")
    ap.add_argument("--with-checked", action="store_true", help="example: also the collision-checked quasi-random")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    if a.what == "speed":
        r = planning_speed(a.heaps, a.seed_start, a.objects)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(r, indent=1))
        print(json.dumps(r, indent=1))
    else:
        policies = list(POLICIES)
        if a.with_checked:
            policies.insert(1, ("quasi_random_checked", "quasi_random", PolicyParams(quasi_random_checked=True)))
        params = StudyParams(object_set=a.object_set, sampling=a.sampling, transfer_speed=a.transfer_speed)
        print(json.dumps(push_example_figure(a.seed, a.out, params, policies), indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
