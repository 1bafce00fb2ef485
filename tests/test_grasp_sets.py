"""Grasp sets (ms_drake.grasping.grasp_sets) and the IndexedGraspPlanner that indexes them."""

import numpy as np
import pytest
import trimesh
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.geometry import Workspace
from ms_drake.grasping.grasp import GraspError
from ms_drake.grasping.grasp_sets import (
    APPROACHES,
    GraspSet,
    compute_grasp_set,
    grasp_set_params,
    grasp_set_path,
    load_grasp_set,
)
from ms_drake.grasping.indexed import IndexedGraspPlanner, environment_parts, jaw_parts
from ms_drake.grasping.planner import LazyGrasps
from ms_drake.scenario import load_scenario
from ms_drake.types import InstanceMasks, ObjectGeometry


def test_grasp_set_of_a_box_round_trips_and_rates_the_graspable_side(tmp_path):
    name = "procedural/box_000"  # 17 x 11.5 x 6.2 cm: only the 6.2 cm side fits the 10 cm jaw
    gs = compute_grasp_set(name, jaw=30, suction=30, robust_samples=2)
    assert len(gs.jaw_center) == 30 and len(gs.suction_point) == 30
    assert gs.jaw_quality.shape == (30, APPROACHES) and gs.suction_quality.shape == (30,)
    assert np.all((gs.jaw_quality >= 0) & (gs.jaw_quality <= 1)) and gs.jaw_quality.max() > 0.5
    # every jaw axis spans the 6.2 cm side (object z): the others do not fit
    assert np.all(np.abs(gs.jaw_axis[:, 2]) > 0.8)
    # approaches are orthogonal to the axis
    assert np.allclose(np.einsum("nkd,nd->nk", gs.jaw_approaches(), gs.jaw_axis), 0, atol=1e-9)
    path = grasp_set_path(name, tmp_path)
    gs.save(path)
    back = GraspSet.load(path)
    assert back.object == name and back.params == gs.params
    assert np.abs(back.jaw_center - gs.jaw_center).max() < 2e-4
    assert np.abs(back.jaw_quality - gs.jaw_quality).max() <= 0.005
    assert np.allclose(np.einsum("nd,nd->n", back.jaw_ref, back.jaw_axis), 0, atol=1e-9)
    assert load_grasp_set(name, tmp_path) is not None and load_grasp_set("procedural/box_001", tmp_path) is None
    # a flat top of the box is a good suction grasp: some suction quality is high
    assert gs.suction_quality.max() >= 0.75


def test_grasp_set_errors_name_the_value():
    with pytest.raises(GraspError, match="nope"):
        grasp_set_params(model="nope")
    with pytest.raises(GraspError, match="robust_samples"):
        grasp_set_params(robust_samples=0)
    with pytest.raises(GraspError, match="<set>/<name>"):
        grasp_set_path("box_000")


