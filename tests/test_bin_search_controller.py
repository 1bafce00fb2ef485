"""The bin-search controller Diagram (ms_drake.policies.bin_search): built alone with fixed
images, wired to a simulated station in three lines, wired to the hardware station over LCM
(memq://) with an emulated YuMi on the far side, and full fidelity on the Panda and the floating
gripper. ImagesReady alone."""

import dataclasses
import shutil

import cv2

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.systems.analysis import Simulator
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from ms_drake.execution import LIFT_THRESHOLD
from ms_drake.geometry import PinholeCamera
from ms_drake.types import Grasp, InstanceMasks, OccupancyMap, TargetEstimate
from ms_drake.experiments.rollout import build_search, run_search
from ms_drake.perception.occupancy import TargetBox
from ms_drake.perception.occupancy_net import default_weights
from ms_drake.perception.ready import ImagesReady
from ms_drake.policies.bin_search import (
    BinSearchAblation,
    BinSearchConfig,
    ControllerError,
    MakeBinSearchController,
    SimulationInfo,
    connect_controller,
    set_initial_conditions,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap, scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.emulator import MakeEmulatedRobot

HARDWARE = BinSearchConfig(policy="largest", fidelity="full", segmenter="euclidean", horizon=1)
YUMI_COMMANDS = ["yumi_right.position", "yumi_left.position", "yumi_right_jaw.position",
                 "yumi_right_jaw.force_limit", "yumi_left_suction.suction"]
OUTPUTS = ["action", "history", "outcome", "removed", "status", "masks", "target", "grasps"]


@pytest.fixture(scope="module")
def heap4():
    return generate_heap(load_scenario(None, "BinHeap15"), 4, seed=3, params=SEARCH_HEAPS)


@pytest.fixture(scope="module")
def yumi_images(heap4):
    """The overhead rgb and depth images of heap4 in a simulated YuMiBin station."""
    s = scenario_with_heap(load_scenario(None, "YuMiBin"), heap4)
    station = MakeStation(s, target_index=heap4.target_index)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, heap4)
    return s, (station.GetOutputPort("overhead.rgb_image").Eval(ctx),
               station.GetOutputPort("overhead.depth_image").Eval(ctx))


def _names(system, kind):
    n = system.num_input_ports() if kind == "in" else system.num_output_ports()
    port = system.get_input_port if kind == "in" else system.get_output_port
    return [port(i).get_name() for i in range(n)]


def test_images_ready_alone():
    ready = ImagesReady(64, 48)
    ctx = ready.CreateDefaultContext()
    ready.GetInputPort("rgb_image").FixValue(ctx, ImageRgba8U(0, 0))  # hardware before the first message
    ready.GetInputPort("depth_image").FixValue(ctx, ImageDepth32F(64, 48))
    assert ready.GetOutputPort("ready").Eval(ctx)[0] == 0.0
    ready.GetInputPort("rgb_image").FixValue(ctx, ImageRgba8U(64, 48))
    assert ready.GetOutputPort("ready").Eval(ctx)[0] == 1.0


def test_controller_alone_from_fixed_images_grasps_the_largest_segment(yumi_images):
    s, (rgb, depth) = yumi_images
    controller = MakeBinSearchController(s, HARDWARE)
    assert _names(controller, "in") == ["overhead.depth_image", "overhead.rgb_image"]  # hardware ports only
    assert _names(controller, "out") == YUMI_COMMANDS + OUTPUTS
    ctx = controller.CreateDefaultContext()
    controller.GetInputPort("overhead.rgb_image").FixValue(ctx, rgb)
    controller.GetInputPort("overhead.depth_image").FixValue(ctx, depth)
    masks = controller.GetOutputPort("masks").Eval(ctx)
    action = controller.GetOutputPort("action").Eval(ctx)
    assert masks.ids[0] == "seg_0" and len(masks) >= 2  # depth segments, largest first
    assert action.kind == "grasp" and action.grasp.object_id == "seg_0" and action.grasp.model == "suction"
    assert controller.GetOutputPort("status").Eval(ctx).steps == 0


