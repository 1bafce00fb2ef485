"""Grasp samplers (mesh, point cloud, depth + mask) and the suction model."""

import numpy as np
import pytest
import trimesh

from ms_drake.grasping import GraspEvaluator, ParallelJawGrasp, SuctionGrasp
from ms_drake.grasping.geometry import MeshData
from ms_drake.grasping.samplers import (depth_normals, depth_to_points, sample_antipodal_grasps,
                                        sample_antipodal_grasps_depth, sample_antipodal_grasps_point_cloud,
                                        sample_suction_grasps, sample_suction_grasps_depth)
from ms_drake.grasping.suction import SuctionEvaluator

BOX = trimesh.creation.box(extents=(0.04, 0.06, 0.03))


def pose_xyz_yaw(x, y, z, yaw):
    X = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    X[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    X[:3, 3] = [x, y, z]
    return X


def test_mesh_antipodal_grasps_are_antipodal_narrow_unique_and_seeded():
    X = pose_xyz_yaw(0.4, -0.1, 0.05, 0.3)
    mu = 0.5
    gs = sample_antipodal_grasps(BOX, X, 30, friction=mu, max_width=0.08, seed=1)
    assert len(gs) == 30
    again = sample_antipodal_grasps(BOX, X, 30, friction=mu, max_width=0.08, seed=1)
    assert all(np.allclose(a.center, b.center) for a, b in zip(gs, again))
    other = sample_antipodal_grasps(BOX, X, 30, friction=mu, max_width=0.08, seed=2)
    assert not np.allclose(gs[0].center, other[0].center)
    data = MeshData.of(BOX)
    Xinv = np.linalg.inv(X)
    cos_h = np.cos(np.arctan(mu))
    for g in gs:
        assert g.width <= 0.08 + 1e-12
        go = g.transformed(Xinv)
        t, n = data.raycast(np.stack([go.center - go.width / 2 * go.axis, go.center + go.width / 2 * go.axis]),
                            np.stack([go.axis, -go.axis]), go.width)
        assert np.all(np.isfinite(t))
        # both contact normals inside the friction cone about the axis
        assert -n[0] @ go.axis >= cos_h - 1e-9 and n[1] @ go.axis >= cos_h - 1e-9
        assert abs(g.approach @ g.axis) < 1e-9
    centers = np.array([g.center for g in gs])
    axes = np.array([g.axis for g in gs])
    for i in range(len(gs)):
        for j in range(i):
            assert np.linalg.norm(centers[i] - centers[j]) >= 0.004 or abs(axes[i] @ axes[j]) <= np.cos(0.2)
    # the 6 cm side needs a 6 cm + 2 cm opening: never with max_width 0.07
    narrow = sample_antipodal_grasps(BOX, np.eye(4), 40, friction=0.3, max_width=0.07, seed=0)
    assert all(abs(g.axis[1]) < 0.9 for g in narrow)


def test_point_cloud_sampler():
    rng = np.random.default_rng(0)
    pts, faces = trimesh.sample.sample_surface(BOX, 3000, seed=0)
    normals = BOX.face_normals[faces]
    gs = sample_antipodal_grasps_point_cloud(pts, normals, 20, friction=0.3, max_width=0.1, seed=0)
    assert len(gs) >= 10
    ev = GraspEvaluator("soft_point", friction=0.8)
    qualities = [ev.quality(BOX, np.eye(4), g, 0.1) for g in gs]
    assert np.mean(qualities) > 0.5
    del rng


def _render_depth(mesh, X_WO, K, X_WC, h, w):
    """Depth image by ray casting the mesh (camera z forward)."""
    data = MeshData.of(mesh)
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1).reshape(-1, 3)
    X_OC = np.linalg.inv(X_WO) @ X_WC
    d_O = d_C @ X_OC[:3, :3].T
    n = np.linalg.norm(d_O, axis=1, keepdims=True)
    t, _ = data.raycast(np.broadcast_to(X_OC[:3, 3], d_O.shape), d_O / n, np.inf)
    return (t / n[:, 0]).reshape(h, w)


