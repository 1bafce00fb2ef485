"""The shelf mechanical-search controller (Ch. 9) as one Drake Diagram, wired to the FetchShelf
station in three lines:

    station = builder.AddSystem(MakeStation(scenario, extra_objects=...))   # a shelf scene's objects
    controller = builder.AddSystem(MakeShelfSearchController(scenario, ShelfSearchConfig(perception="depth")))
    connect_controller(builder, controller, station)

In simulation, start the robot where the controller expects it (parked out of the camera's view):
`set_arm_positions(plant, plant_context, "fetch", controller.initial_commands())`.

Two perceptions (`ShelfSearchConfig.perception`):

"depth" (the hardware station's ports only: front.depth_image, front.rgb_image in):
  depth + rgb -> ShelfSegmenter -> scene (the estimated occluders, ids seg_<k>; the target's
            colour left out)
  depth -> ShelfOccupancyEstimator("learned") -> occupancy
"ground_truth" (simulation only: body_poses in, and `sim=ShelfSimulationInfo(bodies, target_id)`):
  body_poses -> ShelfSceneObserver (the objects' true footprints, the target as scene.target) -> scene
  scene -> ShelfOccupancyEstimator("ground_truth") -> occupancy
Then, in both:
  scene + occupancy + history -> FetchFeasibleSelector(policy) -> action (the policy's best action
            the Fetch reaches in that scene: ShelfBackend.feasible, the plan the executor would
            make from park, IK within the joint limits, then its whole path clear of the other
            occluders, the shelf and the robot itself; with params.ablation.foss_choice: the policy's
            best in FOSS, ShelfSearchSelector); the action carries the scene it was chosen in
            (Action.scene)
  action -> ActionExecutor(ShelfBackend) -> fetch.position, fetch_bluction.position (blade angle),
            fetch_bluction.suction; history -> selector. With perception "depth" the backend has
            no shelf bodies and plans each action in its Action.scene; its outcomes are
            "executed" (agree=nan), and the selector reads them through the next image: an
            action after which the camera sees the same scene failed (`seen_outcomes`), so the
            policy does not repeat it, nor one like it (`refuse_like_unchanged`), while nothing
            changes.
  front.rgb_image + front.depth_image -> ImagesReady -> executor.ready (idle until images arrive)

The policies see only occluders either way (ms_drake.policies.shelf drops the target). The exported
ports are the station's names (connect_controller), so the "depth" controller connects unchanged to
MakeStation(scenario, hardware=True); the "ground_truth" one needs the simulated station's
body_poses, and raises ControllerError when built without `sim`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem

from ms_drake.execution import ActionExecutor
from ms_drake.execution.shelf_backend import ShelfBackend, ShelfBody, observe
from ms_drake.foss import SUCTION_LIFTS, Foss
from ms_drake.perception.ready import ImagesReady
from ms_drake.perception.shelf_occupancy import ShelfOccupancyEstimator
from ms_drake.perception.shelf_segmentation import (
    ShelfSegmentationParams,
    ShelfSegmenter,
)
from ms_drake.policies.bin_search import ControllerError, connect_controller  # noqa: F401 (re-exported)
from ms_drake.config_files import config_dict
from ms_drake.policies.shelf import (
    ShelfPolicyParams,
    ShelfPolicySelector,
    check_shelf_policy,
    footprint_change,
    like_key,
    oracle_last_stage_seconds,
    segment,
)
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.types import Action, ActionOutcome, ShelfScene


#: What the controller observes: "ground_truth" (simulation only: the bodies' poses), "learned" (in FOSS
#: only: the learned occupancy of a depth render, FOSS's objects) or "depth" (the camera images only).
SHELF_PERCEPTIONS = ("ground_truth", "learned", "depth")


@dataclass
class ShelfSearchAblation:
    """Switches that reproduce settings other than the search's; each default is the search's.

    - foss_choice: the policy's best action in FOSS, with no check on the Fetch's planner
      (ShelfSearchSelector instead of FetchFeasibleSelector); on the Fetch only.
    - suction_lift: FOSS's suction lift, "over" (the object is lifted over what its sweeps to and
      from the front cross) or "floor" (2 cm only: those sweeps must be clear, FOSS as a 2D overhead
      simulator); in FOSS only.
    - oracle_push_target: the oracles (oracle_p, oracle_ps) also push the target itself."""

    foss_choice: bool = False
    suction_lift: str = "over"
    oracle_push_target: bool = False

    def __post_init__(self):
        if self.suction_lift not in SUCTION_LIFTS:
            raise ControllerError(f"ablation.suction_lift {self.suction_lift!r}: choose one of "
                                  f"{', '.join(SUCTION_LIFTS)}")


@dataclass
class ShelfSearchConfig:
    """One shelf search's settings, in FOSS (`bench shelf`) and on the Fetch (`bench shelf-physics`,
    MakeShelfSearchController); a Drake YAML file (ms_drake.config_files.load_config).

    - policy: one of ms_drake.policies.shelf.SHELF_POLICIES.
    - perception: one of SHELF_PERCEPTIONS ("learned" in FOSS only).
    - horizon: the action budget H (None: 2n, n the occluders).
    - seed: every random choice (the random policy); set per scene by the benches.
    - psi: the suction / push cost ratio.
    - oracle_seconds: the CPU budget [s] of the oracles' last stage after their staged search finds
      nothing (Oracle-P's exhaustive push search, Oracle-P+S's wide search; None: the policy's
      default, 0: off).
    - camera: the shelf camera. period: the executor's and selector's update period [s].
    - speed / push_speed / slow_speed: the tool's Cartesian speed limits [m/s] (ShelfBackend).
    - max_candidates: FetchFeasibleSelector checks at most this many of the policy's actions, in
      the policy's order, for the best one the Fetch can execute, its planned path clear of the scene.
    - min_move / nil_move / revisit [m] (Bluction-DAR on the Fetch, NIL_RULE_POLICIES; FOSS places
      exactly and runs without them): the policy drops the candidates that FOSS moves their object
      less than min_move and, with ground-truth perception, those like an executed action that moved
      its object less than nil_move while the object is unchanged (ms_drake.policies.shelf.nil_effect;
      perception "depth" judges by the image instead, `refuse_like_unchanged`) and, with
      ground-truth perception too, those FOSS predicts to lead back to a scene observed in the
      search, every object's centre within `revisit` (ms_drake.policies.shelf.returns).
    - ablation: ShelfSearchAblation."""

    policy: str = "bluction_dar"
    perception: str = "ground_truth"
    horizon: int | None = None
    seed: int = 0
    psi: float = 1.3
    oracle_seconds: float | None = None
    camera: str = "front"
    period: float = 0.05
    speed: float = 0.35
    push_speed: float = 0.12
    slow_speed: float = 0.15
    max_candidates: int = 1000
    min_move: float = 0.01
    nil_move: float = 0.01
    revisit: float = 0.01
    ablation: ShelfSearchAblation = dataclasses.field(default_factory=ShelfSearchAblation)

    def __post_init__(self):
        if isinstance(self.ablation, dict):
            self.ablation = ShelfSearchAblation(**self.ablation)
        check_shelf_policy(self.policy)
        if self.perception not in SHELF_PERCEPTIONS:
            raise ControllerError(f"perception {self.perception!r}: choose one of {', '.join(SHELF_PERCEPTIONS)}")
        if int(self.max_candidates) < 1:
            raise ControllerError(f"max_candidates must be >= 1, got {self.max_candidates!r}")
        if not (self.min_move >= 0 and self.nil_move >= 0 and self.revisit >= 0):
            raise ControllerError(f"min_move, nil_move and revisit are distances in m (>= 0; 0: off), got min_move="
                                  f"{self.min_move!r}, nil_move={self.nil_move!r}, revisit={self.revisit!r}")
        if self.horizon is not None and int(self.horizon) < 1:
            raise ControllerError(f"horizon must be >= 1 action (or None for 2n), got {self.horizon!r}")
        if not self.period > 0:
            raise ControllerError(f"period must be > 0 s, got {self.period!r}")
        oracle = self.policy in ("oracle_p", "oracle_ps")
        if self.oracle_seconds is not None and (self.oracle_seconds < 0 or (self.oracle_seconds > 0 and not oracle)):
            raise ControllerError(f"oracle_seconds {self.oracle_seconds:g}: a CPU budget >= 0 s, and only for the "
                                  f"oracles oracle_p and oracle_ps (policy is {self.policy})")
        if self.ablation.oracle_push_target and not oracle:
            raise ControllerError(f"ablation.oracle_push_target: only for the oracles oracle_p and oracle_ps (policy "
                                  f"is {self.policy}); the other policies do not know where the target is")

    @property
    def oracle_budget(self) -> float:
        """oracle_seconds resolved: the policy's default when None, 0 for the non-oracles."""
        return oracle_last_stage_seconds(self.policy) if self.oracle_seconds is None else float(self.oracle_seconds)

    def record(self) -> dict:
        """The config as a record keeps it: all but the seed, the oracle's budget resolved."""
        return config_dict(dataclasses.replace(self, oracle_seconds=self.oracle_budget))


