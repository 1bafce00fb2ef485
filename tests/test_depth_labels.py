"""Label images from the depth image (ms_drake.station.labels.DepthLabeler / DepthLabelImage):
alone (analytic depth, FixValue'd inputs), wired to an RgbdSensor, and in a heap station —
always compared with what RenderEngineVtk renders or with the analytic answer."""

import copy

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    Box,
    Capsule,
    ClippingRange,
    ColorRenderCamera,
    Cylinder,
    DepthRange,
    DepthRenderCamera,
    GeometryInstance,
    MakeRenderEngineVtk,
    PerceptionProperties,
    RenderCameraCore,
    RenderEngineVtkParams,
    RenderLabel,
    Rgba,
    SceneGraph,
    Sphere,
)
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo, ImageDepth32F, ImageLabel16I, RgbdSensor

from ms_drake.errors import ScenarioError
from ms_drake.station.labels import DepthLabeler, DepthLabelImage, make_depth_label_image

W, H = 160, 120
INFO = CameraInfo(W, H, 150.0, 150.0, W / 2 - 0.5, H / 2 - 0.5)
X_WC = RigidTransform(RollPitchYaw(np.pi, 0, 0), [0.0, 0.0, 1.0])  # 1 m above the floor, looking down
FLOOR, BOX, CYL, BALL, CAPSULE = 1, 2, 3, 4, 5


def _scene(extra=()):
    """SceneGraph with a floor slab (top at z = 0) and a box, cylinder and sphere on it (odd
    positions: no edge exactly on a pixel ray)."""
    sg = SceneGraph()
    sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    src = sg.RegisterSource("test")
    items = [(FLOOR, Box(2.0, 2.0, 0.1), [0, 0, -0.05]),
             (BOX, Box(0.12, 0.08, 0.2), [-0.1213, 0.0037, 0.1]),
             (CYL, Cylinder(0.04, 0.15), [0.1011, 0.0613, 0.075]),
             (BALL, Sphere(0.05), [0.08, -0.1, 0.05]), *extra]
    for label, shape, p in items:
        g = GeometryInstance(RigidTransform(p), shape, f"g{label}")
        props = PerceptionProperties()
        props.AddProperty("label", "id", RenderLabel(label))
        props.AddProperty("phong", "diffuse", Rgba(0.5, 0.5, 0.5, 1.0))
        g.set_perception_properties(props)
        sg.RegisterAnchoredGeometry(src, g)
    return sg


def _analytic_depth_and_labels():
    """Depth (camera z) and labels of _scene() by ray casting the primitives analytically, with
    RenderEngineVtk's pixel convention (pixel (u, v) sees the ray through its centre u + 0.5)."""
    v, u = np.mgrid[0:H, 0:W]
    rx = (u + 0.5 - INFO.center_x()) / INFO.focal_x()
    ry = (v + 0.5 - INFO.center_y()) / INFO.focal_y()
    # Camera at (0, 0, 1) looking down: the ray o + t d reaches camera depth t.
    o = np.array([0.0, 0.0, 1.0])
    d = np.stack([rx, -ry, -np.ones_like(rx)], -1)
    depth = np.full((H, W), 1.0)  # the floor's top face
    labels = np.full((H, W), FLOOR, np.int16)

    def keep(t, label):
        closer = np.isfinite(t) & (t > 0) & (t < depth)
        depth[closer] = t[closer]
        labels[closer] = label

    with np.errstate(divide="ignore", invalid="ignore"):
        lo, hi = np.array([-0.1813, -0.0363, 0.0]), np.array([-0.0613, 0.0437, 0.2])  # the box (slab method)
        t1, t2 = (lo - o) / d, (hi - o) / d
        tmin, tmax = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
        keep(np.where(tmin <= tmax, tmin, np.inf), BOX)
        c, r, z1 = np.array([0.1011, 0.0613]), 0.04, 0.15  # the cylinder: side (quadratic) and top cap
        a = (d[..., :2] ** 2).sum(-1)
        b = 2 * (d[..., :2] @ (o[:2] - c))
        disc = b * b - 4 * a * ((o[:2] - c) @ (o[:2] - c) - r * r)
        t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        z_side = 1.0 - t_side
        keep(np.where((disc > 0) & (z_side >= 0) & (z_side <= z1), t_side, np.inf), CYL)
        t_cap = np.full((H, W), 1.0 - z1)
        keep(np.where(np.hypot(rx * t_cap - c[0], -ry * t_cap - c[1]) <= r, t_cap, np.inf), CYL)
    oc = o - np.array([0.08, -0.1, 0.05])  # the sphere
    a, b = (d * d).sum(-1), 2 * (d @ oc)
    disc = b * b - 4 * a * (oc @ oc - 0.05 ** 2)
    keep(np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf), BALL)
    return depth.astype(np.float32), labels


