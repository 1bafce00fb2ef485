"""Target-matching data and benchmark (App. C.2): rendered colour heaps for the siamese matcher of
ms_drake.perception.matcher_net, and the detection benchmark of the `TargetDetector` backends.

Renderer (`ColourHeapRenderer`): the heap's objects in the bin as visual geometry (as
occupancy_data.HeapRenderer), each drawn in a chosen colour, rendering RGB and label images from
any camera; `alone(k, X)` moves every other object out of sight to render object k alone (its
template views and its amodal mask).

`ms-drake data matcher --heaps N --out DIR` writes shards ``matcher_<k>_<split>.npz``, heap j of
shard k being segmentation_data.heap_for_image(seed, k, j, split) (m ~ Poisson(7.5) in [1, 10]
objects of one set; every fifth shard of the test split of the objects, the others of the train
split, so no test object is trained on). Colours: each object takes a colour drawn from the
registry palette and the target red (13 colours); with probability 1/2 two objects are made to
share one (the case where colour alone cannot tell them apart). One jittered overhead view
(occupancy_data.random_camera) of the heap; for every object seen with >= `MIN_PIXELS` pixels:
its crop in the heap (matcher_net.crop of its modal mask), and `TEMPLATE_VIEWS` template crops of
it rendered alone in the same colour, in a random orientation near the bin centre, from the
nominal camera (as perception.target.render_templates). Arrays: ``heap`` (m, 4, 64, 64) float16,
``templates`` (m, T, 4, 64, 64) float16, ``heap_id`` (m,), ``colour`` (m,) int, ``object``
(m,) full names, ``visible`` (m,) modal / amodal pixel ratio. Shards are written atomically; a
rerun skips those on disk.

`bench_target_detection` (``ms-drake bench target-detection``): image s is a heap of held-out
(test-split) objects, sets in turn, 3-10 objects; its target is an object whose visible fraction
(modal / amodal pixels, the reference's occlusion proxy of App. C.3) lies in [0.2, 0.8] (20-80 %
occluded), drawn at random among them (an image without such an object takes the next heap of
its seed). The target is drawn red (objects.TARGET_RGBA) as the search does, the others in palette
colours; on odd seeds a second object (the largest visible other) is drawn red too ("shared
colour" subset). The detector gets the ground-truth modal masks (so the figure is the
detector's alone), the heap's depth image and camera (``sensor``: through a depth sensor preset
of ms_drake.station.sensor_model, seeded by the image's seed; cached clean) and five template
views of the target rendered alone in red, with their depth points. A detection is
correct when its mask is the target's (IoU >= 0.5). Precision = correct / detections, recall =
correct / images (every image holds the target), F1; the same on the shared-colour subset.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from pydrake.geometry import (
    ClippingRange,
    ColorRenderCamera,
    DepthRange,
    DepthRenderCamera,
    MakeRenderEngineVtk,
    RenderCameraCore,
    RenderEngineVtkParams,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo
from scipy.spatial.transform import Rotation

from ms_drake.errors import DatasetError, HeapError
from ms_drake.experiments.occupancy_data import (
    random_camera,
    shard_split,
    truncated_poisson,
)
from ms_drake.experiments.segmentation_data import (
    OBJECT_SETS,
    ground_truth,
    heap_for_image,
    instance_masks,
)
from ms_drake.geometry import PinholeCamera
from ms_drake.objects import TARGET_RGBA
from ms_drake.objects.registry import _PALETTE
from ms_drake.parallel import run_jobs, run_shard_jobs
from ms_drake.perception.matcher_net import crop
from ms_drake.perception.target import TargetDetector, Template
from ms_drake.perception.weights import torch_device
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap
from ms_drake.station.sensor_model import PRESETS, apply_depth_sensor
from ms_drake.station.station import (
    add_environment,
    add_objects,
    make_parser,
    station_objects,
)

COLOURS = [(*c, 1.0) for c in _PALETTE] + [TARGET_RGBA]
RED = len(COLOURS) - 1
MIN_PIXELS = 50
TEMPLATE_VIEWS = 2
BENCH_TEMPLATES = 5
OCCLUSION = (0.2, 0.8)  # occluded fraction of the benchmark's target
DETECTORS = ("color", "template", "learned")


class ColourHeapRenderer:
    """The heap's objects (visual only) in the bin, object k in colour rgba[k]; RGB and label
    images from any PinholeCamera (see the module doc)."""

    def __init__(self, scenario, heap, rgba: list[tuple]):
        builder = DiagramBuilder()
        plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
        sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
        parser = make_parser(plant)
        add_environment(plant, scenario, parser)
        self.instances = add_objects(plant, heap.object_names(), parser=parser,
                                     rgba_overrides={k: tuple(c) for k, c in enumerate(rgba)})
        plant.Finalize()
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()
        self.plant, self.sg = plant, sg
        self.pc = plant.GetMyMutableContextFromRoot(self.context)
        self.q = [np.asarray(op.q, float) for op in heap.objects]
        self.restore()
        self.sg_context = sg.GetMyContextFromRoot(self.context)
        objs = station_objects(plant)
        self.labels_of = [int(o.body_index) for o in objs]
        self.center = np.asarray(scenario.environment.position, float)

    def restore(self):
        for mi, q in zip(self.instances, self.q):
            self.plant.SetPositions(self.pc, mi, q)

    def alone(self, k: int, X: RigidTransform | None = None):
        """Object k alone in view: at its heap pose (X None) or at X; the others far below."""
        for i, (mi, q) in enumerate(zip(self.instances, self.q)):
            if i == k:
                if X is None:
                    self.plant.SetPositions(self.pc, mi, q)
                else:
                    qq = np.concatenate([X.rotation().ToQuaternion().wxyz(), X.translation()])
                    self.plant.SetPositions(self.pc, mi, qq)
            else:
                far = q.copy()
                far[4:7] = (10.0 + 0.5 * i, 10.0, -10.0)
                self.plant.SetPositions(self.pc, mi, far)

    def _core(self, cam: PinholeCamera):
        return RenderCameraCore("vtk", CameraInfo(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy),
                                ClippingRange(0.1, 3.0), RigidTransform())

    def rgb(self, cam: PinholeCamera) -> np.ndarray:
        q = self.sg.get_query_output_port().Eval(self.sg_context)
        img = q.RenderColorImage(ColorRenderCamera(self._core(cam), False), self.sg.world_frame_id(), cam.X_WC)
        return np.array(img.data)[:, :, :3].copy()

    def labels(self, cam: PinholeCamera) -> np.ndarray:
        q = self.sg.get_query_output_port().Eval(self.sg_context)
        img = q.RenderLabelImage(ColorRenderCamera(self._core(cam), False), self.sg.world_frame_id(), cam.X_WC)
        return np.array(img.data)[:, :, 0]

    def depth(self, cam: PinholeCamera) -> np.ndarray:
        """(H, W) float32 depth [m] (inf where nothing is seen)."""
        q = self.sg.get_query_output_port().Eval(self.sg_context)
        img = q.RenderDepthImage(DepthRenderCamera(self._core(cam), DepthRange(0.1, 3.0)), self.sg.world_frame_id(),
                                 cam.X_WC)
        return np.array(img.data)[:, :, 0].astype(np.float32)

    def template(self, k: int, cam: PinholeCamera, rng: np.random.Generator, points: bool = False) -> Template:
        """Object k alone in a random orientation near the bin centre (as render_templates);
        points: with its seen surface points (from the depth image)."""
        R = RotationMatrix(Rotation.random(random_state=rng).as_matrix())
        p = self.center + np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.1])
        self.alone(k, RigidTransform(R, p))
        rgb, mask = self.rgb(cam), self.labels(cam) == self.labels_of[k]
        depth = self.depth(cam) if points else None
        self.restore()
        if not mask.any():
            return None
        return Template.from_view(rgb, mask, depth, cam)

    def amodal_pixels(self, k: int, cam: PinholeCamera) -> int:
        self.alone(k)
        n = int((self.labels(cam) == self.labels_of[k]).sum())
        self.restore()
        return n


def _instances(r: ColourHeapRenderer, cam: PinholeCamera) -> tuple[np.ndarray, list[int]]:
    """(instance image: 0 none, i + 1 = object index objs[i]; object indices seen) of the heap view."""
    lab = r.labels(cam)
    label_to_k = {lbl: k for k, lbl in enumerate(r.labels_of)}
    inst, names = ground_truth(lab, {lbl: str(k) for lbl, k in label_to_k.items()})
    return inst, [int(n) for n in names]


def training_colours(n: int, rng: np.random.Generator) -> list[int]:
    cols = [int(c) for c in rng.integers(0, len(COLOURS), n)]
    if n >= 2 and rng.random() < 0.5:
        a, b = rng.choice(n, 2, replace=False)
        cols[int(b)] = cols[int(a)]
    return cols


def matcher_shard_job(job: tuple) -> dict:
    """(out, k, seed, heaps) -> writes matcher shard k; module-level for pickling."""
    out, k, seed, heaps = job
    split = shard_split(k)
    path = Path(out) / f"matcher_{k:05d}_{split}.npz"
    if path.exists():
        return dict(shard=k, crops=0, skipped=True)
    scenario = load_scenario(None, "BinHeap15")
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    heap_c, tmpl_c, heap_id, colour, names, visible = [], [], [], [], [], []
    t0, failed = time.process_time(), 0
    for j in range(heaps):
        try:
            heap, _, rng = heap_for_image(seed, k, j, split, OBJECT_SETS, scenario)
        except HeapError:
            failed += 1
            continue
        rng = np.random.default_rng([seed, k, j, 17])
        n = len(heap.objects)
        cols = training_colours(n, rng)
        r = ColourHeapRenderer(scenario, heap, [COLOURS[c] for c in cols])
        cam = random_camera(nominal, rng)
        rgb = r.rgb(cam)
        inst, seen = _instances(r, cam)
        for i, obj in enumerate(seen):
            mask = inst == i + 1
            if mask.sum() < MIN_PIXELS:
                continue
            views = [r.template(obj, nominal, rng) for _ in range(TEMPLATE_VIEWS)]
            if any(v is None for v in views):
                continue
            heap_c.append(crop(rgb, mask))
            tmpl_c.append(np.stack([crop(v.rgb, v.mask) for v in views]))
            heap_id.append(k * 1000 + j)
            colour.append(cols[obj])
            names.append(heap.objects[obj].name)
            visible.append(mask.sum() / max(r.amodal_pixels(obj, cam), 1))
    if not heap_c:
        raise DatasetError(f"matcher shard {k}: no object crops (every heap failed)")
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, heap=np.stack(heap_c).astype(np.float16), templates=np.stack(tmpl_c).astype(np.float16),
                        heap_id=np.array(heap_id, np.int64), colour=np.array(colour, np.int64),
                        object=np.array(names), visible=np.array(visible, np.float32), split=np.array(split))
    os.replace(tmp, path)
    return dict(shard=k, crops=len(heap_c), skipped=False, cpu=time.process_time() - t0, failed_heaps=failed)


def write_matcher_dataset(out, heaps: int, seed: int = 0, heaps_per_shard: int = 10, workers: int = 1,
                          progress=None) -> dict:
    """Shards of `heaps` heaps (rounded up to whole shards) into `out`; returns counts."""
    if heaps_per_shard < 1:
        raise DatasetError(f"heaps_per_shard={heaps_per_shard}: must be >= 1")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shards = -(-int(heaps) // heaps_per_shard)
    jobs = [(str(out), k, int(seed), heaps_per_shard) for k in range(shards)
            if not (out / f"matcher_{k:05d}_{shard_split(k)}.npz").exists()]
    res = dict(shards=shards, skipped=shards - len(jobs), written=0, crops=0, cpu=0.0, failed=[])
    return run_shard_jobs(matcher_shard_job, jobs, res, ("crops", "cpu"), progress, workers=workers)


def load_matcher_data(folder, split: str) -> dict:
    """The arrays of every `split` shard of `folder`, concatenated."""
    files = sorted(Path(folder).glob(f"matcher_*_{split}.npz"))
    if not files:
        raise DatasetError(f"{folder}: no {split} shards (matcher_*_{split}.npz); make them with "
                           f"`ms-drake data matcher --heaps 400 --out {folder}`")
    parts = {}
    for f in files:
        with np.load(f) as z:
            for key in ("heap", "templates", "heap_id", "colour", "object", "visible"):
                parts.setdefault(key, []).append(z[key])
    return {k: np.concatenate(v) for k, v in parts.items()}


# ---------------------------------------------------------------------------------------------
# Benchmark: precision / recall / F1 of target detection


def bench_scene(seed: int, scenario=None, attempts: int = 8) -> dict:
    """Benchmark image `seed` (see the module doc): rgb, ground-truth InstanceMasks, the target's
    index among them, its visible fraction, shared (bool) and the target's templates."""
    scenario = scenario or load_scenario(None, "BinHeap15")
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    for a in range(attempts):
        rng = np.random.default_rng([seed, a, 29])
        oset = OBJECT_SETS[(seed + a) % len(OBJECT_SETS)]
        n = truncated_poisson(rng, 7.5, 3, 10)
        try:
            heap = generate_heap(scenario, n, seed * 100 + a + 7_000_000, object_set=oset,
                                 params=HeapParams(engine="bullet", split="test", render=False))
        except HeapError:
            continue
        n = len(heap.objects)
        cols = [int(c) for c in rng.integers(0, RED, n)]
        r = ColourHeapRenderer(scenario, heap, [COLOURS[c] for c in cols])
        cam = random_camera(nominal, rng)
        inst, seen = _instances(r, cam)
        vis = {}
        for i, obj in enumerate(seen):
            px = int((inst == i + 1).sum())
            if px >= MIN_PIXELS:
                vis[obj] = px / max(r.amodal_pixels(obj, cam), 1)
        ok = [o for o, v in vis.items() if OCCLUSION[0] <= 1.0 - v <= OCCLUSION[1]]
        if not ok:
            continue
        target = int(rng.choice(sorted(ok)))
        cols[target] = RED
        shared = seed % 2 == 1 and len(seen) >= 2
        other = -1
        if shared:
            others = [(int((inst == i + 1).sum()), o) for i, o in enumerate(seen) if o != target]
            other = max(others)[1]
            cols[other] = RED
        r = ColourHeapRenderer(scenario, heap, [COLOURS[c] for c in cols])
        rgb = r.rgb(cam)
        masks = instance_masks(inst, [str(o) for o in seen])
        depth = r.depth(cam)
        templates = [t for t in (r.template(target, nominal, rng, points=True) for _ in range(BENCH_TEMPLATES))
                     if t is not None]
        return dict(rgb=rgb, depth=depth, camera=cam, masks=masks, target=seen.index(target), visible=vis[target],
                    shared=shared,
                    objects=n, target_name=heap.objects[target].name, set=oset, templates=templates,
                    other=heap.objects[other].name if other >= 0 else "")
    raise DatasetError(f"benchmark image {seed}: no heap with a target {OCCLUSION[0]:.0%}-{OCCLUSION[1]:.0%} "
                       f"occluded in {attempts} attempts")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 0.0


