"""Shelf search on the Fetch in Drake physics (Ch. 9.5.2 analogue, Table 9.2).

The Diagram is the whole search; a user's script is plain Drake (sims/shelf_search_diagram.py):

    scenario = shelf_physics_scenario(load_scenario(None, "FetchShelf"))
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, extra_objects=shelf_scene_objects(scene)))
    sim = shelf_simulation_info(get_plant(station), scene)
    controller = builder.AddSystem(MakeShelfSearchController(scenario, params, sim=sim))
    connect_controller(builder, controller, station)
    end = builder.AddSystem(ShelfSearchTermination(camera, sim.bodies[sim.target_id], horizon, params.period))
    connect_termination(builder, end, station, controller)
    simulator = Simulator(builder.Build())
    set_initial_conditions(simulator.get_system(), simulator.get_mutable_context(), scene)
    simulator.AdvanceTo(T)      # returns when the search is over; end.termination says why

- `build_shelf_physics(scenario, scene, params)`: that Diagram (ShelfPhysicsSystem): the FetchShelf
  station holding the scene's occluders and target as free bodies (boxes and cylinders of the drawn
  sizes, DENSITY kg/m^3, compliant hydroelastic; the target in the target colour), the shelf
  controller (ms_drake.policies.shelf_search) wired in three lines, and the search's end
  (ms_drake.policies.shelf_termination.ShelfSearchTermination). perception "ground_truth": the
  controller reads the simulation's body poses (ShelfSimulationInfo); "depth": only the station's
  camera ports, as on the hardware station (ShelfSegmenter + the learned occupancy; the termination
  system alone reads the bodies, to measure the target's visibility).
- `set_initial_conditions(system_or_diagram, context, scene)`: the one call that sets a search's
  initial conditions on the Diagram's root context: the scene's objects at their poses (resting on
  the shelf floor) and the Fetch where the controller starts (parked, blade up).
- `run_shelf_physics(system, scene, params)`: build's Diagram simulated by one
  `Simulator.AdvanceTo`: the termination system judges every idle step (the executor between
  actions, the robot parked): the target's visible fraction in the front camera's label image
  (target pixels / pixels of its silhouette, its eight corners at its current pose projected and
  filled); the search succeeds at v = 80 % (FOSS's threshold), fails at the horizon H = 2n or when
  the policy has no action (the Simulator stops there), when the simulation fails (AdvanceTo
  raises; a non-finite body pose fails it too), or at the time limit. The record is read from the
  Diagram's output ports; a read-only Simulator monitor keeps, at the idle steps, the true scene
  (perception "depth") and the pictures (keep_frames). Per executed action the backend's outcome
  says whether physics and FOSS agree (ms_drake.execution.shelf_backend: the moved object within
  2 cm of FOSS's placement, nothing else moved by more than 2 cm, nothing toppled). With perception
  "depth" the controller has no body poses and the experiment judges each action instead
  (`depth_action_outcome`): the true objects before and after it (observed at the idle steps), the
  estimate it chose matched to a true occluder (footprint IoU, `associate`), and FOSS's prediction
  on the estimated scene the action was planned in.
- `run_shelf_physics_bench(...)`: `ms-drake bench shelf-physics`: one JSON line per scene (seed,
  occluders, policy, perception, success, steps, agreement, `refused`: the candidates each of the
  controller's robot rules dropped, ...), flushed and fsync'ed, resumable.
- `physics_table(records)`: the Table 9.2 analogue.
- `replay_shelf_action(scene, action, density)`: one shelf action planned from the park pose and
  played open loop on the station (no controller), with a log of the acted-on object (sealed,
  tilt, position): checks of single actions, e.g. a suction grip of a given box.
- `run_shelf_demo(out, ...)`: `ms-drake demo shelf`: one search with per-step images, a GIF and a
  Meshcat recording; by default from the camera (perception "depth" on DEMO_SCENARIO, whose camera
  has the L515-like depth sensor model).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorStatus
from pydrake.systems.framework import Diagram, DiagramBuilder, EventStatus
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial
from scipy.stats import binomtest

from ms_drake.errors import MsDrakeError
from ms_drake.execution.shelf_backend import BLADE_UP, ShelfBackend, ShelfBody, agreement, observe
from ms_drake.experiments.records import read_record_file
from ms_drake.experiments.scene_images import write_search_pictures
from ms_drake.experiments.shelf import record_scenario, station_label
from ms_drake.experiments.shelf_segmentation import associate
from ms_drake.foss import Foss
from ms_drake.geometry import PinholeCamera
from ms_drake.objects import TARGET_RGBA
from ms_drake.objects.sdf import OBJECT_MODULUS, Inertia, Shape, object_sdf
from ms_drake.parallel import run_jobs
from ms_drake.policies.shelf_search import (
    MakeShelfSearchController,
    ShelfSearchController,
    ShelfSearchConfig,
    ShelfSimulationInfo,
    connect_controller,
)
from ms_drake.policies.shelf_termination import (
    VISIBILITY,
    ShelfSearchTermination,
    connect_termination,
    target_visible_fraction,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import DEFAULT_TARGET, generate_shelf_scene
from ms_drake.scenes.shelf_render import OCCLUDER_RGBA
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.robots import set_arm_positions
from ms_drake.types import Action, ShelfObject, ShelfScene

SCENARIO = "FetchShelf"
FIDELITY = "physics"
DENSITY = 150.0  # kg/m^3: household packaging (a 20 cm cube weighs 1.2 kg; the cup holds ~2 kg in shear)
#: The plant's time step in these runs [s] (the scenario's is 2 ms): the discrete SAP-family solver is
#: stable at 10 ms here, and the same actions end alike at 2, 5 and 10 ms (to 1-3 mm for pushes and
#: suction placements; docs/results/ch9_shelf.md) at a third of
#: the 2 ms cost.
TIME_STEP = 0.01
REFERENCE_PHYSICAL = {"der3": 33, "bluction_dar": 100}  # Table 9.2, "All" row (%)
FAR_SUCTION = 0.05  # m: the table's row of the suction actions that were to move their object this far
PHYSICS_TASKS_PER_CHILD = 4  # scenes per worker process before a fresh one (memory of unfreed diagrams)


class ShelfPhysicsError(MsDrakeError, ValueError):
    """A physics shelf run asked for with settings it cannot honour."""


def shelf_object_sdf(o: ShelfObject, rgba, density: float = DENSITY):
    """sdf(model_name) -> SDF text of a free box / upright cylinder of o's size (`density` kg/m^3,
    compliant)."""
    if not density > 0:
        raise ShelfPhysicsError(f"density={density!r}: give the objects' density in kg/m^3 (> 0; default {DENSITY})")
    w, d, h = o.width, o.depth, o.height
    if o.kind == "box":
        shape = Shape("box", (w, d, h))
        m = density * w * d * h
        inertia = Inertia(m, (0.0, 0.0, 0.0), m * (d * d + h * h) / 12, m * (w * w + h * h) / 12,
                          m * (w * w + d * d) / 12)
    else:
        r = w / 2
        shape = Shape("cylinder", (r, h))
        m = density * np.pi * r * r * h
        inertia = Inertia(m, (0.0, 0.0, 0.0), m * (3 * r * r + h * h) / 12, m * (3 * r * r + h * h) / 12, m * r * r / 2)
    return lambda name: object_sdf(name, inertia, [(shape, rgba)], [shape], compliance="compliant",
                                   modulus=OBJECT_MODULUS, contact_spheres=False)


@dataclass
class ShelfPhysicsSystem:
    """The Diagram build_shelf_physics makes and its parts: the station, its plant, the controller,
    the termination system (ShelfSearchTermination), the scenario it was built from (its plant's
    time step and no scenario objects), the shelf bodies (ShelfSimulationInfo) and the front
    camera's model."""

    diagram: object
    station: object
    plant: object
    controller: object
    scenario: object
    sim: ShelfSimulationInfo
    camera: PinholeCamera
    camera_name: str = "front"
    perception: str = "ground_truth"
    termination: object = None

    def output(self, context, name):
        return self.controller.GetOutputPort(name).Eval(self.controller.GetMyContextFromRoot(context))

    def station_output(self, context, name):
        return self.station.GetOutputPort(name).Eval(self.station.GetMyContextFromRoot(context))

    def termination_output(self, context, name):
        return self.termination.GetOutputPort(name).Eval(self.termination.GetMyContextFromRoot(context))


