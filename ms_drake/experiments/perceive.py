"""`ms-drake perceive`: the perception stack on your own camera's images.

Input: a depth image of a bin seen from above (`.npy`, float metres; or a 16-bit `.png` in
millimetres, 0 = no return), optionally the colour image of the same camera and the target (a
registry object name, or its box size). Output, in a folder:
  masks.png       the instance masks over the depth image (the target outlined in red)
  masks.json      the masks as COCO (one image, RLE segmentations, scores)
  occupancy.png / occupancy.npy   the target's occupancy distribution (when the target is given)
  perceive.json   a summary: masks, the target's mask index and visibility, each stage's time

The depth goes through the stations' preprocessing (geometry.preprocess_depth: the sensor's
holes filled), then the segmenter (default "learned"), the target detector (with a colour image:
"template", views of the target object rendered here, its masks' size checked on the depth, or
"color" for a red target without a name; a target seen in no mask of its own gets one, as in the
search: perception.target_instance) and the learned occupancy (from the target's size). The camera: `--intrinsics FILE`, a
YAML or JSON mapping with width, height, fx, fy, cx, cy, and optionally `pose` ({xyz: [..],
rpy_deg: [..]}, the camera in the bin's frame: floor centre, z up; default 0.8 m above the floor
looking straight down) and `bin` ([x, y, z] inner size, default 0.50 x 0.40 x 0.12 m). Without
it the image must be 640 x 480, the stations' overhead camera. Images of another size are
resized to 640 x 480 for the learned models (masks and occupancy resized back).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from pycocotools import mask as mask_utils
from pydrake.math import RigidTransform, RollPitchYaw

from ms_drake.errors import MsDrakeError
from ms_drake.experiments.scene_images import colorize_masks
from ms_drake.geometry import PinholeCamera, Workspace, preprocess_depth
from ms_drake.objects import get_object
from ms_drake.perception.occupancy import OccupancyEstimator, TargetBox
from ms_drake.perception.segmentation import BACKENDS as SEGMENTERS
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import TargetDetector, render_templates
from ms_drake.perception.target_instance import target_instance
from ms_drake.scenario import load_scenario
from ms_drake.types import InstanceMasks

MODEL_SIZE = (640, 480)  # the learned models' image size (width, height)
DEPTH_RANGE = (0.05, 10.0)  # m: plausible depths of a camera over a bin
PERCEIVE_SEGMENTERS = tuple(s for s in SEGMENTERS if s != "ground_truth")


class PerceiveError(MsDrakeError, ValueError):
    """A user's image or camera file that the perception cannot read (names the file and the fix)."""


@dataclass
class Camera:
    camera: PinholeCamera
    workspace: Workspace


def load_depth(path) -> np.ndarray:
    """(H, W) float32 depth in metres (0 where there is no return) from `.npy` (metres) or a 16-bit
    `.png` (millimetres)."""
    path = Path(path)
    if not path.is_file():
        raise PerceiveError(f"{path}: no such file; give a depth image (.npy in metres or 16-bit .png in mm)")
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise PerceiveError(f"{path}: not a NumPy array file ({e}); save the depth with numpy.save") from None
        if not np.issubdtype(d.dtype, np.number):
            raise PerceiveError(f"{path}: the array holds {d.dtype}, not numbers; save float depths in metres")
        d = d.astype(np.float32)
        unit = "metres"
    elif path.suffix.lower() == ".png":
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise PerceiveError(f"{path}: not a readable PNG image")
        if d.dtype != np.uint16:
            raise PerceiveError(f"{path}: a {d.dtype} PNG; a depth PNG must be 16-bit, in millimetres (0 = no return)")
        d = d.astype(np.float32) / 1000.0
        unit = "millimetres"
    else:
        raise PerceiveError(f"{path}: unknown depth format {path.suffix!r}; give .npy (metres) or 16-bit .png (mm)")
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise PerceiveError(f"{path}: depth of shape {d.shape}; a depth image is (height, width) (one channel)")
    valid = np.isfinite(d) & (d > 0)
    if not valid.any():
        raise PerceiveError(f"{path}: no valid depth (every pixel is 0, negative or not finite)")
    med = float(np.median(d[valid]))
    if not DEPTH_RANGE[0] <= med <= DEPTH_RANGE[1]:
        hint = ("the values look like millimetres: divide by 1000 for .npy, or save a 16-bit PNG in mm"
                if unit == "metres" and med > DEPTH_RANGE[1] else
                f"the depth must be in {unit}")
        raise PerceiveError(f"{path}: median depth {med:.4g} {unit} is outside {DEPTH_RANGE[0]}-{DEPTH_RANGE[1]} m; "
                            f"{hint}")
    return np.where(valid, d, 0.0).astype(np.float32)


def _default_camera() -> Camera:
    s = load_scenario(None, "FloatingGripperBin")
    return Camera(PinholeCamera.from_config(s.cameras["overhead"]), Workspace.from_scenario(s))


