"""Full-fidelity picks on a simulated station: plan with IK + ruckig, then execute through the
station's driver ports (the arm tracks a streamed trajectory; the gripper closes through compliant
hydroelastic pads, or the suction cup seals) and measure what happened to the object.

A pick is planned open-loop before the simulation starts (our choice: the reference's
simulation experiments execute a planned grasp; re-planning belongs to the action executor):
  jaw:     home -> pre-grasp (`approach` above along the tool axis, ruckig joint motion) ->
           straight approach -> close with a force limit -> straight lift -> hold
  suction: the same with vacuum on at contact instead of closing
  push:    home -> pre-push above the start -> straight down -> straight push -> straight up
The timeline is played by `TrajectoryStreamer` into `<arm>.position`; gripper commands are a
zero-order-hold schedule into `<gripper>.position` / `.force_limit` / `.suction`.
Planning failures return a PickPlan with success False and the IK status ("unreachable" /
"collision"), never an exception.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.math import RigidTransform

from ms_drake.types import JointLimits
from ms_drake.planning import ArmIk, TimedTrajectory, TrajectoryStreamer, approach_pose, ik_pose, make_ik_diagram, plan_cartesian_line, plan_joint_motion
from ms_drake.planning.trajectories import JointTrajectory


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

    def source(self):
        from pydrake.systems.primitives import TrajectorySource
        from pydrake.trajectories import PiecewisePolynomial

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


# --------------------------------------------------------------------------------- planning
def arm_ik(scenario, arm: str, frame: str = "tcp", min_distance: float | None = 0.005, seed: int = 0):
    """ArmIk for `arm` of the scenario's robot on a plant with the robot, its grippers (jaws
    open, every arm at home) and the environment (no objects). Returns (ik, limits, q_home,
    keep_alive) -- keep `keep_alive` (the diagram and its context) while using ik."""
    from ms_drake.scenario import resolve_robot_config
    from ms_drake.robots import station_robot_spec
    from ms_drake.station.robots import base_transform, set_home
    from ms_drake.station.station import add_environment

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
    ik = ArmIk(plant, pc, a.joints, plant.GetFrameByName(frame, g[arm]), min_distance=min_distance, restarts=5,
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
    from ms_drake.planning import ik_pose

    return plan_cartesian_line(ik, ik_pose(ik, q_start), displacement, q_start, limits, max_speed=speed)


def plan_pick(ik, limits, q_home, X_grasp: RigidTransform, arm: str, gripper_port: str, kind: str,
              approach: float = 0.10, lift: float = 0.20, force_limit: float = 30.0, max_opening: float = 0.10,
              close_time: float = 0.8, hold_time: float = 0.5, speed: float = 0.15,
              blade: float | None = None, from_home: bool = True) -> PickPlan:
    """Plan a pick at the tool pose X_grasp (kind: parallel_jaw | suction | bluction).
    from_home False: the timeline starts at the pre-grasp configuration (build_run puts the arm
    there), skipping the joint motion from home."""
    axis_only = kind != "parallel_jaw"
    pre = approach_pose(X_grasp, approach)
    res = ik.solve(pre, q_seed=q_home, axis_only=axis_only)
    if not res.success:
        return PickPlan(False, res.status, arm, X_target=X_grasp)
    q_pre = nearest_equivalent(ik, res.q, q_home)
    X_pre = ik_pose(ik, q_pre) if axis_only else pre
    approach_plan = plan_cartesian_line(ik, X_pre, approach * X_grasp.rotation().matrix()[:, 2], q_pre, limits,
                                        axis_only=axis_only, max_speed=speed)
    if not approach_plan.success:
        return PickPlan(False, approach_plan.status, arm, X_target=X_grasp)
    q_grasp = approach_plan.trajectory.final()
    lift_plan = _line(ik, q_grasp, [0, 0, lift], limits, speed)
    if not lift_plan.success:
        return PickPlan(False, lift_plan.status, arm, X_target=X_grasp)
    tl = Timeline(q_home if from_home else q_pre)
    tl.hold(0.2)
    if from_home:
        tl.play(plan_joint_motion([q_home, q_pre], limits))
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
    return PickPlan(True, "ok", arm, tl, commands, X_grasp)


def plan_push(ik, limits, q_home, X_start: RigidTransform, direction, distance: float, arm: str,
              gripper_port: str | None = None, approach: float = 0.10, retreat: float = 0.05,
              speed: float = 0.1, blade: float = 0.0, settle: float = 0.3, from_home: bool = True) -> PickPlan:
    """A straight push: down onto X_start (from `approach` above), `distance` along `direction`
    (world), then up by `retreat`. For the bluction the blade is commanded to `blade` (down)."""
    from ms_drake.planning import ik_pose

    above = RigidTransform(X_start.rotation(), X_start.translation() + [0, 0, approach])
    res = ik.solve(above, q_seed=q_home)
    if not res.success:
        return PickPlan(False, res.status, arm, X_target=X_start)
    q_above = nearest_equivalent(ik, res.q, q_home)
    down = plan_cartesian_line(ik, above, [0, 0, -approach], q_above, limits, max_speed=speed)
    if not down.success:
        return PickPlan(False, down.status, arm, X_target=X_start)
    u = np.asarray(direction, float)
    u = u / np.linalg.norm(u)
    q_start = down.trajectory.final()
    push = plan_cartesian_line(ik, ik_pose(ik, q_start), u * distance, q_start, limits, max_speed=speed)
    if not push.success:
        return PickPlan(False, push.status, arm, X_target=X_start)
    up = _line(ik, push.trajectory.final(), [0, 0, retreat], limits, speed)
    if not up.success:
        return PickPlan(False, up.status, arm, X_target=X_start)
    tl = Timeline(q_home if from_home else q_above)
    tl.hold(0.2)
    if from_home:
        tl.play(plan_joint_motion([q_home, q_above], limits))
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


# --------------------------------------------------------------------------------- execution
@dataclass
class Run:
    """A built pick simulation: the root diagram, its simulator, the station and its plant."""

    diagram: object
    simulator: object
    station: object
    plant: object

    @property
    def context(self):
        return self.simulator.get_context()

    def plant_context(self):
        return self.plant.GetMyContextFromRoot(self.context)

    def object_pose(self, body) -> RigidTransform:
        return self.plant.EvalBodyPoseInWorld(self.plant_context(), body)

    def output(self, name):
        return self.station.GetOutputPort(name).Eval(self.station.GetMyContextFromRoot(self.context))


def pick_scenario(scenario, object_names, cameras: bool = False):
    """A copy of `scenario` holding exactly `object_names` (e.g. ["procedural/box_021"])."""
    objects = dataclasses.replace(scenario.objects, names=list(object_names), count=0)
    return dataclasses.replace(scenario, objects=objects, cameras=scenario.cameras if cameras else {})


def build_run(scenario, plan: PickPlan, object_poses=(), meshcat=None) -> Run:
    """Station + TrajectoryStreamer + command schedules; objects (in station order) at
    `object_poses`. Unscheduled command inputs keep the drivers' defaults."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from ms_drake.station.station import MakeStation, get_plant, station_objects

    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, meshcat=meshcat))
    plant = get_plant(station)
    for obj, X in zip(station_objects(plant), object_poses):
        plant.SetDefaultFloatingBaseBodyPose(plant.get_body(obj.body_index), X)
    n = len(plan.timeline.final())
    streamer = builder.AddSystem(TrajectoryStreamer(n, trajectory=TimedTrajectory(plan.timeline, 0.0)))
    streamer.set_name(f"{plan.arm}_streamer")
    builder.Connect(streamer.GetOutputPort("position"), station.GetInputPort(f"{plan.arm}.position"))
    for port, schedule in plan.commands.items():
        src = builder.AddSystem(schedule.source())
        src.set_name(f"{port}_schedule")
        builder.Connect(src.get_output_port(), station.GetInputPort(port))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    pc = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    from ms_drake.robots import station_robot_spec

    instance = plant.GetModelInstanceByName(scenario.robot.name) if scenario.robot.name != "floating" else None
    q_all = plant.GetPositions(pc)
    for n, q in zip(station_robot_spec(scenario.robot.name).arms[plan.arm].joints, plan.timeline.q_start):
        joint = plant.GetJointByName(n, instance) if instance is not None else plant.GetJointByName(n)
        q_all[joint.position_start()] = q  # the arm starts where the timeline starts
    plant.SetPositions(pc, q_all)
    simulator.Initialize()
    return Run(diagram, simulator, station, plant)


