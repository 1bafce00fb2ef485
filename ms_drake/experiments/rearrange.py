"""Rearrangement on the Panda in Drake physics (Ch. 6.4 / 6.6.1): the controller of
ms_drake.policies.rearrange wired to the PandaTable station.

- `barrier_scene()`: the demo's scene: the target box on the near side of the table (y < 0), a
  row of tall cylinders across the table between it and the placement zone (y > 0).
- `table_scene(seed, objects)`: a Table 6.3 scene: `objects` procedural objects in stable poses,
  without collision, in the Panda's reach on the table (ms_drake.scenes.tabletop.place_objects on
  the reachable part), in a seeded random order.
- Scene sets (`set_scene(scenario, scene_set, seed, objects)`, `bench rearrange --scene-set`):
  `table` (the scene above, the zone the whole reachable table); `barrier`: the reference's
  physical barrier scenes: the fixture fixtures/barrier (a 64 x 6 x 28 cm box welded to the
  table) across the reachable table at x = -0.12, the objects between it and the robot
  (`SOURCE`, x < -0.17) and the placement zone beyond it (`FAR_ZONE`, x > -0.05), so every
  carry goes over it (a straight joint-space path sweeps through it); `one_side`: the same
  objects and zone without the barrier: every placement goes into the far half, which fills up
  as the run goes. Their objects are drawn from the reference's categories: boxes and
  cylinders (procedural test split) and mugs (the YCB cups the 10 cm jaw holds, ycb_unseen
  065-a/c/e/f), a category uniformly per object, those the jaw can hold from above (middle
  extent under 8.5 cm, at most 20 cm long): no bowl fits the jaw (YCB's is 16 cm across).
  A scene's objects at stable, collision-free poses by place_objects; a draw that does not fit
  the side is redrawn (seeded), so a seed always gives the same scene.
- `build_rearrange(scenario, scene, params)`: station + controller (three lines) + the run's end
  (ms_drake.execution.termination.StopWhenDone: 0.5 s after the controller is done, the scene at
  rest); `set_initial(system, context)`: the initial conditions (the heap's poses, the robot at
  home); `run_rearrange(system, ...)`: one Simulator.AdvanceTo, which returns when the end stops it
  (or at the time limit), judging each attempt with the simulation's truth (read by a Simulator
  monitor at the end's check times, every 0.1 s): grasped = the target rose by more than half
  the lift while the attempt ran; placed = it ends at rest in the zone (its centre within it),
  at least 5 cm from where it started, below 5 cm above the table's or an object's top (not held,
  not thrown away). With a fixture (the barrier) the monitor also reads the contacts: an object's
  `barrier_contact` is true when, while it was the target, a robot body or the object itself
  lifted (2 cm above its start) touched the fixture at a check time; the record counts the
  placements without (`placed_without_contact`).
- `run_rearrange_bench(...)`: `ms-drake bench rearrange`: one JSON line per scene (seed, method,
  grasps attempted / successful, placements successful, sim seconds, cpu seconds, minutes),
  flushed, resumable; `rearrange_table(records)`: the Table 6.3 analogue.
- `run_rearrange_demo(out, ...)`: `ms-drake demo rearrange`: the demo scene (or a scene set's
  scene), a GIF of the camera's view and a Meshcat recording.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import imageio
import numpy as np
from pydrake.geometry import Meshcat
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.analysis import ApplySimulatorConfig, Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus

from ms_drake.errors import HeapError, MsDrakeError
from ms_drake.execution.termination import StopWhenDone
from ms_drake.config_files import config_dict
from ms_drake.experiments.harness import read_records
from ms_drake.objects import get_object
from ms_drake.objects.registry import get_object_set
from ms_drake.parallel import run_jobs
from ms_drake.policies.rearrange import (
    METHODS,
    MakeRearrangementController,
    RearrangeParams,
    RearrangeStatus,
    connect_controller,
    sim_info,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.scenes.tabletop import place_objects
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.station import fixture_pose
from ms_drake.types import Heap, ObjectPose

SCENARIO = "PandaTable"
#: The part of the table the Panda (base at x = -0.6) reaches from above: x, y bounds [m].
REACH = (-0.45, 0.15, -0.32, 0.32)
#: Table 6.3's placement zone: the whole reachable table (the reference's default, "the entire workspace").
BENCH_ZONE = REACH
#: The demo's zone: beyond the barrier.
DEMO_ZONE = (-0.40, 0.0, 0.06, 0.28)
DEMO_SEED = 0
#: The run's check period [s] and the rest after the controller is done [s] (StopWhenDone).
CHECK_PERIOD, REST = 0.1, 0.5


class RearrangeError(MsDrakeError, ValueError):
    """A rearrangement run was asked for with settings it cannot honour."""


#: The scene sets of `bench rearrange --scene-set` (module doc).
SCENE_SETS = ("table", "barrier", "one_side")
#: Where the barrier and one_side scenes' objects start: the near half of the reachable table [m].
SOURCE = (-0.45, -0.17, -0.30, 0.30)
#: Their placement zone: the far half, beyond the barrier.
FAR_ZONE = (-0.05, 0.15, -0.30, 0.30)
#: The placement zone of each scene set.
SET_ZONES = {"table": REACH, "barrier": FAR_ZONE, "one_side": FAR_ZONE}
BARRIER = "fixtures/barrier"
#: The objects of the barrier and one_side scenes by category (module doc).
MUGS = ("ycb_unseen/065-a_cups", "ycb_unseen/065-c_cups", "ycb_unseen/065-e_cups", "ycb_unseen/065-f_cups")


def _jaw_holds(o) -> bool:
    return sorted(o.extents)[1] < 0.085 and max(o.extents) < 0.20


def category_objects() -> dict[str, list[str]]:
    """{category: object full names} of the barrier and one_side scenes (module doc)."""
    test = [o for o in get_object_set("procedural").objects if o.split == "test" and _jaw_holds(o)]
    mugs = [n for n in MUGS if _jaw_holds(get_object(n))]
    return {"box": [f"procedural/{o.name}" for o in test if o.name.startswith("box_")],
            "cylinder": [f"procedural/{o.name}" for o in test if o.name.startswith("cylinder_")],
            "mug": mugs}


@dataclass(frozen=True)
class SetScene:
    """A scene of a scene set: the heap (fixtures first), the placement zone, the indices of the
    objects to move and of the fixtures (into heap.objects)."""

    scene_set: str
    heap: Heap
    zone: tuple
    movable: tuple
    fixtures: tuple


def _on_area(scenario, area):
    """The scenario with its table cut to the rectangle `area` (x0, x1, y0, y1) for place_objects."""
    x0, x1, y0, y1 = area
    env = dataclasses.replace(scenario.environment, size=[x1 - x0, y1 - y0, scenario.environment.size[2]],
                              position=[(x0 + x1) / 2, (y0 + y1) / 2, scenario.environment.position[2]])
    return dataclasses.replace(scenario, environment=env)


def set_scene(scenario, scene_set: str, seed: int, objects: int = 10) -> SetScene:
    """Scene `seed` of `scene_set` with `objects` objects to move (module doc)."""
    if scene_set not in SCENE_SETS:
        raise RearrangeError(f"scene set {scene_set!r} unknown; choose one of {', '.join(SCENE_SETS)}")
    if objects < 1:
        raise RearrangeError(f"a scene needs objects >= 1, got {objects}")
    if scene_set == "table":
        heap = table_scene(scenario, seed, objects)
        return SetScene(scene_set, heap, REACH, tuple(range(objects)), ())
    pool = category_objects()
    for draw in range(20):
        rng = np.random.default_rng([seed, 6064, draw])
        left = {c: list(rng.permutation(v)) for c, v in pool.items()}
        names = []
        for _ in range(objects):
            cats = [c for c in left if left[c]]
            if not cats:
                raise RearrangeError(f"{objects} objects: the {scene_set} scenes draw from "
                                     f"{sum(map(len, pool.values()))} objects; use fewer")
            names.append(str(left[cats[rng.integers(len(cats))]].pop()))
        try:
            heap = place_objects(_on_area(scenario, SOURCE), names, seed * 100 + draw, margin=0.01)
            break
        except HeapError:
            continue
    else:
        raise RearrangeError(f"{scene_set} scene {seed}: {objects} objects do not fit the near half in 20 draws; "
                             "use fewer objects")
    fixtures = ()
    if scene_set == "barrier":  # the station welds it there; the heap says where
        X = fixture_pose(get_object(BARRIER), scenario.environment.position)
        q = X.rotation().ToQuaternion()
        barrier = ObjectPose(BARRIER, (q.w(), q.x(), q.y(), q.z(), *map(float, X.translation())))
        heap = dataclasses.replace(heap, objects=(barrier,) + heap.objects)
        fixtures = (0,)
    heap = dataclasses.replace(heap, environment="table")
    return SetScene(scene_set, heap, FAR_ZONE, tuple(range(len(fixtures), len(heap.objects))), fixtures)


def _pose(name: str, x: float, y: float, yaw: float = 0.0) -> ObjectPose:
    ext = get_object(name).extents
    q = RotationMatrix.MakeZRotation(yaw).ToQuaternion()
    return ObjectPose(name, (q.w(), q.x(), q.y(), q.z(), x, y, ext[2] / 2 + 1e-4))


def barrier_scene() -> Heap:
    """The demo scene (module doc): the target procedural/box_048 at (-0.22, -0.20), cylinders
    15-20 cm tall along y = -0.06 from x = -0.42 to 0.06."""
    target = _pose("procedural/box_048", -0.22, -0.20, np.pi / 2)
    row = ["procedural/cylinder_004", "procedural/cylinder_037", "procedural/cylinder_118",
           "procedural/cylinder_127", "procedural/cylinder_133", "procedural/cylinder_073"]
    xs = np.linspace(-0.40, 0.06, len(row))
    return Heap(seed=DEMO_SEED, environment="table",
                objects=(target,) + tuple(_pose(n, float(x), -0.06) for n, x in zip(row, xs)),
                target="procedural/box_048", target_index=0)


def table_scene(scenario, seed: int, objects: int = 10) -> Heap:
    """A Table 6.3 scene (module doc): objects drawn from the procedural set's test split, those the
    10 cm jaw can hold from above in any resting pose (the middle extent under 8.5 cm; at most 20 cm
    long)."""
    names = [f"procedural/{o.name}" for o in get_object_set("procedural").objects if o.split == "test"
             and sorted(o.extents)[1] < 0.085 and max(o.extents) < 0.20]
    rng = np.random.default_rng([seed, 6063])
    chosen = [names[i] for i in rng.choice(len(names), objects, replace=False)]
    x0, x1, y0, y1 = REACH
    env = dataclasses.replace(scenario.environment, size=[x1 - x0, y1 - y0, scenario.environment.size[2]],
                              position=[(x0 + x1) / 2, (y0 + y1) / 2, scenario.environment.position[2]])
    heap = place_objects(dataclasses.replace(scenario, environment=env), chosen, seed, margin=0.01)
    return dataclasses.replace(heap, environment="table")


@dataclass
class RearrangeSystem:
    diagram: object
    station: object
    controller: object
    plant: object
    scenario: object
    heap: Heap
    targets: tuple  # model names in order
    bodies: dict  # model name -> body index
    termination: object = None  # StopWhenDone
    fixtures: tuple = ()  # model names of the fixtures (the barrier)
    robot_bodies: frozenset = frozenset()  # body indices of the arm and the jaw

    def station_output(self, context, name):
        return self.station.GetOutputPort(name).Eval(self.station.GetMyContextFromRoot(context))

    def output(self, context, name):
        return self.controller.GetOutputPort(name).Eval(self.controller.GetMyContextFromRoot(context))


def build_rearrange(scenario, heap: Heap, params: RearrangeParams, order=None, meshcat=None,
                    targets: int | None = None, net=None, fixtures=()) -> RearrangeSystem:
    """The station holding the heap's objects and the controller moving them in `order` (indices
    into heap.objects; default all, in order); `fixtures`: indices of objects that stay (the
    barrier), watched for contacts."""
    scn = scenario_with_heap(scenario, heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scn, meshcat=meshcat))
    plant = get_plant(station)
    objs = station_objects(plant)
    order = list(range(len(objs))) if order is None else list(order)
    names = tuple(objs[i].model_name for i in order)
    controller = builder.AddSystem(MakeRearrangementController(
        scn, params, sim=sim_info(plant, names), targets=targets or len(names), net=net))
    connect_controller(builder, controller, station)
    end = builder.AddNamedSystem("termination", StopWhenDone(CHECK_PERIOD, REST, status_model=RearrangeStatus(),
                                                             poses_model=[RigidTransform()]))
    builder.Connect(controller.GetOutputPort("status"), end.status_port)
    builder.Connect(station.GetOutputPort("body_poses"), end.poses_port)
    diagram = builder.Build()
    robot = frozenset(int(b) for m in ("panda", "panda_jaw") for b in plant.GetBodyIndices(plant.GetModelInstanceByName(m)))
    return RearrangeSystem(diagram, station, controller, plant, scn, heap, names,
                           {o.model_name: int(o.body_index) for o in objs}, end,
                           tuple(objs[i].model_name for i in fixtures), robot)


def set_initial(system: RearrangeSystem, context) -> None:
    """The run's initial conditions on the Diagram's root context: the heap's objects at their
    poses, the Panda at the controller's home."""
    set_heap_poses(system.station, context, system.heap)
    pc = system.plant.GetMyMutableContextFromRoot(context)
    robot = system.plant.GetModelInstanceByName("panda")
    system.plant.SetPositions(pc, robot, system.controller.planner.q_home)


