"""Pick, place and push motion sequences for an arm of a station: IK + ruckig plans played by a
`Timeline` into `<arm>.position`, with gripper commands as zero-order-hold `Schedule`s.

A pick is planned open-loop before it is executed (the reference's simulation experiments
execute a planned grasp; re-planning belongs to the action executor):
  jaw:     home -> above the pre-grasp (ruckig joint motion; with `via_z`) -> straight down to
           the pre-grasp (`approach` back along the tool axis) -> straight approach -> close with
           a force limit -> straight lift -> hold; the jaw opened to `max_opening` on the way
           (and in the IK's collision checks)
  suction: the same with vacuum on at contact instead of closing
  push:    home -> pre-push above the start -> straight down -> straight push -> straight up
Planning failures return a PickPlan with success False and the IK status ("unreachable" /
"collision"), never an exception. ms_drake.experiments.picks runs these plans on a station.
"""


from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from ms_drake.geometry import as_rigid_transform
from ms_drake.planning import (
    ArmIk,
    approach_pose,
    ik_pose,
    make_ik_diagram,
    plan_cartesian_line,
    plan_joint_motion,
)
from ms_drake.planning.cartesian import CartesianPlan
from ms_drake.planning.trajectories import plan_path_motion
from ms_drake.planning.trajectories import JointTrajectory
from ms_drake.robots import CLOSING_FORCE, PICK_APPROACH, station_robot_spec
from ms_drake.scenario import resolve_robot_config
from ms_drake.station.robots import base_transform
from ms_drake.station.station import add_environment
from ms_drake.types import JointLimits


# --------------------------------------------------------------------------------- timelines
class Timeline:
    """Arm joint positions over time: trajectories and holds played one after another."""

    def __init__(self, q_start):
        self._pieces = []  # (start time, duration, trajectory or None for a hold)
        self._q = np.asarray(q_start, float)
        self.q_start = self._q.copy()
        self.duration = 0.0
        self.marks = {}  # name -> time

    def __deepcopy__(self, memo):
        return self

    def mark(self, name):
        self.marks[name] = self.duration

    def hold(self, seconds):
        self._pieces.append((self.duration, seconds, None, self._q.copy()))
        self.duration += seconds

    def play(self, trajectory: JointTrajectory):
        self._pieces.append((self.duration, trajectory.duration, trajectory, None))
        self.duration += trajectory.duration
        self._q = np.asarray(trajectory.final(), float)

    def final(self):
        return self._q.copy()

    def _piece(self, t):
        for start, dur, traj, q in self._pieces:
            if t < start + dur:
                return start, traj, q
        return None

    def value(self, t):
        p = self._piece(t)
        if p is None:
            return self._q.copy()
        start, traj, q = p
        return q.copy() if traj is None else traj.value(t - start)

    def velocity(self, t):
        p = self._piece(t)
        if p is None or p[1] is None:
            return np.zeros_like(self._q)
        return p[1].velocity(t - p[0])


@dataclass
class Schedule:
    """Zero-order-hold commands for one input port: (time, value) steps, the first at t = 0."""

    steps: list = field(default_factory=list)

    def set(self, t, value):
        self.steps.append((float(t), np.atleast_1d(np.asarray(value, float))))

    def __call__(self, t: float) -> np.ndarray:
        """The command at time t: the value of the last step at or before t (the first step's
        value before it)."""
        steps = sorted(self.steps, key=lambda s: s[0])
        v = steps[0][1]
        for ts, vs in steps:
            if ts <= t + 1e-12:
                v = vs
        return v

    def source(self):
        steps = sorted(self.steps, key=lambda s: s[0])
        times = [s[0] for s in steps]
        values = np.stack([s[1] for s in steps], 1)
        if len(times) == 1:  # PiecewisePolynomial needs two breaks
            times.append(times[0] + 1.0)
            values = np.concatenate([values, values], 1)
        times.append(times[-1] + 1e3)
        values = np.concatenate([values, values[:, -1:]], 1)
        return TrajectorySource(PiecewisePolynomial.ZeroOrderHold(times, values))


@dataclass
class PickPlan:
    """What to play: the arm timeline and the gripper command schedules ({port: Schedule})."""

    success: bool
    status: str
    arm: str
    timeline: Timeline | None = None
    commands: dict = field(default_factory=dict)
    X_target: RigidTransform | None = None
    opening: float | None = None  # a jaw pick's opening on the way down [m] (plan_pick's max_opening)


