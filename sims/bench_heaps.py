"""Benchmarks of the foundation: heap generation, rendering, parallel scaling.

    .venv/bin/python sims/bench_heaps.py render [--heaps FILE.jsonl] [--labeler-ref COMMIT]  # depth + label
                           # images/s at 640x480, rendered vs from-depth label images; DepthLabeler alone
    .venv/bin/python sims/bench_heaps.py scaling --heaps 60 --rounds 3  # 1 vs 2 workers, same seeds
    .venv/bin/python sims/bench_heaps.py summary FILE.jsonl  # validity and time of an `ms-drake heaps` run
    .venv/bin/python sims/bench_heaps.py reload FILE.jsonl [--count K]  # heaps reloaded into BinHeap15
    .venv/bin/python sims/bench_heaps.py compare --seeds 0:8 bullet polish drake  # heap engines, paired
    .venv/bin/python sims/bench_heaps.py station --seeds 0:8 bullet polish drake  # their heaps in BinHeap15, paired

Prints a table; the figures go to docs/BENCHMARKS.md by hand with the command.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

from ms_drake.cli import HEAP_TASKS_PER_CHILD, heap_job
from ms_drake.parallel import run_jobs
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import (
    SEARCH_HEAPS,
    HeapParams,
    generate_heap,
    heap_from_dict,
    scenario_with_heap,
    set_heap_poses,
    station_check,
)
from ms_drake.station import MakeStation, get_scene_graph
from ms_drake.station.labels import DepthLabeler

#: The heap configurations of docs/BENCHMARKS.md ("Heaps with Bullet"), by name.
CONFIGS = {
    "bullet": HeapParams(),  # the default: the drop in Bullet
    "polish": HeapParams(polish_time=0.5),  # Bullet, then at most 0.5 s in the Drake drop world (--polish 0.5)
    "drake": SEARCH_HEAPS,  # the Drake drop world (--engine drake), the search benchmarks' heaps
}


def bench_render(n: int = 40, rounds: int = 5, heaps_file: str | None = None, count: int = 8,
                 labeler_ref: str | None = None) -> None:
    """Depth + label pairs at 640x480 of the 15-object heap (seed 0), paired: the station's two
    VTK renders (MakeStation(label_images="render")) against one depth render + the label image
    computed from it (label_images="depth", ms_drake.perception.masks.DepthLabelImage), in
    `rounds` interleaved rounds of `n` pairs each, in this one process. Prints process CPU ms
    (llvmpipe's render threads included) and wall ms per image and per pair (medians over the
    rounds). Then `DepthLabeler.label` alone on that heap's depth image with 1 and 2 threads
    (and, with `labeler_ref` = a git commit, the DepthLabeler of ms_drake/perception/masks.py
    at that commit, e.g. 9855c8e for the OpenCV labeller), interleaved, 5 x 200 calls.
    With `heaps_file` (an `ms-drake heaps` JSONL) also the pixel agreement of the two label
    images on its first `count` heaps."""
    s = load_scenario(None, "BinHeap15")
    heap = generate_heap(s, 15, seed=0)
    rigs = {}
    for mode in ("render", "depth"):
        station = MakeStation(scenario_with_heap(s, heap), label_images=mode)
        ctx = station.CreateDefaultContext()
        set_heap_poses(station, ctx, heap)
        plant = station.GetSubsystemByName("plant")
        ports = station.GetOutputPort("overhead.depth_image"), station.GetOutputPort("overhead.label_image")
        ports[0].Eval(ctx), ports[1].Eval(ctx)  # warm-up (VTK start)
        rigs[mode] = (station, ctx, plant, plant.GetPositions(plant.GetMyContextFromRoot(ctx)).copy(), ports)
    res = {mode: [] for mode in rigs}
    for _ in range(rounds):
        for mode, (station, ctx, plant, q0, (depth, label)) in rigs.items():
            t = np.zeros((2, 2))  # [depth, label] x [cpu, wall]
            for k in range(n):
                q = q0.copy()
                q[4::7] += 1e-4 * (k % 7)  # move the objects so every frame is really rendered
                plant.SetPositions(plant.GetMyMutableContextFromRoot(ctx), q)
                for j, port in enumerate((depth, label)):
                    c, w = time.process_time(), time.perf_counter()
                    port.Eval(ctx)
                    t[j] += time.process_time() - c, time.perf_counter() - w
            res[mode].append(1e3 * t / n)
    print("| label image | depth ms CPU / wall | label ms CPU / wall | pair ms CPU / wall | pairs/s (images/s), wall |")
    print("| --- | --- | --- | --- | --- |")
    for mode, v in res.items():
        m = np.median(np.array(v), axis=0)
        pair = m.sum(axis=0)
        print(f"| {mode} | {m[0, 0]:.1f} / {m[0, 1]:.1f} | {m[1, 0]:.1f} / {m[1, 1]:.1f} | "
              f"{pair[0]:.1f} / {pair[1]:.1f} | {1e3 / pair[1]:.0f} ({2e3 / pair[1]:.0f}) |")
    _bench_labeler(*rigs["depth"][:2], labeler_ref)
    if heaps_file:
        recs = [json.loads(x) for x in Path(heaps_file).read_text().splitlines() if x.strip()][:count]
        for r in recs:
            h = heap_from_dict(r)
            station = MakeStation(scenario_with_heap(s, h), label_images="depth")
            ctx = station.CreateDefaultContext()
            set_heap_poses(station, ctx, h)
            ours = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
            sensor = station.GetSubsystemByName("rgbd_sensor_overhead")
            vtk = np.array(sensor.label_image_output_port().Eval(sensor.GetMyContextFromRoot(ctx)).data)[:, :, 0]
            renders = station.GetSubsystemByName("depth_label_overhead").renders
            print(f"| heap seed {r.get('seed', '?')} | {100 * (ours == vtk).mean():.4f} % pixels equal | "
                  f"{int((ours != vtk).sum())} differ | fallback renders {renders} |")


def _bench_labeler(station, ctx, labeler_ref: str | None, calls: int = 200, rounds: int = 5) -> None:
    """DepthLabeler.label alone (see bench_render)."""
    system = station.GetSubsystemByName("depth_label_overhead")
    sensor = station.GetSubsystemByName("rgbd_sensor_overhead")
    sg = get_scene_graph(station)
    qo = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data)[:, :, 0]
    X_WC = qo.GetPoseInWorld(sensor.default_parent_frame_id()) @ system._X_PC
    core = sensor.default_depth_render_camera().core()
    classes = {"": DepthLabeler}
    if labeler_ref:  # the module at that commit, loaded under another name
        src = subprocess.run(["git", "show", f"{labeler_ref}:ms_drake/perception/masks.py"], check=True,
                             capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1]).stdout
        old = sys.modules.setdefault("masks_" + labeler_ref, types.ModuleType("masks_" + labeler_ref))
        exec(compile(src, f"masks@{labeler_ref}", "exec"), old.__dict__)
        classes[f" @{labeler_ref}"] = old.DepthLabeler
    labelers = {f"{t} thread(s){tag}": cls(sg.model_inspector(), core.intrinsics(), core.renderer_name(), threads=t)
                for tag, cls in classes.items() for t in (1, 2)}
    poses = {g: qo.GetPoseInWorld(g) for g in system.labeler.geometry_ids}
    args = (depth, X_WC, poses, system._z_near, system._z_far)
    first = time.perf_counter()
    ref = system.labeler.label(*args)  # (the station's labeller ran already: compiled or loaded)
    first = time.perf_counter() - first
    times = {k: [] for k in labelers}
    for _ in range(rounds):
        for k, lab in labelers.items():
            assert np.array_equal(lab.label(*args), ref), k
            c, w = time.process_time(), time.perf_counter()
            for _ in range(calls):
                lab.label(*args)
            times[k].append((1e3 * (time.process_time() - c) / calls, 1e3 * (time.perf_counter() - w) / calls))
    print(f"\n| DepthLabeler.label alone, 640x480, {len(poses)} geometries | ms CPU / wall, median of "
          f"{rounds} x {calls} |")
    print("| --- | --- |")
    for k, v in times.items():
        m = np.median(np.array(v), axis=0)
        print(f"| {k} | {m[0]:.2f} / {m[1]:.2f} |")
    print(f"(one more call on the station's labeller: {1e3 * first:.1f} ms)\n")


def bench_scaling(heaps: int = 8, objects: int = 15, seed_start: int = 1000, rounds: int = 1) -> None:
    jobs = [(None, "BinHeap15", objects, k, None) for k in range(seed_start, seed_start + heaps)]
    res = {1: [], 2: []}
    for workers in (1, 2) * rounds:  # interleaved rounds: start-up and cache effects vary by seconds
        t = time.perf_counter()
        out = list(run_jobs(heap_job, jobs, workers=workers, max_tasks_per_child=HEAP_TASKS_PER_CHILD))
        res[workers].append(time.perf_counter() - t)
        rss = max(r.value["peak_rss_mb"] for r in out if r.ok)
        print(f"| {heaps} heaps of {objects}, {workers} worker(s) | {res[workers][-1]:.1f} s wall | "
              f"peak RSS per worker {rss:.0f} MB |", flush=True)
    m = {w: statistics.median(v) for w, v in res.items()}
    print(f"| speed-up 2 workers vs 1 (medians of {rounds} rounds) | {m[1] / m[2]:.2f}x |")


def summary(path: str) -> None:
    recs = [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()]
    n = len(recs)
    first = sum(1 for r in recs if r.get("attempts", 1) == 1)
    secs = [r["seconds"] for r in recs]
    cpu = [r.get("cpu_seconds", float("nan")) for r in recs]
    objs = [len(r["objects"]) for r in recs]
    removed = sum(len(r.get("removed", [])) for r in recs)
    rss = max(r.get("peak_rss_mb", 0) for r in recs)
    print(f"| heaps | {n} |")
    print(f"| valid at the first attempt | {first}/{n} = {100 * first / max(n, 1):.1f} % |")
    print(f"| wall s per heap (median, p90) | {statistics.median(secs):.2f}, {np.percentile(secs, 90):.2f} |")
    print(f"| CPU s per heap (median) | {statistics.median(cpu):.2f} |")
    print(f"| objects per heap (mean; removed for leaving the bin) | {np.mean(objs):.2f}; {removed} |")
    print(f"| simulated settle time s (median) | {statistics.median(r['settle_time'] for r in recs):.2f} |")
    print(f"| peak RSS of the worker | {rss:.0f} MB |")


def reload_check(path: str, count: int = 20) -> None:
    """Reload the first `count` heaps of an `ms-drake heaps` file into the BinHeap15 station (its
    own physics: compliant-hydroelastic objects), measure the deepest penetration at load and how far the
    objects move in 0.5 s of simulation (ms_drake.scenes.heaps.station_check)."""
    s = load_scenario(None, "BinHeap15")
    recs = [json.loads(x) for x in Path(path).read_text().splitlines() if x.strip()][:count]
    pen, mv, med = [], [], []
    for r in recs:
        c = station_check(s, heap_from_dict(r), seconds=0.5)
        pen.append(c["max_penetration"])
        mv.append(c["max_displacement"])
        med.append(c["median_displacement"])
    mm = lambda xs: 1e3 * np.asarray(xs)
    print(f"| heaps reloaded into BinHeap15 | {len(recs)} |")
    print(f"| max penetration at load, mm (median, p90, max) | {np.median(mm(pen)):.1f}, "
          f"{np.percentile(mm(pen), 90):.1f}, {mm(pen).max():.1f} |")
    print(f"| largest object displacement in 0.5 s, mm (median, p90, max) | {np.median(mm(mv)):.1f}, "
          f"{np.percentile(mm(mv), 90):.1f}, {mm(mv).max():.1f} |")
    print(f"| median object displacement in 0.5 s, mm (median over heaps) | {np.median(mm(med)):.1f} |")
    print(f"| heaps whose objects all move <= 5 mm | {sum(m <= 0.005 for m in mv)}/{len(mv)} |")


def compare(names: list[str], seeds: range) -> None:
    """Paired comparison of heap configurations (CONFIGS): for each seed every configuration in
    turn, in one process (CPU seconds drift with the machine's load; pairing keeps the
    comparison fair)."""
    s = load_scenario(None, "BinHeap15")
    params = {n: CONFIGS[n] for n in names}
    for p in params.values():
        generate_heap(s, 3, 999, params=p)  # warm caches
    res = {n: [] for n in names}
    for seed in seeds:
        for n, p in params.items():
            t = time.process_time()
            _, d = generate_heap(s, 15, seed, params=p, return_diagnostics=True)
            ph = d.phases
            res[n].append((time.process_time() - t, d.settle_time, d.attempts, ph.get("waves_cpu", 0),
                           ph.get("waves_sim", 0), ph.get("final_cpu", 0), ph.get("final_sim", 0)))
            print(n, seed, " ".join(f"{x:.2f}" for x in res[n][-1]), f"drop {ph.get('max_drop', 0):.2f}",
                  d.rejected_reasons, flush=True)
    print("| heaps | CPU s | settle s | first attempt | waves CPU s / sim s | final settle CPU s / sim s |")
    for n, v in res.items():
        med = [statistics.median(x[i] for x in v) for i in range(7)]
        print(f"| {n} | {med[0]:.2f} | {med[1]:.2f} | {sum(x[2] == 1 for x in v)}/{len(v)} | "
              f"{med[3]:.2f} / {med[4]:.2f} | {med[5]:.2f} / {med[6]:.2f} |")


def station_compare(names: list[str], seeds: range, seconds: float = 0.5) -> None:
    """Paired station check of heap configurations (CONFIGS): each seed's heap from every
    configuration, reloaded into BinHeap15 (ms_drake.scenes.heaps.station_check, `seconds` of the
    station's physics)."""
    s = load_scenario(None, "BinHeap15")
    res = {n: [] for n in names}
    for seed in seeds:
        for n in names:
            h = generate_heap(s, 15, seed, params=CONFIGS[n])
            c = station_check(s, h, seconds)
            res[n].append((c["max_penetration"], c["max_displacement"], c["median_displacement"]))
            print(n, seed, " ".join(f"{1e3 * x:.1f}" for x in res[n][-1]), flush=True)
    print("| heaps | penetration at load mm (median, max) | largest displacement mm (median, p90, max) | "
          "median object mm | heaps with all <= 5 mm |")
    for n, v in res.items():
        a = 1e3 * np.array(v)
        print(f"| {n} | {np.median(a[:, 0]):.1f}, {a[:, 0].max():.1f} | {np.median(a[:, 1]):.1f}, "
              f"{np.percentile(a[:, 1], 90):.1f}, {a[:, 1].max():.1f} | {np.median(a[:, 2]):.2f} | "
              f"{(a[:, 1] <= 5).sum()}/{len(a)} |")


if __name__ == "__main__":
    cmd = sys.argv[1] if len(sys.argv) > 1 else "render"
    if cmd == "render":
        bench_render(heaps_file=sys.argv[sys.argv.index("--heaps") + 1] if "--heaps" in sys.argv else None,
                     labeler_ref=sys.argv[sys.argv.index("--labeler-ref") + 1] if "--labeler-ref" in sys.argv else None)
    elif cmd == "scaling":
        k = int(sys.argv[sys.argv.index("--heaps") + 1]) if "--heaps" in sys.argv else 8
        bench_scaling(k, rounds=int(sys.argv[sys.argv.index("--rounds") + 1]) if "--rounds" in sys.argv else 1)
    elif cmd == "summary":
        summary(sys.argv[2])
    elif cmd == "compare":
        lo, hi = (sys.argv[sys.argv.index("--seeds") + 1] if "--seeds" in sys.argv else "0:10").split(":")
        compare([a for a in sys.argv[2:] if a in CONFIGS], range(int(lo), int(hi)))
    elif cmd == "station":
        lo, hi = (sys.argv[sys.argv.index("--seeds") + 1] if "--seeds" in sys.argv else "0:6").split(":")
        station_compare([a for a in sys.argv[2:] if a in CONFIGS], range(int(lo), int(hi)))
    elif cmd == "reload":
        reload_check(sys.argv[2], int(sys.argv[sys.argv.index("--count") + 1]) if "--count" in sys.argv else 20)
    else:
        raise SystemExit(__doc__)