def _inspector_labeler(sg):
    return DepthLabeler(sg.model_inspector(), INFO, "vtk")


def _poses(sg, labeler):
    inspector = sg.model_inspector()
    return {g: inspector.GetPoseInFrame(g) for g in labeler.geometry_ids}  # anchored: frame = world


def test_labeler_alone_matches_analytic_labels():
    sg = _scene()
    labeler = _inspector_labeler(sg)
    assert labeler.default_label == FLOOR  # the largest geometry
    depth, expected = _analytic_depth_and_labels()
    got = labeler.label(depth, X_WC, _poses(sg, labeler), 0.1, 3.0)
    assert got.dtype == np.int16 and got.shape == (H, W)
    for lab in (BOX, CYL, BALL):
        assert (expected == lab).sum() > 100
    assert (got != expected).sum() <= 2  # measured: 0
    for threads in (1, 2):  # row bands in threads (45 rows here: 2 bands): the same image
        banded = DepthLabeler(sg.model_inspector(), INFO, "vtk", threads=threads)
        np.testing.assert_array_equal(banded.label(depth, X_WC, _poses(sg, banded), 0.1, 3.0), got)
    depth[:5] = np.inf  # nothing there (kTooFar) -> kEmpty
    got = labeler.label(depth, X_WC, _poses(sg, labeler), 0.1, 3.0)
    assert np.all(got[:5] == int(RenderLabel.kEmpty))


def test_labeler_declines_what_it_cannot_do_exactly():
    sg = _scene(extra=[(CAPSULE, Capsule(0.02, 0.1), [0.0, 0.15, 0.05])])  # capsule: unsupported shape
    labeler = _inspector_labeler(sg)
    depth, _ = _analytic_depth_and_labels()
    assert labeler.label(depth, X_WC, _poses(sg, labeler), 0.1, 3.0) is None  # capsule in view
    poses = _poses(sg, labeler)
    capsule = next(g for g in labeler.geometry_ids if sg.model_inspector().GetName(g) == f"g{CAPSULE}")
    poses[capsule] = RigidTransform([5.0, 0.0, 0.0])  # far outside the view: no need to render
    labels = labeler.label(depth, X_WC, poses, 0.1, 3.0)
    assert labels.shape == depth.shape and len(np.unique(labels)) >= 2  # a label image, objects in it
    depth[0, 0] = 0.0  # kTooClose: the rendered label would show what is there
    assert labeler.label(depth, X_WC, poses, 0.1, 3.0) is None
    with pytest.raises(ValueError, match="160x120"):
        labeler.label(depth[:10], X_WC, poses, 0.1, 3.0)


def test_labeler_renders_for_a_mesh_in_view():
    from pydrake.geometry import Mesh

    from ms_drake.paths import models_dir

    mesh = Mesh(str(models_dir() / "objects/random_urdfs/blob957/visual.obj"), 1.0)
    sg = _scene(extra=[(CAPSULE, mesh, [0.0, 0.15, 0.05])])
    labeler = _inspector_labeler(sg)
    depth, _ = _analytic_depth_and_labels()
    assert labeler.label(depth, X_WC, _poses(sg, labeler), 0.1, 3.0) is None


def _cameras(far_depth=3.0):
    core = RenderCameraCore("vtk", INFO, ClippingRange(0.1, 3.0), RigidTransform())
    return ColorRenderCamera(core, False), DepthRenderCamera(core, DepthRange(0.1, far_depth))


