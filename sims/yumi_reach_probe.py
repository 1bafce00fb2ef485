"""Which grasps at a bin station the YuMi reaches, for several base positions (planning only).

For each base x (the bin centre at x = 0): the arms' park configurations are solved by IK (tools
pointing down, tcps at (base x + PARK_FORWARD, -/+ PARK_SIDE, PARK_HEIGHT): out of the overhead
camera's view), then PickReach (the FullBackend's own pick plan from park) is asked about grasps
on a grid over the bin: 4 x 3 positions 6 cm above the floor, approach straight down or tilted
40 degrees towards +x, -x, +y, -y; the right arm with the jaw, the left arm with the suction cup.

    .venv/bin/python sims/yumi_reach_probe.py --base-x -0.55 -0.50 -0.45 --out docs/data/yumi_reach_probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform

import ms_drake.robots as robots
from ms_drake.execution.reach import PickReach
from ms_drake.planning.cartesian import ik_pose
from ms_drake.planning.sequences import arm_ik
from ms_drake.scenario import load_scenario
from ms_drake.types import Grasp

PARK_FORWARD, PARK_SIDE, PARK_HEIGHT = 0.25, 0.30, 0.30


def park_homes(scenario) -> dict:
    """{arm: joint positions} of the park for the scenario's base (IK from the current homes)."""
    out = {}
    for arm, side in (("yumi_right", -1.0), ("yumi_left", 1.0)):
        ik, _, q_home, _keep = arm_ik(scenario, arm)
        X = ik_pose(ik, q_home)
        base = scenario.robot.base_position
        res = ik.solve(RigidTransform(X.rotation(), [base[0] + PARK_FORWARD, side * PARK_SIDE, PARK_HEIGHT]),
                       q_seed=q_home)
        if not res.success:
            raise RuntimeError(f"park of {arm} at base x {base[0]}: IK {res.status}")
        out[arm] = tuple(float(v) for v in res.q)
    return out


def with_homes(homes: dict):
    """Use `homes` as the YuMi's ArmSpec.home (module state of ms_drake.robots; this script only)."""
    spec = robots.ROBOTS["yumi"]
    arms = {a: dataclasses.replace(s, home=homes.get(a, s.home)) for a, s in spec.arms.items()}
    robots.ROBOTS["yumi"] = dataclasses.replace(spec, arms=arms)


def grasps(kind: str):
    t = np.radians(40.0)
    dirs = {"down": (0, 0, -1), "+x": (np.sin(t), 0, -np.cos(t)), "-x": (-np.sin(t), 0, -np.cos(t)),
            "+y": (0, np.sin(t), -np.cos(t)), "-y": (0, -np.sin(t), -np.cos(t))}
    for x in (-0.15, -0.05, 0.05, 0.15):
        for y in (-0.12, 0.0, 0.12):
            for name, d in dirs.items():
                yield name, Grasp(kind=kind, center=(x, y, 0.06), approach=tuple(float(v) for v in d),
                                  axis=(0.0, 1.0, 0.0), width=0.04, quality=1.0, object_id="probe")


def probe(base_x: float, stored_home: bool = False) -> dict:
    s = load_scenario(None, "YuMiBin")
    s.robot.base_position = [base_x, 0.0, 0.0]
    if not stored_home:
        with_homes(park_homes(s))
    reach = PickReach(s)
    out = {"base_x": base_x, "park": {a: list(arm.home) for a, arm in robots.ROBOTS["yumi"].arms.items()}}
    for kind, label in (("parallel_jaw", "right_jaw"), ("suction", "left_suction")):
        by_dir = {}
        for name, g in grasps(kind):
            by_dir.setdefault(name, []).append(bool(reach(g)))
        out[label] = {"reached": sum(sum(v) for v in by_dir.values()), "of": sum(len(v) for v in by_dir.values()),
                      "by_direction": {k: sum(v) for k, v in by_dir.items()}}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--base-x", type=float, nargs="+", required=True)
    ap.add_argument("--stored-home", action="store_true", help="park at the stored ArmSpec.home (no IK)")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    home0 = dict(robots.ROBOTS["yumi"].arms)
    rows = []
    for bx in a.base_x:
        robots.ROBOTS["yumi"] = dataclasses.replace(robots.ROBOTS["yumi"], arms=home0)  # IK seeds: the stored homes
        rows.append(probe(bx, a.stored_home))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "park"}), flush=True)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