@dataclass(frozen=True)
class ShelfSimulationInfo:
    """What only a simulated shelf station tells the controller: {object id: ShelfBody} (plant body
    index and dimensions of every shelf object, the target included) and the target's id."""

    bodies: dict
    target_id: str = ""

    def __post_init__(self):
        if self.target_id and self.target_id not in self.bodies:
            raise ControllerError(f"ShelfSimulationInfo: target_id {self.target_id!r} is not one of the bodies "
                                  f"({', '.join(self.bodies) or 'none'})")
        for k, b in self.bodies.items():
            if not isinstance(b, ShelfBody):
                raise ControllerError(f"ShelfSimulationInfo.bodies[{k!r}] is a {type(b).__name__}; give a ShelfBody "
                                      "(body index and ShelfObject)")


class ShelfSceneObserver(LeafSystem):
    """Simulation ground truth as a shelf observation. Input ``body_poses`` (the plant's); output
    ``scene`` (ShelfScene of the shelf objects at their poses, the target as scene.target)."""

    def __init__(self, sim: ShelfSimulationInfo, origin):
        super().__init__()
        self.poses_port = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self.DeclareAbstractOutputPort("scene", lambda: AbstractValue.Make(ShelfScene(())), self._calc)
        self.sim = sim
        self.origin = tuple(float(v) for v in origin)

    def _calc(self, context, output):
        if not self.poses_port.HasValue(context):
            raise ControllerError("ShelfSceneObserver: connect body_poses (the station's body_poses output)")
        scene, _ = observe(self.poses_port.Eval(context), self.sim.bodies, self.origin, self.sim.target_id)
        output.set_value(scene)


