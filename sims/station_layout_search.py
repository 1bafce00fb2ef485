"""The cheap proxy of the station reach (sims/station_reach.py) for choosing a bin station's
layout: for each candidate base (x, z, yaw relative to the bin centre) of the scenario's robot,
PickReach's pick plan from park (pre-grasp IK within the joint limits and clear of the bin, the
straight approach and lift; no objects) of probe grasps on a grid over the bin: 5 x 3 positions
(x -0.20 .. 0.20, y -0.15 .. 0.15 m) at 2 heights (4 and 14 cm above the floor) x 5 approaches
(straight down, tilted 35 degrees towards +x, -x, +y, -y); per gripper kind the robot carries.
Also each arm's reachable drop-off trays (FullBackend.drops).

    .venv/bin/python sims/station_layout_search.py --scenario YuMiBin --x -0.45 -0.40 --z 0.0 0.1 \\
        --out out/layout_yumi.jsonl
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time

import numpy as np

from ms_drake.execution.reach import PickReach
from ms_drake.scenario import load_scenario
from ms_drake.types import Grasp

TILT = np.radians(35.0)
DIRECTIONS = {"down": (0.0, 0.0, -1.0), "+x": (np.sin(TILT), 0.0, -np.cos(TILT)),
              "-x": (-np.sin(TILT), 0.0, -np.cos(TILT)), "+y": (0.0, np.sin(TILT), -np.cos(TILT)),
              "-y": (0.0, -np.sin(TILT), -np.cos(TILT))}
XS, YS, ZS = (-0.20, -0.10, 0.0, 0.10, 0.20), (-0.15, 0.0, 0.15), (0.04, 0.14)


def probe_grasps(kind: str, xs=XS, ys=YS, zs=ZS, directions=DIRECTIONS):
    """(position, direction name, Grasp) of the probe grid (module docstring); jaw axis along y
    (along x for the approaches tilted towards +-y)."""
    for x, y, z in itertools.product(xs, ys, zs):
        for name, d in directions.items():
            axis = (1.0, 0.0, 0.0) if "y" in name else (0.0, 1.0, 0.0)
            yield (x, y, z), name, Grasp(kind=kind, center=(x, y, z), approach=d, axis=axis, width=0.04,
                                         quality=1.0, object_id="probe")


def layout_reach(scenario, xs=XS, ys=YS, zs=ZS, directions=DIRECTIONS) -> dict:
    """{kind: {"reached", "of", "misses": [[x, y, z, direction, status]]}, "drops": {arm: n}} of
    the probe grasps for the scenario's robot at its base."""
    reach = PickReach(scenario)
    out = {"drops": {arm: len(q) for arm, q in reach.backend.drops.items()}}
    for kind in reach.backend.grasp_kinds:
        n = k = 0
        misses = []
        for p, name, g in probe_grasps(kind, xs, ys, zs, directions):
            st = reach.status(g)
            n += 1
            k += st == "ok"
            if st != "ok":
                misses.append([*p, name, st])
        out[kind] = {"reached": k, "of": n, "misses": misses}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--x", type=float, nargs="+", required=True, help="base x [m] (bin centre at 0)")
    ap.add_argument("--z", type=float, nargs="+", default=[0.0], help="base height [m]")
    ap.add_argument("--yaw", type=float, nargs="+", default=[0.0], help="base yaw [deg]")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    for x, z, yaw in itertools.product(a.x, a.z, a.yaw):
        s = load_scenario(None, a.scenario)
        s.robot.base_position = [x, 0.0, z]
        s.robot.base_yaw = yaw
        t = time.time()
        r = layout_reach(s)
        r.update(scenario=a.scenario, base=[x, 0.0, z], yaw=yaw, seconds=round(time.time() - t, 1))
        with open(a.out, "a") as f:
            f.write(json.dumps(r) + "\n")
        print(f"{a.scenario} base ({x:+.2f}, 0, {z:.2f}) yaw {yaw:.0f}: "
              + ", ".join(f"{k} {r[k]['reached']}/{r[k]['of']}" for k in r if isinstance(r[k], dict) and "of" in r[k])
              + f", drops {r['drops']}  ({r['seconds']} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
