"""Training and evaluation of the learned occupancy network (Ch. 8.3.2-8.3.3).

`train_occupancy` (``ms-drake train occupancy --data DIR --out FILE.pt``): AdamW (lr 1e-3,
weight decay 5e-4, cosine decay to 0), batches of 32, random horizontal and vertical flips of
input and ground truth together (a mirrored heap is a heap), pixelwise MSE on the channel of each
sample's aspect ratio (occupancy_net.ratio_loss) of the output under the seen-target constraint
(occupancy_net.constrain_to_visible: what the estimator returns), optionally with ground-truth
positives weighted 1 + w (`positive_weight`) and from the weights of an earlier run (`init`,
fine-tuning). Samples whose target is not its ratio's training box (``ms-drake data occupancy
--target``) are zoomed to the training box's size first (`to_training_scale`), as the estimator's
input scaling zooms at inference. Our choices where the reference's (ResNet-50
FCN, SGD with momentum 0.99, lr 1e-5, 40 epochs on a V100) does not fit two shared CPU cores.
Deterministic from `seed` (torch and numpy generators; the batch order of epoch e comes from
(seed, e)). It trains on `device` (cpu | cuda | auto; perception.weights.torch_device). After
every epoch the model, optimizer and scheduler go to ``FILE.ckpt`` (written atomically, tensors on
the CPU), so a killed run resumes with the same command; the shipped ``FILE`` holds the
weights, the network configuration and a `meta` dict (data, command, epochs, seconds, device).

`occupancy_metrics`: line 1466's definitions, on maps scaled to a maximum of 1. A ground-truth
pixel is positive when its value exceeds 0.1; a prediction is right when it lies within 0.2 of
the ground truth. Balanced accuracy = mean of the true-positive rate (right among positives) and
the true-negative rate (right among negatives); IoU = |gt > 0.1 and pred > 0.1| / |gt > 0.1 or
pred > 0.1|. Both are computed per image and averaged over images (images without a positive
pixel count for the negatives' rate only).
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ms_drake.errors import DatasetError
from ms_drake.experiments.occupancy_data import load_dataset, write_occupancy_dataset
from ms_drake.experiments.training import (
    fit_batch,
    resume,
    save_atomically,
    save_checkpoint,
    torch_setup,
)
from ms_drake.perception.occupancy_net import (
    FULL_SHAPE,
    TARGET_AREA,
    TARGET_RATIOS,
    LearnedOccupancy,
    NetConfig,
    load_model,
    make_net,
    estimator_output,
    ratio_loss,
    visible_support,
    zoom,
)
from ms_drake.perception.weights import torch_device

POSITIVE = 0.1
TOLERANCE = 0.2


def occupancy_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """Per-image balanced accuracy and IoU, (n, H, W) maps scaled to max 1 -> arrays (n,)."""
    pred, gt = np.asarray(pred, np.float32), np.asarray(gt, np.float32)
    pos = gt > POSITIVE
    right = np.abs(pred - gt) <= TOLERANCE
    npos, nneg = pos.sum(axis=(1, 2)), (~pos).sum(axis=(1, 2))
    tpr = np.where(npos > 0, (pos & right).sum(axis=(1, 2)) / np.maximum(npos, 1), np.nan)
    tnr = (~pos & right).sum(axis=(1, 2)) / np.maximum(nneg, 1)
    bal = np.where(npos > 0, 0.5 * (tpr + tnr), tnr)
    pp = pred > POSITIVE
    union = (pos | pp).sum(axis=(1, 2))
    iou = np.where(union > 0, (pos & pp).sum(axis=(1, 2)) / np.maximum(union, 1), 1.0)
    return dict(balanced_accuracy=bal, iou=iou, mse=((pred - gt) ** 2).mean(axis=(1, 2)))


def _flip(x: np.ndarray, y: np.ndarray, rng: np.random.Generator):
    if rng.random() < 0.5:
        x, y = x[..., ::-1], y[..., ::-1]
    if rng.random() < 0.5:
        x, y = x[..., ::-1, :], y[..., ::-1, :]
    return np.ascontiguousarray(x), np.ascontiguousarray(y)


def diagonals(size: np.ndarray) -> np.ndarray:
    """(n,) footprint diagonals [m] of (n, 3) target sizes."""
    size = np.asarray(size, np.float64)
    return np.hypot(size[:, 0], size[:, 1])


def batch_constraint(x: np.ndarray, diag: np.ndarray):
    """(support, floor), (n, H, W) float32 each, of the seen-target constraint for a batch of
    inputs (n, 3, H, W): support 1 and floor 0 where nothing is seen."""
    support = np.ones((len(x), *x.shape[2:]), np.float32)
    floor = np.clip(np.asarray(x[:, 0], np.float32), 0.0, 1.0)
    for i in range(len(x)):
        s = visible_support(floor[i], float(diag[i]))
        if s is not None:
            support[i] = s
    return support, floor


def target_scales(size: np.ndarray) -> np.ndarray:
    """(n,) input-scaling factors s = sqrt(area / training area) of (n, 3) target sizes (line 1468;
    `LearnedOccupancy` zooms its input by 1 / s)."""
    size = np.asarray(size, np.float64)
    return np.sqrt(size[:, 0] * size[:, 1] / TARGET_AREA)


def to_training_scale(d: dict) -> int:
    """Zoom, in place, every sample of `d` (load_dataset) whose target differs from its ratio's
    training box by s (> 0.1 % off) by 1 / s about the image centre, inputs and ground truth (the
    latter rescaled to a maximum of 1), as the estimator zooms its input: a network trained on
    targets of other sizes (``ms-drake data occupancy --target``) sees them at the size it serves
    with input scaling. Sizes become the training boxes'; returns the number of samples zoomed."""
    s = target_scales(d["size"])
    idx = np.flatnonzero(np.abs(s - 1.0) > 1e-3)
    if len(idx) == 0:
        return 0
    x = d["x"].astype(np.float32) if d["x"].dtype != np.float32 else d["x"]
    y = d["y"].astype(np.float32) if d["y"].dtype != np.float32 else d["y"]
    for i in idx:
        x[i] = zoom(x[i], 1.0 / s[i])
        yi = zoom(y[i][None], 1.0 / s[i])[0]
        mx = float(yi.max())
        y[i] = yi / mx if mx > 0 else yi
    d["x"], d["y"] = x.astype(d["x"].dtype), y.astype(d["y"].dtype)
    d["size"] = np.asarray(d["size"], np.float64).copy()
    d["size"][idx, :2] /= s[idx, None]
    return int(len(idx))


