"""COCO mask AP / AR@100 of the depth-only segmentation baselines (Table B.1 analogue).

    .venv/bin/python sims/bench_segmentation.py --heaps 50 --seed-start 1000 [--cache DIR]

Images: one overhead 640 x 480 depth image per heap of the BinHeap15 scenario's bin, with
N ~ Poisson(7.5) objects truncated to [1, 10] (rejection sampling; the WISDOM-Sim recipe of
Ch. 5.3), procedural object set; ground truth = the label image's visible masks (>= 20 px).
Heaps and images are cached in --cache (resumable). The parameters were tuned on heaps of
other seeds (0-7), never on these.
"""

from __future__ import annotations

import argparse
import json
import pickle
import statistics
import time
from pathlib import Path

import numpy as np

SECTION = "## Segmentation baselines"


def object_count(seed: int) -> int:
    rng = np.random.default_rng([seed, 55])
    while True:
        n = int(rng.poisson(7.5))
        if 1 <= n <= 10:
            return n


def render_heap(scenario, heap):
    from ms_drake.perception.masks import label_image_to_masks, object_labels
    from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
    from ms_drake.station import MakeStation, get_plant

    station = MakeStation(scenario_with_heap(scenario, heap))
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, heap)
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0].copy()
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
    return depth, label_image_to_masks(labels, object_labels(get_plant(station)), 20)


def dataset(scenario, seeds, cache: Path):
    from ms_drake.scenes.heaps import generate_heap

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for seed in seeds:
        f = cache / f"seg_{seed}.pkl"
        if not f.exists():
            t = time.perf_counter()
            heap = generate_heap(scenario, object_count(seed), seed)
            depth, gt = render_heap(scenario, heap)
            f.write_bytes(pickle.dumps({"depth": depth, "gt": gt, "n": len(heap.objects)}))
            print(f"heap {seed}: {len(heap.objects)} objects, {len(gt)} visible, {time.perf_counter() - t:.1f} s",
                  flush=True)
        out.append(pickle.loads(f.read_bytes()))
    return out


def run(heaps: int, seed_start: int, cache: Path) -> dict:
    from ms_drake.geometry import PinholeCamera
    from ms_drake.geometry import Workspace, world_points
    from ms_drake.perception.segmentation import coco_mask_metrics, euclidean_clustering, region_growing
    from ms_drake.scenario import load_scenario

    s = load_scenario(None, "BinHeap15")
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    ws = Workspace.from_scenario(s)
    data = dataset(s, range(seed_start, seed_start + heaps), cache)
    gts = [d["gt"] for d in data]
    res = {"images": len(data), "objects": sum(d["n"] for d in data), "gt_masks": sum(len(g) for g in gts)}
    for name, fn in (("euclidean", euclidean_clustering), ("region_growing", region_growing)):
        preds, secs = [], []
        for d in data:
            t = time.perf_counter()
            preds.append(fn(world_points(cam, d["depth"].astype(float)), ws))
            secs.append(time.perf_counter() - t)
        m = coco_mask_metrics(gts, preds)
        m["seconds_median"] = statistics.median(secs)
        res[name] = m
        print(name, json.dumps(m), flush=True)
    res["ground_truth"] = coco_mask_metrics(gts, gts)
    return res


def table(res: dict, cmd: str) -> str:
    lines = [SECTION, "",
             f"Command: `{cmd}` (2 cores, no GPU, shared with other jobs).",
             f"{res['images']} simulated 640 x 480 overhead depth images of bin heaps (N ~ Poisson(7.5) truncated "
             f"to [1, 10], {res['objects']} objects, {res['gt_masks']} visible ground-truth masks >= 20 px). "
             "COCO mask AP (IoU 0.50:0.95), AP50 and AR@100 by pycocotools; every baseline score is 1.",
             "",
             "| method | AP | AP50 | AR@100 | masks | median s / image | reference (Table B.1, WISDOM-Sim) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    ref = {"euclidean": "AP 0.161, AR 0.252", "region_growing": "AP 0.172, AR 0.274"}
    for name, label in (("euclidean", "Euclidean clustering"), ("region_growing", "Region growing")):
        m = res[name]
        lines.append(f"| {label} | {m['AP']:.3f} | {m['AP50']:.3f} | {m['AR100']:.3f} | {m['dt']} | "
                     f"{m['seconds_median']:.2f} | {ref[name]} |")
    lines += ["| ground truth (label image, sanity check) | "
              f"{res['ground_truth']['AP']:.3f} | {res['ground_truth']['AP50']:.3f} | "
              f"{res['ground_truth']['AR100']:.3f} | {res['ground_truth']['dt']} | - | SD Mask R-CNN: AP 0.664 |", ""]
    lines += [
        "Both baselines are above the reference's PCL figures: the images here are noise-free, the",
        "camera is fixed and the procedural objects are mostly boxes and cylinders whose faces are",
        "smooth; as there, touching objects of similar height merge (Euclidean clustering) and",
        "box faces split (region growing splits at the 90-degree edges), which keep AP far below a",
        "learned segmenter.", ""]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heaps", type=int, default=50)
    ap.add_argument("--seed-start", type=int, default=1000)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/ms_drake_bench_segmentation"))
    a = ap.parse_args()
    res = run(a.heaps, a.seed_start, a.cache)
    cmd = f".venv/bin/python sims/bench_segmentation.py --heaps {a.heaps} --seed-start {a.seed_start}"
    text = table(res, cmd)
    print(text)


if __name__ == "__main__":
    main()