def overhead_camera(height=0.5):
    K = np.array([[300.0, 0, 64], [0, 300.0, 48], [0, 0, 1]])
    X_WC = np.eye(4)
    X_WC[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # looking down
    X_WC[:3, 3] = [0, 0, height]
    return K, X_WC


def test_depth_sampler_restricted_to_mask():
    K, X_WC = overhead_camera()
    X_WO = pose_xyz_yaw(0.0, 0.0, 0.015, 0.2)
    other = pose_xyz_yaw(0.12, 0.0, 0.015, 0.0)
    d1 = _render_depth(BOX, X_WO, K, X_WC, 96, 128)
    d2 = _render_depth(BOX, other, K, X_WC, 96, 128)
    depth = np.minimum(d1, d2)
    mask = np.isfinite(d1) & (d1 <= d2)
    assert mask.sum() > 100 and (np.isfinite(d2)).sum() > 100
    gs = sample_antipodal_grasps_depth(depth, K, X_WC, mask, 10, friction=0.5, max_width=0.1, seed=0)
    assert len(gs) >= 5
    ev = GraspEvaluator("soft_point", friction=0.8)
    for g in gs:
        assert np.allclose(g.approach, [0, 0, -1], atol=1e-9)  # top-down
        assert abs(g.axis[2]) < 1e-9
        assert np.linalg.norm(g.center[:2] - X_WO[:2, 3]) < 0.04  # on the masked box, not the other
        assert 0.0 < g.center[2] < 0.03
    assert np.mean([ev.quality(BOX, X_WO, g, 0.1) for g in gs]) > 0.5
    # points and normals of the depth image: the box top faces the camera
    P = depth_to_points(depth, K)
    N = depth_normals(P)
    top = N[48, 64] @ X_WC[:3, :3].T
    assert top @ [0, 0, 1] > 0.99
    sg = sample_suction_grasps_depth(depth, K, X_WC, mask, 5, seed=0)
    assert len(sg) == 5 and all(np.linalg.norm(s.point[:2] - X_WO[:2, 3]) < 0.04 for s in sg)


def test_suction_seal_and_wrench():
    ev = SuctionEvaluator(vacuum_force=30.0, cup_radius=0.01)
    top = SuctionGrasp([0, 0, 0.015], [0, 0, -1])
    r = ev.evaluate(BOX, np.eye(4), top, 0.2)
    assert (r.quality, r.reason) == (1.0, "resisted")
    edge = SuctionGrasp([0.015, 0, 0.015], [0, 0, -1])  # the cup overhangs the 2 cm edge
    assert ev.evaluate(BOX, np.eye(4), edge, 0.2).reason == "no_seal"
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.012)
    assert ev.evaluate(ball, np.eye(4), SuctionGrasp([0, 0, 0.012], [0, 0, -1]), 0.01).reason == "no_seal"
    # heavier than the vacuum can hold
    assert ev.evaluate(BOX, np.eye(4), top, 4.0).reason == "slips"
    # side grasp far from the COM: the weight's moment exceeds the cup's restoring moment
    side = SuctionGrasp([-0.02, 0.0, 0.0], [1, 0, 0])
    big = trimesh.creation.box(extents=(0.04, 0.3, 0.03))
    far = SuctionGrasp([-0.02, 0.13, 0.0], [1, 0, 0])
    assert ev.quality(big, np.eye(4), side, 0.1) == 1.0
    assert ev.evaluate(big, np.eye(4), far, 0.5).reason == "slips"
    assert ev.evaluate(BOX, np.eye(4), SuctionGrasp([0, 0, 0.5], [0, 0, -1]), 0.2).reason == "miss"
    rq = ev.evaluate(BOX, np.eye(4), SuctionGrasp([0.0105, 0, 0.015], [0, 0, -1]), 0.2, robust_samples=10, seed=0)
    assert 0.0 < rq.quality < 1.0 and rq.trials == 10


def test_suction_sampler():
    gs = sample_suction_grasps(BOX, np.eye(4), 20, seed=0, max_approach_angle=0.3)
    assert len(gs) == 20
    assert all(g.approach @ [0, 0, -1] > np.cos(0.3) for g in gs)
    assert all(abs(g.point[2] - 0.015) < 1e-9 for g in gs)
    with pytest.raises(Exception):
        ParallelJawGrasp([0, 0, 0], [0, 0, 0], [1, 0, 0], 0.05)