def record(run: Run, meshcat, until: float, html_path) -> float:
    """Advance `run` to `until` while recording Meshcat; write the static HTML; returns wall s."""
    meshcat.StartRecording(set_visualizations_while_recording=False)
    start = time.perf_counter()
    run.simulator.AdvanceTo(until)
    wall = time.perf_counter() - start
    meshcat.StopRecording()
    meshcat.PublishRecording()
    from pathlib import Path

    Path(html_path).parent.mkdir(parents=True, exist_ok=True)
    Path(html_path).write_text(meshcat.StaticHtml())
    return wall


# --------------------------------------------------------------------------------- tasks
@dataclass(frozen=True)
class PickTask:
    """One full-fidelity pick (or push) of the issue's list: scenario, arm, gripper, object and
    its pose, the tool pose (object frame = world here: the object starts axis-aligned)."""

    name: str
    scenario: str
    arm: str
    gripper: str  # port prefix
    kind: str  # parallel_jaw | suction | bluction
    object: str
    xy: tuple  # object centre on the support surface (z from its height)
    mode: str = "pick"  # pick | push
    lift: float = 0.20
    push: tuple = (1.0, 0.0, 0.0)  # direction (world)
    push_distance: float = 0.10
    blade: float = float(np.pi)  # bluction blade for picks (up)


