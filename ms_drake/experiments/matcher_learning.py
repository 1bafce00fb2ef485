"""Training of the siamese target matcher (App. C.2; ms_drake.perception.matcher_net).

`train_matcher` (``ms-drake train matcher --data DIR --out FILE.pt``): pairs are drawn from the
shards of `ms-drake data matcher` (experiments.matcher_data), half positive -- a template view of
an object vs its crop in a heap (another pose, another camera, partly hidden by its neighbours) --
and half negative -- a template view vs the crop of another object: with probability 1/3 one of
the same heap, 1/3 one of the same colour (any heap), 1/3 any. Two crops of the same object name
in different colours count as different objects (the search's target is an object in one
colour). Augmentation (ours, besides the reference's): the candidate crop gets the reference's
occlusion (a random part cut away, 20-80 % of its pixels; matcher_net.occlude) with probability
1/2, and both crops an independent random 90-degree rotation and flip (the camera looks down;
an object's orientation in the image is arbitrary). Loss: binary cross-entropy on the sigmoid
score (the reference names a contrastive loss without its form; BCE is the loss of a sigmoid
same/different output). Adam, lr 1e-3 with cosine decay (the reference: 1e-4 for 10 epochs on
a frozen backbone; ours trains the encoder from scratch), batches of 64 pairs.

An epoch is `steps` batches; batches of epoch e come from (seed, e), so a killed run resumes with
the same command (FILE.ckpt after every epoch, experiments.training). It trains on `device` (cpu |
cuda | auto; perception.weights.torch_device); the files hold CPU tensors. Validation after every
epoch on fixed pairs of the test shards (held-out objects), drawn from `seed` the same way:
loss, accuracy, precision and recall of "same" at t_r = 0.9.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ms_drake.errors import DatasetError
from ms_drake.experiments.matcher_data import load_matcher_data
from ms_drake.experiments.training import resume, save_atomically, save_checkpoint, torch_setup
from ms_drake.perception.matcher_net import THRESHOLD, MatcherConfig, make_net, occlude
from ms_drake.perception.weights import torch_device


class PairSampler:
    """Positive and negative (template, candidate) pairs of one split (see the module doc)."""

    def __init__(self, data: dict):
        self.heap = data["heap"]
        self.templates = data["templates"]
        self.heap_id = data["heap_id"]
        self.colour = data["colour"]
        ident = np.array([f"{o}#{c}" for o, c in zip(data["object"], data["colour"])])
        _, self.ident = np.unique(ident, return_inverse=True)
        self.n = len(self.heap)
        if self.n < 2 or len(np.unique(self.ident)) < 2:
            raise DatasetError(f"{self.n} crops of {len(np.unique(self.ident))} objects: too few to draw pairs; make "
                               "more with `ms-drake data matcher --heaps ...`")
        self.by_heap = {h: np.flatnonzero(self.heap_id == h) for h in np.unique(self.heap_id)}
        self.by_colour = {c: np.flatnonzero(self.colour == c) for c in np.unique(self.colour)}

    def _negative(self, i: int, rng: np.random.Generator) -> int:
        u = rng.random()
        pool = self.by_heap[self.heap_id[i]] if u < 1 / 3 else self.by_colour[self.colour[i]] if u < 2 / 3 else None
        if pool is not None:
            pool = pool[self.ident[pool] != self.ident[i]]
        if pool is None or len(pool) == 0:
            for _ in range(100):
                j = int(rng.integers(self.n))
                if self.ident[j] != self.ident[i]:
                    return j
        return int(rng.choice(pool))

    def pairs(self, count: int, rng: np.random.Generator, augment: bool = True):
        """(a (count, 4, 64, 64), b (count, 4, 64, 64) float32, y (count,) float32)."""
        a = np.empty((count, 4, 64, 64), np.float32)
        b = np.empty_like(a)
        y = np.zeros(count, np.float32)
        for p in range(count):
            i = int(rng.integers(self.n))
            pos = p % 2 == 0
            j = i if pos else self._negative(i, rng)
            a[p] = self.templates[i, int(rng.integers(self.templates.shape[1]))]
            cand = self.heap[j].astype(np.float32)
            if rng.random() < 0.5:
                m = cand[3] > 0.5
                if m.sum() >= 10:
                    cand = cand * occlude(m, rng)[None]
            b[p] = cand
            y[p] = float(pos)
            if augment:
                a[p] = _rot_flip(a[p], rng)
                b[p] = _rot_flip(b[p], rng)
        return a, b, y


def _rot_flip(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    x = np.rot90(x, int(rng.integers(4)), axes=(1, 2))
    if rng.random() < 0.5:
        x = x[:, :, ::-1]
    return np.ascontiguousarray(x)


def evaluate(net, torch, a, b, y) -> dict:
    """Loss, accuracy, precision and recall of `net` (on its device) on the pairs (a, b) labelled y."""
    net.eval()
    dev = next(net.parameters()).device
    with torch.no_grad():
        logits = torch.cat([net(torch.from_numpy(a[k:k + 256]).to(dev), torch.from_numpy(b[k:k + 256]).to(dev))
                            for k in range(0, len(a), 256)]).cpu()
        loss = float(torch.nn.functional.binary_cross_entropy_with_logits(logits, torch.from_numpy(y)))
        s = torch.sigmoid(logits).numpy()
    pred = s >= THRESHOLD
    tp = int((pred & (y > 0.5)).sum())
    return dict(loss=loss, accuracy=float((pred == (y > 0.5)).mean()), precision=tp / max(int(pred.sum()), 1),
                recall=tp / max(int((y > 0.5).sum()), 1), pairs=len(y))


def train_matcher(data, out, epochs: int = 10, steps: int = 150, batch: int = 64, seed: int = 0, threads: int = 1,
                  lr: float = 1e-3, val_pairs: int = 2000, max_minutes: float = 15.0, progress=None,
                  command: str = "", config: MatcherConfig | None = None, device="cpu") -> dict:
    """Train on the train shards of `data`; write `out` (weights + config + meta) and `out`.ckpt
    after every epoch; stop early (after a whole epoch) when `max_minutes` of wall time would be
    exceeded. device: where the network trains (cpu | cuda | auto)."""
    torch = torch_setup(seed, threads)
    dev = torch_device(device)
    config = config or MatcherConfig()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = out.with_suffix(".ckpt")
    train = PairSampler(load_matcher_data(data, "train"))
    test = PairSampler(load_matcher_data(data, "test"))
    va, vb, vy = test.pairs(val_pairs, np.random.default_rng([seed, 999]), augment=False)
    net = make_net(config).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * steps)
    settings = dict(config=asdict(config), epochs=epochs, steps=steps, batch=batch, lr=lr, seed=seed,
                    train_crops=train.n)
    start, history, seconds = resume(torch, ckpt, settings, net, opt, sched)
    t0 = time.perf_counter() - seconds
    meta = {}
    for epoch in range(start, epochs):
        te = time.perf_counter()
        if epoch > 0 and (te - t0) / epoch * (epoch + 1) > 60.0 * max_minutes:
            break
        rng = np.random.default_rng([seed, epoch])
        net.train()
        total = 0.0
        for s in range(steps):
            a, b, y = train.pairs(batch, rng)
            opt.zero_grad()
            loss = torch.nn.functional.binary_cross_entropy_with_logits(
                net(torch.from_numpy(a).to(dev), torch.from_numpy(b).to(dev)), torch.from_numpy(y).to(dev))
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
            if progress is not None:
                progress(epoch, s, steps, loss.item())
        val = evaluate(net, torch, va, vb, vy)
        history.append(dict(epoch=epoch + 1, loss=total / steps, seconds=time.perf_counter() - te,
                            **{f"val_{k}": v for k, v in val.items()}))
        save_checkpoint(torch, ckpt, settings, net, opt, sched, epoch + 1, history, time.perf_counter() - t0)
        meta = dict(data=str(data), train_crops=train.n, test_crops=test.n, train_objects=int(len(np.unique(train.ident))),
                    test_objects=int(len(np.unique(test.ident))), epochs_done=len(history), epochs=epochs, steps=steps,
                    batch=batch, seed=seed, lr=lr, seconds=time.perf_counter() - t0, history=list(history),
                    command=command, torch=torch.__version__, threads=threads, device=str(dev))
        save_atomically(torch, dict(model=net.state_dict(), config=asdict(config), meta=meta), out)
    if not meta:  # every epoch was already in the checkpoint: the weights file holds its meta
        meta = torch.load(out, map_location="cpu", weights_only=False)["meta"] if out.exists() else dict(
            history=list(history), epochs_done=len(history))
    return meta
