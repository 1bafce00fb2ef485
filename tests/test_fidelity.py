"""The two fidelities on the same grasps (ms_drake.experiments.fidelity): a primitive search's
attempts recorded with their scenes, replayed in full fidelity on the YuMi; PickReach (the
robot's pick plan as a grasp filter) alone and inside the IndexedGraspPlanner."""

import numpy as np
import pytest
import trimesh

from ms_drake.execution.reach import PickReach
from ms_drake.experiments.fidelity import (
    build_replay,
    fidelity_config,
    grasp_cameras,
    picture_strip,
    primitive_attempts,
    replay_full,
    summarize,
    wilson,
)
from ms_drake.geometry import Workspace, as_rigid_transform
from ms_drake.grasping.grasp_sets import APPROACHES, GraspSet
from ms_drake.grasping.indexed import IndexedGraspPlanner, environment_parts
from ms_drake.grasping.planner import ObjectGeometry
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap
from ms_drake.station import get_plant, station_objects
from ms_drake.types import Grasp


@pytest.fixture(scope="module")
def yumi_reach():
    return PickReach(load_scenario(None, "YuMiBin"))


def test_pick_reach_of_the_yumi(yumi_reach):
    # straight down onto the bin's near half: the right arm's jaw and the left arm's cup reach it
    assert yumi_reach(Grasp("parallel_jaw", (-0.1, -0.1, 0.05), (0, 0, -1), axis=(0, 1, 0), width=0.05))
    assert yumi_reach(Grasp("suction", (-0.1, 0.1, 0.05), (0, 0, -1)))
    # the far corner, tilted 43 degrees back towards the robot: beyond the left arm
    a = np.array([-0.68, -0.07, -0.73])
    assert yumi_reach.status(Grasp("suction", (0.2, -0.15, 0.13), tuple(a / np.linalg.norm(a)))) == "unreachable"
    assert (yumi_reach.checks, yumi_reach.reached) == (2, 2)
    panda = PickReach(load_scenario(None, "PandaBin"))
    assert panda.status(Grasp("suction", (0.0, 0.0, 0.05), (0, 0, -1))) == "no_suction_gripper"


def _box(oid, size, xyz):
    m = trimesh.creation.box(extents=size)
    X = np.eye(4)
    X[:3, 3] = xyz
    return ObjectGeometry(oid, np.asarray(m.vertices, float), np.asarray(m.faces), X, 0.1)


def test_indexed_planner_keeps_only_reached_grasps():
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    a = _box("a", (0.04, 0.04, 0.04), (ws.center_xy[0], ws.center_xy[1], ws.floor_z + 0.02))
    axes = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    q = np.zeros((2, APPROACHES))
    q[:, 0] = [1.0, 0.8]
    gs = GraspSet("a", "soft_point", np.zeros((2, 3)), axes, np.tile([0.0, 0.0, -1.0], (2, 1)), np.full(2, 0.06), q,
                  np.array([[0.0, 0.0, 0.02]]), np.array([[0.0, 0.0, 1.0]]), np.array([0.9]))
    seen = []

    def reach(g):  # a robot that reaches only jaw grasps closing along x
        seen.append(g)
        return g.kind == "parallel_jaw" and abs(g.axis[0]) > 0.9

    p = IndexedGraspPlanner({}, {"a": gs}, environment_parts(s), ws, 64, 48, reach=reach)
    out = {g.kind: g for g in p.plan_object("a", {"a": a}, p.scene((a,)))}
    assert set(out) == {"parallel_jaw"} and out["parallel_jaw"].quality == pytest.approx(0.8)
    assert [g.kind for g in seen] == ["parallel_jaw", "parallel_jaw", "suction"]  # best first, then the next
    p1 = IndexedGraspPlanner({}, {"a": gs}, environment_parts(s), ws, 64, 48, reach=reach, max_reach_checks=1)
    assert p1.plan_object("a", {"a": a}, p1.scene((a,))) == ()  # one check per kind: the best only
    with pytest.raises(Exception, match="reach must be a callable"):
        IndexedGraspPlanner({}, {}, (), ws, 64, 48, reach=3)


