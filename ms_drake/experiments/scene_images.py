"""A scene (heap or placed objects) in its station, rendered to images and a Meshcat recording.

`make_scene(scenario, seed, num_objects)` -> Heap (a bin heap for bin scenarios, stable
placements on tables and shelves); `write_scene_images(scenario, heap, out_dir)` builds the
station with the heap's objects (the target drawn red), renders every camera and writes
rgb / depth / masks / target PNGs, the heap JSON and optionally a Meshcat HTML recording.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import imageio.v2 as imageio
import numpy as np
from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator

from ms_drake.geometry import PinholeCamera, silhouette
from ms_drake.objects import get_object, get_object_set
from ms_drake.perception.masks import label_image_to_masks, object_labels
from ms_drake.scenario import Scenario
from ms_drake.scenes.heaps import (
    HeapParams,
    generate_heap,
    heap_to_dict,
    scenario_with_heap,
    set_heap_poses,
)
from ms_drake.scenes.tabletop import place_objects
from ms_drake.station.station import MakeStation, get_plant, station_objects
from ms_drake.types import Heap, InstanceMasks


def make_scene(scenario: Scenario, seed: int, num_objects: int | None = None, params: HeapParams | None = None) -> Heap:
    n = scenario.objects.count if num_objects is None else num_objects
    if scenario.environment.type == "bin":
        return generate_heap(scenario, n, seed, params=params)
    rng = np.random.default_rng([seed, 7919])
    oset = get_object_set(scenario.objects.set)
    names = [o.full_name for o in oset.sample(n, rng, scenario.objects.split)]
    return place_objects(scenario, names, seed)


def colorize_masks(masks: InstanceMasks, rgb: np.ndarray | None = None, alpha: float = 0.6) -> np.ndarray:
    """An RGB picture of instance masks (over `rgb` if given), each instance its own colour."""
    h, w = masks.masks.shape[1:] if len(masks) else (rgb.shape[:2] if rgb is not None else (1, 1))
    base = rgb.astype(float) if rgb is not None else np.zeros((h, w, 3))
    out = base.copy()
    rng = np.random.default_rng(0)
    for m in masks.masks:
        color = rng.uniform(60, 255, 3)
        out[m] = (1 - alpha) * base[m] + alpha * color
        cnts, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, cnts, -1, (255, 255, 255), 1)
    return out.clip(0, 255).astype(np.uint8)


def depth_to_png(depth: np.ndarray) -> np.ndarray:
    d = np.where(np.isfinite(depth), depth, np.nan)
    lo, hi = np.nanpercentile(d, 1), np.nanpercentile(d, 99)
    g = np.nan_to_num((d - lo) / max(hi - lo, 1e-6), nan=1.0).clip(0, 1)
    return cv2.applyColorMap((255 * (1 - g)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[:, :, ::-1]


def _save_png(path: Path, rgb: np.ndarray):
    cv2.imwrite(str(path), rgb[:, :, ::-1] if rgb.ndim == 3 else rgb)


def write_scene_images(scenario: Scenario, heap: Heap, out_dir, meshcat_html: bool = False,
                       record_seconds: float = 0.5) -> dict:
    """Render the heap in its station; returns {name: path} of everything written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = scenario_with_heap(scenario, heap)
    meshcat = None
    if meshcat_html:
        meshcat = Meshcat()
    station = MakeStation(s, meshcat=meshcat, target_index=heap.target_index)
    context = station.CreateDefaultContext()
    set_heap_poses(station, context, heap)
    plant = get_plant(station)
    labels_to_id = object_labels(plant)
    objs = station_objects(plant)
    written = {}
    (out / "heap.json").write_text(json.dumps(heap_to_dict(heap), indent=1))
    written["heap"] = str(out / "heap.json")
    for cam_name, cfg in s.cameras.items():
        rgb = np.array(station.GetOutputPort(f"{cam_name}.rgb_image").Eval(context).data)[:, :, :3]
        depth = np.array(station.GetOutputPort(f"{cam_name}.depth_image").Eval(context).data)[:, :, 0]
        labels = np.array(station.GetOutputPort(f"{cam_name}.label_image").Eval(context).data)[:, :, 0]
        masks = label_image_to_masks(labels, labels_to_id, min_pixels=20)
        for key, img in (("rgb", rgb), ("depth", depth_to_png(depth)), ("masks", colorize_masks(masks, rgb))):
            p = out / f"{cam_name}_{key}.png"
            _save_png(p, img)
            written[f"{cam_name}_{key}"] = str(p)
        np.save(out / f"{cam_name}_depth.npy", depth)
        if 0 <= heap.target_index < len(objs):
            cam = PinholeCamera.from_config(cfg)
            o = objs[heap.target_index]

            mesh = get_object(o.full_name).trimesh()
            X = plant.EvalBodyPoseInWorld(plant.GetMyContextFromRoot(context), plant.get_body(o.body_index))
            amodal = silhouette(cam, np.asarray(mesh.vertices) @ X.rotation().matrix().T + X.translation(),
                                np.asarray(mesh.faces))
            modal = labels == int(o.body_index)
            pic = (0.5 * rgb).astype(np.uint8)
            pic[modal] = (255, 40, 40)
            cnts, _ = cv2.findContours(amodal.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(pic, cnts, -1, (255, 255, 0), 2)
            p = out / f"{cam_name}_target.png"
            _save_png(p, pic)
            written[f"{cam_name}_target"] = str(p)
    if meshcat is not None:
        sim = Simulator(station, context)
        meshcat.StartRecording()
        sim.AdvanceTo(record_seconds)
        meshcat.StopRecording()
        meshcat.PublishRecording()
        p = out / "meshcat_recording.html"
        p.write_text(meshcat.StaticHtml())
        written["meshcat"] = str(p)
    return written


def write_search_pictures(out: Path, frames, record: dict, meshcat=None, gif_seconds: float = 1.0) -> dict:
    """The pictures of a search: one PNG per step (`frames`: (step, RGB uint8 image) pairs), a GIF of
    them at half size, the record as search.json and the Meshcat recording (when `meshcat` is
    given). Returns {name: path}."""
    out = Path(out)
    written, images = {}, []
    for step, img in frames:
        p = out / f"step_{step:02d}.png"
        cv2.imwrite(str(p), img[:, :, ::-1])
        written[f"step_{step:02d}"] = str(p)
        images.append(cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA))
    if images:
        gif = out / "search.gif"
        imageio.mimsave(gif, images, duration=gif_seconds, loop=0)
        written["gif"] = str(gif)
    (out / "search.json").write_text(json.dumps(record, indent=1))
    written["search"] = str(out / "search.json")
    if meshcat is not None:
        html = out / "meshcat_recording.html"
        html.write_text(meshcat.StaticHtml())
        written["meshcat"] = str(html)
    return written
