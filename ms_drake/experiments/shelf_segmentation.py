"""How well the ShelfSegmenter recovers a shelf scene from the front camera's depth image.

`bench_shelf_segmentation(...)` (`ms-drake bench shelf-segmentation`): for the scenes of Table 9.1
(generate_shelf_scene(seed, n), the target hidden), a Drake render (depth + label image) and the
segmentation of its depth image. Per scene: the occluders the camera sees (at least `min_pixels`
label pixels), the instances found, those matched to one occluder (mask IoU >= 0.5), and for each
match the estimated object against the true one: kind, centre and size errors and the IoU of the
footprints (seen from above). Over all scenes: COCO mask AP / AR@100 (pycocotools, the bin
segmentation's metric) and the time per image. One JSON line per scene in `out` (resumable), the
summary returned and printed. `scenario`: whose shelf and camera render the scene (FetchShelf;
FetchShelfL515 renders through its camera's L515-like sensor model). `noise` (m) and `dropout` (a
fraction of pixels lost) add Gaussian noise on every depth and missing pixels to the render, drawn
from the scene's seed.

`AssociateShelfObjects` (simulation only): the segmenter's objects named after the true objects
they stand for, so that an action a policy plans on the estimate can be applied by FOSS to the true
scene (a robot needs no names: it acts where the object was seen).
"""

from __future__ import annotations

import functools
import json
import os
import time
from pathlib import Path

import numpy as np
from pycocotools import mask as mask_utils
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from tqdm import tqdm