def same_scene(a: ShelfScene, b: ShelfScene, tolerance: float = 0.01) -> bool:
    """Whether two observed scenes show the same objects: as many, in x order, each of the same
    kind with centre and size within `tolerance` [m]."""
    if len(a.objects) != len(b.objects):
        return False
    key = lambda o: o.x
    for p, q in zip(sorted(a.objects, key=key), sorted(b.objects, key=key)):
        if p.kind != q.kind or footprint_change(p, q) > tolerance:
            return False
    return True


def seen_outcomes(history, scene: ShelfScene, tolerance: float = 0.01) -> tuple:
    """The history as the camera saw it (perception "depth": the backend cannot tell whether an
    action moved anything): an executed shelf action after which the observed scene (the next
    action's Action.scene, or `scene` after the last one) is the same (`same_scene`) changed
    nothing, and its outcome becomes unsuccessful ("no_change_seen"), so the policy's rule drops it
    until something changes, as it drops a refused action."""
    out = list(history)
    for i, o in enumerate(out):
        if not o.success or o.action.scene is None:
            continue
        after = next((h.action.scene for h in out[i + 1:] if h.action.scene is not None), scene)
        if same_scene(o.action.scene, after, tolerance):
            out[i] = dataclasses.replace(o, success=False, message=f"no_change_seen {o.message}")
    return tuple(out)


_unchanged_key = like_key


