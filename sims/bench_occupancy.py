"""Speed and fidelity of the occupancy ground-truth generator (Ch. 8.3.1; the reference: 1.5 s / image).

    .venv/bin/python sims/bench_occupancy.py --heaps 10 --render-images 2

For each of `--heaps` 15-object heaps (BinHeap15, seeds from --seed-start, cached in --cache)
and each reference target box (1:1 = 3 x 3 x 0.5 cm and 10:1 = 9.5 x 0.95 x 0.5 cm, Ch. 8.3.1),
AnalyticOccupancy (64 x 48 translations x 16 rotations) runs on the overhead 640 x 480 depth
image twice: with the target hidden (empty observed mask: the case with the most matching
placements) and with the heap target's observed modal mask. Each call is timed 5 times (median).
On `--render-images` images the straightforward implementation (RenderedOccupancy: one VTK
target-only depth render per placement) runs on the same input in the same process; the ratio of
the two times and the agreement of the two distributions are reported.
"""

from __future__ import annotations

import argparse
import os
import pickle
import statistics
import time
from pathlib import Path

import numpy as np

SECTION = "## Occupancy"
TARGETS = {"1:1": (0.03, 0.03, 0.005), "10:1": (0.095, 0.0095, 0.005)}


def heap_images(scenario, seeds, cache: Path):
    from ms_drake.perception.masks import object_labels
    from ms_drake.scenes.heaps import generate_heap, scenario_with_heap, set_heap_poses
    from ms_drake.station import MakeStation, get_plant, station_objects

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for seed in seeds:
        f = cache / f"occ_{seed}.pkl"
        if f.exists() and "target" not in pickle.loads(f.read_bytes()):
            f.unlink()  # cached before the target's name and pose were kept
        if not f.exists():
            heap = generate_heap(scenario, 15, seed)
            station = MakeStation(scenario_with_heap(scenario, heap))
            ctx = station.CreateDefaultContext()
            set_heap_poses(station, ctx, heap)
            depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0].copy()
            labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
            obj = station_objects(get_plant(station))[heap.target_index]
            label = next(k for k, v in object_labels(get_plant(station)).items() if v == obj.model_name)
            f.write_bytes(pickle.dumps({"depth": depth, "target_mask": labels == label, "seed": seed,
                                        "target": heap.target, "X_WO": heap.objects[heap.target_index].matrix()}))
            print(f"heap {seed} cached", flush=True)
        out.append(pickle.loads(f.read_bytes()))
    return out


def timed(fn, repeats=5):
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        r = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus), r


def run(heaps: int, seed_start: int, render_images: int, cache: Path) -> dict:
    from ms_drake.geometry import PinholeCamera
    from ms_drake.perception.occupancy import AnalyticOccupancy, RenderedOccupancy, TargetMesh
    from ms_drake.geometry import Workspace
    from ms_drake.scenario import load_scenario

    s = load_scenario(None, "BinHeap15")
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    ws = Workspace.from_scenario(s)
    data = heap_images(s, range(seed_start, seed_start + heaps), cache)
    res = {"heaps": len(data), "targets": {}, "load_start": os.getloadavg()[0]}
    for name, size in TARGETS.items():
        t = time.perf_counter()
        occ = AnalyticOccupancy(cam, ws, size)
        init = time.perf_counter() - t
        rows = {"hidden": [], "observed": []}
        for d in data:
            for case, mask in (("hidden", np.zeros_like(d["target_mask"])), ("observed", d["target_mask"])):
                w, c, rho = timed(lambda: occ.estimate(d["depth"], mask))
                rows[case].append((w, c, occ.last_matches, int((rho > 0).sum())))
        res["targets"][name] = {"init": init, "placements": len(occ.gu) * occ.grid.rotations, "runs": len(occ.runs),
                                **{case: {"wall": statistics.median(r[0] for r in v), "cpu": statistics.median(
                                    r[1] for r in v), "wall_max": max(r[0] for r in v),
                                    "matches": statistics.median(r[2] for r in v)} for case, v in rows.items()}}
        print(name, res["targets"][name], flush=True)
    # The heap target's own mesh at its true pose (what the X-Ray rollouts use): one generator per heap.
    rows = {"hidden": [], "observed": []}
    inits, placements, seen_matched, visible = [], [], 0, 0
    for d in data:
        t = time.perf_counter()
        occ = AnalyticOccupancy(cam, ws, TargetMesh.from_object(d["target"], d["X_WO"]))
        inits.append(time.perf_counter() - t)
        placements.append(len(occ.gu) * len(occ.angles))
        for case, mask in (("hidden", np.zeros_like(d["target_mask"])), ("observed", d["target_mask"])):
            w, c, rho = timed(lambda: occ.estimate(d["depth"], mask))
            rows[case].append((w, c, occ.last_matches))
        visible += bool(d["target_mask"].any())
        seen_matched += bool(d["target_mask"].any()) and rows["observed"][-1][2] > 0
    res["mesh"] = {"init": statistics.median(inits), "placements": statistics.median(placements),
                   "seen_matched": seen_matched, "visible": visible, "targets": sorted({d["target"] for d in data}),
                   **{case: {"wall": statistics.median(r[0] for r in v), "cpu": statistics.median(r[1] for r in v),
                             "wall_max": max(r[0] for r in v), "matches": statistics.median(r[2] for r in v)}
                      for case, v in rows.items()}}
    print("mesh", res["mesh"], flush=True)
    comps = []
    size = TARGETS["1:1"]
    fast = AnalyticOccupancy(cam, ws, size)
    slow = RenderedOccupancy(s, size)
    for d in data[:render_images]:
        mask = np.zeros_like(d["target_mask"])
        wf, cf, a = timed(lambda: fast.estimate(d["depth"], mask))
        c0 = time.process_time()
        slow.renders, slow.render_seconds = 0, 0.0
        t = time.perf_counter()
        b = slow.estimate(d["depth"], mask)
        ws_ = time.perf_counter() - t
        cs = time.process_time() - c0
        sa, sb = a > 0, b > 0
        comps.append({"seed": d["seed"], "fast": wf, "fast_cpu": cf, "slow": ws_, "slow_cpu": cs,
                      "renders": slow.renders,
                      "per_render": slow.render_seconds / max(slow.renders, 1), "ratio": ws_ / wf,
                      "ratio_cpu": cs / cf,
                      "support_iou": float((sa & sb).sum() / max((sa | sb).sum(), 1)),
                      "l1": float(np.abs(a - b).sum())})
        print(comps[-1], flush=True)
    res["rendered"] = comps
    res["load_end"] = os.getloadavg()[0]
    return res