from ms_drake.errors import MsDrakeError
from ms_drake.experiments.harness import read_records
from ms_drake.parallel import run_jobs
from ms_drake.perception.segmentation import coco_mask_metrics
from ms_drake.perception.shelf_segmentation import (
    ShelfSegmentationParams,
    segment_shelf,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import generate_shelf_scene
from ms_drake.scenes.shelf_render import render_shelf_scene
from ms_drake.shelf_geometry import Prisms, ShelfGeometry
from ms_drake.types import InstanceMasks, ShelfObject, ShelfScene

SCENARIO = "FetchShelf"


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def sensor_depth(depth: np.ndarray, noise: float, dropout: float, seed: int) -> np.ndarray:
    """A depth image with Gaussian noise (std `noise` m) and a `dropout` fraction of pixels lost (NaN)."""
    if noise < 0 or not 0 <= dropout < 1:
        raise ValueError(f"noise={noise} must be >= 0 and dropout={dropout} in [0, 1)")
    rng = np.random.default_rng([int(seed), 0x5E6])
    out = depth + noise * rng.standard_normal(depth.shape) if noise > 0 else depth.copy()
    if dropout > 0:
        out[rng.random(depth.shape) < dropout] = np.nan
    return out


def _rle(masks: InstanceMasks) -> list[dict]:
    out = []
    for m in masks.masks:
        r = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
        out.append({"size": [int(v) for v in r["size"]], "counts": r["counts"].decode("ascii")})
    return out


def _masks(rles: list[dict], shape) -> InstanceMasks:
    if not rles:
        return InstanceMasks.empty(*shape)
    m = np.stack([mask_utils.decode({"size": r["size"], "counts": r["counts"].encode("ascii")}) for r in rles])
    return InstanceMasks(m.astype(bool), tuple(f"m{k}" for k in range(len(rles))), np.ones(len(rles)))


def scene_record(scenario, geometry: ShelfGeometry, seed: int, occluders: int, min_pixels: int,
                 params: ShelfSegmentationParams, noise: float = 0.0, dropout: float = 0.0) -> dict:
    """The record of one scene (module docstring); its masks (ground truth and found) as COCO RLE."""
    truth = generate_shelf_scene(geometry, seed, occluders).scene
    render = render_shelf_scene(scenario, truth)
    depth = sensor_depth(render.depth, noise, dropout, seed)
    t0 = time.process_time()
    masks, est = segment_shelf(geometry, depth, params)
    seconds = time.process_time() - t0
    visible = [o for o in truth.objects if render.mask(o.id).sum() >= min_pixels]
    gt = InstanceMasks(np.stack([render.mask(o.id) for o in visible]) if visible else
                       np.zeros((0,) + render.depth.shape, bool), tuple(o.id for o in visible), np.ones(len(visible)))
    matches = []
    used = set()
    for k, o in enumerate(est.objects):
        ious = [_iou(masks.masks[k], gt.masks[j]) for j in range(len(gt))]
        j = int(np.argmax(ious)) if ious else -1
        if j < 0 or ious[j] < 0.5 or j in used:
            continue
        used.add(j)
        t = visible[j]
        fp_est, fp_true = Prisms.of([o]).footprints()[0], Prisms.of([t]).footprints()[0]
        matches.append({"id": t.id, "kind_ok": o.kind == t.kind, "mask_iou": ious[j],
                        "dx": o.x - t.x, "dy": o.y - t.y, "dwidth": o.width - t.width, "ddepth": o.depth - t.depth,
                        "dheight": o.height - t.height,
                        "footprint_iou": float(fp_est.intersection(fp_true).area / fp_est.union(fp_true).area)})
    return {"seed": seed, "occluders": occluders, "noise": noise, "dropout": dropout, "visible": len(visible),
            "found": len(est.objects), "matched": len(matches), "seconds": seconds, "matches": matches,
            "shape": list(render.depth.shape), "gt_rle": _rle(gt), "found_rle": _rle(masks)}


@functools.lru_cache(maxsize=2)
def _shelf(name: str = SCENARIO) -> tuple:
    scenario = load_scenario(None, name)
    return scenario, ShelfGeometry.from_scenario(scenario)


def scene_job(job: tuple) -> dict:
    """(occluders, seed, min_pixels, noise, dropout, scenario name) -> scene_record(...); module-level
    for the pool."""
    n, seed, min_pixels, noise, dropout, name = job
    scenario, geometry = _shelf(name)
    rec = scene_record(scenario, geometry, seed, n, min_pixels, ShelfSegmentationParams(), noise, dropout)
    rec["scenario"] = name
    return rec


def bench_shelf_segmentation(scenes: int, occluders: list[int], seed_start: int, out: Path,
                             min_pixels: int = 500, noise: float = 0.0, dropout: float = 0.0, workers: int = 1,
                             use_ray: bool = False, scenario: str = SCENARIO) -> dict:
    """Segment `scenes` scenes per occluder count; one JSON line per scene in `out` (resumes: the
    scenes already there are kept, failed ones are tried again) and the summary over all of the
    requested scenes in the file (module docstring; `failed`: scenes whose worker died this time)."""
    sensor_depth(np.zeros((1, 1)), noise, dropout, 0)  # checks the arguments before any work
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    same = lambda r: (r.get("noise", 0.0) == noise and r.get("dropout", 0.0) == dropout
                      and r.get("scenario", SCENARIO) == scenario)
    done = {(r["occluders"], r["seed"]) for r in read_records(out) if same(r)} if out.exists() else set()
    jobs = [(n, s, min_pixels, noise, dropout, scenario) for n in occluders for s in range(seed_start, seed_start + scenes)
            if (n, s) not in done]
    failed = []
    with open(out, "a") as f:
        for r in tqdm(run_jobs(scene_job, jobs, workers=workers, use_ray=use_ray), total=len(jobs),
                      desc="shelf segmentation", unit="scene"):
            if not r.ok:
                failed.append({"occluders": r.job[0], "seed": r.job[1], "error": (r.error or "").strip()[-300:]})
                tqdm.write(f"scene {r.job[1]} ({r.job[0]} occluders) failed (rerun to retry): {failed[-1]['error']}")
                continue
            f.write(json.dumps(r.value) + "\n")
            f.flush()
            os.fsync(f.fileno())
    recs = [r for r in read_records(out) if same(r) and r["occluders"] in occluders and
            seed_start <= r["seed"] < seed_start + scenes]
    summary = summarize_segmentation(recs)
    summary["failed"] = failed
    return summary


def summarize_segmentation(recs: list[dict]) -> dict:
    """Totals, error quantiles and COCO mask AP / AR@100 of scene records (bench_shelf_segmentation's lines)."""
    matches = [m for r in recs for m in r["matches"]]
    visible = sum(r["visible"] for r in recs)
    found = sum(r["found"] for r in recs)

    def q(key, f=abs):
        v = np.array([f(m[key]) for m in matches]) if matches else np.zeros(1)
        return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90))}

    out = {"scenes": len(recs), "visible": visible, "found": found, "matched": len(matches),
           "recall": len(matches) / max(visible, 1), "precision": len(matches) / max(found, 1),
           "kind_accuracy": float(np.mean([m["kind_ok"] for m in matches])) if matches else 0.0,
           "abs_dx_m": q("dx"), "abs_dwidth_m": q("dwidth"), "abs_ddepth_m": q("ddepth"), "abs_dheight_m": q("dheight"),
           "footprint_iou": q("footprint_iou", float),
           "ms_per_image": {"median": 1000 * float(np.median([r["seconds"] for r in recs])) if recs else 0.0}}
    if recs:
        coco = coco_mask_metrics([_masks(r["gt_rle"], r["shape"]) for r in recs],
                                 [_masks(r["found_rle"], r["shape"]) for r in recs])
        out.update({"ap": coco["AP"], "ap50": coco["AP50"], "ar100": coco["AR100"]})
    return out


