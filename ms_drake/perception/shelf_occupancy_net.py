"""Learned target occupancy on a shelf (Ch. 9.4.2, lines 1636-1642): a small CPU network from the
shelf camera's depth image to the 1D distribution P_t(x) along the image x axis, one head per
target size of TARGET_SIZES (6 x 6 x 6, 6 x 6 x 3 and 6 x 6 x 12 cm; 6 cm wide and deep).

Working resolution. The 640 x 480 depth image is averaged over 4 x 4 blocks (`block_depth`: the
mean of the finite depths of each block, 0 where a block has none) to 160 x 120; that is what
`ms-drake data shelf --depth-block 4` stores. The network predicts P(x) on 160 bins of 4 image
columns; `expand_bins` spreads each bin's mass evenly over its 4 columns (the 640-column P(x) the
policies take).

Inputs (4 channels): depth in units of 0.5 m about 1 m (clipped to [0, 2.5] m), the validity of
the depth (block had a return), and the normalised row and column coordinates (the camera is fixed
to the shelf, so where a pixel is matters: the shelf floor, walls and back are at fixed places).

Network (`ShelfOccupancyNet`): five 3 x 3 convolutions with stride 2 in rows only (120 -> 4 rows,
160 columns kept), BatchNorm + ReLU; each column's remaining 4 rows x C features are one vector;
then 1D convolutions along x (kernel 5, dilations 1, 2, 4, 8, 16, residual), and a 1 x 1
convolution to one logit per head and bin; a softmax over x gives each head's distribution. Its
receptive field spans about +-60 bins (+-240 image columns), the width of the hidden regions behind
the widest occluders. About 0.1 M parameters, ~45 M multiply-adds per image.

The reference trains a network per image on the head of the scene's own target only; our shards
also hold the ground truth of every size behind the same occluders (`image_x_sizes`), so every
head learns from every image (`distribution_loss`: cross entropy of the predicted distribution
against the ground truth, heads whose ground truth is empty -- no hidden placement for that size --
left out).

torch is imported inside functions only (an optional heavy dependency: the rest of ms_drake and
the ground-truth backend work without it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ms_drake.errors import PerceptionError
from ms_drake.paths import models_dir
from ms_drake.perception.weights import torch_device

#: Heads in this order: the keys of ms_drake.scenes.shelf.TARGET_SIZES (cube, flat, tall).
HEAD_SIZES = ((0.06, 0.06, 0.06), (0.06, 0.06, 0.03), (0.06, 0.06, 0.12))
BLOCK = 4
IMAGE_SHAPE = (480, 640)
WORK_SHAPE = (IMAGE_SHAPE[0] // BLOCK, IMAGE_SHAPE[1] // BLOCK)  # (120, 160)
DEPTH_CENTER, DEPTH_UNIT, DEPTH_MAX = 1.0, 0.5, 2.5  # m
MAKE_WEIGHTS = ("ms-drake data shelf --count 5100 --seed-start 100000 --depth-block 4 --out DATA/train && "
                "ms-drake train shelf-occupancy --data DATA --out models/weights/shelf_occupancy.pt --overwrite-shipped")


def default_weights() -> Path:
    return models_dir() / "weights" / "shelf_occupancy.pt"


def head_index(target_size) -> int:
    """The head whose target height is nearest to target_size's (w, d, h) height."""
    h = float(target_size[2])
    return int(np.argmin([abs(np.log(h / s[2])) for s in HEAD_SIZES]))