def with_time_step(scenario, time_step: float | None):
    """The scenario with its plant's time step replaced (None: unchanged)."""
    if time_step is None:
        return scenario
    if not time_step > 0:
        raise ShelfPhysicsError(f"time_step={time_step!r}: give a discrete time step > 0 s (e.g. {TIME_STEP})")
    config = copy.copy(scenario.plant_config)
    config.time_step = float(time_step)
    return dataclasses.replace(scenario, plant_config=config)


def shelf_physics_scenario(scenario, time_step: float | None = TIME_STEP):
    """The shelf scenario of these runs: its plant's time step `time_step` (None: the scenario's)
    and no scenario objects (the shelf scene's objects come as `shelf_scene_objects`)."""
    if scenario.environment.type != "shelf":
        raise ShelfPhysicsError(f"scenario environment is {scenario.environment.type!r}: use FetchShelf")
    return dataclasses.replace(with_time_step(scenario, time_step),
                               objects=dataclasses.replace(scenario.objects, count=0, names=[]))


def shelf_scene_objects(scene: ShelfScene, density: float = DENSITY) -> list:
    """MakeStation's extra_objects for a shelf scene: ("shelf/<id>", sdf) of every occluder and
    the target (shelf_object_sdf; the target in the target colour)."""
    if scene.target is None:
        raise ShelfPhysicsError("the shelf scene needs its target (generate_shelf_scene)")
    objs = list(scene.objects) + [scene.target]
    return [(f"shelf/{o.id}", shelf_object_sdf(o, TARGET_RGBA if o is scene.target else OCCLUDER_RGBA, density))
            for o in objs]


def shelf_simulation_info(plant, scene: ShelfScene) -> ShelfSimulationInfo:
    """ShelfSimulationInfo of a station's plant holding `scene` (shelf_scene_objects): each shelf
    object's body index and shape, and the target's id."""
    by_name = {so.full_name: so for so in station_objects(plant)}
    objs = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    missing = [o.id for o in objs if f"shelf/{o.id}" not in by_name]
    if missing:
        raise ShelfPhysicsError(f"the station's plant has no shelf object {', '.join(missing)}: build the station "
                                "with MakeStation(scenario, extra_objects=shelf_scene_objects(scene)) of this scene")
    bodies = {o.id: ShelfBody(int(by_name[f"shelf/{o.id}"].body_index), o) for o in objs}
    return ShelfSimulationInfo(bodies, scene.target.id if scene.target is not None else "")


def search_horizon(params: ShelfSearchConfig, scene: ShelfScene) -> int:
    """The action budget H: params.horizon, or 2n for n occluders."""
    return int(params.horizon) if params.horizon is not None else 2 * len(scene.objects)


