"""One mechanical-search rollout in the bin: a simulated station holding a heap wired to the
bin-search controller of ms_drake.policies.bin_search (MakeBinSearchController, ground-truth
segmentation and exact grasp meshes through SimulationInfo), simulated by Drake's Simulator.

Only the fidelity's backend and station differ: primitive = FloatingGripperBin + PrimitiveBackend,
full = the scenario's robot (YuMiBin by default, BinSearchConfig.scenario) + FullBackend.

A rollout builds the diagram, sets its initial conditions (`set_initial_conditions`), runs
`Simulator.AdvanceTo(max_sim_time)` and reads the record from the controller's ports: the diagram
itself removes lifted objects (the robot, or the primitive mode's ObjectCarrier, drops them into a
drop-off tray), ends the simulation when the search is over and fails it on a blow-up. A read-only
monitor (SearchObserver) notes what the record needs besides the ports. Failure modes
(RolloutResult.failure): "" on success, else one of FAILURE_MODES.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus

from ms_drake.errors import MsDrakeError
from ms_drake.perception.occupancy import TargetBox, TargetMesh
from ms_drake.policies.bin_search import (
    BinSearchConfig,
    BinSearchController,
    MakeBinSearchController,
    SimulationInfo,
    config_scenario,
    connect_controller,
    search_scenario,
    set_initial_conditions,
)
from ms_drake.policies.bin_selectors import OCCUPANCY_POLICIES
from ms_drake.scenes.layouts import layout_heap
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
    # the whole BinSearchConfig of the search, without its seed (the record's seed)
    config: dict = field(default_factory=dict)
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


def build_search(scenario, heap, config: BinSearchConfig, meshcat=None) -> SearchSystem:
    """Station of `scenario` holding `heap` (target drawn red) + the bin-search controller."""
    s = search_scenario(scenario, heap, config)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, meshcat=meshcat, target_index=heap.target_index))
    sim = SimulationInfo.from_station(station, heap.target_index)
    shape = None
    if config.policy == "oracle" or (config.ablation.occupancy == "analytic" and (config.policy in OCCUPANCY_POLICIES
                                                                                  or meshcat is not None)):
        # Privileged: the target's own mesh at its true initial pose (Ch. 8.3.1 renders the target
        # itself): rotation bin 0 and a grid node are its true placement (see occupancy.TargetMesh).
        shape = (TargetMesh.from_object(heap.target, heap.objects[heap.target_index].matrix())
                 if heap.target_index >= 0 else TargetBox.from_object(heap.target))
    elif config.policy in OCCUPANCY_POLICIES or meshcat is not None:  # (a recorded search shows the occupancy)
        # The learned estimator knows the target's model (its size), never its pose.
        shape = TargetBox.from_object(heap.target)
    controller = builder.AddSystem(MakeBinSearchController(s, config, sim=sim, target_shape=shape))
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
                    self.grasp_plans += len(getattr(self._step_grasps, "planned", ()))
                self._step_grasps = self.system.output(context, "grasps")
                if self.keep_frames:
                    self.frames.append(_frame(self.system, context, steps))
                if self.on_idle is not None:
                    self.on_idle(self.system, context, steps)
        return EventStatus.Succeeded()

    def finish(self) -> int:
        """The number of object grasp plans made (call once, after the simulation)."""
        if self._step_grasps is not None:
            self.grasp_plans += len(getattr(self._step_grasps, "planned", ()))
            self._step_grasps = None
        return self.grasp_plans


def run_search(system: SearchSystem, heap, config: BinSearchConfig, max_sim_time: float | None = None,
               keep_frames: bool = False, meshcat=None, on_idle=None, after: float = 0.0) -> RolloutResult:
    """Simulate the search diagram until it ends itself (the executor's termination event) or
    `max_sim_time` passes; returns the rollout's result (with frames if asked). Nothing here changes
    the plant after the initial conditions: removals, the end and blow-ups happen inside the diagram.
    on_idle(system, context, step): see SearchObserver. after: simulate on so many seconds once the
    search has ended (a recording then shows the last object carried away; the record is the same)."""
    n = len(heap.objects)
    max_sim_time = max_sim_time or 30.0 + 12.0 * config.horizon
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
    res = RolloutResult(seed=heap.seed, policy=config.policy, fidelity=config.fidelity, objects=n, objects_present=n,
                        success=success,
                        actions=len(history), action_kinds=kinds, failure=failure, stop_reason=reason,
                        seconds=time.perf_counter() - t_wall, cpu_seconds=time.process_time() - t_cpu,
                        sim_seconds=t_end, target=heap.target,
                        grasp_successes=sum(1 for o in history if o.action.kind == "grasp" and o.success),
                        grasp_plans=grasp_plans, config=record_config(config),
                        grasp_kinds=[o.action.grasp.kind if o.action.kind == "grasp" and o.action.grasp is not None
                                     else "" for o in history],
                        action_successes=[bool(o.success) for o in history],
                        grasp_objects=[("target" if g.object_id == system.target_id else g.object_id)
                                       if (g := _grasp_of(o)) is not None else "" for o in history],
                        grasp_qualities=[round(float(g.quality), 4) if (g := _grasp_of(o)) is not None else 0.0
                                         for o in history],
                        error=msg, frames=observer.frames)
    return res


def record_config(config: BinSearchConfig) -> dict:
    """What a record keeps of its search's config: all of it but the seed (the record's own)."""
    d = config.to_dict()
    d.pop("seed")
    return d


def rollout(config: BinSearchConfig, seed: int, heap=None, keep_frames: bool = False, meshcat=None) -> RolloutResult:
    """Search heap `seed` of config.heap (or the given `heap`) with the controller of `config`
    seeded by `seed`, on the station config.scenario names (scenario.layouts; policies.bin_search:
    config_scenario)."""
    config = dataclasses.replace(config, seed=int(seed))
    if heap is None:
        heap = layout_heap(config.heap, seed)
    system = build_search(config_scenario(config), heap, config, meshcat=meshcat)
    res = run_search(system, heap, config, keep_frames=keep_frames, meshcat=meshcat)
    res.objects = int(config.heap.objects)  # the N asked for: what the benchmark's files are keyed by
    return res


class RolloutError(MsDrakeError, ValueError):
    """A rollout was asked for with impossible settings."""