# --------------------------------------------------------------------------------- planning
def arm_ik(scenario, arm: str, frame: str = "tcp", min_distance: float | None = 0.005, seed: int = 0):
    """ArmIk for `arm` of the scenario's robot on a plant with the robot, its grippers (jaws
    open, every arm at home) and the environment (no objects). Returns (ik, limits, q_home,
    keep_alive) -- keep `keep_alive` (the diagram and its context) while using ik."""
    chosen, _ = resolve_robot_config(scenario.robot)
    grippers = {a: g for a, g, _ in chosen}
    spec = station_robot_spec(scenario.robot.name)
    diagram, plant, robot, g = _ik_diagram(scenario, grippers, add_environment, base_transform(scenario.robot))
    ctx = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    q = plant.GetPositions(pc)
    for a in spec.arms.values():
        for n, v in zip(a.joints, a.home):
            q[plant.GetJointByName(n, robot).position_start()] = v
    for inst in g.values():  # open jaws
        for name, sign in (("left_finger_sliding_joint", -1), ("right_finger_sliding_joint", 1)):
            if plant.HasJointNamed(name, inst):
                j = plant.GetJointByName(name, inst)
                q[j.position_start()] = j.position_lower_limits()[0] if sign < 0 else j.position_upper_limits()[0]
    plant.SetPositions(pc, q)
    a = spec.arms[arm]
    ik = ArmIk(plant, pc, a.joints, plant.GetFrameByName(frame, g[arm]), min_distance=min_distance, restarts=8,
               seed=seed)
    limits = JointLimits(np.array(a.velocity_limits), np.array(a.acceleration_limits), np.array(a.jerk_limits))
    return ik, limits, np.array(a.home, float), (diagram, ctx)


def _ik_diagram(scenario, grippers, add_environment, X_WR):
    return make_ik_diagram(scenario.robot.name, grippers,
                           add_environment=lambda plant, parser: add_environment(plant, scenario, parser), X_WR=X_WR)


def nearest_equivalent(ik, q, q_ref):
    """q with every continuous joint (infinite limits) shifted by whole turns to within pi of
    q_ref, so a motion from q_ref does not spin a wrist or roll joint by 2 pi for nothing."""
    q = np.array(q, float)
    free = ~np.isfinite(ik.lower) & ~np.isfinite(ik.upper)
    q[free] -= 2 * np.pi * np.round((q[free] - np.asarray(q_ref)[free]) / (2 * np.pi))
    return q


def _line(ik, q_start, displacement, limits, speed):
    return plan_cartesian_line(ik, ik_pose(ik, q_start), displacement, q_start, limits, max_speed=speed)


def _start(q_home, q_first, from_home: bool, limits, q_via=None, descent: CartesianPlan | None = None) -> Timeline:
    """A timeline that rests 0.2 s, then (from_home) moves from q_home to q_first (through q_via
    when given; with `descent`, the straight line from q_via to q_first, joint motion to q_via
    first), where the sequence's first straight line begins (without from_home it starts there).
    Mark "descent": where the motion above the pre-grasp begins to come down (at q_via)."""
    tl = Timeline(q_home if from_home else q_first)
    tl.hold(0.2)
    if from_home:
        if descent is not None:
            tl.play(plan_joint_motion([q_home, q_via], limits))
            tl.mark("descent")
            tl.play(descent.trajectory)
        elif q_via is not None:
            tl.play(plan_joint_motion([q_home, q_via], limits))
            tl.mark("descent")
            tl.play(plan_joint_motion([q_via, q_first], limits))
        else:
            tl.play(plan_joint_motion([q_home, q_first], limits))
    return tl


