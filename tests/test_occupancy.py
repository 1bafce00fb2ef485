"""OccupancyEstimator: the analytic ground truth of Ch. 8.3.1 on synthetic scenes, against the
render-per-placement implementation on a real heap image, alone and wired to a station."""

import copy

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.geometry import PinholeCamera
from ms_drake.perception.masks import object_labels
from ms_drake.perception.occupancy import (AnalyticOccupancy, OccupancyEstimator, OccupancyGrid, RenderedOccupancy,
                                           TargetBox, _yaw, convex_silhouette, floor_points)
from ms_drake.errors import PerceptionError
from ms_drake.geometry import Workspace
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import TargetDetector
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import OccupancyMap, TargetEstimate

CAM = PinholeCamera(640, 480, 685.0, 685.0, 319.5, 239.5, RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 0.8]))
BIN = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)
BOX = TargetBox(0.06, 0.03, 0.01)


def heightfield_depth(height) -> np.ndarray:
    """Depth image of z = height(x, y) seen by the straight-down camera CAM (0.8 m up)."""
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    d = np.full(u.shape, 0.8)
    for _ in range(12):
        d = 0.8 - height((u - CAM.cx) / CAM.fx * d, -(v - CAM.cy) / CAM.fy * d)
    return d


def surface_xy(d: np.ndarray):
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    return (u - CAM.cx) / CAM.fx * d, -(v - CAM.cy) / CAM.fy * d


def target_on_grid(j=30, i=24, r=2, grid=OccupancyGrid(), box=BOX):
    """A target lying exactly at grid placement (column j, row i, rotation r): its height function."""
    us, vs = grid.pixels(640, 480)
    c = floor_points(CAM, np.array([float(us[j])]), np.array([float(vs[i])]), 0.5 * box.thickness)[0]
    th = grid.angles()[r]

    def h(x, y):
        xl = np.cos(th) * (x - c[0]) + np.sin(th) * (y - c[1])
        yl = -np.sin(th) * (x - c[0]) + np.cos(th) * (y - c[1])
        return np.where((np.abs(xl) <= box.length / 2) & (np.abs(yl) <= box.width / 2), box.thickness, 0.0)
    return h, c


def slab(x0, x1, y0, y1, z=0.04):
    return lambda x, y: np.where((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1), z, 0.0)


@pytest.fixture(scope="module")
def analytic():
    return AnalyticOccupancy(CAM, BIN, BOX)


def iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def test_visible_target_collapses_to_its_mask(analytic):
    h, _ = target_on_grid()
    d = heightfield_depth(h)
    seen = h(*surface_xy(d)) > 0
    rho = analytic.estimate(d, seen)
    assert rho.sum() == pytest.approx(1.0)
    assert analytic.last_matches == 1  # only the true placement yields the same image
    assert iou(rho > 0, seen) > 0.95


def test_partly_hidden_target_keeps_the_placements_that_look_the_same(analytic):
    h, c = target_on_grid()
    cover = slab(c[0], c[0] + 0.1, c[1] - 0.1, c[1] + 0.1)  # hides the target's +x half
    d = heightfield_depth(lambda x, y: np.maximum(h(x, y), cover(x, y)))
    xy = surface_xy(d)
    seen = (h(*xy) > 0) & (cover(*xy) == 0)
    amodal = h(*surface_xy(heightfield_depth(h))) > 0
    assert 0.2 < seen.sum() / amodal.sum() < 0.8
    rho = analytic.estimate(d, seen)
    assert rho.sum() == pytest.approx(1.0) and analytic.last_matches >= 1
    assert (rho[amodal] > 0).mean() > 0.97  # the truth is among the matches
    assert ((rho > 0) & ~amodal).sum() < 0.5 * amodal.sum()  # and the support stays near it


def test_hidden_target_spreads_under_the_occluders_only(analytic):
    h, c = target_on_grid()
    cover = slab(c[0] - 0.06, c[0] + 0.06, c[1] - 0.05, c[1] + 0.05)
    d = heightfield_depth(lambda x, y: np.maximum(h(x, y), cover(x, y)))
    rho = analytic.estimate(d, np.zeros((480, 640), bool))
    under = cover(*surface_xy(d)) > 0
    amodal = h(*surface_xy(heightfield_depth(h))) > 0
    assert rho.sum() == pytest.approx(1.0)
    assert (rho[amodal] > 0).all()  # the true pose is one of the hiding places
    assert rho[~under].sum() < 1e-9  # and nothing is outside the slab (the target is fully hidden)
    assert (rho > 0).sum() > 2 * amodal.sum()  # many placements fit under a 12 x 10 cm slab

    # An empty bin has no hiding place: the distribution is all zero.
    rho = analytic.estimate(np.full((480, 640), 0.8), np.zeros((480, 640), bool))
    assert not rho.any()