@dataclass
class RearrangeResult:
    record: dict
    frames: list = field(default_factory=list)


def _in_zone(p, zone, margin: float = 0.0) -> bool:
    x0, x1, y0, y1 = zone
    return x0 - margin <= p[0] <= x1 + margin and y0 - margin <= p[1] <= y1 + margin


class _RearrangeMonitor:
    """Read-only Simulator monitor of a rearrangement run: at the end's check times, each target's
    highest centre so far, the attempts as they finish (log) and, every `frame_every` s, the camera
    image."""

    def __init__(self, system: RearrangeSystem, frame_every: float | None, log, start: dict):
        self.system, self.frame_every, self.log, self.start = system, frame_every, log, start
        self.peak = {k: -np.inf for k in system.bodies}
        self.frames, self.seen, self.next_frame = [], 0, 0.0
        self.fixture_contact = set()  # targets during whose attempts the robot or the held target touched a fixture

    def _touching(self, ctx, body: int) -> set:
        """Body indices in contact with `body` (point pairs and hydroelastic surfaces)."""
        system = self.system
        results = system.station_output(ctx, "contact_results")
        out = set()
        for i in range(results.num_point_pair_contacts()):
            c = results.point_pair_contact_info(i)
            a, b = int(c.bodyA_index()), int(c.bodyB_index())
            if body in (a, b):
                out.add(b if a == body else a)
        if results.num_hydroelastic_contacts():
            inspector = system.station_output(ctx, "query_object").inspector()
            for i in range(results.num_hydroelastic_contacts()):
                surface = results.hydroelastic_contact_info(i).contact_surface()
                a, b = (int(system.plant.GetBodyFromFrameId(inspector.GetFrameId(g)).index())
                        for g in (surface.id_M(), surface.id_N()))
                if body in (a, b):
                    out.add(b if a == body else a)
        return out

    def _watch_fixtures(self, ctx, poses, status):
        system = self.system
        for name in system.fixtures:
            touching = self._touching(ctx, system.bodies[name])
            target = system.bodies.get(status.target)
            lifted = target is not None and poses[target].translation()[2] > self.start[status.target][2] + 0.02
            if touching & system.robot_bodies or (lifted and target in touching):
                self.fixture_contact.add(status.target)

    def __call__(self, ctx):
        system, t = self.system, ctx.get_time()
        if not system.termination.is_check_time(t):
            return EventStatus.Succeeded()
        poses = system.station_output(ctx, "body_poses")
        status = system.output(ctx, "status")
        if status.target in self.peak:
            self.peak[status.target] = max(self.peak[status.target], poses[system.bodies[status.target]].translation()[2])
        if system.fixtures:
            self._watch_fixtures(ctx, poses, status)
        hist = system.output(ctx, "history")
        if self.log is not None and len(hist) > self.seen:
            for o in hist[self.seen:]:
                self.log(f"    t={t:6.1f} s {o.target} attempt {o.attempt}: {o.status} (mppi calls {o.mppi_calls}, "
                         f"planning {o.plan_seconds:.1f} s cpu)")
            self.seen = len(hist)
        if self.frame_every is not None and t > 0 and t >= self.next_frame - 1e-9:
            rgb = np.asarray(system.station_output(ctx, "front.rgb_image").data)[:, :, :3].copy()
            self.frames.append((t, status.phase, rgb))
            self.next_frame = t + self.frame_every
        return EventStatus.Succeeded()


