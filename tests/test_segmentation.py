"""Segmenter: ground truth, Euclidean clustering and region growing -- alone and wired to a station."""

import copy

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from ms_drake.geometry import PinholeCamera
from ms_drake.perception.masks import label_image_to_masks, object_labels
from ms_drake.errors import PerceptionError
from ms_drake.geometry import Workspace, world_points
from ms_drake.perception.segmentation import Segmenter, coco_mask_metrics, euclidean_clustering, region_growing
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import InstanceMasks

CAM = PinholeCamera(640, 480, 685.0, 685.0, 319.5, 239.5, RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 0.8]))
BIN = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)


def heightfield_depth(cam: PinholeCamera, height) -> np.ndarray:
    """Depth image of a heightfield z = height(x, y) seen by the straight-down camera 0.8 m up (the
    overhead camera of the scenarios: 640 x 480, f = 685 px)
    (fixed-point iteration along each ray)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    d = np.full(u.shape, 0.8)
    for _ in range(12):
        x = (u - cam.cx) / cam.fx * d
        y = -(v - cam.cy) / cam.fy * d
        d = 0.8 - height(x, y)
    return d


def box(x0, x1, y0, y1, h):
    return lambda x, y: np.where((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1), h, 0.0)


def depth_image(d: np.ndarray) -> ImageDepth32F:
    img = ImageDepth32F(d.shape[1], d.shape[0])
    np.array(img.mutable_data, copy=False)[:, :, 0] = d
    return img


def test_euclidean_clusters_separate_objects_and_drop_the_bin():
    a, b = box(-0.15, -0.05, -0.05, 0.05, 0.03), box(0.03, 0.12, -0.1, 0.0, 0.05)
    speck = box(0.18, 0.185, 0.1, 0.105, 0.01)  # a few pixels: below min_pixels
    d = heightfield_depth(CAM, lambda x, y: np.maximum(np.maximum(a(x, y), b(x, y)), speck(x, y)))
    masks = euclidean_clustering(world_points(CAM, d), BIN)
    assert len(masks) == 2
    P = world_points(CAM, d)
    for m in masks.masks:  # each cluster is one box, none holds floor points
        z = P[m][:, 2]
        assert np.ptp(z) < 1e-3 and z.min() > 0.02
    assert {round(float(np.median(P[m][:, 0])), 1) for m in masks.masks} == {-0.1, 0.1}


def test_region_growing_splits_a_ridge_that_euclidean_clustering_merges():
    # Two planes meeting at a ridge (a roof), 77 degrees apart, touching with no gap.
    def roof(x, y):
        return np.where((np.abs(x) < 0.05) & (np.abs(y) < 0.06), np.maximum(0.045 - 0.8 * np.abs(x), 0.0), 0.0)

    P = world_points(CAM, heightfield_depth(CAM, roof))
    eu = euclidean_clustering(P, BIN)
    rg = region_growing(P, BIN)
    assert len(eu) == 1
    assert len(rg) == 2
    xs = sorted(float(np.median(P[m][:, 0])) for m in rg.masks)
    assert xs[0] < -0.01 and xs[1] > 0.01


def test_segmenter_alone_fixes_inputs_and_evaluates():
    d = heightfield_depth(CAM, box(-0.1, 0.0, -0.05, 0.05, 0.04))
    eu = Segmenter("euclidean", camera=CAM, workspace=BIN)
    ctx = eu.CreateDefaultContext()
    eu.GetInputPort("depth_image").FixValue(ctx, depth_image(d))
    out = eu.GetOutputPort("masks").Eval(ctx)
    assert isinstance(out, InstanceMasks) and len(out) == 1 and out.ids == ("seg_0",)
    rg = Segmenter("region_growing", camera=CAM, workspace=BIN)
    ctx = rg.CreateDefaultContext()
    rg.GetInputPort("depth_image").FixValue(ctx, depth_image(d))
    assert len(rg.GetOutputPort("masks").Eval(ctx)) == 1

    labels = np.zeros((480, 640), np.int16)
    labels[10:30, 10:40] = 5
    img = ImageLabel16I(640, 480)
    np.array(img.mutable_data, copy=False)[:, :, 0] = labels
    gt = Segmenter("ground_truth", label_to_id={5: "obj00__x__y"})
    ctx = gt.CreateDefaultContext()
    gt.GetInputPort("label_image").FixValue(ctx, img)
    m = gt.GetOutputPort("masks").Eval(ctx)
    assert m.ids == ("obj00__x__y",) and int(m.areas()[0]) == 600


def test_segmenter_rejects_bad_configuration():
    with pytest.raises(PerceptionError, match="unknown"):
        Segmenter("mask_rcnn", camera=CAM, workspace=BIN)
    with pytest.raises(PerceptionError, match="label_to_id"):
        Segmenter("ground_truth")
    with pytest.raises(PerceptionError, match="workspace"):
        Segmenter("euclidean", camera=CAM)
    s = Segmenter("euclidean", camera=CAM, workspace=BIN)
    with pytest.raises(PerceptionError, match="not connected"):
        s.GetOutputPort("masks").Eval(s.CreateDefaultContext())
    with pytest.raises(PerceptionError, match="640x480"):
        world_points(CAM, np.ones((10, 10)))


def test_coco_metrics_perfect_and_empty():
    m = np.zeros((2, 50, 60), bool)
    m[0, 5:20, 5:20] = True
    m[1, 30:45, 30:55] = True
    gt = InstanceMasks(m, ("a", "b"), np.ones(2))
    assert coco_mask_metrics([gt], [gt])["AP"] == pytest.approx(1.0)
    half = InstanceMasks(m[:1], ("a",), np.ones(1))
    r = coco_mask_metrics([gt], [half])
    assert r["AR100"] == pytest.approx(0.5) and r["AP"] < 1.0
    assert coco_mask_metrics([gt], [InstanceMasks.empty(50, 60)])["AP"] == 0.0


def test_segmenters_wired_to_a_station(bin_scenario, small_heap):
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    ws = Workspace.from_scenario(s)
    systems = {}
    for backend in ("ground_truth", "euclidean", "region_growing"):
        seg = builder.AddSystem(Segmenter(backend, camera=cam, workspace=ws, label_to_id=object_labels(get_plant(station))))
        builder.Connect(station.GetOutputPort("overhead.depth_image"), seg.GetInputPort("depth_image"))
        builder.Connect(station.GetOutputPort("overhead.label_image"), seg.GetInputPort("label_image"))
        systems[backend] = seg
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    out = {k: v.GetOutputPort("masks").Eval(v.GetMyContextFromRoot(ctx)) for k, v in systems.items()}
    gt = out["ground_truth"]
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(
        station.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    ref = label_image_to_masks(labels, object_labels(get_plant(station)), 20)
    assert gt.ids == ref.ids and len(gt) >= 1
    assert set(gt.ids) <= {o for o in object_labels(get_plant(station)).values()}
    union = gt.masks.any(axis=0)
    for backend in ("euclidean", "region_growing"):
        pred = out[backend]
        assert len(pred) >= 1
        # Depth-only clusters lie on the objects, not on the bin.
        assert (pred.masks.any(axis=0) & union).sum() >= 0.95 * pred.masks.any(axis=0).sum(), backend
        assert coco_mask_metrics([gt], [pred])["AR100"] > 0.1, backend
