"""One mechanical-search rollout in the bin: a simulated station holding a heap wired to the
bin-search controller of ms_drake.policies.bin_search (MakeBinSearchController, ground-truth
segmentation and exact grasp meshes through SimulationInfo), simulated by Drake's Simulator.

Only the fidelity's backend and station differ: primitive = FloatingGripperBin + PrimitiveBackend,
full = the scenario's robot (YuMiBin by default, `rollout(..., scenario_name=...)`) + FullBackend.

A rollout builds the diagram, sets its initial conditions (`set_initial_conditions`), runs
`Simulator.AdvanceTo(max_sim_time)` and reads the record from the controller's ports: the diagram
itself removes lifted objects (the robot, or the primitive mode's ObjectCarrier, drops them into a
drop-off tray), ends the simulation when the search is over and fails it on a blow-up. A read-only
monitor (SearchObserver) notes what the record needs besides the ports. Failure modes
(RolloutResult.failure): "" on success, else one of FAILURE_MODES.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus

from ms_drake.errors import MsDrakeError
from ms_drake.execution import FIDELITIES, PRIMITIVE_PUSH_TIME_STEP, ExecutionError
from ms_drake.perception.occupancy import TargetBox, TargetMesh
from ms_drake.policies.bin_search import (
    BinSearchController,
    BinSearchParams,
    MakeBinSearchController,
    SimulationInfo,
    check_search_scenario,
    connect_controller,
    search_scenario,
    set_initial_conditions,
)
from ms_drake.policies.bin_selectors import OCCUPANCY_POLICIES, PUSHING, check_policy
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap
from ms_drake.station import MakeStation, get_plant, station_objects

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
# The reference's three failure modes (lines 1326-1328) over ours: (1) "the policy fails to plan an
# action" -- every stop for want of an action, and a run of pushes that never made a grasp possible
# (the selector's stop after 3 of them); (2) "the target object is inadvertently removed";
# (3) the 2N budget ran out. What the reference does not have (the simulator or a worker failed) is
# "other".
REFERENCE_FAILURE_CLASSES = {
    "grasps_below_threshold": "no_action", "target_never_visible": "no_action", "empty_segmentation": "no_action",
    "too_many_pushes": "no_action", "target_removed": "target_removed", "horizon": "horizon",
    "sim_blew_up": "other", "worker_died": "other", "timeout": "other",
}
SCENARIOS = {"primitive": "FloatingGripperBin", "full": "YuMiBin"}


SEARCH_OCCUPANCIES = ("learned", "analytic_image", "analytic_image_best", "analytic")  # SearchParams.occupancy
IMAGE_BEST_MATCH = 0.05  # "analytic_image_best": AnalyticOccupancy(best_match=...)


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
    # OccupancyEstimator backend of X-Ray (SEARCH_OCCUPANCIES): "learned" (from the target's size
    # and the images only), "analytic_image" (the ground-truth generator on the depth image and the
    # target's box, no pose: the distribution the learned network is trained to predict),
    # "analytic_image_best" (the same with best_match = IMAGE_BEST_MATCH: a partly seen target that no
    # placement matches keeps the best-matching placements, not its modal mask) or
    # "analytic" (the generator on the target's own mesh at its true pose: privileged). The oracle
    # always uses "analytic" with the true pose: it is the labelled upper bound.
    occupancy: str = "learned"
    occupancy_weights: str = ""  # the learned occupancy's weights file ("": the shipped one)
    # Plant step [s]; None keeps the scenario's (2 ms). `rollout` sets the primitive mode's
    # (primitive_time_step): the heap only needs to settle, so 10 ms like the heap generator (our
    # choice), and 5 ms for the selectors that push, where the closed jaw's push agrees with the
    # YuMi's (PRIMITIVE_PUSH_TIME_STEP).
    time_step: float | None = None
    # Discrete contact approximation; None (default) keeps the scenario's ("lagged"), the physics
    # station_check validates. History: with the station's former rigid objects (point contact on
    # corner spheres) the primitive mode ran SAP, because under "lagged" at 10 ms those objects kept
    # bouncing. With the compliant station objects of the bin scenarios (objects.compliance) SAP at
    # 10 ms blew up (non-finite poses) in 10 of 200 Random rollouts of Table C.1's heaps, while
    # "lagged" and "similar" ran those heaps without a blow-up (docs/BENCHMARKS.md).
    contact_approximation: str | None = None
    # Perception of the controller (BinSearchParams.segmentation / .detector): "ground_truth" masks
    # from the label image (default) or a depth segmenter ("euclidean", "region_growing",
    # "learned"); the target detector "color" (default), "template" or "learned" (both of the
    # latter match templates rendered of the target object).
    segmenter: str = "ground_truth"
    detector: str = "color"
    # BinSearchParams.grasp_planner: "indexed" (the objects' grasp sets) or "image"; "" (default):
    # indexed for the primitive fidelity, image for the full one
    grasp_planner: str = ""
    # The *_push selectors' pushes (BinSearchParams.push_policy): "" = the Ch. 7 free-space push,
    # or a Ch. 4 policy (ms_drake.pushing.POLICIES).
    push_policy: str = ""
    # BinSearchParams.reach: with the indexed planner, only grasps this robot reaches ("" none,
    # "robot" the station's own, or a scenario name such as "YuMiBin")
    reach: str = ""
    # BinSearchParams.grasp_outcome: the primitive mode's grasp outcome (execution.GRASP_OUTCOMES),
    # "draw" (p = quality), or deterministic: "threshold", "checked", "nominal"
    grasp_outcome: str = "draw"
    # BinSearchParams.skip_failed: a failed grasp is not attempted again on the state it failed on
    skip_failed: bool = False
    # BinSearchParams.jaw_contact: the image jaw planner's depth rule ("center" | "pad")
    jaw_contact: str = "center"

    def __post_init__(self):
        check_policy(self.policy)
        if self.fidelity not in FIDELITIES:
            raise ExecutionError(f"fidelity {self.fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")
        if self.occupancy not in SEARCH_OCCUPANCIES:
            raise ExecutionError(f"occupancy {self.occupancy!r} unknown; choose one of {', '.join(SEARCH_OCCUPANCIES)}")


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
    segmenter: str = "ground_truth"
    detector: str = "color"
    grasp_successes: int = 0
    objects_present: int = 0  # objects in the heap searched (its budget 2N counts these)
    grasp_plans: int = 0  # object grasp plans (LazyGraspPlanner: only the masks the selector reached)
    grasp_planner: str = ""
    push_policy: str = ""
    grasp_outcome: str = "draw"
    skip_failed: bool = False  # SearchParams.skip_failed
    jaw_contact: str = "center"  # SearchParams.jaw_contact
    grasp_samples: int = 8  # the image planners' candidates per mask
    occupancy_weights: str = ""  # the learned occupancy's weights file ("": the shipped one)
    occupancy: str = "learned"  # SearchParams.occupancy
    error: str = ""
    # per action: the grasp's gripper kind ("parallel_jaw" / "suction"; "" for a push) and
    # whether the action succeeded (Table C.2: jaw vs suction grasps)
    grasp_kinds: list = field(default_factory=list)
    action_successes: list = field(default_factory=list)
    # per action: the grasped object's id ("target" for the target, "" for a push) and the grasp's
    # quality (0 for a push): where the failed grasps of a search went
    grasp_objects: list = field(default_factory=list)
    grasp_qualities: list = field(default_factory=list)
    frames: list = field(default_factory=list, repr=False)

    def record(self) -> dict:
        d = asdict(self)
        d.pop("frames")
        return d


@dataclass
class SearchSystem:
    """A simulated station holding a heap, wired to a bin-search controller."""

    diagram: object
    station: object
    plant: object
    controller: BinSearchController
    target_id: str
    bodies: dict  # object id -> body index
    scenario: object

    def output(self, context, name: str):
        """The controller's output `name` evaluated in the root `context`."""
        return self.controller.GetOutputPort(name).Eval(self.controller.GetMyContextFromRoot(context))


