"""The occupancy dataset (Ch. 8.3.1, lines 1452-1458), its training and its Table 8.1 metrics.

`ms-drake data occupancy --count N --out DIR` writes shards ``shard_<k>_<split>.npz`` of
samples at the learned estimator's working resolution (ms_drake.perception.occupancy_net: the
central 512 x 384 px of the 640 x 480 overhead image, 4 x 4 blocks -> 128 x 96):

1. heap: N ~ Poisson(12) truncated to [10, 15] objects of one object set, the sets taken in
   turn heap by heap (ycb, random_urdfs, procedural: mesh objects as well as procedural ones,
   including thin and small ones), dropped by the heap generator (ms_drake.scenes.heaps, Bullet
   engine) in one of the `HEAP_LAYOUTS`: "spread" (the generator's defaults: truncated Gaussian
   offsets, each object released just above the pile) or "compact" (the `xray_compact` drop of
   the search's "compact" heap layout (ms_drake.scenes.layouts): a heap centre uniform in +-10 cm, offsets uniform in +-2.5 cm,
   released from 20 cm above the floor, as the reference's dataset generator drops them);
2. `views` camera views per heap (the heap's cost is shared by its views): the overhead
   PhoXi-like camera with its position jittered (+-2 cm across, 0.75-0.85 m high), tilted by up
   to 2 degrees, turned by up to 5 degrees about its axis, focal lengths +-5 %, principal point
   +-4 px; a depth image rendered by Drake (QueryObject.RenderDepthImage, VTK);
3. the target, per view: one of the ten equal-area boxes (occupancy_net.TARGET_RATIOS, 3 x 3
   ... 9.5 x 0.95 x 0.5 cm), lying flat on the bin floor under the heap (the target is dropped
   first in the reference), its centre drawn under a random object or around the heap's centre
   (`sample_target`), any yaw.
   Our simplification: the box is put into the rendered heap rather than simulated under it (the
   objects above it are not lifted by its 5 mm): a pixel of its footprint shows the box where
   the heap's surface there is below the box's top, and its depth becomes the box's top there.
   This is exactly the visibility model of the ground-truth generator, and it lets one heap
   serve many targets and views;
4. the ground truth: `AnalyticOccupancy` for that box and camera on its plain 64 x 48 x 16
   placement grid (not aligned with the true pose), from the composed depth and modal mask; or,
   with ``--ground-truth posterior`` (our variant), the target's own amodal mask, the target
   placed in the pile as `xray_compact` places it: a network fit to such labels by MSE predicts
   the probability that a pixel holds the target given the image, under that placement law,
   rather than the reference's uniform spread over the placements the image allows.

Splits, by object and by image: every fifth shard is a "test" shard whose heaps draw only from
the test split of their object set (occupancy_net never sees these occluders in training); the
others draw from the train split. A shard is written atomically once all its samples exist, so
an interrupted run resumes by skipping the shards on disk. Every random choice comes from
numpy Generators seeded by (seed, shard, heap, view).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import trimesh
from pydrake.geometry import (
    ClippingRange,
    DepthRange,
    DepthRenderCamera,
    MakeRenderEngineVtk,
    RenderCameraCore,
    RenderEngineVtkParams,
)
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo

from ms_drake.errors import DatasetError, HeapError
from ms_drake.geometry import PinholeCamera, Workspace, preprocess_depth
from ms_drake.parallel import run_shard_jobs
from ms_drake.paths import make_parser
from ms_drake.perception.occupancy import (
    AnalyticOccupancy,
    TargetBox,
    TargetMesh,
    convex_silhouette,
)
from ms_drake.perception.occupancy_net import (
    TARGET_RATIOS,
    WORK_SHAPE,
    nearest_ratio,
    target_box_size,
    working_inputs,
    working_target,
)
from ms_drake.scenario import load_scenario
from ms_drake.station.sensor_model import apply_depth_sensor, depth_sensor_params, image_rng
from ms_drake.scenes.layouts import HEAP_LAYOUTS as SEARCH_LAYOUTS
from ms_drake.scenes.heaps import HeapParams, generate_heap
from ms_drake.station.station import add_environment, add_objects

OBJECT_SETS = ("ycb", "random_urdfs", "procedural")
TEST_EVERY = 5  # shard k is a test shard when k % TEST_EVERY == TEST_EVERY - 1


def shard_split(k: int, test_only: bool = False) -> str:
    return "test" if test_only or k % TEST_EVERY == TEST_EVERY - 1 else "train"


def truncated_poisson(rng: np.random.Generator, lam: float = 12.0, lo: int = 10, hi: int = 15) -> int:
    while True:
        n = int(rng.poisson(lam))
        if lo <= n <= hi:
            return n


class HeapRenderer:
    """A plant holding a heap's objects (rigid, visual only) in the bin, rendering depth images
    from any camera pose and intrinsics."""

    def __init__(self, scenario, heap):
        builder = DiagramBuilder()
        plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
        sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
        parser = make_parser(plant)
        add_environment(plant, scenario, parser)
        names = heap.object_names()
        instances = add_objects(plant, names, parser=parser)
        plant.Finalize()
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()
        pc = plant.GetMyMutableContextFromRoot(self.context)
        for mi, op in zip(instances, heap.objects):
            plant.SetPositions(pc, mi, np.asarray(op.q))
        self.sg = sg
        self.sg_context = sg.GetMyContextFromRoot(self.context)

    def depth(self, cam: PinholeCamera) -> np.ndarray:
        """(H, W) float32 depth [m] (inf where nothing is seen)."""
        core = RenderCameraCore("vtk", CameraInfo(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy),
                                ClippingRange(0.1, 3.0), RigidTransform())
        q = self.sg.get_query_output_port().Eval(self.sg_context)
        img = q.RenderDepthImage(DepthRenderCamera(core, DepthRange(0.1, 3.0)), self.sg.world_frame_id(), cam.X_WC)
        return np.array(img.data)[:, :, 0].astype(np.float32)


def random_camera(nominal: PinholeCamera, rng: np.random.Generator) -> PinholeCamera:
    """The nominal overhead camera jittered as the module doc states."""
    p = nominal.X_WC.translation().copy()
    p[:2] += rng.uniform(-0.02, 0.02, 2)
    p[2] = rng.uniform(0.75, 0.85)
    tilt = np.deg2rad(rng.uniform(-2.0, 2.0, 2))
    spin = np.deg2rad(rng.uniform(-5.0, 5.0))
    R = nominal.X_WC.rotation() @ RotationMatrix(RollPitchYaw(tilt[0], tilt[1], spin))
    f = rng.uniform(0.95, 1.05, 2)
    c = rng.uniform(-4.0, 4.0, 2)
    return PinholeCamera(nominal.width, nominal.height, nominal.fx * f[0], nominal.fy * f[1], nominal.cx + c[0],
                         nominal.cy + c[1], RigidTransform(R, p))


def _ray_z(cam: PinholeCamera) -> np.ndarray:
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    R = cam.X_WC.rotation().matrix()
    return (R[2, 0] * (u - cam.cx) / cam.fx + R[2, 1] * (v - cam.cy) / cam.fy + R[2, 2]).astype(np.float32)


class LyingCylinder:
    """A cylinder lying on the floor along x (the "flute" of Table 8.1: longer, thinner and deeper
    than the boxes): `length`, diameter `width` = `thickness`. It serves `insert_target` as a box
    does (its silhouette is that of its convex mesh, its seen surface the plane of its top -- the
    visibility model of the ground-truth generator, which gets it as a TargetMesh)."""

    def __init__(self, length: float, diameter: float):
        if not 0 < diameter <= length:
            raise DatasetError(f"cylinder {length} x {diameter} m: give 0 < diameter <= length")
        self.length, self.width, self.thickness = float(length), float(diameter), float(diameter)

    def mesh_vertices_faces(self):
        m = trimesh.creation.cylinder(radius=0.5 * self.width, height=self.length, sections=24)
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))  # axis along x
        return np.asarray(m.vertices), np.asarray(m.faces)

    def target_mesh(self) -> TargetMesh:
        v, f = self.mesh_vertices_faces()
        return TargetMesh(v, f, np.eye(3))


def target_shape(spec):
    """A dataset target from its spec: (length, width, thickness) a box lying flat;
    ("cylinder", length, diameter) a LyingCylinder."""
    if len(spec) == 3 and spec[0] == "cylinder":
        return LyingCylinder(float(spec[1]), float(spec[2]))
    return TargetBox.of(spec)


def target_silhouette(cam: PinholeCamera, ws: Workspace, box: TargetBox, xy, yaw: float) -> np.ndarray:
    """(H, W) bool amodal mask of the box (or LyingCylinder) lying flat on the floor at `xy`,
    turned by `yaw`."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    verts, _ = box.mesh_vertices_faces()
    center = np.array([xy[0], xy[1], ws.floor_z + 0.5 * box.thickness])
    return convex_silhouette(cam, verts @ R.T + center)


