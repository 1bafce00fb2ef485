"""The `ms-drake` command.

    ms-drake demo     bin: a full X-Ray search of a 15-object heap; shelf: a shelf search on the Fetch
                      in physics (step PNGs, GIF, Meshcat recording)
    ms-drake scene    a scenario and seed -> images
    ms-drake heaps    many heaps in parallel -> JSON lines (resumable)
    ms-drake diagram  the station's Graphviz diagram (.dot, and .svg/.png when Graphviz is installed)
    ms-drake bench    search / plot: the bin mechanical-search benchmark (resumable JSON lines)
    ms-drake grasp    grasps on one object scored by a contact model, drawn (Fig. 2.1)
    ms-drake pick     a full-fidelity pick or push (yumi_jaw, yumi_suction, panda_jaw, fetch_push, fetch_suction)

User errors (bad scenario, unknown object set, impossible counts) print one clear line and
exit with status 2; they never show a traceback.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import typer
from pydrake.common.yaml import yaml_dump_typed
from tqdm import tqdm

from ms_drake.collision.checker import METHODS as COLLISION_METHODS
from ms_drake.collision.checker import NETWORKS as COLLISION_NETWORKS
from ms_drake.collision.checker import default_weights as default_collision_weights
from ms_drake.collision.checker import load_collision_net
from ms_drake.collision.scene_net import NetConfig as CollisionNetConfig
from ms_drake.config_files import load_config
from ms_drake.errors import MsDrakeError
from ms_drake.execution.lift_rates import check_rates, check_text, count_attempts, read_attempts, rows_text
from ms_drake.execution import FIDELITIES
from ms_drake.experiments.collision_data import (
    SCENES_PER_SHARD as COLLISION_SCENES_PER_SHARD,
)
from ms_drake.experiments.collision_data import write_collision_dataset
from ms_drake.experiments.collision_learning import bench_collision, train_collision
from ms_drake.experiments.demo import DEMO_CONFIG, DEMO_SEED, DEMO_SETTING, run_demo
from ms_drake.experiments.grasp_figure import grasp_figure
from ms_drake.experiments.grasp_set_data import write_grasp_sets
from ms_drake.experiments.harness import (
    format_summary,
    paired_comparison,
    plot,
    read_search_records,
    check_record_heaps,
    replay_records,
    run_bench,
)
from ms_drake.experiments.matcher_data import (
    OCCLUSION,
    bench_target_detection,
    write_matcher_dataset,
)
from ms_drake.experiments.matcher_learning import train_matcher
from ms_drake.experiments.mppi_bench import PLANNERS as MPPI_PLANNERS
from ms_drake.experiments.mppi_bench import bench_mppi
from ms_drake.experiments.occupancy_data import GROUND_TRUTHS, HEAP_LAYOUTS, write_occupancy_dataset
from ms_drake.experiments.occupancy_learning import bench_occupancy, train_occupancy
from ms_drake.experiments.fidelity import format_summary as format_fidelity_summary
from ms_drake.experiments.fidelity import run_fidelity
from ms_drake.experiments.picks import TASKS, run_pick
from ms_drake.experiments.push_fidelity import (
    format_fidelity,
    pushed_records,
    run_push_fidelity,
    summarize_fidelity,
)
from ms_drake.experiments.records import RECORD_FIELDS, read_record_file
from ms_drake.experiments.reproduce import list_recipes
from ms_drake.experiments.reproduce import reproduce as run_reproduce
from ms_drake.experiments.push_study import (
    PushStudyConfig,
    format_push_table,
    plot_push,
    read_jsonl,
    run_push_bench,
    summarize_push,
    write_push_heaps,
)
from ms_drake.experiments.rearrange import DEMO_SEED as REARRANGE_DEMO_SEED
from ms_drake.experiments.rearrange import METHODS as REARRANGE_METHODS
from ms_drake.experiments.rearrange import SCENE_SETS as REARRANGE_SCENE_SETS
from ms_drake.experiments.perceive import PERCEIVE_SEGMENTERS, PerceiveError, load_camera, load_depth
from ms_drake.experiments.perceive import perceive as run_perceive
from ms_drake.experiments.perceive import write_perception
from ms_drake.experiments.rearrange import bench_params
from ms_drake.experiments.rearrange import (
    RearrangeError,
    check_rearrange_scenario,
    rearrange_records,
    rearrange_table,
    run_rearrange_bench,
    run_rearrange_demo,
)
from ms_drake.experiments.scene_images import make_scene, write_scene_images
from ms_drake.experiments.segmentation_data import SENSOR_OPTIONS, write_segmentation_dataset
from ms_drake.experiments.segmentation_learning import (
    bench_segmentation,
    train_segmentation,
)
from ms_drake.experiments.shelf import (
    bench_shelf_scenes,
    plot_shelf,
    run_shelf_bench,
    shelf_records,
    shelf_table,
    write_shelf_dataset,
)
from ms_drake.experiments.shelf_learning import (
    bench_shelf_occupancy,
    train_shelf_occupancy,
)
from ms_drake.experiments.shelf_physics import DEMO_OCCLUDERS as SHELF_DEMO_OCCLUDERS
from ms_drake.experiments.shelf_physics import DEMO_SCENARIO as SHELF_DEMO_SCENARIO
from ms_drake.experiments.shelf_physics import DEMO_SEED as SHELF_DEMO_SEED
from ms_drake.experiments.shelf_physics import (
    ShelfPhysicsError,
    check_shelf_scenario,
    physics_records,
    physics_table,
    physics_vs_foss,
    run_shelf_demo,
    run_shelf_physics_bench,
)
from ms_drake.experiments.shelf_segmentation import bench_shelf_segmentation
from ms_drake.grasping.evaluator import MODELS
from ms_drake.objects import available_sets, get_object_set
from ms_drake.parallel import run_jobs
from ms_drake.paths import model_path
from ms_drake.perception.matcher_net import load_matcher
from ms_drake.perception.occupancy_net import load_model as load_occupancy_net
from ms_drake.perception.segmentation_net import load_model as load_segmentation_net
from ms_drake.perception.shelf_occupancy_net import load_model as load_shelf_occupancy_net
from ms_drake.perception.target import BACKENDS as DETECTOR_BACKENDS
from ms_drake.perception.weights import torch_device
from ms_drake.policies.bin_search import (
    DEFAULT_SCENARIOS,
    ControllerError,
    check_search_scenario,
    load_bin_search_config,
)
from ms_drake.policies.bin_selectors import POLICIES as BIN_POLICIES
from ms_drake.policies.rearrange import RearrangeParams
from ms_drake.policies.bin_selectors import OCCUPANCY_POLICIES
from ms_drake.pushing import POLICIES as PUSH_POLICIES
from ms_drake.policies.shelf import SHELF_POLICIES, check_shelf_policy
from ms_drake.policies.shelf_search import CONTROLLER_PERCEPTIONS as SHELF_CONTROLLER_PERCEPTIONS
from ms_drake.policies.shelf_search import SHELF_PERCEPTIONS, ShelfSearchConfig
from ms_drake.scenario import DEPTH_SENSOR_PRESETS, ScenarioRef, load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap, heap_to_dict
from ms_drake.scenes.layouts import HEAP_LAYOUTS as SEARCH_HEAP_LAYOUTS
from ms_drake.station import MakeStation

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Robot mechanical search in Drake.")

ScenarioFile = typer.Option(None, "--scenario-file", help="Scenario YAML (default: diagrams/scenarios.yaml)")
# Options several commands share (typer reads an option's declaration without changing it).
JsonlOut = typer.Option(..., "--out", help="Output .jsonl (appended to; resumes)")
Ray = typer.Option(False, "--ray", help="Run on a local Ray cluster")
RayAddress = typer.Option(None, "--ray-address", help="Ray cluster address")
JsonSummary = typer.Option(None, "--json", help="Write the summary as JSON")
DatasetSeed = typer.Option(0, "--seed", min=0, help="Dataset seed")
TrainingSeed = typer.Option(0, "--seed", min=0, help="Seed")
TorchThreads = typer.Option(1, "--threads", min=1, help="torch threads")
TrainDevice = typer.Option("cpu", "--device", help="Where the network trains: cpu, cuda (a GPU; an error on a "
                           "machine without one) or auto (cuda where a GPU exists, else cpu). The weights are "
                           "saved with CPU tensors and load anywhere")
Device = typer.Option("cpu", "--device", help="Where the learned network runs: cpu, cuda (a GPU; an error on a "
                      "machine without one) or auto (cuda where a GPU exists, else cpu)")
OverwriteShipped = typer.Option(False, "--overwrite-shipped", help="Allow --out inside the shipped models/weights/ "
                                "folder (replaces the weights the package uses by default)")


def _workers(help: str = "Parallel workers", max: Optional[int] = 64):
    return typer.Option(1, "--workers", min=1, max=max, help=help)


def _seed_start(help: str, default: int = 0):
    return typer.Option(default, "--seed-start", min=0, help=help)


def _write_json(out: Path, value) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(value, indent=1))


def _fail(msg: str, code: int = 2):
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def _scenario(file: Optional[Path], name: str):
    return load_scenario(file, name)


def _need_station(file: Optional[Path], name: str, check):
    """The station of --scenario NAME / --scenario-file FILE, or one clear error: an unknown name, or a
    station `check(scenario, name)` refuses (it raises the project's error naming the fix)."""
    scenario = _scenario(file, name)
    try:
        check(scenario, name)
    except (ControllerError, ShelfPhysicsError, RearrangeError) as e:
        _fail(f"--scenario {name}: {e}")
    return scenario


def _need_search_scenario(file: Optional[Path], name: str, fidelity: str):
    """A bin-search station for `fidelity` (name "" = the fidelity's default)."""
    return _need_station(file, name or DEFAULT_SCENARIOS[fidelity], lambda s, n: check_search_scenario(s, fidelity, n))


def _need_shelf_scenario(file: Optional[Path], name: str):
    return _need_station(file, name, check_shelf_scenario)


def _need_rearrange_scenario(file: Optional[Path], name: str):
    return _need_station(file, name, check_rearrange_scenario)


def _choose(option: str, value, choices, quote: bool = True) -> None:
    """Fail unless `value` (given with `option`) is one of `choices`; `quote`: show it as a repr."""
    if value not in choices:
        shown = repr(value) if quote else value
        _fail(f"{option} {shown}: choose one of {', '.join(choices)}")


def _need_jsonl(out: Path) -> None:
    if out.suffix != ".jsonl":
        _fail(f"--out {out}: give a .jsonl file")


def _need_results(files, command: str) -> None:
    """Fail unless every result file exists and holds records, each with the fields RECORD_FIELDS
    lists for `command` (e.g. "bench search"), the one that writes them. One error (RecordFileError)
    names the file and the line at fault (records.read_record_file)."""
    for f in files:
        read_record_file(f, RECORD_FIELDS[command], command)


def _need_weights(option: str, path: Optional[Path], load, kind: str) -> None:
    """Load the weights file given with `option` (None: the shipped one `load` defaults to) once here,
    before any worker starts: a missing, unreadable or foreign file fails with its name and the fix."""
    given = f"{option} {path}" if path is not None else f"{option} (the shipped weights)"
    try:
        load(path)
    except MsDrakeError as e:
        _fail(f"{given}: {e}")
    except Exception as e:  # noqa: BLE001 - a loader's unexpected error still names the file
        _fail(f"{given}: cannot load {kind} weights ({type(e).__name__}: {e}); give a file written by "
              f"`ms-drake train {kind}`")


def _shipped_weights_dir() -> Path:
    return model_path("weights").resolve()


def _need_training_out(out: Path, overwrite_shipped: bool) -> None:
    """Training writes OUT (and OUT.ckpt); into the shipped models/weights/ only with --overwrite-shipped."""
    if overwrite_shipped:
        return
    shipped = _shipped_weights_dir()
    if out.resolve() == shipped or shipped in out.resolve().parents:
        _fail(f"--out {out}: this is the shipped weights folder {shipped}; give another --out (default "
              "out/weights/<kind>.pt) or add --overwrite-shipped to replace the shipped weights")


def _echo_written(written: dict) -> None:
    for k, v in written.items():
        typer.echo(f"  {k:18s} {v}")


def _job_bar(total: int, desc: str, unit: str, name=None):
    """A tqdm bar and a progress callback for `run_jobs` results: each result ticks the bar; a failed one
    prints `<name(job)>: <last line of its error> (rerun to retry)` (default name: `<unit> <job[1]>`)."""
    bar = tqdm(total=total, desc=desc, unit=unit)
    name = name or (lambda job: f"{unit} {job[1]}")

    def progress(r):
        bar.update(1)
        if not r.ok:
            tqdm.write(f"{name(r.job)}: {r.error.strip().splitlines()[-1]} (rerun to retry)")

    return bar, progress


class _RunProgress:
    """A long run's progress: the resume notice first (`start(done, todo)`, called by the run before
    any job), then a bar (i of N, rate, ETA) with a line per finished record (`line(rec)`, None: no
    line); `write` prints above the bar; Ctrl-C (`interrupted`) says how far the run got and how to
    resume it."""

    def __init__(self, total: int, out: Path, unit: str, line=None):
        self.total, self.out, self.unit, self.line = int(total), out, unit, line
        self.bar, self.done = None, 0

    def start(self, done: int, todo: int):
        self.done = done
        if done:
            typer.echo(f"resuming: {done} of {self.total} {self.unit}s already in {self.out}; running the other {todo}")
        self.bar = tqdm(total=todo, desc=f"{self.unit}s", unit=self.unit)

    def __call__(self, rec):
        self.done += 1
        text = self.line(rec) if self.line is not None else None
        if text:
            self.write(text)
        if self.bar is not None:
            self.bar.update(1)

    def write(self, text: str):
        (self.bar.write if self.bar is not None else typer.echo)(text)

    def close(self):
        if self.bar is not None:
            self.bar.close()

    def interrupted(self):
        self.close()
        typer.echo(f"stopped after {self.done} of {self.total} {self.unit}s; run the same command to resume", err=True)
        raise typer.Exit(130)


def _rollout_line(rec) -> str:
    return (f"seed {rec['seed']}: {'success' if rec['success'] else rec['failure']} after {rec['actions']} actions "
            f"({rec.get('seconds', 0.0):.1f} s)")


def _epoch_bar(epochs: int):
    """A tqdm bar over each epoch's batches and the training progress callback `(epoch, b, n, loss)` for it."""
    bar = tqdm(desc="training", unit="batch")

    def progress(epoch, b, n, loss):
        if b == 0:
            bar.reset(total=n)
            bar.set_description(f"epoch {epoch + 1}/{epochs}")
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4f}")

    return bar, progress