def train_steps(net, opt, x, y, ratio, steps: int = 1, diag: np.ndarray | None = None,
                positive_weight: float = 0.0) -> list[float]:
    """`steps` optimizer steps on one fixed batch (numpy arrays); the losses before each step.
    diag (n,): target diagonals [m] for the seen-target constraint (None: no constraint)."""
    import torch  # optional heavy dependency: only the learned occupancy needs it

    x = np.asarray(x, np.float32)
    xt, yt, rt = torch.from_numpy(x), torch.from_numpy(np.asarray(y, np.float32)), \
        torch.from_numpy(np.asarray(ratio, np.int64))
    sup = flo = None
    if diag is not None:
        sup, flo = (torch.from_numpy(a) for a in batch_constraint(x, diag))
    return fit_batch(net, opt, lambda: ratio_loss(net(xt), yt, rt, sup, flo, positive_weight), steps)


def make_optimizer(net, lr: float = 1e-3, weight_decay: float = 5e-4):
    import torch  # optional heavy dependency: only the learned occupancy needs it

    return torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)


def train_occupancy(data, out, epochs: int = 12, batch: int = 32, seed: int = 0, threads: int = 1,
                    config: NetConfig = NetConfig(), max_minutes: float = 60.0, progress=None,
                    command: str = "", lr: float = 1e-3, positive_weight: float = 0.0,
                    init: str | Path | None = None, device="cpu") -> dict:
    """Train on the train shards of `data`; write `out` (weights + meta) and `out`.ckpt (resume).
    Stops early (after a whole epoch) when `max_minutes` of wall time would be exceeded.
    init: a weights file to start from (its network configuration replaces `config`).
    device: where the network trains (cpu | cuda | auto)."""
    torch = torch_setup(seed, threads)
    dev = torch_device(device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = out.with_suffix(".ckpt")
    d = load_dataset(data, "train")
    rescaled = to_training_scale(d)
    n = len(d["x"])
    if n < batch:
        raise DatasetError(f"{data}: {n} training images, fewer than a batch ({batch}); make more with "
                           "`ms-drake data occupancy --count ...`")
    if init is not None:
        net, ck0 = load_model(init, dev)
        config = NetConfig(**ck0["config"])
    else:
        net = make_net(config).to(dev)
    opt = make_optimizer(net, lr=lr)
    steps_per_epoch = n // batch
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps_per_epoch)
    settings = dict(config=asdict(config), epochs=epochs, n=n, lr=lr, positive_weight=positive_weight,
                    init=str(init) if init is not None else None)
    diag = diagonals(d["size"])
    start, history, seconds = resume(torch, ckpt, settings, net, opt, sched)
    t0 = time.perf_counter() - seconds
    for epoch in range(start, epochs):
        te = time.perf_counter()
        if epoch > start and (te - t0) / epoch * (epoch + 1) > 60.0 * max_minutes:
            break
        rng = np.random.default_rng([seed, epoch])
        order = rng.permutation(n)
        net.train()
        total = 0.0
        for b in range(steps_per_epoch):
            idx = np.sort(order[b * batch:(b + 1) * batch])
            x, y = _flip(d["x"][idx].astype(np.float32), d["y"][idx].astype(np.float32), rng)
            sup, flo = batch_constraint(x, diag[idx])
            opt.zero_grad()
            xt, yt, rt, st, ft = (torch.from_numpy(a).to(dev) for a in (x, y, d["ratio"][idx], sup, flo))
            loss = ratio_loss(net(xt), yt, rt, st, ft, positive_weight)
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
            if progress is not None:
                progress(epoch, b, steps_per_epoch, loss.item())
        history.append(dict(epoch=epoch + 1, loss=total / steps_per_epoch, seconds=time.perf_counter() - te))
        save_checkpoint(torch, ckpt, settings, net, opt, sched, epoch + 1, history, time.perf_counter() - t0)
    meta = dict(data=str(data), train_images=n, epochs_done=len(history), epochs=epochs, batch=batch, seed=seed,
                lr=lr, positive_weight=positive_weight, init=str(init) if init is not None else None,
                rescaled_images=rescaled, seconds=time.perf_counter() - t0, history=history, command=command,
                ratios=list(TARGET_RATIOS), torch=torch.__version__, device=str(dev))
    save_atomically(torch, dict(model=net.state_dict(), config=asdict(config), meta=meta), out)
    return meta