def controller_params(params: SearchParams, num_objects: int) -> BinSearchParams:
    """The controller's settings of a rollout (horizon 2N unless given)."""
    horizon = params.horizon if params.horizon is not None else 2 * num_objects
    return BinSearchParams(policy=params.policy, fidelity=params.fidelity, horizon=horizon, seed=params.seed,
                           grasp_models=tuple(params.grasp_models), grasp_samples=params.grasp_samples,
                           robust_samples=params.robust_samples, grasp_params=params.grasp_params,
                           period=params.period, segmentation=params.segmenter, detector=params.detector,
                           occupancy="analytic" if params.policy == "oracle" or params.occupancy.startswith("analytic")
                           else params.occupancy,
                           occupancy_best_match=IMAGE_BEST_MATCH if params.policy != "oracle"
                           and params.occupancy == "analytic_image_best" else None,
                           occupancy_weights="" if params.policy == "oracle" else params.occupancy_weights,
                           grasp_planner=params.grasp_planner, push_policy=params.push_policy,
                           reach=params.reach, grasp_outcome=params.grasp_outcome,
                           skip_failed=bool(params.skip_failed), jaw_contact=params.jaw_contact)


def build_search(scenario, heap, params: SearchParams, meshcat=None) -> SearchSystem:
    """Station of `scenario` holding `heap` (target drawn red) + the bin-search controller."""
    s = search_scenario(scenario, heap, params.fidelity, params.policy)
    if params.time_step is not None:
        s.plant_config.time_step = float(params.time_step)
    if params.contact_approximation is not None:
        s.plant_config.discrete_contact_approximation = params.contact_approximation
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, meshcat=meshcat, target_index=heap.target_index))
    sim = SimulationInfo.from_station(station, heap.target_index)
    shape = None
    if params.policy == "oracle" or (params.occupancy == "analytic" and (params.policy in OCCUPANCY_POLICIES
                                                                          or meshcat is not None)):
        # Privileged: the target's own mesh at its true initial pose (Ch. 8.3.1 renders the target
        # itself): rotation bin 0 and a grid node are its true placement (see occupancy.TargetMesh).
        shape = (TargetMesh.from_object(heap.target, heap.objects[heap.target_index].matrix())
                 if heap.target_index >= 0 else TargetBox.from_object(heap.target))
    elif params.policy in OCCUPANCY_POLICIES or meshcat is not None:  # (a recorded search shows the occupancy)
        # The learned estimator knows the target's model (its size), never its pose.
        shape = TargetBox.from_object(heap.target)
    controller = builder.AddSystem(MakeBinSearchController(s, controller_params(params, len(heap.objects)),
                                                           sim=sim, target_shape=shape))
    connect_controller(builder, controller, station)
    diagram = builder.Build()
    plant = get_plant(station)
    bodies = {o.model_name: int(o.body_index) for o in station_objects(plant)}
    return SearchSystem(diagram, station, plant, controller, sim.target_id, bodies, s)


