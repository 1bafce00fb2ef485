"""The bin mechanical-search controller as one Drake Diagram, wired to a station in three lines:

    station = builder.AddSystem(MakeStation(scenario))                  # or MakeStation(scenario, hardware=True)
    controller = builder.AddSystem(MakeBinSearchController(scenario, params, sim=SimulationInfo.from_station(station)))
    connect_controller(builder, controller, station)

In simulation, start the robot where the controller expects it (parked out of the camera's view):
`station.robots.set_arm_positions(plant, plant_context, robot, controller.initial_commands())`.

Inside (docs/concepts.md, "Data flow"; every planner is a system of the diagram):
  <cam>.label_image -> Segmenter("ground_truth")   (simulation)  |  <cam>.depth_image -> Segmenter(params.segmenter)
  <cam>.rgb_image + <cam>.depth_image + masks -> TargetDetector(params.detector) -> target (the depth: the
    template detector's geometric check)
  with a depth segmenter: masks + target -> TargetInstance -> masks, target (a target seen in no
    mask of its own gets one); in simulation -> MaskAssociation(<cam>.label_image), the masks
    named after the objects behind them so the simulated executor knows what a grasp lifted
  <cam>.depth_image + target -> OccupancyEstimator(params.occupancy_estimator) -> occupancy (given target_shape; xray reads it)
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


import copy
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pydrake.systems.framework import Diagram, DiagramBuilder

from ms_drake.config_files import load_config
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
from ms_drake.perception.occupancy import OccupancyEstimator, TargetBox
from ms_drake.perception.ready import ImagesReady
from ms_drake.perception.segmentation import BACKENDS as SEGMENTATION_BACKENDS
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import BACKENDS as DETECTOR_BACKENDS
from ms_drake.perception.target import TargetDetector, render_templates
from ms_drake.perception.target_instance import TargetInstance
from ms_drake.policies.bin_selectors import OCCUPANCY_POLICIES, PUSHING, SelectorParams, check_policy
from ms_drake.policies.selector import PolicySelector
from ms_drake.pushing import PushPlanner, PushPolicySystem, check_push_policy
from ms_drake.scenario import default_scenarios_file, load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.scenes.layouts import HeapConfig
from ms_drake.station import get_plant, station_objects
from ms_drake.station.environments import dropoff_points
from ms_drake.station.robots import set_arm_positions


GRASP_PLANNERS = ("indexed", "image")


class ControllerError(MsDrakeError, ValueError):
    """A controller was asked for with settings it cannot honour (names the setting and the fix)."""


OCCUPANCY_ESTIMATORS = ("learned", "analytic_image", "analytic_image_best", "analytic")
IMAGE_BEST_MATCH = 0.05  # "analytic_image_best": AnalyticOccupancy(best_match=...)


@dataclass
class BinSearchAblation:
    """Switches for ablations and for re-running older settings. The defaults are the best settings
    we know; each other value answers a question the benchmarks ask (docs: "Ablations").

    grasp_outcome: the primitive fidelity's grasp outcome (execution.GRASP_OUTCOMES): "nominal"
    (default; deterministic: the nominal contact model lifts the object with the grasp, and a grasp
    that failed is not attempted again on the same state; needs the image grasp planner), "draw"
    (success with probability = quality, the Ch. 7 model), "threshold" (quality >=
    execution.LIFT_THRESHOLD) or "checked" (that test, and only grasps that pass it are attempted).
    The full fidelity's outcome is the physics'.
    skip_failed: an object a grasp failed on is passed over until an action succeeds.
    jaw_contact: the image jaw planner's depth rule, grasping.planner.JAW_CONTACTS: "pad" (default;
    the pads' lower edge, so thin objects lying flat get jaw grasps) or "center".
    occupancy: X-Ray's occupancy estimator: "learned" (default; the network, from the depth image
    and the target's size), "analytic_image" (the ground-truth generator on the depth image and the
    target's box, no pose: what the network learns), "analytic_image_best" (the same, a partly
    seen target keeping its best-matching placements) or "analytic" (the generator on the target's
    mesh at its true pose: privileged). The oracle always uses "analytic".
    time_step / contact_approximation: the plant's step [s] and discrete contact approximation;
    None keeps the search's (the primitive mode: 10 ms, 5 ms for the pushing selectors; full: the
    scenario's).
    """

    grasp_outcome: str = "nominal"
    skip_failed: bool = False
    jaw_contact: str = "pad"
    occupancy: str = "learned"
    time_step: float | None = None
    contact_approximation: str | None = None

    def __post_init__(self):
        if self.jaw_contact not in JAW_CONTACTS:
            raise ControllerError(f"ablation.jaw_contact {self.jaw_contact!r} unknown; choose one of "
                                  f"{', '.join(JAW_CONTACTS)}")
        if self.grasp_outcome not in GRASP_OUTCOMES:
            raise ControllerError(f"ablation.grasp_outcome {self.grasp_outcome!r} unknown; choose one of "
                                  f"{', '.join(GRASP_OUTCOMES)}")
        if self.occupancy not in OCCUPANCY_ESTIMATORS:
            raise ControllerError(f"ablation.occupancy {self.occupancy!r} unknown; choose one of "
                                  f"{', '.join(OCCUPANCY_ESTIMATORS)}")


@dataclass
class BinSearchConfig:
    """One bin search: the station, the heaps and the controller. The defaults are Table 8.2's
    setting (the best we know); a Drake YAML file of this schema (`load_bin_search_config`) or
    `--set key=value` overrides any field.

    policy: a selector of ms_drake.policies.bin_selectors.POLICIES. fidelity: "primitive" (the
    floating gripper; grasp outcomes from the contact models) or "full" (the scenario's robot in
    physics). scenario / scenario_file: the station ("" = FloatingGripperBin for primitive, YuMiBin
    for full, in diagrams/scenarios.yaml). heap: the heaps searched (scenes.layouts.HeapConfig).
    horizon: the action budget H. seed: every random choice of the controller (grasp sampling,
    random selectors, primitive grasp outcomes); a benchmark sets it to the heap's seed.
    segmenter: "ground_truth" (the simulated label image), "euclidean", "region_growing" or
    "learned" (depth only: what runs on a robot). detector: the target detector, "color" (HSV, red
    target), "template" (hue-saturation histograms checked against the target's size from depth) or "learned"
    (the siamese matcher); the last two
    compare every mask with `templates` views of the target rendered alone. occupancy_weights: the
    learned occupancy's weights file ("" = the shipped one).
    grasp_planner: "image" (the planners sample `grasp_samples` candidates per mask on the depth
    image) or "indexed" (in simulation: each object's pre-computed grasp set at its current pose,
    checked against the scene). grasp_models: the planners whose best grasps are compared per object
    (a parallel-jaw contact model and "suction"); grasp_params: GraspEvaluator keywords of the jaw
    models, e.g. {closing_force: 40.0}. reach: with the indexed planner, keep only grasps a robot
    reaches ("" none, "robot" the station's, or a scenario name). push_policy: the pushes of the
    *_push selectors: "" the Ch. 7 free-space push, or a Ch. 4 policy of ms_drake.pushing.POLICIES.
    camera: the camera the controller reads; period: the executor's update period [s].
    """

    policy: str = "xray"
    fidelity: str = "primitive"
    scenario: str = ""
    scenario_file: str = ""
    heap: HeapConfig = field(default_factory=HeapConfig)
    horizon: int = 10
    seed: int = 0
    segmenter: str = "ground_truth"
    detector: str = "color"
    templates: int = 5
    occupancy_weights: str = ""
    grasp_planner: str = "image"
    grasp_models: list[str] = field(default_factory=lambda: ["soft_point", "suction"])
    grasp_samples: int = 32
    robust_samples: int = 4
    grasp_params: dict[str, float] = field(default_factory=dict)
    reach: str = ""
    push_policy: str = ""
    camera: str = "overhead"
    period: float = 0.05
    ablation: BinSearchAblation = field(default_factory=BinSearchAblation)

    def __post_init__(self):
        if isinstance(self.heap, dict):
            self.heap = HeapConfig(**self.heap)
        if isinstance(self.ablation, dict):
            self.ablation = BinSearchAblation(**self.ablation)
        self.grasp_models = list(self.grasp_models)
        check_policy(self.policy)
        if self.push_policy:
            check_push_policy(self.push_policy)
        if self.fidelity not in FIDELITIES:
            raise ControllerError(f"fidelity {self.fidelity!r} unknown; choose one of {', '.join(FIDELITIES)}")
        if self.segmenter not in SEGMENTATION_BACKENDS:
            raise ControllerError(f"segmenter {self.segmenter!r} unknown; choose one of "
                                  f"{', '.join(SEGMENTATION_BACKENDS)}")
        if self.detector not in DETECTOR_BACKENDS:
            raise ControllerError(f"detector {self.detector!r} unknown; choose one of {', '.join(DETECTOR_BACKENDS)}")
        if int(self.templates) < 1:
            raise ControllerError(f"templates must be >= 1 view of the target, got {self.templates!r}")
        if int(self.horizon) < 1:
            raise ControllerError(f"horizon must be >= 1 action, got {self.horizon!r}")
        if int(self.grasp_samples) < 1:
            raise ControllerError(f"grasp_samples must be >= 1 candidate per mask, got {self.grasp_samples!r}")
        if self.grasp_planner not in GRASP_PLANNERS:
            raise ControllerError(f"grasp_planner {self.grasp_planner!r} unknown; choose one of "
                                  f"{', '.join(GRASP_PLANNERS)}")
        if self.ablation.grasp_outcome == "nominal" and self.grasp_planner != "image":
            raise ControllerError("ablation.grasp_outcome 'nominal' needs each grasp's nominal lift verdict, which "
                                  f"only the image planner computes; grasp_planner is {self.grasp_planner!r}: set "
                                  "grasp_planner=image, or another ablation.grasp_outcome (e.g. draw)")
        if self.occupancy_weights and self.ablation.occupancy != "learned":
            raise ControllerError(f"occupancy_weights={self.occupancy_weights!r} is for the learned occupancy; "
                                  f"ablation.occupancy is {self.ablation.occupancy!r}")
        if self.occupancy_weights and not Path(self.occupancy_weights).is_file():
            raise ControllerError(f"occupancy_weights {self.occupancy_weights!r}: file not found; give a weights file "
                                  "written by `ms-drake train occupancy` (or '' for the shipped one)")

    @property
    def occupancy_estimator(self) -> str:
        """The OccupancyEstimator backend: "analytic" for the oracle and the analytic ablations."""
        return "analytic" if self.policy == "oracle" or self.ablation.occupancy.startswith("analytic") else "learned"

    def to_dict(self) -> dict:
        """The config as plain data (what a record stores; `BinSearchConfig(**d)` reads it back)."""
        return dataclasses.asdict(self)

    def key(self) -> str:
        """The config without its seed, as canonical JSON: records of one run share it."""
        d = self.to_dict()
        d.pop("seed")
        return json.dumps(d, sort_keys=True)


def named_search_configs() -> dict[str, Path]:
    """The named bin-search settings: diagrams/search_<name>.yaml beside the scenario file
    (table_8_2: the defaults; ch7: Fig. 7.4 and Table C.1's setting; camera: the search from the
    camera alone, learned perception on the PhoXi-like depth sensor model)."""
    folder = default_scenarios_file().parent
    return {p.stem.removeprefix("search_"): p for p in sorted(folder.glob("search_*.yaml"))}


def load_bin_search_config(path=None, overrides=(), **fields) -> BinSearchConfig:
    """A BinSearchConfig: the defaults, then `path` (a Drake YAML file of any subset of the fields,
    or the name of a setting of named_search_configs(), e.g. "ch7"), then `fields`, then `overrides`,
    each "dotted.key=value" with a YAML value (e.g. "ablation.grasp_outcome=draw",
    "heap.objects=15"). Bad keys or values raise config_files.ConfigError naming them."""
    return load_config(BinSearchConfig, path, overrides, named_search_configs(), **fields)



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


def _backend(scenario, params: BinSearchConfig, workspace: Workspace, sim: SimulationInfo | None):
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
                                grasp_outcome=params.ablation.grasp_outcome)
    return FullBackend(scenario, bodies, workspace, target_id=target_id, seed=params.seed)


def MakeBinSearchController(scenario, params: BinSearchConfig | None = None, sim: SimulationInfo | None = None,
                            target_shape=None, name: str = "bin_search_controller",
                            target_templates=None, segmenter=None, target_detector=None, grasp_planner=None,
                            occupancy_estimator=None) -> "BinSearchController":
    """The controller Diagram of a bin search on `scenario`'s station (see the module docstring).

    target_shape: the target's TargetMesh / TargetBox: with it the controller holds the occupancy
    estimator (exported as `occupancy`; the xray and oracle policies need it).
    target_templates: list of perception.target.Template for the template / learned detectors
    (default in simulation: `params.templates` views of the target rendered in the target colour).

    Your own parts: a Drake System given here replaces the part `params` names. Each reads the
    camera's images through input ports named "depth_image" and/or "rgb_image" (the ones it
    declares are connected) and:
      segmenter             -> output "masks" (types.InstanceMasks)
      target_detector       "masks" -> output "target" (types.TargetEstimate)
      grasp_planner         "masks" -> output "grasps" (a tuple of types.Grasp, or a Mapping object
                            id -> its best Grasp); an input "objects" gets the exact meshes in simulation
      occupancy_estimator   "target" -> output "occupancy" (perception.occupancy.Occupancy)
    In simulation a user's masks are named after the objects behind them (MaskAssociation), as a
    depth segmenter's are. tests/test_bin_search_controller.py has an example of each."""
    params = params or BinSearchConfig()
    if params.camera not in scenario.cameras:
        raise ControllerError(f"camera {params.camera!r} is not a camera of the scenario "
                              f"(cameras: {', '.join(scenario.cameras) or 'none'})")
    if params.segmenter == "ground_truth" and sim is None and segmenter is None:
        raise ControllerError("segmenter 'ground_truth' reads the simulated label image: pass "
                              "sim=SimulationInfo.from_station(station), or segmenter='learned' on hardware")
    if params.policy == "oracle" and sim is None:
        raise ControllerError("the oracle policy reads the true object poses: it needs sim=SimulationInfo")
    if target_shape is None and params.policy in OCCUPANCY_POLICIES and sim is not None and sim.target_id:
        # In simulation the target's model is known: X-Ray estimates occupancy from its size.
        full = next(o.full_name for o in station_objects(sim.plant) if o.model_name == sim.target_id)
        target_shape = TargetBox.from_object(full)
    needs_occupancy = target_shape is not None or occupancy_estimator is not None
    if params.policy in (*OCCUPANCY_POLICIES, "oracle") and not needs_occupancy:
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

    def add_user_part(system, part):
        """A user's System in place of a named part: its image inputs join the camera's."""
        system = builder.AddSystem(system)
        system.set_name(part)
        for port, inputs in (("depth_image", depth_inputs), ("rgb_image", rgb_inputs)):
            if system.HasInputPort(port):
                inputs.append(system.GetInputPort(port))
        return system

    if segmenter is not None:
        seg = add_user_part(segmenter, "segmenter")
    elif params.segmenter == "ground_truth":
        seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(sim.plant)))
        export_input([seg.GetInputPort("label_image")], f"{cam}.label_image")
    else:
        seg = builder.AddSystem(Segmenter(params.segmenter, camera=camera, workspace=workspace))
        depth_inputs.append(seg.GetInputPort("depth_image"))
    seg.set_name("segmenter")
    masks = seg.GetOutputPort("masks")
    segmented = segmenter is not None or params.segmenter != "ground_truth"
    templates = None
    if params.detector != "color" and target_detector is None:
        templates = target_templates
        if templates is None:
            if sim is None or not sim.target_id:
                raise ControllerError(f"detector {params.detector!r} matches views of the target: pass "
                                      "target_templates= (render_templates(scenario, object_name)) or "
                                      "sim=SimulationInfo.from_station(station, target_index)")
            full = next(o.full_name for o in station_objects(sim.plant) if o.model_name == sim.target_id)
            templates = render_templates(scenario, full, int(params.templates), seed=params.seed, camera=cam)
    if target_detector is not None:
        det = add_user_part(target_detector, "target_detector")
    else:
        det = builder.AddSystem(TargetDetector(params.detector, width=camera.width, height=camera.height,
                                               templates=templates, camera=camera))
        det.set_name("target_detector")
        rgb_inputs.append(det.GetInputPort("rgb_image"))
        depth_inputs.append(det.GetInputPort("depth_image"))
    builder.Connect(masks, det.GetInputPort("masks"))
    target = det.GetOutputPort("target")
    if segmented:
        # A segmenter's masks: the target seen inside another object's mask, or in none, gets a
        # mask of its own (perception.target_instance), so that it can be grasped.
        carve = builder.AddSystem(TargetInstance(camera.width, camera.height))
        carve.set_name("target_instance")
        builder.Connect(masks, carve.GetInputPort("masks"))
        builder.Connect(target, carve.GetInputPort("target"))
        masks, target = carve.GetOutputPort("masks"), carve.GetOutputPort("target")
    if segmented and sim is not None:
        # Simulation: the segmenter's masks named after the objects behind them, so the simulated
        # executor knows what a grasp lifted (perception.association; pixels unchanged).
        assoc = builder.AddSystem(MaskAssociation(object_labels(sim.plant), camera.width, camera.height))
        assoc.set_name("mask_association")
        builder.Connect(masks, assoc.GetInputPort("masks"))
        export_input([assoc.GetInputPort("label_image")], f"{cam}.label_image")
        masks = assoc.GetOutputPort("masks")

    color_cam, _ = cfg.MakeCameras()
    planners = [GraspPlanner(color_cam.core().intrinsics(), camera.X_WC, model=m, num_samples=params.grasp_samples,
                             robust_samples=params.robust_samples, seed=params.seed,
                             evaluator_params=params.grasp_params if m != "suction" else None,
                             jaw_contact=params.ablation.jaw_contact)
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
    if grasp_planner is not None:
        grasp = add_user_part(grasp_planner, "grasp_planner")
    else:
        grasp = builder.AddSystem(grasp)
        grasp.set_name("grasp_planner")
        depth_inputs.append(grasp.GetInputPort("depth_image"))
    builder.Connect(masks, grasp.GetInputPort("masks"))
    if sim is not None and grasp.HasInputPort("objects"):
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
    t_thresh = LIFT_THRESHOLD if params.ablation.grasp_outcome == "checked" else SelectorParams.t_thresh
    selector = builder.AddSystem(PolicySelector(params.policy, SelectorParams(horizon=int(params.horizon),
                                                                             seed=params.seed, t_thresh=t_thresh,
                                                                             retry_failed=params.ablation.grasp_outcome != "nominal",
                                                                             skip_failed=params.ablation.skip_failed),
                                                target_id=target_id, width=camera.width, height=camera.height))
    selector.set_name("policy_selector")
    builder.Connect(masks, selector.GetInputPort("masks"))
    builder.Connect(target, selector.GetInputPort("target"))
    builder.Connect(grasp.GetOutputPort("grasps"), selector.GetInputPort("grasps"))
    outputs = {"masks": masks, "target": target, "grasps": grasp.GetOutputPort("grasps")}
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
        weights = {"weights": params.occupancy_weights} if params.occupancy_weights and params.policy != "oracle" else {}
        if params.policy != "oracle" and params.ablation.occupancy == "analytic_image_best":
            weights = {"best_match": IMAGE_BEST_MATCH}
        if occupancy_estimator is not None:
            occ = add_user_part(occupancy_estimator, "occupancy_estimator")
        else:
            occ = builder.AddSystem(OccupancyEstimator(params.occupancy_estimator, camera=camera, workspace=workspace,
                                                       target_size=target_shape, **weights))
            occ.set_name("occupancy_estimator")
            depth_inputs.append(occ.GetInputPort("depth_image"))
        builder.Connect(target, occ.GetInputPort("target"))
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

    def __init__(self, builder: DiagramBuilder, backend, params: BinSearchConfig, target_id: str, scenario=None):
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


def search_scenario(scenario, heap, config: BinSearchConfig | None = None):
    """The station scenario of a search of `heap` on `scenario`'s station: its objects are the
    heap's (scenario_with_heap) and, in the primitive mode, the plant steps at the primitive mode's
    rate (10 ms; 5 ms for the selectors that push: execution.PRIMITIVE_PUSH_TIME_STEP, where the
    floating jaw's push moves objects as the YuMi's does); config.ablation's time_step and
    contact_approximation override the plant's. `scenario` is not changed."""
    config = config or BinSearchConfig()
    s = scenario_with_heap(copy.deepcopy(scenario), heap)
    if config.fidelity == "primitive":
        s.plant_config.time_step = PRIMITIVE_PUSH_TIME_STEP if config.policy in PUSHING else 0.01
    if config.ablation.time_step is not None:
        s.plant_config.time_step = float(config.ablation.time_step)
    if config.ablation.contact_approximation is not None:
        s.plant_config.discrete_contact_approximation = config.ablation.contact_approximation
    return s


DEFAULT_SCENARIOS = {"primitive": "FloatingGripperBin", "full": "YuMiBin"}  # config.scenario ""


def config_scenario(config: BinSearchConfig):
    """The station scenario `config` names (its scenario and scenario_file; "" = DEFAULT_SCENARIOS
    of its fidelity), checked for a bin search of its fidelity (check_search_scenario)."""
    name = config.scenario or DEFAULT_SCENARIOS[config.fidelity]
    scenario = load_scenario(config.scenario_file or None, name)
    check_search_scenario(scenario, config.fidelity, name)
    return scenario


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