def refuse_like_unchanged(foss: Foss, scene: ShelfScene, history) -> list:
    """Refused outcomes ("no_change_seen:like") for every FOSS candidate action in `scene` like
    (`_unchanged_key`) one that changed nothing since the scene last changed (seen_outcomes), to add
    to the history the policy reads: the camera's estimate of an unchanged scene jitters by
    millimetres, so the same failed grasp comes back with a slightly different placement."""
    like = set()
    for o in reversed(tuple(history)):
        if o.success:
            break
        if o.message.startswith("no_change_seen") and o.action.shelf is not None:
            like.add(_unchanged_key(o.action.shelf))
    if not like:
        return []
    candidates = foss.actions(segment(foss.geometry, scene).known, suction=True)
    return [ActionOutcome(Action("shelf", shelf=a), False, message="no_change_seen:like")
            for a in candidates if _unchanged_key(a) in like]


def _search_inputs(selector: ShelfPolicySelector, context) -> tuple:
    """(scene, history, distribution) that FetchFeasibleSelector and ShelfSearchSelector choose from:
    their scene and history inputs (the history read through `seen_outcomes` and
    `refuse_like_unchanged` when the selector judges by scene) and P'_n (None for the oracle)."""
    if not selector.scene_port.HasValue(context):
        raise ControllerError(f"{type(selector).__name__}({selector.policy!r}): connect the scene input")
    scene = selector.scene_port.Eval(context)
    history = tuple(selector.history_port.Eval(context)) if selector.history_port.HasValue(context) else ()
    if selector.judge_by_scene:
        history = seen_outcomes(history, scene)
        history = history + tuple(refuse_like_unchanged(selector.rules.foss, scene, history))
    dist = None if selector.rules.policy.startswith("oracle") else selector._current(context).image_x
    return scene, history, dist


class FetchFeasibleSelector(ShelfPolicySelector):
    """The ShelfPolicySelector (per action) whose action is the policy's best one that the Fetch can
    execute: the reference's "first kinematically feasible action" (Ch. 9.4.3) checked with the
    robot's planner instead of FOSS alone (ShelfBackend.feasible: the executor's plan from the park
    pose, IK + Cartesian lines within the joint limits, and that plan's path sampled every 20 ms
    clear of the other occluders, the shelf and the robot itself; cached per scene to 1 mm). The policy ranks as it does in FOSS; its choice is planned; an
    infeasible choice is added to the history as refused (so the policy's own rule drops it) and
    the policy chooses again, at most `max_candidates` times (then "stop"). The action's reason
    ends with the number of candidates skipped; a shelf action carries `scene` (Action.scene), in
    which the backend plans it. judge_by_scene: read the history through `seen_outcomes` (an
    action after which the camera sees the same scene failed; perception "depth") and refuse the
    actions like one that changed nothing until the scene changes (`refuse_like_unchanged`). Same
    ports as ShelfPolicySelector."""

    def __init__(self, policy: str, foss: Foss, backend: ShelfBackend, params: ShelfPolicyParams | None = None,
                 period: float = 1.0, max_candidates: int = 1000, judge_by_scene: bool = False):
        super().__init__(policy, foss, params, period=period, per_action=True)
        self.judge_by_scene = bool(judge_by_scene)
        if int(max_candidates) < 1:
            raise ControllerError(f"FetchFeasibleSelector: max_candidates must be >= 1, got {max_candidates!r}")
        self.backend = backend
        self.max_candidates = int(max_candidates)
        self._memo: tuple | None = None

    def choose(self, scene: ShelfScene, dist, history=()) -> Action:
        """The policy's best Fetch-feasible action for `scene` (class docstring)."""
        tried = list(history)
        for skipped in range(self.max_candidates):
            action = self.rules.select(scene, dist, tried)
            if action.kind != "shelf" or self.backend.feasible(action.shelf, scene) == "ok":
                return dataclasses.replace(action, reason=f"{action.reason} ({skipped} Fetch-infeasible skipped)",
                                           scene=scene if action.kind == "shelf" else None)
            status = self.backend.feasible(action.shelf, scene)
            tried.append(ActionOutcome(action, False, message=f"fetch_infeasible:{status}"))
        return Action("stop", reason=f"{self.policy}: none of the {self.max_candidates} best actions is feasible "
                                     "on the Fetch")

    def _calc_action(self, context, output):
        scene, history, dist = _search_inputs(self, context)
        key = (tuple((b.id, round(b.x, 4), round(b.y, 4)) for b in scene.objects), len(history),
               None if dist is None else np.asarray(dist).tobytes())
        if self._memo is None or self._memo[0] != key:
            self._memo = (key, self.choose(scene, dist, history))
        output.set_value(self._memo[1])

    def _update(self, context, state):
        # P'_n changes only when the history has grown: skip the occupancy otherwise.
        if context.get_abstract_state(self._count).get_value() == self._steps(context):
            return
        super()._update(context, state)


