"""Training and evaluation of the learned shelf occupancy network (Ch. 9.4.2).

Data: `ms-drake data shelf --depth-block 4` shards; DATA/train and DATA/test are separate seed
ranges (the model card's commands: train seeds from 100000, test seeds from 900000; the Table 9.1
bench scenes are drawn with a given occluder count from seeds 0-99, a different random stream).

`train_shelf_occupancy` (``ms-drake train shelf-occupancy --data DATA --out FILE.pt``): AdamW (lr
2e-3, weight decay 1e-4, cosine decay to 0), batches of 32, a random mirror of image and
distributions about the image's vertical centre line (the shelf and camera are symmetric about
it: the camera's x is the shelf's centre and cx = (W - 1) / 2), shelf_occupancy_net's
distribution_loss on all three heads. Deterministic from `seed` (torch and numpy generators; the
batch order and mirrors of epoch e come from (seed, e)). After every epoch the model, optimizer and
scheduler go to ``FILE.ckpt`` (written atomically), so a killed run resumes with the same command;
training stops after the epoch that ends past `max_minutes`. The shipped ``FILE`` holds the
weights, the network configuration and a `meta` dict (data, command, epochs, seconds, losses).

`bench_shelf_occupancy` (``ms-drake bench shelf-occupancy``): on DATA/test, per head and overall,
for each image's own target size and for all three sizes:
- total variation between predicted and ground-truth P(x) (640 columns): 0.5 * sum |p - q|;
- balanced accuracy and IoU with the definitions of line 1466 (ms_drake.experiments.
  occupancy_learning.occupancy_metrics), on P(x) scaled to a maximum of 1: a ground-truth column
  is positive above 0.1; a prediction is right within 0.2 of the ground truth;
- the same for a uniform P(x) over the columns (a baseline), and the inference time per image
  (one torch thread, from the 480 x 640 depth image: block averaging and the network).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ms_drake.errors import DatasetError
from ms_drake.experiments.occupancy_learning import occupancy_metrics
from ms_drake.experiments.training import (
    fit_batch,
    resume,
    save_atomically,
    save_checkpoint,
    torch_setup,
)
from ms_drake.perception.shelf_occupancy_net import (
    BLOCK,
    HEAD_SIZES,
    IMAGE_SHAPE,
    WORK_SHAPE,
    LearnedShelfOccupancy,
    NetConfig,
    config_dict,
    distribution_loss,
    expand_bins,
    head_index,
    make_net,
    network_input,
    pool_bins,
)
from ms_drake.perception.weights import torch_device


def load_shelf_dataset(folder) -> dict:
    """All shards of one split folder: depth (N, 120, 160), image_x_sizes (N, 3, 640) in HEAD_SIZES
    order, head (N,) of each scene's own target, seeds (N,)."""
    folder = Path(folder)
    shards = sorted(folder.glob("shard_*.npz"))
    if not shards:
        raise DatasetError(f"{folder}: no shards; make them with `ms-drake data shelf --depth-block {BLOCK} "
                           f"--out {folder} --count N --seed-start S`")
    depth, ys, heads, seeds = [], [], [], []
    for path in shards:
        with np.load(path) as z:
            if "depth" not in z or "image_x_sizes" not in z:
                raise DatasetError(f"{path}: no depth or image_x_sizes; regenerate it with `ms-drake data shelf "
                                   f"--depth --depth-block {BLOCK}` (delete the old shards first)")
            d = z["depth"]
            if d.shape[1:] != WORK_SHAPE:
                raise DatasetError(f"{path}: depth of {d.shape[2]} x {d.shape[1]}, the network takes "
                                   f"{WORK_SHAPE[1]} x {WORK_SHAPE[0]}: make it with --depth-block {BLOCK}")
            depth.append(d.astype(np.float32))
            ys.append(z["image_x_sizes"].astype(np.float32))
            heads += [head_index((0, 0, h)) for h in z["target_height"]]
            seeds.append(z["seeds"])
    # image_x_sizes is in TARGET_SIZES order (cube, flat, tall) = HEAD_SIZES order.
    return dict(depth=np.concatenate(depth), image_x_sizes=np.concatenate(ys), head=np.array(heads),
                seeds=np.concatenate(seeds), shards=len(shards))


