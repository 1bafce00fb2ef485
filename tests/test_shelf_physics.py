"""Shelf search on the Fetch in physics: ShelfBackend alone (plans reach the commanded poses),
ShelfSceneObserver alone (fixed body poses) and wired to the FetchShelf station, MakeShelfSearchController
alone (fixed inputs) and wired to the FetchShelf station (one push moves the pushed object along x),
bad inputs."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from ms_drake.execution import ExecutionError
from ms_drake.execution.shelf_backend import (
    BLADE_DOWN,
    BLADE_UP,
    ShelfBackend,
    ShelfBody,
    agreement,
    observe,
)
from ms_drake.experiments.shelf_physics import (
    build_shelf_physics,
    set_initial,
    target_visibility,
)
from ms_drake.planning import ik_pose
from ms_drake.policies.bin_search import ControllerError
from ms_drake.policies.shelf_search import (
    MakeShelfSearchController,
    ShelfSceneObserver,
    ShelfSearchConfig,
    ShelfSimulationInfo,
)
from ms_drake.scenario import load_scenario
from ms_drake.types import Action, ShelfAction, ShelfObject, ShelfScene

OCC = ShelfObject("occ00", "box", 0.0, -0.12, 0.16, 0.08, 0.20)
SIDE = ShelfObject("occ01", "cylinder", -0.18, -0.10, 0.10, 0.10, 0.10)
TARGET = ShelfObject("target", "box", 0.0, 0.02, 0.06, 0.06, 0.06)
SCENE = ShelfScene((OCC, SIDE), TARGET, seed=0)


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, "FetchShelf")


@pytest.fixture(scope="module")
def backend(scenario):
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate((OCC, SIDE, TARGET))}
    return ShelfBackend(scenario, bodies, "target")


def _poses(objs):
    return [RigidTransform([o.x, o.y, o.height / 2]) for o in objs]


def test_observe_reads_footprints_and_toppled():
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate((OCC, TARGET))}
    X = _poses((OCC, TARGET))
    scene, toppled = observe(X, bodies, (0, 0, 0), "target")
    assert scene.target.id == "target" and [o.id for o in scene.objects] == ["occ00"] and toppled == ()
    from pydrake.math import RollPitchYaw
    X[0] = RigidTransform(RollPitchYaw(np.pi / 2, 0, 0), [0.0, -0.1, 0.04])
    scene, toppled = observe(X, bodies, (0, 0, 0), "target")
    assert toppled == ("occ00",) and abs(scene.objects[0].height - OCC.depth) < 1e-9


def test_backend_plans_push_to_the_commanded_pose(backend):
    poses = _poses((OCC, SIDE, TARGET))
    m = backend.plan(Action("shelf", shelf=ShelfAction("push", "occ00", 0.10)), backend.initial_commands(), 0, poses)
    assert not isinstance(m, str), m
    tl = m.commands["fetch.position"].__self__
    # The blade's centre at the push's start: beside occ00's trailing (-x) side, along its front part.
    X = ik_pose(backend.blade_ik, tl.value(tl.marks["push"]))
    p = X.translation()
    assert p[0] < OCC.x - OCC.width / 2 and abs(p[1] - (OCC.y - OCC.depth / 2 + 0.0325)) < 2e-3
    Xe = ik_pose(backend.blade_ik, tl.value(tl.marks["pushed"]))
    assert Xe.translation()[0] - p[0] > 0.10 - 2e-3  # pushed at least dx along +x
    assert np.allclose(tl.final(), backend.q_park, atol=1e-6)  # parked again
    assert m.commands["fetch_bluction.position"](1.0)[0] == BLADE_DOWN
    assert m.info["foss"] == "ok" and m.info["goal_xy"][0] == pytest.approx(OCC.x + 0.10)


def test_backend_plans_suction_to_the_front_face(backend):
    poses = _poses((OCC, SIDE, TARGET))
    a = ShelfAction("suction", "occ01", 0.35, 0.0)
    m = backend.plan(Action("shelf", shelf=a), backend.initial_commands(), 0, poses)
    assert not isinstance(m, str), m
    tl = m.commands["fetch.position"].__self__
    p = ik_pose(backend.cup_ik, tl.value(tl.marks["contact"])).translation()
    assert np.allclose(p, [SIDE.x, SIDE.y - SIDE.depth / 2 - 0.002, SIDE.height - 0.02], atol=2e-3)
    placed = ik_pose(backend.cup_ik, tl.value(tl.marks["placed"])).translation()
    gx, gy = backend.foss.placement_center(SIDE, a.dx, a.dy)
    assert abs(placed[0] - gx) < 2e-3 and abs(placed[1] - (gy - SIDE.depth / 2 - 0.002)) < 2e-3
    vac = m.commands["fetch_bluction.suction"]
    assert vac(0.0)[0] == 0.0 and vac(tl.marks["contact"])[0] == 1.0 and vac(tl.duration)[0] == 0.0
    assert m.commands["fetch_bluction.position"](1.0)[0] == BLADE_UP


def test_backend_outcome_agreement(backend):
    poses = _poses((OCC, SIDE, TARGET))
    action = Action("shelf", shelf=ShelfAction("push", "occ00", 0.10))
    m = backend.plan(action, backend.initial_commands(), 0, poses)
    moved = _poses((OCC.moved(OCC.x + 0.105, OCC.y), SIDE, TARGET))
    out, gone = backend.outcome(action, m, moved, 0, ())
    assert out.success and agreement(out) is True and gone == ()
    out, _ = backend.outcome(action, m, _poses((OCC.moved(OCC.x + 0.03, OCC.y), SIDE, TARGET)), 0, ())
    assert not out.success and agreement(out) is False


def test_backend_bad_inputs(scenario, backend):
    with pytest.raises(ExecutionError, match="kind 'shelf'"):
        backend.plan(Action("push"), backend.initial_commands(), 0, _poses((OCC, SIDE, TARGET)))
    with pytest.raises(ExecutionError, match="body_poses"):
        backend.plan(Action("shelf", shelf=ShelfAction("push", "occ00", 0.1)), backend.initial_commands(), 0, None)
    assert backend.plan(Action("shelf", shelf=ShelfAction("push", "nope", 0.1)), backend.initial_commands(), 0,
                        _poses((OCC, SIDE, TARGET))).startswith("unknown_object")
    with pytest.raises(ExecutionError, match="Fetch"):
        ShelfBackend(load_scenario(None, "YuMiBin"), {}, "")
    with pytest.raises(ExecutionError, match="target_id"):
        ShelfBackend(scenario, {}, "target")


def test_scene_observer_alone_reads_the_body_poses():
    origin = (0.8, -0.1, 0.45)  # the shelf floor's centre in world
    bodies = {o.id: ShelfBody(k + 1, o) for k, o in enumerate((OCC, SIDE, TARGET))}  # body 0: the world
    observer = ShelfSceneObserver(ShelfSimulationInfo(bodies, "target"), origin)
    ctx = observer.CreateDefaultContext()
    with pytest.raises(ControllerError, match="connect body_poses"):
        observer.GetOutputPort("scene").Eval(ctx)
    moved = OCC.moved(OCC.x + 0.05, OCC.y - 0.02)
    poses = [RigidTransform()] + [RigidTransform(np.add(origin, [o.x, o.y, o.height / 2]))
                                  for o in (moved, SIDE, TARGET)]
    observer.GetInputPort("body_poses").FixValue(ctx, poses)
    scene = observer.GetOutputPort("scene").Eval(ctx)
    assert [o.id for o in scene.objects] == ["occ00", "occ01"] and scene.target.id == "target"
    for got, want in zip(scene.objects + (scene.target,), (moved, SIDE, TARGET)):
        assert got.kind == want.kind and (got.width, got.depth, got.height) == (want.width, want.depth, want.height)
        assert (got.x, got.y) == (pytest.approx(want.x, abs=1e-12), pytest.approx(want.y, abs=1e-12))
    # toppled onto its side (90 degrees about x): its footprint is the rotated box
    from pydrake.math import RollPitchYaw

    poses[1] = RigidTransform(RollPitchYaw(np.pi / 2, 0, 0), np.add(origin, [0.1, -0.1, OCC.depth / 2]))
    observer.GetInputPort("body_poses").FixValue(ctx, poses)
    lying = observer.GetOutputPort("scene").Eval(ctx).object("occ00")
    assert (lying.x, lying.y) == (pytest.approx(0.1), pytest.approx(-0.1))
    assert (lying.width, lying.depth, lying.height) == (pytest.approx(OCC.width), pytest.approx(OCC.height),
                                                        pytest.approx(OCC.depth))


def test_scene_observer_wired_to_the_station(scenario):
    """In the simulated station's diagram the observer reads the plant's body poses: the objects
    where set_initial put them, and where an object is moved to."""
    system = build_shelf_physics(scenario, SCENE, ShelfSearchConfig(policy="dar"))
    observer = system.controller.GetSubsystemByName("scene_observer")
    assert isinstance(observer, ShelfSceneObserver)
    ctx = system.diagram.CreateDefaultContext()
    set_initial(system, ctx, SCENE)
    octx = observer.GetMyContextFromRoot(ctx)
    scene = observer.GetOutputPort("scene").Eval(octx)
    assert [o.id for o in scene.objects] == ["occ00", "occ01"] and scene.target.id == "target"
    for got, want in zip(scene.objects + (scene.target,), SCENE.objects + (SCENE.target,)):
        assert abs(got.x - want.x) < 1e-9 and abs(got.y - want.y) < 1e-9 and got.kind == want.kind
    assert system.controller.GetOutputPort("scene").Eval(system.controller.GetMyContextFromRoot(ctx)) == scene
    pc = system.plant.GetMyMutableContextFromRoot(ctx)
    body = system.plant.get_body(BodyIndex(system.sim.bodies["occ01"].body_index))
    origin = np.asarray(scenario.environment.position, float)
    system.plant.SetFreeBodyPose(pc, body, RigidTransform(origin + [0.2, -0.05, SIDE.height / 2]))
    side = observer.GetOutputPort("scene").Eval(octx).object("occ01")
    assert (side.x, side.y) == (pytest.approx(0.2), pytest.approx(-0.05))


def test_controller_alone_fixed_inputs(scenario):
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate((OCC, SIDE, TARGET))}
    c = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="dar"), sim=ShelfSimulationInfo(bodies, "target"))
    names = {c.get_input_port(i).get_name() for i in range(c.num_input_ports())}
    assert names == {"front.rgb_image", "front.depth_image", "body_poses"}
    outs = {c.get_output_port(i).get_name() for i in range(c.num_output_ports())}
    assert {"fetch.position", "fetch_bluction.position", "fetch_bluction.suction", "action", "history"} <= outs
    ctx = c.CreateDefaultContext()
    c.GetInputPort("body_poses").FixValue(ctx, _poses((OCC, SIDE, TARGET)))
    c.GetInputPort("front.rgb_image").FixValue(ctx, ImageRgba8U(640, 480))
    c.GetInputPort("front.depth_image").FixValue(ctx, ImageDepth32F(640, 480))
    a = c.GetOutputPort("action").Eval(ctx)
    assert a.kind == "shelf" and a.shelf.kind == "push" and a.shelf.object_id == "occ00"
    assert c.GetOutputPort("scene").Eval(ctx).target.id == "target"
    assert np.allclose(c.GetOutputPort("fetch.position").Eval(ctx), c.initial_commands()["fetch.position"])


def test_controller_bad_inputs(scenario):
    with pytest.raises(ControllerError, match="sim="):
        MakeShelfSearchController(scenario, ShelfSearchConfig())
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate((OCC, TARGET))}
    with pytest.raises(ControllerError, match="camera"):
        MakeShelfSearchController(scenario, ShelfSearchConfig(camera="overhead"), sim=ShelfSimulationInfo(bodies))
    with pytest.raises(ControllerError, match="target_id"):
        ShelfSimulationInfo(bodies, "nope")
    with pytest.raises(ControllerError, match="horizon"):
        ShelfSearchConfig(horizon=0)
    with pytest.raises(Exception, match="unknown shelf policy"):
        ShelfSearchConfig(policy="xray")


@pytest.mark.slow  # ~15 s of simulated time: 20-50 s on the shared 2 cores
def test_wired_push_moves_the_object_along_x(scenario):
    params = ShelfSearchConfig(policy="dar", horizon=1)
    system = build_shelf_physics(scenario, ShelfScene((OCC,), TARGET, 0), params)
    sim = Simulator(system.diagram)
    ApplySimulatorConfig(system.scenario.simulator_config, sim)
    ctx = sim.get_mutable_context()
    set_initial(system, ctx, ShelfScene((OCC,), TARGET, 0))
    assert target_visibility(system, ctx) < 0.05  # hidden, and the parked tool is out of view
    sim.Initialize()
    a = system.output(ctx, "action").shelf
    assert a.kind == "push" and a.object_id == "occ00"
    k = 0
    while not system.output(ctx, "history") and k < 800:
        k += 1
        sim.AdvanceTo(k * params.period)
    (out,) = system.output(ctx, "history")
    X = system.station_output(ctx, "body_poses")[system.sim.bodies["occ00"].body_index]
    dx = X.translation()[0] - OCC.x
    assert out.success and np.sign(dx) == np.sign(a.dx) and abs(dx - a.dx) < 0.03, out.message
    assert abs(X.translation()[1] - OCC.y) < 0.02