def test_data_grasps_command_writes_and_resumes(tmp_path):
    from typer.testing import CliRunner

    from ms_drake.cli import app

    args = ["data", "grasps", "--objects", "procedural", "--limit", "2", "--jaw", "5", "--suction", "5",
            "--robust", "1", "--out", str(tmp_path)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    # one pack per set, the per-object files removed; both objects read back from it
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == ["pack.npz"]
    assert (tmp_path / "README.md").read_text().count("ms-drake data grasps --objects procedural") == 1
    for name in ("procedural/box_000", "procedural/cylinder_001"):
        gs = load_grasp_set(name, tmp_path)
        assert gs is not None and gs.params["jaw"] == 5 and np.all(gs.suction_quality > 0)
    stamp = (tmp_path / "pack.npz").stat().st_mtime_ns
    r = CliRunner().invoke(app, args)  # resume: nothing recomputed, the pack kept
    assert r.exit_code == 0 and (tmp_path / "pack.npz").stat().st_mtime_ns == stamp
    r = CliRunner().invoke(app, ["data", "grasps", "--objects", "nothing"])
    assert r.exit_code != 0 and "nothing" in r.output


# --------------------------------------------------------------------------- the indexed planner
def _box_geometry(oid, size, xyz, mass=0.1):
    m = trimesh.creation.box(extents=size)
    X = np.eye(4)
    X[:3, 3] = xyz
    return ObjectGeometry(oid, np.asarray(m.vertices, float), np.asarray(m.faces), X, mass)


def _jaw_set(name, axes, qualities):
    """A hand-made grasp set: jaw grasps at the object origin along `axes`, approach 0 = -z."""
    n = len(axes)
    axes = np.asarray(axes, float)
    refs = np.tile([0.0, 0.0, -1.0], (n, 1))
    q = np.zeros((n, APPROACHES))
    q[:, 0] = qualities
    return GraspSet(name, "soft_point", np.zeros((n, 3)), axes, refs, np.full(n, 0.06), q,
                    np.array([[0.0, 0.0, 0.02]]), np.array([[0.0, 0.0, 1.0]]), np.array([0.9]))


@pytest.fixture(scope="module")
def bin_scene():
    s = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(s)
    cx, cy = ws.center_xy
    z = ws.floor_z
    a = _box_geometry("a", (0.04, 0.04, 0.04), (cx, cy, z + 0.02))
    # b: a tall box 2 cm beside a along +y, where a y-axis jaw's finger would go
    b = _box_geometry("b", (0.08, 0.03, 0.08), (cx, cy + 0.02 + 0.02 + 0.015, z + 0.04))
    return s, ws, a, b


def _planner(s, ws, sets, **kw):
    return IndexedGraspPlanner({}, sets, environment_parts(s), ws, 64, 48, **kw)


def test_a_grasp_through_a_neighbour_is_dropped_a_free_one_kept(bin_scene):
    s, ws, a, b = bin_scene
    # grasp 0 (quality 1.0) closes along y: its +y finger goes into b; grasp 1 (0.8) along x is free
    sets = {"a": _jaw_set("a", [[0, 1, 0], [1, 0, 0]], [1.0, 0.8])}
    p = _planner(s, ws, sets)
    geoms = {"a": a, "b": b}
    scene = p.scene((a, b))
    out = {g.kind: g for g in p.plan_object("a", geoms, scene)}
    jaw = out["parallel_jaw"]
    assert jaw.quality == pytest.approx(0.8) and np.allclose(jaw.axis, [1, 0, 0])
    assert np.allclose(jaw.center, a.X_WO[:3, 3]) and np.allclose(jaw.approach, [0, 0, -1])
    # the suction grasp on a's top (approach straight down) is free
    assert out["suction"].quality == pytest.approx(0.9) and np.allclose(out["suction"].approach, [0, 0, -1])
    # without b the best grasp (along y) is kept
    out = {g.kind: g for g in p.plan_object("a", {"a": a}, p.scene((a,)))}
    assert out["parallel_jaw"].quality == pytest.approx(1.0) and np.allclose(out["parallel_jaw"].axis, [0, 1, 0])
    # the jaw geometry really reaches into b: the outer face of grasp 0's +y finger is past b's near face
    fingers = jaw_parts(a.X_WO[:3, 3], [0, 1, 0], [0, 0, -1], 0.06, p.jaw, 0.0)[1:]
    half = 0.5 * (p.jaw.pads.thickness + p.jaw.finger_thickness)
    assert max(f[2][1] for f in fingers) + half > b.X_WO[1, 3] - 0.015


def test_suction_ties_go_to_the_point_nearest_the_centre_of_mass(bin_scene):
    s, ws, a, _ = bin_scene
    gs = _jaw_set("a", [[1, 0, 0]], [0.0])
    # two suction points of equal quality on a's top: 1.5 cm off its centre first, then at it
    gs = GraspSet("a", gs.model, gs.jaw_center, gs.jaw_axis, gs.jaw_ref, gs.jaw_width, gs.jaw_quality,
                  np.array([[0.015, 0.0, 0.02], [0.0, 0.0, 0.02]]), np.array([[0.0, 0.0, 1.0]] * 2), np.array([0.9, 0.9]))
    p = _planner(s, ws, {"a": gs})
    (suction,) = p.plan_object("a", {"a": a}, p.scene((a,)))
    assert np.allclose(suction.center, a.X_WO[:3, 3] + [0, 0, 0.02]) and suction.quality == pytest.approx(0.9)
    # a better quality still comes first, wherever it is
    gs.suction_quality[0] = 1.0
    (suction,) = p.plan_object("a", {"a": a}, p.scene((a,)))
    assert np.allclose(suction.center, a.X_WO[:3, 3] + [0.015, 0, 0.02])


def test_out_of_reach_and_buried_grasps_are_dropped(bin_scene):
    s, ws, a, b = bin_scene
    # a turned upside down (rotation about x by pi): approach 0 now points up, beyond any tilt
    flipped = ObjectGeometry("a", a.vertices, a.faces, a.X_WO @ np.diag([1.0, -1.0, -1.0, 1.0]), a.mass)
    sets = {"a": _jaw_set("a", [[1, 0, 0]], [1.0])}
    sets["a"].jaw_quality[0] = [1.0, 0.0, 0.0, 0.0]  # only approach 0 is any good
    p = _planner(s, ws, sets)
    assert p.plan_object("a", {"a": flipped}, p.scene((flipped,))) == ()
    # a box lying on a's top: the suction cup has no room; the jaw's palm hits it
    lid = _box_geometry("lid", (0.1, 0.1, 0.01), a.X_WO[:3, 3] + [0, 0, 0.0251])
    assert p.plan_object("a", {"a": a, "lid": lid}, p.scene((a, lid))) == ()
    with pytest.raises(GraspError, match="max_tilt"):
        _planner(s, ws, sets, max_tilt=2.0)
    with pytest.raises(GraspError, match="kinds"):
        _planner(s, ws, sets, kinds=("magnet",))


def test_a_grasp_whose_way_down_is_blocked_is_dropped(bin_scene):
    s, ws, a, _ = bin_scene
    sets = {"a": _jaw_set("a", [[1, 0, 0]], [0.0])}  # suction only: the cup on a's top, straight down
    p = _planner(s, ws, sets)
    top = a.X_WO[:3, 3] + [0, 0, 0.02]
    assert len(p.plan_object("a", {"a": a}, p.scene((a,)))) == 1
    # a plate 15 cm above a's top: clear of the cup and its 10 cm stem at the grasp, in the way
    # of the stem on the approach (the pre-grasp is PICK_APPROACH.distance back along it)
    plate = _box_geometry("plate", (0.1, 0.1, 0.01), top + [0, 0, 0.155])
    assert not p.scene((a, plate)).hits(p.gripper.suction(top, [0, 0, -1]))
    assert p.plan_object("a", {"a": a, "plate": plate}, p.scene((a, plate))) == ()
    # higher up, 35 cm above: in the way of the straight descent to the pre-grasp
    plate = _box_geometry("plate", (0.1, 0.1, 0.01), top + [0, 0, 0.35])
    assert p.plan_object("a", {"a": a, "plate": plate}, p.scene((a, plate))) == ()
    # beside the column, 3 cm clear of it: kept
    plate = _box_geometry("plate", (0.1, 0.1, 0.01), top + [0.05 + 0.015 + 0.03, 0, 0.155])
    assert len(p.plan_object("a", {"a": a, "plate": plate}, p.scene((a, plate)))) == 1


def test_indexed_planner_alone_through_its_ports(bin_scene):
    s, ws, a, b = bin_scene
    sets = {"a": _jaw_set("a", [[0, 1, 0], [1, 0, 0]], [1.0, 0.8])}
    p = _planner(s, ws, sets)
    ctx = p.CreateDefaultContext()
    masks = InstanceMasks(np.ones((3, 48, 64), bool), ("a", "b", "c"), np.ones(3))
    p.GetInputPort("depth_image").FixValue(ctx, ImageDepth32F(64, 48))
    p.GetInputPort("masks").FixValue(ctx, masks)
    p.GetInputPort("objects").FixValue(ctx, (a, b))
    out = p.GetOutputPort("grasps").Eval(ctx)
    assert isinstance(out, LazyGrasps) and out.planned == ()
    g = out["a"]  # the best over the jaw (0.8, free) and the suction cup (0.9)
    assert (g.kind, g.object_id, g.quality) == ("suction", "a", pytest.approx(0.9))
    assert "b" not in out and "c" not in out  # no grasp set and no fallback: no grasp
    assert set(out.planned) == {"a", "b", "c"}


def test_indexed_planner_wired_in_the_search_diagram():
    """The search diagram holds the IndexedGraspPlanner; on a heap of objects with committed grasp
    sets, the grasp it gives an object is one of the set's at the object's pose, its jaw free of
    every other object."""
    from pydrake.systems.analysis import Simulator

    from ms_drake.experiments.heap_grasps import (
        grasp_collisions,
        heap_grasp_inputs,
        scene_shapes,
    )
    from ms_drake.experiments.rollout import build_search
    from ms_drake.policies.bin_search import load_bin_search_config, set_initial_conditions
    from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap

    heap = generate_heap(load_scenario(None, "BinHeap15"), 4, seed=3, params=SEARCH_HEAPS)
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap,
                          load_bin_search_config("ch7", policy="largest", seed=5))
    gp = system.controller.GetSubsystemByName("grasp_planner")
    assert isinstance(gp, IndexedGraspPlanner) and len(gp.sets) == len(heap.objects)
    ctx = Simulator(system.diagram).get_mutable_context()
    set_initial_conditions(system.diagram, ctx, heap)
    grasps = system.output(ctx, "grasps")
    action = system.output(ctx, "action")
    assert action.kind == "grasp" and action.grasp.object_id in grasps.planned
    inputs = heap_grasp_inputs(load_scenario(None, "BinHeap15"), heap)
    shapes = scene_shapes(load_scenario(None, "BinHeap15"), inputs)
    geoms = {o.id: o for o in inputs.objects}
    for oid, g in dict(grasps).items():
        gs = gp.sets[oid]
        X = geoms[oid].X_WO
        pts = (gs.jaw_center if g.kind == "parallel_jaw" else gs.suction_point) @ X[:3, :3].T + X[:3, 3]
        assert np.linalg.norm(pts - np.asarray(g.center), axis=1).min() < 0.003  # a set grasp (bodies settle)
        if g.kind == "parallel_jaw":
            assert grasp_collisions(g, [sh for sh in shapes if sh[0] != oid], 0.002) == set()
    # the image-based planner stays an option
    image = build_search(load_scenario(None, "FloatingGripperBin"), heap,
                         load_bin_search_config("ch7", policy="largest", seed=5, grasp_planner="image"))
    assert not isinstance(image.controller.GetSubsystemByName("grasp_planner"), IndexedGraspPlanner)