def run_rearrange(system: RearrangeSystem, params: RearrangeParams, seed: int = 0, max_sim: float = 600.0,
                  frame_every: float | None = None, meshcat=None, log=None) -> RearrangeResult:
    """Simulate until the Diagram's end stops it (the controller done, then 0.5 s of rest) or
    `max_sim` s (module doc); frame_every: keep the camera's rgb image every so many simulated
    seconds (the demo's GIF)."""
    sim = Simulator(system.diagram)
    ApplySimulatorConfig(system.scenario.simulator_config, sim)
    ctx = sim.get_mutable_context()
    set_initial(system, ctx)
    start = {k: system.station_output(ctx, "body_poses")[b].translation() for k, b in system.bodies.items()}
    monitor = _RearrangeMonitor(system, frame_every, log, start)
    sim.set_monitor(monitor)
    if meshcat is not None:
        meshcat.StartRecording(set_visualizations_while_recording=False)
    wall, cpu = time.perf_counter(), time.process_time()
    failure = ""
    try:
        sim.AdvanceTo(max_sim)  # returns early when the end stops it (SimulatorStatus: reached termination)
    except RuntimeError as e:  # a simulation failure ends the run; its record says so
        failure = f"simulation: {str(e).splitlines()[0][:120]}"
    finally:
        sim.clear_monitor()
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    peak, frames = monitor.peak, monitor.frames
    poses = system.station_output(ctx, "body_poses")
    hist = tuple(system.output(ctx, "history"))
    lift = params.lift
    objects = []
    for k in system.targets:
        b = system.bodies[k]
        p0, p1 = start[k], poses[b].translation()
        tries = [o for o in hist if o.target == k]
        grasped = peak[k] - p0[2] > 0.5 * lift
        placed = bool(any(o.placed for o in tries) and _in_zone(p1, params.zone, 0.02)
                      and np.linalg.norm(p1[:2] - p0[:2]) > 0.05 and p1[2] < p0[2] + 0.25)
        objects.append({"id": k, "attempts": len(tries), "grasped": bool(grasped), "placed": placed,
                        **({"barrier_contact": k in monitor.fixture_contact} if system.fixtures else {}),
                        "statuses": [o.status for o in tries],
                        "start": [round(float(v), 4) for v in p0], "end": [round(float(v), 4) for v in p1]})
    rec = {
        "method": params.method,
        "grasps_attempted": sum(o["attempts"] for o in objects),
        "grasps": sum(o["grasped"] for o in objects),
        "placements": sum(o["placed"] for o in objects),
        "objects": len(objects),
        "sim_seconds": round(float(ctx.get_time()), 2),
        "minutes": round(float(ctx.get_time()) / 60.0, 3),
        "cpu_seconds": round(time.process_time() - cpu, 1),
        "wall_seconds": round(time.perf_counter() - wall, 1),
        "plan_cpu_seconds": round(sum(o.plan_seconds for o in hist), 1),
        "mppi_calls": int(sum(o.mppi_calls for o in hist)),
        **({"placed_without_contact": sum(o["placed"] and not o["barrier_contact"] for o in objects)}
           if system.fixtures else {}),
        "failure": failure,
        "per_object": objects,
    }
    return RearrangeResult(rec, frames)


