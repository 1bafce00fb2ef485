"""Target occupancy on a shelf (Ch. 9.4.2): the `ShelfOccupancyEstimator` LeafSystem.

Output: a ShelfOccupancy -- the 2D distribution of the target's footprint centre on the shelf
floor and the 1D distribution P_t(x) along the camera image's x axis (each placement covers the
image columns of its projected box; the reference sums its 2D image distribution over rows).

Backends:
- "ground_truth" (analytic, for ablations and the FOSS tables): the hidden placements of a target
  of the known size behind the scene's occluders (ms_drake.shelf_geometry.hidden_placements, the
  scene generator's computation) applied to the current scene. The target's own position is used
  only as the observation a detector would give: when any of it is visible the distribution
  collapses onto it; while it is hidden its true placement is added to the hidden set (the
  placements consistent with the observation include the truth even when it sits closer to an
  occluder than the grid resolves).
- "learned": the reference's network (ms_drake.perception.shelf_occupancy_net: the shelf camera's
  480 x 640 depth image -> P(x) for three target heights; the head nearest the target's height is
  used). It reads the ``depth_image`` input (ImageDepth32F, metres) instead of the scene; its
  ShelfOccupancy has P(x) only (`floor` is an empty (0, 0) array: the network predicts no floor
  distribution). Its weights (LEARNED_WEIGHTS, models/weights/shelf_occupancy.md) load when the
  system is made; missing weights raise a PerceptionError naming the commands that make them.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.errors import PerceptionError
from ms_drake.geometry import preprocess_depth
from ms_drake.paths import models_dir
from ms_drake.perception.shelf_occupancy_net import IMAGE_SHAPE, LearnedShelfOccupancy
from ms_drake.shelf_geometry import (
    Prisms,
    ShelfGeometry,
    box_corners,
    coverage,
    hidden_placements,
    visible_fraction,
)
from ms_drake.types import ShelfOccupancy, ShelfScene

BACKENDS = ("ground_truth", "learned")
LEARNED_WEIGHTS = "weights/shelf_occupancy.pt"  # under models/
DEFAULT_TARGET = (0.06, 0.06, 0.06)


def _point_occupancy(geometry: ShelfGeometry, hidden, center: np.ndarray, size) -> ShelfOccupancy:
    """All the mass at one placement (the nearest floor grid cell; its projected box's columns)."""
    g = hidden.grid
    floor = np.zeros_like(hidden.mask, float)
    i = int(np.clip(round((center[1] - g.y0) / g.step), 0, g.ny - 1))
    j = int(np.clip(round((center[0] - g.x0) / g.step), 0, g.nx - 1))
    floor[i, j] = 1.0
    u, _, _ = geometry.project(box_corners(center[None], size))
    cov = coverage(np.stack([u.min(axis=1), u.max(axis=1)], axis=1), geometry.camera.width)
    return ShelfOccupancy(floor, cov / cov.sum(), g.x0, g.y0, g.step)


def ground_truth_occupancy(geometry: ShelfGeometry, scene: ShelfScene, target_size=None, step: float = 0.005,
                           clearance: float = 0.0) -> ShelfOccupancy:
    """The "ground_truth" backend as a function (module docstring)."""
    size = tuple(float(v) for v in (target_size if target_size is not None else
                                    (scene.target.width, scene.target.depth, scene.target.height)
                                    if scene.target is not None else DEFAULT_TARGET))
    occluders = Prisms.of(scene.objects)
    hidden = hidden_placements(geometry, occluders, size, step, clearance)
    t = scene.target
    if t is None:
        return hidden.occupancy(geometry)
    center = np.array([t.x, t.y])
    if visible_fraction(geometry, t, occluders) > 0:
        return _point_occupancy(geometry, hidden, center, size)
    g = hidden.grid
    i, j = round((t.y - g.y0) / g.step), round((t.x - g.x0) / g.step)
    if not (0 <= i < g.ny and 0 <= j < g.nx and hidden.mask[i, j]):
        mask = hidden.mask.copy()
        mask[int(np.clip(i, 0, g.ny - 1)), int(np.clip(j, 0, g.nx - 1))] = True
        hidden = type(hidden)(hidden.size, g, mask, hidden.candidates)
    return hidden.occupancy(geometry)


class ShelfOccupancyEstimator(LeafSystem):
    """Ports (declared first): inputs ``scene`` (ShelfScene; the ground-truth backend's observation)
    and ``depth_image`` (ImageDepth32F of the shelf camera; the learned backend's), output
    ``occupancy`` (ShelfOccupancy).

    geometry: the shelf and camera (ShelfGeometry.from_scenario); target_size: the known target's
    (w, d, h) in metres (None: the scene's target's for "ground_truth", DEFAULT_TARGET for
    "learned", which sees no scene); backend: one of BACKENDS; weights: the learned backend's file
    (None: models/weights/shelf_occupancy.pt)."""

    def __init__(self, geometry: ShelfGeometry, target_size=None, backend: str = "ground_truth",
                 step: float = 0.005, weights=None):
        super().__init__()
        if backend not in BACKENDS:
            raise PerceptionError(f"ShelfOccupancyEstimator(backend={backend!r}): choose one of {', '.join(BACKENDS)}")
        if target_size is not None and (len(target_size) != 3 or min(target_size) <= 0):
            raise PerceptionError(f"ShelfOccupancyEstimator(target_size={target_size!r}): give (w, d, h) > 0 in metres")
        width = geometry.camera.width
        if backend == "learned" and (geometry.camera.height, width) != IMAGE_SHAPE:
            raise PerceptionError(f"ShelfOccupancyEstimator(backend='learned'): the camera is {width} x "
                                  f"{geometry.camera.height}; the network takes {IMAGE_SHAPE[1]} x {IMAGE_SHAPE[0]}")
        # Ports first.
        self.scene_port = self.DeclareAbstractInputPort("scene", AbstractValue.Make(ShelfScene(())))
        self.depth_port = self.DeclareAbstractInputPort(
            "depth_image", AbstractValue.Make(ImageDepth32F(width, geometry.camera.height)))
        self.DeclareAbstractOutputPort(
            "occupancy", lambda: AbstractValue.Make(ShelfOccupancy(np.zeros((1, 1)), np.zeros(width))), self._calc)
        self.geometry = geometry
        self.target_size = target_size
        self.backend = backend
        self.step = step
        self.model = LearnedShelfOccupancy(weights if weights is not None else models_dir() / LEARNED_WEIGHTS) \
            if backend == "learned" else None

    def _calc(self, context, output):
        if self.backend == "learned":
            if not self.depth_port.HasValue(context):
                raise PerceptionError("ShelfOccupancyEstimator('learned'): connect the depth_image input (the shelf "
                                      "camera's depth, e.g. ShelfDepthCamera's)")
            depth = preprocess_depth(self.depth_port.Eval(context))
            p = self.model.predict(depth, self.target_size if self.target_size is not None else DEFAULT_TARGET)
            output.set_value(ShelfOccupancy(np.zeros((0, 0)), p))
            return
        if not self.scene_port.HasValue(context):
            raise PerceptionError("ShelfOccupancyEstimator: connect the scene input (FossSystem's scene)")
        output.set_value(ground_truth_occupancy(self.geometry, self.scene_port.Eval(context), self.target_size,
                                                self.step))
