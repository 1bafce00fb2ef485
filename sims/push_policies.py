"""Ch. 4 push policies: planning speed per policy and source, and before/after pictures of heaps.

    .venv/bin/python sims/push_policies.py speed --heaps 20 --objects 8 --out out/push_planning_speed.json
    .venv/bin/python sims/push_policies.py example --seed 12 --out out/push_example_12.png
    .venv/bin/python sims/push_policies.py example --seed 3 --set object_set=procedural --out out/push_example_3.png
    .venv/bin/python sims/push_policies.py example --seed 368 --set ablation.sampling=object \
        --set ablation.transfer_speed=2.0 --with-checked --out out/push_example_368.png

speed: CPU ms to plan one push (ms_drake.experiments.push_study.planning_speed) on dropped
BinHeap15 heaps, from full state (coal) and from the depth image with ground-truth masks.
example: Algorithm 1 replayed on heap `seed`, then every policy's push drawn before and after
(push_study.push_example_figure, the Fig. 4.4 / 4.5 layout); --with-checked adds the collision-checked
quasi-random (the study's ablation.quasi_random_checked, as sims/push_ablation.py); --set KEY=VALUE as
`ms-drake data push-heaps` (the heaps' own config replays their stuck state).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ms_drake.config_files import load_config
from ms_drake.experiments.push_study import PushStudyConfig, planning_speed, push_example_figure
from ms_drake.pushing import POLICIES, PolicyParams


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("speed", "example"))
    ap.add_argument("--heaps", type=int, default=20)
    ap.add_argument("--objects", type=int, default=8)
    ap.add_argument("--seed-start", type=int, default=0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], help="example: a field of the heaps' PushStudyConfig, "
                    "KEY=VALUE (repeatable, as `ms-drake data push-heaps --set`)")
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
        params = load_config(PushStudyConfig, None, a.set)
        print(json.dumps(push_example_figure(a.seed, a.out, params, policies), indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