def test_checked_outcome_attempts_only_grasps_that_lift(yumi_images):
    """grasp_outcome="checked": the selector's grasp threshold is the lift test's, so the grasp it
    chooses passes that test (or it stops); with "draw" it is SelectorParams' 0.15."""
    s, (rgb, depth) = yumi_images
    for outcome, t in (("draw", 0.15), ("checked", LIFT_THRESHOLD)):
        controller = MakeBinSearchController(s, dataclasses.replace(HARDWARE, ablation=BinSearchAblation(grasp_outcome=outcome)))
        assert controller.GetSubsystemByName("policy_selector").params.t_thresh == t
        ctx = controller.CreateDefaultContext()
        controller.GetInputPort("overhead.rgb_image").FixValue(ctx, rgb)
        controller.GetInputPort("overhead.depth_image").FixValue(ctx, depth)
        action = controller.GetOutputPort("action").Eval(ctx)
        assert action.kind == "stop" or action.grasp.quality >= t
        assert action.kind == "stop" or action.grasp.lifts is not None  # the image planner's nominal verdict
    # "nominal": the selector does not retry a failed grasp on its state; the others retry
    nominal = MakeBinSearchController(s, dataclasses.replace(HARDWARE, ablation=BinSearchAblation(grasp_outcome="nominal")))
    assert nominal.GetSubsystemByName("policy_selector").params.retry_failed is False
    assert controller.GetSubsystemByName("policy_selector").params.retry_failed is True
    skipping = MakeBinSearchController(s, dataclasses.replace(HARDWARE, ablation=BinSearchAblation(skip_failed=True)))
    assert skipping.GetSubsystemByName("policy_selector").params.skip_failed is True
    assert controller.GetSubsystemByName("policy_selector").params.skip_failed is False


def test_jaw_contact_reaches_the_jaw_planner(yumi_images):
    """jaw_contact="pad": the jaw GraspPlanner samples with the pad rule and its point model seeks
    contacts down the pads; suction is unchanged; an unknown rule is refused with the choices."""
    from ms_drake.grasping.planner import PAD_BELOW
    s, (rgb, depth) = yumi_images
    for rule, span in (("center", 0.0), ("pad", PAD_BELOW)):
        controller = MakeBinSearchController(s, dataclasses.replace(HARDWARE, ablation=BinSearchAblation(jaw_contact=rule)))
        planners = controller.GetSubsystemByName("grasp_planner").planners
        jaw = [p for p in planners if p.model != "suction"]
        assert jaw and all(p.jaw_contact == rule and p.evaluator.pad_span == span for p in jaw)
        ctx = controller.CreateDefaultContext()
        controller.GetInputPort("overhead.rgb_image").FixValue(ctx, rgb)
        controller.GetInputPort("overhead.depth_image").FixValue(ctx, depth)
        assert controller.GetOutputPort("action").Eval(ctx).kind in ("grasp", "stop")
    with pytest.raises(ControllerError, match="jaw_contact 'tip' unknown; choose one of center, pad"):
        BinSearchAblation(jaw_contact="tip")

