"""Learned target occupancy distribution (Ch. 8.3.2): a small fully-convolutional encoder-decoder
predicting rho from one depth image and the target's modal mask; `OccupancyEstimator("learned")`.

Working resolution. The network sees the central 512 x 384 pixels of the 640 x 480 overhead
image (the 0.5 x 0.4 m bin spans ~428 x 342 px at 0.8 m, so the crop holds the bin with a
~40 px margin for the camera jitter of the training data; the reference's own images are
512 x 384), averaged over 4 x 4 blocks: 128 x 96 pixels. At that size the 3 mm target-height
threshold of the ground truth is still a depth step of several pixels' width for every target
(the thinnest, 9.5 x 0.95 cm, is ~2 working pixels wide), a forward pass takes a few ms on one
core and an epoch of 5,000 images a minute or two on two shared cores, which is what lets
training fit in the hour this machine gives it. Outputs are upsampled back to the full image
(outside the crop: 0).

Inputs (the reference's "augmented depth image", line 1456): [modal target mask, depth, depth],
the mask as the fraction of each 4 x 4 block, the depth in units of 5 cm relative to the median
depth of the crop (invalid pixels take the largest valid depth), so the camera height does not
matter. Outputs: one channel per aspect ratio of `TARGET_RATIOS` (line 1461: one network per
ratio in the reference), each a sigmoid map of the ground truth scaled to a maximum of 1 (the
normalization under which line 1466's thresholds 0.1 / 0.2 are stated).

The seen part of the target (our addition; lines 1470-1480 show the reference's net "collapse
the distribution to a small area around the visible part of the target"): every placement that
explains the observation holds the target's seen pixels, so no pixel farther than the target's
diagonal from any seen pixel can be covered, and the seen pixels themselves are covered by every
placement (value 1 on the max-scaled map). `visible_support` gives that region (the diagonal in
working pixels of the nominal camera, fx 685 px at 0.8 m, times 1.15 for the camera jitter of the
training data, plus one pixel) and `constrain_to_visible` applies both facts to a prediction:
zero outside the region, at least the block's seen fraction inside. The network is trained on the
constrained output (the loss sees only what the estimator returns) and the estimator returns it.

Input scaling (line 1468): for a target whose size differs from the training box of its ratio
by a factor s, the working image is zoomed by 1 / s about its centre (so the target looks like
the training box), predicted, and the prediction zoomed back by s.

torch is imported inside functions only (an optional heavy dependency: the rest of ms_drake,
and the analytic backend, work without it).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ms_drake.errors import PerceptionError
from ms_drake.geometry import preprocess_depth
from ms_drake.objects.registry import TARGET_AREA, TARGET_RATIOS, target_box_size  # noqa: F401 (re-exported)
from ms_drake.paths import models_dir
from ms_drake.perception.weights import load_network

FULL_SHAPE = (480, 640)
CROP = (48, 64, 384, 512)  # top, left, height, width in the full image
BLOCK = 4
WORK_SHAPE = (CROP[2] // BLOCK, CROP[3] // BLOCK)  # (96, 128)
DEPTH_UNIT = 0.05  # m


WORK_PX_PER_M = 685.0 / 0.8 / BLOCK  # working pixels per metre on the bin floor, nominal overhead camera
VISIBLE_SLACK = 1.15  # camera 0.75-0.85 m high, focal lengths +-5 % (occupancy_data.random_camera)


def default_weights() -> Path:
    return models_dir() / "weights" / "occupancy.pt"


def nearest_ratio(length: float, width: float) -> tuple[int, float]:
    """(channel index of the closest trained aspect ratio, scale s = sqrt(area / training area))."""
    r = max(length, width) / max(min(length, width), 1e-6)
    k = int(np.argmin([abs(np.log(r / q)) for q in TARGET_RATIOS]))
    return k, float(np.sqrt(length * width / TARGET_AREA))


def crop_image(a: np.ndarray, user: str = "the learned occupancy") -> np.ndarray:
    """The CROP window of a full (480, 640, ...) overhead image; PerceptionError naming `user` (the
    network that needs the crop) for an image of another size."""
    t, l, h, w = CROP
    if a.shape[:2] != FULL_SHAPE:
        raise PerceptionError(f"image is {a.shape[1]}x{a.shape[0]}; {user} works on "
                              f"{FULL_SHAPE[1]}x{FULL_SHAPE[0]} overhead images")
    return a[t:t + h, l:l + w]


def block_mean(a: np.ndarray) -> np.ndarray:
    h, w = a.shape
    return a.reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3))


def working_inputs(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3, 96, 128) float32 network input from a full depth image (m) and modal mask."""
    d = crop_image(np.asarray(depth, np.float32)).copy()
    ok = np.isfinite(d) & (d > 0)
    fill = float(d[ok].max()) if ok.any() else 1.0
    d[~ok] = fill
    d = block_mean(d)
    d = (d - np.median(d)) / DEPTH_UNIT
    m = block_mean(crop_image(np.asarray(mask, np.float32)))
    return np.stack([m, d, d]).astype(np.float32)