def test_fast_path_equals_shifting_every_silhouette():
    """The run-length prefix sums and difference images give exactly the counts of shifting each
    rotation's silhouette to every placement and comparing pixel by pixel (an elongated target, so
    that row and column runs are both used)."""
    box = TargetBox(0.095, 0.0095, 0.005)
    grid = OccupancyGrid((6, 4), 8)
    fast = AnalyticOccupancy(CAM, BIN, box, grid)
    assert fast.transposed.any() and not fast.transposed.all()
    c = floor_points(CAM, np.array([320.0]), np.array([240.0]), 0.5 * box.thickness)[0]
    v, _ = box.mesh_vertices_faces()
    sils = [convex_silhouette(CAM, v @ _yaw(t).T + c) for t in grid.angles()]
    h, cen = target_on_grid(j=3, i=2, r=3, grid=grid, box=box)
    for y0 in (0.0, -0.2):  # half hidden, then hidden under a wide slab
        cover = slab(cen[0] - 0.1, cen[0] + 0.1, cen[1] + y0, cen[1] + 0.1, 0.02)
        d = heightfield_depth(lambda x, y: np.maximum(h(x, y), cover(x, y)))
        V = fast.height_map(d) <= box.thickness + fast.height_tolerance
        M = V & (h(*surface_xy(d)) > 0)
        assert M.any() == (y0 > -0.1)
        want, acc = np.zeros((len(fast.gu), grid.rotations), bool), np.zeros((480, 640))
        for p, (u, vv) in enumerate(zip(fast.gu, fast.gv)):
            for r, sil in enumerate(sils):
                sh = np.roll(sil, (vv - 240, u - 320), axis=(0, 1))  # the silhouettes stay inside the image
                n, i = (sh & V).sum(), (sh & V & M).sum()
                want[p, r] = n == 0 if not M.any() else i / (n + M.sum() - i) > 0.9
                acc += sh * want[p, r]
        got = fast.match(d, M)
        assert np.array_equal(got, want) and got.any()
        assert np.array_equal(fast.accumulate(got), acc)


def test_analytic_equals_render_per_placement_on_a_heap(bin_scenario, small_heap):
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    station = MakeStation(s)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0]
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    grid = OccupancyGrid((12, 9), 4)
    box = TargetBox(0.05, 0.02, 0.005)
    fast = AnalyticOccupancy(cam, Workspace.from_scenario(s), box, grid)
    slow = RenderedOccupancy(s, box, grid=grid)
    empty = np.zeros(depth.shape, bool)
    a, b = fast.estimate(depth, empty), slow.estimate(depth, empty)
    assert slow.renders == 4 * len(fast.gu) and fast.last_matches > 0
    # The analytic generator shifts one silhouette per rotation (as the reference shifts one render);
    # the renders place the box exactly, so a 2-px sliver of its side shows near the bin's edges.
    assert iou(a > 0, b > 0) > 0.85 and np.abs(a - b).sum() < 0.3


def test_estimator_alone_and_bad_input(analytic):
    h, c = target_on_grid()
    cover = slab(c[0] - 0.06, c[0] + 0.06, c[1] - 0.05, c[1] + 0.05)
    d = heightfield_depth(lambda x, y: np.maximum(h(x, y), cover(x, y)))
    est = OccupancyEstimator(analytic)
    ctx = est.CreateDefaultContext()
    img = ImageDepth32F(640, 480)
    np.array(img.mutable_data, copy=False)[:, :, 0] = d
    est.GetInputPort("depth_image").FixValue(ctx, img)
    est.GetInputPort("target").FixValue(ctx, TargetEstimate(False, np.zeros((480, 640), bool)))
    out = est.GetOutputPort("occupancy").Eval(ctx)
    assert isinstance(out, OccupancyMap) and out.distribution.sum() == pytest.approx(1.0)
    by_name = OccupancyEstimator("analytic", camera=CAM, workspace=BIN, target_size=(0.03, 0.06, 0.01))
    assert by_name.backend.box == BOX  # length and width are sorted
    with pytest.raises(PerceptionError, match="unknown"):
        OccupancyEstimator("network")
    with pytest.raises(PerceptionError, match="target_size"):
        OccupancyEstimator("analytic", camera=CAM, workspace=BIN)
    with pytest.raises(PerceptionError, match="positive"):
        TargetBox(0.05, 0.02, -0.01)
    with pytest.raises(PerceptionError, match="camera"):
        analytic.match(np.ones((10, 10)), np.zeros((10, 10), bool))