def _wired(sg_extra=()):
    builder = DiagramBuilder()
    sg = builder.AddSystem(_scene(sg_extra))
    color, depth = _cameras()
    sensor = builder.AddSystem(RgbdSensor(sg.world_frame_id(), X_WC, color, depth))
    builder.Connect(sg.get_query_output_port(), sensor.query_object_input_port())
    labels = builder.AddSystem(make_depth_label_image(sensor, sg))
    builder.Connect(sensor.depth_image_32F_output_port(), labels.GetInputPort("depth_image"))
    builder.Connect(sg.get_query_output_port(), labels.GetInputPort("query_object"))
    builder.Connect(sensor.label_image_output_port(), labels.GetInputPort("rendered_label_image"))
    diagram = builder.Build()
    return diagram, sg, sensor, labels


def test_system_alone_with_fixed_inputs():
    diagram, sg, sensor, _ = _wired()
    ctx = diagram.CreateDefaultContext()
    qo = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    system = make_depth_label_image(sensor, sg)
    sctx = system.CreateDefaultContext()
    depth, expected = _analytic_depth_and_labels()
    img = ImageDepth32F(W, H)
    np.asarray(img.mutable_data)[:, :, 0] = depth
    system.GetInputPort("depth_image").FixValue(sctx, img)
    system.GetInputPort("query_object").FixValue(sctx, AbstractValue.Make(qo))
    out = system.GetOutputPort("label_image").Eval(sctx)
    assert isinstance(out, ImageLabel16I)
    got = np.array(out.data)[:, :, 0]
    assert (got != expected).sum() <= 3 and system.renders == 0