def build_shelf_physics(scenario, scene: ShelfScene, params: ShelfSearchConfig, meshcat=None,
                        time_step: float | None = TIME_STEP) -> ShelfPhysicsSystem:
    """The station with the scene's objects, the shelf controller (params.perception: "ground_truth"
    or "depth") and the search's end, wired (module docstring); time_step: the plant's (None: the
    scenario's)."""
    if scene.target is None:
        raise ShelfPhysicsError("build_shelf_physics: the scene needs its target (generate_shelf_scene)")
    scenario = shelf_physics_scenario(scenario, time_step)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, meshcat=meshcat, extra_objects=shelf_scene_objects(scene)))
    plant = get_plant(station)
    sim = shelf_simulation_info(plant, scene)
    perception = params.perception
    # with "depth" the controller sees the cameras only; `sim` stays with the termination system
    controller = builder.AddSystem(MakeShelfSearchController(scenario, params, sim=None if perception == "depth" else sim))
    connect_controller(builder, controller, station)
    camera = PinholeCamera.from_config(scenario.cameras[params.camera])
    termination = builder.AddNamedSystem("termination", ShelfSearchTermination(
        camera, sim.bodies[sim.target_id], search_horizon(params, scene), params.period))
    connect_termination(builder, termination, station, controller, params.camera)
    diagram = builder.Build()
    return ShelfPhysicsSystem(diagram, station, plant, controller, scenario, sim, camera, params.camera,
                              perception, termination)


def _subsystems(diagram):
    for s in diagram.GetSystems():
        yield s
        if isinstance(s, Diagram):
            yield from _subsystems(s)


def set_initial_conditions(system_or_diagram, context, scene: ShelfScene) -> None:
    """A shelf search's initial conditions on the root `context` of its Diagram (a
    ShelfPhysicsSystem or any Diagram holding a FetchShelf station with the scene's objects and a
    shelf controller, e.g. sims/shelf_search_diagram.py's): every object of `scene` (occluders
    and target) at its pose, resting on the shelf floor, and the Fetch at the controller's initial
    commands (parked out of the camera's view), the blade up."""
    diagram = system_or_diagram.diagram if isinstance(system_or_diagram, ShelfPhysicsSystem) else system_or_diagram
    if not isinstance(diagram, Diagram):
        raise ShelfPhysicsError(f"set_initial_conditions: give the search's Diagram (or a ShelfPhysicsSystem), got "
                                f"{type(system_or_diagram).__name__}")
    systems = list(_subsystems(diagram))
    plants = [s for s in systems if isinstance(s, MultibodyPlant)]
    controllers = [s for s in systems if isinstance(s, ShelfSearchController)]
    if len(plants) != 1 or len(controllers) != 1:
        raise ShelfPhysicsError(f"set_initial_conditions: the Diagram holds {len(plants)} MultibodyPlant(s) and "
                                f"{len(controllers)} shelf controller(s); it needs one station (MakeStation) and one "
                                "MakeShelfSearchController")
    plant, controller = plants[0], controllers[0]
    sim = shelf_simulation_info(plant, scene)
    pc = plant.GetMyMutableContextFromRoot(context)
    origin = np.asarray(controller.backend.origin, float)
    for b in sim.bodies.values():
        o = b.shape
        X = RigidTransform(origin + [o.x, o.y, o.height / 2 + 1e-4])
        plant.SetFreeBodyPose(pc, plant.get_body(BodyIndex(b.body_index)), X)
    set_arm_positions(plant, pc, "fetch", controller.initial_commands())
    q = plant.GetPositions(pc)
    q[plant.GetJointByName("blade_joint").position_start()] = np.pi
    plant.SetPositions(pc, q)


#: Shorter name of set_initial_conditions.
set_initial = set_initial_conditions


def target_visibility(system: ShelfPhysicsSystem, context) -> float:
    """Target pixels in the front label image / pixels of its silhouette at its current pose
    (ms_drake.policies.shelf_termination.target_visible_fraction)."""
    label = np.asarray(system.station_output(context, f"{system.camera_name}.label_image").data)[:, :, 0]
    b = system.sim.bodies[system.sim.target_id]
    X = system.station_output(context, "body_poses")[b.body_index]
    t = b.shape
    return target_visible_fraction(label, X, (t.width, t.depth, t.height), b.body_index, system.camera)


@dataclass
class ShelfFrame:
    step: int
    rgb: np.ndarray
    depth: np.ndarray
    occupancy: object
    action: object
    visible: float
    scene: ShelfScene | None = None  # the controller's observation (ground truth, or estimated from depth)


@dataclass
class ShelfPhysicsResult:
    record: dict
    frames: list = field(default_factory=list)


class IdleStepRecorder:
    """A read-only Simulator monitor (`simulator.set_monitor(recorder)`) of a shelf search: at every
    idle step the termination system judges (ShelfCheck.judging at its check times) it keeps the
    judged visibility, the true scene (observe: (ShelfScene, toppled ids)) by history length when
    `truths`, and a ShelfFrame when `keep_frames`. It evaluates output ports only and never
    changes the context."""

    def __init__(self, system: ShelfPhysicsSystem, horizon: int, truths: bool = False, keep_frames: bool = False):
        self.system, self.horizon = system, int(horizon)
        self.keep_truths, self.keep_frames = bool(truths), bool(keep_frames)
        self.truths: dict = {}
        self.frames: list = []
        self.visible = 0.0
        self.origin = np.asarray(system.scenario.environment.position, float)

    def __call__(self, context):
        system = self.system
        if system.termination.is_check_time(context.get_time()):
            check = system.termination_output(context, "check")
            if check.judging:
                self._record(context, check)
        return EventStatus.Succeeded()

    def _record(self, context, check) -> None:
        system = self.system
        self.visible = check.visible
        if self.keep_truths:
            self.truths[check.steps] = observe(system.station_output(context, "body_poses"), system.sim.bodies,
                                               self.origin, system.sim.target_id)
        if self.keep_frames:
            action = system.output(context, "action") if check.visible < VISIBILITY and check.steps < self.horizon \
                else None
            rgb = np.array(system.station_output(context, f"{system.camera_name}.rgb_image").data)[..., :3].copy()
            depth = np.array(system.station_output(context, f"{system.camera_name}.depth_image").data)[..., 0].copy()
            self.frames.append(ShelfFrame(check.steps, rgb, depth, system.output(context, "occupancy_history"),
                                          action, check.visible, system.output(context, "scene")))