def save_scene(sc: dict, path: Path) -> None:
    """A bench_scene on disk (atomically), so several backends are scored on the same images."""
    inst = np.zeros(sc["masks"].masks.shape[1:], np.uint8)
    for k, m in enumerate(sc["masks"].masks):
        inst[m] = k + 1
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    cam = sc["camera"]
    np.savez_compressed(tmp, rgb=sc["rgb"], inst=inst, ids=np.array(sc["masks"].ids), depth=sc["depth"],
                        K=np.array([cam.fx, cam.fy, cam.cx, cam.cy]), X_WC=cam.X_WC.GetAsMatrix4(),
                        t_rgb=np.array([t.rgb for t in sc["templates"]] + [None], dtype=object)[:-1],
                        t_mask=np.array([t.mask for t in sc["templates"]] + [None], dtype=object)[:-1],
                        t_points=np.array([t.points for t in sc["templates"]] + [None], dtype=object)[:-1],
                        meta=json.dumps({k: sc[k] for k in ("target", "visible", "shared", "objects", "target_name",
                                                            "set", "other")}))
    os.replace(tmp, path)


def load_scene(path: Path) -> dict:
    """A save_scene file; one written before the depth was kept lacks depth and camera."""
    with np.load(path, allow_pickle=True) as z:
        meta = json.loads(str(z["meta"]))
        ids = [str(i) for i in z["ids"]]
        points = z["t_points"] if "t_points" in z else [None] * len(z["t_rgb"])
        meta.update(rgb=z["rgb"], masks=instance_masks(z["inst"], ids),
                    templates=[Template(r, m, p) for r, m, p in zip(z["t_rgb"], z["t_mask"], points)])
        if "depth" in z:
            h, w = z["rgb"].shape[:2]
            fx, fy, cx, cy = (float(v) for v in z["K"])
            meta.update(depth=z["depth"], camera=PinholeCamera(w, h, fx, fy, cx, cy, RigidTransform(z["X_WC"])))
    return meta