# --------------------------------------------------------------------------------- bench
def bench_params(method: str, seed: int, scene_set: str = "table", **overrides) -> RearrangeParams:
    """The Table 6.3 setting: the scene set's zone (the reachable table for `table`), the
    reference's T and H."""
    if scene_set not in SCENE_SETS:
        raise RearrangeError(f"scene set {scene_set!r} unknown; choose one of {', '.join(SCENE_SETS)}")
    return RearrangeParams(**{"method": method, "zone": list(SET_ZONES[scene_set]), "seed": seed, **overrides})


def check_rearrange_scenario(scenario, name: str = "") -> None:
    """RearrangeError (naming the scenario and the fix) unless `scenario` is a table station with the
    Panda and a front camera, as the rearrangement needs."""
    label = f"scenario {name!r}" if name else "the scenario"
    if scenario.environment.type != "table" or scenario.robot.name != "panda" or "front" not in scenario.cameras:
        raise RearrangeError(f"{label} is a {scenario.environment.type} station with the robot "
                             f"{scenario.robot.name or 'none'!r} and cameras {', '.join(scenario.cameras) or 'none'}; "
                             "the rearrangement runs on a table with the Panda and a front camera (PandaTable)")


def rearrange_rollout(method: str, seed: int, objects: int = 10, max_sim: float = 900.0,
                      scenario_name: str = SCENARIO, scenario_file: str | None = None, scene_set: str = "table",
                      **overrides) -> dict:
    """One scene of `scene_set` on the station `scenario_name` of `scenario_file` (default PandaTable)."""
    scenario = load_scenario(scenario_file, scenario_name)
    check_rearrange_scenario(scenario, scenario_name)
    scene = set_scene(scenario, scene_set, seed, objects)
    order = [scene.movable[i] for i in np.random.default_rng([seed, 31]).permutation(len(scene.movable))]
    params = bench_params(method, seed, scene_set, **overrides)
    system = build_rearrange(scenario, scene.heap, params, order=order, fixtures=scene.fixtures)
    res = run_rearrange(system, params, seed, max_sim=max_sim)
    station = {} if scenario_name == SCENARIO and scenario_file is None else {"scenario": scenario_name,
                                                                             "scenario_file": scenario_file or ""}
    return {"seed": int(seed), "scene_set": scene_set, **res.record, "order": list(system.targets), **station,
            "config": config_dict(params)}