def working_target(rho: np.ndarray) -> np.ndarray:
    """A full-resolution distribution -> (96, 128) working map scaled to a maximum of 1."""
    r = block_mean(crop_image(np.asarray(rho, np.float64)))
    mx = r.max()
    return (r / mx if mx > 0 else r).astype(np.float32)


def target_diagonal(size) -> float:
    """Diagonal [m] of a (length, width[, thickness]) footprint."""
    return float(np.hypot(float(size[0]), float(size[1])))


def visible_support(mask_frac: np.ndarray, diagonal: float, slack: float = VISIBLE_SLACK) -> np.ndarray | None:
    """(96, 128) bool: the working pixels a target of footprint `diagonal` [m] holding every seen
    pixel can cover (within the diagonal of the farthest seen pixel); None when nothing is seen."""
    seen = np.asarray(mask_frac) > 0
    if not seen.any():
        return None
    pts = np.argwhere(seen).astype(np.float32)  # (n, 2): row, column
    if len(pts) > 3:  # the farthest point of a set is one of its convex hull's vertices
        pts = cv2.convexHull(pts[:, ::-1].copy()).reshape(-1, 2)[:, ::-1]
    r = diagonal * WORK_PX_PER_M * slack + 1.0
    rows, cols = np.arange(seen.shape[0], dtype=np.float32), np.arange(seen.shape[1], dtype=np.float32)
    far = np.zeros(seen.shape, np.float32)
    for pr, pc in pts:
        np.maximum(far, (rows[:, None] - pr) ** 2 + (cols[None, :] - pc) ** 2, out=far)
    return far <= r * r


def constrain_to_visible(pred: np.ndarray, mask_frac: np.ndarray, diagonal: float) -> np.ndarray:
    """A (96, 128) working prediction with the seen target applied (module doc): 0 outside
    `visible_support`, at least the seen fraction of each block; unchanged when nothing is seen."""
    support = visible_support(mask_frac, diagonal)
    if support is None:
        return pred
    return np.maximum(np.where(support, pred, 0.0), np.clip(mask_frac, 0.0, 1.0)).astype(np.float32)


def estimator_output(pred: np.ndarray, mask_frac: np.ndarray, diagonal: float) -> np.ndarray:
    """What the estimator returns at working resolution: `constrain_to_visible`, then scaled to a
    maximum of 1 as the ground truth is (the distribution X-Ray reads is normalized to sum 1
    anyway; the scale matters only to line 1466's thresholds)."""
    y = constrain_to_visible(pred, mask_frac, diagonal)
    mx = float(y.max())
    return (y / mx).astype(np.float32) if mx > 0 else y


def full_resolution(work: np.ndarray) -> np.ndarray:
    """(96, 128) working map -> (480, 640) distribution summing to 1 (or all 0)."""
    t, l, h, w = CROP
    out = np.zeros(FULL_SHAPE)
    out[t:t + h, l:l + w] = cv2.resize(np.asarray(work, np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    out = np.maximum(out, 0.0)
    s = out.sum()
    return out / s if s > 0 else out


def zoom(a: np.ndarray, factor: float, fill: float = 0.0) -> np.ndarray:
    """Channels (C, H, W) zoomed by `factor` about the image centre (same size; `fill` outside)."""
    if abs(factor - 1.0) < 1e-6:
        return a
    h, w = a.shape[-2:]
    M = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), 0.0, float(factor))
    return np.stack([cv2.warpAffine(c, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                    borderValue=fill) for c in np.asarray(a, np.float32)])


def unet_levels(x, enc, pool, up, dec):
    """The U-Net levels of the occupancy and segmentation networks on features x: each encoder level
    (max-pooled from the second on), then each decoder level on [upsampled, encoder skip]."""
    import torch  # optional heavy dependency: only the learned backends need it

    skips = []
    for i, e in enumerate(enc):
        x = e(x if i == 0 else pool(x))
        skips.append(x)
    for u, d, skip in zip(up, dec, reversed(skips[:-1])):
        x = d(torch.cat([u(x), skip], dim=1))
    return x


@dataclass(frozen=True)
class NetConfig:
    base: int = 8  # channels of the first level (x2 per level)
    levels: int = 4
    outputs: int = len(TARGET_RATIOS)


