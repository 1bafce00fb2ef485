"""Target recognition (Ch. 7.3.1, App. C.2 lines 1969-1984; Ch. 8.4.2): the `TargetDetector` LeafSystem.

Backends:

- ``color``: HSV thresholding of a red target (the X-Ray experiments' detector; in simulation
  MakeStation(..., target_index=k) draws object k in ms_drake.objects.TARGET_RGBA). Red pixels
  (hue <= `hue_low` or >= `hue_high` on OpenCV's 0-180 scale, saturation >= `min_saturation`,
  value >= `min_value`) are cleaned by a 3x3 opening. The target is the instance mask holding the
  most red pixels, provided they are at least `min_fraction` of the mask; its confidence is that
  fraction. Red pixels that no mask explains (>= `min_pixels`) are still reported as a visible
  target with instance_index -1.
- ``template``: appearance matching of every mask against k target images, threshold
  t_r = 0.9 as in the reference. The reference scores pairs with a Siamese network on ImageNet
  ResNet-50 features; pretrained weights cannot be downloaded here, so the score is a classical,
  rotation- and occlusion-tolerant one (our choice): the correlation of the masked hue-saturation
  histograms (cv2.compareHist, HISTCMP_CORREL, clipped to [0, 1]), maximised over the k
  templates, and set to 0 for a mask larger than `max_area_ratio` x the largest template mask
  (an occluded target never looks larger than the whole target from the same camera). The mask
  with the best score is the target when the score is >= `threshold` (refined by (1)-(4) below).
  Geometric check (our addition; when the templates carry the target's seen surface points and
  the detector gets the depth image and the camera's intrinsics): colour cannot tell the target
  from another object of its colour, its size can. A mask that reaches the threshold is set to 0
  (a) when one of its 3D surface extents (`surface_extents`: along the principal axes of its
  depth points, largest first) exceeds the largest the target's views show by more than 10 % +
  1.5 cm (no visible part of the target is larger than the target), or (b) when nothing hides
  it (`occluded_fraction` <= 2 %: no pixel around it nearer by > 5 mm, not cut by the image
  border), so that it shows a whole object, and its largest or middle extent falls short of the
  smallest the target's views show by more than 10 % + 5 mm (a whole object smaller than any view
  of the target is another object). Limits: (b) wrongly rejects a target hidden by something
  less than 5 mm above it (e.g. a thin object lying flat on it) and seen too small; it cannot tell
  same-coloured objects of one size, or two copies of one object.
  Merged, spilt and split masks (our addition, `parts=True` and `fragments=True`): a learned
  segmenter working on depth rarely gives the thin target a mask of its own when it lies on or
  against another object. The target's colours are the hue-saturation bins that hold `part_mass`
  = 99 % of the templates' pixels; a mask's target-coloured part is its pixels of those colours
  after a 3x3 opening, the largest connected piece. (1) A mask whose histogram falls below t_r
  (it shows other colours too: the target merged with a neighbour) is scored again by its part,
  which takes the mask's place in every check (area, histogram, size) except (b): its border
  with the rest of its mask is one the depth did not tell apart, so it is never taken as seen
  whole. A target found so has the part as its mask, and the mask's instance only when the part
  is at least half of it (else -1: seen, inside a mask that is mostly another object). (2) A
  mask of the target's colours is judged whole (an object of its colour is not cut down to the
  target's size), but (a) measures its part: a mask spilling over the target's edge onto a
  neighbour takes the neighbour's depth into its extents. (3) With the geometric check, the best
  region (whole masks before parts, then by score) is joined by the other matching regions that
  touch it (within 2 px) while the union passes the check, and the estimate's mask is the union:
  the histogram of any pure piece of a split target correlates near 1, so the best score does
  not tell the main piece from a sliver; the instance is the piece showing most of the target
  (same half-of-its-mask rule). (4) When no mask matches, the target-coloured pixels that no
  mask holds (their largest piece, scored like a part, (b) included) are a target the segmenter
  left out: visible, instance -1. Limits: two touching objects of the target's colour that
  together fit its size are taken for one target.
  `render_templates(...)` renders k views of an object alone in the scenario's camera, with the
  points of each view's depth.
- ``learned``: the siamese network of ms_drake.perception.matcher_net (App. C.2's architecture
  on a small encoder trained from scratch on rendered heaps), scoring every mask against the k
  template views (maximum over the views); the best mask is the target when its score is >=
  t_r = 0.9. `weights`: the matcher weights file (default models/weights/matcher.pt).

Output: TargetEstimate(visible, mask (H, W) bool, confidence, instance_index).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U
from scipy.spatial.transform import Rotation

from ms_drake.errors import PerceptionError
from ms_drake.geometry import PinholeCamera
from ms_drake.perception.masks import object_labels
from ms_drake.perception.matcher_net import LearnedMatcher
from ms_drake.station.station import MakeStation, get_plant, station_objects
from ms_drake.types import InstanceMasks, TargetEstimate

BACKENDS = ("color", "template", "learned")


@dataclass(frozen=True)
class ColorParams:
    hue_low: int = 10
    hue_high: int = 170
    min_saturation: int = 100
    min_value: int = 40
    min_fraction: float = 0.3
    min_pixels: int = 20


@dataclass(frozen=True)
class Template:
    """One target image: rgb (h, w, 3) uint8 and the target's mask (h, w) bool in it; points
    (optional): the target's seen surface in that view, (n, 3) float32 camera-frame points [m]
    (from the view's depth image), which tell the target's metric size."""

    rgb: np.ndarray
    mask: np.ndarray
    points: np.ndarray | None = None

    @staticmethod
    def from_view(rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray | None = None, camera=None) -> Template:
        """The template of a full view: its rgb and mask cropped to the mask's bounding box, and
        with depth (H, W) [m] and the camera's intrinsics (fx, fy, cx, cy attributes) its points."""
        ys, xs = np.nonzero(mask)
        sl = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
        pts = None
        if depth is not None and camera is not None:
            pts = mask_points(depth, mask, camera)
        return Template(_rgb_array(rgb)[sl].copy(), np.asarray(mask, bool)[sl].copy(), pts)


def mask_points(depth: np.ndarray, mask: np.ndarray, camera) -> np.ndarray:
    """(n, 3) float32 camera-frame points of the mask's pixels with a valid depth (finite, > 0)."""
    d = np.asarray(depth.data if hasattr(depth, "data") else depth, np.float32)
    d = d.reshape(d.shape[0], d.shape[1])
    v, u = np.nonzero(np.asarray(mask, bool) & np.isfinite(d) & (d > 0))
    z = d[v, u]
    return np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1).astype(np.float32)


