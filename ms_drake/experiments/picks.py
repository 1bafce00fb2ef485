"""Full-fidelity picks on a simulated station: a plan of ms_drake.planning.sequences (IK +
ruckig, open loop) executed through the station's driver ports -- the arm tracks the streamed
trajectory, the gripper closes through compliant hydroelastic pads or the suction cup seals --
and what happened to the object measured (`run_task`, the `ms-drake pick` command).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.geometry import StartMeshcat
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.errors import MsDrakeError
from ms_drake.execution.backends import VIA_CLEARANCE
from ms_drake.geometry import Workspace, as_rigid_transform
from ms_drake.objects import get_object
from ms_drake.planning import TimedTrajectory, TrajectoryStreamer
from ms_drake.planning.sequences import PickPlan, arm_ik, plan_pick, plan_push
from ms_drake.robots import station_robot_spec
from ms_drake.scenario import load_scenario
from ms_drake.station.station import MakeStation, get_plant, station_objects


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
    `object_poses` (RigidTransforms or 4x4 arrays). Unscheduled command inputs keep the drivers'
    defaults."""
    object_poses = [as_rigid_transform(X, f"object_poses[{k}]") for k, X in enumerate(object_poses)]
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
    ApplySimulatorConfig(scenario.simulator_config, simulator)  # the scenario's integrator and rates
    pc = plant.GetMyMutableContextFromRoot(simulator.get_mutable_context())

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
        via_z = None  # in a bin, from home above the walls and straight down, as the bin search's picks
        if scn.environment.type == "bin":
            ws = Workspace.from_scenario(scn)
            via_z = ws.floor_z + ws.wall_height + VIA_CLEARANCE
        plan = plan_pick(ik, limits, q_home, X_tool, task.arm, task.gripper, task.kind, lift=task.lift,
                         speed=speed, blade=task.blade, from_home=from_home, max_opening=opening, via_z=via_z,
                         **pauses)
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
            Path(html_path).parent.mkdir(parents=True, exist_ok=True)
            Path(html_path).write_text(meshcat.StaticHtml())
    out.sim_seconds, out.wall_seconds, out.cpu_seconds = plan.timeline.duration, wall, cpu
    return out


def run_pick(task_name: str, html: Path | None = None, speed: float = 0.15, log=print) -> PickOutcome:
    """One task of TASKS from the home pose (the `ms-drake pick` command); with `html` the Meshcat
    recording is written there."""
    if task_name not in TASKS:
        raise PickError(f"unknown pick task {task_name!r}; choose one of {', '.join(TASKS)}")
    meshcat = StartMeshcat() if html is not None else None
    out = run_task(TASKS[task_name], from_home=True, speed=speed, meshcat=meshcat, html_path=html)
    log(f"{out.task}: success={out.success} status={out.status} lifted={out.lifted:.3f} m slip={out.slip:.4f} m "
        f"moved={out.moved:.3f} m sim={out.sim_seconds:.2f} s wall={out.wall_seconds:.1f} s "
        f"cpu={out.cpu_seconds:.1f} s RTF(wall)={out.real_time_factor:.2f} RTF(cpu)={out.cpu_real_time_factor:.2f}")
    if html is not None:
        log(f"recording: {html}")
    return out


class PickError(MsDrakeError, ValueError):
    """An unknown pick task or impossible pick settings."""