def _via(ik, q_pre, X_pre: RigidTransform, via_z: float | None, axis_only: bool, limits, speed: float):
    """(q_via, descent): the configuration with the tool as at the pre-grasp pose but raised to the
    world height via_z, and the straight line from it down to q_pre (a CartesianPlan, planned
    upwards from q_pre and reversed, so it ends exactly at q_pre; None when it does not plan: then
    the transit's joint motion comes down from q_via). (None, None) when no raise is needed or the
    raised pose does not solve: the transit from park comes down to the pre-grasp from above
    instead of sweeping through the heap."""
    if via_z is None or X_pre.translation()[2] >= via_z:
        return None, None
    rise = via_z - X_pre.translation()[2]
    up = plan_cartesian_line(ik, X_pre, [0.0, 0.0, rise], q_pre, limits, step=0.02, axis_only=axis_only,
                             max_speed=speed)
    if up.success:
        down_qs = up.qs[::-1]
        return down_qs[0], CartesianPlan(True, "ok", down_qs,
                                         plan_path_motion(down_qs, limits, rise, max_speed=speed), 1.0)
    p = X_pre.translation().copy()
    p[2] = via_z
    res = ik.solve(RigidTransform(X_pre.rotation(), p), q_seed=q_pre, axis_only=axis_only)
    return (nearest_equivalent(ik, res.q, q_pre), None) if res.success else (None, None)


@contextmanager
def jaw_opening(ik, opening: float | None):
    """Inside, the jaw on ik's tool frame (its finger joints `left_finger_sliding_joint` /
    `right_finger_sliding_joint`, if it has them) stands opened to `opening` [m between the pads]
    in ik's plant context, so the IK's collision checks (and ms_drake.execution.reach's tool
    parts) see the fingers as the pick moves them; restored on exit. None, or a tool without
    fingers: nothing changes."""
    plant, ctx = ik.plant, ik.context
    inst = ik.frame.model_instance()
    joints = [(plant.GetJointByName(n, inst), sign) for n, sign in
              (("left_finger_sliding_joint", -1), ("right_finger_sliding_joint", 1)) if plant.HasJointNamed(n, inst)]
    if opening is None or not joints:
        yield
        return
    starts = [j.position_start() for j, _ in joints]
    q = plant.GetPositions(ctx).copy()
    old = q[starts].copy()
    for (j, sign), i in zip(joints, starts):
        q[i] = np.clip(sign * 0.5 * float(opening), j.position_lower_limits()[0], j.position_upper_limits()[0])
    plant.SetPositions(ctx, q)
    try:
        yield
    finally:
        q = plant.GetPositions(ctx).copy()
        q[starts] = old
        plant.SetPositions(ctx, q)


def _pick_lines(ik, limits, q_home, X_grasp, approach, lift, speed, axis_only):
    """Each (q_pre, approach line, lift line) of a pick at X_grasp in turn, or (last) the failing
    step's IK status when none plans. The pre-grasp configurations come from ik.solutions (from
    q_home, then each restart): an arm often reaches the pre-grasp in a posture whose straight
    lines leave the joint limits, and in another whose lines do not."""
    pre = approach_pose(X_grasp, approach)
    failure, found = None, False
    for res in ik.solutions(pre, q_seed=q_home, axis_only=axis_only):
        if not res.success:
            break
        q_pre = nearest_equivalent(ik, res.q, q_home)
        X_pre = ik_pose(ik, q_pre) if axis_only else pre
        approach_plan = plan_cartesian_line(ik, X_pre, approach * X_grasp.rotation().matrix()[:, 2], q_pre, limits,
                                            axis_only=axis_only, max_speed=speed)
        if not approach_plan.success:
            failure = failure or approach_plan.status
            continue
        lift_plan = _line(ik, approach_plan.trajectory.final(), [0, 0, lift], limits, speed)
        if not lift_plan.success:
            failure = failure or lift_plan.status
            continue
        found = True
        yield q_pre, approach_plan, lift_plan
    if not found:
        yield failure or res.status or "unreachable"


