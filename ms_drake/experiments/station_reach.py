"""Station reach: which of the grasps the primitive mode plans on a bin heap a station's robot
executes (`sims/station_reach.py` runs it over many heaps).

The grasps: at the heap's initial state, every object the overhead camera sees (>= 20 pixels of
its label) gets its best grasp per gripper kind from the IndexedGraspPlanner without a reach
filter (the primitive mode's grasp-set planner: the best-quality candidate whose gripper is free
of the objects and the bin) -- the grasps the selector chooses from at the first step. Each is
then checked against each station's robot by PickReach (the FullBackend's pick plan from park:
IK of the pre-grasp within the joint limits and 5 mm clear of the bin and the robot, the straight
approach and lift; the arm's links clear of the objects along the approach, links and tool 2 cm
clear along the transit from park) and, when missed, diagnosed (PickReach.diagnose: unreachable /
joint limits / collision with which bodies / arm against which object).

One record per heap: seed, and per station the grasps with kind, object, position, approach,
quality and the diagnosis. `summarize` gives the reached share per station and gripper kind with
Wilson 95 % intervals; `draw_miss` the overhead RGB image with a missed grasp drawn.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from ms_drake.execution.reach import PickReach
from ms_drake.experiments.fidelity import wilson as fidelity_wilson
from ms_drake.scenes.layouts import HeapConfig, cached_heap
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.grasping.grasp_sets import load_grasp_set
from ms_drake.grasping.indexed import IndexedGraspPlanner, environment_parts
from ms_drake.grasping.meshes import object_mesh
from ms_drake.objects import get_object
from ms_drake.perception.masks import object_labels
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.types import Grasp, ObjectGeometry

KIND_LABEL = {"parallel_jaw": "jaw", "suction": "suction"}


def heap_view(heap, camera: str = "overhead", min_pixels: int = 20) -> dict:
    """The heap in BinHeap15's bin (no robot): {"rgb": (H, W, 3) uint8, "camera": PinholeCamera,
    "objects": tuple[ObjectGeometry], "names": id -> full name, "visible": [ids]} (visible: at
    least min_pixels of the object's label in the camera's label image)."""
    s = scenario_with_heap(load_scenario(None, "BinHeap15"), heap)
    station = MakeStation(s, target_index=heap.target_index)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, heap)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(ctx)
    rgb = np.array(station.GetOutputPort(f"{camera}.rgb_image").Eval(ctx).data)[..., :3].astype(np.uint8)
    labels = np.array(station.GetOutputPort(f"{camera}.label_image").Eval(ctx).data)[..., 0]
    counts = dict(zip(*np.unique(labels, return_counts=True)))
    objects, names, visible = [], {}, []
    label_of = object_labels(plant)
    for o in station_objects(plant):
        mesh = object_mesh(o.full_name)
        X = plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)).GetAsMatrix4()
        objects.append(ObjectGeometry(o.model_name, np.asarray(mesh.vertices, float), np.asarray(mesh.faces), X,
                                      get_object(o.full_name).mass))
        names[o.model_name] = o.full_name
    visible = [oid for lab, oid in label_of.items() if counts.get(lab, 0) >= min_pixels]
    return {"rgb": rgb, "camera": PinholeCamera.from_config(s.cameras[camera]), "objects": tuple(objects),
            "names": names, "visible": sorted(visible), "scenario": s}


def planned_grasps(view: dict, kinds=("parallel_jaw", "suction")):
    """(grasps, scene): the best free grasp per kind of every visible object (module docstring)
    and the planner's coal Scene of the objects and the bin."""
    s = view["scenario"]
    names = view["names"]
    sets = {oid: gs for oid, name in names.items() if (gs := load_grasp_set(name)) is not None}
    cam = s.cameras["overhead"]
    planner = IndexedGraspPlanner(names, sets, environment_parts(s), Workspace.from_scenario(s), cam.width,
                                  cam.height, kinds=kinds, jaw_model=next((g.model for g in sets.values()), ""))
    geoms = {o.id: o for o in view["objects"]}
    scene = planner.scene(view["objects"])
    grasps = [g for oid in view["visible"] for g in planner.plan_object(oid, geoms, scene)]
    scene.owners = ["bin"] * len(planner.environment) + [o.id for o in view["objects"]
                                                         for _ in planner._parts_of(o)]
    return grasps, scene


def grasp_record(g: Grasp) -> dict:
    return {"kind": g.kind, "object": g.object_id, "quality": round(float(g.quality), 4),
            "center": [round(float(v), 4) for v in g.center], "approach": [round(float(v), 4) for v in g.approach],
            "axis": [round(float(v), 4) for v in g.axis], "width": round(float(g.width), 4),
            "tilt_deg": round(float(np.degrees(np.arccos(np.clip(-g.approach[2] / np.linalg.norm(g.approach),
                                                                   -1, 1)))), 1)}