def predict(net, x: np.ndarray, ratio: np.ndarray, scales: np.ndarray | None = None, batch: int = 64,
            diag: np.ndarray | None = None) -> np.ndarray:
    """(n, 96, 128) predictions of each sample's ratio channel; `scales` (n,): input scaling per
    sample; `diag` (n,): target diagonals [m], gives what the estimator returns
    (occupancy_net.estimator_output; None: the network's raw output). On the device of `net`."""
    import torch  # optional heavy dependency: only the learned occupancy needs it

    net.eval()
    dev = next(net.parameters()).device
    out = np.zeros((len(x), *x.shape[2:]), np.float32)
    with torch.inference_mode():
        for i in range(0, len(x), batch):
            xb = np.asarray(x[i:i + batch], np.float32)
            if scales is not None:
                xb = np.stack([zoom(xi, 1.0 / s) for xi, s in zip(xb, scales[i:i + batch])])
            y = net(torch.from_numpy(xb).to(dev)).cpu().numpy()
            y = y[np.arange(len(xb)), ratio[i:i + batch]]
            if scales is not None:
                y = np.stack([zoom(yi[None], s)[0] for yi, s in zip(y, scales[i:i + batch])])
            if diag is not None:
                y = np.stack([estimator_output(yi, xi[0], float(di))
                              for yi, xi, di in zip(y, np.asarray(x[i:i + batch], np.float32), diag[i:i + batch])])
            out[i:i + len(xb)] = y
    return out