def end_time(max_sim_time: float, period: float) -> float:
    """The first check time k * period at or after max_sim_time."""
    k = max(0, int(np.ceil(max_sim_time / period)) - 1)
    while k * period < max_sim_time:
        k += 1
    return k * period


def run_shelf_physics(system: ShelfPhysicsSystem, scene: ShelfScene, params: ShelfSearchConfig,
                      keep_frames: bool = False, meshcat=None, max_sim_time: float | None = None) -> ShelfPhysicsResult:
    """Simulate build_shelf_physics's Diagram until its termination system stops it, the simulation
    fails, or max_sim_time (default 60 s + 45 s per action of the horizon); the record (module
    docstring) from its output ports and the idle-step monitor (IdleStepRecorder)."""
    n = len(scene.objects)
    horizon = system.termination.horizon
    max_sim_time = max_sim_time or 60.0 + 45.0 * horizon
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    simulator = Simulator(system.diagram)
    ApplySimulatorConfig(system.scenario.simulator_config, simulator)
    context = simulator.get_mutable_context()
    set_initial_conditions(system, context, scene)
    recorder = IdleStepRecorder(system, horizon, truths=system.perception == "depth", keep_frames=keep_frames)
    simulator.set_monitor(recorder)
    failure, reason, error = "", "", ""
    if meshcat is not None:
        meshcat.StartRecording(set_visualizations_while_recording=False)
    try:
        status = simulator.AdvanceTo(end_time(max_sim_time, system.termination.period))
        if status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition:
            end = system.termination_output(context, "termination")
            failure = "" if end.success else end.reason
            reason = end.message if end.reason == "no_action" else ""
        else:
            failure = "timeout"
        visible = float(system.termination_output(context, "visibility")[0])
    except RuntimeError as e:
        failure, error = "sim_failed", (str(e).splitlines() or [type(e).__name__])[0]
        visible = recorder.visible
    finally:
        simulator.clear_monitor()
        if meshcat is not None:
            meshcat.StopRecording()
            meshcat.PublishRecording()
    history = system.output(context, "history")
    truths = recorder.truths
    if system.perception == "depth":
        foss = Foss(ShelfGeometry.from_scenario(system.scenario, system.camera_name))
        history = tuple(depth_action_outcome(o, truths.get(i), truths.get(i + 1), foss)
                        if not o.message.startswith("plan_failed") else o for i, o in enumerate(history))
    executed = [o for o in history if not o.message.startswith("plan_failed")]
    agree = [agreement(o) for o in executed]
    kinds = [o.action.shelf.kind for o in executed]
    rec = dict(seed=int(scene.seed), occluders=n, objects=n, policy=params.policy, fidelity=FIDELITY,
               perception=system.perception,
               success=not failure, steps=len(history), actions=len(history), executed=len(executed),
               pushes=kinds.count("push"), suctions=kinds.count("suction"),
               plan_failures=len(history) - len(executed),
               agreement=[a for a in agree], agree=sum(1 for a in agree if a), compared=sum(1 for a in agree if a is not None),
               outcomes=[o.message for o in history],
               actions_taken=[[o.action.shelf.kind, o.action.shelf.object_id, round(o.action.shelf.dx, 4),
                               round(o.action.shelf.dy, 4)] for o in history],
               skipped=sum(_skipped(o.action.reason) for o in history),
               refused=_refused(o.action.reason for o in history),
               time_step=float(system.plant.time_step()), config=params.record(),
               visible_fraction=float(visible), failure=failure, stop_reason=reason, error=error,
               sim_seconds=float(context.get_time()), seconds=time.perf_counter() - t_wall,
               cpu_seconds=time.process_time() - t_cpu, pid=os.getpid())
    return ShelfPhysicsResult(rec, recorder.frames)


def depth_action_outcome(outcome, before, after, foss: Foss, tolerance: float = 0.02):
    """The outcome of an action a depth-perception controller executed, judged with the
    simulation's truth (module docstring): `before` / `after` are (true ShelfScene, toppled ids)
    at the idle steps around it (None: not observed, e.g. the run stopped mid-action). The message
    has ShelfBackend.outcome's fields (agree, err, moved, commanded, others, toppled, foss) and
    `chose=<true id>` ("-" when the estimate matched no occluder: then agree=0); err compares the
    true object's displacement with FOSS's displacement of the estimate."""
    a, est = outcome.action.shelf, outcome.action.scene
    if before is None or after is None or est is None:
        return dataclasses.replace(outcome, message=f"{outcome.message} chose=? (not observed)")
    (b, toppled0), (f, toppled1) = before, after
    ids = [o.id for o in est.objects]
    named = associate(est, ShelfScene(b.objects, None, b.seed)).objects[ids.index(a.object_id)].id
    xy = lambda sc: {o.id: np.array([o.x, o.y]) for o in list(sc.objects) + ([sc.target] if sc.target else [])}
    p0, p1 = xy(b), xy(f)
    predicted, fo = foss.step(est, a)
    e0, e1 = est.object(a.object_id), predicted.object(a.object_id)
    commanded = float(np.hypot(e1.x - e0.x, e1.y - e0.y))
    new_toppled = set(toppled1) - set(toppled0)
    foss_msg = "ok" if fo.success else fo.message
    if named not in p0:
        others = max((float(np.linalg.norm(p1[k] - p0[k])) for k in p0), default=0.0)
        msg = (f"agree=0 err=nan moved=nan commanded={commanded:.3f} others={others:.3f} "
               f"toppled={','.join(toppled1) or '-'} foss={foss_msg} chose=-")
        return dataclasses.replace(outcome, message=msg)
    d_true, d_pred = p1[named] - p0[named], np.array([e1.x - e0.x, e1.y - e0.y])
    err = float(np.linalg.norm(d_true - d_pred))
    others = max((float(np.linalg.norm(p1[k] - p0[k])) for k in p0 if k != named), default=0.0)
    agree = fo.success and err <= tolerance and others <= tolerance and not new_toppled
    msg = (f"agree={int(agree)} err={err:.3f} moved={float(np.linalg.norm(d_true)):.3f} commanded={commanded:.3f} "
           f"others={others:.3f} toppled={','.join(toppled1) or '-'} foss={foss_msg} chose={named}")
    return dataclasses.replace(outcome, message=msg)