def make_net(config: NetConfig = NetConfig()):
    """The U-Net-style encoder-decoder (pure torch)."""
    import torch  # optional heavy dependency: only the learned backend needs it
    from torch import nn

    def conv(cin, cout):
        return [nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]

    def block(cin, cout):  # encoder level: two 3x3 convolutions
        return nn.Sequential(*conv(cin, cout), *conv(cout, cout))

    class OccupancyUNet(nn.Module):
        def __init__(self, cfg: NetConfig):
            super().__init__()
            ch = [cfg.base * 2 ** i for i in range(cfg.levels)]
            self.enc = nn.ModuleList([block(3 if i == 0 else ch[i - 1], ch[i]) for i in range(cfg.levels)])
            self.pool = nn.MaxPool2d(2)
            self.up = nn.ModuleList([nn.ConvTranspose2d(ch[i], ch[i - 1], 2, stride=2) for i in range(cfg.levels - 1, 0, -1)])
            # decoder levels: one 3x3 convolution over [upsampled, skip]
            self.dec = nn.ModuleList([nn.Sequential(*conv(2 * ch[i - 1], ch[i - 1])) for i in range(cfg.levels - 1, 0, -1)])
            self.head = nn.Conv2d(ch[0], cfg.outputs, 1)
            # Most ground-truth pixels are 0: start the sigmoid near 0 (0.05) rather than at 0.5,
            # or the first hundreds of steps only pull every output down.
            nn.init.constant_(self.head.bias, -3.0)

        def forward(self, x):
            return torch.sigmoid(self.head(unet_levels(x, self.enc, self.pool, self.up, self.dec)))

    return OccupancyUNet(config)


def ratio_loss(pred, target, ratio_index, support=None, floor=None, positive_weight: float = 0.0):
    """Pixelwise MSE on the channel of each sample's aspect ratio (line 1462). support (n, H, W)
    and floor (n, H, W): the seen-target constraint (`constrain_to_visible`: support all ones and
    floor 0 where nothing is seen) applied to the output before the loss; positive_weight w: the
    squared error of a ground-truth positive (> 0.1, line 1466) counts 1 + w times."""
    import torch  # optional heavy dependency: only the learned backend needs it

    sel = pred[torch.arange(pred.shape[0], device=pred.device), ratio_index]
    if support is not None:
        sel = torch.maximum(sel * support, floor)
    err = (sel - target) ** 2
    if positive_weight:
        err = err * (1.0 + positive_weight * (target > 0.1).to(err.dtype))
    return err.mean()


def load_model(path: Path | str | None = None, device="cpu"):
    """(model in eval mode on `device` (cpu | cuda | auto), checkpoint dict) from a weights file
    written by `ms-drake train occupancy`."""
    return load_network(path, default_weights, "occupancy", "occupancy --count 5000",
                        lambda config: make_net(NetConfig(**config)), device)


class LearnedOccupancy:
    """Backend ``estimate(depth, target_mask) -> (H, W)`` of OccupancyEstimator("learned").

    target_size: the target's (length, width, thickness) [m] (a TargetBox or TargetMesh works too): picks the
    output channel of the closest trained aspect ratio, and with `input_scaling` the zoom s.
    threads: torch's intra-op threads for this process (default 1: the harness runs one process
    per core, and on a loaded machine two threads per process were 5x slower than one, their
    OpenMP workers spinning while they wait; None leaves torch's setting).
    device: where the network runs (cpu | cuda | auto)."""

    name = "learned"

    def __init__(self, target_size, weights: Path | str | None = None, input_scaling: bool = True,
                 ratio_index: int | None = None, threads: int | None = 1, device="cpu"):
        import torch  # optional heavy dependency: only the learned backend needs it

        if threads is not None:
            torch.set_num_threads(int(threads))
        if hasattr(target_size, "length"):
            length, width = float(target_size.length), float(target_size.width)
        elif hasattr(target_size, "vertices"):  # a TargetMesh: its resting footprint's bounding box
            V = np.asarray(target_size.vertices, float) @ np.asarray(target_size.R_WO, float).T
            length, width = sorted(np.ptp(V[:, :2], axis=0), reverse=True)
        else:
            vals = sorted([float(v) for v in target_size][:2], reverse=True)
            length, width = vals
        k, s = nearest_ratio(length, width)
        self.diagonal = float(np.hypot(length, width))
        self.ratio_index = k if ratio_index is None else int(ratio_index)
        self.scale = s if input_scaling else 1.0
        self.net, self.checkpoint = load_model(weights, device)
        self.device = next(self.net.parameters()).device
        self.weights = Path(weights) if weights is not None else default_weights()
        self._torch = torch
        self.last_seconds = 0.0

    def predict_working(self, x: np.ndarray) -> np.ndarray:
        """(3, 96, 128) inputs -> (96, 128) prediction of this target's channel (zoom applied, then
        `estimator_output`)."""
        torch = self._torch
        t = time.perf_counter()
        xin = zoom(x, 1.0 / self.scale)
        with torch.inference_mode():
            xt = torch.from_numpy(np.ascontiguousarray(xin))[None].to(self.device)
            y = self.net(xt)[0, self.ratio_index].cpu().numpy()
        y = estimator_output(zoom(y[None], self.scale)[0], x[0], self.diagonal)
        self.last_seconds = time.perf_counter() - t
        return y

    def estimate(self, depth, target_mask: np.ndarray) -> np.ndarray:
        """(H, W) distribution from a depth image (read through geometry.preprocess_depth) and the
        target's modal mask."""
        return full_resolution(self.predict_working(working_inputs(preprocess_depth(depth), target_mask)))


def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