def insert_target(depth: np.ndarray, cam: PinholeCamera, ws: Workspace, box: TargetBox, xy, yaw: float):
    """(depth with the box's visible top, modal mask): the box (or LyingCylinder) lies flat on the
    floor at `xy`, turned by `yaw`; it shows where the heap's surface is below its top."""
    ray_z = _ray_z(cam)
    z_cam = cam.X_WC.translation()[2]
    d = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(np.inf))
    height = d * ray_z + np.float32(z_cam - ws.floor_z)
    height = np.where(np.isfinite(height), height, -np.inf)
    sil = target_silhouette(cam, ws, box, xy, yaw)
    top = box.thickness
    modal = sil & (height < top)
    d_top = (ws.floor_z + top - z_cam) / ray_z  # depth of the plane z = floor + top along each ray
    out = np.where(modal, d_top, depth).astype(np.float32)
    return out, modal


HEAP_LAYOUTS = {
    "spread": {},
    "compact": {k: getattr(SEARCH_LAYOUTS["compact"].params, k) for k in ("center_uniform", "offset_uniform",
                                                                            "drop_height")},
}


def check_layout(layout: str) -> str:
    if layout not in HEAP_LAYOUTS:
        raise DatasetError(f"unknown heap layout {layout!r}; choose one of {', '.join(HEAP_LAYOUTS)}")
    return layout