def _key(r: dict) -> tuple:
    """A scene's record is done for (scene set, seed, objects, the controller's whole config)."""
    return r.get("scene_set", "table"), int(r["seed"]), r.get("objects"), json.dumps(r["config"], sort_keys=True)


def _bench_job(job: tuple) -> dict:
    method, seed, objects, overrides = job
    return rearrange_rollout(method, seed, objects, **overrides)


def run_rearrange_bench(method: str, scenes: int, seed_start: int, out, objects: int = 10, workers: int = 1,
                        log=print, progress=None, scene_set: str = "table", **overrides) -> list[dict]:
    """`ms-drake bench rearrange`: one JSON line per scene in `out`; seeds already there are skipped.
    progress(rec) after each scene, and its `start(done, todo)`, if it has one, before the first."""
    if method not in METHODS:
        raise RearrangeError(f"method {method!r} unknown; choose one of {', '.join(METHODS)}")
    if scenes < 1 or objects < 1:
        raise RearrangeError(f"scenes and objects must be >= 1, got {scenes}, {objects}")
    if scene_set not in SCENE_SETS:
        raise RearrangeError(f"scene set {scene_set!r} unknown; choose one of {', '.join(SCENE_SETS)}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = {_key(r) for r in read_records(out)}
    overrides = dict(overrides, scene_set=scene_set)
    cfg = {k: v for k, v in overrides.items() if k not in ("scene_set", "scenario_name", "scenario_file", "max_sim")}
    jobs = [(method, s, objects, overrides) for s in range(seed_start, seed_start + scenes)
            if (scene_set, s, objects, json.dumps(config_dict(bench_params(method, s, scene_set, **cfg)),
                                                  sort_keys=True)) not in done]
    recs = []
    if progress is not None and hasattr(progress, "start"):
        progress.start(scenes - len(jobs), len(jobs))
    for res in run_jobs(_bench_job, jobs, workers=workers):
        if res.error:
            log(f"  seed {res.job[1]}: error {res.error.splitlines()[-1] if res.error else ''}")
            continue
        r = res.value
        with out.open("a") as f:
            f.write(json.dumps(r) + "\n")
            f.flush()
            os.fsync(f.fileno())
        recs.append(r)
        log(f"  {method} seed {r['seed']}: grasps {r['grasps']}/{r['grasps_attempted']}, placements "
            f"{r['placements']}/{r['objects']}, {r['minutes']:.1f} sim min, cpu {r['cpu_seconds']:.0f} s")
        if progress is not None:
            progress(r)
    return recs


def rearrange_records(files) -> list[dict]:
    """The records of result files, one per (seed, objects, config): the first."""
    out, seen = [], set()
    for f in files:
        for r in read_records(Path(f)):
            if _key(r) not in seen:
                seen.add(_key(r))
                out.append(r)
    return out


def rearrange_table(records: list[dict]) -> str:
    """The Table 6.3 analogue: per scene set and method, scenes, objects, grasps (successful /
    attempted), placements, placements without a barrier contact (barrier scenes), simulated
    minutes, planning and total CPU seconds."""
    rows = [("| scene set | method | scenes | objects | grasps (successful / attempted) | placements | "
             "placed without barrier contact | time (sim min) | planning cpu s | total cpu s |"),
            "|---|---|---|---|---|---|---|---|---|---|"]
    by = {}
    for r in records:
        key = (r.get("scene_set", "table"), r["method"], r["config"]["trajectories"], r["config"]["horizon"])
        by.setdefault(key, []).append(r)
    for (ss, m, T, H), rs in by.items():
        name = m if m == "ik_line" else f"{m} (T={T}, H={H})"
        clean = str(sum(r["placed_without_contact"] for r in rs)) if ss == "barrier" else "-"
        rows.append(f"| {ss} | {name} | {len(rs)} | {sum(r['objects'] for r in rs)} | {sum(r['grasps'] for r in rs)} / "
                    f"{sum(r['grasps_attempted'] for r in rs)} | {sum(r['placements'] for r in rs)} | {clean} | "
                    f"{sum(r['minutes'] for r in rs):.1f} | {sum(r['plan_cpu_seconds'] for r in rs):.0f} | "
                    f"{sum(r['cpu_seconds'] for r in rs):.0f} |")
    return "\n".join(rows)


# --------------------------------------------------------------------------------- demo
def run_rearrange_demo(out, method: str = "coal_reconstruction", seed: int = DEMO_SEED, meshcat_html: bool = True,
                       log=print, scenario=None, scene_set: str | None = None, objects: int = 3,
                       **overrides) -> dict:
    """`ms-drake demo rearrange`: the demo's scene (a box past a row of cylinders) or, with
    `scene_set`, scene `seed` of that set with `objects` objects; rearrange.gif (the front camera,
    one frame per simulated second, the FSM's state written on it), rearrange.json and
    meshcat_recording.html in `out`. Returns {name: path} and the record under "record"."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario if scenario is not None else load_scenario(None, SCENARIO)
    check_rearrange_scenario(scenario)
    if scene_set is None:
        heap, zone, order, fixtures = barrier_scene(), DEMO_ZONE, [0], ()
    else:
        scene = set_scene(scenario, scene_set, seed, objects)
        heap, zone, order, fixtures = scene.heap, scene.zone, list(scene.movable), scene.fixtures
    params = RearrangeParams(method=method, zone=list(zone), seed=seed, **overrides)
    meshcat = Meshcat() if meshcat_html else None
    system = build_rearrange(scenario, heap, params, order=order, meshcat=meshcat, fixtures=fixtures)
    res = run_rearrange(system, params, seed, max_sim=240.0 * len(order), frame_every=1.0, meshcat=meshcat, log=log)
    images = []
    for t, phase, rgb in res.frames:
        img = np.ascontiguousarray(rgb)
        cv2.putText(img, f"t={t:5.1f} s  {phase}", (12, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        images.append(cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA))
    written = {}
    if images:
        gif = out / "rearrange.gif"
        imageio.mimsave(gif, images, duration=0.25, loop=0)
        written["gif"] = str(gif)
    (out / "rearrange.json").write_text(json.dumps(res.record, indent=1))
    written["record"] = str(out / "rearrange.json")
    if meshcat is not None:
        html = out / "meshcat_recording.html"
        html.write_text(meshcat.StaticHtml())
        written["meshcat"] = str(html)
    r = res.record
    where = "the demo scene" if scene_set is None else f"{scene_set} scene {seed}"
    contact = f", {r['placed_without_contact']} without barrier contact" if "placed_without_contact" in r else ""
    log(f"  {method} on {where}: grasped {r['grasps']}/{r['grasps_attempted']}, placed "
        f"{r['placements']}/{r['objects']}{contact} in {r['sim_seconds']:.0f} s simulated ({r['mppi_calls']} MPPI "
        f"calls, planning {r['plan_cpu_seconds']:.0f} s cpu, total {r['cpu_seconds']:.0f} s cpu)")
    return written | {"success": bool(r["placements"] == r["objects"])}
