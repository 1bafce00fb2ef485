"""Motion: IK (reach, unreachable, collision avoidance, axis-only), ruckig timing within limits,
Cartesian lines, TrajectoryStreamer (unit and in a diagram tracking with inverse dynamics)."""

import numpy as np
import pytest
from pydrake.geometry import Box
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.controllers import InverseDynamicsController
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Multiplexer

from ms_drake.paths import make_parser
from ms_drake.robots import arm_joint_limits
from ms_drake.types import JointLimits
from ms_drake.planning import ArmIk, TimedTrajectory, TrajectoryStreamer, approach_pose, ik_pose, make_ik_diagram, plan_cartesian_line, plan_joint_motion, plan_path_motion
from ms_drake.robots import ROBOTS
from ms_drake.station.robots import add_robot

Q_PANDA = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785])


def _table(plant, parser):
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0.5, 0, -0.05]), Box(0.6, 0.8, 0.1),
                                    "table", CoulombFriction(0.5, 0.5))


@pytest.fixture(scope="module")
def panda():
    diagram, plant, r, g = make_ik_diagram("panda", add_environment=_table)
    ctx = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    spec = ROBOTS["panda"].arms["panda"]
    ik = ArmIk(plant, pc, spec.joints, plant.GetFrameByName("tcp", g["panda"]), seed=1)
    return diagram, ctx, ik


def test_ik_reaches_a_pose_and_holds_other_joints(panda):
    _, _, ik = panda
    X = ik_pose(ik, Q_PANDA + np.array([0.3, 0.2, -0.2, 0.3, 0.1, -0.2, 0.4]))
    before = ik.plant.GetPositions(ik.context).copy()
    res = ik.solve(X, q_seed=Q_PANDA)
    np.testing.assert_array_equal(ik.plant.GetPositions(ik.context), before)  # context restored
    assert res.success and res.status == "ok"
    X_got = ik_pose(ik, res.q)
    assert np.linalg.norm(X_got.translation() - X.translation()) < 1.5e-3
    assert X_got.rotation().InvertAndCompose(X.rotation()).ToAngleAxis().angle() < 0.011
    assert np.all(res.q >= ik.lower - 1e-6) and np.all(res.q <= ik.upper + 1e-6)


@pytest.mark.parametrize("robot,arm", [("yumi", "yumi_right"), ("yumi", "yumi_left"), ("fetch", "fetch")])
def test_ik_every_arm(robot, arm):
    diagram, plant, r, g = make_ik_diagram(robot)
    pc = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
    spec = ROBOTS[robot].arms[arm]
    ik = ArmIk(plant, pc, spec.joints, plant.GetFrameByName("tcp", g[arm]), seed=2)
    finite = np.isfinite(ik.lower) & np.isfinite(ik.upper)
    mid = np.where(finite, (np.where(finite, ik.lower, 0) + np.where(finite, ik.upper, 0)) / 2, 0.0)
    q_goal = np.clip(mid + np.random.default_rng(3).uniform(-0.3, 0.3, len(mid)), ik.lower, ik.upper)
    X = ik_pose(ik, q_goal)
    res = ik.solve(X, q_seed=mid)
    assert res.success, (res.status, res.position_error, res.angle_error, res.min_distance)
    assert np.linalg.norm(ik_pose(ik, res.q).translation() - X.translation()) < 1.5e-3


def test_ik_unreachable_is_a_result_not_an_exception(panda):
    _, _, ik = panda
    res = ik.solve(RigidTransform([2.5, 0, 0.5]))
    assert not res.success and res.unreachable and res.position_error > 1.0


def test_ik_keeps_clear_of_the_environment(panda):
    _, _, ik = panda
    down = RollPitchYaw(np.pi, 0, 0).ToRotationMatrix()
    above = ik.solve(RigidTransform(down, [0.5, 0.0, 0.03]), q_seed=Q_PANDA)
    assert above.success and above.min_distance >= ik.min_distance - 1e-4
    inside = ik.solve(RigidTransform(down, [0.5, 0.0, -0.03]), q_seed=Q_PANDA)  # tcp inside the table
    assert not inside.success and inside.status == "unreachable"


