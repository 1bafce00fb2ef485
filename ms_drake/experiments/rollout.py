"""One mechanical-search rollout in the bin: station + controller diagram + the driver loop.

The controller diagram is the same in both fidelities (DESIGN.md "Data flow"):
  overhead.label_image -> Segmenter(ground_truth) -> masks
  overhead.rgb_image + masks -> TargetDetector(color) -> target
  overhead.depth_image + target -> OccupancyEstimator(analytic)      (xray only)
  depth + masks (+ simulation meshes) -> LazyGraspPlanner (jaw + suction GraspPlanners, robust
                                         contact-model quality, planned per object on demand)
  depth + masks -> PushPlanner                                       (pushing selectors only)
  -> PolicySelector(policy) -> action -> ActionExecutor(backend) -> station command inputs
  ActionExecutor.history -> PolicySelector.history
Only the fidelity's backend and station differ: primitive = FloatingGripperBin + PrimitiveBackend,
full = YuMiBin + FullBackend (jaw grasps; suction grasps are also planned for the YuMi's left arm).

The driver advances the simulator in executor periods; when `removed` grows it moves those
objects out of the plant (remove_objects), and it stops when the executor is done, the simulation
fails, or `max_sim_time` passes. Failure modes (RolloutResult.failure): "" on success, else one of
FAILURE_MODES.
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.errors import MsDrakeError
from ms_drake.execution import (
    FIDELITIES,
    ActionExecutor,
    ExecutionError,
    FullBackend,
    PrimitiveBackend,
    connect_executor,
    remove_objects,
    tcp_offset_of,
)

FAILURE_MODES = {
    "target_never_visible": "the target was not seen in any step",
    "empty_segmentation": "no object mask when an action was needed",
    "grasps_below_threshold": "every grasp below its threshold and no valid push",
    "sim_blew_up": "the simulation failed (solver error or non-finite state)",
    "worker_died": "the worker process died or raised",
    "too_many_pushes": "more than 3 consecutive pushes",
    "horizon": "the action budget (2N, or H) ran out",
    "target_removed": "the target left the bin by accident",
    "timeout": "simulated time ran out before the search ended",
}
SCENARIOS = {"primitive": "FloatingGripperBin", "full": "YuMiBin"}


@dataclass
class SearchParams:
    policy: str = "largest"
    fidelity: str = "primitive"
    horizon: int | None = None  # None: 2N
    seed: int = 0
    # Grasp planners whose candidates are merged (the selector takes the best per mask): the
    # parallel jaw and suction, as in Ch. 7 (primitive: success = quality for either; full: jaw on
    # the right arm, suction on the left).
    grasp_models: tuple = ("soft_point", "suction")
    grasp_samples: int = 8
    robust_samples: int = 4
    grasp_params: dict | None = None  # GraspEvaluator keywords, e.g. {"closing_force": 40.0}
    period: float = 0.05
    # Plant step [s]; None keeps the scenario's (2 ms). The primitive mode only needs the heap to
    # settle and the closed jaw to push, so it runs at 10 ms like the heap generator (our choice).
    time_step: float | None = None
    # Discrete contact approximation; None (default) keeps the scenario's ("lagged"), the physics
    # station_check validates. History: with the station's former rigid objects (point contact on
    # corner spheres) the primitive mode ran SAP, because under "lagged" at 10 ms those objects kept
    # bouncing. With the compliant station objects of the bin scenarios (objects.compliance) SAP at
    # 10 ms blew up (non-finite poses) in 10 of 200 Random rollouts of Table C.1's heaps, while
    # "lagged" and "similar" ran those heaps without a blow-up (docs/BENCHMARKS.md).
    contact_approximation: str | None = None

    def __post_init__(self):
        from ms_drake.policies.bin_selectors import check_policy

        check_policy(self.policy)
        if self.fidelity not in FIDELITIES:
            raise ExecutionError(f"fidelity {self.fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")


@dataclass
class Frame:
    """What the controller saw before an action (for the demo): images and its choice."""

    step: int
    rgb: np.ndarray
    masks: object
    target: object
    occupancy: object
    action: object


@dataclass
class RolloutResult:
    seed: int
    policy: str
    fidelity: str
    objects: int  # N requested (the heap generator drops objects that leave the bin)
    success: bool
    actions: int
    action_kinds: list
    failure: str
    stop_reason: str
    seconds: float  # wall
    cpu_seconds: float  # this process's CPU time (the cost on one core, whatever the machine's load)
    sim_seconds: float
    target: str = ""
    grasp_successes: int = 0
    objects_present: int = 0  # objects in the heap searched (its budget 2N counts these)
    grasp_plans: int = 0  # object grasp plans (LazyGraspPlanner: only the masks the selector reached)
    error: str = ""
    frames: list = field(default_factory=list, repr=False)

    def record(self) -> dict:
        d = asdict(self)
        d.pop("frames")
        return d


@dataclass
class SearchSystem:
    diagram: object
    station: object
    plant: object
    executor: ActionExecutor
    selector: object
    perception: dict
    target_id: str
    bodies: dict  # object id -> body index
    scenario: object


def build_search(scenario, heap, params: SearchParams, meshcat=None) -> SearchSystem:
    """Station of `scenario` holding `heap` (target drawn red) + the controller diagram."""
    from ms_drake.grasping.planner import GraspPlanner, ObjectGeometrySource
    from ms_drake.objects import get_object
    from ms_drake.geometry import PinholeCamera
    from ms_drake.perception.masks import object_labels
    from ms_drake.perception.occupancy import OccupancyEstimator, TargetBox, TargetMesh
    from ms_drake.geometry import Workspace
    from ms_drake.perception.segmentation import Segmenter
    from ms_drake.perception.target import TargetDetector
    from ms_drake.policies import PolicySelector, SelectorParams
    from ms_drake.pushing import PushPlanner
    from ms_drake.scenes.heaps import scenario_with_heap
    from ms_drake.station import MakeStation, get_plant, station_objects

    n = len(heap.objects)
    s = scenario_with_heap(copy.deepcopy(scenario), heap)
    if params.time_step is not None:
        s.plant_config.time_step = float(params.time_step)
    approx = params.contact_approximation
    if approx is not None:
        s.plant_config.discrete_contact_approximation = approx
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, meshcat=meshcat, target_index=heap.target_index))
    plant = get_plant(station)
    objs = station_objects(plant)
    bodies = {o.model_name: int(o.body_index) for o in objs}
    target_id = objs[heap.target_index].model_name if heap.target_index >= 0 else ""
    cfg = s.cameras["overhead"]
    cam = PinholeCamera.from_config(cfg)
    ws = Workspace.from_scenario(s)
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(plant)))
    det = builder.AddSystem(TargetDetector("color", width=cam.width, height=cam.height))
    color_cam, _ = cfg.MakeCameras()
    from ms_drake.experiments.adapters import LazyGraspPlanner

    # The GraspPlanners are not systems of this diagram: LazyGraspPlanner calls them per object.
    planners = [GraspPlanner(color_cam.core().intrinsics(), cam.X_WC, model=m, num_samples=params.grasp_samples,
                             robust_samples=params.robust_samples, seed=params.seed,
                             evaluator_params=params.grasp_params if m != "suction" else None)
                for m in params.grasp_models]
    grasp = builder.AddSystem(LazyGraspPlanner(planners, cam.width, cam.height, seed=params.seed))
    geo = builder.AddSystem(ObjectGeometrySource({
        o.model_name: (plant.get_body(o.body_index), get_object(o.full_name).trimesh(), get_object(o.full_name).mass,
                       None) for o in objs}))
    horizon = params.horizon if params.horizon is not None else 2 * n
    selector = builder.AddSystem(PolicySelector(params.policy, SelectorParams(horizon=horizon, seed=params.seed),
                                                target_id=target_id, width=cam.width, height=cam.height))
    depth, rgb, label = (station.GetOutputPort(f"overhead.{p}") for p in ("depth_image", "rgb_image", "label_image"))
    builder.Connect(label, seg.GetInputPort("label_image"))
    builder.Connect(rgb, det.GetInputPort("rgb_image"))
    builder.Connect(seg.GetOutputPort("masks"), det.GetInputPort("masks"))
    builder.Connect(station.GetOutputPort("body_poses"), geo.GetInputPort("body_poses"))
    builder.Connect(depth, grasp.GetInputPort("depth_image"))
    builder.Connect(seg.GetOutputPort("masks"), grasp.GetInputPort("masks"))
    builder.Connect(geo.GetOutputPort("objects"), grasp.GetInputPort("objects"))
    builder.Connect(seg.GetOutputPort("masks"), selector.GetInputPort("masks"))
    builder.Connect(det.GetOutputPort("target"), selector.GetInputPort("target"))
    builder.Connect(grasp.GetOutputPort("grasps"), selector.GetInputPort("grasps"))
    perception = {"segmenter": seg, "detector": det, "grasps": grasp}
    if params.policy.endswith("_push"):
        pushes = builder.AddSystem(PushPlanner(cam, ws))
        builder.Connect(depth, pushes.GetInputPort("depth_image"))
        builder.Connect(seg.GetOutputPort("masks"), pushes.GetInputPort("masks"))
        builder.Connect(pushes.GetOutputPort("pushes"), selector.GetInputPort("pushes"))
        perception["pushes"] = pushes
    if params.policy == "xray" or meshcat is not None or params.policy == "oracle":
        # The target's own mesh at its true initial pose (Ch. 8.3.1 renders the target itself):
        # rotation bin 0 and a grid node are its true placement (see occupancy.TargetMesh).
        shape = (TargetMesh.from_object(heap.target, heap.objects[heap.target_index].matrix())
                 if heap.target_index >= 0 else TargetBox.from_object(heap.target))
        occ = builder.AddSystem(OccupancyEstimator("analytic", camera=cam, workspace=ws, target_size=shape))
        builder.Connect(depth, occ.GetInputPort("depth_image"))
        builder.Connect(det.GetOutputPort("target"), occ.GetInputPort("target"))
        if params.policy == "xray":
            builder.Connect(occ.GetOutputPort("occupancy"), selector.GetInputPort("occupancy"))
        perception["occupancy"] = occ
    if params.policy == "oracle":
        from ms_drake.experiments.adapters import TargetAmodalMask
        from ms_drake.perception.masks import make_amodal_masks

        amodal = builder.AddSystem(make_amodal_masks(plant, cam))
        pick = builder.AddSystem(TargetAmodalMask(target_id))
        builder.Connect(station.GetOutputPort("body_poses"), amodal.get_input_port())
        builder.Connect(amodal.get_output_port(), pick.get_input_port())
        builder.Connect(pick.get_output_port(), selector.GetInputPort("target_amodal"))
    if params.fidelity == "primitive":
        backend = PrimitiveBackend(bodies, ws, tcp_offset_of(plant), target_id=target_id, seed=params.seed)
    else:
        backend = FullBackend(s, bodies, ws, target_id=target_id, seed=params.seed)
    executor = builder.AddSystem(ActionExecutor(backend, period=params.period))
    connect_executor(builder, executor, station, selector)
    diagram = builder.Build()
    return SearchSystem(diagram, station, plant, executor, selector, perception, target_id, bodies, s)


def _set_initial(system: SearchSystem, context, heap):
    """Heap poses, and the robot at the executor's initial commands (parked / home)."""
    from ms_drake.scenes.heaps import set_heap_poses
    from ms_drake.robots import station_robot_spec

    set_heap_poses(system.station, context, heap)
    plant, pc = system.plant, system.plant.GetMyMutableContextFromRoot(context)
    spec = station_robot_spec(system.scenario.robot.name)
    init = system.executor.backend.initial_commands()
    q = plant.GetPositions(pc)
    for arm, a in spec.arms.items():
        if f"{arm}.position" in init:
            for name, v in zip(a.joints, np.atleast_1d(init[f"{arm}.position"])):
                q[plant.GetJointByName(name).position_start()] = v
    plant.SetPositions(pc, q)


