"""The shelf controller with perception="depth": the camera ports only (as on the hardware station).
ShelfBackend planning in the scene an action was chosen in (Action.scene; fixed inputs), the
controller alone on a rendered image, connected to the hardware station, and wired to the simulated
FetchShelf station until its first action has moved the object it chose; and the `ms-drake scene
FetchShelf` picture with the tool parked out of the front camera's view."""

import dataclasses
import json

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from ms_drake.execution import ExecutionError
from ms_drake.execution.shelf_backend import ShelfBackend, ShelfBody, agreement
from ms_drake.experiments.scene_images import make_scene
from ms_drake.experiments.shelf_physics import (
    action_agreement,
    build_shelf_physics,
    depth_action_outcome,
    physics_records,
    set_initial,
    target_visibility,
)
from ms_drake.experiments.shelf_segmentation import associate
from ms_drake.foss import Foss
from ms_drake.perception.shelf_occupancy import ground_truth_occupancy
from ms_drake.planning import ik_pose
from ms_drake.policies.bin_search import ControllerError, connect_controller
from ms_drake.policies.shelf import ShelfPolicyParams
from ms_drake.policies.shelf_search import (
    FetchFeasibleSelector,
    MakeShelfSearchController,
    ShelfSearchAblation,
    ShelfSearchConfig,
    ShelfSearchSelector,
    ShelfSimulationInfo,
    _unchanged_key,
    refuse_like_unchanged,
    same_scene,
    seen_outcomes,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.scenes.shelf_render import render_shelf_scene
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.types import Action, ActionOutcome, ShelfAction, ShelfObject, ShelfScene

# A tall box in front of the target and a cylinder to its left (the target fully hidden).
OCC = ShelfObject("occ00", "box", 0.0, -0.12, 0.16, 0.08, 0.20)
SIDE = ShelfObject("occ01", "cylinder", -0.18, -0.10, 0.10, 0.10, 0.10)
TARGET = ShelfObject("target", "box", 0.0, 0.02, 0.06, 0.06, 0.06)
SCENE = ShelfScene((OCC, SIDE), TARGET, seed=0)


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, "FetchShelf")


@pytest.fixture(scope="module")
def backend(scenario):
    return ShelfBackend(scenario, {}, "")  # no shelf bodies: as on hardware


@pytest.fixture(scope="module")
def images(scenario):
    """The front camera's depth and rgb images of SCENE (a Drake render), as station port values."""
    r = render_shelf_scene(scenario, SCENE)
    h, w = r.depth.shape
    depth, rgb = ImageDepth32F(w, h), ImageRgba8U(w, h)
    np.asarray(depth.mutable_data)[:, :, 0] = r.depth
    pixels = np.asarray(rgb.mutable_data)
    pixels[:, :, :3] = r.rgb
    pixels[:, :, 3] = 255
    return depth, rgb