def test_controller_rejects_settings_it_cannot_honour(yumi_images):
    s, _ = yumi_images
    with pytest.raises(ControllerError, match="ground_truth' reads the simulated label image"):
        MakeBinSearchController(s, BinSearchConfig(fidelity="full"))
    with pytest.raises(ControllerError, match="primitive' runs in simulation on the floating gripper"):
        MakeBinSearchController(s, BinSearchConfig(policy="largest", fidelity="primitive", segmenter="euclidean"))
    with pytest.raises(ControllerError, match="needs target_shape"):
        MakeBinSearchController(s, BinSearchConfig(policy="xray", fidelity="full", segmenter="euclidean"))
    with pytest.raises(ControllerError, match="camera 'front' is not a camera"):
        MakeBinSearchController(s, BinSearchConfig(fidelity="full", segmenter="euclidean", camera="front"))
    with pytest.raises(ControllerError, match="segmenter 'sonar' unknown"):
        BinSearchConfig(segmenter="sonar")
    with pytest.raises(ControllerError, match="grasp_outcome .coin. unknown; choose one of draw, threshold, checked"):
        BinSearchAblation(grasp_outcome="coin")
    with pytest.raises(ControllerError, match="grasp_outcome 'nominal' needs.*grasp_planner is 'indexed'"):
        BinSearchConfig(grasp_planner="indexed")
    assert BinSearchConfig(grasp_planner="indexed", ablation=BinSearchAblation(grasp_outcome="draw")).grasp_planner \
        == "indexed"
    with pytest.raises(ControllerError, match="occupancy_weights 'nowhere.pt': file not found"):
        BinSearchConfig(occupancy_weights="nowhere.pt")
    with pytest.raises(ControllerError, match="is for the learned occupancy; ablation.occupancy is 'analytic'"):
        BinSearchConfig(occupancy_weights=str(default_weights()), ablation=BinSearchAblation(occupancy="analytic"))
    with pytest.raises(ControllerError, match="ablation.occupancy 'exact' unknown"):
        BinSearchAblation(occupancy="exact")


def test_the_learned_occupancy_reads_the_weights_it_is_given(yumi_images, tmp_path):
    s, _ = yumi_images
    weights = tmp_path / "copy.pt"
    shutil.copy(default_weights(), weights)
    shape = TargetBox(0.045, 0.045, 0.005)
    for given, used in (("", default_weights()), (str(weights), weights)):
        controller = MakeBinSearchController(s, BinSearchConfig(policy="xray", fidelity="full", segmenter="euclidean",
                                                                occupancy_weights=given), target_shape=shape)
        assert controller.GetSubsystemByName("occupancy_estimator").backend.weights == used


def test_three_lines_wire_the_controller_to_a_simulated_station(heap4):
    s = scenario_with_heap(load_scenario(None, "FloatingGripperBin"), heap4)
    s.plant_config.time_step = 0.01
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, target_index=heap4.target_index))
    controller = builder.AddSystem(MakeBinSearchController(
        s, BinSearchConfig(policy="largest", horizon=8, seed=5), sim=SimulationInfo.from_station(station,
                                                                                        heap4.target_index)))
    connect_controller(builder, controller, station)
    diagram = builder.Build()
    assert _names(controller, "in") == ["overhead.label_image", "body_spatial_velocities", "overhead.depth_image",
                                        "overhead.rgb_image", "body_poses"]
    assert "applied_spatial_force" in _names(controller, "out")  # the primitive mode's ObjectCarrier
    ctx = diagram.CreateDefaultContext()
    set_initial_conditions(diagram, ctx, heap4)  # the heap, and the gripper parked where the controller starts
    q = station.GetOutputPort("floating.position_measured").Eval(station.GetMyContextFromRoot(ctx))
    assert np.allclose(q, controller.initial_commands()["floating.position"])
    cc = controller.GetMyContextFromRoot(ctx)
    action = controller.GetOutputPort("action").Eval(cc)
    target = station_objects(get_plant(station))[heap4.target_index].model_name
    assert controller.target_id == target
    assert action.kind == "grasp" and (action.grasp.object_id, action.grasp.quality) == (target, 0.5)


