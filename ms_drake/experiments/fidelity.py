"""The two fidelities on the same grasps (do they agree?): a primitive-mode
search of a heap records, before each grasp attempt, the scene (every object's pose, which
objects were already lifted out) and the grasp it executes; each attempt is then replayed in full
fidelity (YuMiBin + FullBackend: IK + ruckig through the station's drivers, compliant pads /
suction cup) from that very scene with that very grasp, and both outcomes are compared.

One record per attempt (`attempt_records`): seed, step, grasp kind, object, quality, the
primitive outcome (a draw with probability = quality), the full outcome (lifted, the executor's
message: "" / "not_lifted" / "plan_failed:<ik status>", how far the object rose, the load of
the other objects on the grasped one before the approach: `object_load`), CPU seconds.
`summarize` gives per-attempt success in each fidelity, their agreement (both lifted or both
not) with Wilson 95 % intervals, the agreement of the full outcome with the primitive's
expected outcome (quality >= 0.5), and the rates for objects other objects press down apart
(the grasp qualities are those of the object alone; the physical cup lifts the load too).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
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


def build_replay(attempt: Attempt, scenario: str | ScenarioRef = "YuMiBin", seed: int = 0):
    """(simulator, station, executor, backend) of the full-fidelity station of `scenario` (a name or
    ScenarioRef) holding the attempt's scene, the robot parked, the attempt's grasp on the executor's
    action input."""
    s = scenario_with_heap(ScenarioRef.of(scenario).load(), attempt.state)
    s.cameras = {}  # the executor needs body poses only
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
                load_time: float = 0.15) -> Replay:
    """Execute the attempt's grasp in full fidelity from its scene, up to the outcome check. The
    load of the other objects on the grasped one (`object_load`) is read once the arm has held
    its park for `load_time` s (the pick plan rests 0.2 s at park before it moves)."""
    t_cpu = time.process_time()
    simulator, station, executor, backend = build_replay(attempt, scenario, seed=attempt.seed)
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
        history = executor.GetOutputPort("history").Eval(ex_ctx)
        if history:
            break
    rise = float("nan")
    if history and not history[0].message.startswith("plan_failed"):
        pose = executor.poses_port.Eval(ex_ctx)[body]
        rise = float(as_rigid_transform(pose, "pose").translation()[2] - z0)
    out = history[0] if history else None
    return Replay(bool(out and out.success), out.message if out else "timeout", rise, float(t),
                  time.process_time() - t_cpu, *load)


# ------------------------------------------------------------------------------------ benchmark
def heap_job(job: tuple) -> list[dict]:
    """(objects, seed, heap_dir, max_attempts, policy, reach[, scenario]) -> records of one heap: one
    per attempt (kind "attempt") and one for the heap (kind "heap": the primitive search's result).
    reach: BinSearchConfig.reach of the primitive search ("" none, "YuMiBin": only the YuMi's
    reachable grasps); scenario: the robot's station the attempts are replayed on (a ScenarioRef;
    default YuMiBin). Module level for pickling."""
    objects, seed, heap_dir, max_attempts, policy, reach, *rest = job
    ref = ScenarioRef.of(rest[0] if rest else "YuMiBin")
    scenario = str(ref)
    heap = cached_heap(HeapConfig("bin_set", objects), seed, heap_dir)
    t = time.process_time()
    attempts, res = primitive_attempts(heap, fidelity_config(objects, policy, reach), max_attempts=max_attempts)
    prim_cpu = time.process_time() - t
    recs = []
    for a in attempts:
        r = replay_full(a, ref)
        g = a.grasp
        recs.append({"kind": "attempt", "seed": int(seed), "objects": int(objects), "reach": reach, "step": a.step,
                     "scenario": scenario,
                     "grasp": g.kind, "object": g.object_id, "target": a.target, "quality": float(g.quality),
                     "tilt_deg": float(np.degrees(np.arccos(np.clip(-np.asarray(g.approach)[2], -1, 1)))),
                     "center": [float(v) for v in g.center], "approach": [float(v) for v in g.approach],
                     "width": float(g.width), "primitive_lifted": a.primitive_lifted, "full_lifted": r.lifted,
                     "full_message": r.message, "full_rise": None if math.isnan(r.rise) else r.rise,
                     "full_sim_seconds": r.sim_seconds, "full_cpu_seconds": r.cpu_seconds,
                     "full_load": r.load, "full_pressed_by": r.pressed_by})
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
                 progress=None, scenario: str | ScenarioRef = "YuMiBin") -> dict:
    """The paired benchmark, the attempts replayed on `scenario`'s robot (a name or ScenarioRef; the
    records keep it as str(ScenarioRef)): heaps S..S+K-1 not yet in
    `out` (a heap is done once its "heap" record is there; its records are written together, so a killed run loses only the heaps in
    flight and the same command resumes). Returns `summarize` of the file."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ref = ScenarioRef.of(scenario)
    mine = lambda r: r.get("objects") == objects and r.get("scenario", "YuMiBin") == str(ref)  # noqa: E731
    done = {int(r["seed"]) for r in _read(out) if r.get("kind") == "heap" and mine(r)}
    # attempt records of heaps without their heap record (a torn run) are dropped before rerunning
    keep = [r for r in _read(out) if not mine(r) or int(r["seed"]) in done]
    out.write_text("".join(json.dumps(r) + "\n" for r in keep))
    jobs = [(objects, k, heap_dir, max_attempts, policy, reach, ref)
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
    return {"heaps": len(heaps), "attempts": n, "primitive": _rate(prim, n), "full": _rate(full, n),
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
             f"  full failures: {s['full_failures']}",
             f"  primitive search success: {r(s['primitive_search'])}",
             f"  full CPU s per attempt: {s['full_cpu_seconds_per_attempt']:.1f}"]
    for kind, k in list(s["by_kind"].items()) + [(f"object {n}", v) for n, v in s.get("by_load", {}).items()]:
        lines.append(f"  {kind}: primitive {r(k['primitive'])}, full {r(k['full'])}, agreement {r(k['agreement'])}")
    return "\n".join(lines)
