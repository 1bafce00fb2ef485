"""`ms-drake demo`: one full X-Ray search, written out: on the floating gripper (primitive fidelity)
by default, or with a robot's station (YuMiBin, PandaBin) in physics.

The search is the one a robot runs from its own camera, the named setting `camera` (DEMO_SETTING:
Table 8.2's search with the learned segmenter, the template target matcher (checked against the
target's size on the depth) and the learned occupancy, on the overhead depth through the PhoXi-like
sensor model), on a heap of the ``lid``
layout (scenes.layouts: the 6 cm lid dropped first, 14 unseen mesh objects piled on it), seed
`DEMO_SEED` by default: its target starts hidden. `DEMO_CONFIG` is that config; pass another to
search other heaps or with other settings (e.g. `load_bin_search_config("table_8_2")`: ground-truth
masks and the colour detector).

Outputs in the folder: the initial scene (overhead_{rgb,depth,masks,target}.png, heap.json, as
`ms-drake scene`), then per step k: step_kk.png (three panels: RGB with the instance masks and
the target outlined | the target occupancy distribution over the RGB | the chosen action drawn
on the RGB), search.gif (the steps in order), search.json (the rollout record) and
meshcat_recording.html (the whole search, a Meshcat StaticHtml recording).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np
from pydrake.geometry import Meshcat

from ms_drake.experiments.rollout import build_search, run_search
from ms_drake.experiments.scene_images import (
    colorize_masks,
    write_scene_images,
    write_search_pictures,
)
from ms_drake.geometry import PinholeCamera
from ms_drake.policies.bin_search import BinSearchConfig, config_scenario, load_bin_search_config
from ms_drake.scenario import load_scenario
from ms_drake.scenes.layouts import HEAP_SCENARIO, HeapConfig, layout_heap


def _overlay_occupancy(rgb: np.ndarray, occ) -> np.ndarray:
    if occ is None or not np.any(occ.distribution > 0):
        return (0.5 * rgb).astype(np.uint8)
    d = occ.distribution / occ.distribution.max()
    heat = cv2.applyColorMap((255 * d).astype(np.uint8), cv2.COLORMAP_JET)[:, :, ::-1].astype(float)
    a = (0.75 * np.sqrt(d))[..., None]
    return ((1 - a) * rgb + a * heat).clip(0, 255).astype(np.uint8)


def _draw_action(rgb: np.ndarray, action, camera) -> np.ndarray:
    pic = rgb.copy()
    if action.kind == "grasp" and action.grasp is not None:
        g = action.grasp
        c = np.asarray(g.center, float)
        ax = np.asarray(g.axis, float) * max(g.width, 0.03) / 2 if np.linalg.norm(g.axis) > 0 else np.zeros(3)
        uv, _ = camera.project(np.stack([c, c - ax, c + ax]))
        uv = uv.astype(int)
        cv2.line(pic, tuple(uv[1]), tuple(uv[2]), (0, 255, 0), 3)
        cv2.circle(pic, tuple(uv[0]), 6, (0, 255, 0), 2)
        text = f"grasp {g.object_id} q={g.quality:.2f}"
    elif action.kind == "push" and action.push is not None:
        uv, _ = camera.project(np.stack([np.asarray(action.push.start, float), np.asarray(action.push.end, float)]))
        uv = uv.astype(int)
        cv2.arrowedLine(pic, tuple(uv[0]), tuple(uv[1]), (0, 200, 255), 3, tipLength=0.25)
        text = f"push {action.push.object_id}"
    else:
        text = f"stop: {action.reason}"
    cv2.putText(pic, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
    return pic


# How a search ended, in words (the selector's stop reasons).
SEARCH_ENDS = {"success": "success: the target is out of the bin",
               "target_removed": "failure: the target left the bin by accident",
               "no_action": "failure: no action left to plan",
               "horizon": "failure: the action budget ran out",
               "too_many_pushes": "failure: too many pushes in a row"}


def frame_image(frame, camera) -> np.ndarray:
    """The three panels of one step side by side (RGB, uint8)."""
    rgb = frame.rgb
    masks = colorize_masks(frame.masks, rgb, alpha=0.45)
    if frame.target.visible:
        cnts, _ = cv2.findContours(frame.target.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(masks, cnts, -1, (255, 0, 0), 3)
    if frame.action.kind == "stop":  # the search is over: say how it ended
        text = f"step {frame.step}: {SEARCH_ENDS.get(frame.action.reason, 'search over: ' + frame.action.reason)}"
    else:
        text = f"step {frame.step}: {len(frame.masks)} masks, target {'visible' if frame.target.visible else 'hidden'}"
    cv2.putText(masks, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
    occ = _overlay_occupancy(rgb, frame.occupancy)
    cv2.putText(occ, "target occupancy (X-Ray)", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
    return np.concatenate([masks, occ, _draw_action(rgb, frame.action, camera)], axis=1)


DEMO_SEED = 5000
DEMO_SETTING = "camera"
DEMO_CONFIG = dataclasses.replace(load_bin_search_config(DEMO_SETTING), heap=HeapConfig(layout="lid", objects=14))


def run_demo(out: Path, config: BinSearchConfig = DEMO_CONFIG, seed: int = DEMO_SEED, meshcat_html: bool = True,
             log=print) -> dict:
    """Generate heap `seed` of config.heap, write the initial scene, run the search of `config` on
    its station (config.scenario; a robot's searches in physics) and write its pictures."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    config = dataclasses.replace(config, seed=int(seed))
    scenario = config_scenario(config)
    heap = layout_heap(config.heap, seed)
    log(f"  {len(heap.objects)} objects settled in {time.perf_counter() - t:.1f} s; target {heap.target}")
    written = write_scene_images(load_scenario(None, HEAP_SCENARIO), heap, out, meshcat_html=False)
    meshcat = Meshcat() if meshcat_html else None
    system = build_search(scenario, heap, config, meshcat=meshcat)
    res = run_search(system, heap, config, keep_frames=True, meshcat=meshcat, after=1.5 if meshcat else 0.0)
    camera = PinholeCamera.from_config(system.scenario.cameras["overhead"])
    written.update(write_search_pictures(out, [(fr.step, frame_image(fr, camera)) for fr in res.frames], res.record(),
                                         meshcat, gif_seconds=1.0))
    log(f"  {config.policy}: {'success' if res.success else res.failure} after {res.actions} actions "
        f"({', '.join(res.action_kinds) or 'none'}) in {res.seconds:.1f} s")
    return written