def test_backend_plans_in_the_actions_scene(backend):
    # an estimate of OCC (segmenter ids, a little off the truth): the plan follows the estimate
    est = ShelfScene((ShelfObject("seg_0", "cylinder", -0.17, -0.10, 0.09, 0.09, 0.10),
                      ShelfObject("seg_1", "box", 0.01, -0.125, 0.15, 0.07, 0.19)))
    action = Action("shelf", shelf=ShelfAction("push", "seg_1", 0.10), scene=est)
    m = backend.plan(action, backend.initial_commands(), 0, None)
    assert not isinstance(m, str), m
    tl = m.commands["fetch.position"].__self__
    p = ik_pose(backend.blade_ik, tl.value(tl.marks["push"])).translation() - backend.origin
    o = est.objects[1]
    assert p[0] < o.x - o.width / 2 and abs(p[1] - (o.y - o.depth / 2 + 0.0325)) < 2e-3  # beside seg_1's -x side
    assert m.info["before"] is est and m.info["goal_xy"][0] == pytest.approx(o.x + 0.10)
    # the same action in a scene where seg_1 stands 10 cm further left: the blade goes there
    moved = ShelfScene((est.objects[0], o.moved(o.x - 0.10, o.y)))
    m2 = backend.plan(dataclasses.replace(action, scene=moved), backend.initial_commands(), 0, None)
    tl2 = m2.commands["fetch.position"].__self__
    p2 = ik_pose(backend.blade_ik, tl2.value(tl2.marks["push"])).translation() - backend.origin
    assert p2[0] == pytest.approx(p[0] - 0.10, abs=2e-3)
    # no body poses: the outcome is "executed", FOSS agreement not recorded
    out, gone = backend.outcome(action, m, None, 0, ())
    assert out.success and agreement(out) is None and gone == ()
    # neither poses nor a scene: nothing to plan in
    with pytest.raises(ExecutionError, match="Action.scene"):
        backend.plan(dataclasses.replace(action, scene=None), backend.initial_commands(), 0, None)
    assert backend.plan(Action("shelf", shelf=ShelfAction("push", "occ00", 0.1), scene=est),
                        backend.initial_commands(), 0, None).startswith("unknown_object")


def test_depth_controller_alone_fixed_inputs(scenario, images):
    depth, rgb = images
    c = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="bluction_dar", perception="depth"))
    names = {c.get_input_port(i).get_name() for i in range(c.num_input_ports())}
    assert names == {"front.rgb_image", "front.depth_image"}  # no body_poses: the hardware station's ports
    assert isinstance(c.GetSubsystemByName("policy_selector"), FetchFeasibleSelector)
    assert c.backend.bodies == {} and c.perception == "depth"
    ctx = c.CreateDefaultContext()
    c.GetInputPort("front.depth_image").FixValue(ctx, depth)
    c.GetInputPort("front.rgb_image").FixValue(ctx, rgb)
    scene = c.GetOutputPort("scene").Eval(ctx)
    assert scene.target is None and [o.id for o in scene.objects] == ["seg_0", "seg_1"]
    named = associate(scene, SCENE)  # the estimate stands for the two occluders
    assert sorted(o.id for o in named.objects) == ["occ00", "occ01"]
    for o in named.objects:
        t = SCENE.object(o.id)
        assert o.kind == t.kind and abs(o.x - t.x) < 0.01 and abs(o.height - t.height) < 0.01
    occupancy = c.GetOutputPort("occupancy").Eval(ctx)
    assert occupancy.image_x.shape == (640,) and occupancy.image_x.sum() == pytest.approx(1.0, abs=1e-4)
    assert c.GetOutputPort("target_mask").Eval(ctx).sum() == 0  # the target is hidden
    a = c.GetOutputPort("action").Eval(ctx)
    assert a.kind == "shelf" and a.shelf.object_id in ("seg_0", "seg_1") and a.scene == scene
    assert c.backend.feasible(a.shelf, scene) == "ok"
    # FOSS's choice alone: the action carries its scene too
    c2 = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="dar", perception="depth",
                                                                ablation=ShelfSearchAblation(foss_choice=True)))
    assert isinstance(c2.GetSubsystemByName("policy_selector"), ShelfSearchSelector)
    ctx2 = c2.CreateDefaultContext()
    c2.GetInputPort("front.depth_image").FixValue(ctx2, depth)
    c2.GetInputPort("front.rgb_image").FixValue(ctx2, rgb)
    a2 = c2.GetOutputPort("action").Eval(ctx2)
    assert a2.kind == "shelf" and a2.scene == c2.GetOutputPort("scene").Eval(ctx2)