def test_ik_axis_only_frees_rotation_about_the_approach(panda):
    _, _, ik = panda
    tilted = RigidTransform(RollPitchYaw(np.pi, 0, 1.3), [0.45, 0.1, 0.2])
    res = ik.solve(tilted, q_seed=Q_PANDA, axis_only=True)
    assert res.success
    z = ik_pose(ik, res.q).rotation().matrix()[:, 2]
    assert np.dot(z, [0, 0, -1]) > np.cos(0.011)


def _sampled(traj, n=400):
    t = np.linspace(0, traj.duration, n)
    return t, np.array([traj.value(x) for x in t])


def test_ruckig_motion_within_limits_and_ends_at_target():
    limits = arm_joint_limits("panda")
    W = np.array([Q_PANDA, Q_PANDA + 0.5, Q_PANDA - np.array([0.2, 0.1, 0, 0.3, 0, 0.2, 0])])
    traj = plan_joint_motion(W, limits)
    assert traj.duration > 0
    np.testing.assert_allclose(traj.value(0), W[0], atol=1e-9)
    np.testing.assert_allclose(traj.final(), W[-1], atol=1e-9)
    t, q = _sampled(traj, 2000)
    v = np.diff(q, axis=0) / np.diff(t)[:, None]
    assert np.all(np.abs(v) <= limits.velocity * 1.01)
    # a slower table gives a longer motion
    assert plan_joint_motion(W, arm_joint_limits("panda", scale=0.5)).duration > traj.duration


def test_path_timing_respects_joint_limits():
    limits = JointLimits.uniform(2, 1.0, 2.0, 20.0)
    s = np.linspace(0, 1, 50)
    path = np.stack([np.sin(3 * s), 2 * s], 1)
    traj = plan_path_motion(path, limits)
    t, q = _sampled(traj, 3000)
    v = np.diff(q, axis=0) / np.diff(t)[:, None]
    assert np.abs(v).max() <= 1.0 * 1.02
    np.testing.assert_allclose(traj.final(), path[-1], atol=1e-9)


def test_cartesian_lift_is_a_straight_line(panda):
    _, _, ik = panda
    limits = arm_joint_limits("panda")
    X0 = ik_pose(ik, Q_PANDA)
    plan = plan_cartesian_line(ik, X0, [0, 0, 0.1], Q_PANDA, limits)
    assert plan.success and plan.fraction == 1.0
    t, q = _sampled(plan.trajectory, 60)
    p = np.array([ik_pose(ik, qq).translation() for qq in q])
    assert np.abs(p[:, :2] - X0.translation()[:2]).max() < 2e-3  # no sideways drift
    assert p[-1, 2] - X0.translation()[2] == pytest.approx(0.1, abs=2e-3)
    assert np.all(np.diff(p[:, 2]) > -1e-4)  # monotone upwards
    # a line into the table fails with a status, not an exception
    down = plan_cartesian_line(ik, X0, [0, 0, -1.0], Q_PANDA, limits, step=0.05)
    assert not down.success and 0 < down.fraction < 1


@pytest.mark.parametrize("axis_only", [False, True])
def test_approach_then_push(panda, axis_only):
    _, _, ik = panda
    limits = arm_joint_limits("panda")
    X_grasp = RigidTransform(RollPitchYaw(np.pi, 0, 0.4), [0.45, -0.1, 0.04])
    pre = ik.solve(approach_pose(X_grasp, 0.1), q_seed=Q_PANDA, axis_only=axis_only)
    assert pre.success
    q_pre = pre.q
    X_pre = ik_pose(ik, q_pre) if axis_only else approach_pose(X_grasp, 0.1)
    plan = plan_cartesian_line(ik, X_pre, 0.1 * X_grasp.rotation().matrix()[:, 2], q_pre, limits, axis_only=axis_only)
    assert plan.success
    X_end = ik_pose(ik, plan.trajectory.final())
    assert np.linalg.norm(X_end.translation() - X_grasp.translation()) < 2e-3
    assert ik_pose(ik, q_pre).translation()[2] == pytest.approx(0.14, abs=2e-3)  # 10 cm above
    push = plan_cartesian_line(ik, ik_pose(ik, plan.trajectory.final()), [0.1, 0, 0], plan.trajectory.final(), limits)
    assert push.success
    p = ik_pose(ik, push.trajectory.final()).translation()
    np.testing.assert_allclose(p, X_end.translation() + [0.1, 0, 0], atol=2e-3)