def record_grasp(r: dict) -> Grasp:
    return Grasp(kind=r["kind"], center=tuple(r["center"]), approach=tuple(r["approach"]), axis=tuple(r["axis"]),
                 width=r["width"], quality=r["quality"], object_id=r["object"])


def heap_reach(heap, reaches: dict, view: dict | None = None) -> dict:
    """One heap's record: {"seed", "grasps": [grasp_record], "stations": {name: [diagnosis per
    grasp, None for a kind the robot has no gripper of]}, "cpu_s"}. reaches: station name ->
    PickReach."""
    t0 = time.process_time()
    view = view or heap_view(heap)
    kinds = sorted({k for r in reaches.values() for k in r.backend.grasp_kinds})
    grasps, scene = planned_grasps(view, kinds)
    out = {"seed": int(heap.seed), "objects": len(heap.objects), "visible": len(view["visible"]),
           "grasps": [grasp_record(g) for g in grasps], "stations": {}}
    for name, reach in reaches.items():
        have = reach.backend.grasp_kinds
        diags = [reach.diagnose(g, scene) if g.kind in have else None for g in grasps]
        for d in diags:  # name the scene part an arm hit: "transit:<link> x <bin | object id>"
            if d is not None and d["reason"] == "arm_hits_scene" and ">" in d["detail"]:
                link, j = d["detail"].rsplit(">", 1)
                d["detail"] = f"{link} x {scene.owners[int(j)]}"
        out["stations"][name] = diags
    out["cpu_s"] = round(time.process_time() - t0, 2)
    return out


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson score 95 % interval of k successes in n trials, clipped to [0, 1]."""
    lo, hi = fidelity_wilson(k, n)
    return (max(0.0, lo), min(1.0, hi))


def summarize(records: list[dict]) -> dict:
    """{station: {kind: {"reached", "of", "share", "ci", "reasons": {reason: count},
    "reached_but_transit", "share_but_transit"}}}. reached_but_transit: also counting the grasps
    missed only by the transit check (the pick plan exists; the arm or tool passes within the
    transit clearance of an object on the joint-space move from park; their approach is not
    checked, so it is an upper bound of the reach without that check)."""
    out = {}
    for rec in records:
        for name, diags in rec["stations"].items():
            for g, d in zip(rec["grasps"], diags):
                if d is None:
                    continue
                s = out.setdefault(name, {}).setdefault(g["kind"], {"reached": 0, "of": 0, "reasons": {},
                                                                     "reached_but_transit": 0})
                s["of"] += 1
                s["reached"] += d["reason"] == "ok"
                s["reached_but_transit"] += d["reason"] == "ok" or (d["reason"] == "arm_hits_scene"
                                                                     and d["step"] == "transit")
                key = d["reason"] if d["reason"] in ("ok",) else f"{d['reason']}@{d['step']}"
                s["reasons"][key] = s["reasons"].get(key, 0) + 1
    for kinds in out.values():
        for s in kinds.values():
            s["share"] = s["reached"] / s["of"] if s["of"] else float("nan")
            s["ci"] = wilson(s["reached"], s["of"])
            s["share_but_transit"] = s["reached_but_transit"] / s["of"] if s["of"] else float("nan")
    return out


def format_summary(summary: dict, heaps: int) -> str:
    lines = [f"station reach on {heaps} heaps (the best grasp per gripper kind of every visible object):",
             "| station | gripper | reached | share [95 % CI] | without the transit check | misses by reason |",
             "|---|---|---|---|---|---|"]
    for name, kinds in summary.items():
        for kind, s in sorted(kinds.items()):
            misses = ", ".join(f"{k} {v}" for k, v in sorted(s["reasons"].items(), key=lambda kv: -kv[1]) if k != "ok")
            lines.append(f"| {name} | {KIND_LABEL.get(kind, kind)} | {s['reached']}/{s['of']} | "
                         f"{100 * s['share']:.1f} % [{100 * s['ci'][0]:.1f}, {100 * s['ci'][1]:.1f}] | "
                         f"{100 * s['share_but_transit']:.1f} % | "
                         f"{misses or '-'} |")
    return "\n".join(lines)


def read_records(path) -> list[dict]:
    p = Path(path)
    if not p.exists():
        return []
    out = []
    for line in p.read_text().splitlines():
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by an interrupted run: redone
                pass
    return out


def make_reaches(scenarios: list[str], scenario_file: str | None = None, seed: int = 0) -> dict:
    """{name: PickReach} of the named bin stations (errors name the scenario)."""
    out = {}
    for name in scenarios:
        s = load_scenario(scenario_file, name)
        if s.environment.type != "bin" or not s.robot.name or s.robot.name == "floating":
            raise ValueError(f"station reach: scenario {name!r} is not a bin station with an arm "
                             f"(environment {s.environment.type!r}, robot {s.robot.name!r}); use YuMiBin or PandaBin")
        out[name] = PickReach(s, seed=seed)
    return out


def run_station_reach(scenarios: list[str], heaps: int, seed_start: int, out: str, scenario_file: str | None = None,
                      objects: int = 15, heap_dir: str | None = None, progress=print, misses_dir: str | None = None,
                      max_pictures: int = 6) -> list[dict]:
    """Measure heaps seed_start .. seed_start + heaps - 1 (resumable: seeds already in `out` are
    kept), append one JSON line per heap to `out`, draw up to max_pictures misses per station into
    misses_dir. Returns the records of the requested seeds."""
    if heaps < 1:
        raise ValueError(f"station reach: heaps must be >= 1, got {heaps}")
    reaches = make_reaches(scenarios, scenario_file)
    done = {r["seed"]: r for r in read_records(out) if set(scenarios) <= set(r["stations"])}
    seeds = [seed_start + i for i in range(heaps)]
    todo = [s for s in seeds if s not in done]
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    drawn = {n: 0 for n in scenarios}
    t_start = time.time()
    for i, seed in enumerate(todo):
        heap = cached_heap(HeapConfig("bin_set", objects), seed, heap_dir)
        view = heap_view(heap)
        rec = heap_reach(heap, reaches, view)
        with open(out, "a") as f:
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())
        done[seed] = rec
        if misses_dir:
            for name, diags in rec["stations"].items():
                for g, d in zip(rec["grasps"], diags):
                    if d is not None and d["reason"] != "ok" and drawn[name] < max_pictures:
                        draw_miss(view, g, d, Path(misses_dir) / f"{name}_s{seed}_{g['object']}_{g['kind']}.png",
                                  f"{name} seed {seed}")
                        drawn[name] += 1
        el = time.time() - t_start
        eta = el / (i + 1) * (len(todo) - i - 1)
        hits = {n: sum(d is not None and d["reason"] == "ok" for d in rec["stations"][n]) for n in scenarios}
        tot = {n: sum(d is not None for d in rec["stations"][n]) for n in scenarios}
        progress(f"[{sum(s in done for s in seeds)}/{len(seeds)}]"
                 f" seed {seed}: " + ", ".join(f"{n} {hits[n]}/{tot[n]}" for n in scenarios)
                 + f"  {rec['cpu_s']:.1f} CPU-s, elapsed {el / 60:.1f} min, ETA {eta / 60:.1f} min")
    return [done[s] for s in seeds]


def draw_miss(view: dict, g: dict, diag: dict, path, title: str = "") -> Path:
    """The overhead RGB image with the grasp drawn (the grasp point, its approach projected, a jaw's
    axis) and the reason, as a PNG at `path`."""
    matplotlib.use("Agg")
    cam = view["camera"]
    c = np.asarray(g["center"], float)
    a = np.asarray(g["approach"], float)
    pts = np.array([c, c - 0.08 * a])  # the grasp and where the tool comes from
    uv, _ = cam.project(pts)
    fig, ax = plt.subplots(figsize=(6.4, 5.2), dpi=80)
    ax.imshow(view["rgb"])
    ax.plot(*uv[0], "o", color="red", ms=8, mfc="none", mew=2)
    ax.annotate("", xy=uv[0], xytext=uv[1], arrowprops={"arrowstyle": "->", "color": "red", "lw": 2})
    if g["kind"] == "parallel_jaw":
        ax_ = np.asarray(g["axis"], float)
        w = 0.5 * max(g["width"], 0.02)
        e, _ = cam.project(np.array([c - w * ax_, c + w * ax_]))
        ax.plot(e[:, 0], e[:, 1], "-", color="yellow", lw=3)
    reason = diag["reason"] + (f" at {diag['step']}" if diag.get("step") else "")
    ax.set_title(f"{title} (robot on the left): {KIND_LABEL.get(g['kind'], g['kind'])} grasp on {g['object']}, tilt {g['tilt_deg']:.0f} deg"
                 f"\n{reason}: {diag.get('detail', '')}", fontsize=9)
    ax.set_axis_off()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)



def draw_examples(records: list[dict], out_dir, objects: int = 15, heap_dir: str | None = None) -> list[Path]:
    """One picture (draw_miss) per station, gripper kind and miss reason: the first such miss in
    `records` (seed order)."""
    seen, paths, views = set(), [], {}
    for rec in sorted(records, key=lambda r: r["seed"]):
        for name, diags in rec["stations"].items():
            for g, d in zip(rec["grasps"], diags):
                if d is None or d["reason"] == "ok" or (name, g["kind"], d["reason"]) in seen:
                    continue
                seen.add((name, g["kind"], d["reason"]))
                if rec["seed"] not in views:
                    views[rec["seed"]] = heap_view(cached_heap(HeapConfig("bin_set", objects), rec["seed"], heap_dir))
                paths.append(draw_miss(views[rec["seed"]], g, d, Path(out_dir) / (
                    f"{name}_{KIND_LABEL.get(g['kind'], g['kind'])}_{d['reason']}_s{rec['seed']}.png"),
                    f"{name} seed {rec['seed']}"))
    return paths