def test_an_action_after_which_the_camera_sees_no_change_is_not_repeated(scenario, backend):
    seen = ShelfScene((OCC, SIDE))  # what a segmenter reports: the occluders, no target
    nudged = ShelfScene((OCC.moved(OCC.x + 0.004, OCC.y), SIDE))
    assert same_scene(seen, nudged) and not same_scene(seen, ShelfScene((OCC.moved(OCC.x + 0.05, OCC.y), SIDE)))
    assert not same_scene(seen, ShelfScene((OCC,)))
    geometry = ShelfGeometry.from_scenario(scenario)
    occupancy = ground_truth_occupancy(geometry, SCENE)
    for judge in (True, False):
        sel = FetchFeasibleSelector("bluction_dar", Foss(geometry), backend, ShelfPolicyParams(), judge_by_scene=judge)
        ctx = sel.CreateDefaultContext()
        sel.GetInputPort("scene").FixValue(ctx, seen)
        sel.GetInputPort("occupancy").FixValue(ctx, occupancy)
        sel.GetInputPort("history").FixValue(ctx, ())
        first = sel.GetOutputPort("action").Eval(ctx)
        assert first.kind == "shelf" and first.scene == seen
        done = ActionOutcome(first, True, message="agree=nan executed (no body_poses)")
        # executed, and the camera sees the same scene: with judge_by_scene the policy moves on
        sel.GetInputPort("history").FixValue(ctx, (done,))
        again = sel.GetOutputPort("action").Eval(ctx)
        assert (again.shelf != first.shelf) == judge
        # nor an action like it (the same object, kind and push direction: the estimate jitters)
        assert (_unchanged_key(again.shelf) != _unchanged_key(first.shelf)) == judge
        # the scene changed after it: the action counts as done, nothing is refused
        (o,) = seen_outcomes((done,), ShelfScene((OCC.moved(OCC.x + 0.1, OCC.y), SIDE)))
        assert o.success
    (o,) = seen_outcomes((done,), nudged)
    assert not o.success and o.message.startswith("no_change_seen")
    foss = Foss(geometry)
    like = refuse_like_unchanged(foss, seen, (o,))
    assert like and {_unchanged_key(r.action.shelf) for r in like} == {_unchanged_key(first.shelf)}
    assert first.shelf.object_id in {r.action.shelf.object_id for r in like}
    assert refuse_like_unchanged(foss, seen, (o, done)) == []  # something changed since


def test_shelf_search_selector_alone_returns_the_policys_action_with_its_scene(scenario):
    seen = ShelfScene((OCC, SIDE))  # what a segmenter reports: the occluders, no target
    geometry = ShelfGeometry.from_scenario(scenario)
    occupancy = ground_truth_occupancy(geometry, SCENE)
    for judge in (False, True):
        sel = ShelfSearchSelector("bluction_dar", Foss(geometry), ShelfPolicyParams(), judge_by_scene=judge)
        ctx = sel.CreateDefaultContext()
        with pytest.raises(ControllerError, match="ShelfSearchSelector.*scene"):
            sel.GetOutputPort("action").Eval(ctx)
        sel.GetInputPort("scene").FixValue(ctx, seen)
        sel.GetInputPort("occupancy").FixValue(ctx, occupancy)
        first = sel.GetOutputPort("action").Eval(ctx)  # history unconnected: the first step
        best = sel.rules.select(seen, occupancy.image_x, ())
        assert first.kind == "shelf" and first == dataclasses.replace(best, scene=seen)
        # executed, and the camera sees the same scene: with judge_by_scene the policy moves on
        sel.GetInputPort("history").FixValue(ctx, (ActionOutcome(first, True, message="agree=nan executed"),))
        again = sel.GetOutputPort("action").Eval(ctx)
        assert again.kind == "shelf" and again.scene == seen and (again.shelf != first.shelf) == judge
    # nothing to act on: "stop", which carries no scene
    sel.GetInputPort("scene").FixValue(ctx, ShelfScene(()))
    sel.GetInputPort("history").FixValue(ctx, ())
    stop = sel.GetOutputPort("action").Eval(ctx)
    assert stop.kind == "stop" and stop.scene is None


