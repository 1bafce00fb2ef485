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
  with the best score is the target when the score is >= `threshold`.
  `render_templates(...)` renders k views of an object alone in the scenario's camera.
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
from pydrake.systems.sensors import ImageRgba8U
from scipy.spatial.transform import Rotation

from ms_drake.errors import PerceptionError
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
    """One target image: rgb (h, w, 3) uint8 and the target's mask (h, w) bool in it."""

    rgb: np.ndarray
    mask: np.ndarray


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


def _hs_hist(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    hsv = cv2.cvtColor(_rgb_array(rgb), cv2.COLOR_RGB2HSV)
    hist = cv2.calcHist([hsv], [0, 1], mask.astype(np.uint8), [30, 32], [0, 180, 0, 256])
    return cv2.normalize(hist, hist, 1.0, 0.0, cv2.NORM_L1)


class TemplateMatcher:
    """Scores masks against k target templates (see the module doc)."""

    def __init__(self, templates: list[Template], threshold: float = 0.9, max_area_ratio: float = 1.5,
                 min_pixels: int = 20):
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

    def scores(self, rgb, masks: InstanceMasks) -> np.ndarray:
        out = np.zeros(len(masks))
        for k in range(len(masks)):
            area = masks.masks[k].sum()
            if area < self.min_pixels or area > self.max_area_ratio * self.max_area:
                continue
            h = _hs_hist(rgb, masks.masks[k])
            out[k] = max(max(cv2.compareHist(h, t, cv2.HISTCMP_CORREL) for t in self.hists), 0.0)
        return np.clip(out, 0.0, 1.0)

    def detect(self, rgb, masks: InstanceMasks) -> TargetEstimate:
        h, w = _rgb_array(rgb).shape[:2]
        if len(masks):
            s = self.scores(rgb, masks)
            k = int(np.argmax(s))
            if s[k] >= self.threshold:
                return TargetEstimate(True, masks.masks[k].copy(), float(s[k]), k)
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
        mask = labels == label
        if mask.any():
            ys, xs = np.nonzero(mask)
            sl = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
            out.append(Template(rgb[sl].copy(), mask[sl].copy()))
    return out


class TargetDetector(LeafSystem):
    """Finds the target among the instance masks (see the module doc for backends).

    Inputs ``rgb_image`` (ImageRgba8U) and ``masks`` (InstanceMasks); output ``target``
    (TargetEstimate). backend: color | template | learned; params: ColorParams (color); templates,
    threshold (t_r): template and learned; max_area_ratio (template); weights (learned).
    """

    def __init__(self, backend: str = "color", width: int = 640, height: int = 480,
                 params: ColorParams | None = None, templates: list[Template] | None = None,
                 threshold: float = 0.9, max_area_ratio: float = 1.5, weights=None):
        super().__init__()
        if backend not in BACKENDS:
            raise PerceptionError(f"TargetDetector backend {backend!r} unknown; choose one of {', '.join(BACKENDS)}")
        # Ports first.
        self.rgb_port = self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(ImageRgba8U(width, height)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
        self.target_port = self.DeclareAbstractOutputPort(
            "target", lambda: AbstractValue.Make(TargetEstimate(False, np.zeros((height, width), bool))),
            self._calc, prerequisites_of_calc={self.all_input_ports_ticket()})
        self.backend = backend
        self.params = params or ColorParams()
        self.matcher = TemplateMatcher(templates or [], threshold, max_area_ratio) if backend == "template" else None
        self.learned = LearnedMatcher(templates or [], weights, threshold) if backend == "learned" else None

    def detect(self, rgb, masks: InstanceMasks) -> TargetEstimate:
        if self.backend == "color":
            return detect_color(rgb, masks, self.params)
        if self.backend == "template":
            return self.matcher.detect(rgb, masks)
        return detect_learned(self.learned, rgb, masks)

    def _calc(self, context, output):
        if not self.rgb_port.HasValue(context):
            raise PerceptionError("TargetDetector: the rgb_image input is not connected")
        rgb = self.rgb_port.Eval(context)
        masks = self.masks_port.Eval(context) if self.masks_port.HasValue(context) else InstanceMasks.empty(
            rgb.height(), rgb.width())
        output.set_value(self.detect(rgb, masks))
