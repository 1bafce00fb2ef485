"""The bin mechanical-search controller as one Drake Diagram, wired to a station in three lines:

    station = builder.AddSystem(MakeStation(scenario))                  # or MakeStation(scenario, hardware=True)
    controller = builder.AddSystem(MakeBinSearchController(scenario, params, sim=SimulationInfo.from_station(station)))
    connect_controller(builder, controller, station)

In simulation, start the robot where the controller expects it (parked out of the camera's view):
`station.robots.set_arm_positions(plant, plant_context, robot, controller.initial_commands())`.

Inside (DESIGN.md "Data flow"; every planner is a system of the diagram):
  <cam>.label_image -> Segmenter("ground_truth")   (simulation)  |  <cam>.depth_image -> Segmenter(params.segmentation)
    (simulation with a depth segmenter: -> MaskAssociation(<cam>.label_image), the masks named
    after the objects behind them so the simulated executor knows what a grasp lifted)
  <cam>.rgb_image + masks -> TargetDetector(params.detector) -> target
  <cam>.depth_image + target -> OccupancyEstimator(params.occupancy) -> occupancy (given target_shape; xray reads it)
  depth + masks (+ body_poses: exact meshes in simulation) -> LazyGraspPlanner -> grasps
    (simulation, params.grasp_planner "indexed": IndexedGraspPlanner on the objects' grasp sets,
    the LazyGraspPlanner for objects without one)
  depth + masks -> PushPlanner -> pushes                                          (*_push selectors)
  body_poses -> AmodalMasks -> TargetAmodalMask -> target_amodal                 (oracle, simulation)
  -> PolicySelector(policy) -> action -> ActionExecutor(backend) -> station commands; history -> selector
  <cam>.rgb_image + <cam>.depth_image -> ImagesReady -> ActionExecutor.ready (idle until images arrive)

Exported ports, named as the station's so `connect_controller` wires them by name:
  inputs   <cam>.rgb_image, <cam>.depth_image; with `sim`: <cam>.label_image (ground-truth
           segmentation) and body_poses (exact grasp meshes, outcome checks, the oracle)
  outputs  every station command the backend drives (<arm>.position, <gripper>.position,
           <gripper>.force_limit, <gripper>.suction), and action, history, outcome, removed,
           status, masks, target, grasps (+ occupancy, pushes when built)

Backends: fidelity "primitive" (the floating gripper's evaluated grasp primitive; simulation
only) or "full" (IK + ruckig on any robot of the scenario: YuMi, Panda, the floating gripper;
runs unchanged against the hardware station). Grasp models the robot cannot execute (suction on
a jaw-only robot) are not planned.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pydrake.systems.framework import Diagram, DiagramBuilder

from ms_drake.errors import MsDrakeError
from ms_drake.execution import (
    FIDELITIES,
    GRASP_OUTCOMES,
    LIFT_THRESHOLD,
    PRIMITIVE_PUSH_TIME_STEP,
    ActionExecutor,
    FullBackend,
    ObjectCarrier,
    PrimitiveBackend,
    tcp_offset_of,
)
from ms_drake.execution.reach import PickReach
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.grasping.grasp_sets import load_grasp_set
from ms_drake.grasping.indexed import IndexedGraspPlanner, environment_parts
from ms_drake.grasping.meshes import object_mesh
from ms_drake.grasping.planner import JAW_CONTACTS, GraspPlanner, LazyGraspPlanner, ObjectGeometrySource
from ms_drake.objects import get_object
from ms_drake.perception.association import MaskAssociation
from ms_drake.perception.masks import TargetAmodalMask, make_amodal_masks, object_labels
from ms_drake.perception.occupancy import BACKENDS as OCCUPANCY_BACKENDS
from ms_drake.perception.occupancy import OccupancyEstimator, TargetBox
from ms_drake.perception.ready import ImagesReady
from ms_drake.perception.segmentation import BACKENDS as SEGMENTATION_BACKENDS
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import BACKENDS as DETECTOR_BACKENDS
from ms_drake.perception.target import TargetDetector, render_templates
from ms_drake.policies.bin_selectors import OCCUPANCY_POLICIES, PUSHING, SelectorParams, check_policy
from ms_drake.policies.selector import PolicySelector
from ms_drake.pushing import PushPlanner, PushPolicySystem, check_push_policy
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import get_plant, station_objects
from ms_drake.station.environments import dropoff_points
from ms_drake.station.robots import set_arm_positions


GRASP_PLANNERS = ("indexed", "image")


class ControllerError(MsDrakeError, ValueError):
    """A controller was asked for with settings it cannot honour (names the setting and the fix)."""


@dataclass
class BinSearchParams:
    """Settings of the bin-search controller.

    policy: a selector of ms_drake.policies.bin_selectors.POLICIES; fidelity: primitive | full;
    horizon: the action budget H (the reference uses 2N); seed: every random choice of the
    controller (grasp sampling, random selectors, primitive grasp outcomes).
    grasp_models: the GraspPlanners whose best grasps the selector compares per object (parallel
    jaw with a contact model, and "suction"), as in Ch. 7; grasp_params: GraspEvaluator keywords
    of the jaw models, e.g. {"closing_force": 40.0}.
    segmentation: "ground_truth" (label image; needs `sim`), "euclidean", "region_growing" or "learned"
    (depth only, run on hardware). detector: the TargetDetector backend, "color" (HSV, red
    target), "template" (hue-saturation histograms) or "learned" (the siamese matcher); the last
    two compare every mask with `templates` views of the target object rendered alone
    (render_templates; in simulation the target's model comes from `sim`, else pass
    target_templates= to MakeBinSearchController). occupancy: the OccupancyEstimator backend, "learned" (the
    network of ms_drake.perception.occupancy_net, from the target's size) or "analytic" (the
    ground-truth generator; given a TargetMesh with its pose it reads privileged state).
    period: the executor's update period [s].
    grasp_planner: "indexed" (in simulation: each object's pre-computed grasp set at its current
    pose, checked against the scene, ms_drake.grasping.indexed; objects without a set, or
    without `sim`, are planned on the image) or "image" (the image-based planners only); ""
    (default): "indexed" for the primitive fidelity, "image" for the full one.
    reach: with the "indexed" planner, keep only grasps a robot reaches (execution.reach.PickReach:
    the full backend's pick plan, IK from park): "" (default) no check, "robot" the scenario's own
    robot, or a scenario name (e.g. "YuMiBin": the primitive mode choosing the YuMi's grasps).
    push_policy: the pushes of the *_push selectors: "" (default) the Ch. 7 free-space push of
    every object (PushPlanner), or a Ch. 4 policy of ms_drake.pushing.POLICIES (PushPolicySystem
    on the depth image and masks: one push, of the object the policy chooses).
    grasp_outcome: the primitive fidelity's grasp outcome (execution.GRASP_OUTCOMES): "draw"
    (default; success with probability = quality), "threshold" (deterministic: quality >=
    execution.LIFT_THRESHOLD), "checked" (that lift test, and the selector attempts only grasps
    that pass it: SelectorParams.t_thresh = LIFT_THRESHOLD) or "nominal" (deterministic: the
    nominal contact model lifts the object with the grasp, Grasp.lifts; needs grasp_planner
    "image"; a grasp that failed is not attempted again on the same state,
    SelectorParams.retry_failed = False); the full fidelity's outcome is the physics'.
    skip_failed: an object a grasp failed on is passed over until an action succeeds (the state
    changes), whatever the outcome model (SelectorParams.skip_failed): the selector walks on to the
    next mask of its priority list.
    jaw_contact: the image jaw planner's depth rule, grasping.planner.JAW_CONTACTS: "center"
    (default) or "pad" (the pads' lower part holds thin objects lying flat; GraspPlanner).
    """

    policy: str = "largest"
    fidelity: str = "primitive"
    horizon: int = 30
    seed: int = 0
    grasp_models: tuple = ("soft_point", "suction")
    grasp_samples: int = 8
    robust_samples: int = 4
    grasp_params: dict | None = None
    segmentation: str = "ground_truth"
    detector: str = "color"
    templates: int = 5
    occupancy: str = "learned"  # OccupancyEstimator backend: "learned" (target size only) or "analytic"
    occupancy_weights: str = ""  # the learned backend's weights file ("": the shipped models/weights/occupancy.pt)
    occupancy_best_match: float | None = None  # the analytic backend's AnalyticOccupancy(best_match=...)
    camera: str = "overhead"
    period: float = 0.05
    grasp_planner: str = ""
    push_policy: str = ""
    reach: str = ""
    grasp_outcome: str = "draw"
    skip_failed: bool = False
    jaw_contact: str = "center"

    def __post_init__(self):
        check_policy(self.policy)
        if self.jaw_contact not in JAW_CONTACTS:
            raise ControllerError(f"jaw_contact {self.jaw_contact!r} unknown; choose one of {', '.join(JAW_CONTACTS)}")
        if self.grasp_outcome not in GRASP_OUTCOMES:
            raise ControllerError(f"grasp_outcome {self.grasp_outcome!r} unknown; choose one of "
                                  f"{', '.join(GRASP_OUTCOMES)}")
        if self.push_policy:
            check_push_policy(self.push_policy)
        if self.fidelity not in FIDELITIES:
            raise ControllerError(f"fidelity {self.fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")
        if self.segmentation not in SEGMENTATION_BACKENDS:
            raise ControllerError(f"segmentation {self.segmentation!r} unknown; choose one of "
                                  f"{', '.join(SEGMENTATION_BACKENDS)}")
        if self.detector not in DETECTOR_BACKENDS:
            raise ControllerError(f"detector {self.detector!r} unknown; choose one of {', '.join(DETECTOR_BACKENDS)}")
        if int(self.templates) < 1:
            raise ControllerError(f"templates must be >= 1 view of the target, got {self.templates!r}")
        if int(self.horizon) < 1:
            raise ControllerError(f"horizon must be >= 1 action, got {self.horizon!r}")
        if not self.grasp_planner:
            self.grasp_planner = "indexed" if self.fidelity == "primitive" else "image"
        if self.grasp_planner not in GRASP_PLANNERS:
            raise ControllerError(f"grasp_planner {self.grasp_planner!r} unknown; choose one of "
                                  f"{', '.join(GRASP_PLANNERS)}")
        if self.grasp_outcome == "nominal" and self.grasp_planner != "image":
            raise ControllerError(f"grasp_outcome 'nominal' needs each grasp's nominal lift verdict, which only the "
                                  f"image planner computes; grasp_planner is {self.grasp_planner!r}: use "
                                  "grasp_planner='image' (CLI: --grasp-planner image)")
        if self.occupancy not in OCCUPANCY_BACKENDS:
            raise ControllerError(f"occupancy {self.occupancy!r} unknown; choose one of {', '.join(OCCUPANCY_BACKENDS)}")
        if self.occupancy_weights and self.occupancy != "learned":
            raise ControllerError(f"occupancy_weights={self.occupancy_weights!r} is for the learned occupancy backend; "
                                  f"occupancy is {self.occupancy!r}")
        if self.occupancy_best_match is not None and self.occupancy != "analytic":
            raise ControllerError(f"occupancy_best_match is for the analytic occupancy backend; occupancy is "
                                  f"{self.occupancy!r}")
        if self.occupancy_weights and not Path(self.occupancy_weights).is_file():
            raise ControllerError(f"occupancy_weights: no such file {self.occupancy_weights!r}; give a weights file "
                                  "written by `ms-drake train occupancy` (or '' for the shipped one)")


@dataclass(frozen=True)
class SimulationInfo:
    """What only a simulated station can tell a controller: its plant (object labels, meshes and
    bodies for ground-truth segmentation, exact grasp meshes and outcome checks) and which object
    is the target. A controller built without it uses the hardware ports only."""

    plant: object
    target_id: str = ""

    @staticmethod
    def from_station(station, target_index: int = -1) -> "SimulationInfo":
        """The station's plant; the target is its object number `target_index` (-1: none)."""
        plant = get_plant(station)
        objs = station_objects(plant)
        if not -1 <= target_index < len(objs):
            raise ControllerError(f"target_index {target_index} is not an object of the station "
                                  f"({len(objs)} objects; -1 for none)")
        return SimulationInfo(plant, objs[target_index].model_name if target_index >= 0 else "")


def _backend(scenario, params: BinSearchParams, workspace: Workspace, sim: SimulationInfo | None):
    bodies = {}
    if sim is not None:
        bodies = {o.model_name: int(o.body_index) for o in station_objects(sim.plant)}
    target_id = sim.target_id if sim is not None else ""
    if params.fidelity == "primitive":
        if sim is None or scenario.robot.name != "floating":
            raise ControllerError("fidelity 'primitive' runs in simulation on the floating gripper "
                                  "(FloatingGripperBin, with sim=SimulationInfo.from_station(station)); "
                                  "use fidelity 'full' for a robot or the hardware station")
        return PrimitiveBackend(bodies, workspace, tcp_offset_of(sim.plant), target_id=target_id, seed=params.seed,
                                grasp_outcome=params.grasp_outcome)
    return FullBackend(scenario, bodies, workspace, target_id=target_id, seed=params.seed)


def MakeBinSearchController(scenario, params: BinSearchParams | None = None, sim: SimulationInfo | None = None,
                            target_shape=None, name: str = "bin_search_controller",
                            target_templates=None) -> "BinSearchController":
    """The controller Diagram of a bin search on `scenario`'s station (see the module docstring).

    target_shape: the target's TargetMesh / TargetBox: with it the controller holds the occupancy
    estimator (exported as `occupancy`; the xray and oracle policies need it).
    target_templates: list of perception.target.Template for the template / learned detectors
    (default in simulation: `params.templates` views of the target rendered in the target colour)."""
    params = params or BinSearchParams()
    if params.camera not in scenario.cameras:
        raise ControllerError(f"camera {params.camera!r} is not a camera of the scenario "
                              f"(cameras: {', '.join(scenario.cameras) or 'none'})")
    if params.segmentation == "ground_truth" and sim is None:
        raise ControllerError("segmentation 'ground_truth' reads the simulated label image: pass "
                              "sim=SimulationInfo.from_station(station), or segmentation='euclidean' on hardware")
    if params.policy == "oracle" and sim is None:
        raise ControllerError("the oracle policy reads the true object poses: it needs sim=SimulationInfo")
    if target_shape is None and params.policy in OCCUPANCY_POLICIES and sim is not None and sim.target_id:
        # In simulation the target's model is known: X-Ray estimates occupancy from its size.
        full = next(o.full_name for o in station_objects(sim.plant) if o.model_name == sim.target_id)
        target_shape = TargetBox.from_object(full)
    needs_occupancy = target_shape is not None  # built whenever the target's shape is known
    if params.policy in (*OCCUPANCY_POLICIES, "oracle") and target_shape is None:
        raise ControllerError(f"policy {params.policy!r} needs target_shape= (occupancy.TargetMesh or TargetBox)")
    cam = params.camera
    cfg = scenario.cameras[cam]
    camera = PinholeCamera.from_config(cfg)
    workspace = Workspace.from_scenario(scenario)
    backend = _backend(scenario, params, workspace, sim)
    kinds = getattr(backend, "grasp_kinds", ("parallel_jaw", "suction"))
    models = [m for m in params.grasp_models if ("suction" if m == "suction" else "parallel_jaw") in kinds]
    if not models:
        raise ControllerError(f"grasp_models {tuple(params.grasp_models)} holds no model the robot "
                              f"{scenario.robot.name!r} can execute (it has: {', '.join(kinds)})")

    builder = DiagramBuilder()

    def export_input(ports, name):
        builder.ExportInput(ports[0], name)
        for port in ports[1:]:
            builder.ConnectInput(name, port)

    depth_inputs, rgb_inputs, pose_inputs = [], [], []
    if params.segmentation == "ground_truth":
        seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(sim.plant)))
        export_input([seg.GetInputPort("label_image")], f"{cam}.label_image")
    else:
        seg = builder.AddSystem(Segmenter(params.segmentation, camera=camera, workspace=workspace))
        depth_inputs.append(seg.GetInputPort("depth_image"))
    seg.set_name("segmenter")
    masks = seg.GetOutputPort("masks")
    if params.segmentation != "ground_truth" and sim is not None:
        # Simulation: the segmenter's masks named after the objects behind them, so the simulated
        # executor knows what a grasp lifted (perception.association; pixels unchanged).
        assoc = builder.AddSystem(MaskAssociation(object_labels(sim.plant), camera.width, camera.height))
        assoc.set_name("mask_association")
        builder.Connect(masks, assoc.GetInputPort("masks"))
        export_input([assoc.GetInputPort("label_image")], f"{cam}.label_image")
        masks = assoc.GetOutputPort("masks")
    templates = None
    if params.detector != "color":
        templates = target_templates
        if templates is None:
            if sim is None or not sim.target_id:
                raise ControllerError(f"detector {params.detector!r} matches views of the target: pass "
                                      "target_templates= (render_templates(scenario, object_name)) or "
                                      "sim=SimulationInfo.from_station(station, target_index)")
            full = next(o.full_name for o in station_objects(sim.plant) if o.model_name == sim.target_id)
            templates = render_templates(scenario, full, int(params.templates), seed=params.seed, camera=cam)
    det = builder.AddSystem(TargetDetector(params.detector, width=camera.width, height=camera.height,
                                           templates=templates))
    det.set_name("target_detector")
    rgb_inputs.append(det.GetInputPort("rgb_image"))
    builder.Connect(masks, det.GetInputPort("masks"))

    color_cam, _ = cfg.MakeCameras()
    planners = [GraspPlanner(color_cam.core().intrinsics(), camera.X_WC, model=m, num_samples=params.grasp_samples,
                             robust_samples=params.robust_samples, seed=params.seed,
                             evaluator_params=params.grasp_params if m != "suction" else None,
                             jaw_contact=params.jaw_contact)
                for m in models]
    grasp = LazyGraspPlanner(planners, camera.width, camera.height, seed=params.seed)
    if params.grasp_planner == "indexed" and sim is not None:
        # Pre-computed grasp sets of the jaw model planned here (objects without one: the image planners)
        jaw_model = next((m for m in models if m != "suction"), "")
        names = {o.model_name: o.full_name for o in station_objects(sim.plant)}
        sets = {oid: gs for oid, name in names.items()
                if (gs := load_grasp_set(name)) is not None and (not jaw_model or gs.model == jaw_model)}
        grasp_kinds = tuple(sorted({"suction" if m == "suction" else "parallel_jaw" for m in models}))
        reach = None
        if params.reach:
            reach = PickReach(scenario if params.reach == "robot" else load_scenario(None, params.reach),
                              seed=params.seed)
        grasp = IndexedGraspPlanner(names, sets, environment_parts(scenario), workspace, camera.width, camera.height,
                                    kinds=grasp_kinds, fallback=grasp, jaw_model=jaw_model, reach=reach)
    grasp = builder.AddSystem(grasp)
    grasp.set_name("grasp_planner")
    depth_inputs.append(grasp.GetInputPort("depth_image"))
    builder.Connect(masks, grasp.GetInputPort("masks"))
    if sim is not None:
        objs = station_objects(sim.plant)
        # The grasp meshes are the repaired, closed ones (grasping.meshes.object_mesh): the contact
        # models give every grasp on an open visual mesh quality 0 ("non_watertight_mesh"), and
        # most YCB / random_urdfs visual meshes are open.
        geo = builder.AddSystem(ObjectGeometrySource({
            o.model_name: (sim.plant.get_body(o.body_index), object_mesh(o.full_name),
                           get_object(o.full_name).mass, None) for o in objs}))
        geo.set_name("object_geometry")
        pose_inputs.append(geo.GetInputPort("body_poses"))
        builder.Connect(geo.GetOutputPort("objects"), grasp.GetInputPort("objects"))

    target_id = sim.target_id if sim is not None else ""
    t_thresh = LIFT_THRESHOLD if params.grasp_outcome == "checked" else SelectorParams.t_thresh
    selector = builder.AddSystem(PolicySelector(params.policy, SelectorParams(horizon=int(params.horizon),
                                                                             seed=params.seed, t_thresh=t_thresh,
                                                                             retry_failed=params.grasp_outcome != "nominal",
                                                                             skip_failed=params.skip_failed),
                                                target_id=target_id, width=camera.width, height=camera.height))
    selector.set_name("policy_selector")
    builder.Connect(masks, selector.GetInputPort("masks"))
    builder.Connect(det.GetOutputPort("target"), selector.GetInputPort("target"))
    builder.Connect(grasp.GetOutputPort("grasps"), selector.GetInputPort("grasps"))
    outputs = {"masks": masks, "target": det.GetOutputPort("target"), "grasps": grasp.GetOutputPort("grasps")}
    if params.policy.endswith("_push"):
        pushes = builder.AddSystem(PushPolicySystem(params.push_policy, camera, workspace, source="image",
                                                    seed=params.seed) if params.push_policy
                                   else PushPlanner(camera, workspace))
        pushes.set_name("push_planner")
        depth_inputs.append(pushes.GetInputPort("depth_image"))
        builder.Connect(masks, pushes.GetInputPort("masks"))
        builder.Connect(pushes.GetOutputPort("pushes"), selector.GetInputPort("pushes"))
        outputs["pushes"] = pushes.GetOutputPort("pushes")
    if needs_occupancy:
        weights = {"weights": params.occupancy_weights} if params.occupancy_weights else {}
        if params.occupancy_best_match is not None:
            weights = {"best_match": params.occupancy_best_match}
        occ = builder.AddSystem(OccupancyEstimator(params.occupancy, camera=camera, workspace=workspace,
                                                   target_size=target_shape, **weights))
        occ.set_name("occupancy_estimator")
        depth_inputs.append(occ.GetInputPort("depth_image"))
        builder.Connect(det.GetOutputPort("target"), occ.GetInputPort("target"))
        if params.policy in OCCUPANCY_POLICIES:
            builder.Connect(occ.GetOutputPort("occupancy"), selector.GetInputPort("occupancy"))
        outputs["occupancy"] = occ.GetOutputPort("occupancy")
    if params.policy == "oracle":
        amodal = builder.AddSystem(make_amodal_masks(sim.plant, camera))
        pick = builder.AddSystem(TargetAmodalMask(target_id))
        pose_inputs.append(amodal.get_input_port())
        builder.Connect(amodal.get_output_port(), pick.get_input_port())
        builder.Connect(pick.get_output_port(), selector.GetInputPort("target_amodal"))

    executor = builder.AddSystem(ActionExecutor(backend, period=params.period))
    executor.set_name("action_executor")
    builder.Connect(selector.GetOutputPort("action"), executor.action_port)
    builder.Connect(executor.history_port, selector.GetInputPort("history"))
    if sim is not None:
        pose_inputs.append(executor.poses_port)
    carrier = None
    if params.fidelity == "primitive":
        # The primitive mode's lifted objects leave the bin for a drop-off tray, carried in physics.
        radii = {o.model_name: 0.5 * float(np.linalg.norm(get_object(o.full_name).extents))
                 for o in station_objects(sim.plant)}
        carrier = builder.AddSystem(ObjectCarrier(sim.plant, backend.objects, dropoff_points(scenario.environment),
                                                  travel_z=workspace.floor_z + workspace.wall_height + 0.12,
                                                  camera=camera, radii=radii, period=params.period))
        carrier.set_name("object_carrier")
        builder.Connect(executor.removed_port, carrier.GetInputPort("removed"))
        builder.Connect(carrier.GetOutputPort("carrying"), executor.carrying_port)
        pose_inputs.append(carrier.GetInputPort("body_poses"))
        builder.ExportInput(carrier.GetInputPort("body_spatial_velocities"), "body_spatial_velocities")
        builder.ExportOutput(carrier.GetOutputPort("applied_spatial_force"), "applied_spatial_force")
    ready = builder.AddSystem(ImagesReady(camera.width, camera.height))
    ready.set_name("images_ready")
    rgb_inputs.append(ready.GetInputPort("rgb_image"))
    depth_inputs.append(ready.GetInputPort("depth_image"))
    builder.Connect(ready.GetOutputPort("ready"), executor.ready_port)

    export_input(depth_inputs, f"{cam}.depth_image")
    export_input(rgb_inputs, f"{cam}.rgb_image")
    if pose_inputs:
        export_input(pose_inputs, "body_poses")
    for port_name, port in executor.command_ports.items():
        builder.ExportOutput(port, port_name)
    for port_name in ("action", "history", "outcome", "removed", "status"):
        builder.ExportOutput(executor.GetOutputPort(port_name) if port_name != "action"
                             else selector.GetOutputPort("action"), port_name)
    for port_name, port in outputs.items():
        builder.ExportOutput(port, port_name)
    controller = BinSearchController(builder, backend, params, target_id, scenario)
    controller.set_name(name)
    return controller


class BinSearchController(Diagram):
    """The Diagram MakeBinSearchController builds. `initial_commands()`: the station commands
    the controller starts from (arm parked or at home, jaw open, vacuum off), to initialise a
    simulated robot where the controller expects it; `target_id`: the target's object id in
    simulation ("" when unknown)."""

    def __init__(self, builder: DiagramBuilder, backend, params: BinSearchParams, target_id: str, scenario=None):
        super().__init__()
        builder.BuildInto(self)
        self._backend, self.params, self.target_id, self.scenario = backend, params, target_id, scenario

    def initial_commands(self) -> dict:
        return self._backend.initial_commands()


BIN_SEARCH_SCENARIOS = "FloatingGripperBin (primitive or full), YuMiBin or PandaBin (full)"


def check_search_scenario(scenario, fidelity: str, name: str = "") -> None:
    """ControllerError (naming the scenario and the fix) unless `scenario` is a station a bin search
    of `fidelity` runs on: a bin with an overhead camera; the primitive mode on the floating gripper,
    full fidelity on any robot."""
    label = f"scenario {name!r}" if name else "the scenario"
    if fidelity not in FIDELITIES:
        raise ControllerError(f"fidelity {fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")
    if scenario.environment.type != "bin":
        raise ControllerError(f"{label} is a {scenario.environment.type} station; a bin search needs a bin scenario: "
                              f"{BIN_SEARCH_SCENARIOS}")
    if "overhead" not in scenario.cameras:
        raise ControllerError(f"{label} has no overhead camera (cameras: {', '.join(scenario.cameras) or 'none'}); "
                              "add one as in diagrams/scenarios.yaml's bin scenarios")
    if fidelity == "primitive" and scenario.robot.name != "floating":
        raise ControllerError(f"{label} has the robot {scenario.robot.name or 'none'!r}: the primitive mode runs on the "
                              "floating gripper (FloatingGripperBin); use fidelity full for a robot")
    if fidelity == "full" and not scenario.robot.name:
        raise ControllerError(f"{label} has no robot: full fidelity needs one ({BIN_SEARCH_SCENARIOS})")


def search_scenario(scenario, heap, fidelity: str = "primitive", policy: str = "largest"):
    """The station scenario of a search of `heap` on `scenario`'s station: its objects are the
    heap's (scenario_with_heap) and, in the primitive mode, the plant steps at the primitive mode's
    rate (10 ms; 5 ms for the selectors that push: execution.PRIMITIVE_PUSH_TIME_STEP, where the
    floating jaw's push moves objects as the YuMi's does). `scenario` is not changed."""
    check_policy(policy)
    if fidelity not in FIDELITIES:
        raise ControllerError(f"fidelity {fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")
    s = scenario_with_heap(copy.deepcopy(scenario), heap)
    if fidelity == "primitive":
        s.plant_config.time_step = PRIMITIVE_PUSH_TIME_STEP if policy in PUSHING else 0.01
    return s


def _search_parts(diagram):
    """(station, BinSearchController) inside a search diagram (as the README builds it)."""
    controllers = [sys for sys in diagram.GetSystems() if isinstance(sys, BinSearchController)]
    stations = []
    for sys in diagram.GetSystems():
        if isinstance(sys, Diagram) and not isinstance(sys, BinSearchController):
            try:
                sys.GetSubsystemByName("plant")
            except RuntimeError:
                continue
            stations.append(sys)
    if len(controllers) != 1 or len(stations) != 1:
        raise ControllerError(f"the diagram holds {len(stations)} station(s) and {len(controllers)} bin-search "
                              "controller(s); set_initial_conditions needs exactly one of each (MakeStation and "
                              "MakeBinSearchController added to one DiagramBuilder)")
    return stations[0], controllers[0]


def set_initial_conditions(diagram, context, heap) -> None:
    """The search's initial conditions in `context`, the root context of `diagram` (e.g.
    `simulator.get_mutable_context()`): the heap's objects at their saved poses, at rest, and the
    robot where the controller starts (arm parked out of the camera's view, jaw open, vacuum off).
    `diagram` holds one station built from `search_scenario(scenario, heap, ...)` (or
    `scenario_with_heap`) and one controller of MakeBinSearchController."""
    station, controller = _search_parts(diagram)
    set_heap_poses(station, context, heap)
    plant = get_plant(station)
    robot = controller.scenario.robot.name
    if robot:
        set_arm_positions(plant, plant.GetMyMutableContextFromRoot(context), robot, controller.initial_commands())


def connect_controller(builder: DiagramBuilder, controller, station) -> None:
    """Connect every controller input to the station output of the same name and every station
    input of the controller's output names to it (the station's ports are identical in simulation
    and on hardware). A controller input the station lacks raises ControllerError naming it."""
    for i in range(controller.num_input_ports()):
        name = controller.get_input_port(i).get_name()
        if not station.HasOutputPort(name):
            raise ControllerError(f"the controller reads {name!r}, which the station "
                                  f"{station.get_name()!r} does not have (simulation-only ports such as "
                                  "label images and body_poses do not exist on hardware: build the "
                                  "controller without sim= there)")
        builder.Connect(station.GetOutputPort(name), controller.get_input_port(i))
    for i in range(controller.num_output_ports()):
        name = controller.get_output_port(i).get_name()
        if station.HasInputPort(name):
            builder.Connect(controller.get_output_port(i), station.GetInputPort(name))