def test_depth_controller_bad_inputs(scenario):
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate((OCC, TARGET))}
    with pytest.raises(ControllerError, match="without sim="):
        MakeShelfSearchController(scenario, ShelfSearchConfig(perception="depth"),
                                  sim=ShelfSimulationInfo(bodies, "target"))
    with pytest.raises(ControllerError, match="perception='depth'"):
        MakeShelfSearchController(scenario, ShelfSearchConfig())
    with pytest.raises(ControllerError, match="choose one of ground_truth, learned, depth"):
        ShelfSearchConfig(perception="lidar")
    with pytest.raises(ControllerError, match="observes ground_truth or depth"):
        MakeShelfSearchController(scenario, ShelfSearchConfig(perception="learned"))


def test_depth_controller_connects_to_the_hardware_station(scenario):
    builder = DiagramBuilder()
    hardware = builder.AddSystem(MakeStation(scenario, hardware=True, lcm=DrakeLcm("memq://shelf_depth_controller")))
    assert not hardware.HasOutputPort("body_poses")
    controller = builder.AddSystem(MakeShelfSearchController(scenario, ShelfSearchConfig(perception="depth")))
    connect_controller(builder, controller, hardware)
    diagram = builder.Build()
    for name in ("fetch.position", "fetch_bluction.position", "fetch_bluction.suction"):
        assert diagram.GetSubsystemByName(hardware.get_name()).GetInputPort(name) is not None
    ctx = diagram.CreateDefaultContext()  # every controller input is connected: the action evaluates
    assert controller.GetOutputPort("status").Eval(controller.GetMyContextFromRoot(ctx)).steps == 0


def test_wired_depth_controller_moves_the_object_it_chose(scenario):
    # ~13 s simulated: ~45 s on the shared 2 cores under load, so not marked slow
    params = ShelfSearchConfig(policy="bluction_dar", horizon=1, perception="depth")
    system = build_shelf_physics(scenario, SCENE, params)
    assert system.controller.perception == "depth" and not system.controller.backend.bodies
    sim = Simulator(system.diagram)
    ApplySimulatorConfig(system.scenario.simulator_config, sim)
    ctx = sim.get_mutable_context()
    set_initial(system, ctx, SCENE)
    assert target_visibility(system, ctx) < 0.05
    sim.Initialize()
    action = system.output(ctx, "action")
    assert action.kind == "shelf" and action.scene is not None and action.scene.target is None
    a = action.shelf
    chosen = associate(action.scene, SCENE).objects[[o.id for o in action.scene.objects].index(a.object_id)].id
    assert chosen in ("occ00", "occ01")  # the estimate it chose stands for a true occluder
    k = 0
    while not system.output(ctx, "history") and k < 1200:
        k += 1
        sim.AdvanceTo(k * params.period)
    (out,) = system.output(ctx, "history")
    assert out.success and out.message.startswith("agree=nan"), out.message
    poses = system.station_output(ctx, "body_poses")
    origin = np.asarray(system.scenario.environment.position, float)
    p = poses[system.sim.bodies[chosen].body_index].translation() - origin
    before = SCENE.object(chosen)
    est = action.scene.object(a.object_id)
    if a.kind == "push":  # moved along x by the commanded distance, y kept
        assert np.sign(p[0] - before.x) == np.sign(a.dx) and abs((p[0] - before.x) - a.dx) < 0.03
        assert abs(p[1] - before.y) < 0.02
    else:  # placed where FOSS places the estimate, relative to where the estimate was
        gx, gy = system.controller.backend.foss.placement_center(est, a.dx, a.dy)
        assert abs((p[0] - before.x) - (gx - est.x)) < 0.03 and abs((p[1] - before.y) - (gy - est.y)) < 0.03
    # the other occluder stayed
    other = ({"occ00", "occ01"} - {chosen}).pop()
    q = poses[system.sim.bodies[other].body_index].translation() - origin
    assert np.hypot(q[0] - SCENE.object(other).x, q[1] - SCENE.object(other).y) < 0.02


