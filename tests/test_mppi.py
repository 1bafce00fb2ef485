"""MPPI in joint space (ms_drake.planning.mppi): the step, and the LeafSystem alone and wired."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, ZeroOrderHold

from ms_drake.planning.mppi import REFERENCE, MppiError, MppiParams, MppiPlanner, mppi_step, rollouts

LOWER, UPPER = np.array([-3.0, -3.0]), np.array([3.0, 3.0])
CENTRE, RADIUS = np.array([0.0, 0.0]), 0.6


def disc(Q):
    """A disc obstacle in a 2-joint configuration space."""
    return np.linalg.norm(np.asarray(Q) - CENTRE, axis=-1) < RADIUS


def test_free_space_goes_straight_to_the_goal():
    best, info = mppi_step([-2.0, 2.0], [-1.0, 2.5], lambda Q: np.zeros(len(Q), bool), LOWER, UPPER)
    np.testing.assert_allclose(best, [-1.0, 2.5])
    assert info["checks"] == REFERENCE.trajectories * REFERENCE.horizon and info["free_trajectories"] > 0


def test_rollouts_start_with_the_straight_line_and_respect_the_limits():
    rng = np.random.default_rng(0)
    dirs, way = rollouts(np.array([2.9, 0.0]), np.array([2.9, 1.0]), LOWER, UPPER, MppiParams(sigma=2.0), rng)
    np.testing.assert_allclose(dirs[0], [0.0, 1.0])
    assert way.shape == (300, 40, 2) and np.all(way <= UPPER) and np.all(way >= LOWER)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)  # renormalised to |d|


def test_goes_around_an_obstacle_on_the_straight_line():
    q, goal = np.array([-2.0, 0.05]), np.array([2.0, 0.0])
    assert disc(np.linspace(q, goal, 50)).any()  # the straight line is blocked
    rng = np.random.default_rng(1)
    params = MppiParams()
    path = [q]
    for _ in range(30):
        best, _ = mppi_step(q, goal, disc, LOWER, UPPER, params, rng)
        assert best is not None
        # the segment to the waypoint is collision-free at the waypoints' resolution
        assert not disc(np.linspace(q, best, 20)[1:]).any()
        q = best
        path.append(q)
        if np.linalg.norm(q - goal) < 1e-6:
            break
    assert np.linalg.norm(q - goal) < 1e-6
    assert not disc(np.array(path)).any()


def test_weighted_update_reaches_the_goal_past_an_obstacle_beside_the_line():
    q, goal = np.array([-2.0, 0.7]), np.array([2.0, 0.7])  # the line passes 0.1 above the disc
    rng = np.random.default_rng(2)
    for _ in range(20):
        best, info = mppi_step(q, goal, disc, LOWER, UPPER, MppiParams(weighted=True), rng)
        assert best is not None and not disc(best)
        q = best
    assert np.linalg.norm(q - goal) < 0.05


def test_blocked_everywhere_returns_none_and_bad_settings_fail_clearly():
    best, info = mppi_step([0.0, 0.0], [1.0, 0.0], lambda Q: np.ones(len(Q), bool), LOWER, UPPER)
    assert best is None and info["blocked_at_once"] == REFERENCE.trajectories
    with pytest.raises(MppiError, match="horizon"):
        mppi_step([0.0, 0.0], [1.0, 0.0], disc, LOWER, UPPER, MppiParams(horizon=0))
    with pytest.raises(MppiError, match="one shape"):
        mppi_step([0.0, 0.0, 0.0], [1.0, 0.0], disc, LOWER, UPPER)


def test_planner_alone_with_fixed_inputs():
    planner = MppiPlanner(2, disc, LOWER, UPPER)
    ctx = planner.CreateDefaultContext()
    planner.get_input_port(0).FixValue(ctx, [-2.0, 0.05])
    planner.get_input_port(1).FixValue(ctx, [2.0, 0.0])
    w = planner.GetOutputPort("waypoint").Eval(ctx)
    assert planner.GetOutputPort("free").Eval(ctx)[0] == 1.0
    assert not disc(w) and np.linalg.norm(w - [2.0, 0.0]) < 4.0
    best, _ = mppi_step([-2.0, 0.05], [2.0, 0.0], disc, LOWER, UPPER, REFERENCE, np.random.default_rng([0, 0]))
    np.testing.assert_allclose(w, best)


def test_planner_in_a_closed_loop_reaches_the_goal():
    builder = DiagramBuilder()
    planner = builder.AddSystem(MppiPlanner(2, disc, LOWER, UPPER, MppiParams(trajectories=100, horizon=20)))
    goal = builder.AddSystem(ConstantVectorSource([2.0, 0.0]))
    hold = builder.AddSystem(ZeroOrderHold(0.1, 2))  # the robot reaches each waypoint in one period
    builder.Connect(goal.get_output_port(), planner.GetInputPort("goal"))
    builder.Connect(planner.GetOutputPort("waypoint"), hold.get_input_port())
    builder.Connect(hold.get_output_port(), planner.GetInputPort("q"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    hold.GetMyMutableContextFromRoot(ctx).get_mutable_discrete_state(0).SetFromVector([-2.0, 0.05])
    visited = []
    for k in range(1, 31):
        sim.AdvanceTo(0.1 * k)
        visited.append(hold.get_output_port().Eval(hold.GetMyContextFromRoot(ctx)).copy())
    assert not disc(np.array(visited)).any()
    np.testing.assert_allclose(visited[-1], [2.0, 0.0], atol=1e-9)