def test_the_controller_drives_the_hardware_station_over_lcm(heap4):
    """Hardware station + emulated YuMi on a memq:// bus: the controller waits for the first
    camera images, segments the depth image, and its grasp reaches the robot over LCM."""
    s = scenario_with_heap(load_scenario(None, "YuMiBin"), heap4)
    lcm = DrakeLcm("memq://bin_search_controller")
    builder = DiagramBuilder()
    hardware = builder.AddSystem(MakeStation(s, hardware=True, lcm=lcm))
    robot = builder.AddSystem(MakeEmulatedRobot(s, lcm=lcm))
    controller = builder.AddSystem(MakeBinSearchController(s, HARDWARE))
    connect_controller(builder, controller, hardware)
    sim = Simulator(builder.Build())
    ctx = sim.get_mutable_context()
    set_heap_poses(robot.GetSubsystemByName("simulated_station"), ctx, heap4)
    cc, rc = controller.GetMyContextFromRoot(ctx), robot.GetMyContextFromRoot(ctx)
    ready = controller.GetSubsystemByName("images_ready")
    home = robot.GetOutputPort("yumi_left.position_measured").Eval(rc).copy()
    sim.AdvanceTo(0.0)
    assert ready.GetOutputPort("ready").Eval(ready.GetMyContextFromRoot(ctx))[0] == 0.0  # no image yet
    assert not controller.GetOutputPort("status").Eval(cc).busy
    moved = 0.0
    for t in np.arange(0.1, 20.01, 0.1):
        sim.AdvanceTo(t)
        q = robot.GetOutputPort("yumi_left.position_measured").Eval(rc)
        moved = max(moved, float(np.abs(q - home).max()))
        if controller.GetOutputPort("status").Eval(cc).done:  # the search ended the simulation
            break
    history = controller.GetOutputPort("history").Eval(cc)
    status = controller.GetOutputPort("status").Eval(cc)
    assert (status.done, status.steps, status.stop_reason) == (True, 1, "horizon")
    (outcome,) = history
    assert outcome.action.kind == "grasp" and outcome.action.grasp.model == "suction"
    assert outcome.action.grasp.object_id == "seg_0"
    # No body poses on hardware: the lift is not observed, so the outcome says so.
    assert (outcome.success, outcome.message) == (False, "not_lifted")
    assert moved > 0.3  # the suction arm travelled to the grasp and back over LCM [rad]


@pytest.mark.parametrize("scenario_name", ["PandaBin", "FloatingGripperBin"])
def test_full_fidelity_runs_on_the_panda_and_the_floating_gripper(heap4, scenario_name):
    params = BinSearchConfig(policy="largest", fidelity="full", horizon=2, seed=0)
    system = build_search(load_scenario(None, scenario_name), heap4, params)
    assert system.controller.GetSubsystemByName("grasp_planner").planners[0].model == "soft_point"
    assert len(system.controller.GetSubsystemByName("grasp_planner").planners) == 1  # jaw only: no suction
    res = run_search(system, heap4, params)
    # a non-target object, then the target: both lifted by the arm through compliant contact
    assert (res.actions, res.action_kinds, res.grasp_successes) == (2, ["grasp", "grasp"], 2)
    assert (res.success, res.stop_reason) == (True, "success")


class _Threshold(LeafSystem):
    """A user's segmenter: pixels above the bin floor, split into connected regions (OpenCV)."""

    def __init__(self, floor_depth: float):
        super().__init__()
        self.floor_depth = floor_depth
        self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F()))
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make(InstanceMasks(np.zeros((0, 1, 1), bool), (), np.zeros(0))),
                                       self._masks)

    def _masks(self, context, out):
        depth = np.array(self.get_input_port().Eval(context).data)[..., 0]
        n, labels = cv2.connectedComponents((depth < self.floor_depth - 0.005).astype(np.uint8))
        masks = np.stack([labels == k for k in range(1, n) if (labels == k).sum() > 200])
        out.set_value(InstanceMasks(masks, tuple(f"seg_{k}" for k in range(len(masks))), np.ones(len(masks))))