def test_wilson_and_summary():
    lo, hi = wilson(8, 10)
    assert 0.44 < lo < 0.5 and 0.94 < hi < 0.97
    recs = [{"kind": "attempt", "grasp": "suction", "quality": 0.9, "primitive_lifted": p, "full_lifted": f,
             "full_message": "" if f else "not_lifted", "full_cpu_seconds": 1.0, "full_delivered": d}
            for p, f, d in ((True, True, True), (True, False, None), (False, False, None), (True, True, False))]
    recs.append({"kind": "heap", "primitive_success": True})
    s = summarize(recs)
    assert (s["attempts"], s["primitive"]["k"], s["full"]["k"], s["agreement"]["k"]) == (4, 3, 2, 3)
    assert s["difference_points"] == pytest.approx(25.0) and s["full_failures"] == {"not_lifted": 2}
    assert (s["delivered"]["k"], s["delivered"]["n"]) == (1, 2)  # of the lifted objects, one reached the tray


@pytest.fixture(scope="module")
def attempts4():
    heap = generate_heap(load_scenario(None, "BinHeap15"), 4, seed=3, params=SEARCH_HEAPS)
    attempts, res = primitive_attempts(heap, fidelity_config(4, reach="YuMiBin"), seed=0, max_attempts=2)
    return heap, attempts, res


def test_replay_loads_the_attempt_state_and_grasp(attempts4):
    heap, attempts, res = attempts4
    assert len(attempts) == min(2, res.action_kinds.count("grasp")) and attempts[0].step == 0
    assert attempts[0].removed == () and attempts[0].state.object_names() == heap.object_names()
    # the state is the settled scene: within a few mm of the dropped heap
    assert max(np.linalg.norm(np.subtract(o.q[4:], h.q[4:])) for o, h in
               zip(attempts[0].state.objects, heap.objects)) < 0.02
    if len(attempts) > 1 and attempts[0].primitive_lifted:
        assert len(attempts[1].removed) >= 1  # the first attempt's object is out of the second's scene
    a = attempts[-1]
    simulator, station, executor, backend = build_replay(a)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(simulator.get_context())
    for k, (o, op) in enumerate(zip(station_objects(plant), a.state.objects)):
        X = as_rigid_transform(plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)), "X")
        if k in a.removed:
            assert X.translation()[2] < -4.0  # lifted out before the attempt: away from the scene
        else:
            assert np.allclose(plant.GetPositions(pc, o.model_instance), op.q)
    action = executor.action_port.Eval(executor.GetMyContextFromRoot(simulator.get_context()))
    assert action.kind == "grasp" and action.grasp == a.grasp


@pytest.mark.slow
def test_a_reached_grasp_is_lifted_by_the_yumi(attempts4):
    _, attempts, _ = attempts4
    r = replay_full(attempts[0])
    assert r.lifted and r.message == "" and r.rise > 0.075
    assert r.delivered  # carried on to the tray, out of the bin


def test_pick_reach_keeps_the_arm_clear_of_the_scene(yumi_reach):
    # a straight-down suction grasp the left arm reaches; a box 13-23 cm above the grasp point
    # (above the 11.2 cm suction tool, where the wrist is) blocks it, the same box beside it does not
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    g = Grasp("suction", (-0.1, 0.1, 0.05), (0, 0, -1))
    planner = IndexedGraspPlanner({}, {}, environment_parts(s), ws, 64, 48)
    above = planner.scene((_box("wrist", (0.1, 0.1, 0.1), (-0.1, 0.1, 0.05 + 0.175)),))
    beside = planner.scene((_box("wrist", (0.1, 0.1, 0.1), (0.15, -0.15, 0.05 + 0.175)),))
    assert not planner.scene(()).hits(planner.gripper.suction(g.center, g.approach))
    assert not above.hits(planner.gripper.suction(g.center, g.approach))  # the tool itself is free
    blocked = yumi_reach.arm_blocked
    assert yumi_reach(g) and yumi_reach(g, beside)
    assert not yumi_reach(g, above) and yumi_reach.arm_blocked == blocked + 1


def test_pick_reach_keeps_the_transit_from_park_clear(yumi_reach):
    # a box where the cup passes halfway from park to the pre-grasp blocks the grasp (the grasp's
    # own tool and approach are free); the same box in the bin's far corner, or the bin alone, does not
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    g = Grasp("suction", (-0.1, 0.1, 0.05), (0, 0, -1))
    plan = yumi_reach.plan(g)
    links = yumi_reach.links[plan.arm]
    cup = links.at(plan.timeline.value(0.5 * plan.timeline.marks["approach"]), tool=True)[-1][2]
    planner = IndexedGraspPlanner({}, {}, environment_parts(s), ws, 64, 48)
    on_path = planner.scene((_box("box", (0.03, 0.03, 0.03), cup),))
    aside = planner.scene((_box("box", (0.03, 0.03, 0.03), (0.2, -0.15, ws.floor_z + 0.015)),))  # far corner
    assert not on_path.hits(planner.gripper.suction(g.center, g.approach))
    blocked = yumi_reach.arm_blocked
    assert yumi_reach(g, planner.scene(())) and yumi_reach(g, aside)
    assert not yumi_reach(g, on_path) and yumi_reach.arm_blocked == blocked + 1


