"""Full-fidelity picks through the station's driver ports: the YuMi lifts a box from the bin with
the compliant jaw and a flat-topped box with suction, the Panda lifts a box from the table, the
Fetch pushes a box 10 cm along the shelf with the blade and picks one with suction.

The default suite starts each pick at its pre-grasp configuration at 0.3 m/s with short pauses,
and runs one pick and one push from the home pose the same way; the `slow` variants run every
task's whole motion from the home pose as the sims/pick_*.py scripts do."""

import dataclasses
import itertools

import coal

import numpy as np
import pytest

from ms_drake.execution import FullBackend
from ms_drake.experiments.picks import TASKS, plan_task, run_task
from ms_drake.geometry import Workspace
from pydrake.math import RigidTransform, RotationMatrix

from ms_drake.execution.backends import grasp_tool_pose
from ms_drake.execution.reach import PickReach
from ms_drake.grasping.indexed import Scene
from ms_drake.planning import ik_pose, plan_joint_motion
from ms_drake.planning.sequences import Schedule, Timeline, jaw_opening
from ms_drake.robots import PICK_APPROACH
from ms_drake.scenario import load_scenario
from ms_drake.station.environments import dropoff_points
from ms_drake.types import Action, Grasp, JointLimits


def _check(out, task):
    assert out.success, out
    if task.mode == "push":
        assert out.moved == pytest.approx(task.push_distance, abs=0.01) and out.sideways < 0.01
    else:
        assert out.lifted == pytest.approx(task.lift, abs=0.02)  # the box rose with the tool ...
        assert out.slip < 0.005  # ... and did not move in the hand while lifted and held


@pytest.mark.parametrize("name", list(TASKS))
def test_pick_from_pregrasp(name):
    task = TASKS[name]
    _check(run_task(task, from_home=False, speed=0.3, quick=True), task)


@pytest.mark.parametrize("name", ["panda_jaw", "fetch_push"])
def test_pick_and_push_from_home_quick(name):
    task = TASKS[name]
    _check(run_task(task, from_home=True, speed=0.3, quick=True), task)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(TASKS))
def test_pick_from_home(name):
    task = TASKS[name]
    _check(run_task(task, from_home=True), task)


def test_an_unreachable_pick_is_a_result_not_an_exception():
    task = dataclasses.replace(TASKS["yumi_jaw"], xy=(0.2, -0.15))  # the far end of the bin, out of the YuMi's reach
    scenario, plan, _ = plan_task(task, from_home=False)
    assert not plan.success and plan.status == "unreachable" and plan.timeline is None
    out = run_task(task, from_home=False)
    assert not out.success and out.status == plan.status and out.sim_seconds == 0


def test_timeline_plays_trajectories_and_holds():
    limits = JointLimits.uniform(2, 1.0, 4.0, 40.0)
    a = plan_joint_motion([[0.0, 0.0], [0.5, -0.5]], limits)
    tl = Timeline([0.0, 0.0])
    tl.hold(0.2)
    tl.play(a)
    tl.mark("there")
    tl.hold(0.3)
    assert tl.duration == pytest.approx(0.5 + a.duration) and tl.marks["there"] == pytest.approx(0.2 + a.duration)
    np.testing.assert_allclose(tl.value(0.1), [0, 0])
    np.testing.assert_allclose(tl.value(0.2 + a.duration / 2), a.value(a.duration / 2))
    assert np.linalg.norm(tl.velocity(0.2 + a.duration / 2)) > 0.1
    np.testing.assert_allclose(tl.value(10.0), [0.5, -0.5])
    np.testing.assert_allclose(tl.velocity(10.0), 0)


def test_schedule_is_a_zero_order_hold():
    from pydrake.systems.framework import Context  # noqa: F401

    s = Schedule()
    s.set(0.0, 0.1)
    s.set(1.5, 0.0)
    src = s.source()
    ctx = src.CreateDefaultContext()
    for t, v in ((0.0, 0.1), (1.49, 0.1), (1.5, 0.0), (100.0, 0.0)):
        ctx.SetTime(t)
        assert src.get_output_port().Eval(ctx)[0] == pytest.approx(v)


