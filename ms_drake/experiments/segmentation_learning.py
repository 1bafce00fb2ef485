"""Training of the learned depth segmenter and the Table B.1 benchmark (Ch. 5.5-5.6).

`train_segmentation` (``ms-drake train segmentation --data DIR --out FILE.pt``): AdamW (lr 2e-3,
weight decay 1e-4, cosine decay to 0), batches of 16 random `crop` windows (96 x 128 working
pixels, a quarter of the 192 x 256 image), half of them anywhere in the image and half centred
on an object pixel of the image (+- 24 px), random horizontal and vertical flips; pixelwise
cross-entropy on the three classes of segmentation_net. Our choices where the reference's (SGD,
lr 0.01, momentum 0.9, 60 epochs on a Titan X) does not fit two shared CPU cores: the network is
fully convolutional, so it learns from windows and runs on the whole image, at a quarter of the
cost per image. Deterministic from `seed` (the batch order and windows of epoch e come from
(seed, e)). It trains on `device` (cpu | cuda | auto; perception.weights.torch_device). After
every epoch the model, optimizer and scheduler go to ``FILE.ckpt`` (experiments.training; tensors
on the CPU), so a killed run resumes with the same command; ``FILE`` (written after every epoch
too) holds the weights, the network configuration and a `meta` dict (data, command, epochs,
seconds, losses, device).

`bench_segmentation` (``ms-drake bench segmentation --backend B --images N --seed-start S``): image
s is heap s of held-out objects (the test split of its object set; sets taken in turn by seed,
m ~ Poisson(7.5) truncated to [1, 10]) seen by one jittered overhead camera
(occupancy_data.random_camera), as the dataset draws them; the backend segments its depth
image; COCO mask AP (IoU 0.50:0.95), AP50 and AR@100 by pycocotools over all images
(segmentation.coco_metrics), and the median wall and CPU seconds per image of the backend alone.
"""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from pydrake.math import RigidTransform

from ms_drake.errors import DatasetError, HeapError
from ms_drake.experiments.occupancy_data import random_camera, truncated_poisson
from ms_drake.experiments.segmentation_data import (
    MAX_OBJECTS,
    MEAN_OBJECTS,
    OBJECT_SETS,
    LabelledHeapRenderer,
    ground_truth,
    instance_masks,
    sensor_model,
)
from ms_drake.experiments.training import (
    fit_batch,
    resume,
    save_atomically,
    save_checkpoint,
    torch_setup,
)
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.parallel import run_jobs
from ms_drake.perception.segmentation import Segmenter, coco_metrics, encode_masks
from ms_drake.perception.segmentation_net import (
    IGNORE,
    WORK_SHAPE,
    NetConfig,
    class_targets,
    make_net,
    segmentation_loss,
    working_inputs,
)
from ms_drake.perception.weights import torch_device
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap
from ms_drake.station.sensor_model import apply_depth_sensor, depth_sensor_params, image_rng

CROP_SHAPE = (96, 128)
BENCH_BACKENDS = ("euclidean", "region_growing", "learned", "ground_truth")