def pick_plans(ik, limits, q_home, X_grasp: RigidTransform, arm: str, gripper_port: str, kind: str,
               approach: float = PICK_APPROACH.distance, lift: float = 0.20, force_limit: float = CLOSING_FORCE,
               max_opening: float = 0.10, close_time: float = 0.8, hold_time: float = 0.5, speed: float = 0.15,
               blade: float | None = None, from_home: bool = True, via_z: float | None = None):
    """Each pick plan of a grasp in turn (lazily; plan_pick's arguments): per tool pose (a jaw's
    also turned by pi about its axis), each arm posture whose pre-grasp, straight approach and lift
    plan. Only successful plans are yielded; when none plans, one failed PickPlan with the first
    failing step's status. The order is fixed (ArmIk's fixed restarts), so the k-th plan of a grasp
    is the same plan wherever it is asked for."""
    X_grasp = as_rigid_transform(X_grasp, "X_grasp")
    axis_only = kind != "parallel_jaw"
    # A parallel jaw is symmetric: the tool turned by pi about its axis is the same grasp (the
    # fingers swap), and often the only one of the two the wrist reaches.
    poses = [X_grasp] if axis_only else [X_grasp, X_grasp @ RigidTransform(RotationMatrix.MakeZRotation(np.pi))]
    failure, found = None, False
    with jaw_opening(ik, max_opening if kind == "parallel_jaw" else None):
        for X in poses:
            for lines in _pick_lines(ik, limits, q_home, X, approach, lift, speed, axis_only):
                if isinstance(lines, str):
                    failure = failure or lines
                    continue
                q_pre, approach_plan, lift_plan = lines
                q_via, descent = _via(ik, q_pre, ik_pose(ik, q_pre), via_z, axis_only, limits, speed) \
                    if from_home else (None, None)
                found = True
                yield _pick_plan(q_home, q_pre, from_home, limits, q_via, descent, approach_plan, lift_plan, X, arm,
                                 gripper_port, kind, force_limit, max_opening, close_time, hold_time, blade)
    if not found:
        yield PickPlan(False, failure, arm, X_target=X_grasp)


def _pick_plan(q_home, q_pre, from_home, limits, q_via, descent, approach_plan, lift_plan, X_grasp, arm, gripper_port,
               kind, force_limit, max_opening, close_time, hold_time, blade) -> PickPlan:
    tl = _start(q_home, q_pre, from_home, limits, q_via, descent)
    tl.mark("approach")
    tl.play(approach_plan.trajectory)
    tl.mark("contact")
    tl.hold(close_time)
    tl.mark("lift")
    tl.play(lift_plan.trajectory)
    tl.mark("lifted")
    tl.hold(hold_time)
    commands = {}
    if kind == "parallel_jaw":
        pos, force = Schedule(), Schedule()
        pos.set(0.0, max_opening)
        pos.set(tl.marks["contact"], 0.0)
        force.set(0.0, force_limit)
        commands = {f"{gripper_port}.position": pos, f"{gripper_port}.force_limit": force}
    else:
        vac = Schedule()
        vac.set(0.0, 0.0)
        vac.set(tl.marks["contact"] - 0.1, 1.0)  # vacuum on just before touching
        commands = {f"{gripper_port}.suction": vac}
        if kind == "bluction":
            b = Schedule()
            b.set(0.0, np.pi if blade is None else blade)
            commands[f"{gripper_port}.position"] = b
    return PickPlan(True, "ok", arm, tl, commands, X_grasp, max_opening if kind == "parallel_jaw" else None)


def plan_pick(ik, limits, q_home, X_grasp: RigidTransform, arm: str, gripper_port: str, kind: str,
              approach: float = PICK_APPROACH.distance, lift: float = 0.20, force_limit: float = CLOSING_FORCE,
              max_opening: float = 0.10,
              close_time: float = 0.8, hold_time: float = 0.5, speed: float = 0.15,
              blade: float | None = None, from_home: bool = True, via_z: float | None = None,
              posture: int = 0) -> PickPlan:
    """Plan a pick at the tool pose X_grasp (kind: parallel_jaw | suction | bluction).
    from_home False: the timeline starts at the pre-grasp configuration (build_run puts the arm
    there), skipping the joint motion from home. via_z: the move from home passes above the
    pre-grasp pose at this world height (e.g. above a bin's walls and heap; None: straight there)
    and comes straight down to it (timeline mark "descent"). max_opening: the jaw's opening [m]
    from the start to contact, also held by the IK's fingers while the pick is planned (e.g.
    ms_drake.execution.backends.pick_opening of the grasp). X_grasp: RigidTransform or 4x4 array.
    posture: the plan's rank among pick_plans (0: the first that plans; e.g. the one a reach check
    found clear of the scene); the first plan when there are fewer."""
    return nth_plan(pick_plans(ik, limits, q_home, X_grasp, arm, gripper_port, kind, approach, lift, force_limit,
                               max_opening, close_time, hold_time, speed, blade, from_home, via_z), posture)


def nth_plan(plans, k: int) -> PickPlan:
    """Plan number k of a pick_plans iterator (the first when there are fewer; its failed plan when
    none plans). Closes the iterator (which restores the IK's fingers)."""
    first = None
    try:
        for i, plan in enumerate(plans):
            first = first or plan
            if i == k or not plan.success:
                return plan
        return first
    finally:
        plans.close()


