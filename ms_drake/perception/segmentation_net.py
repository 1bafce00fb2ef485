"""Learned category-agnostic instance segmentation from one depth image (Ch. 5): a small pure-torch
U-Net with a three-class head (background / object interior / boundary between two objects)
and a connected-components grouping; the ``learned`` backend of `Segmenter`.

Why this design. The reference trains a Mask R-CNN (ResNet-35 FPN) for 24 h on a GPU. Here the
network has to train in about an hour on two shared CPU cores and run in <= 50 ms on one, with
pure torch (no torchvision, so no RoI-Align or detection heads to build on). A bottom-up
segmenter needs none of that: one dense prediction per pixel and a grouping step. Of the dense
formulations (Panoptic-DeepLab's centre heatmap + offsets, UOIS / embedding clustering, and the
"touching-boundary" three-class map used for touching cells and nuclei), the three-class map is
the cheapest to learn: a plain per-pixel cross-entropy, no regression targets whose scale has to
be tuned, and a grouping that is one connected-components pass. In a bin, objects touch one
another and the depth step between them is what the network learns to mark; objects on the
floor are separated from the floor by height. Its known limits: a modal mask cut in two by an
occluder comes out as two instances (an offset head would join them), and an object thinner than
about two working pixels (5 mm) has no interior and is lost.

Working resolution. The central 512 x 384 px of the 640 x 480 overhead image (the bin with a
~40 px margin for the camera jitter of the data, as `occupancy_net.CROP`) averaged over 2 x 2
blocks: 256 x 192 px, ~2.3 mm per pixel at 0.8 m, so a 1 cm object is ~4 px wide.
Inputs, two channels: the depth relative to the crop's median in units of 5 cm (missing pixels
take the largest valid depth) and the valid-pixel fraction (sensor dropout). Targets: label 0
where no object is seen, 2 on object pixels with a different object within `BOUNDARY` pixels
(Chebyshev distance; a band 2 x 2 px wide along a contact, ~9 mm), 1 on the other object pixels.

Grouping (`instances_from_probabilities`): the connected components (4-connectivity) of the
pixels with P(interior) > 0.5 are the seeds (>= `min_seed` pixels); every pixel with P(background)
< 0.5 within `grow` pixels of a seed joins its nearest seed (Euclidean distance transform). A
mask's score is the mean P(interior) over its seed. Masks are upsampled (nearest) to the full
image; outside the crop nothing is segmented.

torch is imported inside functions only (an optional heavy dependency: the rest of ms_drake works
without it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from ms_drake.paths import models_dir
from ms_drake.perception.weights import load_network
from ms_drake.perception.occupancy_net import CROP, DEPTH_UNIT, FULL_SHAPE, crop_image, unet_levels
from ms_drake.types import InstanceMasks

BLOCK = 2
WORK_SHAPE = (CROP[2] // BLOCK, CROP[3] // BLOCK)  # (192, 256)
CLASSES = ("background", "interior", "boundary")
MIN_GT_PIXELS = 20  # full-resolution visible pixels for a ground-truth mask
IGNORE = 255  # target value of pixels that carry no loss (objects left out of a training subset)
BOUNDARY = 2  # working pixels on either side of a contact between two objects


def default_weights() -> Path:
    return models_dir() / "weights" / "segmentation.pt"


def _crop(a: np.ndarray) -> np.ndarray:
    return crop_image(a, "the learned segmenter")


def working_inputs(depth: np.ndarray) -> np.ndarray:
    """(2, 192, 256) float32 network input from a full (480, 640) depth image in metres (0, nan
    or inf = missing)."""
    d = _crop(np.asarray(depth, np.float32))
    ok = np.isfinite(d) & (d > 0)
    fill = float(d[ok].max()) if ok.any() else 1.0
    d = np.where(ok, d, np.float32(fill))
    h, w = WORK_SHAPE
    d = d.reshape(h, BLOCK, w, BLOCK).mean(axis=(1, 3))
    v = ok.reshape(h, BLOCK, w, BLOCK).mean(axis=(1, 3))
    d = (d - np.median(d)) / DEPTH_UNIT
    return np.stack([d, v]).astype(np.float32)


def working_labels(labels: np.ndarray) -> np.ndarray:
    """(192, 256) instance labels (0 = none) sampled from a full-resolution label image (nearest)."""
    return np.ascontiguousarray(_crop(np.asarray(labels))[::BLOCK, ::BLOCK])


def class_targets(lab: np.ndarray) -> np.ndarray:
    """Instance labels (H, W) (0 = background) -> classes 0 background, 1 interior, 2 boundary."""
    lab = np.asarray(lab)
    k = np.ones((2 * BOUNDARY + 1, 2 * BOUNDARY + 1), np.uint8)
    big = np.where(lab > 0, lab, 0).astype(np.float32)
    small = np.where(lab > 0, lab, np.float32(65535.0)).astype(np.float32)
    hi = cv2.dilate(big, k)
    lo = cv2.erode(small, k)
    fg = lab > 0
    boundary = fg & ((hi != lab) | (lo != lab))
    out = fg.astype(np.int64)
    out[boundary] = 2
    return out


@dataclass(frozen=True)
class NetConfig:
    fine: int = 8  # channels at the working resolution (the full-resolution stem and the last layer)
    base: int = 16  # channels of the U-Net's first level, at half the working resolution (x2 per level)
    levels: int = 4
    inputs: int = 2
    outputs: int = len(CLASSES)


def make_net(config: NetConfig = NetConfig()):
    """The network (pure torch): a 3x3 stem at the working resolution, a stride-2 convolution into a
    U-Net at half resolution (two 3x3 convolutions per encoder level, one per decoder level), a
    transposed convolution back to the working resolution joined with the stem's features, one 3x3
    convolution and a 1x1 head. Most of the computation runs at half resolution (4x cheaper); the
    stem's skip keeps the boundaries at the working resolution."""
    import torch  # optional heavy dependency: only the learned backend needs it
    from torch import nn

    def conv(cin, cout, stride=1):
        return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(cout),
                nn.ReLU(inplace=True)]

    class SegmentationUNet(nn.Module):
        def __init__(self, cfg: NetConfig):
            super().__init__()
            ch = [cfg.base * 2 ** i for i in range(cfg.levels)]
            self.stem = nn.Sequential(*conv(cfg.inputs, cfg.fine))
            self.down = nn.Sequential(*conv(cfg.fine, ch[0], stride=2))
            self.enc = nn.ModuleList([nn.Sequential(*conv(ch[0] if i == 0 else ch[i - 1], ch[i]),
                                                    *conv(ch[i], ch[i])) for i in range(cfg.levels)])
            self.pool = nn.MaxPool2d(2)
            self.up = nn.ModuleList([nn.ConvTranspose2d(ch[i], ch[i - 1], 2, stride=2)
                                     for i in range(cfg.levels - 1, 0, -1)])
            self.dec = nn.ModuleList([nn.Sequential(*conv(2 * ch[i - 1], ch[i - 1]))
                                      for i in range(cfg.levels - 1, 0, -1)])
            self.up_fine = nn.ConvTranspose2d(ch[0], cfg.fine, 2, stride=2)
            self.dec_fine = nn.Sequential(*conv(2 * cfg.fine, cfg.fine))
            self.head = nn.Conv2d(cfg.fine, cfg.outputs, 1)

        def forward(self, x):
            f0 = self.stem(x)
            x = unet_levels(self.down(f0), self.enc, self.pool, self.up, self.dec)
            x = self.dec_fine(torch.cat([self.up_fine(x), f0], dim=1))
            return self.head(x)  # logits (N, 3, H, W)

    return SegmentationUNet(config)