def metrics_table(d: dict, pred: np.ndarray, ratios=(1, 2, 5, 10)) -> list[dict]:
    """Rows per aspect ratio, all, all with the target hidden ("hidden") and partly seen ("seen"):
    images, balanced accuracy, IoU (means), MSE."""
    m = occupancy_metrics(pred, d["y"].astype(np.float32))
    rows = []
    for r in list(ratios) + ["all", "hidden", "seen"]:
        sel = (np.ones(len(pred), bool) if r == "all" else d["visible"] == 0 if r == "hidden" else
               d["visible"] > 0 if r == "seen" else d["ratio"] == TARGET_RATIOS.index(r))
        if not sel.any():
            continue
        rows.append(dict(ratio=r, images=int(sel.sum()), balanced_accuracy=float(np.mean(m["balanced_accuracy"][sel])),
                         iou=float(np.mean(m["iou"][sel])), mse=float(np.mean(m["mse"][sel])),
                         hidden=int((d["visible"][sel] == 0).sum())))
    return rows


def sensor_test_set(folder, sensor: str, images: int, seed: int = 7, workers: int = 1, progress=None) -> Path:
    """``folder/<sensor>``: a test-only occupancy set of about `images` samples (held-out occluders)
    whose network inputs went through the depth sensor preset `sensor` and the hole filling
    (occupancy_data.make_samples); made if absent (resumable). The same `seed` gives the same heaps,
    cameras, targets and ground truth for every preset, so the presets compare on the same images."""
    out = Path(folder) / sensor
    write_occupancy_dataset(out, images, seed=seed, workers=workers, test_only=True, sensor=sensor,
                            progress=progress)
    return out


def bench_occupancy(data, weights=None, scaling: bool = False, timed: int = 50, seed: int = 0,
                    sensor: str | None = None, sensor_images: int = 96, sensor_seed: int = 7,
                    device="cpu") -> dict:
    """Table 8.1 rows on the test shards of `data` (the estimator's output: the network under the
    seen-target constraint, scaled to a maximum of 1; `raw_rows`: the network alone), two
    baselines, and the inference time. sensor: bench on `sensor_test_set(data, sensor,
    sensor_images, sensor_seed)` instead (made first if absent).

    Baselines: "uniform" predicts one value over the bin's pixels (the uniform distribution scaled
    to a maximum of 1); "modal" predicts the observed modal mask (nothing when hidden).
    Timing: `LearnedOccupancy.estimate` on full 640 x 480 inputs (preprocessing, forward pass,
    upsampling; the cost does not depend on the content), one torch thread, median of `timed` calls,
    wall and CPU time of the process (on a shared machine the CPU time is the cost on one core).
    device: where the network runs (cpu | cuda | auto)."""
    dev = torch_device(device)
    if sensor is not None:
        data = sensor_test_set(data, sensor, sensor_images, sensor_seed)
    torch = torch_setup(seed, 1)
    d = load_dataset(data, "test")
    net, ck = load_model(weights, dev)
    d["y"] = d["y"].astype(np.float32)
    scales = None
    if scaling:
        scales = target_scales(d["size"])
    pred = predict(net, d["x"], d["ratio"], scales, diag=diagonals(d["size"]))
    rows = metrics_table(d, pred)
    raw_rows = metrics_table(d, predict(net, d["x"], d["ratio"], scales))  # without the seen-target constraint
    # the bin's pixels: the working crop minus its border (the bin spans ~107 x 85 of 128 x 96)
    uni = np.zeros_like(d["y"])
    uni[:, 6:-6, 10:-10] = 1.0
    modal = (d["x"][:, 0].astype(np.float32) > 0.25).astype(np.float32)
    base = {}
    for name, p in (("uniform", uni), ("modal", modal)):
        m = occupancy_metrics(p, d["y"])
        base[name] = {k: float(np.mean(v)) for k, v in m.items()}
    est = LearnedOccupancy((0.03, 0.03, 0.005), weights=weights, input_scaling=False, device=dev)
    depth, mask = np.full(FULL_SHAPE, 0.8, np.float32), np.zeros(FULL_SHAPE, bool)
    est.estimate(depth, mask)  # warm-up
    times, cpu = [], []
    for _ in range(timed):
        t, c = time.perf_counter(), time.process_time()
        est.estimate(depth, mask)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return dict(rows=rows, raw_rows=raw_rows, baselines=base, ms_per_image=1000 * float(np.median(times)),
                cpu_ms_per_image=1000 * float(np.median(cpu)), timed=timed,
                scaling=scaling, weights=str(weights or "shipped"), test_images=len(pred), data=str(data), sensor=sensor,
                files=len(d["files"]), torch_threads=torch.get_num_threads(), device=str(dev))