def _push_lines_from_above(ik, limits, q_home, X_start, u, distance, approach, retreat, speed):
    """(q_above, down, push, up) of a push planned from `approach` above its start (IK seeded with
    q_home, then the straight lines down, along and up), or the failing step's status."""
    above = RigidTransform(X_start.rotation(), X_start.translation() + [0, 0, approach])
    res = ik.solve(above, q_seed=q_home)
    if not res.success:
        return res.status
    q_above = nearest_equivalent(ik, res.q, q_home)
    down = plan_cartesian_line(ik, above, [0, 0, -approach], q_above, limits, max_speed=speed)
    if not down.success:
        return down.status
    push = plan_cartesian_line(ik, ik_pose(ik, down.trajectory.final()), u * distance, down.trajectory.final(),
                               limits, max_speed=speed)
    if not push.success:
        return push.status
    up = _line(ik, push.trajectory.final(), [0, 0, retreat], limits, speed)
    if not up.success:
        return up.status
    return q_above, down, push, up


def _push_lines(ik, limits, q_start, X_start, u, distance, approach, retreat, speed):
    """(q_above, down, push, up) of a push from X_start along unit u, planned from the push's
    start configuration q_start outwards (down is the line up from the start, reversed), or the
    failing step's status."""
    push = plan_cartesian_line(ik, X_start, u * distance, q_start, limits, max_speed=speed)
    if not push.success:
        return push.status
    rise = plan_cartesian_line(ik, X_start, [0, 0, approach], q_start, limits, max_speed=speed)
    if not rise.success:
        return rise.status
    down_qs = rise.qs[::-1]
    down = CartesianPlan(True, "ok", down_qs, plan_path_motion(down_qs, limits, approach, max_speed=speed), 1.0)
    up = _line(ik, push.trajectory.final(), [0, 0, retreat], limits, speed)
    if not up.success:
        return up.status
    return down_qs[0], down, push, up


def plan_push(ik, limits, q_home, X_start: RigidTransform, direction, distance: float, arm: str,
              gripper_port: str | None = None, approach: float = 0.10, retreat: float = 0.05,
              speed: float = 0.1, blade: float = 0.0, settle: float = 0.3, from_home: bool = True,
              branches: int = 6) -> PickPlan:
    """A straight push: down onto X_start (from `approach` above), `distance` along `direction`
    (world), then up by `retreat`. For the bluction the blade is commanded to `blade` (down).
    X_start: RigidTransform or 4x4 array. First the IK solution above the start nearest q_home and
    the lines down, along and up from it; when a line fails there (a joint limit or a jump of a
    redundant arm along it), the lines are planned outwards from up to `branches` IK solutions at
    the push's start (ik.solutions: from q_home, then from the IK's fixed restarts); branches=0
    keeps to the first plan."""
    X_start = as_rigid_transform(X_start, "X_start")
    u = np.asarray(direction, float)
    u = u / np.linalg.norm(u)
    lines = _push_lines_from_above(ik, limits, q_home, X_start, u, distance, approach, retreat, speed)
    failure = lines if isinstance(lines, str) else None
    if failure:
        solutions = ik.solutions(X_start, q_seed=q_home) if branches > 0 else ()
        for k, res in enumerate(solutions):
            if not res.success or k >= branches:
                break
            lines = _push_lines(ik, limits, nearest_equivalent(ik, res.q, q_home), X_start, u, distance, approach,
                                retreat, speed)
            if not isinstance(lines, str):
                break
        if isinstance(lines, str):
            return PickPlan(False, failure, arm, X_target=X_start)
    q_above, down, push, up = lines
    tl = _start(q_home, q_above, from_home, limits)
    tl.play(down.trajectory)
    tl.mark("push")
    tl.play(push.trajectory)
    tl.hold(settle)  # the arm catches up with the end of the push (joint-stiffness lag) before leaving
    tl.mark("pushed")
    tl.play(up.trajectory)
    tl.hold(0.3)
    commands = {}
    if gripper_port is not None:
        b = Schedule()
        b.set(0.0, blade)
        commands[f"{gripper_port}.position"] = b
    return PickPlan(True, "ok", arm, tl, commands, X_start)