def _skipped(reason: str) -> int:
    """Candidates FetchFeasibleSelector skipped before an action ("... (k Fetch-infeasible skipped)")."""
    m = re.search(r"\((\d+) Fetch-infeasible skipped\)", reason or "")
    return int(m.group(1)) if m else 0


def _refused(reasons) -> dict:
    """Candidates the policy's robot rules dropped, summed over the actions, per rule: the reasons'
    "[refused: nil_move 0, min_move 12, revisit 1]" (ms_drake.policies.shelf.ShelfPolicies)."""
    out: dict = {}
    for reason in reasons:
        m = re.search(r"\[refused: ([^\]]*)\]", reason or "")
        for rule, n in re.findall(r"(\w+) (\d+)", m.group(1) if m else ""):
            out[rule] = out.get(rule, 0) + int(n)
    return out


def check_shelf_scenario(scenario, name: str = "") -> None:
    """ShelfPhysicsError (naming the scenario and the fix) unless `scenario` is a shelf station with
    the Fetch and its bluction tool, as the shelf search needs."""
    label = f"scenario {name!r}" if name else "the scenario"
    if scenario.environment.type != "shelf":
        raise ShelfPhysicsError(f"{label} is a {scenario.environment.type} station; the shelf search needs a shelf "
                                "scenario with the Fetch (FetchShelf)")
    if scenario.robot.name != "fetch" or "bluction" not in scenario.robot.grippers:
        raise ShelfPhysicsError(f"{label} has the robot {scenario.robot.name or 'none'!r} with "
                                f"{', '.join(scenario.robot.grippers) or 'no grippers'}; the shelf search runs on the "
                                "Fetch with the bluction tool (FetchShelf)")


def shelf_physics_rollout(config: ShelfSearchConfig, seed: int, occluders: int | None = None,
                          scenario_name: str = SCENARIO, meshcat=None, keep_frames: bool = False,
                          time_step: float | None = TIME_STEP, scenario_file: str | None = None) -> ShelfPhysicsResult:
    """Generate the scene of `seed` (occluders: None draws 2-12 from the seed) and search it with the
    controller of `config` (its seed set to `seed`) on the station `scenario_name` of `scenario_file`
    (default FetchShelf of diagrams/scenarios.yaml)."""
    scenario = load_scenario(scenario_file, scenario_name)
    check_shelf_scenario(scenario, scenario_name)
    geometry = ShelfGeometry.from_scenario(scenario)
    sample = generate_shelf_scene(geometry, seed, occluders, DEFAULT_TARGET)
    params = dataclasses.replace(config, seed=int(seed))
    system = build_shelf_physics(scenario, sample.scene, params, meshcat=meshcat, time_step=time_step)
    result = run_shelf_physics(system, sample.scene, params, keep_frames=keep_frames, meshcat=meshcat)
    result.record["scenario"] = station_label(scenario_name, scenario_file)
    return result


@dataclass
class ShelfActionReplay:
    """One shelf action played open loop on the station (replay_shelf_action): the backend's
    outcome (ActionOutcome; its message as in the searches' records) and, every `log_period`, the
    acted-on object: rows (t [s], vacuum on, sealed, tilt [deg], x, y, z in the shelf frame [m])."""

    outcome: object
    log: np.ndarray

    def sealed_span(self) -> tuple[float, float] | None:
        """(first, last) time the cup held the object (None: never)."""
        t = self.log[self.log[:, 2] > 0.5, 0]
        return (float(t[0]), float(t[-1])) if t.size else None

    def max_tilt_sealed(self) -> float:
        rows = self.log[self.log[:, 2] > 0.5]
        return float(rows[:, 3].max()) if len(rows) else float("nan")


