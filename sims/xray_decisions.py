"""X-Ray's occluder choice with several occupancy estimators on the same search states.

    .venv/bin/python sims/xray_decisions.py --seeds 5000 5100 --heap-dir HEAPS --out decisions.jsonl \
        [--weights shipped=models/weights/occupancy.pt 1x1=models/weights/occupancy_1x1.pt] [--height-prior]
    .venv/bin/python sims/xray_decisions.py --summarize decisions.jsonl

Runs X-Ray with `--occupancy analytic_image_best` (the ground-truth generator on the depth image and
the target's box, best-matching placements) on the cached `xray_compact` heaps (`--grasp-samples 32`,
H = 10, the settings of docs/BENCHMARKS.md) and, before each action, asks every estimator which
occluder X-Ray would take first on that very state (its order without the seen target, which
X-Ray tries first in any case): "best" (the generator itself) and each network of --weights (input
scaling on). Per decision it writes the target's seen pixels, the occluder the oracle takes (the
mask covering the most of the target's true amodal mask), each estimator's choice, how much of the
amodal mask that choice covers, and the estimator's mass on the amodal mask. --height-prior adds
each estimator's map weighted by the pile's height (blurred, sigma 25 px) and its square: the
target is dropped first, so it may lie where the pile is highest. A heap's decisions are written
together after its search (resumable: heaps already in --out are skipped).

The summary splits the decisions where an occluder covers the target by the target's state
(hidden / partly seen): how often each estimator's first occluder covers the target, is the
oracle's, and the share of the oracle's cover it reaches.
"""
import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from ms_drake.experiments.harness import cached_heap
from ms_drake.experiments.occupancy_data import _ray_z
from ms_drake.experiments.rollout import SCENARIOS, SearchParams, build_search, primitive_time_step, run_search
from ms_drake.experiments.xray import XRAY_SMALL_TARGET
from ms_drake.perception.masks import make_amodal_masks
from ms_drake.perception.occupancy import TargetBox
from ms_drake.perception.occupancy_net import LearnedOccupancy
from ms_drake.policies.bin_selectors import priority_oracle, priority_xray, target_index
from ms_drake.scenario import load_scenario
from ms_drake.types import OccupancyMap


def pile_height(depth, occ_system) -> np.ndarray:
    """(H, W) height of the seen surface above the bin floor [m], blurred (sigma 25 px)."""
    cam, ws = occ_system.backend.camera, occ_system.backend.workspace
    d = np.asarray(depth.data, np.float32)[..., 0]
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
    h = np.nan_to_num(d * _ray_z(cam) + (cam.X_WC.translation()[2] - ws.floor_z), nan=0.0).clip(0.0, 0.3)
    return cv2.GaussianBlur(h.astype(np.float32), (0, 0), 25)