def test_streamer_unit_outputs_trajectory_samples():
    traj = plan_joint_motion([[0.0, 0.0], [1.0, -0.5]], JointLimits.uniform(2, 1.0, 4.0, 40.0))
    streamer = TrajectoryStreamer(2, q_hold=[0.3, 0.3])
    ctx = streamer.CreateDefaultContext()
    assert streamer.GetOutputPort("done").Eval(ctx)[0] == 1.0  # nothing to play
    np.testing.assert_allclose(streamer.GetOutputPort("position").Eval(ctx), [0.3, 0.3])
    streamer.GetInputPort("trajectory").FixValue(ctx, TimedTrajectory(traj, start_time=1.0))
    for t in (0.5, 1.0 + 0.4 * traj.duration, 1.0 + traj.duration + 1.0):
        ctx.SetTime(t)
        np.testing.assert_allclose(streamer.GetOutputPort("position").Eval(ctx), traj.value(t - 1.0), atol=1e-12)
    ctx.SetTime(1.0 + 0.5 * traj.duration)
    assert streamer.GetOutputPort("done").Eval(ctx)[0] == 0.0
    assert np.linalg.norm(streamer.GetOutputPort("velocity").Eval(ctx)) > 0.1
    ctx.SetTime(1.0 + traj.duration)
    assert streamer.GetOutputPort("done").Eval(ctx)[0] == 1.0


def test_streamer_drives_a_panda_in_a_diagram():
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
    r = add_robot(plant, make_parser(plant), "panda")
    plant.Finalize()
    control_plant = MultibodyPlant(0.0)
    add_robot(control_plant, make_parser(control_plant), "panda")
    control_plant.Finalize()
    q_end = Q_PANDA + np.array([0.4, 0.3, -0.3, 0.4, 0.2, -0.3, 0.5])
    traj = plan_joint_motion([Q_PANDA, q_end], arm_joint_limits("panda", scale=0.5))
    streamer = builder.AddSystem(TrajectoryStreamer(7, trajectory=TimedTrajectory(traj, start_time=0.2)))
    idc = builder.AddSystem(InverseDynamicsController(control_plant, [400.0] * 7, [1.0] * 7, [40.0] * 7, False))
    mux = builder.AddSystem(Multiplexer([7, 7]))
    builder.Connect(streamer.GetOutputPort("position"), mux.get_input_port(0))
    builder.Connect(streamer.GetOutputPort("velocity"), mux.get_input_port(1))
    builder.Connect(mux.get_output_port(), idc.get_input_port_desired_state())
    builder.Connect(plant.get_state_output_port(r), idc.get_input_port_estimated_state())
    builder.Connect(idc.get_output_port_control(), plant.get_actuation_input_port(r))
    diagram = builder.Build()
    sim = Simulator(diagram)
    pc = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    plant.SetPositions(pc, r, Q_PANDA)
    sim.AdvanceTo(0.2 + 0.5 * traj.duration)
    mid = plant.GetPositions(pc, r)
    assert np.abs(mid - traj.value(0.5 * traj.duration)).max() < 0.02
    sim.AdvanceTo(0.2 + traj.duration + 0.3)
    assert np.abs(plant.GetPositions(pc, r) - q_end).max() < 5e-3


def test_schedule_holds_each_value_until_the_next_step_and_matches_its_source():

    from ms_drake.planning.sequences import Schedule

    s = Schedule()
    s.set(0.5, [2.0])
    s.set(0.0, [1.0])
    s.set(1.0, [3.0])
    assert [float(s(t)[0]) for t in (-1.0, 0.0, 0.49, 0.5, 0.99, 1.0, 5.0)] == [1.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0]
    src = s.source()
    ctx = src.CreateDefaultContext()
    for t in (0.25, 0.75, 2.0):
        ctx.SetTime(t)
        assert src.get_output_port().Eval(ctx)[0] == s(t)[0]