def layout_heap_params(layout: str, split: str) -> HeapParams:
    """The heap generator's parameters of a training heap in `layout` drawing from `split`."""
    return HeapParams(engine="bullet", split=split, render=False, **HEAP_LAYOUTS[check_layout(layout)])


def sample_target(heap, ws: Workspace, box: TargetBox, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Box centre (x, y) under a random object of the heap (sigma 3 cm about the object's origin)
    or, one time in four, around the heap's centre (sigma 6 cm), kept inside the bin; yaw
    uniform. (Our choice: a one-layer heap leaves most of the floor open, and the target is
    mostly hidden in the reference's heaps.)"""
    pts = np.array([op.q[4:6] for op in heap.objects]) if heap.objects else np.zeros((1, 2))
    if rng.random() < 0.25:
        c = pts.mean(axis=0) + rng.normal(0.0, 0.06, 2)
    else:
        c = pts[int(rng.integers(len(pts)))] + rng.normal(0.0, 0.03, 2)
    half = 0.5 * np.asarray(ws.size_xy) - 0.5 * box.length
    c = np.clip(c, np.asarray(ws.center_xy) - half, np.asarray(ws.center_xy) + half)
    return c, float(rng.uniform(0.0, np.pi))


GROUND_TRUTHS = ("generator", "posterior")
PILE_SPREAD = 0.025  # m: SEARCH_LAYOUTS["compact"].params.offset_uniform, every object's offset from the heap centre


def check_ground_truth(ground_truth: str) -> str:
    if ground_truth not in GROUND_TRUTHS:
        raise DatasetError(f"unknown ground truth {ground_truth!r}; choose one of {', '.join(GROUND_TRUTHS)}")
    return ground_truth


def sample_target_in_pile(heap, ws: Workspace, box: TargetBox, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Box centre (x, y) as the `xray_compact` heaps place their target: dropped like every object,
    offset uniformly by up to PILE_SPREAD on each axis from the heap's centre (here the mean of
    the objects' positions), kept inside the bin; yaw uniform."""
    pts = np.array([op.q[4:6] for op in heap.objects]) if heap.objects else np.zeros((1, 2))
    c = pts.mean(axis=0) + rng.uniform(-PILE_SPREAD, PILE_SPREAD, 2)
    half = 0.5 * np.asarray(ws.size_xy) - 0.5 * box.length
    c = np.clip(c, np.asarray(ws.center_xy) - half, np.asarray(ws.center_xy) + half)
    return c, float(rng.uniform(0.0, np.pi))


def make_samples(scenario, heap, views: int, rng: np.random.Generator, ratios=TARGET_RATIOS,
                 box_sizes=None, best_match: float | None = None, ground_truth: str = "generator",
                 sensor: str = "none") -> list[dict]:
    """`views` samples of one heap (see the module doc). box_sizes: explicit targets to draw from
    instead of the training boxes (out-of-set targets; specs of `target_shape`). ground_truth:
    "generator" (AnalyticOccupancy, the target placed by `sample_target`) or "posterior" (the
    target's own amodal mask, placed by `sample_target_in_pile`). sensor: a depth sensor preset
    (ms_drake.station.sensor_model) applied to the network's input only, then the hole filling
    (geometry.preprocess_depth), as the estimator reads a camera's depth; view v's draws come from
    image_rng(heap seed, "overhead", v), apart from `rng`, so every preset gets the same heaps,
    cameras and targets. The ground truth comes from the perfect depth."""
    params = depth_sensor_params(sensor)
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    ws = Workspace.from_scenario(scenario)
    renderer = HeapRenderer(scenario, heap)
    out = []
    for v in range(views):
        cam = random_camera(nominal, rng)
        depth = renderer.depth(cam)
        if box_sizes is None:
            k = int(rng.integers(len(ratios)))
            box = TargetBox.of(target_box_size(ratios[k]))
        else:
            box = target_shape(box_sizes[int(rng.integers(len(box_sizes)))])
            k = nearest_ratio(box.length, box.width)[0]  # the channel that serves this target
        if ground_truth == "posterior":
            xy, yaw = sample_target_in_pile(heap, ws, box, rng)
        else:
            xy, yaw = sample_target(heap, ws, box, rng)
        d2, modal = insert_target(depth, cam, ws, box, xy, yaw)
        if ground_truth == "posterior":
            rho = target_silhouette(cam, ws, box, xy, yaw).astype(np.float64)
        else:
            shape = box.target_mesh() if isinstance(box, LyingCylinder) else box
            rho = AnalyticOccupancy(cam, ws, shape, best_match=best_match).estimate(d2, modal)
        seen = d2
        if not params.is_identity():
            seen = preprocess_depth(apply_depth_sensor(d2, params, image_rng(heap.seed, "overhead", float(v)),
                                                       cam.fx, cam.fy, cam.cx, cam.cy))
        x = working_inputs(seen, modal)
        out.append(dict(x=x.astype(np.float16), y=working_target(rho).astype(np.float16), ratio=k,
                        visible=int(modal.sum()), heap_seed=int(heap.seed), size=np.array([box.length, box.width,
                                                                                             box.thickness])))
    return out


def shard_job(job: tuple) -> dict:
    """(out, k, seed, heaps_per_shard, views, sets, targets, test_only, layout, best_match, ground_truth[, sensor])
    -> writes shard k; module-level for pickling."""
    out, k, seed, heaps_per_shard, views, sets, targets, test_only, layout, best_match, ground_truth = job[:11]
    sensor = job[11] if len(job) > 11 else "none"
    split = shard_split(k, test_only)
    path = Path(out) / f"shard_{k:05d}_{split}.npz"
    if path.exists():
        return dict(shard=k, samples=0, skipped=True)
    scenario = load_scenario(None, "BinHeap15")
    samples, t0, failed = [], time.process_time(), 0
    for j in range(heaps_per_shard):
        heap_seed = seed * 1_000_000 + k * heaps_per_shard + j
        rng = np.random.default_rng([seed, k, j])
        oset = sets[(k * heaps_per_shard + j) % len(sets)]
        n = truncated_poisson(rng)
        try:
            heap = generate_heap(scenario, n, heap_seed, object_set=oset,
                                 params=layout_heap_params(layout, split))
        except HeapError:
            failed += 1
            continue
        samples += make_samples(scenario, heap, views, rng, box_sizes=targets, best_match=best_match,
                                ground_truth=ground_truth, sensor=sensor)
        for s in samples[-views:]:
            s["set"] = oset
            s["objects"] = ",".join(heap.object_names())
    if not samples:
        raise DatasetError(f"shard {k}: every heap failed")
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, x=np.stack([s["x"] for s in samples]), y=np.stack([s["y"] for s in samples]),
                        ratio=np.array([s["ratio"] for s in samples], np.int64),
                        visible=np.array([s["visible"] for s in samples], np.int64),
                        heap_seed=np.array([s["heap_seed"] for s in samples], np.int64),
                        size=np.stack([s["size"] for s in samples]),
                        set=np.array([s["set"] for s in samples]),
                        objects=np.array([s["objects"] for s in samples]), split=np.array(split),
                        layout=np.array(layout), best_match=np.array(-1.0 if best_match is None else best_match),
                        ground_truth=np.array(ground_truth), sensor=np.array(sensor))
    os.replace(tmp, path)
    return dict(shard=k, samples=len(samples), skipped=False, cpu=time.process_time() - t0, failed_heaps=failed)


def write_occupancy_dataset(out, count: int, seed: int = 0, views: int = 8, heaps_per_shard: int = 4,
                            workers: int = 1, use_ray: bool = False, ray_address: str | None = None,
                            progress=None, sets=OBJECT_SETS, targets=None, test_only: bool = False,
                            layout: str = "spread", best_match: float | None = None,
                            ground_truth: str = "generator", sensor: str = "none") -> dict:
    """Shards of about `count` images into `out` (see the module doc); returns counts.
    targets: (length, width, thickness) boxes or ("cylinder", length, diameter) cylinders to use
    instead of the ten training boxes (an out-of-set evaluation set; each sample's ratio is the
    channel of its closest aspect ratio);
    test_only: every shard is a test shard (held-out occluders only);
    layout: how the heaps are dropped (`HEAP_LAYOUTS`); best_match: the ground truth's
    AnalyticOccupancy(best_match=...) for partly seen targets no grid placement matches (None:
    the observed modal mask); ground_truth: `GROUND_TRUTHS` ("posterior": each sample's target
    amodal mask, the target placed in the pile as the `xray_compact` heaps place it; the MSE
    minimiser over such labels is the probability that a pixel holds the target given the image);
    sensor: the depth sensor preset of the network inputs (`make_samples`);
    a folder holds one layout, one best_match, one ground truth and one sensor."""
    check_layout(layout)
    depth_sensor_params(sensor)  # an unknown preset fails here
    check_ground_truth(ground_truth)
    if ground_truth == "posterior" and best_match is not None:
        raise DatasetError("best_match is a setting of the generator's ground truth; the posterior ground truth "
                           "is the target's own amodal mask (drop --best-match)")
    if views < 1 or heaps_per_shard < 1:
        raise DatasetError(f"views={views}, heaps_per_shard={heaps_per_shard}: both must be >= 1")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per = views * heaps_per_shard
    shards = -(-int(count) // per)
    targets = None if targets is None else tuple(
        ("cylinder", float(t[1]), float(t[2])) if t[0] == "cylinder" else tuple(float(v) for v in t) for t in targets)
    for f in sorted(out.glob("shard_*.npz"))[:1]:
        with np.load(f) as z:
            there = str(z["layout"]) if "layout" in z.files else "spread"
            bm = float(z["best_match"]) if "best_match" in z.files else -1.0
            gt = str(z["ground_truth"]) if "ground_truth" in z.files else "generator"
            sens = str(z["sensor"]) if "sensor" in z.files else "none"
        if there != layout:
            raise DatasetError(f"{out} holds {there!r} heaps ({f.name}) and --layout is {layout!r}; "
                               f"write the {layout!r} heaps into a folder of their own")
        if bm != (-1.0 if best_match is None else best_match):
            raise DatasetError(f"{out} holds shards with best_match {None if bm < 0 else bm} ({f.name}), asked for "
                               f"{best_match}; write them into a folder of their own")
        if gt != ground_truth:
            raise DatasetError(f"{out} holds shards with the {gt!r} ground truth ({f.name}) and --ground-truth is "
                               f"{ground_truth!r}; write them into a folder of their own")
        if sens != sensor:
            raise DatasetError(f"{out} holds shards made with the {sens!r} depth sensor ({f.name}), asked for "
                               f"{sensor!r}; write them into a folder of their own")
    jobs = [(str(out), k, int(seed), heaps_per_shard, views, tuple(sets), targets, test_only, layout, best_match,
             ground_truth, sensor)
            for k in range(shards)]
    todo = [j for j in jobs if not (out / f"shard_{j[1]:05d}_{shard_split(j[1], test_only)}.npz").exists()]
    res = dict(shards=shards, skipped=shards - len(todo), written=0, failed=[])
    return run_shard_jobs(shard_job, todo, res, progress=progress, workers=workers, use_ray=use_ray,
                          ray_address=ray_address, max_tasks_per_child=50)


def load_dataset(folder, split: str) -> dict:
    """All shards of `split` ("train" / "test") in `folder`, concatenated: x float16 (n, 3, 96, 128)
    inputs, y float16 (n, 96, 128) ground truth (max 1), ratio (channel index), visible (target
    pixels seen, full resolution), heap_seed, size (target box, m), set, objects (the heap's
    objects, comma-separated)."""
    files = sorted(Path(folder).glob(f"shard_*_{split}.npz"))
    if not files:
        raise DatasetError(f"{folder}: no {split} shards (shard_*_{split}.npz); make them with "
                           f"`ms-drake data occupancy --count 5000 --out {folder}`")
    parts = [dict(np.load(f)) for f in files]
    keys = ("x", "y", "ratio", "visible", "heap_seed", "size", "set", "objects")
    data = {k: np.concatenate([p[k] for p in parts]) for k in keys if all(k in p for p in parts)}
    if data["x"].shape[1:] != (3, *WORK_SHAPE):
        raise DatasetError(f"{folder}: inputs are {data['x'].shape[1:]}, expected {(3, *WORK_SHAPE)}; regenerate it")
    data["files"] = [str(f) for f in files]
    return data