def test_depth_action_outcome_judges_the_action_with_the_truth(scenario):
    foss = Foss(ShelfGeometry.from_scenario(scenario))
    est = ShelfScene((ShelfObject("seg_0", "cylinder", -0.175, -0.10, 0.09, 0.09, 0.10),
                      ShelfObject("seg_1", "box", 0.005, -0.125, 0.15, 0.07, 0.19)))
    action = Action("shelf", shelf=ShelfAction("push", "seg_1", 0.10), scene=est)
    executed = ActionOutcome(action, True, message="agree=nan executed (no body_poses)")
    before = (SCENE, ())
    # OCC (the true object behind seg_1) moved 10.5 cm along x: FOSS's push of the estimate agrees
    after = (ShelfScene((OCC.moved(OCC.x + 0.105, OCC.y), SIDE), TARGET), ())
    out = depth_action_outcome(executed, before, after, foss)
    assert out.success and agreement(out) is True and "chose=occ00" in out.message
    # it moved 3 cm only, and the cylinder toppled: no agreement
    after = (ShelfScene((OCC.moved(OCC.x + 0.03, OCC.y), SIDE), TARGET), ("occ01",))
    out = depth_action_outcome(executed, before, after, foss)
    assert agreement(out) is False and "toppled=occ01" in out.message
    # an estimate that stands for no occluder
    ghost = ShelfScene((ShelfObject("seg_0", "box", 0.2, 0.15, 0.05, 0.05, 0.05),))
    out = depth_action_outcome(ActionOutcome(dataclasses.replace(
        action, shelf=ShelfAction("push", "seg_0", -0.05), scene=ghost), True), before, before, foss)
    assert agreement(out) is False and "chose=-" in out.message
    rec = {"actions_taken": [["push", "seg_1", 0.1, 0.0], ["push", "seg_0", -0.05, 0.0]],
           "outcomes": [depth_action_outcome(executed, before, (ShelfScene((OCC.moved(0.105, OCC.y), SIDE), TARGET),
                                                                 ()), foss).message, out.message]}
    assert action_agreement(rec) == [("push", True), ("push", False)]
    # not observed after (the run stopped mid-action): no agreement recorded
    assert agreement(depth_action_outcome(executed, before, None, foss)) is None


def test_physics_records_by_perception(tmp_path):
    f = tmp_path / "r.jsonl"
    lines = [{"seed": 1, "policy": "der3", "fidelity": "physics", "perception": p, "steps": k,
              "config": ShelfSearchConfig(policy="der3", perception=p).record()}
             for p, k in (("ground_truth", 2), ("depth", 4))]
    f.write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert [r["steps"] for r in physics_records([f])] == [2, 4]
    assert [r["steps"] for r in physics_records([f], "ground_truth")] == [2]
    assert [r["steps"] for r in physics_records([f], "depth")] == [4]


def test_scene_command_parks_the_tool_out_of_the_front_view(scenario):
    """`ms-drake scene FetchShelf` (make_scene + write_scene_images' station): no pixel of the
    bluction tool nor of the Fetch's arm in the front camera's label image."""
    heap = make_scene(scenario, 0)
    station = MakeStation(scenario_with_heap(scenario, heap))
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, heap)
    label = np.asarray(station.GetOutputPort("front.label_image").Eval(ctx).data)[:, :, 0]
    plant = get_plant(station)
    body_of = lambda i: plant.get_body(BodyIndex(i))
    tool = [i for i in range(plant.num_bodies()) if plant.GetModelInstanceName(body_of(i).model_instance()) == "fetch_bluction"]
    hand = [int(plant.GetBodyByName(n).index()) for n in ("forearm_roll_link", "wrist_flex_link", "wrist_roll_link")]
    assert len(tool) >= 2
    assert np.count_nonzero(np.isin(label, tool + hand)) == 0
    # the scene's objects are in view
    objects = [int(o.body_index) for o in station_objects(plant)]
    assert len(objects) == len(heap.objects) and np.count_nonzero(np.isin(label, objects)) > 2000