def _tool_rotation(task):
    from pydrake.math import RollPitchYaw, RotationMatrix

    if task.scenario == "FetchShelf":  # tool level, pointing into the shelf (+y), body y up (blade down)
        return RotationMatrix(np.array([[-1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]))
    if task.kind == "parallel_jaw":  # pointing down, closing across the object's y (its short side)
        return RotationMatrix(RollPitchYaw(np.pi, 0, np.pi / 2))
    return RotationMatrix(RollPitchYaw(np.pi, 0, 0))  # suction from above


TASKS = {
    "yumi_jaw": PickTask("yumi_jaw", "YuMiBin", "yumi_right", "yumi_right_jaw", "parallel_jaw",
                         "procedural/box_021", (-0.10, -0.12)),
    "yumi_suction": PickTask("yumi_suction", "YuMiBin", "yumi_left", "yumi_left_suction", "suction",
                             "procedural/box_027", (-0.10, 0.12)),
    "panda_jaw": PickTask("panda_jaw", "PandaTable", "panda", "panda_jaw", "parallel_jaw",
                          "procedural/box_048", (-0.15, 0.0)),
    "fetch_push": PickTask("fetch_push", "FetchShelf", "fetch", "fetch_bluction", "bluction",
                           "procedural/box_021", (0.0, -0.05), mode="push"),
    "fetch_suction": PickTask("fetch_suction", "FetchShelf", "fetch", "fetch_bluction", "bluction",
                              "procedural/box_021", (0.0, -0.05), lift=0.10),
}


def task_tool_pose(task) -> RigidTransform:
    """The tool pose of the task: the jaw's tcp 17 mm below the object's top (pads fully on it);
    the suction cup's lip 2 mm above the top (or in front of the face for the Fetch); the
    bluction blade 15 mm beside the object's -x face, 6 mm above the shelf."""
    from ms_drake.objects import get_object

    ext = get_object(task.object).extents
    x, y = task.xy
    R = _tool_rotation(task)
    if task.mode == "push":
        return RigidTransform(R, [x - ext[0] / 2 - 0.015, y, 0.006 + 0.075 / 2])
    if task.scenario == "FetchShelf":
        return RigidTransform(R, [x, y - ext[1] / 2 - 0.002, ext[2] / 2])
    if task.kind == "parallel_jaw":
        return RigidTransform(R, [x, y, ext[2] - 0.017])
    return RigidTransform(R, [x, y, ext[2] + 0.002])


def plan_task(task: PickTask, from_home: bool = True, speed: float = 0.15, scenario=None, quick: bool = False):
    """(scenario, plan, X_object) of a task; scenario defaults to the task's, holding only the object.
    quick: shorter pauses (close 0.5 s, hold 0.25 s) for tests."""
    from ms_drake.objects import get_object
    from ms_drake.scenario import load_scenario

    base = scenario or load_scenario(None, task.scenario)
    scn = pick_scenario(base, [task.object])
    ext = get_object(task.object).extents
    X_object = RigidTransform([task.xy[0], task.xy[1], ext[2] / 2 + 1e-4])
    frame = "blade_tcp" if task.mode == "push" else "tcp"
    ik, limits, q_home, keep = arm_ik(scn, task.arm, frame=frame)
    X_tool = task_tool_pose(task)
    if task.mode == "push":
        plan = plan_push(ik, limits, q_home, X_tool, task.push, task.push_distance + 0.013, task.arm, task.gripper,
                         speed=min(speed, 0.1), from_home=from_home)
    else:
        opening = 0.10
        pauses = dict(close_time=0.5, hold_time=0.25) if quick else {}
        plan = plan_pick(ik, limits, q_home, X_tool, task.arm, task.gripper, task.kind, lift=task.lift,
                         speed=speed, blade=task.blade, from_home=from_home, max_opening=opening, **pauses)
    del keep
    return scn, plan, X_object


@dataclass
class PickOutcome:
    """What happened: success, object motion, and the simulation's cost."""

    task: str
    success: bool
    status: str
    lifted: float = 0.0  # m the object rose (picks)
    slip: float = float("nan")  # m the object moved relative to the tool while lifted (picks)
    moved: float = 0.0  # m the object moved along the push direction (pushes)
    sideways: float = 0.0  # m off the push line
    sim_seconds: float = 0.0
    wall_seconds: float = 0.0
    cpu_seconds: float = 0.0

    @property
    def real_time_factor(self) -> float:
        return self.sim_seconds / self.wall_seconds if self.wall_seconds else float("nan")

    @property
    def cpu_real_time_factor(self) -> float:
        return self.sim_seconds / self.cpu_seconds if self.cpu_seconds else float("nan")


def run_task(task: PickTask, from_home: bool = True, speed: float = 0.15, meshcat=None, html_path=None,
             scenario=None, quick: bool = False) -> PickOutcome:
    """Plan and simulate a task; with meshcat + html_path also write the Meshcat recording."""
    from ms_drake.station.station import station_objects

    scn, plan, X_object = plan_task(task, from_home, speed, scenario, quick)
    if not plan.success:
        return PickOutcome(task.name, False, plan.status)
    run = build_run(scn, plan, [X_object], meshcat=meshcat)
    body = run.plant.get_body(station_objects(run.plant)[0].body_index)
    tool = run.plant.GetFrameByName("tcp", run.plant.GetModelInstanceByName(task.gripper))
    p0 = run.object_pose(body).translation()
    marks = plan.timeline.marks
    wall = cpu = 0.0

    def advance(t):
        nonlocal wall, cpu
        w, c = time.perf_counter(), time.process_time()
        run.simulator.AdvanceTo(t)
        wall += time.perf_counter() - w
        cpu += time.process_time() - c

    if meshcat is not None:
        meshcat.StartRecording(set_visualizations_while_recording=False)
    if task.mode == "push":
        advance(plan.timeline.duration)
        p1 = run.object_pose(body).translation()
        u = np.asarray(task.push, float) / np.linalg.norm(task.push)
        moved = float(np.dot(p1 - p0, u))
        sideways = float(np.linalg.norm((p1 - p0) - moved * u))
        ok = abs(moved - task.push_distance) < 0.01 and sideways < 0.01 and abs(p1[2] - p0[2]) < 0.005
        out = PickOutcome(task.name, ok, "ok" if ok else "missed", moved=moved, sideways=sideways)
    else:
        advance(marks["lift"])
        X_TO_grasped = tool.CalcPoseInWorld(run.plant_context()).inverse() @ run.object_pose(body)
        advance(plan.timeline.duration)
        X_TO_end = tool.CalcPoseInWorld(run.plant_context()).inverse() @ run.object_pose(body)
        lifted = float(run.object_pose(body).translation()[2] - p0[2])
        slip = float(np.linalg.norm(X_TO_end.translation() - X_TO_grasped.translation()))
        ok = lifted > 0.9 * task.lift and slip < 0.01
        out = PickOutcome(task.name, ok, "ok" if ok else "dropped", lifted=lifted, slip=slip)
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        if html_path is not None:
            from pathlib import Path

            Path(html_path).parent.mkdir(parents=True, exist_ok=True)
            Path(html_path).write_text(meshcat.StaticHtml())
    out.sim_seconds, out.wall_seconds, out.cpu_seconds = plan.timeline.duration, wall, cpu
    return out


def main(task_name: str, argv=None):
    """Command line of the sims/pick_*.py scripts: run one task from home and write its Meshcat
    recording (default sims/out/<task>.html)."""
    import argparse

    parser = argparse.ArgumentParser(description=f"Full-fidelity pick: {task_name}")
    parser.add_argument("--html", default=f"sims/out/{task_name}.html", help="Meshcat recording to write")
    parser.add_argument("--no-meshcat", action="store_true", help="simulate only (no recording)")
    parser.add_argument("--speed", type=float, default=0.15, help="tool speed on straight lines [m/s]")
    args = parser.parse_args(argv)
    meshcat = None
    if not args.no_meshcat:
        from pydrake.geometry import StartMeshcat

        meshcat = StartMeshcat()
    out = run_task(TASKS[task_name], from_home=True, speed=args.speed, meshcat=meshcat,
                   html_path=None if args.no_meshcat else args.html)
    print(f"{out.task}: success={out.success} status={out.status} lifted={out.lifted:.3f} m slip={out.slip:.4f} m "
          f"moved={out.moved:.3f} m sim={out.sim_seconds:.2f} s wall={out.wall_seconds:.1f} s "
          f"cpu={out.cpu_seconds:.1f} s RTF(wall)={out.real_time_factor:.2f} RTF(cpu)={out.cpu_real_time_factor:.2f}")
    if meshcat is not None and not args.no_meshcat:
        print(f"recording: {args.html}")
    return out
