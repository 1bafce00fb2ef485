"""Shelf objects from one depth image of the shelf camera (Ch. 9.4.2): the `ShelfSegmenter` LeafSystem.

The reference's perception "segments the scene into object instances using the input depth image"
and its policies work on those masks and on the objects they imply. Here:

1. Points. The depth image is deprojected into the shelf frame (ms_drake.shelf_geometry); points on
   or outside the shelf's floor, walls and ceiling (within `margin`) are background.
2. Instances. A clustering of the organized cloud: neighbouring pixels (4-connectivity) belong to
   one object when their points are closer than `tolerance`; connected components with at least
   `min_pixels` pixels are the instances. On the pixel grid, unlike the bin's Euclidean clustering
   of a subsampled cloud (ms_drake.perception.segmentation), surfaces seen at a grazing angle (the
   tops, 30 degrees below the camera) stay connected, and an object standing behind another is
   split from it by the depth jump at the front object's silhouette.
3. Objects. Each instance becomes an upright ShelfObject (what FOSS and the policies plan with):
   - height: the highest point; x extent: the instance's; front: its frontmost y (each leaving out
     the `outliers` percent of points at the ends, which a noisy sensor scatters);
   - cylinder or box: along x, the front of each 1 cm column of the lower 80 % of the instance (the
     `front_percentile` of its y, not the frontmost point, which a noisy sensor's stray points set)
     follows a circular arc for a cylinder and stays at the front for a box; the instance is a
     cylinder when the mean setback of the columns within `inner` of the half-width from the
     centre (the outer columns of a box seen from the side hold its side face) behind the front
     (the same percentile of the column fronts) exceeds `cylinder_setback` of the half-width;
   - depth: a box's top face is seen from the camera above the shelf, so its y extent is the box's
     depth (when the top is hidden, e.g. behind a taller object in front, the depth is the width);
     a cylinder's diameter is the larger of its x extent and its top's y extent.
   An instance partly hidden by an object in front of it has a narrower x extent than the object
   (the reference's Sec. 9.5 reports the same effect of narrow masks on its DER-3 runs).

The target is not an occluder: with the optional ``rgb_image`` input connected, the target's
pixels (its colour, ms_drake.perception.target.red_pixels) are left out of the instances and given
as the ``target_mask`` output.

Ports (declared first): inputs ``depth_image`` (ImageDepth32F, metres; the shelf camera's) and
``rgb_image`` (ImageRgba8U, optional), outputs ``masks`` (InstanceMasks, ids ``seg_<k>`` ordered by
x from left to right), ``scene`` (ShelfScene of the estimated objects, ids as the masks', no
target) and ``target_mask`` ((H, W) bool; all False without the rgb input).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from ms_drake.errors import PerceptionError
from ms_drake.geometry import depth_array, preprocess_depth, world_points
from ms_drake.perception.target import red_pixels
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.types import InstanceMasks, ShelfObject, ShelfScene


@dataclass(frozen=True)
class ShelfSegmentationParams:
    """tolerance: largest distance [m] between neighbouring pixels' points of one object;
    min_pixels: smallest instance kept; margin: points this close [m] to the floor, walls or
    ceiling are the shelf; column: x bin width [m] of the cylinder test; cylinder_setback: the
    cylinder test's threshold (mean setback of the inner columns' fronts / half-width; a cylinder's
    is about 0.12 with inner = 0.8, a box's 0); inner: the columns the test uses, as a fraction of
    the half-width from the centre; min_depth: a box top's y extent below this [m] counts as
    unseen (the depth is then the width); outliers: the percentage of an instance's points at each end