def load_camera(path=None, shape: tuple[int, int] | None = None) -> Camera:
    """The camera of `--intrinsics FILE` (module doc), or the stations' overhead camera; shape: the
    depth image's (H, W), checked against it."""
    if path is None:
        cam = _default_camera()
        if shape is not None and shape != (cam.camera.height, cam.camera.width):
            raise PerceiveError(f"the depth image is {shape[1]} x {shape[0]} but no --intrinsics was given (the default "
                                f"is the stations' {cam.camera.width} x {cam.camera.height} overhead camera); give "
                                "--intrinsics FILE with width, height, fx, fy, cx, cy")
        return cam
    path = Path(path)
    if not path.is_file():
        raise PerceiveError(f"{path}: no such intrinsics file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise PerceiveError(f"{path}: not YAML or JSON ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise PerceiveError(f"{path}: expected a mapping with width, height, fx, fy, cx, cy")
    need = ("width", "height", "fx", "fy", "cx", "cy")
    missing = [k for k in need if k not in data]
    unknown = sorted(set(data) - set(need) - {"pose", "bin"})
    if missing or unknown:
        raise PerceiveError(f"{path}: " + "; ".join(
            ([f"missing {', '.join(missing)}"] if missing else []) + ([f"unknown key(s) {', '.join(unknown)}"] if unknown
                                                                      else []))
            + f" (keys: {', '.join(need)}, optional pose, bin)")
    try:
        w, h = int(data["width"]), int(data["height"])
        fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
        pose = data.get("pose") or {"xyz": [0.0, 0.0, 0.8], "rpy_deg": [180.0, 0.0, 0.0]}
        X = RigidTransform(RollPitchYaw(np.radians(np.asarray(pose.get("rpy_deg", [180.0, 0.0, 0.0]), float))),
                           np.asarray(pose.get("xyz", [0.0, 0.0, 0.8]), float))
        size = np.asarray(data.get("bin", [0.50, 0.40, 0.12]), float)
    except (TypeError, ValueError) as e:
        raise PerceiveError(f"{path}: a value is not a number ({e})") from None
    if min(w, h) < 16 or min(fx, fy) <= 0 or size.shape != (3,) or np.any(size <= 0):
        raise PerceiveError(f"{path}: width/height >= 16 px, fx/fy > 0 and bin = [x, y, z] > 0 m are required")
    if shape is not None and shape != (h, w):
        raise PerceiveError(f"the depth image is {shape[1]} x {shape[0]} but {path} says {w} x {h}")
    # Drake's camera convention (+z forward, +x right, +y down), as the stations' CameraConfig X_PB.
    return Camera(PinholeCamera(w, h, fx, fy, cx, cy, X),
                  Workspace((0.0, 0.0), (float(size[0]), float(size[1])), 0.0, float(size[2])))


def _resize(a: np.ndarray, size, nearest: bool = True) -> np.ndarray:
    return cv2.resize(a, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)


def _target_size(target: str | None, target_size) -> TargetBox | None:
    if target_size:
        L, W, T = (float(v) for v in target_size)
        if min(L, W, T) <= 0:
            raise PerceiveError(f"--target-size {target_size}: three positive sizes in metres")
        return TargetBox(*sorted((L, W, T), reverse=True))
    if target:
        try:
            get_object(target)
        except Exception as e:  # registry lookups name the known sets
            raise PerceiveError(f"--target {target}: {e}") from None
        return TargetBox.from_object(target)
    return None


def perceive(depth: np.ndarray, camera: Camera | None = None, segmenter: str = "learned", rgb: np.ndarray | None = None,
             target: str | None = None, target_size=None, device: str = "cpu") -> dict:
    """The perception of one image: {"masks": InstanceMasks, "target": TargetEstimate | None,
    "occupancy": (H, W) | None, "ms": {stage: CPU milliseconds of the inference, models loaded and
    run once}} at
    the depth image's size. device: where the learned networks (segmenter, occupancy) run (cpu |
    cuda | auto)."""
    if segmenter not in PERCEIVE_SEGMENTERS:
        raise PerceiveError(f"segmenter {segmenter!r} unknown; choose one of {', '.join(PERCEIVE_SEGMENTERS)}")
    camera = camera or load_camera(None, depth.shape)
    h, w = depth.shape
    box = _target_size(target, target_size)
    ms = {}
    t = time.process_time()
    filled = preprocess_depth(depth)
    model_depth = filled if (w, h) == MODEL_SIZE else _resize(filled, MODEL_SIZE)
    ms["preprocess"] = 1000 * (time.process_time() - t)
    seg = (Segmenter("learned", device=device) if segmenter == "learned" else
           Segmenter(segmenter, camera=camera.camera, workspace=camera.workspace))  # (loads the network)
    if segmenter == "learned":
        seg.segment(depth=model_depth)  # torch's first call allocates; a camera's stream pays it once
    t = time.process_time()
    if segmenter == "learned":
        masks = seg.segment(depth=model_depth)
        if (w, h) != MODEL_SIZE:
            masks = InstanceMasks(np.stack([_resize(m.astype(np.uint8), (w, h)) > 0 for m in masks.masks])
                                  if len(masks) else np.zeros((0, h, w), bool), masks.ids, masks.scores)
    else:
        masks = seg.segment(depth=filled)
    ms["segmentation"] = 1000 * (time.process_time() - t)
    found = None
    if rgb is not None:
        if rgb.shape[:2] != (h, w):
            raise PerceiveError(f"the colour image is {rgb.shape[1]} x {rgb.shape[0]}, the depth {w} x {h}: give both "
                                "from the same (registered) camera")
        templates = render_templates(load_scenario(None, "BinHeap15"), target, 5) if target else None
        det = TargetDetector("template" if target else "color", width=w, height=h, templates=templates)
        t = time.process_time()
        found = det.detect(rgb, masks, depth, camera.camera)  # depth: the template's size check
        masks, found = target_instance(masks, found)  # a target seen in no mask of its own gets one
        ms["target_detection"] = 1000 * (time.process_time() - t)
    occupancy = None
    if box is not None:
        mask = found.mask if found is not None and found.visible else np.zeros((h, w), bool)
        est = OccupancyEstimator("learned", target_size=box, device=device)
        est.backend.estimate(model_depth, np.zeros(model_depth.shape, bool))  # (loads the network)
        t = time.process_time()
        occ = est.backend.estimate(model_depth, mask if (w, h) == MODEL_SIZE else _resize(mask.astype(np.uint8),
                                                                                           MODEL_SIZE) > 0)
        if (w, h) != MODEL_SIZE:
            occ = _resize(occ.astype(np.float32), (w, h), nearest=False)
            occ = occ / occ.sum() if occ.sum() > 0 else occ
        occupancy = occ
        ms["occupancy"] = 1000 * (time.process_time() - t)
    return {"masks": masks, "target": found, "occupancy": occupancy, "ms": ms}


def coco_json(masks: InstanceMasks, file_name: str) -> dict:
    """One image's masks as a COCO result file (RLE segmentations)."""
    h, w = masks.masks.shape[1:]
    anns = []
    for k in range(len(masks)):
        rle = mask_utils.encode(np.asfortranarray(masks.masks[k].astype(np.uint8)))
        anns.append({"id": k + 1, "image_id": 1, "category_id": 1, "iscrowd": 0,
                     "segmentation": {"size": [int(h), int(w)], "counts": rle["counts"].decode()},
                     "area": int(mask_utils.area(rle)), "bbox": [float(v) for v in mask_utils.toBbox(rle)],
                     "score": float(masks.scores[k]) if len(masks.scores) > k else 1.0})
    return {"images": [{"id": 1, "file_name": file_name, "width": int(w), "height": int(h)}],
            "annotations": anns, "categories": [{"id": 1, "name": "object"}]}


def _depth_picture(depth: np.ndarray) -> np.ndarray:
    valid = depth > 0
    lo, hi = (np.percentile(depth[valid], [1, 99]) if valid.any() else (0.0, 1.0))
    g = np.clip((hi - depth) / max(hi - lo, 1e-6), 0, 1)
    return np.repeat((255 * np.where(valid, g, 0))[..., None], 3, axis=2).astype(np.uint8)


def write_perception(out, depth_path, result: dict, depth: np.ndarray) -> dict:
    """masks.png, masks.json, occupancy.png / .npy, perceive.json in `out`; returns {name: path}."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    masks, found, occ = result["masks"], result["target"], result["occupancy"]
    pic = colorize_masks(masks, _depth_picture(depth), alpha=0.5)
    if found is not None and found.visible:
        cnts, _ = cv2.findContours(found.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(pic, cnts, -1, (255, 0, 0), 3)
    written = {"masks_png": out / "masks.png", "masks_json": out / "masks.json", "summary": out / "perceive.json"}
    cv2.imwrite(str(written["masks_png"]), pic[..., ::-1])
    written["masks_json"].write_text(json.dumps(coco_json(masks, Path(depth_path).name)))
    if occ is not None:
        written["occupancy_npy"], written["occupancy_png"] = out / "occupancy.npy", out / "occupancy.png"
        np.save(written["occupancy_npy"], occ.astype(np.float32))
        d = occ / occ.max() if occ.max() > 0 else occ
        heat = cv2.applyColorMap((255 * d).astype(np.uint8), cv2.COLORMAP_JET)
        a = (0.75 * np.sqrt(d))[..., None]
        cv2.imwrite(str(written["occupancy_png"]), ((1 - a) * _depth_picture(depth)[..., ::-1] + a * heat).astype(np.uint8))
    summary = {"depth": str(depth_path), "masks": len(masks), "ids": list(masks.ids),
               "target": None if found is None else {"visible": bool(found.visible),
                                                     "mask_index": int(found.instance_index),
                                                     "confidence": float(found.confidence)},
               "occupancy": occ is not None, "ms": {k: round(v, 1) for k, v in result["ms"].items()}}
    written["summary"].write_text(json.dumps(summary, indent=1))
    return {k: str(v) for k, v in written.items()}


__all__ = ["PERCEIVE_SEGMENTERS", "PerceiveError", "coco_json", "load_camera", "load_depth", "perceive",
           "write_perception"]