def make_optimizer(net, lr: float = 2e-3, weight_decay: float = 1e-4):
    import torch  # optional heavy dependency: only the learned shelf occupancy needs it

    return torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)


def batch_arrays(depth: np.ndarray, image_x_sizes: np.ndarray, mirror: np.ndarray | None = None):
    """(inputs (B, 4, 120, 160), targets (B, 3, 160)) of depth (B, 120, 160) and P(x) (B, 3, 640),
    the samples with mirror[i] mirrored about the image's vertical centre line."""
    d, y = np.array(depth, np.float32), pool_bins(image_x_sizes)
    if mirror is not None and mirror.any():
        d[mirror] = d[mirror][..., ::-1]
        y[mirror] = y[mirror][..., ::-1]
    return network_input(d), np.ascontiguousarray(y)


def train_steps(net, opt, x, y, steps: int = 1) -> list[float]:
    """`steps` optimizer steps on one fixed batch (numpy arrays); the losses before each step."""
    import torch  # optional heavy dependency: only the learned shelf occupancy needs it

    xt, yt = torch.from_numpy(np.asarray(x, np.float32)), torch.from_numpy(np.asarray(y, np.float32))
    return fit_batch(net, opt, lambda: distribution_loss(net(xt), yt), steps)


def train_shelf_occupancy(data, out, epochs: int = 8, batch: int = 32, seed: int = 0, threads: int = 1,
                          config: NetConfig = NetConfig(), max_minutes: float = 30.0, progress=None,
                          command: str = "", device="cpu") -> dict:
    """Train on DATA/train; write `out` (weights + meta) and `out`.ckpt (resume); module docstring.
    device: where the network trains (cpu | cuda | auto)."""
    torch = torch_setup(seed, threads)
    dev = torch_device(device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = out.with_suffix(".ckpt")
    d = load_shelf_dataset(Path(data) / "train")
    n = len(d["depth"])
    if n < batch:
        raise DatasetError(f"{data}/train: {n} scenes, fewer than a batch ({batch}); make more with "
                           "`ms-drake data shelf --count ...`")
    torch.manual_seed(seed)
    net = make_net(config)
    torch.manual_seed(seed)
    for m in net.modules():  # the seed's initial weights
        if hasattr(m, "reset_parameters"):
            m.reset_parameters()
    net.to(dev)
    opt = make_optimizer(net)
    steps_per_epoch = n // batch
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps_per_epoch)
    settings = dict(config=config_dict(config), epochs=epochs, batch=batch, seed=seed, scenes=n)
    start_epoch, history, seconds = resume(torch, ckpt, settings, net, opt, sched)
    t_run = time.perf_counter()
    for epoch in range(start_epoch, epochs):
        if seconds + (time.perf_counter() - t_run) > 60 * max_minutes:
            break
        t0 = time.perf_counter()
        rng = np.random.default_rng([seed, epoch])
        order = rng.permutation(n)
        mirror = rng.random(n) < 0.5
        net.train()
        losses = []
        for b in range(steps_per_epoch):
            idx = np.sort(order[b * batch:(b + 1) * batch])
            x, y = batch_arrays(d["depth"][idx], d["image_x_sizes"][idx], mirror[idx])
            opt.zero_grad()
            loss = distribution_loss(net(torch.from_numpy(x).to(dev)), torch.from_numpy(y).to(dev))
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            if progress is not None:
                progress(epoch, b, steps_per_epoch, loss.item())
        history.append(dict(epoch=epoch + 1, loss=float(np.mean(losses)), seconds=time.perf_counter() - t0))
        save_checkpoint(torch, ckpt, settings, net, opt, sched, epoch + 1, history,
                        seconds + time.perf_counter() - t_run)
    seconds += time.perf_counter() - t_run
    done = history[-1]["epoch"] if history else 0
    meta = dict(data=str(data), scenes=n, seeds=[int(d["seeds"].min()), int(d["seeds"].max())], epochs=epochs,
                epochs_done=done, batch=batch, seed=seed, threads=threads, seconds=seconds, history=history,
                command=command, torch=torch.__version__, device=str(dev))
    save_atomically(torch, dict(config=config_dict(config), state_dict=net.state_dict(), meta=meta), out)
    return meta