of its x, y and z ranges left out of the extents (a noisy sensor's stray points); front_percentile:
the percentile of a column's y taken as its front in the cylinder test (with 0, the frontmost
point, the L515 sensor model's stray points make boxes look round)."""

    tolerance: float = 0.006
    min_pixels: int = 150
    margin: float = 0.005
    column: float = 0.01
    cylinder_setback: float = 0.035
    inner: float = 0.8
    min_depth: float = 0.015
    outliers: float = 0.2
    front_percentile: float = 10.0

    def __post_init__(self):
        if self.tolerance <= 0 or self.min_pixels < 1 or self.margin < 0 or self.column <= 0:
            raise PerceptionError(f"ShelfSegmentationParams: tolerance={self.tolerance} and column={self.column} "
                                  f"must be > 0, min_pixels={self.min_pixels} >= 1, margin={self.margin} >= 0")


def shelf_points(geometry: ShelfGeometry, depth) -> np.ndarray:
    """(H, W, 3) shelf-frame points of the shelf camera's depth image (holes filled by
    geometry.preprocess_depth; NaN where invalid)."""
    return world_points(geometry.camera, depth_array(preprocess_depth(depth))) - np.asarray(geometry.origin, float)


def shelf_foreground(geometry: ShelfGeometry, P: np.ndarray, margin: float) -> np.ndarray:
    """(H, W) bool: points inside the shelf, off its floor, walls and ceiling by `margin`."""
    ok = np.all(np.isfinite(P), axis=-1)
    Q = np.where(ok[..., None], P, 0.0)
    hx, hy = 0.5 * geometry.size[0] - margin, 0.5 * geometry.size[1] - margin
    return ok & (np.abs(Q[..., 0]) < hx) & (Q[..., 1] > -0.5 * geometry.size[1]) & (Q[..., 1] < hy) & \
        (Q[..., 2] > margin) & (Q[..., 2] < geometry.size[2] - margin)


def organized_clusters(P: np.ndarray, foreground: np.ndarray, tolerance: float) -> np.ndarray:
    """(H, W) labels (-1: background) of the connected components of the pixel grid whose edges
    join 4-neighbours in the foreground with points closer than `tolerance`."""
    h, w = foreground.shape
    index = np.arange(h * w).reshape(h, w)
    rows, cols = [], []
    for a, b, pa, pb in ((foreground[:, :-1], foreground[:, 1:], P[:, :-1], P[:, 1:]),
                         (foreground[:-1, :], foreground[1:, :], P[:-1, :], P[1:, :])):
        close = a & b & (np.linalg.norm(np.nan_to_num(pa - pb, nan=np.inf), axis=-1) < tolerance)
        ia = index[:, :-1] if a.shape[1] == w - 1 else index[:-1, :]
        ib = index[:, 1:] if a.shape[1] == w - 1 else index[1:, :]
        rows.append(ia[close])
        cols.append(ib[close])
    fg = np.flatnonzero(foreground)
    labels = np.full(h * w, -1, np.int64)
    if len(fg) == 0:
        return labels.reshape(h, w)
    local = np.full(h * w, -1, np.int64)
    local[fg] = np.arange(len(fg))
    r, c = local[np.concatenate(rows)], local[np.concatenate(cols)]
    graph = sparse.coo_matrix((np.ones(len(r), bool), (r, c)), shape=(len(fg), len(fg)))
    _, comp = connected_components(graph, directed=False)
    labels[fg] = comp
    return labels.reshape(h, w)


def estimate_object(object_id: str, points: np.ndarray, geometry: ShelfGeometry,
                    params: ShelfSegmentationParams = ShelfSegmentationParams()) -> ShelfObject:
    """The upright box or cylinder (module docstring, step 3) behind one instance's points (V, 3)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    lo, hi = params.outliers, 100.0 - params.outliers  # robust to a sensor's noise
    height = float(np.percentile(z, hi))
    x_lo, x_hi = (float(v) for v in np.percentile(x, [lo, hi]))
    half_width = max(0.5 * (x_hi - x_lo), 1e-3)
    front = float(np.percentile(y, lo))
    side = z < 0.8 * height
    setback = 0.0
    if side.sum() >= 3:
        bins = np.floor((x[side] - x_lo) / params.column).astype(int)
        ys = y[side]
        columns = [b for b in np.unique(bins) if abs((b + 0.5) * params.column / half_width - 1.0) <= params.inner]
        fronts = np.array([np.percentile(ys[bins == b], params.front_percentile) for b in columns])
        if len(fronts) >= 3:
            ref = np.percentile(fronts, params.front_percentile)
            setback = float(np.mean(np.maximum(fronts - ref, 0.0))) / half_width
    top = points[z > height - 0.004]
    top_extent = float(np.subtract(*np.percentile(top[:, 1], [hi, lo]))) if len(top) else 0.0
    back = 0.5 * geometry.size[1]
    if setback > params.cylinder_setback:
        diameter = min(max(2 * half_width, top_extent), back - front)
        return ShelfObject(object_id, "cylinder", 0.5 * (x_lo + x_hi), front + 0.5 * diameter, diameter, diameter,
                           height)
    depth = top_extent if top_extent >= params.min_depth else 2 * half_width
    depth = max(min(depth, back - front), 1e-3)
    return ShelfObject(object_id, "box", 0.5 * (x_lo + x_hi), front + 0.5 * depth, 2 * half_width, depth, height)


def segment_shelf(geometry: ShelfGeometry, depth, params: ShelfSegmentationParams = ShelfSegmentationParams(),
                  exclude: np.ndarray | None = None) -> tuple[InstanceMasks, ShelfScene]:
    """(masks, scene) of the shelf camera's depth image (module docstring); pixels where `exclude`
    ((H, W) bool, e.g. the target's) is True belong to no instance."""
    P = shelf_points(geometry, depth)
    foreground = shelf_foreground(geometry, P, params.margin)
    if exclude is not None:
        if exclude.shape != foreground.shape:
            raise PerceptionError(f"segment_shelf: exclude mask is {exclude.shape}, the depth image "
                                  f"{foreground.shape}; give masks of the same camera")
        foreground &= ~exclude
    labels = organized_clusters(P, foreground, params.tolerance)
    present, counts = np.unique(labels[labels >= 0], return_counts=True)
    keep = present[counts >= params.min_pixels]
    h, w = labels.shape
    if len(keep) == 0:
        return InstanceMasks.empty(h, w), ShelfScene(())
    masks = [labels == k for k in keep]
    objects = [estimate_object("", P[m], geometry, params) for m in masks]
    order = sorted(range(len(masks)), key=lambda i: objects[i].x)
    ids = tuple(f"seg_{k}" for k in range(len(order)))
    scene = ShelfScene(tuple(ShelfObject(ids[k], objects[i].kind, objects[i].x, objects[i].y, objects[i].width,
                                         objects[i].depth, objects[i].height) for k, i in enumerate(order)))
    return InstanceMasks(np.stack([masks[i] for i in order]), ids, np.ones(len(order))), scene


class ShelfSegmenter(LeafSystem):
    """Ports (declared first): inputs ``depth_image`` (ImageDepth32F of the shelf camera, metres) and
    ``rgb_image`` (ImageRgba8U, optional: the target's colour is left out); outputs ``masks``
    (InstanceMasks), ``scene`` (ShelfScene of the estimated objects, no target) and ``target_mask``.
    geometry: the shelf and its camera (ShelfGeometry.from_scenario); params: ShelfSegmentationParams."""

    def __init__(self, geometry: ShelfGeometry, params: ShelfSegmentationParams | None = None):
        super().__init__()
        cam = geometry.camera
        self.depth_port = self.DeclareAbstractInputPort("depth_image",
                                                        AbstractValue.Make(ImageDepth32F(cam.width, cam.height)))
        self.rgb_port = self.DeclareAbstractInputPort("rgb_image",
                                                      AbstractValue.Make(ImageRgba8U(cam.width, cam.height)))
        empty_mask = np.zeros((cam.height, cam.width), bool)
        self._cache = self.DeclareCacheEntry(
            "segmentation", ValueProducer(
                allocate=lambda: AbstractValue.Make((InstanceMasks.empty(cam.height, cam.width), ShelfScene(()),
                                                     empty_mask)),
                calc=self._segment), prerequisites_of_calc={self.all_input_ports_ticket()})
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make(InstanceMasks.empty(cam.height, cam.width)),
                                       lambda c, o: o.set_value(self._cache.EvalAbstract(c).get_value()[0]),
                                       prerequisites_of_calc={self._cache.ticket()})
        self.DeclareAbstractOutputPort("scene", lambda: AbstractValue.Make(ShelfScene(())),
                                       lambda c, o: o.set_value(self._cache.EvalAbstract(c).get_value()[1]),
                                       prerequisites_of_calc={self._cache.ticket()})
        self.DeclareAbstractOutputPort("target_mask", lambda: AbstractValue.Make(empty_mask),
                                       lambda c, o: o.set_value(self._cache.EvalAbstract(c).get_value()[2]),
                                       prerequisites_of_calc={self._cache.ticket()})
        self.geometry = geometry
        self.params = params or ShelfSegmentationParams()

    def _segment(self, context, value):
        if not self.depth_port.HasValue(context):
            raise PerceptionError("ShelfSegmenter: connect the depth_image input (the shelf camera's, e.g. the "
                                  "station's front.depth_image)")
        cam = self.geometry.camera
        target = red_pixels(self.rgb_port.Eval(context).data) if self.rgb_port.HasValue(context) else \
            np.zeros((cam.height, cam.width), bool)
        masks, scene = segment_shelf(self.geometry, self.depth_port.Eval(context), self.params, target)
        value.set_value((masks, scene, target))
