"""The synthetic depth segmentation dataset (WISDOM-Sim analogue, Ch. 5.3-5.4.1, lines 855-870).

`ms-drake data segmentation --count N --out DIR` writes shards ``shard_<k>_<split>.npz`` and their
COCO annotation files ``shard_<k>_<split>.json``, then merges the latter into
``coco_train.json`` / ``coco_test.json`` (pycocotools' `COCO(file)` reads them):

1. heap: m ~ Poisson(7.5) truncated to [1, 10] foreground objects of one object set, the sets
   taken in turn heap by heap (ycb and random_urdfs meshes, procedural boxes, cylinders and the
   cardboard-backed "packaged" objects), dropped one by one into the bin by the heap generator
   (ms_drake.scenes.heaps, Bullet engine, as the reference's PyBullet drop); the table and the
   bin are the two fixed background objects;
2. `views` camera views per heap (the heap's cost is shared): the overhead camera with its pose
   and intrinsics jittered (`occupancy_data.random_camera`: +-2 cm across, 0.75-0.85 m high,
   tilt <= 2 deg, turn <= 5 deg, focal lengths +-5 %, principal point +-4 px); a depth image and
   a label image rendered by Drake (VTK);
3. modal masks: the pixels of each object in the label image (an object's visible pixels: the
   reference's "render each object alone and keep the pixels within a threshold of the full
   depth" gives the same set); masks under `MIN_GT_PIXELS` (20) are dropped;
4. sensor model (optional, off by default as in the reference, whose PhoXi has very little
   noise): Gaussian depth noise of `noise` m and missing pixels (depth 0) with probability
   `dropout`, half of them as single pixels and half at depth discontinuities (> 5 mm to a
   neighbour), where structured-light sensors lose their returns.
5. depth sensor models (``sensor``, optional, off by default): the station's camera models
   (ms_drake.station.sensor_model). ``sensor="random"`` draws, per image, one of the presets
   (none, phoxi, l515, primesense, equally likely) and jitters its parameters (`draw_sensor`:
   noise x 0.5-2, edge / grazing / single-pixel dropout x 0.5-1.5, blob count x 0.5-2 and size
   x 0.7-1.4, edge band +-1 px, grazing onset +-10 deg); a preset name applies that preset
   unchanged to every image. The draw comes from a Generator seeded by (seed, shard, heap, view)
   alone, so the heaps and cameras are those of the data without sensors and a rerun draws the
   same presets. The network's inputs ``x`` are made from the depth as the station's consumers
   read it (`geometry.preprocess_depth`, hole filling, then `working_inputs`), ``depth`` keeps
   the sensor's raw image (holes = 0); shards then also hold ``sensor`` (each image's preset)
   and ``sensor_params`` (n, len(SENSOR_FIELDS)) float32.

Shards hold ``depth`` (n, 480, 640) float16 m, ``labels`` (n, 480, 640) uint8 (0 = none, k =
the k-th object of the image's ``objects``), the network's working arrays ``x`` (n, 2, 192, 256)
float16 and ``lab`` (n, 192, 256) uint8 (segmentation_net), ``K`` (n, 3, 3) and ``X_WC`` (n, 4, 4)
of each camera, ``objects`` (comma-separated full names), ``set`` and ``heap_seed`` (and with a
sensor model ``sensor`` and ``sensor_params``).

Splits, by image and by object: every fifth shard is a "test" shard whose heaps draw only from
the test split of their object set (`occupancy_data.shard_split`; the registry splits every set
by object), the others from the train split, so no test object is seen in training (80/20 as
the reference). A shard is written atomically once all its images exist, so an interrupted run
resumes by skipping the shards on disk. Every random choice comes from numpy Generators seeded
by (seed, shard, heap).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils
from pydrake.geometry import ClippingRange, ColorRenderCamera, RenderCameraCore
from pydrake.math import RigidTransform
from pydrake.systems.sensors import CameraInfo

from ms_drake.errors import DatasetError, HeapError
from ms_drake.experiments.occupancy_data import (
    HeapRenderer,
    random_camera,
    shard_split,
    truncated_poisson,
)
from ms_drake.geometry import PinholeCamera, preprocess_depth
from ms_drake.parallel import run_shard_jobs
from ms_drake.perception.segmentation_net import (
    MIN_GT_PIXELS,
    working_inputs,
    working_labels,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap
from ms_drake.station.sensor_model import PRESETS, DepthSensorParams, apply_depth_sensor
from ms_drake.station.station import station_objects
from ms_drake.types import InstanceMasks

OBJECT_SETS = ("ycb", "random_urdfs", "procedural")
MEAN_OBJECTS, MAX_OBJECTS = 7.5, 10
IMAGE_ID_STRIDE = 10_000  # COCO image id = shard * stride + index in the shard
SENSOR_OPTIONS = ("none", "random", *[p for p in PRESETS if p != "none"])
SENSOR_FIELDS = tuple(f.name for f in dataclasses.fields(DepthSensorParams))


class LabelledHeapRenderer(HeapRenderer):
    """HeapRenderer that also renders label images (Drake's default render label of a body is its
    BodyIndex) and names the objects behind them (full names, ``set/object``)."""

    def __init__(self, scenario, heap):
        super().__init__(scenario, heap)
        plant = self.diagram.GetSubsystemByName("plant")
        self.label_to_name = {int(o.body_index): o.full_name for o in station_objects(plant)}

    def labels(self, cam: PinholeCamera) -> np.ndarray:
        core = RenderCameraCore("vtk", CameraInfo(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy),
                                ClippingRange(0.1, 3.0), RigidTransform())
        q = self.sg.get_query_output_port().Eval(self.sg_context)
        img = q.RenderLabelImage(ColorRenderCamera(core, False), self.sg.world_frame_id(), cam.X_WC)
        return np.array(img.data)[:, :, 0]


def sensor_model(depth: np.ndarray, rng: np.random.Generator, noise: float = 0.0, dropout: float = 0.0) -> np.ndarray:
    """Depth with Gaussian noise (sigma `noise` m) and missing pixels (0) at rate `dropout` (see
    the module doc)."""
    d = np.asarray(depth, np.float32).copy()
    if noise > 0:
        d += rng.normal(0.0, noise, d.shape).astype(np.float32)
    if dropout > 0:
        finite = np.where(np.isfinite(d), d, 0.0)
        edge = np.zeros(d.shape, bool)
        edge[:, 1:] |= np.abs(np.diff(finite, axis=1)) > 0.005
        edge[1:, :] |= np.abs(np.diff(finite, axis=0)) > 0.005
        lost = rng.random(d.shape) < 0.5 * dropout
        n_edge = int(edge.sum())
        if n_edge:
            lost |= edge & (rng.random(d.shape) < min(1.0, 0.5 * dropout * d.size / n_edge))
        d[lost] = 0.0
    return d


def draw_sensor(sensor: str, seed: int, k: int, j: int, v: int) -> tuple[str, DepthSensorParams, np.random.Generator]:
    """(preset name, parameters, Generator for the model's own draws) of view v of heap j of shard k
    (module doc, item 5); seeded by (seed, k, j, v) only, so reproducible and independent of the
    heap's and the camera's draws."""
    if sensor not in SENSOR_OPTIONS:
        raise DatasetError(f"sensor {sensor!r}: choose one of {', '.join(SENSOR_OPTIONS)}")
    rng = np.random.default_rng([int(seed), int(k), int(j), int(v), 29])
    if sensor != "random":
        return sensor, PRESETS[sensor], rng
    name = str(rng.choice(list(PRESETS)))
    p = PRESETS[name]
    if p.is_identity():
        return name, p, rng
    u = rng.uniform
    p = dataclasses.replace(
        p, noise_a=p.noise_a * u(0.5, 2.0), noise_b=p.noise_b * u(0.5, 2.0),
        edge_width=max(1, p.edge_width + int(rng.integers(-1, 2))),
        edge_dropout=min(1.0, p.edge_dropout * u(0.5, 1.5)),
        grazing_deg=float(np.clip(p.grazing_deg + u(-10.0, 10.0), 45.0, 85.0)),
        grazing_dropout=min(1.0, p.grazing_dropout * u(0.5, 1.5)),
        holes=p.holes * u(0.5, 2.0), hole_radius=p.hole_radius * u(0.7, 1.4),
        pixel_dropout=min(0.05, p.pixel_dropout * u(0.5, 1.5)))
    return name, p, rng


def ground_truth(labels: np.ndarray, label_to_name: dict[int, str]) -> tuple[np.ndarray, list[str]]:
    """(instance image uint8: 0 none, k = objects[k - 1]; objects seen with >= MIN_GT_PIXELS pixels)."""
    out = np.zeros(labels.shape, np.uint8)
    names = []
    present, counts = np.unique(labels, return_counts=True)
    for lbl, n in zip(present, counts):
        if int(lbl) in label_to_name and n >= MIN_GT_PIXELS:
            names.append(label_to_name[int(lbl)])
            out[labels == lbl] = len(names)
    return out, names


def instance_masks(inst: np.ndarray, names) -> InstanceMasks:
    """InstanceMasks (ids = object names) of an instance image from `ground_truth`."""
    if not len(names):
        return InstanceMasks.empty(*inst.shape)
    return InstanceMasks(np.stack([inst == k + 1 for k in range(len(names))]), tuple(names), np.ones(len(names)))


def render_views(scenario, heap, views: int, rng: np.random.Generator, noise: float = 0.0,
                 dropout: float = 0.0, sensor: str = "none", sensor_key: tuple = (0, 0, 0)) -> list[dict]:
    """`views` images of one heap: dict(depth, inst, objects, cam); with a `sensor` (module doc,
    item 5; `sensor_key` = (seed, shard, heap) of the draw) also sensor, sensor_params and x (the
    network's inputs from the hole-filled depth)."""
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    r = LabelledHeapRenderer(scenario, heap)
    out = []
    for v in range(views):
        cam = random_camera(nominal, rng)
        depth = sensor_model(r.depth(cam), rng, noise, dropout)
        inst, names = ground_truth(r.labels(cam), r.label_to_name)
        im = dict(depth=depth, inst=inst, objects=names, cam=cam)
        if sensor != "none":
            name, params, srng = draw_sensor(sensor, *sensor_key, v)
            depth = apply_depth_sensor(depth, params, srng, cam.fx, cam.fy, cam.cx, cam.cy)
            im.update(depth=depth, sensor=name, x=working_inputs(preprocess_depth(depth)),
                      sensor_params=np.array([getattr(params, f) for f in SENSOR_FIELDS], np.float32))
        out.append(im)
    return out


def heap_for_image(seed: int, k: int, j: int, split: str, sets=OBJECT_SETS, scenario=None):
    """Heap j of shard k (its seed, object set and split as the writer draws them), and its rng."""
    scenario = scenario or load_scenario(None, "BinHeap15")
    rng = np.random.default_rng([seed, k, j, 5])
    oset = sets[(k * 7919 + j) % len(sets)]
    n = truncated_poisson(rng, MEAN_OBJECTS, 1, MAX_OBJECTS)
    heap = generate_heap(scenario, n, seed * 1_000_000 + k * 1000 + j, object_set=oset,
                         params=HeapParams(engine="bullet", split=split, render=False))
    return heap, oset, rng


def coco_annotations(images: list[dict], image_ids: list[int], file_name: str) -> dict:
    """COCO dict (images, annotations with RLE modal masks, one category) of rendered images;
    annotations also carry the object's full name ("object")."""
    imgs, anns = [], []
    for i, (im, iid) in enumerate(zip(images, image_ids)):
        h, w = im["inst"].shape
        imgs.append({"id": iid, "file_name": f"{file_name}#{i}", "height": int(h), "width": int(w),
                     "objects": list(im["objects"])})
        for k, name in enumerate(im["objects"]):
            rle = mask_utils.encode(np.asfortranarray((im["inst"] == k + 1).astype(np.uint8)))
            area = float(mask_utils.area(rle))
            bbox = [float(v) for v in mask_utils.toBbox(rle)]
            rle["counts"] = rle["counts"].decode("ascii")
            anns.append({"image_id": iid, "category_id": 1, "segmentation": rle, "area": area, "bbox": bbox,
                         "iscrowd": 0, "object": name})
    return {"images": imgs, "annotations": anns, "categories": [{"id": 1, "name": "object"}]}


def shard_job(job: tuple) -> dict:
    """(out, k, seed, heaps, views, sets, noise, dropout[, sensor]) -> writes shard k; module-level for
    pickling."""
    out, k, seed, heaps, views, sets, noise, dropout = job[:8]
    sensor = job[8] if len(job) > 8 else "none"
    split = shard_split(k)
    path = Path(out) / f"shard_{k:05d}_{split}.npz"
    if path.exists():
        return dict(shard=k, images=0, skipped=True)
    scenario = load_scenario(None, "BinHeap15")
    images, t0, failed = [], time.process_time(), 0
    for j in range(heaps):
        try:
            heap, oset, rng = heap_for_image(seed, k, j, split, sets, scenario)
        except HeapError:
            failed += 1
            continue
        for im in render_views(scenario, heap, views, rng, noise, dropout, sensor, (seed, k, j)):
            im.update(set=oset, heap_seed=int(heap.seed))
            images.append(im)
    if not images:
        raise DatasetError(f"shard {k}: every heap failed")
    ids = [k * IMAGE_ID_STRIDE + i for i in range(len(images))]
    coco = coco_annotations(images, ids, path.name)
    cam_K = np.stack([[[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]] for c in (im["cam"] for im in images)])
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    extra = {} if sensor == "none" else dict(sensor=np.array([im["sensor"] for im in images]),
                                             sensor_params=np.stack([im["sensor_params"] for im in images]))
    np.savez_compressed(
        tmp, **extra, depth=np.stack([im["depth"] for im in images]).astype(np.float16),
        labels=np.stack([im["inst"] for im in images]),
        x=np.stack([im["x"] if "x" in im else working_inputs(im["depth"]) for im in images]).astype(np.float16),
        lab=np.stack([working_labels(im["inst"]) for im in images]),
        K=cam_K, X_WC=np.stack([im["cam"].X_WC.GetAsMatrix4() for im in images]),
        objects=np.array([",".join(im["objects"]) for im in images]), set=np.array([im["set"] for im in images]),
        heap_seed=np.array([im["heap_seed"] for im in images], np.int64), image_id=np.array(ids, np.int64),
        split=np.array(split))
    jtmp = path.with_suffix(f".{os.getpid()}.tmp.json")
    jtmp.write_text(json.dumps(coco))
    os.replace(jtmp, path.with_suffix(".json"))
    os.replace(tmp, path)
    return dict(shard=k, images=len(images), skipped=False, cpu=time.process_time() - t0, failed_heaps=failed)


def merge_coco(folder, split: str) -> Path:
    """``coco_<split>.json``: the shards' COCO files of `split` merged (annotation ids 1..)."""
    folder = Path(folder)
    files = sorted(folder.glob(f"shard_*_{split}.json"))
    merged = {"images": [], "annotations": [], "categories": [{"id": 1, "name": "object"}]}
    for f in files:
        c = json.loads(f.read_text())
        merged["images"] += c["images"]
        merged["annotations"] += c["annotations"]
    for i, a in enumerate(merged["annotations"]):
        a["id"] = i + 1
    out = folder / f"coco_{split}.json"
    tmp = out.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(merged))
    os.replace(tmp, out)
    return out


def write_segmentation_dataset(out, count: int, seed: int = 0, views: int = 4, heaps_per_shard: int = 8,
                               workers: int = 1, use_ray: bool = False, ray_address: str | None = None,
                               progress=None, sets=OBJECT_SETS, noise: float = 0.0, dropout: float = 0.0,
                               sensor: str = "none") -> dict:
    """Shards of about `count` images into `out` (see the module doc), then coco_train.json and
    coco_test.json; returns counts. sensor: "none", "random" or a preset (module doc, item 5)."""
    if views < 1 or heaps_per_shard < 1:
        raise DatasetError(f"views={views}, heaps_per_shard={heaps_per_shard}: both must be >= 1")
    if noise < 0 or not 0 <= dropout < 1:
        raise DatasetError(f"noise={noise}, dropout={dropout}: need noise >= 0 and 0 <= dropout < 1")
    if sensor not in SENSOR_OPTIONS:
        raise DatasetError(f"--sensor {sensor!r}: choose one of {', '.join(SENSOR_OPTIONS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per = views * heaps_per_shard
    shards = -(-int(count) // per)
    jobs = [(str(out), k, int(seed), heaps_per_shard, views, tuple(sets), float(noise), float(dropout))
            + ((sensor,) if sensor != "none" else ()) for k in range(shards)]
    todo = [j for j in jobs if not (out / f"shard_{j[1]:05d}_{shard_split(j[1])}.npz").exists()]
    res = dict(shards=shards, skipped=shards - len(todo), written=0, failed=[], images=0, cpu=0.0)
    run_shard_jobs(shard_job, todo, res, ("images", "cpu"), progress, workers=workers, use_ray=use_ray,
                   ray_address=ray_address, max_tasks_per_child=10)
    res["coco"] = [str(merge_coco(out, s)) for s in ("train", "test")]
    return res


def load_working(folder, split: str) -> dict:
    """The working arrays of every `split` shard: x float16 (n, 2, 192, 256), lab uint8 (n, 192, 256),
    objects, set, files."""
    files = sorted(Path(folder).glob(f"shard_*_{split}.npz"))
    if not files:
        raise DatasetError(f"{folder}: no {split} shards (shard_*_{split}.npz); make them with "
                           f"`ms-drake data segmentation --count 4000 --out {folder}`")
    xs, labs, objs, sets = [], [], [], []
    for f in files:
        with np.load(f) as z:
            xs.append(z["x"])
            labs.append(z["lab"])
            objs.append(z["objects"])
            sets.append(z["set"])
    return dict(x=np.concatenate(xs), lab=np.concatenate(labs), objects=np.concatenate(objs),
                set=np.concatenate(sets), files=[str(f) for f in files])