def _rgb_array(rgb) -> np.ndarray:
    a = np.asarray(rgb.data if hasattr(rgb, "data") else rgb)
    return np.ascontiguousarray(a[..., :3]).astype(np.uint8)


def red_pixels(rgb: np.ndarray, params: ColorParams = ColorParams()) -> np.ndarray:
    """(H, W) bool: red pixels of an RGB image (HSV threshold + 3x3 opening)."""
    hsv = cv2.cvtColor(_rgb_array(rgb), cv2.COLOR_RGB2HSV)
    h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    red = ((h <= params.hue_low) | (h >= params.hue_high)) & (s >= params.min_saturation) & (v >= params.min_value)
    red = cv2.morphologyEx(red.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    return red.astype(bool)


def detect_color(rgb, masks: InstanceMasks, params: ColorParams = ColorParams()) -> TargetEstimate:
    """The colour backend as a function (see the module doc)."""
    red = red_pixels(rgb, params)
    if len(masks):
        counts = (masks.masks & red[None]).reshape(len(masks), -1).sum(axis=1)
        frac = counts / np.maximum(masks.areas(), 1)
        ok = (frac >= params.min_fraction) & (counts > 0)
        if ok.any():
            k = int(np.argmax(np.where(ok, counts, -1)))
            return TargetEstimate(True, masks.masks[k].copy(), float(frac[k]), k)
    if red.sum() >= params.min_pixels:
        return TargetEstimate(True, red, 1.0, -1)
    return TargetEstimate(False, np.zeros(red.shape, bool), 0.0, -1)


_H_BINS, _S_BINS = 30, 32  # the hue-saturation histogram's bins


def _hsv(rgb) -> np.ndarray:
    return cv2.cvtColor(_rgb_array(rgb), cv2.COLOR_RGB2HSV)


def _box(mask: np.ndarray, pad: int = 0):
    """(row slice, column slice) of the mask's bounding box grown by `pad` pixels, or None if empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return (slice(max(rows[0] - pad, 0), rows[-1] + 1 + pad), slice(max(cols[0] - pad, 0), cols[-1] + 1 + pad))


def _hs_hist(rgb: np.ndarray, mask: np.ndarray, hsv: np.ndarray | None = None) -> np.ndarray:
    """The mask's hue-saturation histogram (L1-normalised); hsv: the image in HSV, if at hand.
    Computed on the mask's bounding box: the same histogram, at a box's cost."""
    hsv = _hsv(rgb) if hsv is None else hsv
    box = _box(mask)
    if box is None:
        box = (slice(0, 0), slice(0, 0))
    hist = cv2.calcHist([np.ascontiguousarray(hsv[box])], [0, 1], np.ascontiguousarray(mask[box]).astype(np.uint8),
                        [_H_BINS, _S_BINS], [0, 180, 0, 256])
    return cv2.normalize(hist, hist, 1.0, 0.0, cv2.NORM_L1)


@dataclass(frozen=True)
class GeometryParams:
    """The template backend's geometric consistency check (module doc); lengths in metres.

    extent_tolerance, extent_margin: a mask is rejected when one of its sorted 3D extents exceeds
    the target's by more than this factor plus margin. whole_occluded: a mask whose boundary has
    at most this fraction of occluded pixels (a nearer neighbour, or the image border) is seen
    whole; whole_tolerance, whole_margin: such a mask is rejected when its largest or middle
    extent falls short of the smallest of the target's views by more than this fraction plus
    margin. occlusion_step: the depth step that makes a neighbour an occluder; ring: the width of
    the ring of pixels around the mask that is examined; min_points: masks with fewer valid depth
    pixels are not checked."""

    extent_tolerance: float = 0.1
    extent_margin: float = 0.015
    whole_occluded: float = 0.02
    whole_tolerance: float = 0.1
    whole_margin: float = 0.005
    occlusion_step: float = 0.005
    ring: int = 3
    min_points: int = 20


_TRIM_PERCENT = 1.0  # percentile trimmed from each end of the extents (depth noise, stray pixels)


def surface_extents(points: np.ndarray) -> np.ndarray:
    """(3,) the extents [m] of a set of 3D points along its principal axes, largest first (the
    1st-99th percentile spread along each axis)."""
    p = np.asarray(points, np.float64)
    if len(p) < 3:
        return np.zeros(3)
    c = p - p.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)
    lo, hi = np.percentile(c @ vecs, [_TRIM_PERCENT, 100.0 - _TRIM_PERCENT], axis=0)
    return np.sort(hi - lo)[::-1]


def occluded_fraction(depth: np.ndarray, mask: np.ndarray, step: float = 0.005, ring: int = 3) -> float:
    """The fraction of a mask's boundary that something hides: of the pixels in a `ring`-px ring
    around the mask with a valid depth, those nearer than the mask's nearest pixel around them by
    more than `step` [m]; the mask's pixels on the image border (cut by the frame) count as hidden
    ring pixels, `ring` each."""
    d = np.asarray(depth, np.float32)
    mask = np.asarray(mask, bool)
    valid = np.isfinite(d) & (d > 0)
    k = 2 * ring + 1
    around = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool) & ~mask
    far = np.float32(1e3)
    near = cv2.erode(np.where(mask & valid, d, far).astype(np.float32), np.ones((2 * k - 1, 2 * k - 1), np.uint8))
    seen = around & valid & (near < far)
    hidden = seen & (d < near - step)
    border = ring * int(mask[0].sum() + mask[-1].sum() + mask[1:-1, 0].sum() + mask[1:-1, -1].sum())
    n = int(seen.sum()) + border
    return float((int(hidden.sum()) + border) / n) if n else 0.0


class TemplateMatcher:
    """Scores masks against k target templates (see the module doc)."""

    def __init__(self, templates: list[Template], threshold: float = 0.9, max_area_ratio: float = 1.5,
                 min_pixels: int = 20, geometry: GeometryParams = GeometryParams(), parts: bool = True,
                 part_mass: float = 0.99, fragments: bool = True):
        if not templates:
            raise PerceptionError("TargetDetector(backend='template') needs at least one template image "
                                  "(render_templates(scenario, object_name, k))")
        for i, t in enumerate(templates):
            if t.mask.shape != t.rgb.shape[:2] or not t.mask.any():
                raise PerceptionError(f"template {i}: its mask must be a non-empty (h, w) array matching its image")
        if not 0.0 <= threshold <= 1.0:
            raise PerceptionError(f"template threshold t_r={threshold} must lie in [0, 1] (reference: 0.9)")
        self.hists = [_hs_hist(t.rgb, t.mask) for t in templates]
        self.max_area = max(int(t.mask.sum()) for t in templates)
        self.threshold, self.max_area_ratio, self.min_pixels = float(threshold), float(max_area_ratio), int(min_pixels)
        self.geometry = geometry
        # The target's colours: the hue-saturation bins holding `part_mass` of the templates' pixels.
        total = np.sum(self.hists, axis=0)
        order = np.argsort(total, axis=None)[::-1]
        n = int(np.searchsorted(np.cumsum(total.ravel()[order]), part_mass * total.sum())) + 1
        self.colour_bins = np.zeros(total.shape, bool)
        self.colour_bins.flat[order[:n]] = True
        self.parts, self.fragments = bool(parts), bool(fragments)
        # The target's size from the views with points: the largest extents any view shows (what
        # no part of it can exceed) and the smallest a whole view shows.
        ext = [surface_extents(t.points) for t in templates
               if t.points is not None and len(t.points) >= geometry.min_points]
        self.extent_max = np.max(ext, axis=0) if ext else None
        self.extent_min = np.min(ext, axis=0) if ext else None

    def geometry_ok(self, mask: np.ndarray, depth: np.ndarray, camera, surface: np.ndarray | None = None,
                    may_be_whole: bool = True) -> bool:
        """Whether the mask's 3D surface (from depth and the camera's intrinsics) can be the
        target's: no extent larger than the target's, and, if seen whole, not smaller than any
        whole view of it. surface (optional, within the mask): the pixels whose extents are held
        against the target's largest (the mask's target-coloured part); the mask itself is what
        is seen whole or not, and held against the smallest (not when may_be_whole is False). True
        when the templates carry no points or the mask too few."""
        g = self.geometry
        if self.extent_max is None:
            return True
        pts = mask_points(depth, mask, camera)
        if len(pts) < g.min_points:
            return True
        e = e_large = surface_extents(pts)
        if surface is not None:
            sp = mask_points(depth, surface, camera)
            if len(sp) >= g.min_points:
                e_large = surface_extents(sp)
        if np.any(e_large > (1.0 + g.extent_tolerance) * self.extent_max + g.extent_margin):
            return False
        if may_be_whole and occluded_fraction(depth, mask, g.occlusion_step, g.ring) <= g.whole_occluded:
            return not np.any(e[:2] < (1.0 - g.whole_tolerance) * self.extent_min[:2] - g.whole_margin)
        return True

    def target_colours(self, rgb, hsv: np.ndarray | None = None) -> np.ndarray:
        """(H, W) bool: pixels whose hue-saturation bin is one of the target's colours."""
        hsv = _hsv(rgb) if hsv is None else hsv
        h = np.minimum(hsv[..., 0].astype(np.int32) * _H_BINS // 180, _H_BINS - 1)
        s = hsv[..., 1].astype(np.int32) * _S_BINS // 256
        return self.colour_bins[h, s]

    def target_part(self, mask: np.ndarray, colours: np.ndarray) -> np.ndarray:
        """The mask's target-coloured part: its pixels of the target's colours (`colours`, from
        target_colours), after a 3x3 opening, the largest 4-connected piece (all False if none)."""
        mask = np.asarray(mask, bool)
        out = np.zeros(mask.shape, bool)
        # (within the mask's bounding box and 2 px around it: the same result, at a box's cost)
        box = _box(mask, 2)
        if box is None:
            return out
        part = cv2.morphologyEx((mask[box] & colours[box]).astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        n, lab, stats, _ = cv2.connectedComponentsWithStats(part, connectivity=4)
        if n > 1:
            out[box] = lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        return out

    def colour_score(self, rgb, mask: np.ndarray, hsv: np.ndarray | None = None) -> float:
        """The region's hue-saturation histogram correlation, best over the templates, in [0, 1]."""
        h = _hs_hist(rgb, mask, hsv)
        return min(max(max(cv2.compareHist(h, t, cv2.HISTCMP_CORREL) for t in self.hists), 0.0), 1.0)

    def _score(self, rgb, mask: np.ndarray, d, camera, colour: float | None = None, surface=None,
               may_be_whole: bool = True, hsv: np.ndarray | None = None) -> float:
        """One region's score: 0 outside the area limits or when it (or `surface`, its pixels of
        the target's surface) fails the geometric check. hsv: the image in HSV, if at hand."""
        area = int(mask.sum())
        if area < self.min_pixels or area > self.max_area_ratio * self.max_area:
            return 0.0
        s = self.colour_score(rgb, mask, hsv) if colour is None else colour
        if s >= self.threshold and d is not None and not self.geometry_ok(mask, d, camera, surface, may_be_whole):
            return 0.0
        return s

    def regions(self, rgb, masks: InstanceMasks, depth=None, camera=None) -> tuple[np.ndarray, list, np.ndarray]:
        """Each mask's score, the region it was scored on and whether that is a part: the mask
        itself, or, for a mask whose colours are not the target's (histogram below t_r) when `parts`
        is on, its target-coloured part (module doc). With a depth image (H, W) [m] of the same
        camera and its intrinsics (fx, fy, cx, cy), a region that fails the geometric check scores
        0; with `parts` on, a whole mask's check measures its target-coloured part (the pixels of
        a neighbour that the mask spills onto are not the target's surface)."""
        d = self._depth(depth) if camera is not None else None
        out, regions, is_part = np.zeros(len(masks)), [None] * len(masks), np.zeros(len(masks), bool)
        colours = None
        hsv = _hsv(rgb)  # the image in HSV once, for every region's histogram
        for k in range(len(masks)):
            m = masks.masks[k]
            regions[k] = m
            if m.sum() < self.min_pixels:
                continue
            c = self.colour_score(rgb, m, hsv)
            if not self.parts:
                out[k] = self._score(rgb, m, d, camera, c)
                continue
            if colours is None:
                colours = self.target_colours(rgb, hsv)
            part = self.target_part(m, colours)
            if c >= self.threshold:
                # The target's colours: judged whole (another object of its colour is not cut down),
                # its size measured on its target-coloured part.
                out[k] = self._score(rgb, m, d, camera, c, part if part.sum() >= self.min_pixels else None)
                continue
            if part.sum() >= self.min_pixels:
                # Never seen whole: the depth did not separate it from the rest of its mask.
                s = self._score(rgb, part, d, camera, may_be_whole=False, hsv=hsv)
                if s >= self.threshold:
                    out[k], regions[k], is_part[k] = s, part, True
        return out, regions, is_part

    def scores(self, rgb, masks: InstanceMasks, depth=None, camera=None) -> np.ndarray:
        """Each mask's score (see `regions`)."""
        return self.regions(rgb, masks, depth, camera)[0]

    def _depth(self, depth):
        if depth is None:
            return None
        d = np.asarray(depth.data if hasattr(depth, "data") else depth, np.float32)
        return d.reshape(d.shape[0], d.shape[1])

    def detect(self, rgb, masks: InstanceMasks, depth=None, camera=None) -> TargetEstimate:
        h, w = _rgb_array(rgb).shape[:2]
        if len(masks):
            s, regions, is_part = self.regions(rgb, masks, depth, camera)
            # Whole masks first (the segmenter agrees that they are one object), by score.
            ok = sorted((int(i) for i in np.flatnonzero(s >= self.threshold)),
                        key=lambda i: (bool(is_part[i]), -s[i], i))
            if ok:
                k = ok[0]
                target, pieces = regions[k].copy(), [k]
                d = self._depth(depth) if camera is not None else None
                if self.fragments and d is not None and self.extent_max is not None:
                    # Other matching masks touching it that keep the whole within the target's size
                    # are pieces of the same target (a segmenter that split it).
                    near = cv2.dilate(target.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
                    for j in ok[1:]:
                        if not (regions[j] & near).any():
                            continue
                        union = target | regions[j]
                        if union.sum() <= self.max_area_ratio * self.max_area and self.geometry_ok(union, d, camera):
                            target, pieces = union, pieces + [j]
                            near = cv2.dilate(target.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
                # The instance: the piece showing most of the target, if the target is most of its mask.
                i = max(pieces, key=lambda j: int(regions[j].sum()))
                index = i if not is_part[i] or 2 * int(regions[i].sum()) >= int(masks.masks[i].sum()) else -1
                return TargetEstimate(True, target, float(s[k]), index)
        if self.parts:
            # The target's colours where no mask is: a target the segmenter left out.
            free = self.target_part(~masks.masks.any(axis=0) if len(masks) else np.ones((h, w), bool),
                                    self.target_colours(rgb))
            if free.sum() >= self.min_pixels:
                d = self._depth(depth) if camera is not None else None
                s = self._score(rgb, free, d, camera)
                if s >= self.threshold:
                    return TargetEstimate(True, free, float(s), -1)
        return TargetEstimate(False, np.zeros((h, w), bool), 0.0, -1)


def detect_learned(matcher: LearnedMatcher, rgb, masks: InstanceMasks) -> TargetEstimate:
    """The learned backend as a function: the best-scoring mask if its score is >= t_r."""
    img = _rgb_array(rgb)
    if len(masks):
        s = matcher.scores(img, masks)
        k = int(np.argmax(s))
        if s[k] >= matcher.threshold:
            return TargetEstimate(True, masks.masks[k].copy(), float(s[k]), k)
    return TargetEstimate(False, np.zeros(img.shape[:2], bool), 0.0, -1)


def render_templates(scenario, object_name: str, k: int = 5, seed: int = 0, red: bool = True,
                     camera: str | None = None) -> list[Template]:
    """k views of `object_name` (full registry name) alone in the scenario's bin, each in a random
    orientation (seeded) at a random spot near the bin centre, rendered by the scenario's camera.
    red: draw it in the target colour (as MakeStation(target_index=...) does)."""

    if k < 1:
        raise PerceptionError(f"render_templates: k={k}; ask for at least one view")
    s = copy.deepcopy(scenario)
    s.objects.names = [object_name]
    s.objects.count = 1
    s.robot.name = ""
    s.robot.grippers = []
    cam = camera or next(iter(s.cameras), None)
    if cam is None or cam not in s.cameras:
        raise PerceptionError(f"render_templates: scenario has no camera {camera!r}")
    intrinsics = PinholeCamera.from_config(s.cameras[cam])
    station = MakeStation(s, target_index=0 if red else -1)
    ctx = station.CreateDefaultContext()
    plant = get_plant(station)
    pc = plant.GetMyMutableContextFromRoot(ctx)
    (obj,) = station_objects(plant)
    label = next(lbl for lbl, name in object_labels(plant).items() if name == obj.model_name)
    body = plant.get_body(obj.body_index)
    rng = np.random.default_rng([seed, 4241])
    center = np.asarray(s.environment.position, float)
    out = []
    for _ in range(k):
        R = RotationMatrix(Rotation.random(random_state=rng).as_matrix())
        p = center + np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.1])
        plant.SetFreeBodyPose(pc, body, RigidTransform(R, p))
        rgb = _rgb_array(station.GetOutputPort(f"{cam}.rgb_image").Eval(ctx))
        labels = np.array(station.GetOutputPort(f"{cam}.label_image").Eval(ctx).data)[:, :, 0]
        depth = np.array(station.GetOutputPort(f"{cam}.depth_image").Eval(ctx).data)[:, :, 0]
        mask = labels == label
        if mask.any():
            out.append(Template.from_view(rgb, mask, depth, intrinsics))
    return out


class TargetDetector(LeafSystem):
    """Finds the target among the instance masks (see the module doc for backends).

    Inputs ``rgb_image`` (ImageRgba8U), ``masks`` (InstanceMasks) and, optional, ``depth_image``
    (ImageDepth32F, metres, the same camera); output ``target`` (TargetEstimate). backend: color |
    template | learned; params: ColorParams (color); templates, threshold (t_r): template and
    learned; max_area_ratio, geometry (GeometryParams) and camera (the intrinsics, fx, fy, cx, cy
    attributes, e.g. a PinholeCamera): template, whose geometric check runs when the depth input
    is connected and camera is given; weights and device (cpu | cuda | auto, where the network runs):
    learned.
    """

    def __init__(self, backend: str = "color", width: int = 640, height: int = 480,
                 params: ColorParams | None = None, templates: list[Template] | None = None,
                 threshold: float = 0.9, max_area_ratio: float = 1.5, weights=None, camera=None,
                 geometry: GeometryParams | None = None, device="cpu"):
        super().__init__()
        if backend not in BACKENDS:
            raise PerceptionError(f"TargetDetector backend {backend!r} unknown; choose one of {', '.join(BACKENDS)}")
        # Ports first.
        self.rgb_port = self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(ImageRgba8U(width, height)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(width, height)))
        self.target_port = self.DeclareAbstractOutputPort(
            "target", lambda: AbstractValue.Make(TargetEstimate(False, np.zeros((height, width), bool))),
            self._calc, prerequisites_of_calc={self.all_input_ports_ticket()})
        self.backend = backend
        self.camera = camera
        self.params = params or ColorParams()
        self.matcher = TemplateMatcher(templates or [], threshold, max_area_ratio,
                                       geometry=geometry or GeometryParams()) if backend == "template" else None
        self.learned = LearnedMatcher(templates or [], weights, threshold, device=device) if backend == "learned" \
            else None

    def detect(self, rgb, masks: InstanceMasks, depth=None, camera=None) -> TargetEstimate:
        """depth (H, W) [m] and camera (default: the constructor's): the template backend's
        geometric check; the other backends ignore them."""
        if self.backend == "color":
            return detect_color(rgb, masks, self.params)
        if self.backend == "template":
            return self.matcher.detect(rgb, masks, depth, camera if camera is not None else self.camera)
        return detect_learned(self.learned, rgb, masks)

    def _calc(self, context, output):
        if not self.rgb_port.HasValue(context):
            raise PerceptionError("TargetDetector: the rgb_image input is not connected")
        rgb = self.rgb_port.Eval(context)
        masks = self.masks_port.Eval(context) if self.masks_port.HasValue(context) else InstanceMasks.empty(
            rgb.height(), rgb.width())
        depth = self.depth_port.Eval(context) if self.depth_port.HasValue(context) else None
        output.set_value(self.detect(rgb, masks, depth))