def total_variation(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """0.5 * sum |p - q| over the last axis."""
    return 0.5 * np.abs(np.asarray(p) - np.asarray(q)).sum(-1)


def _scaled(a: np.ndarray) -> np.ndarray:
    m = a.max(-1, keepdims=True)
    return np.where(m > 0, a / np.where(m > 0, m, 1), 0)


def distribution_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """Means over the (image, head) pairs with a non-empty ground truth, (n, 640) arrays."""
    ok = gt.sum(-1) > 0
    pred, gt = pred[ok], gt[ok]
    m = occupancy_metrics(_scaled(pred)[:, None], _scaled(gt)[:, None])
    return dict(pairs=int(ok.sum()), tv=float(total_variation(pred, gt).mean()),
                balanced_accuracy=float(np.mean(m["balanced_accuracy"])), iou=float(np.mean(m["iou"])))


def bench_shelf_occupancy(data, weights=None, timed: int = 50, seed: int = 0, device="cpu") -> dict:
    """The module docstring's metrics on DATA/test, the network on `device` (cpu | cuda | auto)."""
    model = LearnedShelfOccupancy(weights, threads=1, device=device)
    d = load_shelf_dataset(Path(data) / "test")
    n = len(d["depth"])
    pred = np.concatenate([model.predict_bins(network_input(d["depth"][i:i + 64])) for i in range(0, n, 64)])
    pred = expand_bins(pred)  # (n, 3, 640)
    gt = d["image_x_sizes"]
    uniform = np.full_like(gt, 1.0 / gt.shape[-1])
    own = np.arange(n), d["head"]
    rows = []
    for k, size in enumerate(HEAD_SIZES):
        sel = d["head"] == k
        rows.append(dict(head=k, size=list(size), scenes=int(sel.sum()),
                         own=distribution_metrics(pred[sel, k], gt[sel, k]),
                         all_images=distribution_metrics(pred[:, k], gt[:, k]),
                         uniform=distribution_metrics(uniform[:, k], gt[:, k])))
    overall = dict(own=distribution_metrics(pred[own], gt[own]),
                   all_images=distribution_metrics(pred.reshape(-1, gt.shape[-1]), gt.reshape(-1, gt.shape[-1])),
                   uniform=distribution_metrics(uniform[own], gt[own]))
    # Inference time from the full-resolution depth image (block averaging + network), one thread.
    rng = np.random.default_rng(seed)
    full = np.repeat(np.repeat(d["depth"][rng.integers(0, n, min(timed, n))], BLOCK, 1), BLOCK, 2)
    full[full == 0] = np.inf
    assert full.shape[1:] == IMAGE_SHAPE
    ms = []
    for img in full:
        t = time.perf_counter()
        model.predict(img, HEAD_SIZES[0])
        ms.append(1e3 * (time.perf_counter() - t))
    return dict(data=str(data), test_scenes=n, test_seeds=[int(d["seeds"].min()), int(d["seeds"].max())],
                weights=str(weights) if weights else "models/weights/shelf_occupancy.pt", rows=rows, overall=overall,
                ms_per_image=float(np.median(ms)), ms_p90=float(np.percentile(ms, 90)), timed=len(ms),
                train_meta={k: v for k, v in model.meta.items() if k != "history"})