class ShelfSearchSelector(ShelfPolicySelector):
    """The ShelfPolicySelector (per action) whose shelf action carries the scene it was chosen in
    (Action.scene), which the backend plans it in; judge_by_scene as FetchFeasibleSelector's.
    Same ports as ShelfPolicySelector."""

    def __init__(self, policy: str, foss: Foss, params: ShelfPolicyParams | None = None, period: float = 1.0,
                 judge_by_scene: bool = False):
        super().__init__(policy, foss, params, period=period, per_action=True)
        self.judge_by_scene = bool(judge_by_scene)

    def _calc_action(self, context, output):
        scene, history, dist = _search_inputs(self, context)
        action = self.rules.select(scene, dist, history)
        output.set_value(dataclasses.replace(action, scene=scene) if action.kind == "shelf" else action)


CONTROLLER_PERCEPTIONS = ("ground_truth", "depth")  # what the controller on a station observes
NIL_RULE_POLICIES = ("bluction_dar",)  # the policies ShelfSearchConfig.min_move / nil_move / revisit apply to


def MakeShelfSearchController(scenario, params: ShelfSearchConfig | None = None,
                              sim: ShelfSimulationInfo | None = None, target_size=None,
                              name: str = "shelf_search_controller",
                              segmentation: ShelfSegmentationParams | None = None,
                              weights=None) -> ShelfSearchController:
    """The controller Diagram of a shelf search on `scenario`'s station (FetchShelf; module docstring).
    params.perception: "ground_truth" (needs `sim`) or "depth" (the station's camera ports only;
    `sim` must be None); target_size: the target's (w, d, h) [m] for the occupancy (None: the
    observed target's, or the learned estimator's default); segmentation: the ShelfSegmenter's
    parameters and weights the learned occupancy's file (perception "depth"; None: the defaults)."""
    params = params or ShelfSearchConfig()
    perception = params.perception
    if perception not in CONTROLLER_PERCEPTIONS:
        raise ControllerError(f"perception {perception!r}: the controller on a station observes "
                              f"{' or '.join(CONTROLLER_PERCEPTIONS)} (\"learned\" is FOSS's, `bench shelf`)")
    depth = perception == "depth"
    if depth and sim is not None:
        raise ControllerError("perception 'depth' reads only the station's camera ports (as on hardware): build it "
                              "without sim= (ShelfSimulationInfo is for perception 'ground_truth')")
    if not depth and sim is None:
        raise ControllerError("perception 'ground_truth' observes the scene through the simulation's ground truth: "
                              "pass sim=ShelfSimulationInfo(bodies, target_id), or set ShelfSearchConfig("
                              "perception='depth') (the camera images only, e.g. for the hardware station)")
    if params.camera not in scenario.cameras:
        raise ControllerError(f"camera {params.camera!r} is not a camera of the scenario "
                              f"(cameras: {', '.join(scenario.cameras) or 'none'})")
    geometry = ShelfGeometry.from_scenario(scenario, params.camera)
    foss = Foss(geometry)
    bodies, target_id = ({}, "") if depth else (sim.bodies, sim.target_id)
    backend = ShelfBackend(scenario, bodies, target_id, foss=foss, seed=params.seed, speed=params.speed,
                           push_speed=params.push_speed, slow_speed=params.slow_speed)
    cam = scenario.cameras[params.camera]
    builder = DiagramBuilder()
    ready = builder.AddNamedSystem("images_ready", ImagesReady(cam.width, cam.height))
    rgb_name, depth_name = f"{params.camera}.rgb_image", f"{params.camera}.depth_image"
    builder.ExportInput(ready.GetInputPort("rgb_image"), rgb_name)
    builder.ExportInput(ready.GetInputPort("depth_image"), depth_name)
    if depth:
        segmenter = builder.AddNamedSystem("shelf_segmenter", ShelfSegmenter(geometry, segmentation))
        occupancy = builder.AddNamedSystem("occupancy_estimator",
                                           ShelfOccupancyEstimator(geometry, target_size, "learned", weights=weights))
        builder.ConnectInput(depth_name, segmenter.GetInputPort("depth_image"))
        builder.ConnectInput(rgb_name, segmenter.GetInputPort("rgb_image"))
        builder.ConnectInput(depth_name, occupancy.GetInputPort("depth_image"))
        scene = segmenter.GetOutputPort("scene")
    else:
        observer = builder.AddNamedSystem("scene_observer", ShelfSceneObserver(sim, scenario.environment.position))
        occupancy = builder.AddNamedSystem("occupancy_estimator", ShelfOccupancyEstimator(geometry, target_size))
        scene = observer.GetOutputPort("scene")
        builder.Connect(scene, occupancy.GetInputPort("scene"))
    # The nil-action rules are Bluction-DAR's on the Fetch (DER-3 and the others keep their rules as measured).
    nil_rules = params.policy in NIL_RULE_POLICIES
    policy_params = ShelfPolicyParams(psi=params.psi, seed=params.seed, horizon=params.horizon,
                                      min_move=params.min_move if nil_rules else 0.0,
                                      nil_move=params.nil_move if nil_rules and not depth else 0.0,
                                      revisit=params.revisit if nil_rules and not depth else 0.0,
                                      oracle_exhaustive_seconds=params.oracle_seconds,
                                      oracle_push_target=params.ablation.oracle_push_target)
    if not params.ablation.foss_choice:
        selector = FetchFeasibleSelector(params.policy, foss, backend, policy_params, period=params.period,
                                         max_candidates=params.max_candidates, judge_by_scene=depth)
    else:
        selector = ShelfSearchSelector(params.policy, foss, policy_params, period=params.period, judge_by_scene=depth)
    builder.AddNamedSystem("policy_selector", selector)
    executor = builder.AddNamedSystem("action_executor", ActionExecutor(backend, period=params.period))
    builder.Connect(scene, selector.GetInputPort("scene"))
    builder.Connect(occupancy.GetOutputPort("occupancy"), selector.GetInputPort("occupancy"))
    builder.Connect(selector.GetOutputPort("action"), executor.action_port)
    builder.Connect(executor.history_port, selector.GetInputPort("history"))
    builder.Connect(ready.GetOutputPort("ready"), executor.ready_port)
    if not depth:
        builder.ExportInput(observer.poses_port, "body_poses")
        builder.ConnectInput("body_poses", executor.poses_port)
    for port_name, port in executor.command_ports.items():
        builder.ExportOutput(port, port_name)
    for port_name in ("history", "outcome", "removed", "status"):
        builder.ExportOutput(executor.GetOutputPort(port_name), port_name)
    builder.ExportOutput(selector.GetOutputPort("action"), "action")
    builder.ExportOutput(selector.GetOutputPort("occupancy_history"), "occupancy_history")
    builder.ExportOutput(occupancy.GetOutputPort("occupancy"), "occupancy")
    builder.ExportOutput(scene, "scene")
    if depth:
        builder.ExportOutput(segmenter.GetOutputPort("masks"), "masks")
        builder.ExportOutput(segmenter.GetOutputPort("target_mask"), "target_mask")
    controller = ShelfSearchController(builder, backend, params, target_id, perception)
    controller.set_name(name)
    return controller


class ShelfSearchController(Diagram):
    """The Diagram MakeShelfSearchController builds; `initial_commands()`: the station commands it
    starts from (the Fetch parked out of the camera's view, blade up, vacuum off); `backend`: its
    ShelfBackend; `perception`: "ground_truth" or "depth"."""

    def __init__(self, builder: DiagramBuilder, backend, params: ShelfSearchConfig, target_id: str,
                 perception: str = "ground_truth"):
        super().__init__()
        builder.BuildInto(self)
        self.backend, self.params, self.target_id, self.perception = backend, params, target_id, perception

    def initial_commands(self) -> dict:
        return self.backend.initial_commands()