def test_a_pick_from_park_comes_straight_down_to_the_pregrasp_with_the_jaw_opened_for_the_grasp():
    s = load_scenario(None, "PandaBin")
    ws = Workspace.from_scenario(s)
    backend = FullBackend(s, {}, ws)
    cx, cy = ws.center_xy
    g = Grasp(kind="parallel_jaw", center=(cx, cy, ws.floor_z + 0.05), approach=(0.0, 0.0, -1.0),
              axis=(0.0, 1.0, 0.0), width=0.04, quality=1.0, object_id="probe")
    plan = backend.plan_grasp(g)
    assert plan.success, plan.status
    # the jaw opens to the grasp's width (the planners' opening), from the start to contact
    assert plan.opening == pytest.approx(g.width)
    port = backend.jaw[1]
    assert plan.commands[f"{port}.position"](0.0)[0] == pytest.approx(plan.opening)
    assert plan.commands[f"{port}.position"](plan.timeline.marks["contact"])[0] == 0.0
    # from above the walls straight down to the pre-grasp, PICK_APPROACH.distance above the grasp
    ik = backend.ik[plan.arm][0]
    tl = plan.timeline
    P = np.array([ik_pose(ik, tl.value(t)).translation()
                  for t in np.linspace(tl.marks["descent"], tl.marks["approach"], 25)])
    assert np.abs(P[:, :2] - [cx, cy]).max() < 3e-3
    assert P[0, 2] > ws.floor_z + ws.wall_height + 0.2
    assert P[-1, 2] == pytest.approx(g.center[2] + PICK_APPROACH.distance, abs=2e-3)
    assert np.all(np.diff(P[:, 2]) <= 1e-4)


def test_jaw_opening_sets_the_ik_fingers_and_restores_them():
    s = load_scenario(None, "FloatingGripperBin")
    backend = FullBackend(s, {}, Workspace.from_scenario(s))
    ik = backend.ik[backend.jaw[0]][0]
    plant, ctx = ik.plant, ik.context
    inst = ik.frame.model_instance()
    left = plant.GetJointByName("left_finger_sliding_joint", inst)
    right = plant.GetJointByName("right_finger_sliding_joint", inst)
    before = plant.GetPositions(ctx).copy()
    with jaw_opening(ik, 0.03):
        assert left.get_translation(ctx) == pytest.approx(-0.015) and right.get_translation(ctx) == pytest.approx(0.015)
    assert np.array_equal(plant.GetPositions(ctx), before)
    with jaw_opening(ik, None):
        assert np.array_equal(plant.GetPositions(ctx), before)


def test_a_pick_takes_the_pregrasp_posture_whose_straight_lines_solve():
    # A vertical suction grasp at the bin's far end (station-reach heap 9404): the YuMi's left arm
    # reaches its pre-grasp from park in a posture whose straight approach leaves the joint limits;
    # the plan goes on to the restarts' postures and finds one whose approach and lift solve.
    s = load_scenario(None, "YuMiBin")
    backend = FullBackend(s, {}, Workspace.from_scenario(s))
    g = Grasp(kind="suction", center=(0.1815, -0.0901, 0.1575), approach=(0.0014, -0.0011, -1.0), axis=(0.0, 0.0, 0.0),
              width=0.0, quality=1.0, object_id="probe")
    ik = backend.ik[backend.suction[0]][0]
    restarts, ik.restarts = ik.restarts, 0
    try:
        only_park = backend.plan_grasp(g)
    finally:
        ik.restarts = restarts
    assert not only_park.success  # the park posture's lines fail ...
    plan = backend.plan_grasp(g)
    assert plan.success, plan.status  # ... and the pick is planned from another posture
    tl = plan.timeline
    P = ik_pose(ik, tl.value(tl.marks["contact"]))
    assert np.linalg.norm(P.translation() - grasp_tool_pose(g).translation()) < 2e-3


def test_an_ik_solve_does_not_depend_on_the_solves_before_it():
    s = load_scenario(None, "YuMiBin")
    backend = FullBackend(s, {}, Workspace.from_scenario(s))
    ik, _, q_home = backend.ik[backend.suction[0]]
    far = RigidTransform(RotationMatrix.MakeXRotation(np.pi), [0.2, 0.15, 0.25])
    near = RigidTransform(RotationMatrix.MakeXRotation(np.pi), [-0.1, 0.0, 0.25])
    fresh = ik.solve(far, q_seed=q_home, axis_only=True)
    ik.solve(near, q_seed=q_home, axis_only=True)
    again = ik.solve(far, q_seed=q_home, axis_only=True)
    assert fresh.status == again.status and np.array_equal(fresh.q, again.q)
    sols = [r for r in ik.solutions(near, q_seed=q_home, axis_only=True) if r.success]
    assert len(sols) >= 2 and all(np.linalg.norm(ik_pose(ik, r.q).translation() - near.translation()) < 2e-3
                                  for r in sols)