def test_suction_candidates_whose_cup_would_land_on_a_taller_neighbour_are_dropped():
    # camera 0.8 m above a floor (z = 0), looking down; a 5 mm plate (the mask) with a 3 cm block
    # lying over its right part (x > 0): only the plate's left part is seen
    f, W, H = 500.0, 200, 160
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    X_WC = np.eye(4)
    X_WC[:3, :3] = np.diag([1.0, -1.0, -1.0])  # camera z down, x along world x
    X_WC[2, 3] = 0.8
    u, v = np.meshgrid(np.arange(W), np.arange(H))

    def height(x, y):
        h = np.zeros_like(x)
        h = np.where((np.abs(x) < 0.05) & (np.abs(y) < 0.03), 0.005, h)  # the plate
        return np.where((x > 0.0) & (x < 0.06) & (np.abs(y) < 0.05), 0.03, h)  # the block on it

    # depth of the plane z = h under each pixel: x = (u - cx) z_c / f, z_c = 0.8 - h (two passes)
    zc = np.full((H, W), 0.8)
    for _ in range(3):
        x, y = (u - W / 2) * zc / f, -(v - H / 2) * zc / f
        zc = 0.8 - height(x, y)
    x, y = (u - W / 2) * zc / f, -(v - H / 2) * zc / f
    mask = (np.abs(x) < 0.05) & (np.abs(y) < 0.03) & (height(x, y) < 0.01)
    free = sample_suction_grasps_depth(zc, K, X_WC, mask, 40, seed=0)
    checked = sample_suction_grasps_depth(zc, K, X_WC, mask, 40, seed=0, cup_radius=0.015, clearance=0.005)
    xs = np.array([g.point[0] for g in free])
    assert xs.min() < -0.02 and xs.max() > -0.01  # without the check: up to the block's edge (x = 0)
    assert checked and all(g.point[0] < -0.015 + 0.002 for g in checked)  # a cup radius away from it
    assert all(abs(g.point[1]) < 0.03 and abs(g.point[2] - 0.005) < 1e-3 for g in checked)


def test_thin_object_lying_flat_gets_jaw_grasps_only_with_pad_contact():
    """A 1.2 cm bar on the floor: the jaws' centre cannot go 5 mm under its top without the pads'
    lower edge (15 mm under the centre) touching the floor, so the centre rule finds no grasp; the
    pad rule does, and the point model finds the contacts on the pads' lower part."""
    bar = trimesh.creation.box([0.08, 0.02, 0.012])
    floor = trimesh.creation.box([0.4, 0.4, 0.01])
    K, X_WC = overhead_camera()
    X_bar = pose_xyz_yaw(0.0, 0.0, 0.006, 0.3)
    d_bar = _render_depth(bar, X_bar, K, X_WC, 96, 128)
    d_floor = _render_depth(floor, pose_xyz_yaw(0.0, 0.0, -0.005, 0.0), K, X_WC, 96, 128)
    depth = np.minimum(d_bar, d_floor)
    mask = np.isfinite(d_bar) & (d_bar <= d_floor)
    assert mask.sum() > 100
    kw = dict(friction=0.5, max_width=0.1, seed=0, pad_below=0.015)
    assert sample_antipodal_grasps_depth(depth, K, X_WC, mask, 10, **kw) == []
    gs = sample_antipodal_grasps_depth(depth, K, X_WC, mask, 10, pad_contact=True, **kw)
    assert len(gs) >= 3
    for g in gs:
        assert g.center[2] > 0.012  # the tool point above the bar, the pads' lower edge above the floor
        assert g.center[2] - 0.015 >= 0.0
        assert np.linalg.norm(g.center[:2]) < 0.045
    centre_only = GraspEvaluator("soft_point", friction=0.5)
    pads = GraspEvaluator("soft_point", friction=0.5, pad_span=0.015)
    assert all(centre_only.evaluate(bar, X_bar, g, 0.05).reason == "miss" for g in gs)
    res = [pads.evaluate(bar, X_bar, g, 0.05) for g in gs]
    assert sum(r.quality for r in res) >= 2 and all(r.reason != "miss" for r in res)


def test_ray_contacts_down_the_pads():
    """pad_span: the middle of the run of lines where both jaws touch; a jaw collision first is one."""
    from ms_drake.grasping.point_models import ray_contacts
    data = MeshData.of(trimesh.creation.box([0.02, 0.02, 0.01]))  # z in [-5, 5] mm
    c, axis, down = np.array([0.0, 0.0, 0.02]), np.array([1.0, 0, 0]), np.array([0.0, 0, -1])
    assert ray_contacts(data, c, axis, 0.04) == (None, "miss")
    assert ray_contacts(data, c, axis, 0.04, down, 0.01) == (None, "miss")  # the pads end above it
    (p, n), reason = ray_contacts(data, c, axis, 0.04, down, 0.03)
    assert reason == "" and np.allclose(p[:, 0], [-0.01, 0.01]) and abs(p[0, 2]) < 1.5e-3  # mid-height
    assert np.allclose(n, [[1, 0, 0], [-1, 0, 0]])
    assert ray_contacts(data, c, axis, 0.01, down, 0.03) == (None, "jaw_collision")  # opening too narrow
    with pytest.raises(ValueError, match="approach"):
        ray_contacts(data, c, axis, 0.04, None, 0.03)