def bench_detection_job(job: tuple) -> dict:
    """(backend, seed, weights[, scene_dir[, sensor[, device]]]) -> one benchmark record; module-level
    for pickling. scene_dir: images are read from / saved to it (scene_<seed>.npz); sensor: the depth
    sensor preset the heap's depth image goes through (seeded by the image's seed); device: where
    the learned backend's network runs (cpu | cuda | auto)."""
    backend, seed, weights, *rest = job
    cache = Path(rest[0]) / f"scene_{seed}.npz" if rest and rest[0] else None
    sensor = rest[1] if len(rest) > 1 and rest[1] else "none"
    device = rest[2] if len(rest) > 2 else "cpu"
    if sensor not in PRESETS:
        raise DatasetError(f"sensor {sensor!r} unknown; choose one of {', '.join(PRESETS)}")
    if cache is not None and cache.exists():
        sc = load_scene(cache)
        if "depth" not in sc:
            sc = bench_scene(seed)
            save_scene(sc, cache)
    else:
        sc = bench_scene(seed)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            save_scene(sc, cache)
    h, w = sc["rgb"].shape[:2]
    cam, depth = sc["camera"], sc["depth"]
    if sensor != "none":
        depth = apply_depth_sensor(depth, PRESETS[sensor], np.random.default_rng([seed, 31]), cam.fx, cam.fy, cam.cx,
                                   cam.cy, sc["rgb"])
    det = TargetDetector(backend, width=w, height=h, templates=sc["templates"] if backend != "color" else None,
                         weights=weights, camera=cam, device=device)
    t0, c0 = time.perf_counter(), time.process_time()
    est = det.detect(sc["rgb"], sc["masks"], depth)
    secs, cpu = time.perf_counter() - t0, time.process_time() - c0
    truth = sc["masks"].masks[sc["target"]]
    correct = bool(est.visible and _iou(est.mask, truth) >= 0.5)
    return dict(seed=seed, backend=backend, sensor=sensor, detected=bool(est.visible), correct=correct,
                confidence=float(est.confidence), visible=float(sc["visible"]), shared=bool(sc["shared"]),
                objects=int(sc["objects"]), target=sc["target_name"], other=sc["other"], set=sc["set"],
                seconds=secs, cpu_seconds=cpu)