def _frame(system: SearchSystem, context, step: int) -> Frame:
    station_ctx = system.station.GetMyContextFromRoot(context)
    rgb = np.array(system.station.GetOutputPort("overhead.rgb_image").Eval(station_ctx).data)[..., :3].copy()
    occ = system.output(context, "occupancy") if system.controller.HasOutputPort("occupancy") else None
    return Frame(step, rgb, system.output(context, "masks"), system.output(context, "target"), occ,
                 system.output(context, "action"))


def _grasp_of(outcome):
    """The grasp of an executed action (None for a push)."""
    return outcome.action.grasp if outcome.action.kind == "grasp" else None


class SearchObserver:
    """A read-only Simulator monitor of a search: at each moment the executor is about to choose
    an action it notes whether the target is seen, the grasps the selector reads (the same cache
    entries the executor's update then uses), and, if asked, the frame of images and choice (the
    demo). It never changes the context. on_idle(system, context, step): called at those moments
    too (e.g. to record the state of each attempt, ms_drake.experiments.fidelity)."""

    def __init__(self, system: SearchSystem, keep_frames: bool = False, on_idle=None):
        self.system, self.keep_frames, self.on_idle = system, keep_frames, on_idle
        self.executor = system.controller.GetSubsystemByName("action_executor")
        self.seen_visible, self.frames, self.grasp_plans = False, [], 0
        self._last_steps, self._step_grasps = -1, None
        self.t_end = None  # when the search ended (its status done)

    def __call__(self, context):
        ctx = self.executor.GetMyContextFromRoot(context)
        if self.t_end is None and self.system.output(context, "status").done:
            self.t_end = float(context.get_time())
        if self.executor.ready_to_act(ctx):
            steps = self.system.output(context, "status").steps
            if steps != self._last_steps:
                self._last_steps = steps
                self.seen_visible |= bool(self.system.output(context, "target").visible)
                # The objects planned for a step are those the selector looked up in its grasps.
                if self._step_grasps is not None:
                    self.grasp_plans += len(self._step_grasps.planned)
                self._step_grasps = self.system.output(context, "grasps")
                if self.keep_frames:
                    self.frames.append(_frame(self.system, context, steps))
                if self.on_idle is not None:
                    self.on_idle(self.system, context, steps)
        return EventStatus.Succeeded()

    def finish(self) -> int:
        """The number of object grasp plans made (call once, after the simulation)."""
        if self._step_grasps is not None:
            self.grasp_plans += len(self._step_grasps.planned)
            self._step_grasps = None
        return self.grasp_plans