def _device_args(device: str) -> list[str]:
    """The --device of a training's recorded command line (none for the default, cpu)."""
    return ["--device", device] if device != "cpu" else []


def _echo_trained(out: Path, meta: dict, epochs: int, loss_format: str = ".5f") -> None:
    """Each epoch's loss and time from a training's meta, then where the weights went."""
    for h in meta["history"]:
        typer.echo(f"epoch {h['epoch']}: loss {h['loss']:{loss_format}} ({h['seconds']:.0f} s)")
    typer.echo(f"wrote {out} ({meta['epochs_done']} of {epochs} epochs, {meta['seconds'] / 60:.1f} min)")


@app.command()
def demo(kind: str = typer.Argument("bin", help="bin (X-Ray on the floating gripper), shelf (the Fetch "
                                                "with the bluction tool, in physics) or rearrange (the Panda "
                                                "moves a target past a barrier, MPPI, in physics)"),
         out: Optional[Path] = typer.Option(None, help="Output folder (default out/demo, out/demo_shelf)"),
         seed: Optional[int] = typer.Option(None, help=f"Heap seed (default {DEMO_SEED}: a Table 8.2 heap) / shelf scene seed "
                                                        f"(default {SHELF_DEMO_SEED})"),
         objects: Optional[int] = typer.Option(None, min=2, max=60, help="Objects in the heap, the target "
                                                                         "included (default 15) / "
                                                                         f"occluders on the shelf (default {SHELF_DEMO_OCCLUDERS})"),
         policy: Optional[str] = typer.Option(None, help="Selector (default: X-Ray) / shelf policy "
                                                         "(default: bluction_dar)"),
         horizon: Optional[int] = typer.Option(None, min=1, help="Action budget H (default 10 / 2n)"),
         meshcat: bool = typer.Option(True, help="Write a Meshcat HTML recording"),
         perception: str = typer.Option("depth", "--perception",
                                        help="shelf: the controller's perception, depth (the camera's images only, "
                                             "as on hardware) or ground_truth (the simulation's body poses)"),
         method: str = typer.Option("coal_reconstruction", "--method",
                                    help=f"rearrange: the collision checker, {', '.join(REARRANGE_METHODS)}"),
         scenario: str = typer.Option("", "--scenario", help="bin: the station (default FloatingGripperBin; a "
                                      "robot's, e.g. YuMiBin or PandaBin, searches with that robot in physics); "
                                      f"shelf: a shelf scenario with the Fetch (default {SHELF_DEMO_SCENARIO}: "
                                      "FetchShelf's camera with its L515-like sensor model); rearrange: a "
                                      "table scenario with the Panda (default PandaTable)"),
         scenario_file: Optional[Path] = ScenarioFile,
         config: Optional[str] = typer.Option(None, "--config", help="bin: the search's named setting or YAML file, "
                                              "as `bench search --config` (default camera: learned masks, target "
                                              "matcher and occupancy on a noisy depth sensor, the search from the "
                                              "camera alone; table_8_2: ground-truth masks); the demo's heap stays"),
         scene_set: Optional[str] = typer.Option(None, "--scene-set", help="rearrange: scene --seed (default 0) of "
                                                 "a scene set, table | barrier | one_side, with --objects objects "
                                                 "(default 3), instead of the demo's scene")):
    """A full search with per-step PNGs, a GIF and a Meshcat recording: `bin` (heap, X-Ray on the
    floating gripper: masks, occupancy, action) or `shelf` (a shelf scene searched by the Fetch with
    the bluction tool in Drake physics: depth, distribution, action)."""
    if kind not in ("bin", "shelf", "rearrange"):
        _fail(f"demo {kind!r}: choose bin, shelf or rearrange")
    if kind == "rearrange":
        _choose("--method", method, REARRANGE_METHODS, quote=False)
        if scene_set is not None:
            _choose("--scene-set", scene_set, REARRANGE_SCENE_SETS, quote=False)
        station = _need_rearrange_scenario(scenario_file, scenario or "PandaTable")
        out = out or Path("out/demo_rearrange")
        t = time.perf_counter()
        where = "past the barrier" if scene_set is None else f"in {scene_set} scene {seed or 0}"
        typer.echo(f"moving objects {where} with MPPI ({method}) on the Panda ...")
        written = run_rearrange_demo(out, method=method, seed=(REARRANGE_DEMO_SEED if scene_set is None else 0)
                                     if seed is None else seed, meshcat_html=meshcat, log=typer.echo,
                                     scenario=station, scene_set=scene_set, objects=objects or 3)
        _echo_written(written)
        typer.echo(f"done in {time.perf_counter() - t:.1f} s")
        return
    if kind == "shelf":
        policy = check_shelf_policy(policy or "bluction_dar")
        seed = SHELF_DEMO_SEED if seed is None else seed
        objects = SHELF_DEMO_OCCLUDERS if objects is None else objects
        if not 2 <= objects <= 12:
            _fail(f"--objects {objects}: a shelf scene has 2 to 12 occluders")
        _choose("--perception", perception, SHELF_CONTROLLER_PERCEPTIONS, quote=False)
        out = out or Path("out/demo_shelf")
        t = time.perf_counter()
        station = _need_shelf_scenario(scenario_file, scenario or SHELF_DEMO_SCENARIO)
        typer.echo(f"searching shelf scene {seed} ({objects} occluders) with {policy} on the Fetch "
                   f"({perception} perception) ...")
        written = run_shelf_demo(out, seed=seed, occluders=objects, policy=policy, horizon=horizon,
                                 meshcat_html=meshcat, log=typer.echo, perception=perception, scenario=station)
        _echo_written(written)
        typer.echo(f"wrote {len(written)} files to {out} in {time.perf_counter() - t:.1f} s")
        return
    config = config or DEMO_SETTING
    try:
        named = load_bin_search_config(config)
    except MsDrakeError as e:
        _fail(str(e))
    station = _scenario(scenario_file, scenario or named.scenario or DEFAULT_SCENARIOS["primitive"])
    fidelity = "primitive" if station.robot.name == "floating" else "full"
    cfg = _bin_search_config(policy or named.policy, fidelity, scenario, scenario_file, config, None)
    cfg.heap = DEMO_CONFIG.heap if objects is None else dataclasses.replace(DEMO_CONFIG.heap, objects=objects - 1)
    if horizon is not None:
        cfg.horizon = horizon
    out = out or Path("out/demo")
    seed = DEMO_SEED if seed is None else seed
    t = time.perf_counter()
    typer.echo(f"generating a {cfg.heap.objects + 1}-object heap (seed {seed}) and searching it with {cfg.policy} "
               f"({station.robot.name if fidelity == 'full' else 'floating gripper'}, {fidelity} fidelity) ...")
    written = run_demo(out, cfg, seed=seed, meshcat_html=meshcat, log=typer.echo)
    _echo_written(written)
    typer.echo(f"wrote {len(written)} files to {out} in {time.perf_counter() - t:.1f} s")


@app.command()
def reproduce(name: Optional[str] = typer.Argument(None, help="The table or figure, e.g. table_8_2 (--list names "
                                                   "them all)"),
              size: str = typer.Option("small", "--size", help="small (<= 15 minutes on 2 cores) | full (the "
                                       "reference's counts)"),
              seed_start: Optional[int] = typer.Option(None, "--seed-start", min=0, help="First seed (default: the "
                                                       "table's)"),
              workers: int = _workers("Parallel workers (W), for the benches that run jobs in parallel"),
              ray: bool = Ray,
              out: Path = typer.Option(Path("out/reproduce"), "--out", help="Folder; the table's records, markdown "
                                       "and figures go to OUT/NAME/ (a run resumes from them)"),
              list_: bool = typer.Option(False, "--list", help="List the tables and figures and exit")):
    """Reproduce one of the reference's tables or figures: runs what it needs (resuming from the
    records in OUT/NAME/), then writes OUT/NAME/NAME.md (ours with 95 % intervals beside the
    reference's, the command, machine and date), its figures and records."""
    if list_ or name is None:
        for r in list_recipes():
            typer.echo(f"{r.name:10s} {r.title}")
        if name is None and not list_:
            _fail("give a table or figure name (listed above), e.g. ms-drake reproduce table_8_2")
        return
    _choose("table or figure", name, [r.name for r in list_recipes()])
    _choose("--size", size, ("small", "full"))
    _need_writable("--out", out)
    bar = tqdm(total=0, desc=name, unit="item")

    def progress(done: int, total: int):
        if bar.total != total:
            bar.reset(total=total)
        bar.n = done
        bar.refresh()

    try:
        path = run_reproduce(name, size=size, seed_start=seed_start, workers=workers, use_ray=ray, out=out,
                             progress=progress, log=tqdm.write)
    except KeyboardInterrupt:
        bar.close()
        typer.echo(f"stopped after {bar.n} of {bar.total} items; run the same command to resume", err=True)
        raise typer.Exit(130)
    finally:
        bar.close()
    typer.echo(path.read_text())
    typer.echo(f"wrote {path}")


@app.command()
def perceive(depth: Path = typer.Argument(..., help="Depth image of a bin from above: .npy (float metres) or "
                                          "16-bit .png (millimetres, 0 = no return)"),
             intrinsics: Optional[Path] = typer.Option(None, "--intrinsics", help="YAML/JSON camera file: width, "
                                                       "height, fx, fy, cx, cy [, pose: {xyz, rpy_deg} in the bin's "
                                                       "frame, bin: [x, y, z]]; default the stations' 640 x 480 "
                                                       "overhead camera"),
             rgb: Optional[Path] = typer.Option(None, "--rgb", help="Colour image of the same camera (finds the target "
                                                "among the masks)"),
             target: Optional[str] = typer.Option(None, "--target", help="The target object, a registry name "
                                                  "'<set>/<name>' (its size gives the occupancy; with --rgb its "
                                                  "rendered views find it)"),
             target_size: Optional[tuple[float, float, float]] = typer.Option(
                 None, "--target-size", help="The target's box size L W T [m] (instead of --target)"),
             segmenter: str = typer.Option("learned", "--segmenter", help="learned | euclidean | region_growing"),
             out: Path = typer.Option(Path("out/perceive"), "--out", help="Output folder"),
             device: str = Device):
    """The perception stack on your own depth image: instance masks (PNG and COCO JSON), the target
    and its occupancy distribution when a target is given, and each stage's CPU time."""
    _choose("--segmenter", segmenter, PERCEIVE_SEGMENTERS)
    if target and target_size:
        _fail("--target and --target-size: give one of them")
    torch_device(device)
    try:
        d = load_depth(depth)
        camera = load_camera(intrinsics, d.shape)
        colour = None
        if rgb is not None:
            img = cv2.imread(str(rgb), cv2.IMREAD_COLOR)
            if img is None:
                raise PerceiveError(f"{rgb}: not a readable colour image")
            colour = img[..., ::-1].copy()
        result = run_perceive(d, camera, segmenter=segmenter, rgb=colour, target=target,
                              target_size=list(target_size) if target_size else None, device=device)
    except PerceiveError as e:
        _fail(str(e))
    written = write_perception(out, depth, result, d)
    _echo_written(written)
    found = result["target"]
    typer.echo(f"{len(result['masks'])} masks" + ("" if found is None else
               f"; target {'mask ' + str(found.instance_index) if found.visible else 'not seen'}")
               + "; " + ", ".join(f"{k} {v:.0f} ms" for k, v in result["ms"].items()))


@app.command()
def scene(scenario: str = typer.Argument(..., help="Scenario name, e.g. BinHeap15, PandaTable, FetchShelf"),
          seed: int = typer.Option(0, help="Scene seed"),
          objects: Optional[int] = typer.Option(None, min=0, max=60, help="Objects (default: scenario's count)"),
          out: Path = typer.Option(Path("out/scene"), help="Output folder"),
          scenario_file: Optional[Path] = ScenarioFile):
    """Make the scene of a scenario and seed, and write its images."""
    s = _scenario(scenario_file, scenario)
    heap = make_scene(s, seed, objects)
    written = write_scene_images(s, heap, out)
    _echo_written(written)


def _read_done(path: Path) -> set[int]:
    """Seeds already in a JSON-lines file; a torn last line (killed mid-write) is dropped."""
    done = set()
    if not path.exists():
        return done
    good = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
            done.add(int(rec["seed"]))
            good.append(line)
        except (ValueError, KeyError, TypeError):
            continue
    path.write_text("".join(g + "\n" for g in good))
    return done


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


#: Heap workers are not recycled every 20 jobs like rollout workers: a heap's diagram is all C++
#: and is freed (peak RSS 412 MB after 10 and after 80 heaps in one worker), while a fresh worker
#: costs ~3 s of start-up, 5 heaps' worth (docs/results/foundation.md).
HEAP_TASKS_PER_CHILD = 1000