def replay_shelf_action(scene: ShelfScene, action, density: float = DENSITY, scenario_name: str = SCENARIO,
                        time_step: float | None = TIME_STEP, log_period: float = 0.1) -> ShelfActionReplay:
    """ShelfAction `action` planned by ShelfBackend from the park pose in `scene` and played open
    loop (the Motion's commands sampled every 10 ms into TrajectorySources, no controller) on the
    FetchShelf station holding the scene's objects at `density`; for checking one action's physics
    (e.g. a suction grip of a given box) without a search. Raises ShelfPhysicsError when the action
    does not plan."""
    scenario = load_scenario(None, scenario_name)
    scenario = dataclasses.replace(with_time_step(scenario, time_step),
                                   objects=dataclasses.replace(scenario.objects, count=0, names=[]))
    objs = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    extra = [(f"shelf/{o.id}", shelf_object_sdf(o, TARGET_RGBA if o is scene.target else OCCLUDER_RGBA, density))
             for o in objs]
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, extra_objects=extra))
    plant = get_plant(station)
    by_name = {so.full_name: so for so in station_objects(plant)}
    bodies = {o.id: ShelfBody(int(by_name[f"shelf/{o.id}"].body_index), o) for o in objs}
    backend = ShelfBackend(scenario, bodies, scene.target.id if scene.target is not None else "")
    motion = backend.plan_scene(action, backend.q_park, scene)
    if isinstance(motion, str):
        raise ShelfPhysicsError(f"replay_shelf_action: {action} does not plan on the Fetch ({motion})")
    hold = backend.initial_commands()
    times = np.arange(0.0, motion.duration + 0.01, 0.01)
    for port in (f"{backend.arm}.position", f"{backend.tool}.suction", f"{backend.tool}.position"):
        values = np.array([motion.values(t, hold)[port] for t in times]).T
        traj = (PiecewisePolynomial.FirstOrderHold if port.startswith(backend.arm + ".") else
                PiecewisePolynomial.ZeroOrderHold)(times, values)
        src = builder.AddSystem(TrajectorySource(traj))
        builder.Connect(src.get_output_port(), station.GetInputPort(port))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator_config, sim)
    ctx = sim.get_mutable_context()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    origin = np.asarray(scenario.environment.position, float)
    for b in bodies.values():
        o = b.shape
        plant.SetFreeBodyPose(pc, plant.get_body(BodyIndex(b.body_index)), RigidTransform(origin + [o.x, o.y, o.height / 2 + 1e-4]))
    set_arm_positions(plant, pc, backend.arm, {f"{backend.arm}.position": backend.q_park})
    q = plant.GetPositions(pc)
    q[plant.GetJointByName("blade_joint").position_start()] = BLADE_UP
    plant.SetPositions(pc, q)
    sim.Initialize()
    sc = station.GetMyContextFromRoot(ctx)
    body = bodies[action.object_id].body_index
    rows, t = [], 0.0
    while t < motion.duration - 1e-9:
        t = min(t + log_period, motion.duration)
        sim.AdvanceTo(t)
        X = station.GetOutputPort("body_poses").Eval(sc)[body]
        tilt = float(np.degrees(np.arccos(np.clip(X.rotation().matrix()[2, 2], -1.0, 1.0))))
        sealed = station.GetOutputPort(f"{backend.tool}.suction_state").Eval(sc)[0]
        vacuum = motion.values(t, hold)[f"{backend.tool}.suction"][0]
        rows.append([t, vacuum, sealed, tilt, *(X.translation() - origin)])
    outcome, _ = backend.outcome(Action("shelf", shelf=action), motion, station.GetOutputPort("body_poses").Eval(sc),
                                 0, ())
    return ShelfActionReplay(outcome, np.array(rows))


def _bench_job(job: tuple) -> dict:
    config, seed, n, kwargs = job
    return shelf_physics_rollout(ShelfSearchConfig(**config), seed, n, **kwargs).record


def _config_key(config: dict) -> str:
    return json.dumps(config, sort_keys=True)


def read_physics_records(path) -> list[dict]:
    """The records of a `bench shelf-physics` file (resuming: a missing file has none); each keeps
    its config, else one error names the file and line."""
    return read_record_file(path, ("seed", "config"), writer="bench shelf-physics", resume=True)