def detection_metrics(recs: list[dict]) -> dict:
    n = len(recs)
    det = sum(r["detected"] for r in recs)
    tp = sum(r["correct"] for r in recs)
    p = tp / det if det else float("nan")
    rec = tp / n if n else float("nan")
    f1 = 2 * p * rec / (p + rec) if det and (p + rec) > 0 else 0.0
    return dict(images=n, detections=det, correct=tp, precision=p, recall=rec, f1=f1)


def bench_target_detection(backend: str, images: int, seed_start: int, out, workers: int = 1, weights=None,
                           progress=None, scene_dir=None, sensor: str = "none", device: str = "cpu") -> dict:
    """Run the missing images of seeds S..S+N-1 (one JSON line each in OUT.jsonl next to `out`,
    resumable), then write `out` (JSON: metrics overall and on the shared-colour subset).
    scene_dir: a folder caching the rendered images, shared by the backends' runs. sensor: the
    depth sensor preset (station.sensor_model.PRESETS) of the depth image the detector gets.
    device: where the learned backend's network runs in each worker (cpu | cuda | auto)."""
    if backend not in DETECTORS:
        raise DatasetError(f"backend {backend!r} unknown; choose one of {', '.join(DETECTORS)}")
    if sensor not in PRESETS:
        raise DatasetError(f"sensor {sensor!r} unknown; choose one of {', '.join(PRESETS)}")
    if backend == "learned":
        torch_device(device)  # a device this machine lacks fails here, before any job
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    lines = out.with_suffix(".jsonl")
    recs = []
    if lines.exists():
        for line in lines.read_text().splitlines():
            try:
                recs.append(json.loads(line))
            except ValueError:
                continue

    def mine(r: dict) -> bool:
        return r.get("backend") == backend and r.get("sensor", "none") == sensor

    done = {r["seed"] for r in recs if mine(r)}
    jobs = [(backend, s, None if weights is None else str(weights), None if scene_dir is None else str(scene_dir),
             sensor, device) for s in range(seed_start, seed_start + images) if s not in done]
    with open(lines, "a") as f:
        for r in run_jobs(bench_detection_job, jobs, workers=workers):
            if r.ok:
                f.write(json.dumps(r.value) + "\n")
                f.flush()
                recs.append(r.value)
            if progress is not None:
                progress(r)
    recs = [r for r in recs if mine(r) and seed_start <= r["seed"] < seed_start + images]
    vis = [r["visible"] for r in recs]
    res = dict(backend=backend, sensor=sensor, seed_start=seed_start, **detection_metrics(recs),
               shared_colour=detection_metrics([r for r in recs if r["shared"]]),
               distinct_colour=detection_metrics([r for r in recs if not r["shared"]]),
               occluded_fraction=[1.0 - max(vis), 1.0 - min(vis)] if vis else [],
               occlusion_range=list(OCCLUSION), median_cpu_seconds=float(np.median([r["cpu_seconds"] for r in recs])) if recs else float("nan"),
               median_seconds=float(np.median([r["seconds"] for r in recs])) if recs else
               float("nan"), failed=images - len(recs))
    tmp = out.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(res, indent=1))
    os.replace(tmp, out)
    return res