def heap_job(job: tuple) -> dict:
    """One heap as a JSON-able record (module-level so workers can unpickle it)."""
    scenario_file, scenario_name, n, seed, object_set, *rest = job

    s = load_scenario(scenario_file, scenario_name)
    engine = rest[0] if rest and rest[0] else HeapParams.engine
    params = HeapParams(engine=engine, polish_time=rest[1] if len(rest) > 1 else 0.0)
    t, cpu0 = time.perf_counter(), time.process_time()
    heap, diag = generate_heap(s, n, seed, object_set=object_set, params=params, return_diagnostics=True)
    rec = heap_to_dict(heap)
    rec.update(engine=params.engine, polish_time=params.polish_time, seconds=time.perf_counter() - t, attempts=diag.attempts, removed=diag.removed,
               settle_time=diag.settle_time, rejected=diag.rejected_reasons, pid=os.getpid(),
               cpu_seconds=time.process_time() - cpu0, peak_rss_mb=_peak_rss_mb())
    return rec


@app.command()
def heaps(objects: int = typer.Option(15, "--objects", min=1, max=60, help="Objects per heap (N)"),
          count: int = typer.Option(10, "--count", min=1, help="Number of heaps (K)"),
          seed_start: int = _seed_start("First seed (S)"),
          workers: int = _workers("Parallel workers (W)"),
          out: Path = JsonlOut,
          object_set: Optional[str] = typer.Option(None, "--object-set", help="Object set (default: scenario's)"),
          scenario: str = typer.Option("BinHeap15", help="Scenario name"),
          scenario_file: Optional[Path] = ScenarioFile,
          engine: Optional[str] = typer.Option(None, "--engine", help="Drop physics: bullet or drake "
                                               "(default: ms_drake.scenes.heaps.HeapParams.engine)"),
          polish: float = typer.Option(0.0, "--polish", min=0.0, max=5.0,
                                       help="With bullet: then settle up to this many simulated seconds in the "
                                            "compliant Drake drop world (0.5: heaps at rest in the bin stations)"),
          ray: bool = Ray,
          ray_address: Optional[str] = RayAddress):
    """Generate heaps for seeds S..S+K-1 in parallel, one JSON line per heap (resumable)."""

    s = _scenario(scenario_file, scenario)  # validate before starting workers
    if object_set:
        get_object_set(object_set)
    _need_jsonl(out)
    if engine not in (None, "bullet", "drake"):
        _fail(f"--engine {engine}: use bullet or drake")
    out.parent.mkdir(parents=True, exist_ok=True)
    done = _read_done(out)
    seeds = [k for k in range(seed_start, seed_start + count) if k not in done]
    if len(seeds) < count:
        typer.echo(f"resuming: {count - len(seeds)} of {count} heaps already in {out}")
    if polish > 0 and engine == "drake":
        _fail("--polish: only with --engine bullet (a Drake-dropped heap is already at rest in Drake)")
    jobs = [(str(scenario_file) if scenario_file else None, scenario, objects, k, object_set, engine, polish)
            for k in seeds]
    del s
    failures = 0
    t0 = time.perf_counter()
    with open(out, "a") as f, tqdm(total=len(jobs), desc="heaps", unit="heap") as bar:
        for r in run_jobs(heap_job, jobs, workers=workers, use_ray=ray, ray_address=ray_address,
                          max_tasks_per_child=HEAP_TASKS_PER_CHILD):
            if r.ok:
                f.write(json.dumps(r.value) + "\n")
                f.flush()
                os.fsync(f.fileno())
            else:
                failures += 1
                tqdm.write(f"seed {r.job[3]}: {r.error.splitlines()[0]}")
            bar.update(1)
    typer.echo(f"{len(jobs) - failures} heaps written to {out} in {time.perf_counter() - t0:.1f} s"
               + (f"; {failures} failed (rerun to retry)" if failures else ""))
    if failures:
        raise typer.Exit(1)


@app.command()
def diagram(scenario: str = typer.Argument("BinHeap15", help="Scenario name"),
            out: Path = typer.Option(Path("out/diagram.svg"), help="Output .svg, .png or .dot"),
            depth: int = typer.Option(1, help="Graphviz max depth"),
            scenario_file: Optional[Path] = ScenarioFile):
    """Write the station's Graphviz diagram."""
    if out.suffix not in (".svg", ".png", ".dot"):
        _fail(f"--out {out}: use a .svg, .png or .dot file")
    station = MakeStation(_scenario(scenario_file, scenario))
    dot = station.GetGraphvizString(max_depth=depth)
    out.parent.mkdir(parents=True, exist_ok=True)
    dot_path = out.with_suffix(".dot")
    dot_path.write_text(dot)
    if out.suffix == ".dot":
        typer.echo(f"wrote {dot_path}")
        return
    exe = shutil.which("dot")
    if exe is None:
        _fail(f"wrote {dot_path}, but Graphviz's `dot` is not installed for {out.suffix}; "
              "install it (Debian: apt-get install graphviz) or use --out FILE.dot")
    subprocess.run([exe, f"-T{out.suffix[1:]}", str(dot_path), "-o", str(out)], check=True)
    typer.echo(f"wrote {out}")


bench_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Mechanical-search benchmarks.")
app.add_typer(bench_app, name="bench")


ConfigFile = typer.Option(None, "--config", help="A named setting (table_8_2: the defaults; ch7: Fig. 7.4 and "
                          "Table C.1; camera: learned perception on a noisy depth sensor) or a YAML file of any of BinSearchConfig's fields (`ms-drake bench config` "
                          "prints them all)")
SetOption = typer.Option(None, "--set", help="Override one config field, repeatable: KEY=VALUE, e.g. "
                         "heap.objects=15, heap.layout=bin_set, horizon=30, segmenter=learned, "
                         "ablation.grasp_outcome=draw (the fields: `ms-drake bench config`)")


def _bin_search_config(policy: Optional[str], fidelity: Optional[str], scenario: str,
                       scenario_file: Optional[Path], config: Optional[str], sets: Optional[list[str]]):
    """The BinSearchConfig of a command's options: defaults < --config file < the named options < --set."""
    fields = {k: v for k, v in dict(policy=policy, fidelity=fidelity, scenario=scenario or None,
                                    scenario_file=str(scenario_file) if scenario_file else None).items()
              if v is not None}
    try:
        cfg = load_bin_search_config(config, sets or (), **fields)
    except MsDrakeError as e:
        _fail(str(e))
    _need_search_scenario(Path(cfg.scenario_file) if cfg.scenario_file else None,
                          cfg.scenario or DEFAULT_SCENARIOS[cfg.fidelity], cfg.fidelity)
    # The learned parts' weights load here once, before any worker starts (not as a failure per rollout).
    if cfg.policy in OCCUPANCY_POLICIES and cfg.ablation.occupancy == "learned":
        _need_weights("occupancy_weights", Path(cfg.occupancy_weights) if cfg.occupancy_weights else None,
                      load_occupancy_net, "occupancy")
    if cfg.segmenter == "learned":
        _need_weights("segmenter learned", None, load_segmentation_net, "segmentation")
    if cfg.detector == "learned":
        _need_weights("detector learned", None, load_matcher, "matcher")
    return cfg


@bench_app.command("search")
def bench_search(policy: str = typer.Option(..., "--policy", help="Selector: " + ", ".join(BIN_POLICIES)),
                 heaps_: int = typer.Option(10, "--heaps", min=1, help="Number of heaps (K)"),
                 seed_start: int = _seed_start("First heap seed (S)"),
                 out: Path = JsonlOut,
                 config: Optional[str] = ConfigFile,
                 set_: Optional[list[str]] = SetOption,
                 fidelity: Optional[str] = typer.Option(None, "--fidelity", help="primitive (default: the floating "
                                                        "gripper, grasp outcomes from the contact models) | full (the "
                                                        "scenario's robot in physics)"),
                 scenario: str = typer.Option("", "--scenario", help="The station: a bin scenario name (default "
                                              "FloatingGripperBin for primitive, YuMiBin for full; PandaBin: the Panda)"),
                 scenario_file: Optional[Path] = ScenarioFile,
                 workers: int = _workers("Parallel workers (W)"),
                 ray: bool = Ray,
                 ray_address: Optional[str] = RayAddress,
                 heap_dir: Optional[Path] = typer.Option(
                     None, "--heap-dir", help="Folder of cached heaps, shared by runs of several policies so they "
                     "search the same heaps; made on first use")):
    """Search heaps S..S+K-1 with a policy; one JSON line per rollout (resumable), then a summary.
    With no --config or --set it runs Table 8.2's setting (14 household objects on a hidden 4.5 cm
    target, 10 actions, ground-truth masks)."""
    if fidelity is not None:
        _choose("--fidelity", fidelity, FIDELITIES)
    cfg = _bin_search_config(policy, fidelity, scenario, scenario_file, config, set_)
    _need_jsonl(out)
    progress = _RunProgress(heaps_, out, "rollout", _rollout_line)
    try:
        s = run_bench(cfg, heaps_, seed_start, out, workers=workers, use_ray=ray or ray_address is not None,
                      ray_address=ray_address, progress=progress,
                      heap_dir=str(heap_dir) if heap_dir is not None else None)
    except KeyboardInterrupt:
        progress.interrupted()
    progress.close()
    typer.echo(format_summary(policy, s))
    typer.echo(f"results in {out}")


@bench_app.command("config")
def bench_config(policy: Optional[str] = typer.Option(None, "--policy", help="Selector: " + ", ".join(BIN_POLICIES)),
                 config: Optional[str] = ConfigFile,
                 set_: Optional[list[str]] = SetOption):
    """Print the bin-search config that `bench search` with these options runs (YAML: every field
    and its value; the heap layouts are listed below it)."""
    cfg = _bin_search_config(policy, None, "", None, config, set_)
    typer.echo(yaml_dump_typed(cfg).rstrip())
    typer.echo("# heap layouts (heap.layout):")
    for name, layout in SEARCH_HEAP_LAYOUTS.items():
        typer.echo(f"#   {name}: {layout.description}")


@bench_app.command("plot")
def bench_plot(files: list[Path] = typer.Argument(..., help="Result .jsonl files (ms-drake bench search)"),
               out: Path = typer.Option(Path("out/bench"), "--out", help="Output folder for the PNGs")):
    """Cumulative successes vs actions (Fig. 7.4 B) and the actions histogram (Fig. 8.6) as PNG."""
    _need_results(files, "bench search")
    for p in plot(files, out):
        typer.echo(f"wrote {p}")


@app.command()
def grasp(object: str = typer.Option(..., "--object", help="Object name, '<set>/<name>' (e.g. procedural/box_000)"),
          model: str = typer.Option("6dfc", "--model", help=f"Contact model: {' | '.join(MODELS)}"),
          samples: int = typer.Option(100, "--samples", min=1, help="Number of antipodal grasps to sample"),
          out: Path = typer.Option(Path("grasp_out"), "--out", help="Output folder for the PNG and JSON"),
          robust: int = typer.Option(10, "--robust", min=0, help="Robust trials per grasp (0 = binary quality)"),
          friction: float = typer.Option(0.8, "--friction", help="Friction coefficient"),
          closing_force: float = typer.Option(10.0, "--closing-force", help="Jaw closing force [N]"),
          seed: int = typer.Option(0, "--seed", help="Seed of sampling and robust trials")):
    """Sample grasps on an object, score them with a contact model, write a PNG (Fig. 2.1 style)
    and a JSON, and print the grasp table."""
    grasp_figure(object, model, samples, out, robust, friction, closing_force, seed)


@app.command()
def pick(task: str = typer.Argument(..., help=f"Pick task: {', '.join(TASKS)}"),
         html: Optional[Path] = typer.Option(None, "--html", help="Write a Meshcat recording here"),
         speed: float = typer.Option(0.15, "--speed", min=0.01, help="Tool speed on straight lines [m/s]")):
    """A full-fidelity pick or push from the home pose through the station's drivers."""
    run_pick(task, html=html, speed=speed, log=typer.echo)


# -- Shelf search (Ch. 9): ms-drake bench shelf / shelf-table, ms-drake data shelf -----------------------


data_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Datasets made by the simulator.")
app.add_typer(data_app, name="data")


# -- Linear push policies (Ch. 4): ms-drake data push-heaps, bench push / push-table ---------------------


PushConfigFile = typer.Option(None, "--config", help="A YAML file of PushStudyConfig's fields (grasp sets, "
                              "Algorithm 1, the heaps' object set, the ablation switches)")
PushSetOption = typer.Option(None, "--set", help="Override one config field, repeatable: KEY=VALUE, e.g. "
                             "object_set=procedural, grasps=50, ablation.transfer_speed=2.0, ablation.sampling=object, "
                             "ablation.quasi_random_checked=true (the fields: PushStudyConfig in the API reference)")


def _push_config(config: Optional[Path], sets: Optional[list[str]]) -> PushStudyConfig:
    try:
        return load_config(PushStudyConfig, config, sets or ())
    except MsDrakeError as e:
        _fail(str(e))


@data_app.command("push-heaps")
def data_push_heaps(count: int = typer.Option(..., "--count", min=1, help="Heaps to drop (seeds S..S+N-1)"),
                    out: Path = typer.Option(..., "--out", help="Output folder (heaps.jsonl; resumes)"),
                    seed_start: int = _seed_start("First heap seed (S)"),
                    config: Optional[Path] = PushConfigFile,
                    set_: Optional[list[str]] = PushSetOption,
                    workers: int = _workers(),
                    ray: bool = Ray,
                    ray_address: Optional[str] = RayAddress):
    """Improvable heaps (Ch. 4, Algorithm 1): drop, grasp until stuck, run the five push policies;
    one record per heap (with its config), `improvable` when some policy raises the overall grasp
    quality. Defaults: household-object heaps, the reference's 100 grasps per object."""
    cfg = _push_config(config, set_)
    progress = _RunProgress(count, out / "heaps.jsonl", "heap", lambda r: None if r.ok else (
        f"seed {r.job[0]}: {r.error.splitlines()[-1] if r.error else 'failed'} (rerun to retry)"))
    try:
        s = write_push_heaps(count, out, seed_start, workers=workers, use_ray=ray or ray_address is not None,
                             ray_address=ray_address, params=cfg, bar=progress)
    except KeyboardInterrupt:
        progress.interrupted()
    progress.close()
    typer.echo(f"{s['dropped']} heaps dropped, {s['recorded']} stuck (recorded), {s['improvable']} improvable "
               f"-> {s['path']}" + (f"; {len(s['failed'])} failed (rerun to retry)" if s["failed"] else ""))
    if s["failed"]:
        raise typer.Exit(1)