def test_pick_plans_come_in_a_fixed_order_and_a_grasp_names_one_by_its_posture():
    s = load_scenario(None, "YuMiBin")
    backend = FullBackend(s, {}, Workspace.from_scenario(s))
    g = Grasp(kind="suction", center=(0.0, 0.02, 0.08), approach=(0.0, 0.0, -1.0), quality=1.0, object_id="probe")
    plans = list(itertools.islice(backend.pick_plans(g), 3))
    assert len(plans) >= 2 and all(p.success for p in plans)
    starts = [p.timeline.value(p.timeline.marks["approach"]) for p in plans]
    assert not np.allclose(starts[0], starts[1], atol=1e-3)  # two arm postures at the pre-grasp
    again = list(itertools.islice(backend.pick_plans(g), 3))
    assert all(np.array_equal(a.timeline.value(a.timeline.marks["approach"]), s_) for a, s_ in zip(again, starts))
    second = backend.plan_grasp(dataclasses.replace(g, posture=1))
    assert np.array_equal(second.timeline.value(second.timeline.marks["approach"]), starts[1])
    beyond = backend.plan_grasp(dataclasses.replace(g, posture=50))  # fewer plans: the first
    assert np.array_equal(beyond.timeline.value(beyond.timeline.marks["approach"]), starts[0])


def test_reach_takes_the_posture_whose_arm_clears_the_scene_and_the_backend_executes_it():
    # A 1 cm sphere where the first plan's arm passes (on its way from park) and the second's does
    # not: the reach check returns the grasp with posture 1, and the backend plans that plan.
    reach = PickReach(load_scenario(None, "YuMiBin"))
    g = Grasp(kind="suction", center=(0.1, 0.05, 0.08), approach=(0.0, 0.0, -1.0), quality=1.0, object_id="probe")
    first, second = itertools.islice(reach.backend.pick_plans(g), 2)
    c = np.array([-0.0065, 0.108, 0.4759])
    T = np.eye(4)
    T[:3, 3] = c
    scene = Scene([(coal.Sphere(0.01), T, c, 0.01)])
    assert reach.arm_hit(first, scene) and not reach.arm_hit(second, scene)
    chosen = reach(g, scene)
    assert isinstance(chosen, Grasp) and chosen.posture == 1
    plan = reach.backend.plan_grasp(chosen)
    assert np.array_equal(plan.timeline.value(plan.timeline.marks["approach"]),
                          second.timeline.value(second.timeline.marks["approach"]))
    assert reach(g) is True  # no scene: the first plan
    one = PickReach(load_scenario(None, "YuMiBin"), max_postures=1)  # only the first plan: blocked
    assert one(g, scene) is False and one.arm_blocked == 1


def test_a_lifted_object_leaves_the_bin_straight_up_before_the_carry_to_the_tray():
    s = load_scenario(None, "YuMiBin")
    ws = Workspace.from_scenario(s)
    backend = FullBackend(s, {}, ws)
    cx, cy = ws.center_xy
    g = Grasp(kind="suction", center=(cx, cy, ws.floor_z + 0.03), approach=(0.0, 0.0, -1.0), axis=(1.0, 0.0, 0.0),
              width=0.0, quality=1.0, object_id="probe")
    arm = backend.suction[0]
    motion = backend.plan(Action("grasp", grasp=g), backend.initial_commands(), 0)
    ik = backend.ik[arm][0]
    q = motion.commands[f"{arm}.position"]
    P = np.array([ik_pose(ik, q(t)).translation() for t in np.linspace(motion.check_time, motion.settle_from, 300)])
    up = int(np.argmax(P[:, 2] >= backend.via_z - 2e-3))  # the first sample at the carry height
    assert P[up, 2] >= backend.via_z - 2e-3 > ws.floor_z + ws.wall_height + 0.2
    assert np.abs(P[:up + 1, :2] - P[0, :2]).max() < 5e-3  # straight up from the lift's end
    trays = [np.linalg.norm(P[:, :2] - d[:2], axis=1).min() for d in dropoff_points(s.environment)]
    assert min(trays) < 0.02  # and on to above a tray