def block_depth(depth: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Mean of the finite depths of each block x block pixel block (0 where a block has none)."""
    depth = np.asarray(depth, np.float32)
    if block == 1:
        return depth
    h, w = depth.shape
    d = depth[:h - h % block, :w - w % block].reshape(h // block, block, w // block, block)
    ok = np.isfinite(d) & (d > 0)
    n = ok.sum(axis=(1, 3))
    return np.where(n > 0, np.where(ok, d, 0).sum(axis=(1, 3)) / np.maximum(n, 1), 0).astype(np.float32)


def network_input(work_depth: np.ndarray) -> np.ndarray:
    """(..., 4, 120, 160) float32 input from block-averaged depth images (..., 120, 160) (metres, 0: none)."""
    d = np.asarray(work_depth, np.float32)
    if d.shape[-2:] != WORK_SHAPE:
        raise PerceptionError(f"depth image of {d.shape[-1]} x {d.shape[-2]} working pixels; the shelf occupancy "
                              f"network takes {IMAGE_SHAPE[1]} x {IMAGE_SHAPE[0]} images averaged over {BLOCK} x "
                              f"{BLOCK} blocks ({WORK_SHAPE[1]} x {WORK_SHAPE[0]})")
    valid = (d > 0).astype(np.float32)
    depth = np.where(valid > 0, (np.minimum(d, DEPTH_MAX) - DEPTH_CENTER) / DEPTH_UNIT, 0).astype(np.float32)
    rows = np.broadcast_to(np.linspace(-1, 1, WORK_SHAPE[0], dtype=np.float32)[:, None], d.shape)
    cols = np.broadcast_to(np.linspace(-1, 1, WORK_SHAPE[1], dtype=np.float32)[None, :], d.shape)
    return np.stack([depth, valid, rows, cols], axis=-3)


def image_input(depth: np.ndarray) -> np.ndarray:
    """network_input of a full-resolution (480 x 640) depth image in metres (inf / nan / 0: none)."""
    d = np.asarray(depth, np.float32)
    if d.shape != IMAGE_SHAPE:
        raise PerceptionError(f"depth image is {d.shape[1] if d.ndim > 1 else '?'} x {d.shape[0]}; the shelf "
                              f"occupancy network takes {IMAGE_SHAPE[1]} x {IMAGE_SHAPE[0]} images")
    return network_input(block_depth(d))


def pool_bins(image_x: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(..., 640) column distribution -> (..., 160) bin distribution (sums of 4 columns)."""
    a = np.asarray(image_x, np.float32)
    return a.reshape(*a.shape[:-1], a.shape[-1] // block, block).sum(-1)


def expand_bins(p: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """(..., 160) bin distribution -> (..., 640): each bin's mass spread evenly over its columns."""
    return np.repeat(np.asarray(p), block, axis=-1) / block


@dataclass(frozen=True)
class NetConfig:
    channels: tuple = (16, 24, 32, 32, 32)  # the five row-striding 2D convolutions
    width: int = 64  # channels of the 1D convolutions along x
    dilations: tuple = (1, 2, 4, 8, 16)
    heads: int = len(HEAD_SIZES)


def make_net(config: NetConfig = NetConfig()):
    """A ShelfOccupancyNet (module docstring): (B, 4, 120, 160) -> logits (B, heads, 160)."""
    import torch  # optional heavy dependency: only the learned shelf occupancy needs it
    from torch import nn

    class ShelfOccupancyNet(nn.Module):
        def __init__(self, cfg: NetConfig):
            super().__init__()
            layers, c_in, rows = [], 4, WORK_SHAPE[0]
            for c in cfg.channels:
                layers += [nn.Conv2d(c_in, c, 3, stride=(2, 1), padding=1, bias=False), nn.BatchNorm2d(c),
                           nn.ReLU(inplace=True)]
                c_in, rows = c, (rows + 1) // 2
            self.encoder = nn.Sequential(*layers)
            self.project = nn.Sequential(nn.Conv1d(c_in * rows, cfg.width, 1, bias=False),
                                         nn.BatchNorm1d(cfg.width), nn.ReLU(inplace=True))
            self.blocks = nn.ModuleList(
                nn.Sequential(nn.Conv1d(cfg.width, cfg.width, 5, padding=2 * d, dilation=d, bias=False),
                              nn.BatchNorm1d(cfg.width), nn.ReLU(inplace=True)) for d in cfg.dilations)
            self.head = nn.Conv1d(cfg.width, cfg.heads, 1)

        def forward(self, x):
            f = self.encoder(x)  # (B, C, rows, W)
            f = self.project(f.flatten(1, 2))  # (B, width, W)
            for block in self.blocks:
                f = f + block(f)
            return self.head(f)

    torch.manual_seed(0)  # the initial weights (training reseeds before it makes its net)
    return ShelfOccupancyNet(config)


def distribution_loss(logits, target):
    """Mean cross entropy -sum_x q(x) log p(x) over the (sample, head) pairs with a non-empty
    ground truth q; logits and target (B, heads, bins)."""
    import torch  # optional heavy dependency: only the learned shelf occupancy needs it

    logp = torch.log_softmax(logits, dim=-1)
    mass = target.sum(-1)
    ok = mass > 0
    q = target / mass.clamp_min(1e-12).unsqueeze(-1)
    ce = -(q * logp).sum(-1)
    return (ce * ok).sum() / ok.sum().clamp_min(1)


def load_model(path=None, device="cpu"):
    """(net in eval mode on `device` (cpu | cuda | auto), meta) from a weights file written by
    training; PerceptionError naming the command that makes it when missing."""
    import torch  # optional heavy dependency: only the learned shelf occupancy needs it

    dev = torch_device(device)
    path = Path(path) if path is not None else default_weights()
    if not path.exists():
        raise PerceptionError(f"shelf occupancy weights {path} not found; the learned shelf occupancy needs them: "
                              f"make them with "
                              f"`{MAKE_WEIGHTS}` (see models/weights/shelf_occupancy.md), or use "
                              "backend='ground_truth'")
    fix = f"give a weights file written by `ms-drake train shelf-occupancy`, or make it with `{MAKE_WEIGHTS}`"
    try:
        blob = torch.load(path, map_location=dev, weights_only=False)
    except Exception as e:  # garbage bytes, a truncated file: torch / pickle raise many types
        raise PerceptionError(f"shelf occupancy weights {path} cannot be read ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else 'unreadable'}); {fix}") from None
    try:
        net = make_net(NetConfig(**{k: tuple(v) if isinstance(v, list) else v
                                    for k, v in blob["config"].items()})).to(dev)
        net.load_state_dict(blob["state_dict"])
    except Exception as e:  # another network's file: no config / state_dict, mis-shaped tensors
        raise PerceptionError(f"{path} does not hold the shelf occupancy network ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else 'mismatch'}); {fix}") from None
    net.eval()
    return net, blob.get("meta", {})


def config_dict(config: NetConfig) -> dict:
    return asdict(config)


class LearnedShelfOccupancy:
    """The loaded network: `predict(depth, target_size)` -> P(x) over the 640 image columns; it runs
    on `device` (cpu | cuda | auto)."""

    def __init__(self, path=None, threads: int = 1, device="cpu"):
        import torch  # optional heavy dependency: only the learned shelf occupancy needs it

        self.net, self.meta = load_model(path, device)
        self.device = next(self.net.parameters()).device
        self.threads = threads
        self._torch = torch

    def predict_bins(self, inputs: np.ndarray) -> np.ndarray:
        """(B, 4, 120, 160) inputs -> (B, heads, 160) distributions."""
        torch = self._torch
        if torch.get_num_threads() != self.threads:
            torch.set_num_threads(self.threads)
        with torch.inference_mode():
            x = torch.from_numpy(np.ascontiguousarray(inputs, np.float32)).to(self.device)
            return torch.softmax(self.net(x), -1).cpu().numpy()

    def predict(self, depth: np.ndarray, target_size) -> np.ndarray:
        """P(x) (640,) of the head nearest to target_size from a 480 x 640 depth image (metres)."""
        p = self.predict_bins(image_input(depth)[None])[0, head_index(target_size)]
        return expand_bins(p).astype(float)