@bench_app.command("push")
def bench_push(policy: str = typer.Option(..., "--policy", help=f"Push policy: {' | '.join(PUSH_POLICIES)}"),
               heaps_: int = typer.Option(400, "--heaps", min=1, help="Improvable heaps (the first N, by seed)"),
               seed_start: int = _seed_start("Lowest heap seed (S)"),
               out: Path = JsonlOut,
               heap_dir: Path = typer.Option(Path("out/push_heaps"), "--heap-dir",
                                             help="Folder of `ms-drake data push-heaps`"),
               workers: int = _workers("Parallel workers (--rerun)"),
               rerun: bool = typer.Option(False, "--rerun", help="Execute the push again instead of taking "
                                          "the data step's execution of the policy on the heap"),
               from_state: bool = typer.Option(False, "--from-state", help="With --rerun: from the record's stored "
                                               "state (no drop, no grasping) instead of Algorithm 1 from the seed"),
               set_: Optional[list[str]] = typer.Option(
                   None, "--set", help="With --rerun: the heaps' config but these ablation switches, KEY=VALUE, "
                   "e.g. ablation.transfer_speed=2.0, ablation.quasi_random_checked=true")):
    """One JSON line per improvable heap: seed, policy, separation / jaw / suction / overall gain, and
    the config the push ran under."""
    _choose("--policy", policy, PUSH_POLICIES)
    _need_jsonl(out)
    if not (heap_dir / "heaps.jsonl").exists():
        _fail(f"--heap-dir {heap_dir}: no heaps.jsonl; run `ms-drake data push-heaps --out {heap_dir}` first")
    if (from_state or set_) and not rerun:
        _fail("--from-state and --set re-execute the pushes: add --rerun")
    bad = [item for item in set_ or () if not str(item).startswith("ablation.")]
    if bad:
        _fail(f"--set {bad[0]}: a re-run keeps the heaps' config but its ablation switches (ablation.KEY=VALUE)")
    s = run_push_bench(policy, heaps_, seed_start, out, heap_dir, workers=workers, rerun=rerun,
                       params=_push_config(None, set_), from_state=from_state)
    typer.echo(f"{policy}: {s['rows']} heaps in {out} ({s['new']} added; {s['available']} improvable heaps "
               f"available from seed {seed_start})")
    if s["available"] < heaps_:
        typer.echo(f"only {s['available']} improvable heaps in {heap_dir}: drop more with "
                   f"`ms-drake data push-heaps`")


@bench_app.command("push-table")
def bench_push_table(files: list[Path] = typer.Argument(..., help="Result .jsonl files (ms-drake bench push)"),
                     figures: Optional[Path] = typer.Option(None, "--figures", help="Write Fig. 4.2 / 4.3 "
                                                            "analogues (PNG) into this folder"),
                     json_out: Optional[Path] = JsonSummary):
    """Mean +- standard error per policy and metric on the heaps every policy has, one-way ANOVA per metric."""
    _need_results(files, "bench push")
    rows = [r for f in files for r in read_jsonl(f)]
    s = summarize_push(rows)
    typer.echo(format_push_table(s))
    if json_out is not None:
        _write_json(json_out, s)
    if figures is not None:
        for p in plot_push(s, figures):
            typer.echo(f"wrote {p}")


@bench_app.command("push-fidelity")
def bench_push_fidelity(heaps_: int = typer.Option(400, "--heaps", min=1, help="Improvable heaps (the first N, by seed)"),
                        seed_start: int = _seed_start("Lowest heap seed (S)"),
                        heap_dirs: list[Path] = typer.Option(..., "--heap-dir", help="Folder of `ms-drake data "
                                                             "push-heaps` (repeat for several)"),
                        out: Path = JsonlOut,
                        workers: int = _workers(),
                        policies: Optional[list[str]] = typer.Option(None, "--policy", help="Push policies "
                                                                     f"(repeat; default all): {' | '.join(PUSH_POLICIES)}"),
                        scenario: str = typer.Option("YuMiBin", "--scenario", help="The robot's station of the full "
                                                     "side (YuMiBin, PandaBin)"),
                        scenario_file: Optional[Path] = ScenarioFile,
                        json_out: Optional[Path] = JsonSummary):
    """Each policy's recorded push on a robot (full fidelity, --scenario) and in the primitive mode from
    the same state: one JSON line per (heap, policy) with status, agree, gain_sign_agree, object motions, CPU s."""
    _need_search_scenario(scenario_file, scenario, "full")
    ref = ScenarioRef(scenario, str(scenario_file) if scenario_file is not None else None)
    bad = [p for p in policies or [] if p not in PUSH_POLICIES]
    if bad:
        _fail(f"--policy {', '.join(bad)}: choose from {', '.join(PUSH_POLICIES)}")
    _need_jsonl(out)
    missing = [str(d) for d in heap_dirs if not (d / "heaps.jsonl").exists()]
    if missing:
        _fail(f"--heap-dir {', '.join(missing)}: no heaps.jsonl; run `ms-drake data push-heaps --out DIR` first")
    pols = tuple(policies) if policies else PUSH_POLICIES
    total = sum(len(ps) for _, ps in pushed_records(heap_dirs, heaps_, seed_start, pols))
    with tqdm(total=total, desc="push fidelity", unit="push") as bar:
        done = {(int(r["seed"]), r["policy"]) for r in read_jsonl(out)} if out.exists() else set()
        bar.update(sum(len([p for p in ps if (int(r["seed"]), p) in done])
                       for r, ps in pushed_records(heap_dirs, heaps_, seed_start, pols)))
        s = run_push_fidelity(heap_dirs, heaps_, seed_start, out, workers=workers, policies=pols,
                              progress=lambda rows: bar.update(len(rows)), scenario=ref)
    summary = summarize_fidelity(s["rows"])
    typer.echo(f"{len(s['rows'])} of {s['pushes']} pushes on {s['heaps']} heaps in {out}")
    typer.echo(format_fidelity(summary))
    if json_out is not None:
        _write_json(json_out, summary)
    if s["failed"]:
        typer.echo(f"{len(s['failed'])} heaps failed (rerun to retry): {s['failed'][:3]}")
        raise typer.Exit(1)


@bench_app.command("fidelity")
def bench_fidelity(heaps_: int = typer.Option(50, "--heaps", min=1, help="Heaps (seeds S..S+K-1)"),
                   objects: int = typer.Option(10, "--objects", min=1, help="Objects per heap (N)"),
                   seed_start: int = _seed_start("Lowest heap seed (S)", 5000),
                   heap_dir: Optional[Path] = typer.Option(None, "--heap-dir", help="Heap cache folder (shared "
                                                           "with `bench search --heap-dir`)"),
                   out: Path = JsonlOut,
                   workers: int = _workers(),
                   attempts: int = typer.Option(2, "--attempts", min=1, help="First K grasp attempts per heap"),
                   scenario: str = typer.Option("YuMiBin", "--scenario", help="The robot's station the attempts "
                                                "are replayed on (YuMiBin, PandaBin)"),
                   reach: Optional[str] = typer.Option(None, "--reach", help="The primitive search keeps only grasps "
                                                       "this robot reaches, a scenario of diagrams/scenarios.yaml "
                                                       "(default: --scenario's, none with --scenario-file; '' for none)"),
                   scenario_file: Optional[Path] = ScenarioFile,
                   pictures: Optional[Path] = typer.Option(None, "--pictures", help="Folder for a picture of "
                                                           "every attempt whose outcomes differ (two cameras at the "
                                                           "grasp, the last 2 s before the outcome)"),
                   json_out: Optional[Path] = JsonSummary):
    """The primitive search's first grasp attempts per heap, each replayed on a robot (full
    fidelity, --scenario) from the same scene with the same grasp: one JSON line per attempt
    (primitive and full outcome, CPU s), per-attempt success in each fidelity and their agreement."""
    _need_search_scenario(scenario_file, scenario, "full")
    reach = scenario if reach is None and scenario_file is None else (reach or "")
    if reach:
        _need_search_scenario(None, reach, "full")
    _need_jsonl(out)
    with tqdm(total=heaps_, desc="fidelity", unit="heap") as bar:
        s = run_fidelity(heaps_, seed_start, out, objects=objects, heap_dir=str(heap_dir) if heap_dir else None,
                         workers=workers, max_attempts=attempts, reach=reach,
                         scenario=ScenarioRef(scenario, str(scenario_file) if scenario_file is not None else None),
                         progress=lambda rec: bar.update(1 if rec.get("kind") == "heap" else 0),
                         pictures=str(pictures) if pictures is not None else None)
    typer.echo(format_fidelity_summary(s))
    if json_out is not None:
        _write_json(json_out, s)


@bench_app.command("lift-rates")
def bench_lift_rates(files: list[Path] = typer.Argument(..., help="Result files (.jsonl or .jsonl.gz) of `ms-drake "
                                                        "bench search --fidelity full` or `ms-drake bench fidelity`"),
                     station: str = typer.Option(..., "--station", help="The robot's station the records ran on "
                                                 "(PandaBin, YuMiBin)"),
                     check: Optional[list[Path]] = typer.Option(None, "--check", help="Records of other attempts "
                                                                "(repeatable): how well the rates predict their "
                                                                "lifts, beside the quality alone")):
    """A station's lift rate per gripper kind and grasp quality in physics, from its full-fidelity
    grasp attempts; with --check, how well the rates and the quality alone predict other attempts."""
    rates = count_attempts(files, station)
    typer.echo(rows_text(rates))
    if check:
        typer.echo(check_text(check_rates(rates, read_attempts(check, station))))


def _occluder_counts(first: list[int], extra: list[str]) -> list[int]:
    """--occluders 4 6 8 10: click gives the first value to the option and the rest as extra args."""
    out = list(first)
    for a in extra:
        try:
            out.append(int(a))
        except ValueError:
            _fail(f"unexpected argument {a!r}; occluder counts are integers, e.g. --occluders 4 6 8 10")
    return sorted(set(out))


ShelfSetOption = typer.Option(None, "--set", help="Override one config field, repeatable: KEY=VALUE, e.g. "
                              "horizon=20, psi=1.5, oracle_seconds=0, ablation.suction_lift=floor, "
                              "ablation.foss_choice=true (the fields: ShelfSearchConfig in the API reference)")
ShelfConfigFile = typer.Option(None, "--config", help="A YAML file of ShelfSearchConfig's fields (the policy's, "
                               "the robot's and the ablation switches)")


def _shelf_config(policy: str, perception: Optional[str], config: Optional[Path], sets: Optional[list[str]],
                  perceptions) -> ShelfSearchConfig:
    """The ShelfSearchConfig of a command's options: defaults < --config file < --policy, --perception < --set."""
    fields = {k: v for k, v in dict(policy=policy, perception=perception).items() if v is not None}
    try:
        cfg = load_config(ShelfSearchConfig, config, sets or (), **fields)
    except MsDrakeError as e:
        _fail(str(e))
    _choose("--perception", cfg.perception, perceptions, quote=False)
    if cfg.perception != "ground_truth":
        _need_weights(f"--perception {cfg.perception}", None, load_shelf_occupancy_net, "shelf-occupancy")
    return cfg