def run_search(system: SearchSystem, heap, params: SearchParams, max_sim_time: float | None = None,
               keep_frames: bool = False, meshcat=None, on_idle=None, after: float = 0.0) -> RolloutResult:
    """Simulate the search diagram until it ends itself (the executor's termination event) or
    `max_sim_time` passes; returns the rollout's result (with frames if asked). Nothing here changes
    the plant after the initial conditions: removals, the end and blow-ups happen inside the diagram.
    on_idle(system, context, step): see SearchObserver. after: simulate on so many seconds once the
    search has ended (a recording then shows the last object carried away; the record is the same)."""
    n = len(heap.objects)
    horizon = params.horizon if params.horizon is not None else 2 * n
    max_sim_time = max_sim_time or 30.0 + 12.0 * horizon
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    simulator = Simulator(system.diagram)
    ApplySimulatorConfig(system.scenario.simulator_config, simulator)  # the scenario's integrator and rates
    context = simulator.get_mutable_context()
    set_initial_conditions(system.diagram, context, heap)
    observer = SearchObserver(system, keep_frames=keep_frames, on_idle=on_idle)
    simulator.set_monitor(observer)
    failure, msg = "", ""
    if meshcat is not None:
        meshcat.StartRecording(set_visualizations_while_recording=False)
    try:
        simulator.Initialize()
        simulator.AdvanceTo(max_sim_time)
        if after > 0:
            simulator.AdvanceTo(context.get_time() + after)
            if keep_frames and observer.frames and observer.frames[-1].action.kind == "stop":
                # the last frame shows the scene the search left behind (the last object carried away)
                observer.frames[-1] = _frame(system, context, observer.frames[-1].step)
    except RuntimeError as e:  # Drake solver failures and the executor's non-finite check
        failure = "sim_blew_up"
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
    finally:
        if meshcat is not None:
            meshcat.StopRecording()
            meshcat.PublishRecording()
    grasp_plans = observer.finish()
    t_end = observer.t_end if observer.t_end is not None else float(context.get_time())
    status = system.output(context, "status")
    history = system.output(context, "history")
    if not failure and not status.done:
        failure = "timeout"
    reason = status.stop_reason if status.done else failure
    success = reason == "success"
    if not failure and not success:
        if reason == "no_action":
            masks = system.output(context, "masks")
            failure = ("empty_segmentation" if len(masks) == 0 else
                       "target_never_visible" if not observer.seen_visible else "grasps_below_threshold")
        else:
            failure = reason or "unknown"
    kinds = [o.action.kind for o in history]
    res = RolloutResult(seed=heap.seed, policy=params.policy, fidelity=params.fidelity, objects=n, objects_present=n,
                        success=success,
                        actions=len(history), action_kinds=kinds, failure=failure, stop_reason=reason,
                        seconds=time.perf_counter() - t_wall, cpu_seconds=time.process_time() - t_cpu,
                        sim_seconds=t_end,
                        target=heap.target, segmenter=params.segmenter, detector=params.detector,
                        grasp_successes=sum(1 for o in history if o.action.kind == "grasp" and o.success),
                        grasp_plans=grasp_plans, grasp_planner=system.controller.params.grasp_planner,
                        push_policy=params.push_policy, grasp_outcome=params.grasp_outcome,
                        skip_failed=bool(params.skip_failed), jaw_contact=params.jaw_contact,
                        grasp_samples=int(params.grasp_samples), occupancy_weights=params.occupancy_weights,
                        occupancy=params.occupancy,
                        grasp_kinds=[o.action.grasp.kind if o.action.kind == "grasp" and o.action.grasp is not None
                                     else "" for o in history],
                        action_successes=[bool(o.success) for o in history],
                        grasp_objects=[("target" if g.object_id == system.target_id else g.object_id)
                                       if (g := _grasp_of(o)) is not None else "" for o in history],
                        grasp_qualities=[round(float(g.quality), 4) if (g := _grasp_of(o)) is not None else 0.0
                                         for o in history],
                        error=msg, frames=observer.frames)
    return res


