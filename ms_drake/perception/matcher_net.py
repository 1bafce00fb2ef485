"""Learned target matching (App. C.2, lines 1969-1984): a small siamese network in pure torch that
scores whether an instance mask in a heap image shows the same object as a template view of the
target; the ``learned`` backend of `TargetDetector`.

The reference featurises 512 x 512 RGB crops with a frozen ImageNet ResNet-50, concatenates the
two feature vectors and scores them with a 1024-unit dense layer and a sigmoid output, threshold
t_r = 0.9. Pretrained weights cannot be downloaded here (and torchvision does not import next to
the CPU torch), so the encoder is a small CNN trained from scratch on rendered heaps
(``ms-drake data matcher``, ``ms-drake train matcher``).

Input of the shared encoder, 4 channels x 64 x 64 (`crop`):
- the RGB image multiplied by the instance mask (3 channels, in [0, 1]): the object's own colour
  and shading, with the neighbours and the bin blanked out -- neighbours differ between the heap
  and the template, so leaving them in would teach the network to match backgrounds;
- the mask itself (1 channel): the silhouette. When two objects share a colour (the case where
  the HSV detector must fail) the silhouette and its size are what tell them apart, and a
  masked-out dark object would otherwise look like background.
The crop is a fixed 192 x 192 px window of the 640 x 480 image centred on the mask's bounding box,
averaged down to 64 x 64 (3 x 3 blocks): a fixed scale, not one stretched to the mask, so the
object's size in the image (the camera is the same for templates and heap) reaches the network.
An object larger than the window is cut at its edge.

Network: encoder conv(4->24, stride 2) - conv(24->32, s2) - conv(32->48, s2) - conv(48->64, s2) -
conv(64->64) (3x3, BatchNorm, ReLU), global average and max pooling -> 128 features; the head reads
the concatenation [f_a, f_b, |f_a - f_b|] (the concatenation of the reference, with the absolute
difference added so that a small head on little data learns a distance rather than two separate
appearances) -> dense 128 (ReLU) -> dense 1 -> sigmoid. A score is the maximum over the target's
template views; the best-scoring mask is the target when its score is >= t_r = 0.9.

torch is imported inside functions only (an optional heavy dependency).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ms_drake.errors import PerceptionError
from ms_drake.paths import models_dir
from ms_drake.perception.weights import load_network

WINDOW = 192  # full-resolution pixels of the crop window
SIZE = 64  # crop side after averaging (WINDOW / 3)
CHANNELS = 4  # masked R, G, B and the mask
THRESHOLD = 0.9  # t_r of the reference


def default_weights() -> Path:
    return models_dir() / "weights" / "matcher.pt"


def crop(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(4, 64, 64) float32 network input of one mask of an (H, W, 3) uint8 image (see the module doc)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise PerceptionError("matcher crop: the mask is empty; give a mask with at least one pixel")
    ys, xs = np.nonzero(mask)
    cy, cx = (ys.min() + ys.max() + 1) // 2, (xs.min() + xs.max() + 1) // 2
    h, w = mask.shape
    half = WINDOW // 2
    y0, x0 = cy - half, cx - half
    win = np.zeros((WINDOW, WINDOW, 4), np.float32)
    sy0, sx0 = max(0, y0), max(0, x0)
    sy1, sx1 = min(h, y0 + WINDOW), min(w, x0 + WINDOW)
    m = mask[sy0:sy1, sx0:sx1].astype(np.float32)
    win[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0, :3] = np.asarray(rgb[sy0:sy1, sx0:sx1, :3], np.float32) / 255.0 * m[..., None]
    win[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0, 3] = m
    small = cv2.resize(win, (SIZE, SIZE), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small.transpose(2, 0, 1))


def occlude(mask: np.ndarray, rng: np.random.Generator, low: float = 0.2, high: float = 0.8) -> np.ndarray:
    """The mask with a random part cut away (a half-plane of random direction whose offset removes
    a fraction in [low, high] of its pixels): the occlusion augmentation of App. C.2."""
    mask = np.asarray(mask, bool)
    ys, xs = np.nonzero(mask)
    if len(ys) < 5:
        return mask.copy()
    a = rng.uniform(0, 2 * np.pi)
    proj = xs * np.cos(a) + ys * np.sin(a)
    frac = rng.uniform(low, high)
    cut = np.quantile(proj, frac)
    out = np.zeros_like(mask)
    keep = proj >= cut
    out[ys[keep], xs[keep]] = True
    return out


@dataclass(frozen=True)
class MatcherConfig:
    widths: tuple = (24, 32, 48, 64, 64)
    hidden: int = 128


def make_net(config: MatcherConfig = MatcherConfig()):
    """The siamese network (encoder + head), a torch.nn.Module: forward(a, b) -> logits (n,)."""
    import torch  # optional heavy dependency: only the learned matcher needs it
    from torch import nn

    class SiameseMatcher(nn.Module):
        def __init__(self, cfg: MatcherConfig):
            super().__init__()
            layers, cin = [], CHANNELS
            for i, c in enumerate(cfg.widths):
                stride = 2 if i < len(cfg.widths) - 1 else 1
                layers += [nn.Conv2d(cin, c, 3, stride, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)]
                cin = c
            self.encoder = nn.Sequential(*layers)
            self.features = 2 * cin
            self.head = nn.Sequential(nn.Linear(3 * self.features, cfg.hidden), nn.ReLU(inplace=True),
                                      nn.Linear(cfg.hidden, 1))

        def embed(self, x):
            f = self.encoder(x)
            return torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3))], dim=1)

        def score_features(self, fa, fb):
            return self.head(torch.cat([fa, fb, (fa - fb).abs()], dim=1)).squeeze(1)

        def forward(self, a, b):
            return self.score_features(self.embed(a), self.embed(b))

    return SiameseMatcher(config)


def load_matcher(path: Path | str | None = None, device="cpu"):
    """(network in eval mode on `device` (cpu | cuda | auto), checkpoint dict) from a weights file of
    `ms-drake train matcher`."""
    return load_network(path, default_weights, "matcher", "matcher --heaps 400", lambda config: make_net(
        MatcherConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in config.items()})), device)


class LearnedMatcher:
    """Scores the masks of an image against the target's template views with the siamese network.

    templates: objects with `rgb` (h, w, 3) uint8 and `mask` (h, w) bool (perception.target.Template).
    threshold: t_r; min_pixels: smaller masks score 0; device: where the network runs (cpu | cuda |
    auto)."""

    def __init__(self, templates, weights: Path | str | None = None, threshold: float = THRESHOLD,
                 min_pixels: int = 20, threads: int | None = 1, device="cpu"):
        import torch  # optional heavy dependency: only the learned matcher needs it

        if not templates:
            raise PerceptionError("TargetDetector(backend='learned') needs at least one template image "
                                  "(render_templates(scenario, object_name, k))")
        if not 0.0 <= threshold <= 1.0:
            raise PerceptionError(f"matcher threshold t_r={threshold} must lie in [0, 1] (reference: 0.9)")
        for i, t in enumerate(templates):
            if t.mask.shape != t.rgb.shape[:2] or not t.mask.any():
                raise PerceptionError(f"template {i}: its mask must be a non-empty (h, w) array matching its image")
        if threads is not None:
            torch.set_num_threads(int(threads))
        self.torch = torch
        self.net, self.checkpoint = load_matcher(weights, device)
        self.device = next(self.net.parameters()).device
        self.threshold, self.min_pixels = float(threshold), int(min_pixels)
        with torch.no_grad():
            x = torch.from_numpy(np.stack([crop(t.rgb, t.mask) for t in templates])).to(self.device)
            self.template_features = self.net.embed(x)

    def scores_of_crops(self, crops: np.ndarray) -> np.ndarray:
        """(n,) max-over-templates sigmoid scores of (n, 4, 64, 64) candidate crops."""
        torch = self.torch
        if len(crops) == 0:
            return np.zeros(0)
        with torch.no_grad():
            fb = self.net.embed(torch.from_numpy(np.ascontiguousarray(crops, np.float32)).to(self.device))
            t = len(self.template_features)
            fa = self.template_features.repeat(len(fb), 1)
            fbr = fb.repeat_interleave(t, dim=0)
            s = torch.sigmoid(self.net.score_features(fa, fbr)).reshape(len(fb), t)
        return s.amax(dim=1).cpu().numpy().astype(float)

    def scores(self, rgb: np.ndarray, masks) -> np.ndarray:
        """(K,) scores of the K masks of an InstanceMasks in the (H, W, 3) uint8 image."""
        out = np.zeros(len(masks))
        keep = [k for k in range(len(masks)) if masks.masks[k].sum() >= self.min_pixels]
        if keep:
            out[keep] = self.scores_of_crops(np.stack([crop(rgb, masks.masks[k]) for k in keep]))
        return out