def table(res: dict, cmd: str) -> str:
    lines = [SECTION, "",
             f"Command: `{cmd}`. Machine: 2 cores, no GPU, shared with other engineers' jobs (load average "
             f"{res['load_start']:.1f} at the start, {res['load_end']:.1f} at the end), so wall times are upper "
             "bounds; CPU is the process's own time. Analytic ground truth of Ch. 8.3.1 (64 x 48 translations x 16 "
             f"rotations, IoU > 0.9 or both empty) on {res['heaps']} overhead 640 x 480 depth images of 15-object "
             "heaps; placements are restricted to the bin (ms_drake/perception/occupancy.py). Median of 5 calls per "
             "image, then median over images.",
             "",
             "| target box | placements in the bin | target hidden: wall / CPU per image (worst image, wall) | "
             "target seen: wall / CPU per image | matching placements (hidden, median) | setup once |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, t in res["targets"].items():
        h, o = t["hidden"], t["observed"]
        lines.append(f"| {name} {TARGETS[name]} m | {t['placements']} | {1e3 * h['wall']:.0f} ms / {1e3 * h['cpu']:.0f} ms "
                     f"({1e3 * h['wall_max']:.0f} ms) | {1e3 * o['wall']:.0f} ms / {1e3 * o['cpu']:.0f} ms | "
                     f"{h['matches']:.0f} | {t['init']:.2f} s |")
    if "mesh" in res:
        m = res["mesh"]
        h, o = m["hidden"], m["observed"]
        lines.append(f"| heap target's own mesh at its true pose (TargetMesh; median over the {res['heaps']} heaps) | "
                     f"{m['placements']:.0f} | {1e3 * h['wall']:.0f} ms / {1e3 * h['cpu']:.0f} ms "
                     f"({1e3 * h['wall_max']:.0f} ms) | {1e3 * o['wall']:.0f} ms / {1e3 * o['cpu']:.0f} ms | "
                     f"{h['matches']:.0f} | {m['init']:.2f} s per target |")
    mesh_text = ""
    if "mesh" in res:
        m = res["mesh"]
        mesh_text = (f" The last row uses each heap target's own mesh at its true pose (the X-Ray rollouts' "
                     f"generator; targets {', '.join(m['targets'])}): of the {m['visible']} heaps whose target "
                     f"is seen, {m['seen_matched']} had at least one matching placement (its true placement is "
                     "among them by construction); where none matches (e.g. a target resting on another object, "
                     "higher than the floor the placements assume) the distribution falls back to the observed "
                     "mask, as it does for the box rows when a seen heap target is no box of their size.")
    lines += ["",
              "Target: <= 0.1 s per image (the reference: 1.5 s per image on a 12-core i7); the CPU time is what one "
              "free core takes, the wall time what the shared machine gave. \"target seen\" uses the heap target's "
              "observed modal mask (empty when the heap's target is hidden, then the same as the hidden case)."
              + mesh_text, "",
              "Against the straightforward implementation (RenderedOccupancy: one VTK target-only depth render per "
              "placement, same image, same process, 1:1 target hidden):", "",
              "| heap seed | analytic wall / CPU | render per placement wall / CPU | renders | per render | "
              "ratio wall / CPU | support IoU | L1 |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for c in res["rendered"]:
        lines.append(f"| {c['seed']} | {1e3 * c['fast']:.0f} ms / {1e3 * c['fast_cpu']:.0f} ms | {c['slow']:.0f} s / "
                     f"{c['slow_cpu']:.0f} s | {c['renders']} | {1e3 * c['per_render']:.1f} ms | "
                     f"{c['ratio']:.0f}x / {c['ratio_cpu']:.0f}x | {c['support_iou']:.3f} | {c['l1']:.3f} |")
    lines += ["",
              "Both implement the same test, so the distributions agree up to the reference's shift approximation",
              "(the analytic generator translates one silhouette per rotation; the renders place the box exactly,",
              "so near the bin's edges a sliver of the box's side shows in the renders). tests/test_occupancy.py",
              "checks that the fast path's counts equal shifting every silhouette pixel by pixel.", "", ""]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heaps", type=int, default=10)
    ap.add_argument("--seed-start", type=int, default=2000)
    ap.add_argument("--render-images", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/ms_drake_bench_occupancy"))
    a = ap.parse_args()
    res = run(a.heaps, a.seed_start, a.render_images, a.cache)
    cmd = (f".venv/bin/python sims/bench_occupancy.py --heaps {a.heaps} --seed-start {a.seed_start} "
           f"--render-images {a.render_images}")
    text = table(res, cmd)
    print(text)


if __name__ == "__main__":
    main()