CLASS_WEIGHTS = (1.0, 1.0, 4.0)  # boundaries are few pixels but decide every split


def segmentation_loss(logits, targets):
    """Pixelwise cross-entropy over the three classes (boundary weighted by CLASS_WEIGHTS); pixels
    whose target is IGNORE carry no loss."""
    import torch  # optional heavy dependency: only the learned backend needs it

    w = torch.tensor(CLASS_WEIGHTS, dtype=logits.dtype, device=logits.device)
    return torch.nn.functional.cross_entropy(logits, targets, weight=w, ignore_index=IGNORE)


def instances_from_probabilities(prob: np.ndarray, min_seed: int = 4, grow: float = 4.0,
                                 threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(labels (H, W) int32 with 0 = none and 1..K, scores (K,)) from class probabilities (3, H, W);
    see the module doc."""
    p_bg, p_int = prob[0], prob[1]
    seeds = (p_int > threshold).astype(np.uint8)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(seeds, connectivity=4)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_seed
    relabel = np.zeros(n, np.int32)
    relabel[keep] = np.arange(1, keep.sum() + 1)
    comp = relabel[comp]
    k = int(keep.sum())
    if k == 0:
        return np.zeros(prob.shape[1:], np.int32), np.zeros(0)
    dist, (iy, ix) = ndimage.distance_transform_edt(comp == 0, return_indices=True)
    fg = (p_bg < threshold) & (dist <= grow)
    labels = np.where(fg | (comp > 0), comp[iy, ix], 0).astype(np.int32)
    sums = np.bincount(comp.ravel(), weights=p_int.ravel(), minlength=k + 1)
    cnts = np.bincount(comp.ravel(), minlength=k + 1)
    scores = sums[1:] / np.maximum(cnts[1:], 1)
    return labels, scores


def full_resolution_masks(labels: np.ndarray, scores: np.ndarray, min_pixels: int = MIN_GT_PIXELS) -> InstanceMasks:
    """Working labels (192, 256) -> InstanceMasks on the full 640 x 480 image, by decreasing score."""
    t, l, h, w = CROP
    up = cv2.resize(labels.astype(np.int32), (w, h), interpolation=cv2.INTER_NEAREST)
    full = np.zeros(FULL_SHAPE, np.int32)
    full[t:t + h, l:l + w] = up
    order = np.argsort(-scores, kind="stable")
    masks, keep = [], []
    for j in order:
        m = full == j + 1
        if m.sum() >= min_pixels:
            masks.append(m)
            keep.append(j)
    if not masks:
        return InstanceMasks.empty(*FULL_SHAPE)
    return InstanceMasks(np.stack(masks), tuple(f"seg_{i}" for i in range(len(masks))),
                         np.asarray(scores)[keep].astype(float))


def load_model(path: Path | str | None = None, device="cpu"):
    """(model in eval mode on `device` (cpu | cuda | auto), checkpoint dict) from a weights file
    written by `ms-drake train segmentation`."""
    return load_network(path, default_weights, "segmentation", "segmentation --count 4000",
                        lambda config: make_net(NetConfig(**config)), device)


class LearnedSegmentation:
    """``segment(depth) -> InstanceMasks`` with the trained network (one torch thread by default:
    the harness runs one process per core; None leaves torch's setting) on `device` (cpu | cuda |
    auto)."""

    name = "learned"

    def __init__(self, weights: Path | str | None = None, threads: int | None = 1, min_seed: int = 4,
                 grow: float = 4.0, device="cpu"):
        import torch  # optional heavy dependency: only the learned backend needs it

        if threads is not None:
            torch.set_num_threads(int(threads))
        self.net, self.checkpoint = load_model(weights, device)
        self.device = next(self.net.parameters()).device
        self.weights = Path(weights) if weights is not None else default_weights()
        self.min_seed, self.grow = int(min_seed), float(grow)
        self._torch = torch
        self.last_seconds = 0.0

    def probabilities(self, x: np.ndarray) -> np.ndarray:
        """(2, 192, 256) inputs -> (3, 192, 256) class probabilities."""
        torch = self._torch
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(x))[None].to(self.device)
            return torch.softmax(self.net(x), dim=1)[0].cpu().numpy()

    def segment(self, depth) -> InstanceMasks:
        t = time.perf_counter()
        d = np.asarray(depth.data if hasattr(depth, "data") else depth, np.float32)
        d = d[..., 0] if d.ndim == 3 else d
        if not (np.isfinite(d) & (d > 0)).any():  # no depth return at all: nothing to segment
            self.last_seconds = time.perf_counter() - t
            return InstanceMasks.empty(*d.shape)
        labels, scores = instances_from_probabilities(self.probabilities(working_inputs(d)), self.min_seed, self.grow)
        out = full_resolution_masks(labels, scores)
        self.last_seconds = time.perf_counter() - t
        return out
