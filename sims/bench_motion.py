"""Benchmark of the motion stack: IK median ms per solve, ruckig us per call, jaw-lift real-time factor.

    .venv/bin/python sims/bench_motion.py [--solves 50] [--out docs/bench_motion.json]

IK targets: tool poses from forward kinematics of random configurations (seeded) within +-0.4 rad
of the middle of the joint ranges, solved from the middle configuration, with collision avoidance
on (lazy constraint, see ms_drake/planning/ik.py). Panda with a table below it; YuMi (right arm,
with the left arm and both grippers present); Fetch (torso + arm).
Ruckig: one 7-DoF rest-to-rest `calculate` with the Panda limits (random targets).
Jaw lift: floating compliant-pad jaw picks a 0.2 kg box and lifts it 10 cm (3.2 s simulated,
SAP, 2 ms step), wall-clock real-time factor.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def bench_ik(solves: int, seed: int = 0) -> dict:
    from pydrake.geometry import Box
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import CoulombFriction

    from ms_drake.planning import ArmIk, ik_pose, make_ik_diagram
    from ms_drake.robots import ROBOTS

    def table(plant, parser):
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0.5, 0, -0.05]), Box(0.6, 0.8, 0.1),
                                        "table", CoulombFriction(0.5, 0.5))

    out = {}
    for robot, arm in (("panda", "panda"), ("yumi", "yumi_right"), ("fetch", "fetch")):
        diagram, plant, r, g = make_ik_diagram(robot, add_environment=table if robot == "panda" else None)
        pc = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
        spec = ROBOTS[robot].arms[arm]
        ik = ArmIk(plant, pc, spec.joints, plant.GetFrameByName("tcp", g[arm]), seed=seed)
        finite = np.isfinite(ik.lower) & np.isfinite(ik.upper)
        mid = np.where(finite, (np.where(finite, ik.lower, 0) + np.where(finite, ik.upper, 0)) / 2, 0.0)
        if robot == "panda":
            mid = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785])
        rng = np.random.default_rng(seed)
        times, ok, statuses = [], 0, {}
        for _ in range(solves):
            q_goal = np.clip(mid + rng.uniform(-0.4, 0.4, len(mid)), ik.lower, ik.upper)
            X = ik_pose(ik, q_goal)
            t0 = time.perf_counter()
            res = ik.solve(X, q_seed=mid)
            times.append(time.perf_counter() - t0)
            ok += res.success
            statuses[res.status] = statuses.get(res.status, 0) + 1
        out[robot] = {"median_ms": 1e3 * float(np.median(times)), "p90_ms": 1e3 * float(np.percentile(times, 90)),
                      "success": ok / solves, "statuses": statuses, "solves": solves}
    return out


def bench_ruckig(calls: int = 2000, seed: int = 0) -> dict:
    from ruckig import InputParameter, Ruckig, Trajectory

    from ms_drake.robots import arm_joint_limits

    lim = arm_joint_limits("panda")
    rng = np.random.default_rng(seed)
    otg, inp, traj = Ruckig(7), InputParameter(7), Trajectory(7)
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = list(lim.velocity), list(lim.acceleration), list(lim.jerk)
    targets = rng.uniform(-1.5, 1.5, (calls, 7))
    t0 = time.perf_counter()
    for k in range(calls):
        inp.current_position = list(targets[k - 1])
        inp.target_position = list(targets[k])
        otg.calculate(inp, traj)
    per = (time.perf_counter() - t0) / calls
    return {"us_per_call": 1e6 * per, "calls": calls, "dof": 7}


def bench_jaw_lift() -> dict:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_grippers import jaw_pick

    t0 = time.perf_counter()
    z, X, _, _ = jaw_pick(0.2)
    wall = time.perf_counter() - t0
    return {"sim_s": 3.2, "wall_s": wall, "realtime_factor": 3.2 / wall, "lifted_m": float(z - 0.025)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solves", type=int, default=50)
    ap.add_argument("--out", default="docs/bench_motion.json")
    args = ap.parse_args()
    res = {"ik": bench_ik(args.solves), "ruckig": bench_ruckig(), "jaw_lift": bench_jaw_lift()}
    print(f"{'robot':8s} {'IK median ms':>12s} {'p90 ms':>8s} {'success':>8s}")
    for robot, r in res["ik"].items():
        print(f"{robot:8s} {r['median_ms']:12.1f} {r['p90_ms']:8.1f} {r['success']:8.2f}  {r['statuses']}")
    print(f"ruckig 7-DoF calculate: {res['ruckig']['us_per_call']:.1f} us per call")
    print(f"jaw lift (0.2 kg, 3.2 s sim): real-time factor {res['jaw_lift']['realtime_factor']:.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