def decisions(seed: int, heap_dir: Path, nets: dict, height_prior: bool) -> list[dict]:
    heap = cached_heap(14, seed, str(heap_dir), "xray_compact", "drake")
    p = SearchParams(policy="xray", fidelity="primitive", horizon=10, seed=seed, time_step=primitive_time_step("xray"),
                     grasp_planner="image", grasp_samples=32, occupancy="analytic_image_best")
    s = build_search(load_scenario(None, SCENARIOS["primitive"]), heap, p)
    rows = []

    def on_idle(system, context, step):
        occ = system.controller.GetSubsystemByName("occupancy_estimator")
        oc = occ.GetMyContextFromRoot(context)
        depth, target = occ.GetInputPort("depth_image").Eval(oc), occ.GetInputPort("target").Eval(oc)
        masks = system.output(context, "masks")
        poses = system.plant.get_body_poses_output_port().Eval(system.plant.GetMyContextFromRoot(context))
        am = make_amodal_masks(system.plant, occ.backend.camera).masks_for(poses)
        amodal = np.asarray(am.masks[am.ids.index(system.target_id)], bool)
        cover = (masks.masks & amodal[None]).reshape(len(masks), -1).sum(axis=1)
        t = target_index(masks, target)

        def first_occluder(order):
            return next((i for i in order if i != t), -1)

        seen = target.mask if target.visible else np.zeros(amodal.shape, bool)
        maps = {"best": system.output(context, "occupancy").distribution}
        maps.update({k: est.estimate(depth, seen) for k, est in nets.items()})
        if height_prior:
            h = pile_height(depth, occ)
            maps.update({f"{k}_h{a}": m * h ** a for k, m in list(maps.items()) for a in (1, 2)})
        row = dict(seed=seed, step=step, seen=int(seen.sum()), amodal=int(amodal.sum()), masks=len(masks),
                   oracle=first_occluder(priority_oracle(masks, "", amodal)),
                   max_cover=int(max((cover[i] for i in range(len(masks)) if i != t), default=0)))
        for k, m in maps.items():
            i = first_occluder(priority_xray(masks, OccupancyMap(m), None))
            row[k] = dict(choice=i, cover=int(cover[i]) if i >= 0 else 0,
                          mass=float(m[amodal].sum() / max(m.sum(), 1e-12)))
        rows.append(row)

    res = run_search(s, heap, p, on_idle=on_idle)
    for r in rows:
        r["success"] = bool(res.success)
    return rows


def summarize(path: Path):
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    names = [k for k, v in rows[0].items() if isinstance(v, dict)]
    print(f"{len({r['seed'] for r in rows})} heaps, {len(rows)} decisions")
    for phase, keep in (("target hidden", lambda r: r["seen"] == 0), ("target partly seen", lambda r: r["seen"] > 0)):
        rs = [r for r in rows if keep(r) and r["max_cover"] > 0]
        print(f"{phase}: {len(rs)} decisions where an occluder covers the target")
        for k in names:
            hit = np.mean([r[k]["cover"] > 0 for r in rs])
            orc = np.mean([r[k]["choice"] == r["oracle"] for r in rs])
            share = np.mean([r[k]["cover"] / r["max_cover"] for r in rs])
            mass = np.median([r[k]["mass"] for r in rs])
            print(f"  {k:12s} first occluder covers the target {hit:5.1%}, is the oracle's {orc:5.1%}, "
                  f"covers {share:.2f} of the oracle's cover; mass on the target (median) {mass:.3f}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", nargs=2, type=int, metavar=("FROM", "TO"))
    ap.add_argument("--heap-dir", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--weights", nargs="*", default=["shipped=models/weights/occupancy.pt"],
                    help="NAME=FILE networks to compare with the generator")
    ap.add_argument("--height-prior", action="store_true")
    ap.add_argument("--summarize", type=Path)
    args = ap.parse_args()
    if args.summarize:
        summarize(args.summarize)
        return
    if not (args.seeds and args.heap_dir and args.out):
        ap.error("give --seeds FROM TO, --heap-dir and --out (or --summarize FILE)")
    box = TargetBox.from_object(XRAY_SMALL_TARGET)  # the 4.5 cm square box the heaps hide
    nets = {}
    for spec in args.weights:
        name, _, path = spec.partition("=")
        if not Path(path).is_file():
            ap.error(f"--weights {spec}: no such file {path!r}; give NAME=FILE")
        nets[name] = LearnedOccupancy(box, weights=path)
    done = {json.loads(line)["seed"] for line in args.out.read_text().splitlines()} if args.out.exists() else set()
    with args.out.open("a") as f:
        for seed in range(*args.seeds):
            if seed in done:
                continue
            rows = decisions(seed, args.heap_dir, nets, args.height_prior)
            f.write("".join(json.dumps(r) + "\n" for r in rows))
            f.flush()
            print(seed, len(rows), "decisions, success" if rows and rows[0]["success"] else "decisions, failure", flush=True)
    summarize(args.out)


if __name__ == "__main__":
    main()
