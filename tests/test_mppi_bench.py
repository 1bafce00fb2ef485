"""`ms-drake bench mppi` (ms_drake.experiments.mppi_bench): the Panda problem and the planners."""

import numpy as np
import pytest
import torch

from ms_drake.collision.scene_net import NetConfig, make_net
from ms_drake.errors import MsDrakeError
from ms_drake.experiments.mppi_bench import bench_mppi, mppi_problem, run_ours
from ms_drake.planning.mppi import MppiParams


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("w") / "net.pt"
    torch.save(dict(model=make_net(NetConfig()).state_dict(), config=dict(NetConfig().__dict__)), path)
    return path


def test_lazy_and_full_checks_choose_the_same_waypoint(weights, tmp_path):
    from ms_drake.collision.checker import load_collision_net  # noqa: PLC0415

    net = load_collision_net(weights, "net")[0]
    robot, q0, goal, lo, hi, keep = mppi_problem(3, "net", tmp_path, net)
    assert not robot.collides(np.stack([q0, goal])).any() and np.linalg.norm(goal - q0) > 0.1
    params = MppiParams(trajectories=40, horizon=8, seed=3)
    full = run_ours(robot, q0, goal, lo, hi, params, steps=2)
    lazy = run_ours(robot, q0, goal, lo, hi, params, steps=2, lazy=True)
    assert full["final_distance"] == pytest.approx(lazy["final_distance"], abs=1e-12)
    assert full["steps"] == lazy["steps"]
    recs = bench_mppi("net", 1, 3, trajectories=20, horizon=4, steps=1, planner="ours", cache=tmp_path, weights=weights)
    assert {"seed", "method", "planner", "ms_per_step", "hz", "reached"} <= set(recs[0]) and recs[0]["seed"] == 3
    with pytest.raises(MsDrakeError, match="ours, ours_lazy, pytorch_mppi"):
        bench_mppi("net", 1, 3, planner="rrt", weights=weights)
