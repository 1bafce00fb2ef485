"""Jaw GraspPlanner (soft point, as in the bin-search rollouts) on a real 5-object bin heap:
sensible qualities on the graspable objects, jaws clear of the neighbours and the bin (exact
check with coal on the objects' collision primitives), and one chosen grasp lifts its object in
the hydroelastic physics of simulate_grasp. Plus the depth sampler's clearance rules on
synthetic depth images."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from ms_drake.experiments.heap_grasps import grasp_collisions, heap_grasp_inputs, heap_grasp_report, scene_shapes
from ms_drake.grasping.planner import GraspPlanner
from ms_drake.grasping.samplers import sample_antipodal_grasps_depth
from test_grasp_samplers import _render_depth, overhead_camera, pose_xyz_yaw

# generate_heap(load_scenario(None, "BinHeap15"), 5, seed=3), saved so that the test does not
# depend on the heap generator's version: 5 objects, 4 graspable-sized and >= 50 % visible
# (three boxes, one lying on another, and an upright cylinder).
HEAP = Path(__file__).parent / "data" / "grasp_heap_5_seed3.json"
HEAP_SEED = 3


@pytest.fixture(scope="module")
def heap_rows():
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import load_heap

    s = load_scenario(None, "BinHeap15")
    inputs = heap_grasp_inputs(s, load_heap(HEAP))
    planner = GraspPlanner(inputs.camera_info, inputs.X_WC, model="soft_point", num_samples=8, robust_samples=4,
                           seed=HEAP_SEED)
    return s, inputs, heap_grasp_report(inputs, planner, diagnose=False, scenario=s)


def test_jaw_planner_on_heap_graspable_objects_and_collision_free(heap_rows):
    _, inputs, rows = heap_rows
    assert len(rows) == len(inputs.masks) == 5
    # (name, graspable size, >= 50 % visible, robust quality over 4 samples): the box lying on
    # another (box_231) has no grasp that holds; the rest hold in every sample.
    assert [(r["name"], r["graspable_size"], r["visible"] >= 0.5, r["quality"]) for r in rows] == [
        ("procedural/cylinder_391", True, True, 1.0),
        ("procedural/packaged_101", False, True, 0.0),
        ("procedural/box_231", True, True, 0.0),
        ("procedural/box_162", True, True, 1.0),
        ("procedural/box_309", True, True, 1.0),
    ]
    for r in rows:  # every object gets a top-down grasp whose jaws clear the neighbours and the bin
        g = r["grasp"]
        assert g is not None and r["collides"] == [], (r["name"], r["collides"])
        assert np.allclose(g.approach, [0, 0, -1]) and abs(g.axis[2]) < 1e-9 and g.width <= 0.1 + 1e-12


def test_chosen_heap_grasp_lifts_in_physics(heap_rows):
    from ms_drake.grasping import ParallelJawGrasp
    from ms_drake.grasping.physics import simulate_grasp

    _, inputs, rows = heap_rows
    geoms = {o.id: o for o in inputs.objects}
    best = max((r for r in rows if r["name"].split("/")[1].startswith("box")), key=lambda r: r["quality"])
    assert best["quality"] >= 0.5
    o = geoms[best["id"]]
    mesh = trimesh.Trimesh(o.vertices, o.faces)
    out = simulate_grasp(mesh, o.X_WO, ParallelJawGrasp.from_grasp(best["grasp"]), o.mass)
    assert out.contact and out.success, out


def test_collision_check_sees_a_jaw_inside_a_neighbour(heap_rows):
    s, inputs, rows = heap_rows
    shapes = scene_shapes(s, inputs)
    r = next(r for r in rows if r["grasp"] is not None and r["quality"] > 0.15)
    other = next(o for o in inputs.objects if o.id != r["id"])
    from dataclasses import replace

    g = r["grasp"]
    # the same jaw moved so that its tool point sits at the neighbour's origin
    moved = replace(g, center=tuple(np.asarray(other.X_WO)[:3, 3]))
    assert other.id in grasp_collisions(moved, shapes)
    low = replace(g, center=tuple(np.asarray(g.center) - [0, 0, 0.2]))
    assert "bin" in grasp_collisions(low, shapes)


def _floor_depth(K, X_WC, h, w, z=0.0):
    """Depth of the plane z = `z` seen by the overhead test camera (looking straight down)."""
    return np.full((h, w), X_WC[2, 3] - z)


def test_depth_sampler_keeps_fingers_off_a_tall_neighbour():
    K, X_WC = overhead_camera()
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.03))
    wall = trimesh.creation.box(extents=(0.02, 0.12, 0.05))
    X_box = pose_xyz_yaw(0.0, 0.0, 0.015, 0.0)
    X_wall = pose_xyz_yaw(0.035, 0.0, 0.025, 0.0)  # 5 mm beside the box's +x face, 2 cm taller
    d_box = _render_depth(box, X_box, K, X_WC, 96, 128)
    d_wall = _render_depth(wall, X_wall, K, X_WC, 96, 128)
    depth = np.minimum(np.minimum(d_box, d_wall), _floor_depth(K, X_WC, 96, 128))
    mask = np.isfinite(d_box) & (d_box <= d_wall)
    gs = sample_antipodal_grasps_depth(depth, K, X_WC, mask, 10, friction=0.5, seed=0)
    assert len(gs) >= 3
    for g in gs:
        assert abs(g.axis[0]) < 0.5  # no finger between the box and the wall: the axis runs along y
        assert 0.005 <= 0.03 - g.center[2] <= 0.03  # the centre is under the top, the pads above the floor
    # without the wall the x axis is allowed again
    free = np.minimum(d_box, _floor_depth(K, X_WC, 96, 128))
    gs = sample_antipodal_grasps_depth(free, K, X_WC, np.isfinite(d_box), 20, friction=0.5, seed=0)
    assert any(abs(g.axis[0]) > 0.9 for g in gs)
    # half-way down the side (15 mm under the top), raised so that the pads (15 mm under the
    # centre) stay 5 mm above the floor: the centre at 20 mm
    assert all(abs(g.center[2] - 0.02) < 0.003 for g in gs)


def test_depth_sampler_follows_a_tall_object_off_the_optical_axis():
    """A 10 cm tall box 6 cm off the optical axis: the image mask spans its top and one side
    face; the grasp centre must still be over the box (the deprojected midpoint of two mask-boundary
    pixels lands 2 cm beside it)."""
    K, X_WC = overhead_camera()
    box = trimesh.creation.box(extents=(0.03, 0.03, 0.10))
    X = pose_xyz_yaw(0.06, 0.02, 0.05, 0.0)
    d = _render_depth(box, X, K, X_WC, 96, 128)
    depth = np.minimum(d, _floor_depth(K, X_WC, 96, 128))
    gs = sample_antipodal_grasps_depth(depth, K, X_WC, np.isfinite(d), 10, friction=0.5, seed=0)
    assert len(gs) >= 3
    from ms_drake.grasping import GraspEvaluator

    ev = GraspEvaluator("soft_point", friction=0.5)
    for g in gs:
        assert np.all(np.abs(g.center[:2] - X[:2, 3]) < 0.013)  # over the 3 x 3 cm top
        assert 0.07 <= g.center[2] <= 0.095
        assert ev.quality(box, X, g, 0.05) == 1.0