def _frame(system: SearchSystem, context, step: int) -> Frame:
    def ev(sys, port):
        return sys.GetOutputPort(port).Eval(sys.GetMyContextFromRoot(context))

    occ = system.perception.get("occupancy")
    return Frame(step, np.array(ev(system.station, "overhead.rgb_image").data)[..., :3].copy(),
                 ev(system.perception["segmenter"], "masks"), ev(system.perception["detector"], "target"),
                 ev(occ, "occupancy") if occ is not None else None, ev(system.selector, "action"))


def run_search(system: SearchSystem, heap, params: SearchParams, max_sim_time: float | None = None,
               keep_frames: bool = False, meshcat=None) -> RolloutResult:
    """Simulate until the executor is done; returns the rollout's result (with frames if asked)."""
    n = len(heap.objects)
    horizon = params.horizon if params.horizon is not None else 2 * n
    max_sim_time = max_sim_time or 30.0 + 12.0 * horizon
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    simulator = Simulator(system.diagram)
    context = simulator.get_mutable_context()
    _set_initial(system, context, heap)
    simulator.Initialize()
    ex = system.executor
    ex_ctx = ex.GetMyContextFromRoot(context)
    pc = system.plant.GetMyMutableContextFromRoot(context)
    seen_visible, empty_at_stop = False, False
    frames, removed_done, last_steps = [], set(), -1
    failure, t, k = "", 0.0, 0
    if meshcat is not None:
        meshcat.StartRecording(set_visualizations_while_recording=False)
    try:
        while True:
            status = ex.status_port.Eval(ex_ctx)
            if status.done:
                break
            if not status.busy and status.steps != last_steps:  # idle: the next action is chosen now
                last_steps = status.steps
                target = system.perception["detector"].GetOutputPort("target").Eval(
                    system.perception["detector"].GetMyContextFromRoot(context))
                seen_visible |= bool(target.visible)
                if keep_frames:
                    frames.append(_frame(system, context, status.steps))
            if t >= max_sim_time:
                failure = "timeout"
                break
            # t = k * period exactly as Drake computes the executor's update times, so this
            # loop's perception evaluation at an idle step is the very context (and cache) the
            # executor's update then reads (an accumulated sum drifts below the event time and
            # every image would be rendered twice).
            k += 1
            t = k * params.period
            simulator.AdvanceTo(t)
            gone = [r for r in ex.removed_port.Eval(ex_ctx) if r not in removed_done]
            if gone:
                remove_objects(system.plant, pc, [system.bodies[r] for r in gone if r in system.bodies])
                removed_done.update(gone)
            if not np.all(np.isfinite(system.plant.GetPositions(pc))):
                raise RuntimeError("non-finite plant state")
    except RuntimeError as e:  # Drake solver failures surface as RuntimeError
        failure = "sim_blew_up"
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
    else:
        msg = ""
    finally:
        if meshcat is not None:
            meshcat.StopRecording()
            meshcat.PublishRecording()
    status = ex.status_port.Eval(ex_ctx)
    history = ex.history_port.Eval(ex_ctx)
    reason = status.stop_reason if status.done else failure
    success = reason == "success"
    if not failure and not success:
        if reason == "no_action":
            masks = system.perception["segmenter"].GetOutputPort("masks").Eval(
                system.perception["segmenter"].GetMyContextFromRoot(context))
            empty_at_stop = len(masks) == 0
            failure = ("empty_segmentation" if empty_at_stop else
                       "target_never_visible" if not seen_visible else "grasps_below_threshold")
        else:
            failure = reason or "unknown"
    kinds = [o.action.kind for o in history]
    res = RolloutResult(seed=heap.seed, policy=params.policy, fidelity=params.fidelity, objects=n, objects_present=n,
                        success=success,
                        actions=len(history), action_kinds=kinds, failure=failure, stop_reason=reason,
                        seconds=time.perf_counter() - t_wall, cpu_seconds=time.process_time() - t_cpu,
                        sim_seconds=float(context.get_time()),
                        target=heap.target,
                        grasp_successes=sum(1 for o in history if o.action.kind == "grasp" and o.success),
                        grasp_plans=system.perception["grasps"].planned,
                        error=msg, frames=frames)
    return res


def rollout(policy: str, objects: int, seed: int, fidelity: str = "primitive", horizon: int | None = None,
            heap=None, keep_frames: bool = False, meshcat=None, **kw) -> RolloutResult:
    """Generate heap `seed` (N objects, BinHeap15's bin) and search it with `policy`."""
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap

    kw.setdefault("time_step", 0.01 if fidelity == "primitive" else None)
    params = SearchParams(policy=policy, fidelity=fidelity, horizon=horizon, seed=seed, **kw)
    if heap is None:
        heap = generate_heap(load_scenario(None, "BinHeap15"), objects, seed, params=SEARCH_HEAPS)
    scenario = load_scenario(None, SCENARIOS[fidelity])
    system = build_search(scenario, heap, params, meshcat=meshcat)
    res = run_search(system, heap, params, keep_frames=keep_frames, meshcat=meshcat)
    res.objects = int(objects)  # the N asked for: what the benchmark's files are keyed by
    return res


class RolloutError(MsDrakeError, ValueError):
    """A rollout was asked for with impossible settings."""
