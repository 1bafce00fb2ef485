"""What a higher park would do to YuMiBin's station reach (exploration; the shipped park is
ms_drake.robots ArmSpec.home): each arm's park tcp raised by --dz (IK from the stored park, tool
orientation kept; module state of ms_drake.robots, this script only), then the grasps of the
first --heaps heaps of a station-reach records file (sims/station_reach.py) re-diagnosed with
PickReach, and the parked arms' pixels in the overhead image over the bin counted.

    .venv/bin/python sims/station_reach_park.py --records out/station_reach/after.jsonl --heaps 30 \\
        --dz 0.10 --heap-dir out/heaps
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np
from pydrake.math import RigidTransform

import ms_drake.robots as robots
from ms_drake.execution.reach import PickReach
from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.station_reach import format_summary, heap_view, planned_grasps, read_records, summarize
from ms_drake.planning.cartesian import ik_pose
from ms_drake.planning.sequences import arm_ik
from ms_drake.scenario import load_scenario
from ms_drake.station import MakeStation


def raised_homes(scenario, dz: float) -> dict:
    out = {}
    for arm in ("yumi_right", "yumi_left"):
        ik, _, q_home, _keep = arm_ik(scenario, arm)
        X = ik_pose(ik, q_home)
        res = ik.solve(RigidTransform(X.rotation(), X.translation() + [0, 0, dz]), q_seed=q_home)
        if not res.success:
            raise RuntimeError(f"park of {arm} raised by {dz} m: IK {res.status}")
        out[arm] = tuple(float(v) for v in res.q)
    return out


def robot_pixels_over_bin(scenario) -> int:
    def render(robot):
        s = dataclasses.replace(scenario)
        s.objects = dataclasses.replace(s.objects, count=0)
        if not robot:
            s.robot = dataclasses.replace(s.robot, name="", grippers=[])
        st = MakeStation(s, label_images="render")
        return np.array(st.GetOutputPort("overhead.depth_image").Eval(st.CreateDefaultContext()).data, float)[..., 0]
    d, d0 = render(True), render(False)
    m = np.abs(np.nan_to_num(d, posinf=9) - np.nan_to_num(d0, posinf=9)) > 1e-4
    cam = scenario.cameras["overhead"]
    v, u = np.nonzero(m)
    x = (u - (cam.width - 1) / 2) / cam.focal.x * d[m]
    return int(np.sum(x >= -0.5 * scenario.environment.size[0] - scenario.environment.wall_thickness))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--records", required=True)
    ap.add_argument("--heaps", type=int, default=30)
    ap.add_argument("--dz", type=float, default=0.10)
    ap.add_argument("--heap-dir", default=None)
    a = ap.parse_args(argv)
    s = load_scenario(None, "YuMiBin")
    homes = raised_homes(s, a.dz)
    spec = robots.ROBOTS["yumi"]
    robots.ROBOTS["yumi"] = dataclasses.replace(
        spec, arms={k: dataclasses.replace(v, home=homes.get(k, v.home)) for k, v in spec.arms.items()})
    print(f"park raised by {a.dz} m: {homes}; robot pixels over the bin: {robot_pixels_over_bin(s)}", flush=True)
    reach = PickReach(s)
    recs = sorted(read_records(a.records), key=lambda r: r["seed"])[: a.heaps]
    new = []
    for r in recs:
        view = heap_view(cached_heap(r["objects"], r["seed"], a.heap_dir))
        grasps, scene = planned_grasps(view, reach.backend.grasp_kinds)
        new.append({"seed": r["seed"], "grasps": [{"kind": g.kind} for g in grasps],
                    "stations": {"YuMiBin": [reach.diagnose(g, scene) for g in grasps]}})
    print("the same heaps as recorded:\n" + format_summary(summarize(
        [{**r, "stations": {"YuMiBin": r["stations"]["YuMiBin"]}} for r in recs]), len(recs)))
    print(f"park raised by {a.dz} m:\n" + format_summary(summarize(new), len(new)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