def primitive_time_step(policy: str) -> float:
    """The primitive mode's plant step for selector `policy` [s]: PRIMITIVE_PUSH_TIME_STEP for the
    pushing selectors (their push agrees with the YuMi's there, the push study's), 10 ms else."""
    check_policy(policy)
    return PRIMITIVE_PUSH_TIME_STEP if policy in PUSHING else 0.01


def rollout(policy: str, objects: int, seed: int, fidelity: str = "primitive", horizon: int | None = None,
            heap=None, keep_frames: bool = False, meshcat=None, scenario_name: str | None = None,
            scenario_file: str | None = None, **kw) -> RolloutResult:
    """Generate heap `seed` (N objects, BinHeap15's bin) and search it with `policy` on the station
    of `scenario_name` in `scenario_file` (defaults: FloatingGripperBin for primitive, YuMiBin for
    full fidelity, in diagrams/scenarios.yaml); full fidelity uses the scenario's robot."""
    kw.setdefault("time_step", primitive_time_step(policy) if fidelity == "primitive" else None)
    params = SearchParams(policy=policy, fidelity=fidelity, horizon=horizon, seed=seed, **kw)
    if heap is None:
        heap = generate_heap(load_scenario(None, "BinHeap15"), objects, seed, params=SEARCH_HEAPS)
    name = scenario_name or SCENARIOS[fidelity]
    scenario = load_scenario(scenario_file, name)
    check_search_scenario(scenario, fidelity, name)
    system = build_search(scenario, heap, params, meshcat=meshcat)
    res = run_search(system, heap, params, keep_frames=keep_frames, meshcat=meshcat)
    res.objects = int(objects)  # the N asked for: what the benchmark's files are keyed by
    return res


class RolloutError(MsDrakeError, ValueError):
    """A rollout was asked for with impossible settings."""
