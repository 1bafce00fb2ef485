"""`ms-drake perceive`: the perception stack on a user's depth image (.npy metres or 16-bit PNG
millimetres), with clear errors for files it cannot read."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ms_drake.experiments.perceive import PerceiveError, load_camera, load_depth, perceive
from ms_drake.perception.masks import label_image_to_masks, object_labels
from ms_drake.scenario import load_scenario
from ms_drake.scenes import SEARCH_HEAPS, generate_heap, scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """A rendered heap of 6 objects: depth (.npy and .png), colour, and the true masks."""
    s = load_scenario(None, "BinHeap15")
    heap = generate_heap(s, 6, 2, params=SEARCH_HEAPS)
    st = MakeStation(scenario_with_heap(s, heap), target_index=heap.target_index)
    ctx = st.CreateDefaultContext()
    set_heap_poses(st, ctx, heap)
    d = np.array(st.GetOutputPort("overhead.depth_image").Eval(ctx).data)[..., 0]
    rgb = np.array(st.GetOutputPort("overhead.rgb_image").Eval(ctx).data)[..., :3]
    labels = np.array(st.GetOutputPort("overhead.label_image").Eval(ctx).data)[..., 0]
    truth = label_image_to_masks(labels, object_labels(get_plant(st)), 20)
    folder = tmp_path_factory.mktemp("perceive")
    np.save(folder / "depth.npy", d)
    cv2.imwrite(str(folder / "depth.png"), np.where(np.isfinite(d), np.round(d * 1000), 0).astype(np.uint16))
    cv2.imwrite(str(folder / "rgb.png"), rgb[..., ::-1])
    return folder, heap, truth


def _best_iou(masks, truth):
    inter = (masks.masks[:, None] & truth.masks[None]).reshape(len(masks), len(truth), -1).sum(-1)
    union = (masks.masks[:, None] | truth.masks[None]).reshape(len(masks), len(truth), -1).sum(-1)
    return (inter / np.maximum(union, 1)).max(axis=0)  # per true object


def test_perceive_finds_the_objects_the_target_and_its_occupancy(images):
    folder, heap, truth = images
    d = load_depth(folder / "depth.npy")
    rgb = cv2.imread(str(folder / "rgb.png"))[..., ::-1].copy()
    # the station draws the target red: without the target's name the colour detector finds it
    res = perceive(d, load_camera(None, d.shape), rgb=rgb, target_size=(0.1, 0.05, 0.02))
    masks = res["masks"]
    assert np.mean(_best_iou(masks, truth) > 0.5) >= 0.8  # most objects found as one mask each
    found = res["target"]
    target_id = truth.ids.index(next(i for i in truth.ids if i.startswith(f"obj{heap.target_index:02d}")))
    assert found.visible and 0 <= found.instance_index < len(masks)
    iou = (found.mask & truth.masks[target_id]).sum() / max((found.mask | truth.masks[target_id]).sum(), 1)
    assert iou > 0.5  # the mask it picked is the target's
    occ = res["occupancy"]
    assert occ.shape == d.shape and np.isclose(occ.sum(), 1.0, atol=1e-3)
    # the PNG in millimetres gives the same masks (1 mm rounding)
    d_png = load_depth(folder / "depth.png")
    assert np.abs(d_png - np.where(np.isfinite(d), d, 0)).max() < 1e-3


def test_the_cli_writes_masks_coco_json_and_the_occupancy(images, tmp_path):
    folder, heap, truth = images
    out = subprocess.run([str(Path(sys.executable).parent / "ms-drake"), "perceive", str(folder / "depth.png"),
                          "--target-size", "0.1", "0.05", "0.02", "--out", str(tmp_path)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    coco = json.loads((tmp_path / "masks.json").read_text())
    assert coco["images"][0]["width"] == 640 and len(coco["annotations"]) >= 0.8 * len(truth)
    summary = json.loads((tmp_path / "perceive.json").read_text())
    assert summary["masks"] == len(coco["annotations"]) and summary["occupancy"]
    assert (tmp_path / "masks.png").is_file() and np.load(tmp_path / "occupancy.npy").shape == (480, 640)


def test_other_image_sizes_need_intrinsics_and_are_resized(images, tmp_path):
    folder, _, truth = images
    d = load_depth(folder / "depth.npy")
    small = cv2.resize(d, (320, 240), interpolation=cv2.INTER_NEAREST)
    with pytest.raises(PerceiveError, match="no --intrinsics"):
        load_camera(None, small.shape)
    f = tmp_path / "cam.yaml"
    f.write_text("width: 320\nheight: 240\nfx: 342.5\nfy: 342.5\ncx: 160\ncy: 120\n")
    res = perceive(small, load_camera(f, small.shape))
    assert res["masks"].masks.shape[1:] == (240, 320) and len(res["masks"]) >= 0.8 * len(truth)


@pytest.mark.parametrize("make,message", [
    (lambda p: np.save(p / "x.npy", np.full((480, 640), 800.0)), "look like millimetres"),
    (lambda p: np.save(p / "x.npy", np.zeros((480, 640, 3))), "one channel"),
    (lambda p: np.save(p / "x.npy", np.zeros((480, 640))), "no valid depth"),
    (lambda p: cv2.imwrite(str(p / "x.png"), np.full((480, 640), 200, np.uint8)), "must be 16-bit"),
    (lambda p: (p / "x.txt").write_text("1 2 3"), "unknown depth format"),
])
def test_bad_depth_files_get_one_clear_error(tmp_path, make, message):
    make(tmp_path)
    (path,) = tmp_path.iterdir()
    with pytest.raises(PerceiveError, match=message):
        load_depth(path)


@pytest.mark.parametrize("text,message", [
    ("width: 640\nheight: 480\nfx: 600\n", "missing fy, cx, cy"),
    ("width: 640\nheight: 480\nfx: 600\nfy: 600\ncx: 320\ncy: 240\nfocus: 3\n", "unknown key"),
    ("width: 640\nheight: 480\nfx: a\nfy: 600\ncx: 320\ncy: 240\n", "not a number"),
    ("width: 320\nheight: 240\nfx: 600\nfy: 600\ncx: 160\ncy: 120\n", "says 320 x 240"),
])
def test_bad_intrinsics_get_one_clear_error(tmp_path, text, message):
    f = tmp_path / "cam.yaml"
    f.write_text(text)
    with pytest.raises(PerceiveError, match=message):
        load_camera(f, (480, 640))


def test_the_cli_exits_2_on_a_bad_file(tmp_path):
    np.save(tmp_path / "mm.npy", np.full((480, 640), 800.0))
    out = subprocess.run([str(Path(sys.executable).parent / "ms-drake"), "perceive", str(tmp_path / "mm.npy")],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "millimetres" in out.stderr and "Traceback" not in out.stderr