def test_pick_reach_checks_the_open_fingers_in_transit(yumi_reach):
    # a small box where the open jaw's left finger passes on its way from park to the pre-grasp of a
    # tilted jaw grasp, clear of the arm's links and the palm: the finger would knock it, so the
    # grasp is not reached (fidelity heap 5092); the same box in the far corner leaves it reached
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    g = Grasp("parallel_jaw", (-0.1, 0.05, 0.06), (0.29, 0.09, -0.95), axis=(0.0, 1.0, 0.0), width=0.03)
    plan = yumi_reach.plan(g)
    assert not isinstance(plan, str) and plan.success
    links = yumi_reach.links[plan.arm]
    names = [b.name() for b, *_ in links.parts + links.tool_parts]
    assert "left_finger" in names and "right_finger" in names
    t = 0.9 * plan.timeline.marks["approach"]
    parts = links.at(plan.timeline.value(t), tool=True)
    finger = next(p for p, n in zip(parts, names) if n == "left_finger")
    others = [p for p, n in zip(parts, names) if "finger" not in n]
    planner = IndexedGraspPlanner({}, {}, environment_parts(s), ws, 64, 48)
    on_path = planner.scene((_box("box", (0.01, 0.01, 0.01), finger[2]),))
    aside = planner.scene((_box("box", (0.01, 0.01, 0.01), (0.2, -0.15, ws.floor_z + 0.005)),))
    assert on_path.hits([finger]) and not on_path.hits(others, yumi_reach.transit_clearance)
    assert yumi_reach(g, aside)
    assert not yumi_reach(g, on_path)


def test_scene_hits_within_a_margin():
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    planner = IndexedGraspPlanner({}, {}, (), ws, 64, 48)
    scene = planner.scene((_box("a", (0.04, 0.04, 0.04), (0.0, 0.0, 0.5)),))
    probe = planner.scene((_box("b", (0.04, 0.04, 0.04), (0.055, 0.0, 0.5)),))  # 1.5 cm apart
    parts = [(sh, T.getRotation(), T.getTranslation(), r) for sh, T, r in zip(probe.shapes, probe.transforms, probe.radii)]
    assert not scene.hits(parts) and not scene.hits(parts, margin=0.01)
    assert scene.hits(parts, margin=0.02)


def test_grasp_cameras_look_at_the_grasp_from_two_sides():
    c = np.array([0.05, -0.02, 0.1])
    cams = grasp_cameras(c, distance=0.5)
    assert set(cams) == {"grasp_x", "grasp_y"}
    sides = []
    for cam in cams.values():
        X = cam.X_PB.GetDeterministicValue()
        R, p = X.rotation().matrix(), X.translation()
        assert np.isclose(np.linalg.norm(p - c), 0.5)
        assert np.allclose(R[:, 2], (c - p) / 0.5, atol=1e-9)  # +z (the optical axis) at the grasp
        assert np.isclose(np.degrees(np.arcsin(-R[2, 2])), 45.0)  # 45 degrees down
        assert R[2, 0] == pytest.approx(0.0, abs=1e-9) and R[2, 1] < 0  # level horizon, image +y down
        sides.append(np.sign(np.round(p[:2] - c[:2], 6)))
    assert {tuple(s) for s in sides} == {(1.0, 0.0), (0.0, -1.0)}


def test_a_filmed_replay_renders_the_grasp_and_makes_a_picture(attempts4):
    _, attempts, _ = attempts4
    r = replay_full(attempts[0], max_sim_time=0.45, film=True)
    assert [round(t, 2) for t, _ in r.frames] == [0.2, 0.4]
    for _, images in r.frames:
        assert set(images) == {"grasp_x", "grasp_y"}
        for im in images.values():
            assert im.shape == (240, 320, 3) and im.std() > 10  # a rendered scene, not a blank image
    pic = picture_strip(r.frames, "title")
    assert pic.shape == (30 + 2 * 240, 2 * 320, 3)
    with pytest.raises(ValueError, match="no frames"):
        picture_strip((), "title")
