"""The two fidelities on the same grasps (do they agree?): a primitive-mode
search of a heap records, before each grasp attempt, the scene (every object's pose, which
objects were already lifted out) and the grasp it executes; each attempt is then replayed in full
fidelity (YuMiBin + FullBackend: IK + ruckig through the station's drivers, compliant pads /
suction cup) from that very scene with that very grasp, and both outcomes are compared.

One record per attempt (`attempt_records`): seed, step, grasp kind, object, quality, the
primitive outcome (a draw with probability = quality), the full outcome (lifted, the executor's
message: "" / "not_lifted" / "plan_failed:<ik status>", how far the object rose, the load of
the other objects on the grasped one before the approach: `object_load`; whether a lifted object
reached the tray), CPU seconds.
`summarize` gives per-attempt success in each fidelity, their agreement (both lifted or both
not) with Wilson 95 % intervals, the share of the objects lifted in full fidelity that reach the
tray (`full_delivered`: outside the bin when the action ends; the primitive carrier drops none), the agreement of the full outcome with the primitive's
expected outcome (quality >= 0.5), and the rates for objects other objects press down apart
(the grasp qualities are those of the object alone; the physical cup lifts the load too).

Pictures (`run_fidelity(pictures=DIR)`, `bench fidelity --pictures DIR`): every attempt whose
full outcome differs from the primitive's is also filmed by two colour cameras aimed at the grasp
(`grasp_cameras`: 45 degrees down, from the bin's +x and -y sides) and written as
DIR/<seed>_<step>.jpg: the last `STRIP_FRAMES` frames before the outcome, `FRAME_PERIOD` s
apart (the jaw closing, the lift, the slip), one row per camera.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydrake.common.schema import Transform
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.sensors import CameraConfig
from pydrake.systems.framework import DiagramBuilder

from ms_drake.execution import (
    ActionExecutor,
    FullBackend,
    connect_executor,
    remove_objects,
)
from ms_drake.experiments.harness import read_records
from ms_drake.experiments.rollout import build_search, run_search
from ms_drake.policies.bin_search import BinSearchConfig, load_bin_search_config
from ms_drake.scenes.layouts import HeapConfig, cached_heap
from ms_drake.geometry import Workspace, as_rigid_transform
from ms_drake.parallel import run_jobs
from ms_drake.scenario import ScenarioRef, load_scenario
from ms_drake.scenes.heaps import ObjectPose, scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, get_scene_graph, station_objects
from ms_drake.station.robots import set_arm_positions
from ms_drake.types import Action, Grasp


@dataclass
class Attempt:
    """One grasp of a primitive search and the scene it was executed in."""

    seed: int
    step: int
    grasp: Grasp
    state: object  # the heap (objects in order) with every object's pose before the attempt
    removed: tuple  # indices (heap order) of the objects already lifted out
    primitive_lifted: bool = False
    target: bool = False  # the grasped object is the target


def fidelity_config(objects: int, policy: str = "largest", reach: str = "") -> BinSearchConfig:
    """The primitive search whose grasp attempts the benchmark replays: the Ch. 7 setting (the named
    setting "ch7") on N-object heaps with the budget 2N; reach: keep only grasps this robot reaches
    ("" none, or a scenario name such as "YuMiBin")."""
    return load_bin_search_config("ch7", policy=policy, reach=reach, horizon=2 * int(objects),
                                  heap=HeapConfig("bin_set", int(objects)))


def primitive_attempts(heap, config: BinSearchConfig, seed: int | None = None, max_attempts: int | None = None,
                       scenario_name: str = "FloatingGripperBin") -> tuple[list[Attempt], object]:
    """Search `heap` in the primitive mode with `config` (fidelity_config) and return its grasp
    attempts, each with the scene before it, and the RolloutResult.
    max_attempts: keep the first K grasp attempts (the search runs to its end regardless)."""
    params = dataclasses.replace(config, seed=heap.seed if seed is None else seed)
    system = build_search(load_scenario(None, scenario_name), heap, params)
    names = {o.model_name: k for k, o in enumerate(station_objects(system.plant))}
    attempts = []

    def on_idle(sys_, context, step):
        history = sys_.output(context, "history")
        for a in attempts:  # outcomes of the attempts executed so far
            if a.step < len(history):
                a.primitive_lifted = bool(history[a.step].success)
        action = sys_.output(context, "action")
        if action.kind != "grasp" or (max_attempts is not None and len(attempts) >= max_attempts):
            return
        pc = sys_.plant.GetMyContextFromRoot(context)
        removed = set(sys_.output(context, "removed"))
        objs = station_objects(sys_.plant)
        state = dataclasses.replace(heap, objects=tuple(
            ObjectPose(o.full_name, tuple(float(v) for v in sys_.plant.GetPositions(pc, o.model_instance)))
            for o in objs))
        attempts.append(Attempt(int(heap.seed), int(step), action.grasp, state,
                                tuple(sorted(names[r] for r in removed if r in names)),
                                target=action.grasp.object_id == sys_.target_id))

    res = run_search(system, heap, params, on_idle=on_idle)
    return attempts, res


@dataclass
class Replay:
    """A full-fidelity execution of one attempt."""

    lifted: bool
    message: str  # the executor's outcome message ("", "not_lifted", "plan_failed:<status>")
    rise: float  # m the grasped object rose by the outcome check (nan if never executed)
    sim_seconds: float
    cpu_seconds: float
    load: float = float("nan")  # N, vertical force of the other objects on the grasped one before the approach
    pressed_by: int = 0  # other objects pressing on it from above (downward force > 0.1 N)
    delivered: bool | None = None  # a lifted object lies outside the bin when the action ends (None: not lifted)
    frames: tuple = ()  # (t, {camera: RGB image}) every FRAME_PERIOD s when filmed (replay_full(film=True))


def object_load(plant, inspector, plant_context, body_index: int) -> tuple[float, int]:
    """(net vertical force [N] the other objects exert on body `body_index`, how many of them push
    it down by more than 0.1 N): negative when objects rest on it. From the plant's contact
    results (hydroelastic and point contacts); the robot, its grippers and the environment are
    not objects (bodies of model instances whose name starts with "obj")."""
    res = plant.get_contact_results_output_port().Eval(plant_context)

    def is_object(b):
        return plant.GetModelInstanceName(plant.get_body(b).model_instance()).startswith("obj")

    forces = {}  # other body -> vertical force on body_index
    pairs = [(plant.GetBodyFromFrameId(inspector.GetFrameId(c.contact_surface().id_M())).index(),
              plant.GetBodyFromFrameId(inspector.GetFrameId(c.contact_surface().id_N())).index(),
              c.F_Ac_W().translational()[2]) for c in map(res.hydroelastic_contact_info,
                                                          range(res.num_hydroelastic_contacts()))]
    pairs += [(c.bodyB_index(), c.bodyA_index(), c.contact_force()[2])  # contact_force acts on B
              for c in map(res.point_pair_contact_info, range(res.num_point_pair_contacts()))]
    for a, b, fz in pairs:  # fz acts on the first body of the pair
        if int(a) == body_index and is_object(b):
            forces[int(b)] = forces.get(int(b), 0.0) + fz
        elif int(b) == body_index and is_object(a):
            forces[int(a)] = forces.get(int(a), 0.0) - fz
    return float(sum(forces.values())), int(sum(f < -0.1 for f in forces.values()))


FRAME_PERIOD = 0.2  # s between the pictures' frames
STRIP_FRAMES = 10  # frames per picture, before the outcome


def _look_at(eye, target) -> RigidTransform:
    """A camera pose (Drake's: +z forward, +y down in the image) at `eye` looking at `target`."""
    z = np.subtract(target, eye) / np.linalg.norm(np.subtract(target, eye))
    y = np.array([0.0, 0.0, -1.0]) + z[2] * z  # world down, made normal to z
    y /= np.linalg.norm(y)
    return RigidTransform(RotationMatrix(np.column_stack([np.cross(y, z), y, z])), np.asarray(eye, float))


def grasp_cameras(center, distance: float = 0.5) -> dict:
    """Two colour cameras (320 x 240) `distance` m from the grasp centre (world), 45 degrees down,
    from the bin's +x and -y sides."""
    c = np.asarray(center, float)
    h = distance / np.sqrt(2.0)
    eyes = {"grasp_x": c + [h, 0.0, h], "grasp_y": c + [0.0, -h, h]}
    return {k: CameraConfig(name=k, width=320, height=240, X_PB=Transform(_look_at(e, c)), rgb=True, depth=False,
                            renderer_name="vtk") for k, e in eyes.items()}


def build_replay(attempt: Attempt, scenario: str | ScenarioRef = "YuMiBin", seed: int = 0, cameras=None):
    """(simulator, station, executor, backend) of the full-fidelity station of `scenario` (a name or
    ScenarioRef) holding the attempt's scene, the robot parked, the attempt's grasp on the executor's
    action input; its cameras are `cameras` ({name: CameraConfig}; none by default: the executor
    needs body poses only)."""
    s = scenario_with_heap(ScenarioRef.of(scenario).load(), attempt.state)
    s.cameras = dict(cameras or {})
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    plant = get_plant(station)
    objs = station_objects(plant)
    backend = FullBackend(s, {o.model_name: int(o.body_index) for o in objs}, Workspace.from_scenario(s), seed=seed)
    executor = builder.AddSystem(ActionExecutor(backend))
    connect_executor(builder, executor, station)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    ApplySimulatorConfig(s.simulator_config, simulator)
    context = simulator.get_mutable_context()
    set_heap_poses(station, context, attempt.state)
    pc = plant.GetMyMutableContextFromRoot(context)
    remove_objects(plant, pc, [objs[k].body_index for k in attempt.removed])
    set_arm_positions(plant, pc, s.robot.name, backend.initial_commands())
    executor.action_port.FixValue(executor.GetMyMutableContextFromRoot(context),
                                  Action("grasp", grasp=attempt.grasp))
    simulator.Initialize()
    return simulator, station, executor, backend


def replay_full(attempt: Attempt, scenario: str | ScenarioRef = "YuMiBin", max_sim_time: float = 30.0,
                load_time: float = 0.15, film: bool = False) -> Replay:
    """Execute the attempt's grasp in full fidelity from its scene: up to the outcome check, and a
    lifted object on to the drop-off tray (the action's end: Replay.delivered says whether the
    object then lies outside the bin, or fell back into it). The load of the other objects on the
    grasped one (`object_load`) is read once the arm has held its park for `load_time` s (the pick
    plan rests 0.2 s at park before it moves). film: also render `grasp_cameras` every
    FRAME_PERIOD s up to the outcome (Replay.frames)."""
    t_cpu = time.process_time()
    cameras = grasp_cameras(attempt.grasp.center) if film else None
    simulator, station, executor, backend = build_replay(attempt, scenario, seed=attempt.seed, cameras=cameras)
    station_context = station.GetMyContextFromRoot(simulator.get_context())
    frames = []
    every = max(1, int(round(FRAME_PERIOD / executor.period)))
    context = simulator.get_mutable_context()
    ex_ctx = executor.GetMyContextFromRoot(context)
    body = backend.objects.get(attempt.grasp.object_id)
    z0 = as_rigid_transform(executor.poses_port.Eval(ex_ctx)[body], "pose").translation()[2]
    plant = get_plant(station)
    inspector = get_scene_graph(station).model_inspector()
    k, t, history, load = 0, 0.0, (), (float("nan"), 0)
    while t < max_sim_time:
        k += 1
        t = k * executor.period
        simulator.AdvanceTo(t)
        if math.isnan(load[0]) and t >= load_time:
            load = object_load(plant, inspector, plant.GetMyContextFromRoot(context), body)
        if cameras and k % every == 0:
            frames.append((t, {c: station.GetOutputPort(f"{c}.rgb_image").Eval(station_context).data[:, :, :3].copy()
                               for c in cameras}))
        history = executor.GetOutputPort("history").Eval(ex_ctx)
        if history:
            break
    rise = float("nan")
    if history and not history[0].message.startswith("plan_failed"):
        pose = executor.poses_port.Eval(ex_ctx)[body]
        rise = float(as_rigid_transform(pose, "pose").translation()[2] - z0)
    out = history[0] if history else None
    delivered = None
    if out is not None and out.success:  # on to the tray: the action ends when the executor is idle
        while t < max_sim_time and executor.GetOutputPort("status").Eval(ex_ctx).busy:
            k += 1
            t = k * executor.period
            simulator.AdvanceTo(t)
        delivered = attempt.grasp.object_id in backend.left_bin(executor.poses_port.Eval(ex_ctx))
    return Replay(bool(out and out.success), out.message if out else "timeout", rise, float(t),
                  time.process_time() - t_cpu, *load, delivered=delivered, frames=tuple(frames))


def picture_strip(frames, title: str) -> np.ndarray:
    """One picture of a filmed replay (Replay.frames): its last STRIP_FRAMES frames, one row per
    camera, each frame stamped with its time, `title` on top; RGB."""
    frames = list(frames)[-STRIP_FRAMES:]
    if not frames:
        raise ValueError("picture_strip: no frames (replay_full(film=True) films the attempt)")
    rows = []
    for cam in frames[0][1]:
        tiles = []
        for t, images in frames:
            tile = np.ascontiguousarray(images[cam])
            cv2.putText(tile, f"{t:.1f} s", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
            tiles.append(tile)
        rows.append(np.concatenate(tiles, axis=1))
    body = np.concatenate(rows, axis=0)
    head = np.full((30, body.shape[1], 3), 255, np.uint8)
    cv2.putText(head, title, (6, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1)
    return np.concatenate([head, body], axis=0)


# ------------------------------------------------------------------------------------ benchmark
def heap_job(job: tuple) -> list[dict]:
    """(objects, seed, heap_dir, max_attempts, policy, reach[, scenario]) -> records of one heap: one
    per attempt (kind "attempt") and one for the heap (kind "heap": the primitive search's result).
    reach: BinSearchConfig.reach of the primitive search ("" none, "YuMiBin": only the YuMi's
    reachable grasps); scenario: the robot's station the attempts are replayed on (a ScenarioRef;
    default YuMiBin). Module level for pickling."""
    objects, seed, heap_dir, max_attempts, policy, reach, *rest = job
    ref = ScenarioRef.of(rest[0] if rest else "YuMiBin")
    pictures = rest[1] if len(rest) > 1 else None
    scenario = str(ref)
    heap = cached_heap(HeapConfig("bin_set", objects), seed, heap_dir)
    t = time.process_time()
    attempts, res = primitive_attempts(heap, fidelity_config(objects, policy, reach), max_attempts=max_attempts)
    prim_cpu = time.process_time() - t
    recs = []
    for a in attempts:
        r = replay_full(a, ref, film=pictures is not None)
        g = a.grasp
        if pictures is not None and r.lifted != a.primitive_lifted:
            title = (f"heap {seed}, attempt {a.step}: {g.kind} on {g.object_id}, quality {g.quality:.2f}; primitive "
                     f"{'lifted' if a.primitive_lifted else 'failed'}, {ref.name} {'lifted' if r.lifted else 'failed'}"
                     f"{' (' + r.message + ')' if r.message else ''}")
            Path(pictures).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(Path(pictures) / f"{seed}_{a.step}.jpg"), picture_strip(r.frames, title)[:, :, ::-1],
                        [cv2.IMWRITE_JPEG_QUALITY, 85])
        recs.append({"kind": "attempt", "seed": int(seed), "objects": int(objects), "reach": reach, "step": a.step,
                     "scenario": scenario,
                     "grasp": g.kind, "object": g.object_id, "target": a.target, "quality": float(g.quality),
                     "tilt_deg": float(np.degrees(np.arccos(np.clip(-np.asarray(g.approach)[2], -1, 1)))),
                     "center": [float(v) for v in g.center], "approach": [float(v) for v in g.approach],
                     "width": float(g.width), "primitive_lifted": a.primitive_lifted, "full_lifted": r.lifted,
                     "full_message": r.message, "full_rise": None if math.isnan(r.rise) else r.rise,
                     "full_sim_seconds": r.sim_seconds, "full_cpu_seconds": r.cpu_seconds,
                     "full_load": r.load, "full_pressed_by": r.pressed_by, "full_delivered": r.delivered})
    recs.append({"kind": "heap", "seed": int(seed), "objects": int(objects), "reach": reach, "policy": policy,
                 "primitive_success": bool(res.success), "primitive_actions": int(res.actions),
                 "primitive_grasps": sum(1 for k in res.action_kinds if k == "grasp"),
                 "primitive_lifts": int(res.grasp_successes), "primitive_failure": res.failure,
                 "attempts_replayed": len(attempts), "primitive_cpu_seconds": prim_cpu, "pid": os.getpid(),
                 "scenario": scenario})
    return recs


def _read(path: Path) -> list[dict]:
    """The records of a result file being resumed (harness.read_records: a torn last line is cut)."""
    return read_records(path)


def run_fidelity(heaps: int, seed_start: int, out, objects: int = 10, heap_dir: str | None = None,
                 workers: int = 1, max_attempts: int | None = 3, policy: str = "largest", reach: str = "YuMiBin",
                 progress=None, scenario: str | ScenarioRef = "YuMiBin", pictures: str | None = None) -> dict:
    """The paired benchmark, the attempts replayed on `scenario`'s robot (a name or ScenarioRef; the
    records keep it as str(ScenarioRef)): heaps S..S+K-1 not yet in
    `out` (a heap is done once its "heap" record is there; its records are written together, so a killed run loses only the heaps in
    flight and the same command resumes). pictures: a folder for the pictures of the attempts
    whose fidelities disagree (module docstring). Returns `summarize` of the file."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ref = ScenarioRef.of(scenario)
    mine = lambda r: r.get("objects") == objects and r.get("scenario", "YuMiBin") == str(ref)  # noqa: E731
    done = {int(r["seed"]) for r in _read(out) if r.get("kind") == "heap" and mine(r)}
    # attempt records of heaps without their heap record (a torn run) are dropped before rerunning
    keep = [r for r in _read(out) if not mine(r) or int(r["seed"]) in done]
    out.write_text("".join(json.dumps(r) + "\n" for r in keep))
    jobs = [(objects, k, heap_dir, max_attempts, policy, reach, ref, pictures)
            for k in range(seed_start, seed_start + heaps) if k not in done]
    with out.open("a") as f:
        for res in run_jobs(heap_job, jobs, workers=workers):
            if not res.ok:
                if progress is not None:
                    progress({"kind": "error", "seed": res.job[1], "error": res.error})
                continue
            for r in res.value:
                f.write(json.dumps(r) + "\n")
            f.flush()
            os.fsync(f.fileno())
            if progress is not None:
                progress(res.value[-1])
    recs = [r for r in _read(out) if mine(r) and seed_start <= int(r["seed"]) < seed_start + heaps]
    return summarize(recs)


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score 95 % interval of k successes in n trials."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (c - h, c + h)


def _rate(k: int, n: int) -> dict:
    lo, hi = wilson(k, n)
    return {"k": int(k), "n": int(n), "rate": k / n if n else float("nan"), "ci95": [lo, hi]}


def summarize(recs: list[dict]) -> dict:
    """Per-attempt success in each fidelity, agreement (both lifted or both not), the full
    outcome against the primitive's expected one (quality >= 0.5), the full failures by message,
    the same rates by grasp kind and by load (objects pressed down by others or not), and the
    primitive searches' success."""
    att = [r for r in recs if r.get("kind") == "attempt"]
    heaps = [r for r in recs if r.get("kind") == "heap"]
    n = len(att)
    prim = sum(r["primitive_lifted"] for r in att)
    full = sum(r["full_lifted"] for r in att)
    agree = sum(r["primitive_lifted"] == r["full_lifted"] for r in att)
    expect = sum((r["quality"] >= 0.5) == r["full_lifted"] for r in att)
    messages = {}
    for r in att:
        if not r["full_lifted"]:
            messages[r["full_message"] or "?"] = messages.get(r["full_message"] or "?", 0) + 1
    by_kind = {}
    for kind in sorted({r["grasp"] for r in att}):
        a = [r for r in att if r["grasp"] == kind]
        by_kind[kind] = {"primitive": _rate(sum(r["primitive_lifted"] for r in a), len(a)),
                         "full": _rate(sum(r["full_lifted"] for r in a), len(a)),
                         "agreement": _rate(sum(r["primitive_lifted"] == r["full_lifted"] for r in a), len(a))}
    by_load = {}  # attempts on objects other objects press down (records with full_pressed_by) and the rest
    for name, sel in (("pressed", lambda r: r["full_pressed_by"] > 0), ("free", lambda r: r["full_pressed_by"] == 0)):
        a = [r for r in att if "full_pressed_by" in r and sel(r)]
        if a:
            by_load[name] = {"primitive": _rate(sum(r["primitive_lifted"] for r in a), len(a)),
                             "full": _rate(sum(r["full_lifted"] for r in a), len(a)),
                             "agreement": _rate(sum(r["primitive_lifted"] == r["full_lifted"] for r in a), len(a))}
    carried = [r for r in att if r["full_lifted"] and r.get("full_delivered") is not None]
    return {"heaps": len(heaps), "attempts": n, "primitive": _rate(prim, n), "full": _rate(full, n),
            "delivered": _rate(sum(r["full_delivered"] for r in carried), len(carried)),
            "difference_points": 100.0 * (prim - full) / n if n else float("nan"),
            "agreement": _rate(agree, n), "agreement_with_quality": _rate(expect, n),
            "full_failures": dict(sorted(messages.items(), key=lambda kv: -kv[1])), "by_kind": by_kind,
            "by_load": by_load,
            "primitive_search": _rate(sum(r["primitive_success"] for r in heaps), len(heaps)),
            "full_cpu_seconds_per_attempt": float(np.mean([r["full_cpu_seconds"] for r in att])) if att else 0.0}


def format_summary(s: dict) -> str:
    """The summary as text: rates with their Wilson 95 % intervals."""

    def r(x):
        return f"{100 * x['rate']:.0f} % ({x['k']}/{x['n']}) [{100 * x['ci95'][0]:.0f}, {100 * x['ci95'][1]:.0f}]"

    lines = [f"{s['heaps']} heaps, {s['attempts']} attempts",
             f"  lifted, primitive: {r(s['primitive'])}", f"  lifted, full:      {r(s['full'])}",
             f"  difference: {s['difference_points']:.1f} points", f"  agreement:  {r(s['agreement'])}",
             f"  full vs quality >= 0.5: {r(s['agreement_with_quality'])}",
             f"  lifted objects that reach the tray (full): {r(s['delivered'])}",
             f"  full failures: {s['full_failures']}",
             f"  primitive search success: {r(s['primitive_search'])}",
             f"  full CPU s per attempt: {s['full_cpu_seconds_per_attempt']:.1f}"]
    for kind, k in list(s["by_kind"].items()) + [(f"object {n}", v) for n, v in s.get("by_load", {}).items()]:
        lines.append(f"  {kind}: primitive {r(k['primitive'])}, full {r(k['full'])}, agreement {r(k['agreement'])}")
    return "\n".join(lines)