@bench_app.command("shelf", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def bench_shelf(ctx: typer.Context,
                policy: str = typer.Option(..., "--policy", help=f"Shelf policy: {', '.join(SHELF_POLICIES)}"),
                occluders: list[int] = typer.Option([4, 6, 8, 10], "--occluders",
                                                    help="Occluder counts (2-12), e.g. --occluders 4 6 8 10"),
                scenes: int = typer.Option(100, "--scenes", min=1, help="Scenes per occluder count (K)"),
                seed_start: int = _seed_start("First scene seed (S)"),
                out: Path = JsonlOut,
                perception: Optional[str] = typer.Option(
                    None, "--perception", help="ground_truth (default: FOSS's scene, analytic occupancy), learned "
                    "(learned occupancy of depth renders) or depth (also the objects segmented from the render)"),
                config: Optional[Path] = ShelfConfigFile,
                set_: Optional[list[str]] = ShelfSetOption,
                workers: int = _workers("Parallel workers (W)"),
                ray: bool = Ray,
                ray_address: Optional[str] = RayAddress,
                scenario: str = typer.Option("FetchShelf", "--scenario", help="Whose shelf and camera: a shelf "
                                             "scenario (FetchShelf: the reference's simulated 0.6 m shelf; "
                                             "FetchWideShelf: its physical 0.8 x 0.5 m one)")):
    """Shelf search in FOSS (Table 9.1): scenes S..S+K-1 for each occluder count; one JSON line per
    search (resumable; each keeps its config and station), then success rates and median steps."""
    cfg = _shelf_config(policy, perception, config, set_, SHELF_PERCEPTIONS)
    counts = _occluder_counts(occluders, ctx.args)
    _need_jsonl(out)
    _need_shelf_scenario(None, scenario)
    progress = _RunProgress(len(counts) * scenes, out, "scene", lambda rec: (
        f"occluders {rec['occluders']} seed {rec['seed']}: {rec.get('error', '')} (rerun to retry)"
        if rec.get("failure") == "worker_died" else None))
    try:
        s = run_shelf_bench(cfg, counts, scenes, seed_start, out, workers=workers,
                            use_ray=ray or ray_address is not None, ray_address=ray_address, progress=progress,
                            scenario_name=scenario)
    except KeyboardInterrupt:
        progress.interrupted()
    progress.close()
    for n in counts + ["all"]:
        q = s[n]["success_quartiles"]
        typer.echo(f"{policy} occluders {n}: {s[n]['rollouts']} scenes, success {100 * s[n]['success_rate']:.1f} % "
                   f"[{100 * s[n]['success_ci'][0]:.1f}, {100 * s[n]['success_ci'][1]:.1f}], median steps "
                   f"{q[1]:g} (IQR {q[0]:g} - {q[2]:g})")
    typer.echo(f"results in {out}")


@bench_app.command("shelf-physics")
def bench_shelf_physics(policy: str = typer.Option(..., "--policy", help=f"Shelf policy: {', '.join(SHELF_POLICIES)}"),
                        scenes: int = typer.Option(10, "--scenes", min=1, help="Scenes (N)"),
                        seed_start: int = _seed_start("First scene seed (S)"),
                        out: Path = JsonlOut,
                        occluders: Optional[list[int]] = typer.Option(None, "--occluders",
                                                                      help="Occluder counts cycled over the seeds "
                                                                           "(default: drawn from the seed)"),
                        perception: Optional[str] = typer.Option(
                            None, "--perception", help="The controller's perception: ground_truth (default: the "
                            "simulation's body poses) or depth (the camera images only, as on hardware)"),
                        config: Optional[Path] = ShelfConfigFile,
                        set_: Optional[list[str]] = ShelfSetOption,
                        workers: int = _workers("Local worker processes", max=None),
                        scenario: str = typer.Option("FetchShelf", "--scenario",
                                                     help="The station: a shelf scenario with the Fetch"),
                        scenario_file: Optional[Path] = ScenarioFile):
    """Shelf search on the Fetch in Drake physics (Table 9.2 analogue): scenes S..S+N-1; one JSON
    line per scene (seed, occluders, policy, perception, success, steps, physics-FOSS agreement,
    the config); resumable."""
    cfg = _shelf_config(policy, perception, config, set_, SHELF_CONTROLLER_PERCEPTIONS)
    _need_jsonl(out)
    if occluders and any(not 2 <= n <= 12 for n in occluders):
        _fail(f"--occluders {occluders}: shelf scenes have 2 to 12 occluders")
    _need_shelf_scenario(scenario_file, scenario)
    station = {} if scenario == "FetchShelf" and scenario_file is None else {
        "scenario_name": scenario, "scenario_file": str(scenario_file) if scenario_file is not None else None}
    progress = _RunProgress(scenes, out, "scene")
    try:
        run_shelf_physics_bench(cfg, scenes, seed_start, out, occluders, workers=workers, log=progress.write,
                                progress=progress, **station)
    except KeyboardInterrupt:
        progress.interrupted()
    progress.close()
    recs = physics_records([out], cfg.perception)
    typer.echo(physics_table(recs, tuple(dict.fromkeys(r["policy"] for r in recs))))
    typer.echo(f"results in {out}")


@bench_app.command("rearrange")
def bench_rearrange(method: Optional[str] = typer.Option(None, "--method",
                                                         help=f"Collision checker: {', '.join(REARRANGE_METHODS)}"),
                    scenes: int = typer.Option(10, "--scenes", min=1, help="Scenes (N)"),
                    objects: int = typer.Option(10, "--objects", min=1, max=20, help="Objects per scene (K)"),
                    seed_start: int = _seed_start("First scene seed (S)"),
                    out: Path = JsonlOut,
                    workers: int = _workers("Local worker processes", max=None),
                    config: Optional[Path] = typer.Option(None, "--config", help="A YAML file of RearrangeParams' "
                                                          "fields (the controller: MPPI, placements, grasping)"),
                    set_: Optional[list[str]] = typer.Option(None, "--set", help="Override one controller field, "
                                                             "repeatable: KEY=VALUE, e.g. trajectories=100, "
                                                             "horizon=20 (MPPI's T and H)"),
                    table: bool = typer.Option(False, "--table", help="Only print the table of --out"),
                    scenario: str = typer.Option("PandaTable", "--scenario", help="The station: a table scenario "
                                                 "with the Panda and a front camera"),
                    scenario_file: Optional[Path] = ScenarioFile,
                    scene_set: str = typer.Option("table", "--scene-set", help="table (objects anywhere on the "
                                                  "reachable table, placed anywhere on it) | barrier (a 28 cm box "
                                                  "across the table, objects on its near side, the zone beyond) | "
                                                  "one_side (the same without the barrier: the far half fills up)")):
    """Rearrangement on the Panda in Drake physics (Table 6.3 analogue): scenes S..S+N-1 of K objects
    of the scene set, each moved (two attempts) into the set's zone by the MPPI controller with the
    given collision checker; one JSON line per scene (grasps attempted / successful, placements, sim
    minutes, cpu seconds); resumable. --table: the table of every set and method in --out."""
    _choose("--scene-set", scene_set, REARRANGE_SCENE_SETS, quote=False)
    if not table:
        _choose("--method", method, REARRANGE_METHODS, quote=False)
    _need_jsonl(out)
    if table:
        _need_results((out,), "bench rearrange")
    else:
        _need_rearrange_scenario(scenario_file, scenario)
        station = {} if scenario == "PandaTable" and scenario_file is None else {
            "scenario_name": scenario, "scenario_file": str(scenario_file) if scenario_file is not None else None}
        params = load_config(RearrangeParams, config, set_ or (), **bench_params(method, 0, scene_set).__dict__)
        overrides = {k: v for k, v in dataclasses.asdict(params).items() if k not in ("method", "seed")}
        progress = _RunProgress(scenes, out, "scene")
        try:
            run_rearrange_bench(method, scenes, seed_start, out, objects=objects, workers=workers, log=progress.write,
                                progress=progress, scene_set=scene_set, **overrides, **station)
        except KeyboardInterrupt:
            progress.interrupted()
        progress.close()
    typer.echo(rearrange_table(rearrange_records([out])))
    typer.echo(f"results in {out}")


@bench_app.command("shelf-physics-table")
def bench_shelf_physics_table(files: list[Path] = typer.Argument(..., help="Result .jsonl files "
                                                                         "(ms-drake bench shelf-physics)"),
                              perception: str = typer.Option("ground_truth", "--perception",
                                                             help="The records of this controller perception "
                                                                  "(ground_truth or depth)"),
                              foss: Optional[list[Path]] = typer.Option(
                                  None, "--foss", help="FOSS result .jsonl (ms-drake bench shelf) of the same scenes: "
                                                       "also the search outcome in physics against FOSS, paired")):
    """The Table 9.2 analogue (markdown) from physics shelf result files."""
    for f in files:  # a FOSS file among the physics ones would only be skipped
        if f.is_file() and {r.get("fidelity") for r in read_record_file(f)} == {"foss"}:
            _fail(f"{f} holds FOSS records (ms-drake bench shelf), not physics ones: give it with --foss {f} "
                  "(one --foss per file)")
    _need_results(files, "bench shelf-physics")
    recs = physics_records(files, perception)
    typer.echo(physics_table(recs))
    if foss:
        _need_results(foss, "bench shelf")
        typer.echo("")
        typer.echo(physics_vs_foss(recs, shelf_records(foss), tuple(dict.fromkeys(r["policy"] for r in recs))))


@bench_app.command("shelf-table")
def bench_shelf_table(files: list[Path] = typer.Argument(..., help="Result .jsonl files (ms-drake bench shelf)"),
                      plot_dir: Optional[Path] = typer.Option(None, "--plot", help="Also write the figure here")):
    """Table 9.1 (markdown) from shelf result files, and optionally its figure."""
    _need_results(files, "bench shelf")
    recs = shelf_records(files)
    typer.echo(shelf_table(recs))
    if plot_dir is not None:
        typer.echo(f"wrote {plot_shelf(recs, plot_dir)}")


@bench_app.command("shelf-segmentation")
def bench_shelf_segmentation_cmd(
        scenes: int = typer.Option(100, "--scenes", min=1, help="Scenes per occluder count"),
        occluders: list[int] = typer.Option([4, 6, 8, 10], "--occluders", help="Occluder counts (repeat)"),
        seed_start: int = _seed_start("First scene seed"),
        out: Path = typer.Option(..., "--out", help="Result .jsonl (one line per scene; resumes)"),
        noise: float = typer.Option(0.0, "--noise", min=0.0, help="Depth noise std [m]"),
        dropout: float = typer.Option(0.0, "--dropout", min=0.0, max=0.99, help="Fraction of pixels lost"),
        scenario: str = typer.Option("FetchShelf", "--scenario",
                                     help="Whose shelf and camera render the scenes: a shelf scenario (FetchShelfL515 "
                                          "renders through its L515-like depth sensor model)"),
        workers: int = _workers("Local worker processes", max=None),
        use_ray: bool = typer.Option(False, "--ray", help="Run on Ray")):
    """How well the ShelfSegmenter recovers Table 9.1's scenes from the front camera's depth image."""
    bad = [n for n in occluders if not 2 <= n <= 12]
    if bad:
        _fail(f"--occluders {' '.join(map(str, bad))}: shelf scenes have 2 to 12 occluders")
    _need_shelf_scenario(None, scenario)
    r = bench_shelf_segmentation(scenes, occluders, seed_start, out, noise=noise, dropout=dropout, workers=workers,
                                 use_ray=use_ray, scenario=scenario)
    typer.echo(json.dumps(r, indent=1))


@bench_app.command("shelf-scenes")
def bench_shelf_scenes_cmd(count: int = typer.Option(1000, "--count", min=1, help="Scenes"),
                           seed_start: int = _seed_start("First scene seed")):
    """CPU time per generated shelf scene (one core): median, p90, max, per occluder count."""
    r = bench_shelf_scenes(count, seed_start)
    typer.echo(f"{r['scenes']} scenes: median {r['median_ms']:.2f} ms, p90 {r['p90_ms']:.2f} ms, max "
               f"{r['max_ms']:.1f} ms CPU per scene; {r['mean_tries']:.2f} scenes drawn per scene")
    typer.echo("median by occluders: " + ", ".join(f"{n}: {v:.1f}" for n, v in r["median_ms_by_occluders"].items()))


@data_app.command("shelf")
def data_shelf(count: int = typer.Option(..., "--count", min=1, help="Scenes (N)"),
               out: Path = typer.Option(..., "--out", help="Output folder (shard_<k>.npz; resumes)"),
               seed_start: int = _seed_start("First scene seed"),
               shard_size: int = typer.Option(100, "--shard-size", min=1, help="Scenes per shard"),
               depth: bool = typer.Option(True, "--depth/--no-depth", help="Render the Drake depth image of each scene"),
               depth_block: int = typer.Option(1, "--depth-block", min=1, help="Store depth averaged over BxB blocks"),
               workers: int = _workers(),
               ray: bool = Ray,
               ray_address: Optional[str] = RayAddress):
    """Shelf scenes with their ground-truth target distributions (floor 2D, image-x 1D) and depth
    images, sharded; shards already written are kept."""
    t0 = time.perf_counter()
    bar, progress = _job_bar((count + shard_size - 1) // shard_size, "shards", "shard")
    res = write_shelf_dataset(out, count, seed_start, shard_size, depth, workers, ray or ray_address is not None,
                              ray_address, progress, depth_block)
    bar.close()
    typer.echo(f"{res['written']} shards written, {res['skipped']} already there, {len(res['failed'])} failed, "
               f"in {out} ({time.perf_counter() - t0:.1f} s)")
    if res["failed"]:
        raise typer.Exit(1)


# ---------------------------------------------------------------------------------------------
# Grasp sets: ms-drake data grasps


@data_app.command("grasps")
def data_grasps(objects: str = typer.Option(..., "--objects", help="Object set: procedural, ycb, random_urdfs, targets"),
                out: Optional[Path] = typer.Option(None, "--out", help="Folder (default: models/objects/<set>/grasps)"),
                model: str = typer.Option("soft_point", "--model", help="Jaw contact model: soft_point, reach, 6dfc, ..."),
                jaw: int = typer.Option(200, "--jaw", min=0, help="Antipodal jaw grasps per object"),
                suction: int = typer.Option(200, "--suction", min=0, help="Suction grasps per object"),
                robust: int = typer.Option(4, "--robust", min=1, help="Robust trials per grasp (and approach)"),
                seed: int = typer.Option(0, "--seed", min=0, help="Sampling seed"),
                limit: Optional[int] = typer.Option(None, "--limit", min=1, help="Only the first K objects"),
                workers: int = _workers()):
    """Pre-computed jaw and suction grasps with their robust quality, one npz per object;
    objects already done with the same parameters are kept (resume)."""
    if objects not in [*available_sets(), "targets"]:
        _fail(f"--objects {objects!r}: choose one of {', '.join(available_sets())}, targets")
    cmd = " ".join(["ms-drake", "data", "grasps", "--objects", objects, "--model", model, "--jaw", str(jaw),
                    "--suction", str(suction), "--robust", str(robust), "--seed", str(seed)]
                   + (["--limit", str(limit)] if limit else []) + (["--out", str(out)] if out else []))
    n = len(get_object_set(objects).objects[:limit])
    bar, progress = _job_bar(n, f"{objects} grasp sets", "object", name=lambda job: job[0])
    try:
        man = write_grasp_sets(objects, out, workers, limit, cmd, progress, model=model, jaw=jaw, suction=suction,
                               robust_samples=robust, seed=seed)
    except MsDrakeError as e:
        _fail(str(e))
    bar.close()
    cpu = man.get("cpu_s_per_object", {})
    typer.echo(f"{len(man['objects'])} objects in the manifest, {len(man['errors'])} failed; CPU per object "
               f"median {cpu.get('median', 0):.2f} s, max {cpu.get('max', 0):.2f} s; {man['wall_s']:.0f} s wall")
    if man["errors"]:
        raise typer.Exit(1)


# ---------------------------------------------------------------------------------------------
# Learned occupancy (Ch. 8.3): dataset, training, Table 8.1


@data_app.command("occupancy")
def data_occupancy(count: int = typer.Option(..., "--count", min=1, help="Images (N), rounded up to whole shards"),
                   out: Path = typer.Option(..., "--out", help="Output folder (shard_<k>_<split>.npz; resumes)"),
                   seed: int = DatasetSeed,
                   views: int = typer.Option(8, "--views", min=1, help="Camera views (images) per heap"),
                   heaps_per_shard: int = typer.Option(4, "--heaps-per-shard", min=1, help="Heaps per shard"),
                   workers: int = _workers(),
                   ray: bool = Ray,
                   ray_address: Optional[str] = RayAddress,
                   target: Optional[list[str]] = typer.Option(None, "--target", help="Out-of-set box target "
                                                              "'L,W,T' in metres (repeatable), e.g. 0.06,0.06,0.005, or a "
                                                              "cylinder lying flat 'cyl:L,D', e.g. cyl:0.15,0.015"),
                   test_only: bool = typer.Option(False, "--test-only", help="Every shard a test shard"),
                   layout: str = typer.Option("spread", "--layout", help="How the heaps are dropped: spread "
                                              "(Gaussian offsets, released just above the pile) or compact "
                                              "(as the bin search's compact heap layout: centre +-10 cm, offsets +-2.5 cm, "
                                              "released from 20 cm)"),
                   best_match: Optional[float] = typer.Option(None, "--best-match", min=0.0, max=0.99,
                                                              help="Ground truth of a partly seen target no grid "
                                                              "placement matches (IoU > 0.9): the placements within "
                                                              "this IoU of the best one (default: the observed "
                                                              "modal mask)"),
                   ground_truth: str = typer.Option("generator", "--ground-truth", help="generator (the "
                                                    "reference's: every placement the image allows) or posterior "
                                                    "(the target's own amodal mask, the target placed in the pile "
                                                    "as the compact heap layout places it)")):
    """Depth images + target modal masks + ground-truth occupancy (ten box aspect ratios), split by
    image and by object, sharded; shards already written are kept."""
    try:
        targets = [("cylinder", *(float(v) for v in t[4:].split(","))) if t.startswith("cyl:")
                   else tuple(float(v) for v in t.split(",")) for t in target] if target else None
    except ValueError:
        _fail(f"--target {target}: give L,W,T in metres, e.g. --target 0.06,0.06,0.005, or cyl:L,D")
    if targets and any(len(t) != 3 for t in targets):
        _fail(f"--target {target}: give three numbers L,W,T per box target, two (cyl:L,D) per cylinder")
    _choose("--layout", layout, tuple(HEAP_LAYOUTS))
    _choose("--ground-truth", ground_truth, GROUND_TRUTHS)
    if ground_truth == "posterior" and best_match is not None:
        _fail("--best-match is a setting of the generator's ground truth; drop it with --ground-truth posterior")
    t0 = time.perf_counter()
    per = views * heaps_per_shard
    bar, progress = _job_bar(-(-count // per), "shards", "shard")
    res = write_occupancy_dataset(out, count, seed, views, heaps_per_shard, workers,
                                  ray or ray_address is not None, ray_address, progress, targets=targets,
                                  test_only=test_only, layout=layout, best_match=best_match,
                                  ground_truth=ground_truth)
    bar.close()
    typer.echo(f"{res['written']} shards written, {res['skipped']} already there, {len(res['failed'])} failed, "
               f"in {out} ({time.perf_counter() - t0:.1f} s)")
    if res["failed"]:
        raise typer.Exit(1)


train_app = typer.Typer(add_completion=False, no_args_is_help=True, help="Training of the learned models.")
app.add_typer(train_app, name="train")


@train_app.command("occupancy")
def train_occupancy_cmd(data: Path = typer.Option(..., "--data", help="Dataset folder (ms-drake data occupancy)"),
                        out: Path = typer.Option(Path("out/weights/occupancy.pt"), "--out", help="Weights file"),
                        epochs: int = typer.Option(12, "--epochs", min=1, help="Epochs (cosine schedule over all)"),
                        batch: int = typer.Option(32, "--batch", min=1, help="Batch size"),
                        seed: int = TrainingSeed,
                        threads: int = typer.Option(1, "--threads", min=1, help="torch threads (1: on a shared "
                                                    "machine 2 threads were 5x slower, their OpenMP workers spinning)"),
                        max_minutes: float = typer.Option(60.0, "--max-minutes", help="Stop after the epoch that "
                                                          "would end past this wall time"),
                        lr: float = typer.Option(1e-3, "--lr", help="AdamW learning rate (cosine decay to 0)"),
                        positive_weight: float = typer.Option(0.0, "--positive-weight", min=0.0,
                                                              help="Squared errors on ground-truth positives "
                                                              "(> 0.1) count 1 + W times"),
                        init: Optional[Path] = typer.Option(None, "--init", help="Start from these weights "
                                                            "(fine-tuning; their network configuration)"),
                        device: str = TrainDevice,
                        overwrite_shipped: bool = OverwriteShipped):
    """Train the occupancy network; resumes from OUT.ckpt; writes OUT (weights + meta)."""
    torch_device(device)
    _need_training_out(out, overwrite_shipped)
    if init is not None:
        _need_weights("--init", init, load_occupancy_net, "occupancy")
    bar, progress = _epoch_bar(epochs)
    cmd = " ".join(["ms-drake", "train", "occupancy", "--data", str(data), "--out", str(out), "--epochs", str(epochs),
                    "--batch", str(batch), "--seed", str(seed), "--threads", str(threads), "--lr", str(lr),
                    "--positive-weight", str(positive_weight)] + (["--init", str(init)] if init else [])
                   + _device_args(device) + (["--overwrite-shipped"] if overwrite_shipped else []))
    meta = train_occupancy(data, out, epochs=epochs, batch=batch, seed=seed, threads=threads,
                           max_minutes=max_minutes, progress=progress, command=cmd, lr=lr,
                           positive_weight=positive_weight, init=init, device=device)
    bar.close()
    _echo_trained(out, meta, epochs)


@bench_app.command("paired")
def bench_paired(a: Path = typer.Argument(..., help="Result .jsonl of policy A"),
                 b: Path = typer.Argument(..., help="Result .jsonl of policy B (the same heaps)")):
    """Paired sign test of success, A vs B, on the heaps both files hold."""
    _need_results((a, b), "bench search")
    r = paired_comparison(read_search_records(a), read_search_records(b), (str(a), str(b)))
    typer.echo(f"{r['heaps']} heaps: only A {len(r['only_a'])}, only B {len(r['only_b'])}, both {r['both']}, "
               f"neither {r['neither']}; two-sided sign test p = {r['p']:.3g}")
    typer.echo(f"only A: {r['only_a']}")
    typer.echo(f"only B: {r['only_b']}")


@bench_app.command("replay")
def bench_replay(file: Path = typer.Argument(..., help="Result .jsonl of `ms-drake bench search`"),
                 heap_dir: Optional[Path] = typer.Option(None, "--heap-dir", help="The heap cache the records "
                                                          "searched (default: regenerate each heap from its seed)"),
                 seeds: Optional[list[int]] = typer.Option(None, "--seed", help="Replay these seeds (repeatable)"),
                 count: Optional[int] = typer.Option(None, "--count", min=1, help="Replay the first K records "
                                                     "(default: all)"),
                 heaps_only: bool = typer.Option(False, "--heaps-only", help="Check only that each record's "
                                                 "heap (cached or regenerated) has the record's digest; no search"),
                 workers: int = _workers("Parallel workers (W)")):
    """Re-run recorded searches with this code and check that each ends as recorded: the same
    actions, grasp kinds and outcomes, and the same heap (its digest). Exit code 1 if one differs."""
    _need_results((file,), "bench search")

    def progress(r):
        heap = "" if r["heap_same"] is None else f"heap {'same' if r['heap_same'] else 'DIFFERS'}"
        if heaps_only:
            what = "ERROR: " + r.get("error", "") if r["differs"] == ["error"] else (heap or "no digest recorded")
        else:
            what = ("same" if r["same"] else "DIFFERS in " + ", ".join(r["differs"] or ["heap"])) + \
                   (f"; {heap}" if heap else "")
        typer.echo(f"{r['policy']} seed {r['seed']}: {what}")

    try:
        rows = (check_record_heaps if heaps_only else replay_records)(
            file, str(heap_dir) if heap_dir is not None else None, seeds=seeds or None, count=count,
            workers=workers, progress=progress)
    except ValueError as e:
        _fail(str(e))
    same = sum(r["same"] for r in rows)
    codes = sorted({r["code"] or "(not recorded)" for r in rows})
    if heaps_only:
        typer.echo(f"{same} of {len(rows)} records' heaps are the recorded ones (recorded with {', '.join(codes)})")
    else:
        typer.echo(f"{same} of {len(rows)} records replay with code {rows[0]['code_now'] if rows else '-'} "
                   f"(recorded with {', '.join(codes)})")
    if same < len(rows):
        raise typer.Exit(1)


@bench_app.command("occupancy")
def bench_occupancy_cmd(data: Path = typer.Option(..., "--data", help="Dataset folder (its test shards)"),
                        weights: Optional[Path] = typer.Option(None, "--weights", help="Weights (default: shipped)"),
                        out: Optional[Path] = typer.Option(None, "--out", help="Also write the rows as JSON here"),
                        scaling: bool = typer.Option(False, "--scaling/--no-scaling",
                                                     help="Input scaling by the target's size over its ratio's box"),
                        sensor: Optional[str] = typer.Option(
                            None, "--sensor", help="Depth sensor preset (none | phoxi | l515 | primesense): bench on "
                            "DATA/<preset>, a test set made first if absent with that sensor model and hole filling"),
                        images: int = typer.Option(96, "--images", min=1, help="With --sensor: images of the test set"),
                        sensor_seed: int = typer.Option(7, "--sensor-seed", help="With --sensor: the test set's seed"),
                        device: str = Device):
    """Table 8.1: balanced accuracy and IoU per aspect ratio on the held-out test shards, and the
    inference time per image on one core."""
    torch_device(device)
    _need_weights("--weights", weights, load_occupancy_net, "occupancy")
    res = bench_occupancy(data, weights, scaling, sensor=sensor, sensor_images=images, sensor_seed=sensor_seed,
                          device=device)
    typer.echo("| ratio | images | hidden | bal. acc. % | IoU | MSE |")
    typer.echo("|---|---|---|---|---|---|")
    for r, raw in zip(res["rows"], res["raw_rows"]):
        typer.echo(f"| {r['ratio']}{':1' if isinstance(r['ratio'], int) else ''} | {r['images']} | {r['hidden']} | "
                   f"{100 * r['balanced_accuracy']:.1f} | {r['iou']:.2f} | {r['mse']:.4f} | (network alone: "
                   f"{100 * raw['balanced_accuracy']:.1f} / {raw['iou']:.2f})")
    for name, r in res["baselines"].items():
        typer.echo(f"baseline {name}: bal. acc. {100 * r['balanced_accuracy']:.1f} %, IoU {r['iou']:.2f}, "
                   f"MSE {r['mse']:.4f}")
    typer.echo(f"inference: {res['ms_per_image']:.1f} ms wall, {res['cpu_ms_per_image']:.1f} ms CPU per image (median "
               f"of {res['timed']}, one torch thread, preprocessing and upsampling included)")
    if out is not None:
        _write_json(out, res)
        typer.echo(f"wrote {out}")


# -- Learned shelf occupancy (Ch. 9.4.2): ms-drake train / bench shelf-occupancy ------------------------


@train_app.command("shelf-occupancy")
def train_shelf_occupancy_cmd(
        data: Path = typer.Option(..., "--data", help="Dataset folder with train/ (ms-drake data shelf --depth-block 4)"),
        out: Path = typer.Option(Path("out/weights/shelf_occupancy.pt"), "--out", help="Weights file"),
        epochs: int = typer.Option(8, "--epochs", min=1, help="Epochs (cosine schedule over all)"),
        batch: int = typer.Option(32, "--batch", min=1, help="Batch size"),
        seed: int = TrainingSeed,
        threads: int = typer.Option(1, "--threads", min=1, help="torch threads (1 on this shared machine)"),
        max_minutes: float = typer.Option(30.0, "--max-minutes", help="Stop after the epoch that ends past this"),
        device: str = TrainDevice,
        overwrite_shipped: bool = OverwriteShipped):
    """Train the shelf occupancy network; resumes from OUT.ckpt; writes OUT (weights + meta)."""
    torch_device(device)
    _need_training_out(out, overwrite_shipped)
    bar, progress = _epoch_bar(epochs)
    cmd = " ".join(["ms-drake", "train", "shelf-occupancy", "--data", str(data), "--out", str(out), "--epochs",
                    str(epochs), "--batch", str(batch), "--seed", str(seed), "--threads", str(threads),
                    "--max-minutes", f"{max_minutes:g}"] + _device_args(device)
                   + (["--overwrite-shipped"] if overwrite_shipped else []))
    meta = train_shelf_occupancy(data, out, epochs=epochs, batch=batch, seed=seed, threads=threads,
                                 max_minutes=max_minutes, progress=progress, command=cmd, device=device)
    bar.close()
    _echo_trained(out, meta, epochs, loss_format=".4f")


@bench_app.command("shelf-occupancy")
def bench_shelf_occupancy_cmd(
        data: Path = typer.Option(..., "--data", help="Dataset folder with test/ (ms-drake data shelf --depth-block 4)"),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Weights (default: shipped)"),
        out: Optional[Path] = typer.Option(None, "--out", help="Also write the results as JSON here"),
        device: str = Device):
    """Held-out accuracy of the learned shelf occupancy: total variation of P(x), balanced accuracy
    and IoU (at the reference's thresholds) per target height, against a uniform P(x); inference ms."""
    torch_device(device)
    _need_weights("--weights", weights, load_shelf_occupancy_net, "shelf-occupancy")
    res = bench_shelf_occupancy(data, weights, device=device)
    typer.echo(f"{res['test_scenes']} test scenes (seeds {res['test_seeds'][0]}-{res['test_seeds'][1]})")
    typer.echo("| target (w x d x h cm) | scenes | TV | bal. acc. % | IoU | TV, all images | uniform TV | "
               "uniform bal. acc. % | uniform IoU |")
    typer.echo("|---|---|---|---|---|---|---|---|---|")
    for r in res["rows"] + [dict(size=None, scenes=res["test_scenes"], **res["overall"])]:
        name = "all" if r["size"] is None else " x ".join(f"{100 * v:g}" for v in r["size"])
        o, a, u = r["own"], r["all_images"], r["uniform"]
        typer.echo(f"| {name} | {r['scenes']} | {o['tv']:.3f} | {100 * o['balanced_accuracy']:.1f} | {o['iou']:.2f} | "
                   f"{a['tv']:.3f} | {u['tv']:.3f} | {100 * u['balanced_accuracy']:.1f} | {u['iou']:.2f} |")
    typer.echo(f"inference: {res['ms_per_image']:.1f} ms per image (median of {res['timed']}, p90 "
               f"{res['ms_p90']:.1f}; one torch thread, from the 480 x 640 depth image)")
    if out is not None:
        _write_json(out, res)
        typer.echo(f"wrote {out}")


# ---------------------------------------------------------------------------------------------
# Learned depth segmentation (Ch. 5): ms-drake data / train / bench segmentation


@data_app.command("segmentation")
def data_segmentation(count: int = typer.Option(..., "--count", min=1, help="Images (N), rounded up to whole shards"),
                      out: Path = typer.Option(..., "--out", help="Output folder (shard_<k>_<split>.npz/.json; resumes)"),
                      seed: int = DatasetSeed,
                      views: int = typer.Option(4, "--views", min=1, help="Camera views (images) per heap"),
                      heaps_per_shard: int = typer.Option(8, "--heaps-per-shard", min=1, help="Heaps per shard"),
                      noise: float = typer.Option(0.0, "--noise", min=0.0, help="Gaussian depth noise sigma, m"),
                      dropout: float = typer.Option(0.0, "--dropout", min=0.0, max=0.99,
                                                    help="Missing-pixel rate (half single pixels, half at edges)"),
                      sensor: str = typer.Option("none", "--sensor", help="Depth sensor model: none | random (a preset "
                                                 "and its parameters drawn per image) | phoxi | l515 | primesense; "
                                                 "the inputs are made from the hole-filled depth"),
                      workers: int = _workers(),
                      ray: bool = Ray,
                      ray_address: Optional[str] = RayAddress):
    """WISDOM-Sim-like depth images of heaps with modal masks (COCO JSON), split by image and by
    object, sharded; shards already written are kept."""
    t0 = time.perf_counter()
    bar, progress = _job_bar(-(-count // (views * heaps_per_shard)), "shards", "shard")
    res = write_segmentation_dataset(out, count, seed, views, heaps_per_shard, workers, ray or ray_address is not None,
                                     ray_address, progress, noise=noise, dropout=dropout, sensor=sensor)
    bar.close()
    wall = time.perf_counter() - t0
    per = f"; {res['cpu'] / res['images']:.3f} CPU-s and {wall * workers / res['images']:.3f} wall-s x workers " \
          "per image" if res["images"] else ""
    typer.echo(f"{res['written']} shards ({res['images']} images) written, {res['skipped']} already there, "
               f"{len(res['failed'])} failed, in {out} ({wall:.1f} s{per}); COCO: {', '.join(res['coco'])}")
    if res["failed"]:
        raise typer.Exit(1)


@train_app.command("segmentation")
def train_segmentation_cmd(
        data: Path = typer.Option(..., "--data", help="Dataset folder (ms-drake data segmentation)"),
        out: Path = typer.Option(Path("out/weights/segmentation.pt"), "--out", help="Weights file"),
        epochs: int = typer.Option(8, "--epochs", min=1, help="Epochs (cosine schedule over all)"),
        batch: int = typer.Option(16, "--batch", min=1, help="Batch size (96 x 128 windows)"),
        lr: float = typer.Option(2e-3, "--lr", help="AdamW learning rate (cosine decay to 0)"),
        max_images: Optional[int] = typer.Option(None, "--max-images", min=1, help="Train on the first N images"),
        steps_per_epoch: Optional[int] = typer.Option(None, "--steps-per-epoch", min=1, help="Batches per epoch, "
                                                      "from the shards on disk at its start (default: one pass)"),
        init: Optional[Path] = typer.Option(None, "--init", help="Start from these weights (fine-tuning)"),
        object_fraction: Optional[float] = typer.Option(None, "--object-fraction", min=0.0, max=1.0,
                                                        help="Supervise only this fraction of the training "
                                                        "objects, per object set (the others' pixels carry no loss)"),
        noise: float = typer.Option(0.0, "--noise", min=0.0, help="Augmentation: Gaussian depth noise sigma, m, on "
                                    "half the images of a batch (the writer's sensor model)"),
        dropout: float = typer.Option(0.0, "--dropout", min=0.0, max=0.99, help="Augmentation: missing-pixel rate "
                                      "on the same images"),
        seed: int = TrainingSeed,
        threads: int = TorchThreads,
        max_minutes: float = typer.Option(60.0, "--max-minutes", help="Stop after the epoch that would end past "
                                          "this wall time"),
        device: str = TrainDevice,
        overwrite_shipped: bool = OverwriteShipped):
    """Train the depth segmentation network; resumes from OUT.ckpt; writes OUT (weights + meta) after
    every epoch."""
    torch_device(device)
    _need_training_out(out, overwrite_shipped)
    if init is not None:
        _need_weights("--init", init, load_segmentation_net, "segmentation")
    bar, progress = _epoch_bar(epochs)
    cmd = " ".join(["ms-drake", "train", "segmentation", "--data", str(data), "--out", str(out), "--epochs",
                    str(epochs), "--batch", str(batch), "--lr", str(lr), "--seed", str(seed), "--threads",
                    str(threads)] + (["--max-images", str(max_images)] if max_images else [])
                   + (["--steps-per-epoch", str(steps_per_epoch)] if steps_per_epoch else [])
                   + (["--init", str(init)] if init else [])
                   + (["--object-fraction", str(object_fraction)] if object_fraction is not None else [])
                   + (["--noise", str(noise), "--dropout", str(dropout)] if noise > 0 or dropout > 0 else [])
                   + _device_args(device) + (["--overwrite-shipped"] if overwrite_shipped else []))
    meta = train_segmentation(data, out, epochs=epochs, batch=batch, seed=seed, threads=threads, lr=lr,
                              max_minutes=max_minutes, progress=progress, command=cmd, max_images=max_images,
                              steps_per_epoch=steps_per_epoch, init=init, object_fraction=object_fraction,
                              noise=noise, dropout=dropout, device=device)
    bar.close()
    _echo_trained(out, meta, epochs)


@bench_app.command("collision")
def bench_collision_cmd(
        method: str = typer.Option(..., "--method", help="net | pointnet_grid | coal_reconstruction | sdf"),
        scenes: int = typer.Option(50, "--scenes", min=1, help="Held-out scenes (2,048 queries each)"),
        seed_start: int = _seed_start("Seed of the first scene", 100000),
        out: Optional[Path] = typer.Option(None, "--out", help="Write the result (method, accuracy, ap, "
                                           "us_per_query, queries) as JSON"),
        cache: Optional[Path] = typer.Option(None, "--cache", help="Keep / reuse the scenes in this folder"),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Network weights (default "
                                               "models/weights/collision.pt; pointnet_grid: "
                                               "collision_pointnet_grid.pt)"),
        threads: int = typer.Option(1, "--threads", min=1, help="torch threads (net)"),
        sensor: str = typer.Option("none", "--sensor", help="Depth sensor preset of the scene clouds: none | phoxi "
                                   "| l515 | primesense (the same scenes and queries)"),
        device: str = Device):
    """Table 6.1: collision accuracy, AP and CPU time per query of one method on held-out scenes."""
    _choose("--method", method, COLLISION_METHODS)
    _choose("--sensor", sensor, DEPTH_SENSOR_PRESETS)
    if method in COLLISION_NETWORKS:
        torch_device(device)
        _need_weights("--weights", weights or default_collision_weights(method),
                      lambda p: load_collision_net(p, method), "collision")
    bar = tqdm(total=scenes, desc=method, unit="scene")
    res = bench_collision(method, scenes, seed_start, cache, weights, threads, progress=lambda k: bar.update(1),
                          device=device, sensor=sensor)
    bar.close()
    typer.echo(f"{method}: {res['queries']} queries ({100 * res['positive']:.1f} % in collision): accuracy "
               f"{100 * res['accuracy']:.1f} %, AP {res['ap']:.3f}, {res['us_per_query']:.1f} us CPU per query, "
               f"{res['setup_ms_per_scene']:.1f} ms set-up per scene")
    if out is not None:
        _write_json(out, res)


@bench_app.command("mppi")
def bench_mppi_cmd(
        method: str = typer.Option("net", "--method", help="Collision checker: net | pointnet_grid | "
                                   "coal_reconstruction | sdf"),
        planner: str = typer.Option("ours", "--planner", help="ours | ours_lazy | pytorch_mppi (the `bench` extra)"),
        scenes: int = typer.Option(5, "--scenes", min=1, help="Held-out tabletop scenes"),
        seed_start: int = _seed_start("Seed of the first scene", 100000),
        trajectories: int = typer.Option(300, "--trajectories", min=1, help="T (the reference: 300)"),
        horizon: int = typer.Option(40, "--horizon", min=1, help="H (the reference: 40)"),
        steps: int = typer.Option(5, "--steps", min=1, help="MPPI calls per scene (fewer when the goal is reached)"),
        out: Optional[Path] = typer.Option(None, "--out", help="Write the records (one per scene) as JSON"),
        cache: Optional[Path] = typer.Option(None, "--cache", help="Keep / reuse the scenes in this folder"),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Network weights (default: shipped)"),
        threads: int = TorchThreads,
        device: str = typer.Option("cpu", "--device", help="Where the collision network's queries and "
                                   "pytorch_mppi's rollouts run: cpu, cuda (a GPU; an error on a machine without "
                                   "one) or auto (cuda where a GPU exists, else cpu); kinematics stay on the CPU")):
    """Speed of one MPPI call on the Panda (T x H waypoints, every link and the gripper checked
    against the scene cloud): CPU ms per call and rate, ours or pytorch_mppi's."""
    _choose("--method", method, COLLISION_METHODS)
    _choose("--planner", planner, MPPI_PLANNERS)
    torch_device(device)
    if method in COLLISION_NETWORKS:
        _need_weights("--weights", weights or default_collision_weights(method),
                      lambda p: load_collision_net(p, method), "collision")
    bar = tqdm(total=scenes, desc=f"{planner} {method}", unit="scene")
    recs = bench_mppi(method, scenes, seed_start, trajectories, horizon, steps, planner, cache, weights, threads,
                      progress=lambda r: bar.update(1), device=device)
    bar.close()
    ms = np.median([r["ms_per_step"] for r in recs])
    typer.echo(f"{planner} with {method}, T = {trajectories}, H = {horizon}: median {ms:.0f} ms CPU per call "
               f"({1e3 / ms:.2f} Hz), {np.median([r['checks_per_s'] for r in recs]):.0f} waypoints checked per s; "
               f"goal reached in {sum(r['reached'] for r in recs)}/{len(recs)} scenes")
    if out is not None:
        _write_json(out, recs)
        typer.echo(f"wrote {out}")


@bench_app.command("segmentation")
def bench_segmentation_cmd(
        backend: str = typer.Option(..., "--backend", help="euclidean | region_growing | learned | ground_truth"),
        images: int = typer.Option(100, "--images", min=1, help="Held-out images (one heap each)"),
        seed_start: int = _seed_start("Seed of the first image", 100000),
        out: Optional[Path] = typer.Option(None, "--out", help="Write the result (backend, ap, ar, images) as JSON"),
        workers: int = _workers(),
        noise: float = typer.Option(0.0, "--noise", min=0.0, help="Gaussian depth noise sigma, m"),
        dropout: float = typer.Option(0.0, "--dropout", min=0.0, max=0.99, help="Missing-pixel rate"),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Learned backend's weights (default: shipped)"),
        cache: Optional[Path] = typer.Option(None, "--cache", help="Keep / reuse the rendered images in this folder"),
        sensor: str = typer.Option("none", "--sensor", help="Depth sensor model preset: none | phoxi | l515 | "
                                   "primesense (ms_drake.station.sensor_model)"),
        fill_holes: bool = typer.Option(True, "--fill-holes/--no-fill-holes",
                                        help="Fill the depth's holes before segmenting (geometry.preprocess_depth)"),
        device: str = Device):
    """Table B.1: COCO mask AP / AR@100 of one segmentation backend on held-out heap images made from
    the seeds."""
    if backend == "learned":
        torch_device(device)
        _need_weights("--weights", weights, load_segmentation_net, "segmentation")
    bar = tqdm(total=images, desc=f"bench {backend}", unit="image")
    res = bench_segmentation(backend, images, seed_start, workers, noise, dropout, weights, progress=bar.update,
                             cache=cache, sensor=sensor, fill_holes=fill_holes, device=device)
    bar.close()
    typer.echo(f"{backend}: AP {res['ap']:.3f}, AP50 {res['ap50']:.3f}, AR@100 {res['ar']:.3f} on {res['images']} "
               f"images ({res['gt']} masks, {res['dt']} detections); median {res['seconds_median'] * 1000:.0f} ms "
               "per image")
    if out is not None:
        _write_json(out, res)
        typer.echo(f"wrote {out}")


# ---------------------------------------------------------------------------------------------
# Target matching (App. C.2): ms-drake data / train matcher, ms-drake bench target-detection


@data_app.command("collision")
def data_collision(count: int = typer.Option(..., "--count", min=1, help="Scenes, rounded up to whole shards"),
                   out: Path = typer.Option(..., "--out", help="Output folder (shard_<k>_<split>.npz; resumes)"),
                   seed: int = DatasetSeed,
                   sensor: str = typer.Option("none", "--sensor", help="Depth sensor model of the scene clouds: none "
                                              "| random (a preset and its parameters drawn per scene) | phoxi | l515 "
                                              "| primesense"),
                   workers: int = _workers(),
                   ray: bool = Ray,
                   ray_address: Optional[str] = RayAddress):
    """Tabletop scenes (point cloud from the PandaTable camera) with a query object and 2,048 poses
    along 64 trajectories labelled by exact mesh collision (Ch. 6); split by scene and object;
    shards already written are kept."""
    _choose("--sensor", sensor, SENSOR_OPTIONS)
    t0 = time.perf_counter()
    bar, progress = _job_bar(-(-count // COLLISION_SCENES_PER_SHARD), "shards", "shard")
    res = write_collision_dataset(out, count, seed, workers, ray or ray_address is not None, ray_address, progress,
                                  sensor=sensor)
    bar.close()
    per = f"; {res['cpu'] / res['scenes']:.2f} CPU-s per scene" if res["scenes"] else ""
    typer.echo(f"{res['written']} shards ({res['scenes']} scenes, {res['queries']} queries, "
               f"{100 * res['positive']:.1f} % in collision) written, {res['skipped']} already there, "
               f"{len(res['failed'])} failed, in {out} ({time.perf_counter() - t0:.0f} s{per})")
    if res["failed"]:
        raise typer.Exit(1)


@data_app.command("matcher")
def data_matcher(heaps: int = typer.Option(..., "--heaps", min=1, help="Heaps, rounded up to whole shards"),
                 out: Path = typer.Option(..., "--out", help="Output folder (matcher_<k>_<split>.npz; resumes)"),
                 seed: int = DatasetSeed,
                 heaps_per_shard: int = typer.Option(10, "--heaps-per-shard", min=1, help="Heaps per shard"),
                 workers: int = _workers()):
    """Colour heap images with object crops and template views of every object, for the siamese
    target matcher; split by object; shards already written are kept."""
    t0 = time.perf_counter()
    bar, progress = _job_bar(-(-heaps // heaps_per_shard), "shards", "shard")
    res = write_matcher_dataset(out, heaps, seed, heaps_per_shard, workers, progress)
    bar.close()
    typer.echo(f"{res['written']} shards ({res['crops']} object crops) written, {res['skipped']} already there, "
               f"{len(res['failed'])} failed, in {out} ({time.perf_counter() - t0:.0f} s, {res['cpu']:.0f} CPU-s)")
    if res["failed"]:
        raise typer.Exit(1)


@train_app.command("collision")
def train_collision_cmd(
        data: Path = typer.Option(..., "--data", help="Dataset folder (ms-drake data collision)"),
        out: Path = typer.Option(Path("out/weights/collision.pt"), "--out", help="Weights file"),
        epochs: int = typer.Option(20, "--epochs", min=1, help="Passes over the training scenes"),
        seed: int = TrainingSeed,
        threads: int = TorchThreads,
        lr: float = typer.Option(1e-3, "--lr", min=0.0, help="Adam learning rate"),
        max_minutes: float = typer.Option(90.0, "--max-minutes", min=0.1, help="Stop after the epoch that "
                                          "would pass this wall time"),
        pointnet_grid: bool = typer.Option(False, "--pointnet-grid", help="Train the PointNet-grid ablation "
                                           "(no 3D convolutions)"),
        hidden: int = typer.Option(128, "--hidden", min=8, help="Width of the query classifier"),
        query_layers: int = typer.Option(1, "--query-layers", min=0, help="Hidden layers of the query classifier "
                                         "after its first"),
        voxel_features: int = typer.Option(64, "--voxel-features", min=8, help="Voxel feature channels (the "
                                           "PointNet-grid needs 64, the point features' width)"),
        encoders: Optional[Path] = typer.Option(None, "--encoders", help="Weights file whose scene and object "
                                                "encoders are copied and frozen: only the query classifier "
                                                "trains"),
        device: str = TrainDevice,
        overwrite_shipped: bool = OverwriteShipped):
    """Train SceneCollisionNet (Ch. 6); resumes from OUT.ckpt; writes OUT (weights + meta)."""
    torch_device(device)
    _need_training_out(out, overwrite_shipped)
    if encoders is not None:
        _need_weights("--encoders", encoders, load_collision_net, "collision")
    cmd = " ".join(["ms-drake", "train", "collision", "--data", str(data), "--out", str(out), "--epochs", str(epochs),
                    "--seed", str(seed), "--threads", str(threads), "--lr", str(lr), "--hidden", str(hidden),
                    "--query-layers", str(query_layers), "--voxel-features", str(voxel_features)]
                   + (["--pointnet-grid"] if pointnet_grid else [])
                   + (["--encoders", str(encoders)] if encoders is not None else [])
                   + _device_args(device) + (["--overwrite-shipped"] if overwrite_shipped else []))
    config = CollisionNetConfig(hidden=hidden, query_layers=query_layers, voxel_features=voxel_features,
                                conv_layers=0 if pointnet_grid else 3)
    bar = tqdm(desc="training", unit="scene")

    def progress(epoch, b, n, loss):
        if bar.total != n:
            bar.reset(total=n)
        bar.set_description(f"epoch {epoch + 1}/{epochs}")
        bar.update(1)
        bar.set_postfix(loss=f"{loss:.4f}")

    meta = train_collision(data, out, epochs=epochs, seed=seed, threads=threads, lr=lr, max_minutes=max_minutes,
                           config=config, encoders=encoders,
                           progress=progress, command=cmd, device=device)
    bar.close()
    last = meta["history"][-1] if meta["history"] else {}
    typer.echo(f"{meta['epochs_done']} epochs on {meta['train_scenes']} scenes in {meta['seconds'] / 60:.1f} min; "
               f"last loss {last.get('loss', float('nan')):.4f}, train accuracy "
               f"{100 * last.get('train_accuracy', float('nan')):.1f} %; weights {out}")


@train_app.command("matcher")
def train_matcher_cmd(
        data: Path = typer.Option(..., "--data", help="Dataset folder (ms-drake data matcher)"),
        out: Path = typer.Option(Path("out/weights/matcher.pt"), "--out", help="Weights file"),
        epochs: int = typer.Option(10, "--epochs", min=1, help="Epochs (cosine schedule over all)"),
        steps: int = typer.Option(150, "--steps", min=1, help="Batches per epoch"),
        batch: int = typer.Option(64, "--batch", min=2, help="Pairs per batch (half positive)"),
        lr: float = typer.Option(1e-3, "--lr", help="Adam learning rate (cosine decay to 0)"),
        seed: int = TrainingSeed,
        threads: int = TorchThreads,
        max_minutes: float = typer.Option(15.0, "--max-minutes", help="Stop after the epoch that would end past "
                                          "this wall time"),
        device: str = TrainDevice,
        overwrite_shipped: bool = OverwriteShipped):
    """Train the siamese target matcher; resumes from OUT.ckpt; writes OUT (weights + meta) after
    every epoch."""
    torch_device(device)
    _need_training_out(out, overwrite_shipped)
    bar, progress = _epoch_bar(epochs)
    cmd = " ".join(["ms-drake", "train", "matcher", "--data", str(data), "--out", str(out), "--epochs", str(epochs),
                    "--steps", str(steps), "--batch", str(batch), "--lr", str(lr), "--seed", str(seed),
                    "--threads", str(threads)] + _device_args(device)
                   + (["--overwrite-shipped"] if overwrite_shipped else []))
    meta = train_matcher(data, out, epochs=epochs, steps=steps, batch=batch, seed=seed, threads=threads, lr=lr,
                         max_minutes=max_minutes, progress=progress, command=cmd, device=device)
    bar.close()
    for h in meta["history"]:
        typer.echo(f"epoch {h['epoch']}: loss {h['loss']:.4f}, held-out loss {h['val_loss']:.4f}, accuracy "
                   f"{100 * h['val_accuracy']:.1f} %, precision {100 * h['val_precision']:.1f} %, recall "
                   f"{100 * h['val_recall']:.1f} % at t_r = 0.9 ({h['seconds']:.0f} s)")
    typer.echo(f"wrote {out} ({meta['epochs_done']} of {epochs} epochs, {meta['seconds'] / 60:.1f} min)")


@bench_app.command("target-detection")
def bench_target_detection_cmd(
        backend: str = typer.Option(..., "--backend", help="color | template | learned"),
        images: int = typer.Option(300, "--images", min=1, help="Images (N)"),
        seed_start: int = _seed_start("First image seed (S)"),
        out: Path = typer.Option(..., "--out", help="Result .json (per-image lines go to the .jsonl beside it; "
                                 "resumes)"),
        workers: int = _workers(),
        weights: Optional[Path] = typer.Option(None, "--weights", help="Matcher weights (learned; default: shipped)"),
        scene_dir: Optional[Path] = typer.Option(None, "--scene-dir", help="Folder caching the rendered images "
                                                 "(scene_<seed>.npz), shared by the runs of several backends"),
        sensor: str = typer.Option("none", "--sensor", help="Depth sensor model preset of the depth image the "
                                   "detector gets: none | phoxi | l515 | primesense (ms_drake.station.sensor_model)"),
        device: str = Device):
    """Target detection on held-out heaps with the target 20-80 % occluded (half of them with a second
    red object): precision, recall, F1, also on the shared-colour subset."""
    _choose("--backend", backend, DETECTOR_BACKENDS)
    _choose("--sensor", sensor, DEPTH_SENSOR_PRESETS)
    if out.suffix != ".json":
        _fail(f"--out {out}: give a .json file")
    if backend == "learned":
        torch_device(device)
        _need_weights("--weights", weights, load_matcher, "matcher")
    bar, progress = _job_bar(images, backend, "image")
    res = bench_target_detection(backend, images, seed_start, out, workers, weights, progress, scene_dir, sensor,
                                 device)
    bar.close()
    for name, m in (("all", res), ("shared colour", res["shared_colour"]), ("distinct colours", res["distinct_colour"])):
        typer.echo(f"{backend}, {name}: {m['images']} images, precision {m['precision']:.3f}, recall "
                   f"{m['recall']:.3f}, F1 {m['f1']:.3f}")
    typer.echo(f"target occluded {100 * res['occluded_fraction'][0]:.0f}-{100 * res['occluded_fraction'][1]:.0f} % "
               f"(drawn in {100 * OCCLUSION[0]:.0f}-{100 * OCCLUSION[1]:.0f} %); wrote {out}")


#: Options that name what a command writes (a file or a folder).
OUTPUT_OPTIONS = ("--out", "--json", "--figures", "--plot", "--html")


def _need_writable(option: str, path) -> None:
    """Fail unless `path` (given with `option`) can be written: it, or the folder it would be made in,
    is writable and no regular file stands where a folder is needed."""
    path = Path(path)
    place = path
    while not place.exists() and place != place.parent:
        place = place.parent
    if place != path and not place.is_dir():
        _fail(f"{option} {path}: {place} is a file, not a folder; give a path in a writable folder")
    if not os.access(place, os.W_OK | (os.X_OK if place.is_dir() else 0)):
        _fail(f"{option} {path}: {place} is not writable; give a path in a writable folder")


def _guard_outputs(command) -> None:
    """Make every command (recursively) check its OUTPUT_OPTIONS before it starts any work, and end on
    Ctrl-C with one line and status 130 (a long command's records are written as they finish, so the
    same command resumes; bench search and reproduce also say how far they got)."""
    for sub in getattr(command, "commands", {}).values():
        _guard_outputs(sub)
    if command.callback is None:
        return
    outs = [(p.name, p.opts[0]) for p in command.params
            if p.param_type_name == "option" and set(p.opts) & set(OUTPUT_OPTIONS)]
    callback = command.callback

    @functools.wraps(callback)
    def guarded(*args, **kwargs):
        for name, option in outs:
            if kwargs.get(name) is not None:
                _need_writable(option, kwargs[name])
        try:
            return callback(*args, **kwargs)
        except KeyboardInterrupt:
            typer.echo("stopped; the finished results are in their files: run the same command to resume", err=True)
            raise typer.Exit(130) from None

    command.callback = guarded


#: OSErrors that mean "this path cannot be written here".
WRITE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENOSPC}


def main():
    """The `ms-drake` command: a user error (MsDrakeError, or an OSError on a path, e.g. an --out that
    cannot be written) prints one line naming it and exits with status 2, without a traceback."""
    command = typer.main.get_command(app)
    _guard_outputs(command)
    try:
        command()
    except MsDrakeError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except OSError as e:
        if e.filename is None:
            raise
        fix = "; give a path in a writable folder" if e.errno in WRITE_ERRNOS else ""
        typer.echo(f"error: {e.filename}: {e.strerror or e}{fix}", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