class _FirstMaskIsTheTarget(LeafSystem):
    """A user's target detector: the first mask."""

    def __init__(self):
        super().__init__()
        self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks(np.zeros((0, 1, 1), bool), (), np.zeros(0))))
        self.DeclareAbstractOutputPort("target", lambda: AbstractValue.Make(TargetEstimate(False, np.zeros((1, 1), bool))),
                                       self._target)

    def _target(self, context, out):
        m = self.get_input_port().Eval(context)
        out.set_value(TargetEstimate(True, m.masks[0], 1.0, 0) if len(m) else TargetEstimate(False, np.zeros((1, 1), bool)))


class _OneSuctionGraspPerMask(LeafSystem):
    """A user's grasp planner: a vertical suction grasp at each mask's highest point."""

    def __init__(self, camera):
        super().__init__()
        self.camera = camera
        self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F()))
        self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks(np.zeros((0, 1, 1), bool), (), np.zeros(0))))
        self.DeclareAbstractOutputPort("grasps", lambda: AbstractValue.Make(()), self._grasps)

    def _grasps(self, context, out):
        depth = np.array(self.GetInputPort("depth_image").Eval(context).data)[..., 0]
        masks = self.GetInputPort("masks").Eval(context)
        grasps = []
        for oid, m in zip(masks.ids, masks.masks):
            v, u = np.unravel_index(np.where(m, depth, np.inf).argmin(), depth.shape)
            p_C = self.camera.deproject(depth)[v, u]
            p = self.camera.X_WC.multiply(p_C)
            grasps.append(Grasp("suction", tuple(p), (0.0, 0.0, -1.0), object_id=oid, quality=0.9))
        out.set_value(tuple(grasps))


class _UniformOverTheTarget(LeafSystem):
    """A user's occupancy estimator: uniform over the target's mask."""

    def __init__(self):
        super().__init__()
        self.DeclareAbstractInputPort("target", AbstractValue.Make(TargetEstimate(False, np.zeros((1, 1), bool))))
        self.DeclareAbstractOutputPort("occupancy", lambda: AbstractValue.Make(OccupancyMap(np.zeros((1, 1)))),
                                       self._occupancy)

    def _occupancy(self, context, out):
        m = self.get_input_port().Eval(context).mask.astype(float)
        out.set_value(OccupancyMap(m / max(m.sum(), 1.0)))


def test_the_controller_takes_a_user_s_own_segmenter_detector_grasp_planner_and_occupancy(yumi_images):
    """Each part given as a Drake System replaces the named one, wired by its port names; X-Ray
    then chooses among the user's grasps with the user's occupancy."""
    s, (rgb, depth) = yumi_images
    camera = PinholeCamera.from_config(s.cameras["overhead"])
    d = np.array(depth.data)[..., 0]
    floor = float(np.percentile(d[np.isfinite(d)], 90))  # most of the image is the bin floor
    parts = dict(segmenter=_Threshold(floor), target_detector=_FirstMaskIsTheTarget(),
                 grasp_planner=_OneSuctionGraspPerMask(camera), occupancy_estimator=_UniformOverTheTarget())
    controller = MakeBinSearchController(s, BinSearchConfig(policy="xray", fidelity="full", horizon=1), **parts)
    for part, system in parts.items():
        assert controller.GetSubsystemByName(part) is system
    assert set(_names(controller, "in")) == {"overhead.depth_image", "overhead.rgb_image"}
    ctx = controller.CreateDefaultContext()
    controller.GetInputPort("overhead.rgb_image").FixValue(ctx, rgb)
    controller.GetInputPort("overhead.depth_image").FixValue(ctx, depth)
    masks = controller.GetOutputPort("masks").Eval(ctx)
    grasps = controller.GetOutputPort("grasps").Eval(ctx)
    assert len(masks) >= 1 and len(grasps) == len(masks)
    assert controller.GetOutputPort("occupancy").Eval(ctx).distribution.sum() == pytest.approx(1.0)
    action = controller.GetOutputPort("action").Eval(ctx)
    assert action.kind == "grasp" and action.grasp in grasps