def _windows(lab: np.ndarray, shape, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Top-left corners of one `shape` window per image: half of them anywhere in the image (the bin's
    walls and empty floor must be learnt too), half centred on a random object pixel (+- 24 px)."""
    H, W = lab.shape[1:]
    h, w = shape
    out = []
    for im in lab:
        if rng.random() < 0.5:
            out.append((int(rng.integers(0, H - h + 1)), int(rng.integers(0, W - w + 1))))
            continue
        ys, xs = np.nonzero(im > 0)
        if len(ys):
            j = int(rng.integers(len(ys)))
            cy, cx = ys[j] + int(rng.integers(-24, 25)), xs[j] + int(rng.integers(-24, 25))
        else:
            cy, cx = H // 2, W // 2
        out.append((int(np.clip(cy - h // 2, 0, H - h)), int(np.clip(cx - w // 2, 0, W - w))))
    return out


def make_batch(x: np.ndarray, y: np.ndarray, idx, rng: np.random.Generator, shape=CROP_SHAPE):
    """(inputs (B, 2, h, w) float32, classes (B, h, w) int64): windows and flips of images `idx`."""
    xs, ys = [], []
    corners = _windows(y[idx], shape, rng) if shape is not None else [(0, 0)] * len(idx)
    h, w = shape if shape is not None else y.shape[1:]
    for i, (t, l) in zip(idx, corners):
        xi = x[i, :, t:t + h, l:l + w].astype(np.float32)
        yi = y[i, t:t + h, l:l + w]
        if rng.random() < 0.5:
            xi, yi = xi[..., ::-1], yi[..., ::-1]
        if rng.random() < 0.5:
            xi, yi = xi[..., ::-1, :], yi[..., ::-1, :]
        xs.append(xi)
        ys.append(yi)
    return np.ascontiguousarray(np.stack(xs)), np.ascontiguousarray(np.stack(ys)).astype(np.int64)


def make_optimizer(net, lr: float = 2e-3, weight_decay: float = 1e-4):
    import torch  # optional heavy dependency: only the learned segmenter needs it

    return torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)


def train_steps(net, opt, x, y, steps: int = 1) -> list[float]:
    """`steps` optimizer steps on one fixed batch (numpy: inputs (B, 2, h, w), classes (B, h, w));
    the losses before each step."""
    import torch  # optional heavy dependency: only the learned segmenter needs it

    xt, yt = torch.from_numpy(np.asarray(x, np.float32)), torch.from_numpy(np.asarray(y, np.int64))
    return fit_batch(net, opt, lambda: segmentation_loss(net(xt), yt), steps)


def object_subset(names, fraction: float, seed: int = 0) -> set[str]:
    """The training objects kept by an object subset (Fig. 5.6, right): in each object set (the
    part of the full name before "/"), the first ceil(fraction x its count) of `names` in an order
    drawn from `seed`. The order depends only on the names and the seed, so the subsets of one seed
    are nested (the 25 % subset is inside the 50 % one)."""
    if not 0 < fraction <= 1:
        raise DatasetError(f"object fraction {fraction}: give a fraction in (0, 1], e.g. 0.25")
    by_set: dict[str, list[str]] = {}
    for n in sorted(set(names)):
        by_set.setdefault(n.split("/")[0], []).append(n)
    keep = set()
    for oset, members in sorted(by_set.items()):
        rng = np.random.default_rng([seed, 56, len(members)])
        order = rng.permutation(len(members))
        keep |= {members[i] for i in order[:int(np.ceil(fraction * len(members)))]}
    return keep


class TrainingImages:
    """The working arrays and class targets of the train shards of `data` (the first `max_images`);
    `refresh()` adds shards written since (a dataset still being generated).

    object_fraction: train on a subset of the objects (`object_subset` of the objects in the
    images loaded, drawn from `object_seed`): the pixels of the other objects, and the boundary
    band on their side of a contact, become IGNORE (no loss); the images and their backgrounds stay.
    Images whose objects are all in a 25 % subset are too rare to select (7.5 objects per heap)."""

    def __init__(self, data, max_images: int | None = None, object_fraction: float | None = None,
                 object_seed: int = 0, depth: bool = False):
        self.data, self.max_images, self.keep_depth = Path(data), max_images, depth
        self.depth = np.zeros((0, 480, 640), np.float16)
        self.object_fraction, self.object_seed = object_fraction, object_seed
        self.files: list[str] = []
        self.x = np.zeros((0, 2, *WORK_SHAPE), np.float16)
        self.y = np.zeros((0, *WORK_SHAPE), np.uint8)
        self.lab = np.zeros((0, *WORK_SHAPE), np.uint8)
        self.objects: list[list[str]] = []
        self.kept: set[str] = set()
        self.refresh()

    def refresh(self) -> int:
        files = [str(f) for f in sorted(self.data.glob("shard_*_train.npz"))]
        new = [f for f in files if f not in self.files]
        if self.max_images is not None and len(self.x) >= self.max_images:
            new = []
        if new:
            xs, ys, labs, depths = [self.x], [self.y], [self.lab], [self.depth]
            for f in new:
                with np.load(f) as z:
                    xs.append(z["x"])
                    if self.keep_depth:
                        depths.append(z["depth"])
                    ys.append(np.stack([class_targets(m) for m in z["lab"]]).astype(np.uint8))
                    self.objects += [[n for n in str(o).split(",") if n] for o in z["objects"]]
                    if self.object_fraction is not None:
                        labs.append(z["lab"])
            self.x, self.y = np.concatenate(xs)[:self.max_images], np.concatenate(ys)[:self.max_images]
            self.files += new
            self.objects = self.objects[:self.max_images]
            if self.keep_depth:
                self.depth = np.concatenate(depths)[:self.max_images]
            if self.object_fraction is not None:
                self.lab = np.concatenate(labs)[:self.max_images]
                self._ignore_other_objects()
        return len(self.x)

    def _ignore_other_objects(self) -> None:
        self.kept = object_subset([n for o in self.objects for n in o], self.object_fraction, self.object_seed)
        for i, (lab, names) in enumerate(zip(self.lab, self.objects)):
            y = class_targets(lab).astype(np.uint8)  # afresh: a grown pool can change the subset
            y[np.isin(lab, [k + 1 for k, n in enumerate(names) if n not in self.kept])] = IGNORE
            self.y[i] = y

    def object_counts(self) -> dict:
        """Objects in the images loaded and objects trained on (all of them without a subset)."""
        seen = {n for o in self.objects for n in o}
        return dict(objects_seen=len(seen), objects_trained=len(self.kept) if self.object_fraction else None)


def augmented_inputs(images: TrainingImages, idx, rng: np.random.Generator, noise: float,
                     dropout: float) -> np.ndarray:
    """The working inputs of images `idx`, each with probability 1/2 remade from its depth image
    with sensor noise and dropout (`sensor_model`)."""
    x = images.x[idx].astype(np.float32)
    for j, i in enumerate(idx):
        if rng.random() < 0.5:
            x[j] = working_inputs(sensor_model(images.depth[i], rng, noise, dropout))
    return x


def train_segmentation(data, out, epochs: int = 8, batch: int = 16, seed: int = 0, threads: int = 1,
                       config: NetConfig | None = None, max_minutes: float = 60.0, progress=None, command: str = "",
                       lr: float = 2e-3, max_images: int | None = None, steps_per_epoch: int | None = None,
                       init=None, object_fraction: float | None = None, noise: float = 0.0,
                       dropout: float = 0.0, device="cpu") -> dict:
    """Train on the train shards of `data` (the first `max_images` if given); write `out` (weights +
    meta) and `out`.ckpt (resume). Stops early (after a whole epoch) when `max_minutes` of wall
    time would be exceeded.

    steps_per_epoch None: an epoch is one pass over the images. Given: an epoch is that many
    batches, drawn from the train shards on disk when it starts (training can start while
    `ms-drake data segmentation` is still writing; each epoch's image count is in the history).
    init: a weights file to start from (fine-tuning; its network configuration is used).
    object_fraction: supervise only that fraction of the training objects (`TrainingImages`; the
    subset is drawn from `seed`).
    noise, dropout: sensor augmentation: each image of a batch, with probability 1/2, is made again
    from its full-resolution depth through `sensor_model(depth, rng, noise, dropout)` (the writer's
    sensor model) before its window is cut.
    device: where the network trains (cpu | cuda | auto)."""
    torch = torch_setup(seed, threads)
    dev = torch_device(device)
    config = config or NetConfig()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = out.with_suffix(".ckpt")
    augment = noise > 0 or dropout > 0
    images = TrainingImages(data, max_images, object_fraction, seed, depth=augment)
    n = len(images.x)
    if n == 0:
        raise DatasetError(f"{data}: no train shards (shard_*_train.npz); make them with "
                           f"`ms-drake data segmentation --count 4000 --out {data}`")
    if n < batch:
        raise DatasetError(f"{data}: {n} training images, fewer than a batch ({batch}); make more with "
                           "`ms-drake data segmentation --count ...`")
    if init is not None:
        ck = torch.load(init, map_location="cpu", weights_only=False)
        config = NetConfig(**ck["config"])
    net = make_net(config)
    if init is not None:
        net.load_state_dict(ck["model"])
    net.to(dev)
    opt = make_optimizer(net, lr)
    steps = steps_per_epoch or n // batch
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps)
    settings = dict(config=asdict(config), epochs=epochs, batch=batch, lr=lr, seed=seed, max_images=max_images,
                    steps_per_epoch=steps_per_epoch, n=None if steps_per_epoch else n,
                    init=None if init is None else str(init))
    if object_fraction is not None:
        settings["object_fraction"] = object_fraction
    if augment:
        settings.update(noise=noise, dropout=dropout)
    start, history, seconds = resume(torch, ckpt, settings, net, opt, sched)
    t0 = time.perf_counter() - seconds
    for epoch in range(start, epochs):
        te = time.perf_counter()
        if epoch > 0 and (te - t0) / epoch * (epoch + 1) > 60.0 * max_minutes:
            break
        if steps_per_epoch:
            n = images.refresh()
        rng = np.random.default_rng([seed, epoch])
        order = np.concatenate([rng.permutation(n) for _ in range(-(-steps * batch // n))])
        net.train()
        total = 0.0
        for b in range(steps):
            idx = np.sort(order[b * batch:(b + 1) * batch])
            if augment:
                xb, yb = make_batch(augmented_inputs(images, idx, rng, noise, dropout), images.y[idx],
                                    np.arange(len(idx)), rng)
            else:
                xb, yb = make_batch(images.x, images.y, idx, rng)
            opt.zero_grad()
            loss = segmentation_loss(net(torch.from_numpy(xb).to(dev)), torch.from_numpy(yb).to(dev))
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
            if progress is not None:
                progress(epoch, b, steps, loss.item())
        history.append(dict(epoch=epoch + 1, loss=total / steps, images=n, seconds=time.perf_counter() - te))
        save_checkpoint(torch, ckpt, settings, net, opt, sched, epoch + 1, history, time.perf_counter() - t0)
        save_atomically(torch, dict(model=net.state_dict(), config=asdict(config),
                                    meta=_meta(data, n, history, epochs, batch, seed, lr, t0, command, torch,
                                               images, noise, dropout, dev)), out)
    meta = _meta(data, n, history, epochs, batch, seed, lr, t0, command, torch, images, noise, dropout, dev)
    save_atomically(torch, dict(model=net.state_dict(), config=asdict(config), meta=meta), out)
    return meta


def _meta(data, n, history, epochs, batch, seed, lr, t0, command, torch, images, noise=0.0,
          dropout=0.0, device="cpu") -> dict:
    return dict(data=str(data), train_images=n, epochs_done=len(history), epochs=epochs, batch=batch, seed=seed,
                lr=lr, crop=list(CROP_SHAPE), seconds=time.perf_counter() - t0, history=list(history),
                command=command, torch=torch.__version__, device=str(device),
                object_fraction=images.object_fraction, noise=noise, dropout=dropout,
                **images.object_counts())


# ---------------------------------------------------------------------------------------------
# Table B.1: held-out images from seeds, each backend, COCO AP / AR


def bench_image(seed: int, noise: float = 0.0, dropout: float = 0.0, scenario=None):
    """(depth (480, 640) float32 m, ground-truth InstanceMasks, camera) of benchmark image `seed`:
    a heap of held-out (test-split) objects, one jittered camera (see the module doc)."""
    scenario = scenario or load_scenario(None, "BinHeap15")
    rng = np.random.default_rng([seed, 91])
    oset = OBJECT_SETS[seed % len(OBJECT_SETS)]
    n = truncated_poisson(rng, MEAN_OBJECTS, 1, MAX_OBJECTS)
    heap = generate_heap(scenario, n, seed, object_set=oset, params=HeapParams(engine="bullet", split="test",
                                                                              render=False))
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    r = LabelledHeapRenderer(scenario, heap)
    cam = random_camera(nominal, rng)
    depth = sensor_model(r.depth(cam), rng, noise, dropout)
    inst, names = ground_truth(r.labels(cam), r.label_to_name)
    return depth, instance_masks(inst, names), cam


def sensor_rng(seed: int, cam: PinholeCamera, scenario=None) -> np.random.Generator:
    """The Generator of benchmark image `seed` as `bench_image` holds it when it applies the sensor
    model (after the object count and the camera), so a cached noise-free image gets the same noise
    and dropout as a rendering with them; `cam` (the image's camera) checks the replay."""
    scenario = scenario or load_scenario(None, "BinHeap15")
    rng = np.random.default_rng([seed, 91])
    truncated_poisson(rng, MEAN_OBJECTS, 1, MAX_OBJECTS)
    nominal = PinholeCamera.from_config(scenario.cameras[next(iter(scenario.cameras))])
    replay = random_camera(nominal, rng)
    if not np.allclose([replay.fx, replay.fy, replay.cx, replay.cy], [cam.fx, cam.fy, cam.cx, cam.cy]):
        raise DatasetError(f"image {seed}: the cached camera differs from the seed's; delete the cache's "
                           f"img_{seed}_*.npz files and rerun")
    return rng


def make_segmenter(backend: str, cam: PinholeCamera, workspace: Workspace, weights=None,
                   fill_holes: bool = True, device="cpu") -> Segmenter:
    if backend == "learned":
        return Segmenter("learned", weights=weights, fill_holes=fill_holes, device=device)
    return Segmenter(backend, camera=cam, workspace=workspace, label_to_id={}, fill_holes=fill_holes)


#: The camera name the benchmark images' sensor model draws with (BinHeap15's overhead camera).
BENCH_CAMERA = "overhead"


def sensor_image(depth: np.ndarray, seed: int, cam: PinholeCamera, sensor: str) -> np.ndarray:
    """Benchmark image `seed`'s depth through the depth sensor model `sensor` (a preset name of
    ms_drake.station.sensor_model), drawn from image_rng(seed, BENCH_CAMERA, 0): what the station's
    overhead camera with that model gives for a scenario with random_seed = seed at time 0. No
    colour image here, so no dark-surface dropout."""
    params = depth_sensor_params(sensor)
    if params.is_identity():
        return depth
    return apply_depth_sensor(depth, params, image_rng(seed, BENCH_CAMERA, 0.0), cam.fx, cam.fy, cam.cx, cam.cy)


def cached_bench_image(seed: int, noise: float, dropout: float, scenario, cache) -> tuple:
    """`bench_image`, kept in (or read from) ``cache/img_<seed>_<noise>_<dropout>.npz`` if `cache`; with
    noise or dropout, made from the cached noise-free image when there is one (no rendering, nothing
    written: the noise costs milliseconds)."""
    f = None if cache is None else Path(cache) / f"img_{seed}_{noise:g}_{dropout:g}.npz"
    if f is not None and f.exists():
        with np.load(f) as z:
            cam = PinholeCamera(640, 480, *[float(v) for v in z["intrinsics"]], RigidTransform(z["X_WC"]))
            return z["depth"], instance_masks(z["inst"], [str(v) for v in z["objects"]]), cam
    clean = None if cache is None else Path(cache) / f"img_{seed}_0_0.npz"
    if (noise > 0 or dropout > 0) and clean is not None and clean.exists():
        depth, gt, cam = cached_bench_image(seed, 0.0, 0.0, scenario, cache)
        return sensor_model(depth, sensor_rng(seed, cam, scenario), noise, dropout), gt, cam
    depth, gt, cam = bench_image(seed, noise, dropout, scenario)
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        inst = np.zeros(depth.shape, np.uint8)
        for k, m in enumerate(gt.masks):
            inst[m] = k + 1
        tmp = f.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, depth=depth, inst=inst, objects=np.array(gt.ids, dtype=str),
                            intrinsics=np.array([cam.fx, cam.fy, cam.cx, cam.cy]), X_WC=cam.X_WC.GetAsMatrix4())
        os.replace(tmp, f)
    return depth, gt, cam


def bench_job(job: tuple) -> list[dict]:
    """(backend, seeds, noise, dropout, weights[, cache[, sensor[, fill_holes[, device]]]]) -> per image:
    RLEs of ground truth and detections, seconds; module-level for pickling."""
    backend, seeds, noise, dropout, weights = job[:5]
    cache = job[5] if len(job) > 5 else None
    sensor = job[6] if len(job) > 6 else "none"
    fill_holes = job[7] if len(job) > 7 else True
    device = job[8] if len(job) > 8 else "cpu"
    scenario = load_scenario(None, "BinHeap15")
    ws = Workspace.from_scenario(scenario)
    out, learned = [], None
    for s in seeds:
        try:
            depth, gt, cam = cached_bench_image(s, noise, dropout, scenario, cache)
        except HeapError as e:
            out.append(dict(seed=s, error=str(e)))
            continue
        depth = sensor_image(depth, s, cam, sensor)
        if backend == "learned":
            learned = learned or make_segmenter("learned", cam, ws, weights, fill_holes, device)
            seg = learned
        else:
            seg = make_segmenter(backend, cam, ws, fill_holes=fill_holes)
        t, c = time.perf_counter(), time.process_time()
        pred = gt if backend == "ground_truth" else seg.segment(depth=depth)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        out.append(dict(seed=s, gt=encode_masks(gt), dt=encode_masks(pred), seconds=dt, cpu_seconds=dc))
    return out


def bench_segmentation(backend: str, images: int, seed_start: int, workers: int = 1, noise: float = 0.0,
                       dropout: float = 0.0, weights=None, progress=None, chunk: int = 10, cache=None,
                       sensor: str = "none", fill_holes: bool = True, device: str = "cpu") -> dict:
    """Table B.1 row of `backend` on images seed_start .. seed_start + images - 1 (module doc).
    cache: a folder keeping the rendered images (and ground truth) for the other backends.
    sensor: a depth sensor preset applied to each image (`sensor_image`; the cache keeps the
    clean image); fill_holes: the segmenter reads its depth through geometry.preprocess_depth;
    device: where the learned backend's network runs in each worker (cpu | cuda | auto)."""
    if backend not in BENCH_BACKENDS:
        raise DatasetError(f"--backend {backend!r}: choose one of {', '.join(BENCH_BACKENDS)}")
    depth_sensor_params(sensor)  # an unknown preset fails here, before any job
    if backend == "learned":
        torch_device(device)  # so does a device this machine lacks
    seeds = list(range(seed_start, seed_start + images))
    jobs = [(backend, tuple(seeds[i:i + chunk]), noise, dropout, None if weights is None else str(weights),
             None if cache is None else str(cache), sensor, bool(fill_holes), device)
            for i in range(0, len(seeds), chunk)]
    rows = []
    for r in run_jobs(bench_job, jobs, workers=workers, max_tasks_per_child=5):
        if not r.ok:
            raise DatasetError(f"bench segmentation: images {r.job[1][0]}-{r.job[1][-1]} failed: "
                               f"{(r.error or '').strip().splitlines()[-1:]}")
        rows += r.value
        if progress is not None:
            progress(len(r.value))
    rows.sort(key=lambda r: r["seed"])
    ok = [r for r in rows if "gt" in r]
    m = coco_metrics([r["gt"] for r in ok], [r["dt"] for r in ok])
    secs = [r["seconds"] for r in ok]
    return dict(backend=backend, ap=m["AP"], ap50=m["AP50"], ar=m["AR100"], images=len(ok), gt=m["gt"], dt=m["dt"],
                failed_images=[r["seed"] for r in rows if "gt" not in r], seed_start=seed_start, noise=noise,
                dropout=dropout, sensor=sensor, fill_holes=bool(fill_holes), seconds_median=statistics.median(secs) if secs else 0.0,
                cpu_seconds_median=statistics.median([r["cpu_seconds"] for r in ok]) if ok else 0.0,
                weights=None if weights is None else str(weights), device=device if backend == "learned" else None)