def associate(estimate: ShelfScene, truth: ShelfScene, min_iou: float = 0.3) -> ShelfScene:
    """`estimate`'s objects, each renamed to the occluder of `truth` whose footprint overlaps it
    most (footprint IoU >= min_iou, one to one, best pairs first); the others keep their names."""
    if not estimate.objects or not truth.objects:
        return ShelfScene(estimate.objects, None, truth.seed)
    fe, ft = Prisms.of(estimate.objects).footprints(), Prisms.of(truth.objects).footprints()
    iou = np.array([[a.intersection(b).area / max(a.union(b).area, 1e-12) for b in ft] for a in fe])
    names = {}
    taken = set()
    for flat in np.argsort(-iou, axis=None):
        i, j = np.unravel_index(flat, iou.shape)
        if iou[i, j] < min_iou:
            break
        if i in names or j in taken:
            continue
        names[i] = truth.objects[j].id
        taken.add(j)
    objects = tuple(ShelfObject(names.get(i, o.id), o.kind, o.x, o.y, o.width, o.depth, o.height)
                    for i, o in enumerate(estimate.objects))
    return ShelfScene(objects, None, truth.seed)


class AssociateShelfObjects(LeafSystem):
    """Ports (declared first): inputs ``estimate`` (ShelfScene, the ShelfSegmenter's) and ``scene``
    (ShelfScene, the simulator's truth); output ``scene`` (the estimate, objects named after the true
    ones they match: `associate`)."""

    def __init__(self, min_iou: float = 0.3):
        super().__init__()
        self.estimate_port = self.DeclareAbstractInputPort("estimate", AbstractValue.Make(ShelfScene(())))
        self.truth_port = self.DeclareAbstractInputPort("scene", AbstractValue.Make(ShelfScene(())))
        self.DeclareAbstractOutputPort("scene", lambda: AbstractValue.Make(ShelfScene(())), self._calc)
        self.min_iou = float(min_iou)

    def _calc(self, context, output):
        if not (self.estimate_port.HasValue(context) and self.truth_port.HasValue(context)):
            raise MsDrakeError("AssociateShelfObjects: connect both the estimate (ShelfSegmenter.scene) and the "
                               "scene (FossSystem.scene) inputs")
        output.set_value(associate(self.estimate_port.Eval(context), self.truth_port.Eval(context), self.min_iou))
