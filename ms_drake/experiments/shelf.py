"""Shelf search in FOSS (Table 9.1) and shelf datasets.

- `build_shelf_search(foss, scene, policy)`: the wired Diagram FossSystem -> ShelfOccupancyEstimator
  ("ground_truth") -> ShelfPolicySelector -> back to FossSystem, stepping once per period; with
  perception="learned" the estimator reads the depth image of a ShelfDepthCamera on FossSystem's
  scene (a Drake render of every state) instead of the scene; with perception="depth" the policy
  also sees only what the ShelfSegmenter makes of that render (objects estimated from the depth
  image, the target's colour left out; AssociateShelfObjects names them after the true objects so
  FOSS can apply the actions) instead of FOSS's idealised segmentation.
- `shelf_rollout(policy, occluders, seed)`: one search of the scene generate_shelf_scene(seed,
  occluders) (the same scene for every policy) with horizon H = 2n; a JSON-able record: seed,
  occluders, policy, perception (one of PERCEPTIONS), success, steps, push / suction counts, refused actions, the failure
  ("horizon": budget spent; "no_action": the policy had nothing to do), timings (scene generation,
  perception, decision and FOSS step, ms).
- `run_shelf_bench(...)`: the missing rollouts of (occluders x seeds) through ms_drake.parallel,
  one JSON line each, flushed and fsync'ed (resumable: the same command skips the seeds already in
  the file and retries the lines of dead workers), then per-density summaries
  (ms_drake.experiments.harness.summarize: success rate with a bootstrap 95 % interval; steps are
  also stored as `actions` and occluders as `objects` for it).
- `shelf_table`, `plot_shelf`: Table 9.1 (success %, median steps (IQR) of the successful
  searches) and a figure.
- `write_shelf_dataset(...)`: `ms-drake data shelf`: shards of generated scenes with both
  ground-truth distributions, the 1D ground truth of all three target sizes, and (optionally) the
  Drake depth image (block-averaged with --depth-block), resumable shard by shard.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.errors import MsDrakeError
from ms_drake.experiments.figures import figure_dir, save_png
from ms_drake.experiments.harness import summarize
from ms_drake.experiments.records import read_record_file
from ms_drake.experiments.shelf_segmentation import AssociateShelfObjects
from ms_drake.foss import Foss, FossParams, FossSystem
from ms_drake.parallel import run_jobs, run_shard_jobs
from ms_drake.paths import code_version
from ms_drake.perception.shelf_occupancy import ShelfOccupancyEstimator
from ms_drake.perception.shelf_occupancy_net import block_depth
from ms_drake.perception.shelf_segmentation import ShelfSegmenter
from ms_drake.policies.shelf import (
    SHELF_POLICIES,
    ShelfPolicyParams,
    ShelfPolicySelector,
    oracle_last_stage_seconds,
)
from ms_drake.policies.shelf_search import SHELF_PERCEPTIONS, ShelfSearchConfig
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import (
    DEFAULT_TARGET,
    TARGET_SIZES,
    ShelfSceneParams,
    generate_shelf_scene,
    scene_to_dict,
)
from ms_drake.scenes.shelf_render import ShelfDepthCamera, render_shelf_scene
from ms_drake.shelf_geometry import Prisms, ShelfGeometry, hidden_placements
from ms_drake.types import ShelfScene

SCENARIO = "FetchShelf"
FIDELITY = "foss"
#: What the policies observe: FOSS's scene and the analytic occupancy; the learned occupancy of a
#: depth render; the learned occupancy and the ShelfSegmenter's objects of that render.
PERCEPTIONS = SHELF_PERCEPTIONS
REFERENCE = {  # the reference's Table 9.1, "All" row: success rate (%)
    "oracle_p": 98, "oracle_ps": 100, "dar": 54, "der3": 60, "bluction_dar": 86}
POLICY_NAMES = {"oracle_p": "Oracle-P", "oracle_ps": "Oracle-P+S", "dar": "DAR", "der3": "DER-3",
                "bluction_dar": "Bluction-DAR", "random": "Random"}


@functools.lru_cache(maxsize=4)
def shelf_geometry(scenario_name: str = SCENARIO, camera: str = "front") -> ShelfGeometry:
    return ShelfGeometry.from_scenario(load_scenario(None, scenario_name), camera)


def build_shelf_search(foss: Foss, scene: ShelfScene, policy: str, params: ShelfPolicyParams | None = None,
                       target_size=None, period: float = 1.0, perception: str = "ground_truth",
                       scenario_name: str = SCENARIO):
    """The search Diagram; exported outputs: action, visible_fraction, scene, history, occupancy,
    occupancy_history."""
    if perception not in PERCEPTIONS:
        raise MsDrakeError(f"perception {perception!r}: choose one of {', '.join(PERCEPTIONS)}")
    builder = DiagramBuilder()
    sim = builder.AddNamedSystem("foss", FossSystem(foss, scene, period))
    backend = "ground_truth" if perception == "ground_truth" else "learned"
    est = builder.AddNamedSystem("occupancy", ShelfOccupancyEstimator(foss.geometry, target_size, backend))
    sel = builder.AddNamedSystem("policy", ShelfPolicySelector(policy, foss, params, period))
    builder.Connect(sim.GetOutputPort("scene"), est.GetInputPort("scene"))
    observed = sim.GetOutputPort("scene")
    if perception != "ground_truth":
        cam = builder.AddNamedSystem("camera", ShelfDepthCamera(load_scenario(None, scenario_name)))
        builder.Connect(sim.GetOutputPort("scene"), cam.GetInputPort("scene"))
        builder.Connect(cam.GetOutputPort("depth_image"), est.GetInputPort("depth_image"))
    if perception == "depth":
        seg = builder.AddNamedSystem("segmenter", ShelfSegmenter(foss.geometry))
        builder.Connect(cam.GetOutputPort("depth_image"), seg.GetInputPort("depth_image"))
        builder.Connect(cam.GetOutputPort("rgb_image"), seg.GetInputPort("rgb_image"))
        names = builder.AddNamedSystem("associate", AssociateShelfObjects())
        builder.Connect(seg.GetOutputPort("scene"), names.GetInputPort("estimate"))
        builder.Connect(sim.GetOutputPort("scene"), names.GetInputPort("scene"))
        observed = names.GetOutputPort("scene")
    builder.Connect(observed, sel.GetInputPort("scene"))
    builder.Connect(sim.GetOutputPort("history"), sel.GetInputPort("history"))
    builder.Connect(est.GetOutputPort("occupancy"), sel.GetInputPort("occupancy"))
    builder.Connect(sel.GetOutputPort("action"), sim.GetInputPort("action"))
    for system, port in ((sel, "action"), (sim, "visible_fraction"), (sim, "scene"), (sim, "history"),
                         (est, "occupancy"), (sel, "occupancy_history")):
        builder.ExportOutput(system.GetOutputPort(port), port)
    diagram = builder.Build()
    diagram.set_name(f"shelf_search_{policy}")
    return diagram


def station_label(scenario_name: str, scenario_file=None) -> str:
    """How a record names its station: the scenario's name (of diagrams/scenarios.yaml), else
    "FILE:NAME"."""
    return scenario_name if scenario_file is None else f"{scenario_file}:{scenario_name}"


def record_scenario(rec: dict) -> str:
    """The station a shelf record (physics or FOSS) was run on: its scenario name (records written
    before scenarios were recorded ran on FetchShelf)."""
    return rec.get("scenario", SCENARIO)


def shelf_rollout(config: ShelfSearchConfig, occluders: int, seed: int, target_size=DEFAULT_TARGET,
                  scenario_name: str = SCENARIO) -> dict:
    """One search in FOSS (module docstring) with `config`'s policy, perception, horizon, cost ratio,
    oracle budget and ablation switches (its seed set to `seed`; FOSS places exactly, so the robot's
    min_move / nil_move / revisit rules are off); the record of it."""
    policy = config.policy
    params = ShelfPolicyParams(seed=seed, horizon=config.horizon, psi=config.psi,
                               oracle_exhaustive_seconds=config.oracle_seconds,
                               oracle_push_target=config.ablation.oracle_push_target)
    perception, suction_lift = config.perception, config.ablation.suction_lift
    t_start, cpu_start = time.perf_counter(), time.process_time()
    geometry = shelf_geometry(scenario_name)
    foss = Foss(geometry, FossParams.for_suction_lift(suction_lift))
    t = time.process_time()
    sample = generate_shelf_scene(geometry, seed, occluders, target_size)
    scene_ms = 1e3 * (time.process_time() - t)
    diagram = build_shelf_search(foss, sample.scene, policy, params, target_size, perception=perception,
                                 scenario_name=scenario_name)
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    period = diagram.GetSubsystemByName("foss").period
    horizon = params.horizon if params.horizon is not None else 2 * occluders
    ports = {name: diagram.GetOutputPort(name) for name in ("action", "visible_fraction", "scene", "history",
                                                             "occupancy")}
    perceive, decisions, steps_ms = [], [], []
    failure, reason, steps = "", "", 0
    while True:
        visible = float(ports["visible_fraction"].Eval(context)[0])
        if visible >= foss.params.visibility_threshold:
            break
        if steps >= horizon:
            failure = "horizon"
            break
        t = time.process_time()
        ports["occupancy"].Eval(context)
        t1 = time.process_time()
        action = ports["action"].Eval(context)
        t2 = time.process_time()
        perceive.append(t1 - t)
        decisions.append(t2 - t1)
        if action.kind != "shelf":
            failure, reason = "no_action", action.reason
            break
        scene = ports["scene"].Eval(context)
        t = time.process_time()
        foss.step(scene, action)  # timed alone; the simulator applies it below
        steps_ms.append(time.process_time() - t)
        steps += 1
        simulator.AdvanceTo((steps + 0.5) * period)  # past the update at steps * period
    history = ports["history"].Eval(context)
    done = [o for o in history if o.success]
    kinds = [o.action.shelf.kind for o in done]

    def ms(x, f):
        return float(1e3 * f(x)) if x else float("nan")

    return dict(seed=int(seed), occluders=int(occluders), objects=int(occluders), policy=policy, fidelity=FIDELITY,
                perception=perception, scenario=scenario_name, config=config.record(),
                success=not failure, steps=steps, actions=steps, pushes=kinds.count("push"),
                suctions=kinds.count("suction"), refused=len(history) - len(done),
                cost=kinds.count("push") + params.psi * kinds.count("suction"), failure=failure, stop_reason=reason,
                visible_fraction=float(ports["visible_fraction"].Eval(context)[0]),
                target_size=list(map(float, target_size)), scene_ms=scene_ms,
                perception_ms=ms(perceive, np.median), decision_ms=ms(decisions, np.median),
                decision_ms_max=ms(decisions, np.max), foss_ms=ms(steps_ms, np.median),
                seconds=time.perf_counter() - t_start, cpu_seconds=time.process_time() - cpu_start, pid=os.getpid(),
                code=code_version())


def shelf_rollout_job(job: tuple) -> dict:
    """(ShelfSearchConfig as a dict, occluders, seed, scenario name) -> record; module-level for the
    worker pool."""
    config, occluders, seed, scenario_name = job
    return shelf_rollout(ShelfSearchConfig(**config), occluders, seed, scenario_name=scenario_name)


def _config_key(config: dict) -> str:
    return json.dumps(config, sort_keys=True)


def read_shelf_records(path) -> list[dict]:
    """The records of a `bench shelf` file a run appends to (a missing file has none); each keeps its
    config, else one error names the file and line."""
    return read_record_file(path, ("seed", "config"), writer="bench shelf", resume=True)


def final_shelf_records(recs: list[dict]) -> list[dict]:
    """The last record per (config, occluders, seed): a retried search replaces its failure; other
    settings in the same file stay apart."""
    out = {}
    for r in recs:
        out[(_config_key(r["config"]), record_scenario(r), r.get("objects"), int(r["seed"]))] = r
    return list(out.values())


def run_shelf_bench(config: ShelfSearchConfig, occluders: list[int], scenes: int, seed_start: int, out,
                    workers: int = 1, use_ray: bool = False, ray_address: str | None = None, progress=None,
                    scenario_name: str = SCENARIO) -> dict:
    """Run the missing rollouts of `config` on seeds S..S+K-1 for every occluder count in the shelf of
    the scenario `scenario_name`, append them to `out` (JSON lines; a record of another config or
    station is not one of them); returns {occluders or "all": summary} over the requested seeds.
    progress(rec) after each search; an object with a `start(done, todo)` method hears first how
    many are already done."""
    bad = [n for n in occluders if not 2 <= n <= 12]
    if bad:
        raise MsDrakeError(f"--occluders {' '.join(map(str, bad))}: shelf scenes have 2 to 12 occluders")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    key = _config_key(config.record())
    mine = [r for r in final_shelf_records(read_shelf_records(out))
            if r.get("fidelity") == FIDELITY and _config_key(r["config"]) == key and record_scenario(r) == scenario_name]
    done = {(int(r["objects"]), int(r["seed"])) for r in mine if r.get("failure") != "worker_died"}
    seeds = range(seed_start, seed_start + scenes)
    jobs = [(dataclasses.asdict(config), n, s, scenario_name) for n in occluders for s in seeds if (n, s) not in done]
    if progress is not None and hasattr(progress, "start"):  # before any search: (already done, to run)
        progress.start(len(occluders) * len(seeds) - len(jobs), len(jobs))
    with open(out, "a") as f:
        for r in run_jobs(shelf_rollout_job, jobs, workers=workers, use_ray=use_ray, ray_address=ray_address):
            if r.ok:
                rec = r.value
            else:
                err = (r.error or "").strip().splitlines()
                rec = dict(seed=r.job[2], occluders=r.job[1], objects=r.job[1], policy=config.policy,
                           fidelity=FIDELITY, perception=config.perception, scenario=scenario_name,
                           config=config.record(), success=False,
                           steps=0, actions=0, failure="worker_died", error=err[-1] if err else "")
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())
            if progress is not None:
                progress(rec)
    recs = [r for r in final_shelf_records(read_shelf_records(out))
            if r.get("fidelity") == FIDELITY and _config_key(r["config"]) == key and int(r["seed"]) in seeds
            and int(r["objects"]) in occluders and record_scenario(r) == scenario_name]
    summary = {n: summarize([r for r in recs if int(r["objects"]) == n]) for n in occluders}
    summary["all"] = summarize(recs)
    summary["resumed"] = sum(1 for n in occluders for s in seeds if (n, s) in done)
    return summary


def shelf_records(files) -> list[dict]:
    out = []
    for f in files:
        out += [r for r in final_shelf_records(read_record_file(Path(f), ("seed", "config"), writer="bench shelf"))
                if r.get("fidelity") == FIDELITY]
    return out


def _cell(recs: list[dict]) -> tuple[str, str]:
    if not recs:
        return "-", "-"
    s = summarize(recs)
    q = s["success_quartiles"]
    rate = f"{100 * s['success_rate']:.0f} % [{100 * s['success_ci'][0]:.0f}, {100 * s['success_ci'][1]:.0f}]"
    steps = f"{q[1]:.1f} ({q[0]:.1f} - {q[2]:.1f})" if np.isfinite(q[1]) else "-"
    return rate, steps


def _column_key(r: dict) -> tuple[str, float, str, bool, str]:
    c = r["config"]
    return (c["policy"], float(c["oracle_seconds"]), c["ablation"]["suction_lift"],
            bool(c["ablation"]["oracle_push_target"]), record_scenario(r))


def _columns(recs: list[dict], policies) -> list[tuple[str, float, str, bool, str]]:
    """The table's columns present in `recs`: (policy, the budget of the oracle's last stage, the
    suction lift rule, whether the oracle pushes the target, the station), the default station
    first, then in policy order, an oracle's default budget, the default lift and the target left
    where it is first."""
    keys = {_column_key(r) for r in recs}
    return sorted((k for k in keys if k[0] in policies),
                  key=lambda k: (k[4] != SCENARIO, k[4], k[2] != "over", list(policies).index(k[0]), k[3],
                                 k[1] != oracle_last_stage_seconds(k[0]), k[1]))


def _column_name(key: tuple[str, float, str, bool, str]) -> str:
    p, last, lift, push_target, station = key
    name = POLICY_NAMES.get(p, p)
    if p in ("oracle_p", "oracle_ps") and last != oracle_last_stage_seconds(p):
        stage = "exhaustive" if p == "oracle_p" else "wide"
        name += f" ({stage} search {last:g} s)" if last else " (staged search only)"
    return (name + (", target pushed" if push_target else "") + (f", suction lift {lift}" if lift != "over" else "")
            + (f", {station}" if station != SCENARIO else ""))


def _in_column(r: dict, key: tuple[str, float, str, bool, str]) -> bool:
    return _column_key(r) == key


def shelf_table(recs: list[dict], policies=SHELF_POLICIES) -> str:
    """Table 9.1 as markdown: per density and overall, success % [bootstrap 95 % CI] and the median
    steps (IQR) of the successful searches, one column per policy present (Oracle-P with the
    exhaustive push search in a column of its own)."""
    present = _columns(recs, policies)
    densities = sorted({int(r["objects"]) for r in recs})
    head = "| occluders | metric | " + " | ".join(_column_name(k) for k in present) + " |"
    lines = [head, "|" + "---|" * (2 + len(present))]
    for n in densities + ["All"]:
        cells = [_cell([r for r in recs if _in_column(r, k) and (n == "All" or int(r["objects"]) == n)])
                 for k in present]
        count = max((sum(1 for r in recs if _in_column(r, k) and (n == "All" or int(r["objects"]) == n))
                     for k in present), default=0)
        lines.append(f"| {n} ({count}) | success | " + " | ".join(c[0] for c in cells) + " |")
        lines.append(f"| {n} | median steps (IQR) | " + " | ".join(c[1] for c in cells) + " |")
    lines.append("| All | reference success | " + " | ".join(
        f"{REFERENCE[k[0]]} %" if k[0] in REFERENCE else "-" for k in present) + " |")
    return "\n".join(lines)


def plot_shelf(recs: list[dict], out_dir) -> Path:
    """Success rate (with bootstrap 95 % intervals) and median steps against the occluder count."""
    out_dir = figure_dir(out_dir)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    for key in _columns(recs, SHELF_POLICIES):
        mine = [r for r in recs if _in_column(r, key)]
        ns = sorted({int(r["objects"]) for r in mine})
        ss = [summarize([r for r in mine if int(r["objects"]) == n]) for n in ns]
        rate = np.array([100 * s["success_rate"] for s in ss])
        ci = np.array([[100 * s["success_ci"][0], 100 * s["success_ci"][1]] for s in ss])
        a1.errorbar(ns, rate, yerr=[rate - ci[:, 0], ci[:, 1] - rate], marker="o", capsize=3,
                    label=_column_name(key))
        q = np.array([s["success_quartiles"] for s in ss])
        a2.errorbar(ns, q[:, 1], yerr=[q[:, 1] - q[:, 0], q[:, 2] - q[:, 1]], marker="o", capsize=3,
                    label=_column_name(key))
    a1.set_xlabel("occluders")
    a1.set_ylabel("success rate (%)")
    a1.set_title("Shelf search in FOSS (cf. Table 9.1)")
    a2.set_xlabel("occluders")
    a2.set_ylabel("steps of successful searches (median, IQR)")
    a1.legend(fontsize=7)
    return save_png(fig, out_dir / "shelf_table91.png")


def bench_shelf_scenes(count: int, seed_start: int = 0, target_size=DEFAULT_TARGET) -> dict:
    """CPU time of generate_shelf_scene on seeds S..S+count-1 (occluder counts drawn from the seed):
    median / p90 / max ms, and the median per occluder count."""
    geometry = shelf_geometry(SCENARIO)
    ms, counts, tries = [], [], []
    for seed in range(seed_start, seed_start + count):
        t = time.process_time()
        sample = generate_shelf_scene(geometry, seed, None, target_size)
        ms.append(1e3 * (time.process_time() - t))
        counts.append(len(sample.scene.objects))
        tries.append(sample.tries)
    ms, counts = np.array(ms), np.array(counts)
    return dict(scenes=count, median_ms=float(np.median(ms)), p90_ms=float(np.percentile(ms, 90)),
                max_ms=float(ms.max()), mean_tries=float(np.mean(tries)),
                median_ms_by_occluders={int(n): float(np.median(ms[counts == n])) for n in np.unique(counts)})


# -- datasets -----------------------------------------------------------------------------------------


def dataset_shard_job(job: tuple) -> dict:
    """(out_dir, shard index, first seed, count, depth[, block]) -> {shard, path, scenes, seconds}:
    writes out_dir/shard_<index>.npz atomically. Scene `seed` has a drawn occluder count and the
    target of TARGET_SIZES in turn (seed mod 3); `image_x_sizes` also holds the 1D ground truth of
    every size of TARGET_SIZES behind the same occluders, so every head of a multi-height network
    gets data from every image. block > 1: the depth image is stored as block_depth(depth, block)."""
    out_dir, index, first, count, depth, *rest = job
    block = int(rest[0]) if rest else 1
    sizes = list(TARGET_SIZES.values())
    t0 = time.perf_counter()
    geometry = shelf_geometry(SCENARIO)
    scenario = load_scenario(None, SCENARIO) if depth else None
    scenes, floors, image_x, depths, heights, all_x = [], [], [], [], [], []
    params = ShelfSceneParams()
    for seed in range(first, first + count):
        size = sizes[seed % len(sizes)]
        sample = generate_shelf_scene(geometry, seed, None, size, params)
        scenes.append(scene_to_dict(sample.scene))
        floors.append(sample.occupancy.floor.astype(np.float32))
        image_x.append(sample.occupancy.image_x.astype(np.float32))
        heights.append(size[2])
        prisms = Prisms.of(sample.scene.objects)
        all_x.append([sample.occupancy.image_x if s == size else
                      hidden_placements(geometry, prisms, s, params.grid_step, params.gap).occupancy(geometry).image_x
                      for s in sizes])
        if depth:
            depths.append(block_depth(render_shelf_scene(scenario, sample.scene).depth.astype(np.float32), block))
    occ = sample.occupancy
    arrays = dict(floor=np.stack(floors), image_x=np.stack(image_x), target_height=np.array(heights, np.float32),
                  image_x_sizes=np.array(all_x, np.float32), depth_block=np.array(block),
                  seeds=np.arange(first, first + count), floor_origin=np.array([occ.x0, occ.y0, occ.step]),
                  scenes=np.array(json.dumps(scenes)))
    if depth:
        arrays["depth"] = np.stack(depths)
    path = Path(out_dir) / f"shard_{index:05d}.npz"
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return dict(shard=index, path=str(path), scenes=count, seconds=time.perf_counter() - t0)


def write_shelf_dataset(out_dir, count: int, seed_start: int = 0, shard_size: int = 100, depth: bool = True,
                        workers: int = 1, use_ray: bool = False, ray_address: str | None = None,
                        progress=None, block: int = 1) -> dict:
    """Shards of `shard_size` scenes for seeds S..S+count-1 into out_dir (existing shards are kept:
    resumable); depth images block-averaged by `block`; returns {written, skipped, failed}."""
    if count < 1 or shard_size < 1 or block < 1:
        raise MsDrakeError(f"--count {count} / shard size {shard_size} / --depth-block {block}: all must be >= 1")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "index.json").write_text(json.dumps(dict(
        scenario=SCENARIO, seed_start=seed_start, count=count, shard_size=shard_size, depth=depth,
        target_sizes=TARGET_SIZES, generator="ms_drake.scenes.shelf.generate_shelf_scene",
        depth_block=block,
        arrays="floor (K, ny, nx), image_x (K, W), target_height (K,), image_x_sizes (K, 3, W) (TARGET_SIZES order), "
               "seeds (K,), floor_origin (x0, y0, step), scenes (JSON), depth (K, H / block, W / block) metres (mean of "
               "the finite depths of each block, 0 where none)"), indent=1))
    jobs, skipped = [], 0
    for index, first in enumerate(range(seed_start, seed_start + count, shard_size)):
        n = min(shard_size, seed_start + count - first)
        if (out / f"shard_{index:05d}.npz").exists():
            skipped += 1
            continue
        jobs.append((str(out), index, first, n, depth, block))
    return run_shard_jobs(dataset_shard_job, jobs, dict(written=0, skipped=skipped, failed=[]), progress=progress,
                          workers=workers, use_ray=use_ray, ray_address=ray_address)