def run_shelf_physics_bench(config: ShelfSearchConfig, scenes: int, seed_start: int, out,
                            occluders: list[int] | None = None, workers: int = 1, log=print, progress=None,
                            **kwargs) -> list[dict]:
    """Missing (seed) rollouts of `config`, one JSON line each (flushed and fsync'ed as each scene
    ends: resumable; a record of another config is not one of them); occluders cycles through the
    given counts by seed (None: drawn from the seed); workers: local processes
    (ms_drake.parallel.run_jobs; fresh processes every few scenes, as Drake diagrams are never
    freed); progress(rec) after each scene, and its `start(done, todo)`, if it has one, before the
    first; kwargs: shelf_physics_rollout's (scenario_name, scenario_file, time_step)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    key = _config_key(config.record())
    station = station_label(kwargs.get("scenario_name", SCENARIO), kwargs.get("scenario_file"))
    done = {int(r["seed"]) for r in read_physics_records(out)
            if _config_key(r["config"]) == key and record_scenario(r) == station}
    jobs = [(dataclasses.asdict(config), seed, occluders[i % len(occluders)] if occluders else None, dict(kwargs))
            for i, seed in enumerate(range(seed_start, seed_start + scenes)) if seed not in done]
    recs = []
    policy, perception = config.policy, config.perception
    if progress is not None and hasattr(progress, "start"):
        progress.start(scenes - len(jobs), len(jobs))
    for res in run_jobs(_bench_job, jobs, workers=workers, max_tasks_per_child=PHYSICS_TASKS_PER_CHILD):
        if not res.ok:
            log(f"seed {res.job[1]} {policy}: failed ({res.error.splitlines()[0]}); run again to retry it")
            continue
        rec = res.value
        with open(out, "a") as f:
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())
        recs.append(rec)
        log(f"seed {rec['seed']} ({rec['occluders']} occluders) {policy} ({perception}): "
            f"{'success' if rec['success'] else rec['failure']} after {rec['steps']} actions "
            f"({rec['plan_failures']} plan failures, {rec['skipped']} Fetch-infeasible skipped), FOSS agrees on "
            f"{rec['agree']}/{rec['compared']}, {rec['sim_seconds']:.0f} s simulated in {rec['cpu_seconds']:.0f} s CPU "
            f"({rec['seconds']:.0f} s wall)")
        if progress is not None:
            progress(rec)
    return recs


def _fields(message: str) -> dict:
    return dict(tok.split("=", 1) for tok in message.split() if "=" in tok)


def action_agreement(rec: dict, tolerance: float = 0.02, min_commanded: float = 0.0) -> list[tuple[str, bool]]:
    """(kind, physics = FOSS) of every executed action of a record, from its outcome messages
    (ms_drake.execution.shelf_backend): FOSS accepted it, the moved object ended within
    `tolerance` of FOSS's placement, nothing else moved by more than `tolerance`, and the action
    toppled nothing (an object lying toppled since an earlier action does not count again).
    min_commanded [m]: only the actions that were to move their object at least that far (a
    suction that puts an object back within a centimetre of where it was agrees with FOSS by
    doing next to nothing)."""
    out, before = [], set()
    for (kind, *_), msg in zip(rec["actions_taken"], rec["outcomes"]):
        f = _fields(msg)
        if "err" not in f:
            continue  # a plan failure: nothing executed
        toppled = set() if f.get("toppled", "-") == "-" else set(f["toppled"].split(","))
        ok = (f.get("foss") == "ok" and float(f["err"]) <= tolerance and float(f["others"]) <= tolerance
              and not toppled - before)
        if float(f.get("commanded", "nan")) >= min_commanded or min_commanded <= 0:
            out.append((kind, bool(ok)))
        before = toppled
    return out


def physics_table(recs: list[dict], policies=("der3", "bluction_dar")) -> str:
    """Table 9.2 analogue (markdown): per occluder count and policy, successes and the steps of the
    successful searches; then success rate, median steps (IQR), plan failures (actions the Fetch
    could not plan when executing them), candidates the Fetch-feasibility check skipped, and
    physics-FOSS agreement per executed action (action_agreement), for pushes and suction apart."""
    names = {"der3": "DER-3", "bluction_dar": "Bluction-DAR", "dar": "DAR", "random": "Random",
             "oracle_p": "Oracle-P", "oracle_ps": "Oracle-P+S"}
    by = {p: [r for r in recs if r["policy"] == p] for p in policies}
    counts = sorted({r["occluders"] for r in recs})
    lines = ["| occluders | metric | " + " | ".join(names.get(p, p) for p in policies) + " |",
             "| --- | --- | " + " | ".join("---" for _ in policies) + " |"]
    for n in counts:
        cells, steps = [], []
        for p in policies:
            rs = [r for r in by[p] if r["occluders"] == n]
            ok = [r for r in rs if r["success"]]
            cells.append(f"{len(ok)}/{len(rs)}")
            steps.append(", ".join(str(r["steps"]) for r in ok) or "(-)")
        lines.append(f"| {n} | successes | " + " | ".join(cells) + " |")
        lines.append("| | no. steps | " + " | ".join(steps) + " |")

    def pct(a, c):
        return f"{100 * a / c:.0f} % ({a}/{c})" if c else "-"

    rows = {k: [] for k in ("rate", "med", "fail", "skip", "agree", "push", "suction", "far")}
    for p in policies:
        rs = by[p]
        ok = [r["steps"] for r in rs if r["success"]]
        rows["rate"].append(pct(len(ok), len(rs)) if rs else "-")
        rows["med"].append(f"{np.median(ok):.1f} ({np.percentile(ok, 25):.1f} - {np.percentile(ok, 75):.1f})"
                           if ok else "-")
        rows["fail"].append(f"{sum(r['plan_failures'] for r in rs)} of {sum(r['steps'] for r in rs)} steps")
        rows["skip"].append(str(sum(r.get("skipped", 0) for r in rs)))
        ag = [a for r in rs for a in action_agreement(r)]
        rows["agree"].append(pct(sum(ok for _, ok in ag), len(ag)))
        for kind in ("push", "suction"):
            k = [ok for kd, ok in ag if kd == kind]
            rows[kind].append(pct(sum(k), len(k)))
        far = [ok for r in rs for kd, ok in action_agreement(r, min_commanded=FAR_SUCTION) if kd == "suction"]
        rows["far"].append(pct(sum(far), len(far)))
    for key, label in (("rate", "success rate"), ("med", "median steps (IQR)"), ("fail", "plan failures"),
                       ("skip", "Fetch-infeasible candidates skipped"), ("agree", "physics = FOSS per action"),
                       ("push", "physics = FOSS, pushes"), ("suction", "physics = FOSS, suction"),
                       ("far", f"physics = FOSS, suction moving >= {100 * FAR_SUCTION:.0f} cm")):
        lines.append(f"| all | {label} | " + " | ".join(rows[key]) + " |")
    return "\n".join(lines)


def physics_vs_foss(phys: list[dict], foss: list[dict], policies=("der3", "bluction_dar")) -> str:
    """The search outcome in physics against FOSS on the same scenes (markdown): per policy, the
    scenes in both (same seed, occluder count and policy; ground-truth perception in FOSS), the
    successes of each, the scenes only one of them solves, and the two-sided exact sign test on
    those. Says whether the Fetch's failures are the policy's (FOSS fails too) or the physics'."""
    names = {"der3": "DER-3", "bluction_dar": "Bluction-DAR", "dar": "DAR"}
    lines = ["| policy | scenes | physics | FOSS | both | physics only | FOSS only | sign test p |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for p in policies:
        a = {(record_scenario(r), r["occluders"], r["seed"]): bool(r["success"]) for r in phys if r["policy"] == p}
        b = {(record_scenario(r), r["occluders"], r["seed"]): bool(r["success"]) for r in foss
             if r["policy"] == p and r.get("perception", "ground_truth") == "ground_truth"}
        keys = sorted(set(a) & set(b))
        if not keys:
            continue
        only_a = [k for k in keys if a[k] and not b[k]]
        only_b = [k for k in keys if b[k] and not a[k]]
        n = len(only_a) + len(only_b)
        pval = float(binomtest(len(only_a), n, 0.5).pvalue) if n else 1.0

        def seeds(ks):
            return f"{len(ks)}" + (" (seeds " + ", ".join(str(s) for *_, s in ks) + ")" if ks else "")
        lines.append(f"| {names.get(p, p)} | {len(keys)} | {sum(a[k] for k in keys)} | {sum(b[k] for k in keys)} | "
                     f"{sum(a[k] and b[k] for k in keys)} | {seeds(only_a)} | {seeds(only_b)} | {pval:.2g} |")
    if len(lines) == 2:
        raise ShelfPhysicsError("no scene is in both the physics and the FOSS records (same station, seed, occluders, "
                                "policy): run `ms-drake bench shelf` with the physics run's --scenario, --occluders "
                                "and --seed-start")
    return "\n".join(lines)


# ------------------------------------------------------------------------------ demo
DEMO_SEED = 0
DEMO_OCCLUDERS = 6
DEMO_SCENARIO = "FetchShelfL515"  # FetchShelf with its camera's L515-like sensor model: the search from the camera


def _depth_panel(depth: np.ndarray) -> np.ndarray:
    d = np.where(np.isfinite(depth), depth, np.nan)
    lo, hi = np.nanpercentile(d, 1), np.nanpercentile(d, 99)
    g = np.nan_to_num((d - lo) / max(hi - lo, 1e-6), nan=1.0).clip(0, 1)
    return cv2.applyColorMap((255 * (1 - g)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[:, :, ::-1].copy()


def _distribution_panel(rgb: np.ndarray, occ) -> np.ndarray:
    pic = (0.6 * rgb).astype(np.uint8)
    if occ is not None and occ.image_x.size == rgb.shape[1] and occ.image_x.max() > 0:
        h = rgb.shape[0]
        p = occ.image_x / occ.image_x.max()
        for u, v in enumerate(p):
            if v > 0:
                cv2.line(pic, (u, h - 1), (u, h - 1 - int(0.8 * h * v)), (255, 140, 0), 1)
    cv2.putText(pic, "P'_t(x): target occupancy along the image x axis", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                (255, 255, 255), 2)
    return pic


def _action_panel(rgb: np.ndarray, frame: ShelfFrame, system: ShelfPhysicsSystem, scene: ShelfScene) -> np.ndarray:
    pic = rgb.copy()
    a = frame.action.shelf if frame.action is not None and frame.action.kind == "shelf" else None
    origin = np.asarray(system.scenario.environment.position, float)
    if a is not None:
        o = scene.object(a.object_id)
        if a.kind == "push":
            p0 = origin + [o.x, o.y - o.depth / 2, 0.04]
            p1 = p0 + [a.dx, 0.0, 0.0]
            color, text = (0, 200, 255), f"push {a.object_id} dx={a.dx:+.3f} m"
        else:
            half = 0.5 * system.scenario.environment.resolved_size()[1]
            p0 = origin + [o.x, o.y, o.height]
            p1 = origin + [o.x + a.dx, -half + a.dy + o.depth / 2, o.height]
            color, text = (0, 255, 0), f"suction {a.object_id} dx={a.dx:+.3f} dy={a.dy:.3f} m"
        uv, _ = system.camera.project(np.stack([p0, p1]))
        uv = np.round(uv).astype(int)
        cv2.arrowedLine(pic, tuple(map(int, uv[0])), tuple(map(int, uv[1])), color, 3, tipLength=0.2)
    else:
        text = "target revealed" if frame.visible >= VISIBILITY else "stop"
    cv2.putText(pic, f"step {frame.step}: visible {100 * frame.visible:.0f} %  {text}", (8, 24),
                cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2)
    return pic


def run_shelf_demo(out, seed: int = DEMO_SEED, occluders: int = DEMO_OCCLUDERS, policy: str = "bluction_dar",
                   horizon: int | None = None, meshcat_html: bool = True, log=print,
                   perception: str = "depth", scenario=None) -> dict:
    """One search on the Fetch (module docstring) with the controller's `perception`: step_kk.png
    (depth | distribution | action on the observed scene), search.gif, search.json and
    meshcat_recording.html in `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario if scenario is not None else load_scenario(None, DEMO_SCENARIO)
    check_shelf_scenario(scenario)
    sample = generate_shelf_scene(ShelfGeometry.from_scenario(scenario), seed, occluders, DEFAULT_TARGET)
    params = ShelfSearchConfig(policy=policy, horizon=horizon, seed=seed, perception=perception)
    meshcat = Meshcat() if meshcat_html else None
    system = build_shelf_physics(scenario, sample.scene, params, meshcat=meshcat)
    res = run_shelf_physics(system, sample.scene, params, keep_frames=True, meshcat=meshcat)
    pictures, scene = [], sample.scene
    for k, fr in enumerate(res.frames):
        # the scene the action was chosen in: the controller's observation at that step
        scene = _observed(res, k, sample.scene)
        pictures.append((fr.step, np.concatenate([_depth_panel(fr.depth), _distribution_panel(fr.rgb, fr.occupancy),
                                                  _action_panel(fr.rgb, fr, system, scene)], axis=1)))
    written = write_search_pictures(out, pictures, res.record, meshcat, gif_seconds=1.5)
    r = res.record
    log(f"  {policy} ({perception} perception) on seed {seed} ({occluders} occluders): {'success' if r['success'] else r['failure']} after "
        f"{r['steps']} actions (visible {100 * r['visible_fraction']:.0f} %), FOSS agrees on {r['agree']}/{r['compared']}, "
        f"{r['sim_seconds']:.0f} s simulated in {r['seconds']:.0f} s")
    return written


def _observed(res: ShelfPhysicsResult, k: int, scene: ShelfScene) -> ShelfScene:
    return res.frames[k].scene if getattr(res.frames[k], "scene", None) is not None else scene


def physics_records(files, perception: str | None = None) -> list[dict]:
    """The physics shelf records (fidelity "physics") of result files, one per (config, seed): the
    first (two runs over overlapping seed ranges into one file may both write a seed); perception:
    only that perception's (None: all)."""
    out, seen = [], set()
    for f in files:
        for r in read_record_file(Path(f), ("seed", "config"), writer="bench shelf-physics"):
            key = (_config_key(r["config"]), r["perception"], r["seed"], record_scenario(r))
            if r.get("fidelity") == FIDELITY and key not in seen and perception in (None, key[1]):
                seen.add(key)
                out.append(r)
    return out