def test_wired_system_equals_the_rendered_label_image():
    diagram, _, sensor, labels = _wired()
    ctx = diagram.CreateDefaultContext()
    ours = np.array(labels.GetOutputPort("label_image").Eval(labels.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    vtk = np.array(sensor.label_image_output_port().Eval(sensor.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    assert labels.renders == 0
    for lab in (FLOOR, BOX, CYL, BALL):
        assert (vtk == lab).sum() > 100
    assert (ours == vtk).mean() >= 0.999


def test_wired_system_renders_when_an_unsupported_shape_is_in_view():
    diagram, _, sensor, labels = _wired([(CAPSULE, Capsule(0.02, 0.1), [0.0, 0.15, 0.05])])
    ctx = diagram.CreateDefaultContext()
    ours = np.array(labels.GetOutputPort("label_image").Eval(labels.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    vtk = np.array(sensor.label_image_output_port().Eval(sensor.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    assert labels.renders == 1 and (vtk == CAPSULE).sum() > 20
    np.testing.assert_array_equal(ours, vtk)


def test_unconnected_fallback_is_a_clear_error():
    diagram, sg, sensor, _ = _wired([(CAPSULE, Capsule(0.02, 0.1), [0.0, 0.15, 0.05])])
    ctx = diagram.CreateDefaultContext()
    system = make_depth_label_image(sensor, sg)
    sctx = system.CreateDefaultContext()
    system.GetInputPort("depth_image").FixValue(sctx, sensor.depth_image_32F_output_port().Eval(
        sensor.GetMyContextFromRoot(ctx)))
    system.GetInputPort("query_object").FixValue(
        sctx, AbstractValue.Make(sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))))
    with pytest.raises(ValueError, match="rendered_label_image"):
        system.GetOutputPort("label_image").Eval(sctx)


def test_mismatched_cameras_are_refused():
    sg = _scene()
    color, _ = _cameras()
    _, depth = _cameras(far_depth=1.0)  # depth range ends before the far clipping plane
    sensor = RgbdSensor(sg.world_frame_id(), X_WC, color, depth)
    with pytest.raises(ValueError, match="z_far >= clipping_far"):
        make_depth_label_image(sensor, sg)
    assert isinstance(make_depth_label_image(RgbdSensor(sg.world_frame_id(), X_WC, *_cameras()), sg),
                      DepthLabelImage)


def test_station_label_images_from_depth(bin_scenario, small_heap):
    from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
    from ms_drake.station import MakeStation, get_plant, station_objects

    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    station = MakeStation(s, label_images="depth")
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    ours = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
    sensor = station.GetSubsystemByName("rgbd_sensor_overhead")
    vtk = np.array(sensor.label_image_output_port().Eval(sensor.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    assert station.GetSubsystemByName("depth_label_overhead").renders == 0
    assert (ours == vtk).mean() >= 0.9995
    for o in station_objects(get_plant(station)):
        n = (vtk == int(o.body_index)).sum()
        assert abs(int((ours == int(o.body_index)).sum()) - int(n)) <= max(3, 0.01 * n), o.full_name
    with pytest.raises(ScenarioError, match="label_images"):
        MakeStation(s, label_images="fast")


# ---- An OpenCV labeller, kept here only as the reference of the numba kernel ----

def _reference_rects(labeler, X_CG, z_near, z_far):
    """The screen rectangles [v0, v1, u0, u1) that can see each geometry (numpy)."""
    pc = np.einsum("nij,nkj->nki", X_CG[:, :3, :3], labeler._corners) + X_CG[:, None, :3, 3]
    z = pc[..., 2]
    zs = np.where(z > 1e-6, z, 1.0)
    u = labeler.fx * pc[..., 0] / zs + labeler.cx - 0.5
    v = labeler.fy * pc[..., 1] / zs + labeler.cy - 0.5
    rects = np.stack([np.floor(v.min(1)), np.ceil(v.max(1)) + 1, np.floor(u.min(1)), np.ceil(u.max(1)) + 1], 1)
    rects = np.clip(rects, 0, [labeler.height, labeler.height, labeler.width, labeler.width]).astype(int)
    rects[np.any(z <= 1e-6, axis=1)] = [0, labeler.height, 0, labeler.width]
    rects[np.all(z <= z_near, axis=1) | np.all(z > z_far, axis=1)] = 0
    return rects


def _opencv_reference_label(labeler, depth, X_WC, poses, z_near, z_far):
    """DepthLabeler.label with OpenCV (one OpenCV pass per geometry, then numpy
    for the pixels several geometries claim; one thread)."""
    import cv2

    depth = np.asarray(depth, np.float32)
    if depth.min() <= 0:
        return None
    label = np.full(depth.shape, np.int16(labeler.default_label))
    label[depth == np.inf] = np.int16(int(RenderLabel.kEmpty))
    prims = labeler._prims
    if not prims:
        return label
    X_CG = X_WC.inverse().GetAsMatrix4() @ np.stack([poses[p.geometry_id].GetAsMatrix4() for p in prims])
    rects = _reference_rects(labeler, X_CG, z_near, z_far)
    seen = np.flatnonzero((rects[:, 1] > rects[:, 0]) & (rects[:, 3] > rects[:, 2]))
    if seen.size == 0:
        return label
    if any(prims[i].kind in ("unsupported", "not_rendered") for i in seen):
        return None
    v0, u0, v1, u1 = rects[seen, 0].min(), rects[seen, 2].min(), rects[seen, 1].max(), rects[seen, 3].max()
    R_GC = np.swapaxes(X_CG[:, :3, :3], 1, 2)
    M = np.concatenate([R_GC, -R_GC @ X_CG[:, :3, 3:]], axis=2).astype(np.float32)
    z = depth[v0:v1, u0:u1]
    with np.errstate(invalid="ignore"):  # kTooFar: inf * 0 = NaN, which no claim accepts
        P = cv2.merge([labeler._rx[None, u0:u1] * z, labeler._ry[v0:v1, None] * z, z])
    count = np.zeros(z.shape, np.uint8)
    lab = label[v0:v1, u0:u1]
    radial = {"cylinder": np.array([[1, 1, 0]], np.float32), "sphere": np.array([[1, 1, 1]], np.float32)}
    work = []
    for i in seen:
        p = prims[i]
        a0, a1, b0, b1 = rects[i, 0] - v0, rects[i, 1] - v0, rects[i, 2] - u0, rects[i, 3] - u0
        pg = cv2.transform(P[a0:a1, b0:b1], M[i])
        h = p.half
        if p.kind == "box":
            m = cv2.inRange(pg, (-h[0], -h[1], -h[2]), (h[0], h[1], h[2]))
        else:
            m = cv2.inRange(cv2.transform(cv2.multiply(pg, pg), radial[p.kind]), 0.0, float(h[0] ** 2))
            if p.kind == "cylinder":
                m &= cv2.inRange(pg, (-h[0], -h[1], -h[2]), (h[0], h[1], h[2]))
        lab[a0:a1, b0:b1][m > 0] = p.label
        count[a0:a1, b0:b1] += m > 0
        work.append((p, M[i], (a0, a1, b0, b1)))
    vs, us = np.nonzero(count > 1)
    pts = P[vs, us].astype(np.float64)
    best = np.full(len(vs), np.inf)
    out = lab[vs, us].copy()
    for p, Mi, (a0, a1, b0, b1) in work:
        inside = (vs >= a0) & (vs < a1) & (us >= b0) & (us < b1)
        x = pts[inside] @ Mi[:, :3].T.astype(np.float64) + Mi[:, 3]
        h = p.size
        if p.kind == "box":
            q = np.abs(x) - h
            d = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        elif p.kind == "cylinder":
            rr, qz = np.hypot(x[:, 0], x[:, 1]) - h[0], np.abs(x[:, 2]) - h[2]
            d = np.hypot(np.maximum(rr, 0), np.maximum(qz, 0)) + np.minimum(np.maximum(rr, qz), 0)
        else:
            d = np.linalg.norm(x, axis=1) - h[0]
        d = np.abs(d)
        cur = best[inside]
        win = (d < cur) & (d <= p.eps)
        cur[win] = d[win]
        best[inside] = cur
        sub = out[inside]
        sub[win] = p.label
        out[inside] = sub
    lab[vs, us] = out
    return label, int(len(vs)), int(np.isfinite(best).sum())


def test_numba_kernel_equals_the_opencv_labeller_on_heap_views(bin_scenario, small_heap):
    """The numba kernel against the OpenCV reference labeller on depth images of a heap station
    rendered from 5 camera poses (overhead, tilted, closer), with 1 and 2 threads."""
    from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
    from ms_drake.station import MakeStation, get_scene_graph

    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    station = MakeStation(s, label_images="depth")
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    sg = get_scene_graph(station)
    qo = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    system = station.GetSubsystemByName("depth_label_overhead")
    sensor = station.GetSubsystemByName("rgbd_sensor_overhead")
    camera = sensor.default_depth_render_camera()
    X_WC0 = qo.GetPoseInWorld(sensor.default_parent_frame_id()) @ system._X_PC
    lab1 = system.labeler
    lab2 = DepthLabeler(sg.model_inspector(), camera.core().intrinsics(), camera.core().renderer_name(), threads=2)
    assert lab1.geometry_ids == lab2.geometry_ids
    poses = {g: qo.GetPoseInWorld(g) for g in lab1.geometry_ids}
    views = [RigidTransform(), RigidTransform(RollPitchYaw(0.12, 0, 0), [0, 0, 0]),
             RigidTransform(RollPitchYaw(0, -0.15, 0.3), [0, 0, 0]), RigidTransform([0.02, -0.03, 0.25]),
             RigidTransform(RollPitchYaw(-0.1, 0.1, -0.5), [0.0, 0.05, 0.15])]
    crowded, objects = 0, set()
    for X_CC in views:
        X_WC = X_WC0 @ X_CC
        img = qo.RenderDepthImage(camera, sg.world_frame_id(), X_WC)
        depth = np.array(img.data)[:, :, 0]
        ref, n, _ = _opencv_reference_label(lab1, depth, X_WC, poses, system._z_near, system._z_far)
        crowded += n
        objects |= set(np.unique(ref).tolist())
        for labeler in (lab1, lab2):
            got = labeler.label(depth, X_WC, poses, system._z_near, system._z_far)
            assert (got != ref).sum() <= 10  # float64 vs OpenCV's float32 at the claim edges; measured 0
    assert crowded > 0  # the resolution of several claimers was exercised
    assert len(objects) >= 3  # objects and the environment in view


def test_numba_kernel_equals_the_opencv_labeller_on_overlapping_shapes():
    """Overlapping (tilted) shapes seen from 0.45 m, and a depth image that mixes the rendered
    surface with random depths: many pixels claimed by 2-3 geometries, with a winner within eps
    (the surface of one inside another) and without (random points inside the overlaps)."""
    tilt = RollPitchYaw(0.3, -0.2, 0.5)
    box = (6, Box(0.1, 0.09, 0.1), RigidTransform(tilt, [-0.1, 0.02, 0.12]))
    ball = (7, Sphere(0.07), [-0.06, 0.03, 0.1])
    cyl = (8, Cylinder(0.05, 0.3), RigidTransform(RollPitchYaw(1.2, 0.1, 0), [-0.02, 0.0, 0.1]))
    X_WC_near = RigidTransform(RollPitchYaw(np.pi, 0, 0), [-0.04, 0.02, 0.45])
    # The surface is rendered without the ball, so that the ball holds surface points of others.
    diagram, sg, _, _ = _wired([box, cyl])
    qo = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(diagram.CreateDefaultContext()))
    surface = np.array(qo.RenderDepthImage(_cameras()[1], sg.world_frame_id(), X_WC_near).data)[:, :, 0]
    sg = _scene([box, ball, cyl])
    rng = np.random.default_rng(7)
    depth = np.where(rng.random((H, W)) < 0.5, surface, rng.uniform(0.2, 0.45, (H, W))).astype(np.float32)
    depth[rng.random((H, W)) < 0.02] = np.inf
    labeler = _inspector_labeler(sg)
    poses = _poses(sg, labeler)
    ref, crowded, by_distance = _opencv_reference_label(labeler, depth, X_WC_near, poses, 0.1, 3.0)
    assert by_distance > 300 and crowded - by_distance > 300  # both ways of resolving (measured 604 / 578)
    for threads in (1, 2):
        banded = DepthLabeler(sg.model_inspector(), INFO, "vtk", threads=threads)
        got = banded.label(depth, X_WC_near, poses, 0.1, 3.0)
        assert (got != ref).sum() <= 10  # float64 vs OpenCV's float32 at the claim edges; measured 0
    assert set(np.unique(ref).tolist()) >= {FLOOR, BOX, CYL, BALL, 6, 7, 8, int(RenderLabel.kEmpty)}


def test_kernel_rectangles_and_transforms_equal_numpy():
    """_label_kernel.prepare (per image: X_GC rows and screen rectangles) against numpy, for
    random camera poses: in view, partly out of the image, straddling the camera plane, behind
    the camera, before z_near and beyond z_far."""
    from ms_drake.station._label_kernel import prepare

    sg = _scene()
    labeler = _inspector_labeler(sg)
    poses = _poses(sg, labeler)
    X_WG = np.array([poses[g].GetAsMatrix4() for g in labeler.geometry_ids])
    rng = np.random.default_rng(3)
    kinds = set()
    for k in range(200):
        X = RigidTransform(RollPitchYaw(np.pi + rng.normal(0, 0.6, 3)),
                           rng.uniform([-0.5, -0.5, 0.05], [0.5, 0.5, 1.5]))
        z_near, z_far = (0.1, 3.0) if k % 3 else (0.9, 1.05)
        M, rects = prepare(X.inverse().GetAsMatrix4(), X_WG, labeler._corners, labeler.fx, labeler.fy, labeler.cx,
                           labeler.cy, labeler.height, labeler.width, z_near, z_far)
        X_CG = X.inverse().GetAsMatrix4() @ X_WG
        np.testing.assert_array_equal(rects, _reference_rects(labeler, X_CG, z_near, z_far))
        X_GC = np.linalg.inv(X_CG)[:, :3]
        np.testing.assert_allclose(M, X_GC, atol=1e-6)
        assert M.dtype == np.float32
        area = (rects[:, 1] - rects[:, 0]) * (rects[:, 3] - rects[:, 2])
        kinds |= {"empty" if a == 0 else "whole" if a == H * W else "part" for a in area}
    assert kinds == {"empty", "whole", "part"}


def test_kernel_compiles_without_a_writable_cache_dir(monkeypatch):
    """numba raises at decoration when no cache directory is writable; ms_drake.jit.njit_cached (the
    label kernel's and the grasp samplers' decorator) then compiles without a cache (here: every
    cache directory refused, as read-only)."""
    import numba.core.caching as caching

    from ms_drake.jit import njit_cached

    def read_only(self):
        raise PermissionError(f"read-only: {self.get_cache_path()}")

    monkeypatch.setattr(caching._CacheLocator, "ensure_cache_path", read_only)

    def twice(a):
        return 2 * a

    jitted = njit_cached(twice)
    assert jitted(np.arange(3)).tolist() == [0, 2, 4]
    assert isinstance(jitted._cache, caching.NullCache)