def test_estimator_wired_to_a_station(bin_scenario, small_heap):
    k = small_heap.target_index
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, target_index=k))
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(get_plant(station))))
    det = builder.AddSystem(TargetDetector("color"))
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    occ = builder.AddSystem(OccupancyEstimator("analytic", camera=cam, workspace=Workspace.from_scenario(s),
                                               target_size=TargetBox.from_object(small_heap.target)))
    builder.Connect(station.GetOutputPort("overhead.label_image"), seg.GetInputPort("label_image"))
    builder.Connect(station.GetOutputPort("overhead.rgb_image"), det.GetInputPort("rgb_image"))
    builder.Connect(seg.GetOutputPort("masks"), det.GetInputPort("masks"))
    builder.Connect(station.GetOutputPort("overhead.depth_image"), occ.GetInputPort("depth_image"))
    builder.Connect(det.GetOutputPort("target"), occ.GetInputPort("target"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    target = det.GetOutputPort("target").Eval(det.GetMyContextFromRoot(ctx))
    rho = occ.GetOutputPort("occupancy").Eval(occ.GetMyContextFromRoot(ctx)).distribution
    assert rho.shape == (480, 640) and rho.min() >= 0
    assert rho.sum() == pytest.approx(1.0)
    assert target.visible and (rho[target.mask] > 0).all()  # small_heap's target shows; the support holds it


def raycast_depth(scene, window=(150, 490, 100, 380)):
    """Exact depth image of CAM looking at the trimesh `scene` (world frame) over the floor z = 0,
    ray cast inside the pixel window (u0, u1, v0, v1); the floor elsewhere."""
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    d = heightfield_depth(lambda x, y: 0.0 * x)
    u0, u1, v0, v1 = window
    uu, vv = u[v0:v1, u0:u1].ravel(), v[v0:v1, u0:u1].ravel()
    dirs = np.stack([(uu - CAM.cx) / CAM.fx, -(vv - CAM.cy) / CAM.fy, -np.ones(len(uu))], axis=1)
    origins = np.tile([0.0, 0.0, 0.8], (len(uu), 1))
    loc, ray, _ = scene.ray.intersects_location(origins, dirs, multiple_hits=False)
    dd = d[v0:v1, u0:u1].ravel().copy()
    dd[ray] = 0.8 - loc[:, 2]  # depth = distance along the optical axis (world -z)
    d[v0:v1, u0:u1] = dd.reshape(v1 - v0, u1 - u0)
    return d


def lying_cylinder(x0=0.02, y0=-0.01, radius=0.015, length=0.08):
    """A cylinder lying along the world x on the floor: (its mesh in the world, TargetMesh at its pose)."""
    import trimesh

    from ms_drake.perception.occupancy import TargetMesh

    m = trimesh.creation.cylinder(radius=radius, height=length, sections=32)  # axis = its z
    R = RollPitchYaw(0, np.pi / 2, 0).ToRotationMatrix().matrix()  # its z along the world x
    p = np.array([x0, y0, radius])
    world = m.copy().apply_transform(np.block([[R, p[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    return world, TargetMesh(np.asarray(m.vertices), np.asarray(m.faces), R, p)


def test_a_visible_cylinder_matches_its_own_mesh_placement():
    import trimesh

    from ms_drake.perception.occupancy import TargetMesh

    cyl, target = lying_cylinder()
    grid = OccupancyGrid((64, 48), 8)
    occ = AnalyticOccupancy(CAM, BIN, target, grid)
    assert len(occ.angles) == 8 and np.isclose(occ.angles[-1], 7 * np.pi / 8)  # turned by pi it looks the same
    # A 4 cm slab covers one end: the seen part is the rest of the cylinder.
    cover = trimesh.creation.box((0.05, 0.10, 0.04)).apply_translation((0.075, 0.0, 0.02))
    d = raycast_depth(trimesh.util.concatenate([cyl, cover]))
    d_alone = raycast_depth(cyl)
    seen = (d < 0.8 - 1e-4) & (np.abs(d - d_alone) < 1e-6)
    x, _ = surface_xy(d)
    assert 300 < seen.sum() and x[seen].max() < 0.05
    rho = occ.estimate(d, seen)
    assert occ.last_matches >= 1  # the grid was aligned on the true pose: its placement matches
    assert rho.sum() == pytest.approx(1.0) and rho[seen].sum() > 0.5
    v, u = np.nonzero(rho > 0)
    assert x[v, u].max() > 0.05  # the amodal masks reach under the slab
    # Hidden under a wide slab: the distribution spreads under the slab only.
    wide = trimesh.creation.box((0.16, 0.12, 0.04)).apply_translation((0.02, 0.0, 0.02))
    d2 = raycast_depth(trimesh.util.concatenate([cyl, wide]))
    rho2 = occ.estimate(d2, np.zeros(d2.shape, bool))
    under = d2 < 0.8 - 0.035
    assert occ.last_matches > 0 and rho2[~under].sum() < 0.05
    # Not symmetric under a half turn (an L-shaped mesh): the bins span the whole turn.
    L = trimesh.util.concatenate([trimesh.creation.box((0.06, 0.02, 0.01)),
                                  trimesh.creation.box((0.02, 0.04, 0.01)).apply_translation((0.02, 0.03, 0))])
    occ_l = AnalyticOccupancy(CAM, BIN, TargetMesh(np.asarray(L.vertices), np.asarray(L.faces), np.eye(3)), grid)
    assert np.isclose(occ_l.angles[-1], 7 * 2 * np.pi / 8) and occ_l.grid.offset == (0, 0)
    with pytest.raises(PerceptionError, match="TargetMesh"):
        TargetMesh(np.zeros((2, 3)), np.zeros((0, 3), int), np.eye(3))


def test_visible_cylinder_target_in_a_heap_gets_a_distribution_on_its_mask(bin_scenario, small_heap):
    """Every visible cylinder of a small heap as the target, its own mesh at its true pose: a
    non-zero distribution that overlaps its mask (placements matched, or the mask as fallback)."""
    from ms_drake.perception.masks import label_image_to_masks
    from ms_drake.perception.occupancy import TargetMesh
    from ms_drake.station import station_objects

    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    station = MakeStation(s)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0]
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
    plant = get_plant(station)
    masks = label_image_to_masks(labels, object_labels(plant))
    cam, ws = PinholeCamera.from_config(s.cameras["overhead"]), Workspace.from_scenario(s)
    tried = matched = 0
    for o, so in zip(small_heap.objects, station_objects(plant)):
        if "cylinder" not in o.name or so.model_name not in masks.ids:
            continue
        M = masks.masks[masks.ids.index(so.model_name)]
        occ = AnalyticOccupancy(cam, ws, TargetMesh.from_object(o.name, o.matrix()))
        rho = occ.estimate(depth, M)
        tried += 1
        matched += occ.last_matches > 0
        assert rho.sum() == pytest.approx(1.0) and rho[M].sum() > 0.5
    assert tried == matched == 2  # small_heap's two cylinders are visible, and the grid matches each


def test_best_match_extends_a_partly_seen_target_off_the_grid_under_its_occluder():
    grid = OccupancyGrid()
    us, vs = grid.pixels(640, 480)
    # the target half a grid step and half a rotation bin away from every placement
    u0, v0 = 0.5 * (us[30] + us[31]), 0.5 * (vs[24] + vs[25])
    c = floor_points(CAM, np.array([u0]), np.array([v0]), 0.5 * BOX.thickness)[0]
    th = 0.5 * (grid.angles()[2] + grid.angles()[3])

    def h(x, y):
        xl = np.cos(th) * (x - c[0]) + np.sin(th) * (y - c[1])
        yl = -np.sin(th) * (x - c[0]) + np.cos(th) * (y - c[1])
        return np.where((np.abs(xl) <= BOX.length / 2) & (np.abs(yl) <= BOX.width / 2), BOX.thickness, 0.0)
    cover = slab(c[0], c[0] + 0.1, c[1] - 0.1, c[1] + 0.1)
    d = heightfield_depth(lambda x, y: np.maximum(h(x, y), cover(x, y)))
    xy = surface_xy(d)
    seen = (h(*xy) > 0) & (cover(*xy) == 0)
    amodal = h(*surface_xy(heightfield_depth(h))) > 0
    plain = AnalyticOccupancy(CAM, BIN, BOX)
    rho = plain.estimate(d, seen)
    assert plain.last_matches == 0 and np.array_equal(rho > 0, seen)  # no placement passes: the modal mask
    best = AnalyticOccupancy(CAM, BIN, BOX, best_match=0.05)
    rho = best.estimate(d, seen)
    under = cover(*xy) > 0
    assert rho.sum() == pytest.approx(1.0) and best.last_matches >= 1
    assert (rho[amodal & under] > 0).mean() > 0.5  # most of its hidden part is in the support (the plain: none)
    assert ((rho > 0) & ~amodal).sum() < amodal.sum()  # and the support stays near it
    with pytest.raises(PerceptionError, match="best_match=1.5"):
        AnalyticOccupancy(CAM, BIN, BOX, best_match=1.5)
