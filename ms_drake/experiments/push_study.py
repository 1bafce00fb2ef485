"""The linear push policies study of Ch. 4: metrics, improvable heaps (Algorithm 1), the benchmark.

Physics: the primitive mode's floating closed jaw (FloatingGripperBin, PrimitiveBackend) moves
along the push segment in Drake (5 ms steps, PRIMITIVE_PUSH_TIME_STEP: the search's pushing
selectors' step, where the push agrees with the YuMi's): from its park pose beside
the bin to above the start, down, along the segment, up and back, commanded through the station's
floating-gripper driver; then `settle` s. Objects that leave the bin are out of the after state.

Metrics (lines 590-642), on the objects in the bin before and after the push:
  separation gain  Delta D = (D1 - D0) / max(D0, D1), D the mean of the pairwise distances of the
                   objects' centres of mass and of each centre's distance to the nearest bin wall
                   (both in the bin's plane: our choice; the reference writes ||o_i - o_j||);
  jaw / suction / overall gain  Q*_1 - Q*_0, Q*_j = max over every object's `grasps` sampled
                   parallel-jaw grasps (antipodal pairs, approach within `max_approach` of straight
                   down) of the robust soft-point quality (GraspEvaluator("soft_point"),
                   `robust_samples` trials), Q*_s the same for suction grasps (surface points along
                   minus the normal, SuctionEvaluator), Q*_o = max(Q*_j, Q*_s). The max runs over
                   the grasps whose gripper is collision-free (coal: the opened jaw's palm and
                   fingers, or the cup's stem as a cylinder along the approach, against the other
                   objects' collision shapes and the bin): best per object, then the best object.
A grasp's quality depends only on where gravity points in the object's frame, so an object's
grasps are sampled and scored once per tilt bin (gravity in the object frame rounded to
`tilt_grid` per component, ~3 degrees), in a frame where the rounded gravity points exactly down:
the metrics of a state do not depend on the states measured before it. The collision check is
redone in every state. `sampling` says what seeds the grasp draw and the robust trials:
  "tilt_bin"  (heap seed, object, bin): an object that rolls into another bin gets a fresh draw of
              contacts and trials, so its Q* changes by the draw's noise alone (~0.2 at stuck states,
              `quality_noise`); the states Algorithm 1 keeps scored low partly by that noise, and a
              push that moves the object regresses them upwards whatever it does;
  "object"    (heap seed, object): common random numbers -- the same surface points and the same
              perturbation draws in every bin (the approaches and the gravity of each bin still
              differ), so the quality of an object changes only with its pose and its neighbours.

Algorithm 1 (lines 704-720), `improvable_heap(seed)`: a heap of N objects, N uniform in
[`min_objects`, `max_objects`] (our choice: small heaps, as the reference's final heaps mostly
were), dropped (ms_drake.scenes.heaps) and settled in the station; while objects remain: Q*_o of
the state; below `threshold` -> record the state; else execute the best grasp (primitive mode:
success with probability = its quality, from (seed, t)); `max_failures` consecutive failures ->
record the state. A recorded state is improvable when at least one of the five policies'
pushes, executed in physics, gives an overall quality gain > 0 (the reference's rejection step).
"""

from __future__ import annotations

import copy
import functools
import json
import os
import time
import zlib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import coal
import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.systems.analysis import Simulator
from scipy.stats import f_oneway

from ms_drake.config_files import ConfigError
from ms_drake.errors import MsDrakeError
from ms_drake.execution import PRIMITIVE_PUSH_TIME_STEP, FullBackend, Motion, PrimitiveBackend, remove_objects
from ms_drake.execution.backends import tcp_offset_of
from ms_drake.experiments.figures import figure_dir, save_png
from ms_drake.experiments.records import read_record_file
from ms_drake.experiments.heap_grasps import (
    _coal_shape,
    _shape_pose,
    gripper_boxes,
    heap_grasp_inputs,
)
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.grasping.evaluator import GraspEvaluator
from ms_drake.grasping.grasp import SuctionGrasp
from ms_drake.grasping.indexed import object_parts
from ms_drake.grasping.meshes import object_mesh
from ms_drake.grasping.samplers import sample_antipodal_grasps, sample_suction_grasps
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.objects import get_object
from ms_drake.parallel import run_jobs
from ms_drake.pushing.policies import (
    POLICIES,
    PolicyParams,
    check_push_policy,
    image_scene,
    plan_policy_push,
    state_scene,
)
from ms_drake.scenario import ScenarioRef, load_scenario
from ms_drake.scenes.heaps import (
    generate_heap,
    heap_from_dict,
    heap_to_dict,
    scenario_with_heap,
    set_heap_poses,
)
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.environments import _boxes
from ms_drake.station.robots import set_arm_positions
from ms_drake.types import Action, Heap, ObjectGeometry

METRICS = ("separation_gain", "jaw_gain", "suction_gain", "overall_gain")
SAMPLINGS = ("tilt_bin", "object")  # PushStudyAblation.sampling
OBJECT_SETS = ("ycb", "procedural")  # PushStudyConfig.object_set
WORLD_SCENARIOS = {"primitive": "FloatingGripperBin", "full": "YuMiBin"}  # PushWorld's station per fidelity


@functools.lru_cache(maxsize=512)
def _mesh(name: str):
    """An object's watertight trimesh (cached; mesh-set objects repaired or closed by
    grasping.meshes.object_mesh, procedural ones as they are)."""
    return object_mesh(name)


@functools.lru_cache(maxsize=4)
def _scenario(name: str):
    return load_scenario(None, name)


@dataclass(frozen=True)
class PushStudyAblation:
    """Switches that reproduce settings other than the study's; each default is the study's.

    - sampling: what seeds an object's grasp draw and robust trials (module docstring): "tilt_bin"
      or "object" (the same draw in every tilt bin: common random numbers across bins).
    - compare_sampling: another sampling scored on the same states and pushes ("" = none): the heap
      records then carry its before metrics and gains under "compare".
    - transfer_speed: the primitive jaw's transfers between its park pose and above the push (free
      space above the walls) [m/s]; None = the push's travel speed (0.5 m/s). 2.0 halves the CPU.
    - quasi_random_checked: quasi-random's push only as far as the object is free to move, its
      start free, like the other policies' pushes (PolicyParams.quasi_random_checked)."""

    sampling: str = "tilt_bin"
    compare_sampling: str = ""
    transfer_speed: float | None = None
    quasi_random_checked: bool = False

    def __post_init__(self):
        for key, value, allowed in (("sampling", self.sampling, SAMPLINGS),
                                    ("compare_sampling", self.compare_sampling, ("",) + SAMPLINGS)):
            if value not in allowed:
                raise ConfigError(f"ablation.{key} {value!r} unknown; choose one of "
                                 f"{', '.join(repr(a) for a in allowed)}")
        if self.transfer_speed is not None and not self.transfer_speed > 0:
            raise ConfigError(f"ablation.transfer_speed {self.transfer_speed!r}: a speed > 0 m/s, or None (the "
                             "push's travel speed)")


@dataclass(frozen=True)
class PushStudyConfig:
    """The push study's settings (Ch. 4: improvable heaps by Algorithm 1, the five policies' pushes
    and their grasp-quality gains); a Drake YAML file (ms_drake.config_files.load_config). Every heap
    record keeps it (`config`). object_set: the heaps' objects, household meshes ("ycb", as the
    reference's: Algorithm 1 leaves several objects stuck) or "procedural" (BinHeap15's shapes,
    which it leaves stuck mostly on one lying cylinder no push makes graspable)."""

    grasps: int = 100  # per object and gripper (the reference's)
    robust_samples: int = 4
    max_approach: float = np.radians(60.0)
    tilt_grid: float = 0.05  # gravity in the object frame, rounded per component (bins of ~3 degrees)
    cup_length: float = 0.10  # the suction stem checked for collisions along the approach
    cup_radius: float = 0.015
    threshold: float = 0.5
    max_failures: int = 3
    min_objects: int = 4
    max_objects: int = 10
    settle: float = 0.5
    time_step: float = PRIMITIVE_PUSH_TIME_STEP  # where the primitive push agrees with the YuMi's
    object_set: str = "ycb"
    ablation: PushStudyAblation = field(default_factory=PushStudyAblation)

    def __post_init__(self):
        if isinstance(self.ablation, dict):
            object.__setattr__(self, "ablation", PushStudyAblation(**self.ablation))
        if self.object_set not in OBJECT_SETS:
            raise ConfigError(f"object_set {self.object_set!r} unknown; choose one of "
                             f"{', '.join(repr(a) for a in OBJECT_SETS)}")

    def policy_params(self) -> PolicyParams:
        """The push planners' parameters in this study."""
        return PolicyParams(quasi_random_checked=self.ablation.quasi_random_checked)


def heap_config(rec: dict) -> PushStudyConfig:
    """The config a heap record was made with (its `config`)."""
    if "config" not in rec:
        raise MsDrakeError(f"heap record of seed {rec.get('seed')} has no config: re-run `ms-drake data push-heaps`")
    return PushStudyConfig(**rec["config"])


# --------------------------------------------------------------------------- physics
class PushWorld:
    """A bin station holding a heap (cameras off unless asked): states, grasps, pushes.

    fidelity "primitive" (the study's): FloatingGripperBin + PrimitiveBackend, plant step
    `params.time_step`. fidelity "full": YuMiBin (or `scenario`, any robot scenario) at the
    scenario's own plant step + FullBackend (IK + ruckig from the arm's park configuration through
    the station's drivers). Commands are held over one plant step."""

    def __init__(self, heap: Heap, params: PushStudyConfig = PushStudyConfig(), cameras: bool = False,
                 fidelity: str = "primitive", scenario: str | ScenarioRef | None = None):
        if fidelity not in WORLD_SCENARIOS:
            raise ValueError(f"fidelity {fidelity!r} unknown; choose one of {', '.join(WORLD_SCENARIOS)}")
        s = scenario_with_heap(ScenarioRef.of(scenario or WORLD_SCENARIOS[fidelity]).load(), heap)
        if fidelity == "primitive":
            s.plant_config.time_step = params.time_step
        if not cameras:
            s.cameras = {}
        self.scenario, self.params, self.fidelity = s, params, fidelity
        self.step = float(s.plant_config.time_step)
        self.station = MakeStation(s, target_index=-1)
        self.plant = get_plant(self.station)
        self.sim = Simulator(self.station)
        self.context = self.sim.get_mutable_context()
        self.pc = self.plant.GetMyMutableContextFromRoot(self.context)
        self.objects = station_objects(self.plant)
        self.ids = [o.model_name for o in self.objects]
        self.names = {o.model_name: o.full_name for o in self.objects}
        self.workspace = Workspace.from_scenario(s)
        bodies = {o.model_name: int(o.body_index) for o in self.objects}
        if fidelity == "primitive":
            self.backend = PrimitiveBackend(bodies, self.workspace, tcp_offset_of(self.plant),
                                            transfer_speed=params.ablation.transfer_speed)
        else:
            self.backend = FullBackend(s, bodies, self.workspace)
        self.removed: set = set()
        cmds = self.backend.initial_commands()
        self.hold = {port: np.atleast_1d(np.asarray(v, float)) for port, v in cmds.items()}
        self._fix(self.hold)
        set_heap_poses(self.station, self.context, heap)
        set_arm_positions(self.plant, self.pc, s.robot.name, cmds)
        self.sim.Initialize()

    def _fix(self, commands: dict):
        for port, v in commands.items():
            self.station.GetInputPort(port).FixValue(self.context, v)

    # state --------------------------------------------------------------------------------
    def snapshot(self):
        return self.context.Clone(), set(self.removed), dict(self.hold)

    def restore(self, snap):
        ctx, removed, hold = snap
        self.context.SetTimeStateAndParametersFrom(ctx)
        self.removed = set(removed)
        self.hold = dict(hold)
        self._fix(self.hold)
        self.sim.Initialize()

    def set_state(self, poses: dict):
        """Objects of `poses` ({id: 4x4}, e.g. a heap record's "state") at those poses, at rest;
        every other object out of the scene (removed)."""
        unknown = sorted(set(poses) - set(self.ids))
        if unknown:
            raise ValueError(f"state objects {unknown} are not in this world ({len(self.ids)} objects); build the "
                             f"world from the record's own heap")
        for o, oid in zip(self.objects, self.ids):
            if oid in poses:
                body = self.plant.get_body(o.body_index)
                self.plant.SetFreeBodyPose(self.pc, body, RigidTransform(np.asarray(poses[oid], float)))
                self.plant.SetFreeBodySpatialVelocity(self.pc, body, SpatialVelocity(np.zeros(3), np.zeros(3)))
            elif oid not in self.removed:
                self.remove(oid)
        self.sim.Initialize()

    def pose(self, oid: str) -> np.ndarray:
        o = self.objects[self.ids.index(oid)]
        return self.plant.EvalBodyPoseInWorld(self.pc, self.plant.get_body(o.body_index)).GetAsMatrix4()

    def present(self) -> list[str]:
        """Objects in the bin (not grasped, not fallen out)."""
        ws = self.workspace
        out = []
        for oid in self.ids:
            if oid in self.removed:
                continue
            p = self.pose(oid)[:3, 3]
            if p[2] < ws.floor_z - 0.03 or not ws.inside_xy(p, margin=-0.02):
                continue
            out.append(oid)
        return out

    def geometry(self, ids=None) -> tuple:
        out = []
        for oid in ids if ids is not None else self.present():
            spec = get_object(self.names[oid])
            m = _mesh(self.names[oid])
            out.append(ObjectGeometry(oid, np.asarray(m.vertices, float), np.asarray(m.faces), self.pose(oid),
                                      float(spec.mass)))
        return tuple(out)

    def poses_record(self) -> dict:
        """{id: 4x4 as nested lists} of the objects present."""
        return {oid: np.round(self.pose(oid), 6).tolist() for oid in self.present()}

    # actions ------------------------------------------------------------------------------
    def advance(self, dt: float, motion: Motion | None = None):
        """Simulate `dt` s in plant steps; with `motion`, its commands (at the time since the call)
        on their input ports at every step, the held commands on the others; at the end the
        motion's final commands are held."""
        t0 = self.context.get_time()
        steps = max(1, round(dt / self.step))
        for k in range(1, steps + 1):
            t = t0 + k * self.step
            if motion is not None:
                v = motion.values(t - t0, self.hold)
                self._fix({port: v[port] for port in motion.commands})
            self.sim.AdvanceTo(t)
        if motion is not None:
            self.hold = motion.values(motion.duration, self.hold)
        q = self.plant.GetPositions(self.pc)
        if not np.all(np.isfinite(q)):
            raise RuntimeError("non-finite plant state")

    def remove(self, oid: str):
        o = self.objects[self.ids.index(oid)]
        remove_objects(self.plant, self.pc, [int(o.body_index)])
        self.removed.add(oid)

    def execute_push(self, push) -> float | str:
        """The backend's push, then the settle time. Primitive: PrimitiveBackend's legs from the
        parked jaw (above the start, down, along the segment, up, back to the park pose), each a
        command of the floating-gripper driver. Full: FullBackend's closed jaw at the push's height
        along the segment (plan_push: above the start, down, along, up), the arm back to park.
        Returns the simulated seconds, or the planner's status (a str: "unreachable",
        "collision", ...) when the robot cannot execute the push (nothing is simulated)."""
        motion = self.backend.plan(Action("push", push=push), self.hold, 0)
        if isinstance(motion, str):
            return motion
        self.advance(motion.duration, motion)
        return motion.duration


# --------------------------------------------------------------------------- metrics
def mean_separation(centers_xy: np.ndarray, workspace: Workspace) -> float:
    """D of line 600: pairwise centre distances and each centre's distance to the nearest wall,
    averaged over C(n, 2) + n terms."""
    C = np.asarray(centers_xy, float).reshape(-1, 2)
    n = len(C)
    if n == 0:
        return 0.0
    half = 0.5 * np.asarray(workspace.size_xy)
    rel = np.abs(C - np.asarray(workspace.center_xy))
    wall = np.maximum(np.min(half - rel, axis=1), 0.0)
    iu = np.triu_indices(n, 1)
    pair = np.linalg.norm(C[:, None] - C[None], axis=-1)[iu]
    return float((pair.sum() + wall.sum()) / (len(pair) + n))


def separation_gain(d0: float, d1: float) -> float:
    m = max(d0, d1)
    return 0.0 if m <= 0 else float((d1 - d0) / m)


def _center(geom: ObjectGeometry) -> np.ndarray:
    X = np.asarray(geom.X_WO, float)
    v, f = np.asarray(geom.vertices, float), np.asarray(geom.faces, int)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    com = v.mean(axis=0) if abs(vol.sum()) < 1e-12 else ((a + b + c) / 4.0 * vol[:, None]).sum(axis=0) / vol.sum()
    return X[:3, :3] @ com + X[:3, 3]


def _bin_shapes(scenario) -> list:
    env = scenario.environment
    X_env = np.eye(4)
    X_env[:3, 3] = np.asarray(env.position, float)
    out = []
    for _, sh, _ in _boxes(env.type, env.resolved_size(), env.wall_thickness):
        T = _shape_pose(X_env, sh.pose)
        out.append(_prepared(_coal_shape(sh), T[:3, :3], T[:3, 3]))
    return out


def _object_shapes(oid: str, name: str, X: np.ndarray) -> list:
    """The object's collision shapes at pose X (primitives, and convex hulls of mesh parts: the
    grasp planner's `object_parts`)."""
    out = []
    for shape, T, c, r in object_parts(name):
        TW = X @ T
        sphere = None if isinstance(shape, (coal.Box, coal.Cylinder, coal.Sphere)) else (X[:3, :3] @ c + X[:3, 3], r)
        out.append(_prepared(shape, TW[:3, :3], TW[:3, 3], sphere))
    return out


def _half(shape) -> np.ndarray:
    if isinstance(shape, coal.Box):
        return np.asarray(shape.halfSide, float)
    if isinstance(shape, coal.Cylinder):
        return np.array([shape.radius, shape.radius, shape.halfLength])
    return np.full(3, float(shape.radius))


def _prepared(shape, R: np.ndarray, p: np.ndarray, sphere=None) -> tuple:
    """(shape, coal pose, world AABB lo, hi): the AABB skips coal calls that cannot collide.
    sphere: (world centre, radius) bounding a shape that is not a primitive (a convex hull)."""
    if sphere is not None:
        c, r = np.asarray(sphere[0], float), float(sphere[1])
        return shape, coal.Transform3s(R, p), c - r, c + r
    e = np.abs(R) @ _half(shape)
    return shape, coal.Transform3s(R, p), p - e, p + e


def _collides(boxes, shapes) -> bool:
    """Any of `boxes` against any of `shapes` (both lists of _prepared tuples)."""
    req = coal.CollisionRequest()
    for shape1, T1, lo1, hi1 in boxes:
        for shape, T2, lo2, hi2 in shapes:
            if np.any(lo1 > hi2) or np.any(lo2 > hi1):
                continue
            res = coal.CollisionResult()
            if coal.collide(shape1, T1, shape, T2, req, res):
                return True
    return False


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R a = b (unit vectors)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: half a turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        axis = axis if np.linalg.norm(axis) > 1e-6 else np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1 + c)


def _jaw_boxes(g):
    return [_prepared(coal.Box(*np.maximum(size - 0.002, 1e-6)), X[:3, :3], X[:3, 3])
            for _, size, X in gripper_boxes(g)]


def _cup_boxes(point, approach, params: PushStudyConfig):
    z = -np.asarray(approach, float)  # out of the surface
    z /= np.linalg.norm(z)
    x = np.cross(z, [1.0, 0.0, 0.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    c = np.asarray(point, float) + z * (0.003 + 0.5 * params.cup_length)
    return [_prepared(coal.Cylinder(params.cup_radius, params.cup_length), R, c)]


class GraspSets:
    """Sampled grasps per object, kept in the object frame while the object's tilt is unchanged
    (module docstring); a grasp's robust quality is evaluated when it is first found
    collision-free and kept with it. Per state and object the grasps are checked in sampled order
    and the search stops at a quality of 1 (nothing beats it), so the maxima are exact."""

    def __init__(self, params: PushStudyConfig = PushStudyConfig(), seed: int = 0):
        self.params, self.seed = params, int(seed)
        self.jaw_eval = GraspEvaluator("soft_point")
        self.suction_eval = SuctionEvaluator()
        self._cache: dict = {}  # (id, tilt bin) -> [X of the bin, jaw [[g_O, q]], suction [[p_O, a_O, q]], bin, seed]
        self.evaluations = 0

    def _sets(self, oid: str, name: str, X: np.ndarray):
        """The object's grasp set for its tilt bin: gravity in the object frame rounded to a grid of
        `tilt_grid` per component; sampled and scored in a frame where that rounded gravity points
        exactly down, so the set and its qualities depend on (seed, object, bin) only."""
        g_O = X[:3, :3].T @ np.array([0.0, 0.0, -1.0])
        key = tuple(int(v) for v in np.round(g_O / self.params.tilt_grid))
        hit = self._cache.get((oid, key))
        if hit is not None:
            return hit
        p = self.params
        mesh = _mesh(name)
        gq = np.asarray(key, float)
        gq = gq / np.linalg.norm(gq) if np.linalg.norm(gq) > 0 else g_O
        Xq = np.eye(4)
        Xq[:3, :3] = _rotation_between(gq, np.array([0.0, 0.0, -1.0]))
        draw = [self.seed, zlib.crc32(oid.encode())]
        if p.ablation.sampling == "tilt_bin":
            draw.append(zlib.crc32(repr(key).encode()))
        rng_seed = int(np.random.default_rng(draw).integers(2**31))
        Xq_inv = np.linalg.inv(Xq)
        jaw = [[g.transformed(Xq_inv), None] for g in sample_antipodal_grasps(mesh, Xq, p.grasps, seed=rng_seed)
               if -g.approach[2] >= np.cos(p.max_approach)]
        suc = [[Xq_inv[:3, :3] @ g.point, Xq_inv[:3, :3] @ g.approach, None]
               for g in sample_suction_grasps(mesh, Xq, p.grasps, seed=rng_seed + 1, max_approach_angle=p.max_approach)]
        entry = [Xq, jaw, suc, key, rng_seed]
        self._cache[(oid, key)] = entry
        return entry

    def _best(self, oid, name, X, others, kind):
        entry = self._sets(oid, name, X)
        spec = get_object(name)
        best, best_g = 0.0, None
        for item in (entry[1] if kind == "jaw" else entry[2]):
            if kind == "jaw":
                g = item[0].transformed(X)
                boxes = _jaw_boxes(g)
            else:
                g = (X[:3, :3] @ item[0] + X[:3, 3], X[:3, :3] @ item[1])
                boxes = _cup_boxes(g[0], g[1], self.params)
            if item[-1] is not None and item[-1] <= best:
                continue  # cannot beat the best so far
            if _collides(boxes, others):
                continue
            if item[-1] is None:  # scored in the bin's frame (gravity exactly the rounded one)
                mesh, Xq = _mesh(name), entry[0]
                if kind == "jaw":
                    item[-1] = float(self.jaw_eval.quality(mesh, Xq, item[0].transformed(Xq), spec.mass,
                                                           self.params.robust_samples, seed=entry[4]))
                else:
                    sg = SuctionGrasp(Xq[:3, :3] @ item[0], Xq[:3, :3] @ item[1])
                    item[-1] = float(self.suction_eval.quality(mesh, Xq, sg, spec.mass, self.params.robust_samples,
                                                               seed=entry[4]))
                self.evaluations += 1
            if item[-1] > best:
                best, best_g = item[-1], g
                if best >= 1.0:
                    break
        return best, best_g

    def qualities(self, world: PushWorld, ids=None) -> dict:
        """{"jaw": Q*_j, "suction": Q*_s, "overall": Q*_o, "per_object": {id: [best jaw, best suction]},
        "best": (kind, id, grasp, quality) of the best grasp}."""
        ids = world.present() if ids is None else ids
        X = {oid: world.pose(oid) for oid in ids}
        shapes = {oid: _object_shapes(oid, world.names[oid], X[oid]) for oid in ids}
        bin_shapes = _bin_shapes(world.scenario)
        per, best = {}, ("", "", None, 0.0)
        for oid in ids:
            others = [s for k, v in shapes.items() if k != oid for s in v] + bin_shapes
            bj, gj = self._best(oid, world.names[oid], X[oid], others, "jaw")
            bs, gs = self._best(oid, world.names[oid], X[oid], others, "suction")
            if bj > best[3]:
                best = ("parallel_jaw", oid, gj, bj)
            if bs > best[3]:
                best = ("suction", oid, gs, bs)
            per[oid] = [bj, bs]
        qj = max((v[0] for v in per.values()), default=0.0)
        qs = max((v[1] for v in per.values()), default=0.0)
        return {"jaw": qj, "suction": qs, "overall": max(qj, qs), "per_object": per, "best": best}


def state_metrics(world: PushWorld, sets: GraspSets) -> dict:
    ids = world.present()
    geoms = world.geometry(ids)
    D = mean_separation(np.array([_center(g)[:2] for g in geoms]), world.workspace)
    q = sets.qualities(world, ids)
    return {"D": D, "jaw": q["jaw"], "suction": q["suction"], "overall": q["overall"],
            "per_object": q["per_object"], "objects": len(ids), "_best": q["best"]}


def gains(before: dict, after: dict) -> dict:
    return {"separation_gain": separation_gain(before["D"], after["D"]),
            "jaw_gain": after["jaw"] - before["jaw"], "suction_gain": after["suction"] - before["suction"],
            "overall_gain": after["overall"] - before["overall"]}


def motion_of(before: dict, after: dict, pushed: str) -> dict:
    """How the objects moved in a push ({id: 4x4} before and after; objects gone after are left
    out): the pushed object's and the largest displacement [m] and tilt change [deg] of any object.
    Tilt change: the angle between gravity in the object's frame before and after (a turn about the
    vertical is none; tipping over or rolling is), what an object's grasp qualities depend on."""
    def moved(a, b):
        ga, gb = a[:3, :3].T @ [0.0, 0.0, -1.0], b[:3, :3].T @ [0.0, 0.0, -1.0]
        return float(np.linalg.norm(b[:3, 3] - a[:3, 3])), float(np.degrees(np.arccos(np.clip(ga @ gb, -1.0, 1.0))))
    m = {oid: moved(before[oid], after[oid]) for oid in before if oid in after}
    d, r = m.get(pushed, (0.0, 0.0))
    return {"pushed_displacement": d, "pushed_tilt_deg": r,
            "max_displacement": max((v[0] for v in m.values()), default=0.0),
            "max_tilt_deg": max((v[1] for v in m.values()), default=0.0)}


def run_policy(world: PushWorld, snap, before: dict, sets: GraspSets, policy: str, seed: int,
               policy_params: PolicyParams | None = None, compare: tuple | None = None) -> dict:
    """Plan `policy`'s push on the full state of `snap`, execute it in physics, the four gains.
    compare: (GraspSets, before metrics) of another sampling: its gains on the same push go to
    the record's "compare" entry."""
    check_push_policy(policy)
    world.restore(snap)
    geoms = world.geometry()
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    push = plan_policy_push(policy, state_scene(geoms, world.workspace), policy_params or PolicyParams(),
                            seed=[int(seed), POLICIES.index(policy)])
    plan_ms = 1000 * (time.process_time() - cpu0)
    del t0
    rec = {"policy": policy, "pushed": push is not None, "plan_ms": plan_ms, "push": None}
    if push is None:  # no collision-free push: the state is unchanged
        rec.update({k: 0.0 for k in METRICS}, left_bin=0, after={k: before[k] for k in ("D", "jaw", "suction",
                                                                                        "overall")})
        if compare is not None:
            rec["compare"] = {k: 0.0 for k in METRICS}
        return rec
    rec["push"] = {"start": list(push.start), "end": list(push.end), "object": push.object_id}
    X0 = {oid: world.pose(oid) for oid in world.present()}
    cpu1 = time.process_time()
    try:
        done = world.execute_push(push)
    except RuntimeError as e:
        rec.update({k: 0.0 for k in METRICS}, error=str(e).splitlines()[0] if str(e) else "RuntimeError")
        return rec
    if isinstance(done, str):  # the robot cannot execute it (full fidelity): the state is unchanged
        rec.update({k: 0.0 for k in METRICS}, error=f"plan_failed:{done}")
        return rec
    rec["sim_cpu_s"] = time.process_time() - cpu1
    rec.update(motion_of(X0, {oid: world.pose(oid) for oid in world.present()}, push.object_id))
    after = state_metrics(world, sets)
    rec.update(gains(before, after))
    rec["left_bin"] = before["objects"] - after["objects"]
    rec["after"] = {k: after[k] for k in ("D", "jaw", "suction", "overall")}
    rec["after_per_object"] = after["per_object"]
    if compare is not None:
        alt = state_metrics(world, compare[0])
        rec["compare"] = dict(gains(compare[1], alt), after={k: alt[k] for k in ("jaw", "suction", "overall")})
    return rec


# --------------------------------------------------------------------------- Algorithm 1
def _heap_size(seed: int, params: PushStudyConfig) -> int:
    return int(np.random.default_rng([seed, 17]).integers(params.min_objects, params.max_objects + 1))


def grasp_until_stuck(world: PushWorld, sets: GraspSets, seed: int, params: PushStudyConfig) -> tuple[str, dict, int]:
    """Algorithm 1's loop: ("low_quality" | "failures" | "cleared", metrics of the final state, grasps)."""
    failures, t = 0, 0
    while True:
        m = state_metrics(world, sets)
        if m["objects"] == 0:
            return "cleared", m, t
        if m["overall"] < params.threshold:
            return "low_quality", m, t
        _, oid, _, q = m["_best"]
        ok = bool(np.random.default_rng([seed, t, 4242]).random() < q)
        t += 1
        if ok:
            world.remove(oid)
            failures = 0
        else:
            failures += 1
            if failures >= params.max_failures:
                return "failures", m, t
        world.advance(params.settle)


def study_heap(seed: int, params: PushStudyConfig) -> tuple[Heap, int]:
    """(heap `seed` of the study, its object count): N drawn from the seed, objects of
    `params.object_set`; no target in this study."""
    n = _heap_size(seed, params)
    heap = generate_heap(copy.deepcopy(_scenario("BinHeap15")), n, seed, object_set=None if params.object_set == "procedural" else params.object_set)
    return Heap(heap.seed, heap.environment, heap.objects), n


def improvable_heap(seed: int, params: PushStudyConfig = PushStudyConfig(), policies=POLICIES) -> dict:
    """One heap through Algorithm 1 and the five policies: a JSON-able record (module docstring)."""
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    heap, n = study_heap(seed, params)
    world = PushWorld(heap, params)
    world.advance(params.settle)  # the dropped heap at rest in the station's contact model
    sets = GraspSets(params, seed)
    reason, before, grasps = grasp_until_stuck(world, sets, seed, params)
    rec = {"seed": int(seed), "config": asdict(params), "objects_dropped": n, "grasps": grasps, "stop": reason,
           "objects": before["objects"], "heap": heap_to_dict(heap), "improvable": False}
    if reason == "cleared":
        rec.update(seconds=time.perf_counter() - t_wall, cpu_seconds=time.process_time() - t_cpu)
        return rec
    snap = world.snapshot()
    rec["state"] = world.poses_record()
    rec["before"] = {k: before[k] for k in ("D", "jaw", "suction", "overall")}
    rec["before_per_object"] = before["per_object"]
    compare = None
    if params.ablation.compare_sampling:
        alt_sets = GraspSets(replace(params, ablation=replace(params.ablation, sampling=params.ablation.compare_sampling)),
                             seed)
        compare = (alt_sets, state_metrics(world, alt_sets))
        rec["compare"] = {"sampling": params.ablation.compare_sampling,
                          "before": {k: compare[1][k] for k in ("jaw", "suction", "overall")}}
    results = {}
    for p in policies:
        results[p] = run_policy(world, snap, before, sets, p, seed, policy_params=params.policy_params(),
                                compare=compare)
    rec["policies"] = results
    rec["improvable"] = any(r.get("overall_gain", 0.0) > 1e-9 for r in results.values())
    rec["grasp_evaluations"] = sets.evaluations
    rec.update(seconds=time.perf_counter() - t_wall, cpu_seconds=time.process_time() - t_cpu)
    return rec


# --------------------------------------------------------------------------- data and benchmark
HEAPS_FILE = "heaps.jsonl"


def push_heap_job(job: tuple) -> dict:
    """(seed, PushStudyConfig as a dict) -> improvable_heap's record (module-level for worker pools)."""
    seed, params = job
    return improvable_heap(int(seed), PushStudyConfig(**params))


def read_jsonl(path: Path) -> list[dict]:
    """Records of a JSON-lines file (none when it is missing or empty); a torn last line (killed
    mid-write) is skipped, any other line that is not a record raises RecordFileError
    (records.read_record_file)."""
    path = Path(path)
    if not path.exists() or not path.read_text().strip():
        return []
    return read_record_file(path, required=())


def _append(path: Path, rec: dict) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(rec) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _rewrite_clean(path: Path, recs: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))


def write_push_heaps(count: int, out_dir: Path, seed_start: int = 0, workers: int = 1, use_ray: bool = False,
                     ray_address: str | None = None, params: PushStudyConfig = PushStudyConfig(), bar=None) -> dict:
    """Algorithm 1 on heaps seed_start .. seed_start + count - 1 into out_dir/heaps.jsonl (one record
    per heap, resumable: finished seeds are kept and skipped). Returns the counts."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / HEAPS_FILE
    recs = read_jsonl(path)
    mine = asdict(params)
    for n, r in enumerate(recs, start=1):
        if r.get("config") != mine:
            theirs = r.get("config")
            diff = ("no config" if theirs is None else ", ".join(
                f"{k}={theirs.get(k)!r}" for k in mine if theirs.get(k) != mine[k]))
            raise MsDrakeError(f"{path}, line {n}: a heap of another config ({diff}); write to another folder, or "
                             "run with that config (--config / --set)")
    _rewrite_clean(path, recs)
    done = {int(r["seed"]) for r in recs}
    seeds = [k for k in range(seed_start, seed_start + count) if k not in done]
    jobs = [(k, asdict(params)) for k in seeds]
    if bar is not None and hasattr(bar, "start"):  # before any heap: (already done, to run)
        bar.start(count - len(seeds), len(seeds))
    failed = []
    for r in run_jobs(push_heap_job, jobs, workers=workers, use_ray=use_ray, ray_address=ray_address):
        if r.ok:
            _append(path, r.value)
        else:
            failed.append((r.job[0], r.error.splitlines()[-1] if r.error else ""))
        if bar is not None:
            bar(r)
    recs = [r for r in read_jsonl(path) if seed_start <= int(r["seed"]) < seed_start + count]
    return {"dropped": len(recs), "recorded": sum(1 for r in recs if r["stop"] != "cleared"),
            "improvable": sum(1 for r in recs if r["improvable"]), "resumed": count - len(seeds),
            "failed": failed, "path": str(path)}


def improvable_records(heap_dir: Path, heaps: int, seed_start: int = 0) -> list[dict]:
    """The first `heaps` improvable heaps with seed >= seed_start of heap_dir/heaps.jsonl, by seed."""
    recs = sorted((r for r in read_jsonl(Path(heap_dir) / HEAPS_FILE)
                   if r["improvable"] and int(r["seed"]) >= seed_start), key=lambda r: int(r["seed"]))
    return recs[:heaps]


def bench_row(heap_rec: dict, policy: str, result: dict, source: str, config: PushStudyConfig) -> dict:
    """One `bench push` row: the policy's gains on a heap, with the config its push ran under."""
    row = {"seed": int(heap_rec["seed"]), "policy": policy, "objects": heap_rec["objects"], "source": source,
           "config": asdict(config)}
    row.update({k: float(result.get(k, 0.0)) for k in METRICS})
    row.update(pushed=bool(result.get("pushed")), plan_ms=float(result.get("plan_ms", 0.0)),
               push=result.get("push"), before=heap_rec.get("before"), after=result.get("after"),
               left_bin=int(result.get("left_bin", 0)))
    if result.get("error"):
        row["error"] = result["error"]
    return row


def rerun_job(job: tuple) -> dict:
    """(seed, policy, PushStudyConfig dict) -> the heap's record with only `policy` run (Algorithm 1
    again from the seed: deterministic, so it reproduces the data step's state)."""
    seed, policy, params = job
    return improvable_heap(int(seed), PushStudyConfig(**params), policies=(policy,))


def policies_from_state(rec: dict, params: PushStudyConfig, policies=POLICIES) -> dict:
    """`policies` on a heap record's stored state (its poses at rest): the study without Algorithm
    1's drop and grasping. Returns {"before": metrics, "policies": {policy: run_policy's record},
    "cpu_s": all of it (world, before, pushes, after)}. The stored poses are rounded to 1 um and
    at rest, so a push from them is the data step's push up to that rounding."""
    c = time.process_time()
    params = replace(params, object_set=heap_config(rec).object_set)
    world = PushWorld(heap_from_dict(rec["heap"]), params)
    world.set_state(rec["state"])
    sets = GraspSets(params, int(rec["seed"]))
    before = state_metrics(world, sets)
    snap = world.snapshot()
    results = {p: run_policy(world, snap, before, sets, p, int(rec["seed"]), policy_params=params.policy_params())
               for p in policies}
    return {"before": {k: before[k] for k in ("D", "jaw", "suction", "overall")}, "policies": results,
            "cpu_s": time.process_time() - c}


def state_job(job: tuple) -> dict:
    """(heap record, policies, PushStudyConfig dict) -> policies_from_state (module-level for pools)."""
    rec, policies, params = job
    return policies_from_state(rec, PushStudyConfig(**params), tuple(policies))


def run_push_bench(policy: str, heaps: int, seed_start: int, out: Path, heap_dir: Path, workers: int = 1,
                   rerun: bool = False, params: PushStudyConfig = PushStudyConfig(), progress=None,
                   from_state: bool = False) -> dict:
    """Rows of `policy` on the first `heaps` improvable heaps (seed >= seed_start) of heap_dir into
    `out` (resumable). By default a row is the data step's own execution of the policy on that heap
    (push-heaps runs all five to decide improvability); rerun=True executes it again: Algorithm 1
    from the seed, or with from_state from the record's stored state (policies_from_state; the
    row's `cpu_s` is that job's CPU)."""
    check_push_policy(policy)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = read_jsonl(out)
    _rewrite_clean(out, rows)
    def params_of(h):  # a heap is re-run with its own config, but the transfer speed and the planners' switch
        c = heap_config(h)
        if not rerun:
            return c
        return replace(c, ablation=replace(c.ablation, compare_sampling="", transfer_speed=params.ablation.transfer_speed,
                                           quasi_random_checked=params.ablation.quasi_random_checked))

    def key(config):
        return json.dumps(config, sort_keys=True)

    improvable = improvable_records(heap_dir, heaps, seed_start)
    wanted = {key(asdict(params_of(h))) for h in improvable}
    done = {(int(r["seed"]), r["policy"], key(r["config"])) for r in rows if "config" in r}
    todo = [h for h in improvable if (int(h["seed"]), policy, key(asdict(params_of(h)))) not in done]

    def add(row):
        _append(out, row)
        if progress:
            progress(row)

    if rerun and from_state:
        jobs = [(h, (policy,), asdict(params_of(h))) for h in todo]
        for r in run_jobs(state_job, jobs, workers=workers):
            if r.ok:
                h = dict(r.job[0], before=r.value["before"])
                row = bench_row(h, policy, r.value["policies"][policy], "state", params_of(r.job[0]))
                row["cpu_s"] = r.value["cpu_s"]
                add(row)
    elif rerun:
        jobs = [(int(h["seed"]), policy, asdict(params_of(h))) for h in todo]
        for r in run_jobs(rerun_job, jobs, workers=workers):
            if r.ok:
                row = bench_row(r.value, policy, r.value["policies"][policy], "rerun", heap_config(r.value))
                add(row)
    else:
        for h in todo:
            row = bench_row(h, policy, h["policies"][policy], "push-heaps", heap_config(h))
            add(row)
    got = [r for r in read_jsonl(out) if r["policy"] == policy and key(r.get("config", {})) in wanted]
    return {"rows": len(got), "new": len(todo), "available": len(improvable_records(heap_dir, 10**9, seed_start))}


def summarize_push(rows: list[dict]) -> dict:
    """Per policy and metric: n, mean, standard error; per metric the one-way ANOVA across policies
    on the heaps every policy has (scipy.stats.f_oneway: F, p, degrees of freedom)."""
    by = {}
    for r in rows:
        by.setdefault(r["policy"], {})[int(r["seed"])] = r
    pols = [p for p in POLICIES if p in by]
    common = sorted(set.intersection(*(set(by[p]) for p in pols))) if pols else []
    out = {"policies": {}, "anova": {}, "heaps": len(common)}
    for p in pols:
        out["policies"][p] = {}
        for m in METRICS:
            x = np.array([by[p][s][m] for s in common], float)
            se = float(x.std(ddof=1) / np.sqrt(len(x))) if len(x) > 1 else 0.0
            out["policies"][p][m] = {"n": len(x), "mean": float(x.mean()) if len(x) else 0.0, "se": se}
        out["policies"][p]["pushed"] = float(np.mean([by[p][s]["pushed"] for s in common])) if common else 0.0
        out["policies"][p]["positive_overall"] = float(np.mean([by[p][s]["overall_gain"] > 1e-9
                                                                for s in common])) if common else 0.0
        pushed = np.array([by[p][s]["overall_gain"] for s in common if by[p][s]["pushed"]], float)
        out["policies"][p]["overall_when_pushed"] = {
            "n": len(pushed), "mean": float(pushed.mean()) if len(pushed) else 0.0,
            "se": float(pushed.std(ddof=1) / np.sqrt(len(pushed))) if len(pushed) > 1 else 0.0}
    # overall gain by the number of objects at the push (1, 2, 3, >= 4): where the policies differ
    groups = {"1": (1, 1), "2": (2, 2), "3": (3, 3), ">=4": (4, 10**6)}
    out["by_objects"] = {}
    for g, (lo, hi) in groups.items():
        seeds = [s for s in common if lo <= int(by[pols[0]][s].get("objects", 0)) <= hi]
        if seeds:
            out["by_objects"][g] = {"heaps": len(seeds), **{p: float(np.mean([by[p][s]["overall_gain"] for s in seeds]))
                                                            for p in pols}}
    if len(pols) >= 2 and len(common) >= 2:
        for m in METRICS:
            groups = [np.array([by[p][s][m] for s in common], float) for p in pols]
            if all(np.ptp(g) == 0 for g in groups) and len({float(g[0]) for g in groups}) == 1:
                out["anova"][m] = {"F": float("nan"), "p": float("nan"), "df": [len(pols) - 1, len(pols) * (len(common) - 1)]}
                continue
            F, pv = f_oneway(*groups)
            out["anova"][m] = {"F": float(F), "p": float(pv), "df": [len(pols) - 1, len(pols) * len(common) - len(pols)]}
    return out


def format_push_table(s: dict) -> str:
    lines = [f"{s['heaps']} improvable heaps, every policy on each (mean +- standard error)",
             f"{'policy':18s} " + " ".join(f"{m:>16s}" for m in METRICS) + "   pushed  overall>0"
             + "  overall when pushed"]
    for p, v in s["policies"].items():
        w = v.get("overall_when_pushed", {"n": 0, "mean": 0.0, "se": 0.0})
        lines.append(f"{p:18s} " + " ".join(f"{v[m]['mean']:+7.3f} +- {v[m]['se']:.3f}" for m in METRICS)
                     + f"   {100 * v['pushed']:5.1f} %  {100 * v['positive_overall']:5.1f} %"
                     + f"  {w['mean']:+.3f} +- {w['se']:.3f} (n = {w['n']})")
    for m, a in s["anova"].items():
        lines.append(f"ANOVA {m}: F({a['df'][0]}, {a['df'][1]}) = {a['F']:.2f}, p = {a['p']:.2g}")
    if s.get("by_objects"):
        pols = list(s["policies"])
        lines.append("mean overall gain by the objects at the push")
        lines.append(f"{'objects (heaps)':18s} " + " ".join(f"{p:>18s}" for p in pols))
        for g, v in s["by_objects"].items():
            lines.append(f"{g + ' (' + str(v['heaps']) + ')':18s} " + " ".join(f"{v[p]:+18.3f}" for p in pols))
    return "\n".join(lines)


def plot_push(s: dict, out_dir: Path) -> list[Path]:
    """Fig. 4.2 (every metric per policy) and Fig. 4.3 (jaw vs suction per policy) as PNG."""
    out_dir = figure_dir(out_dir)
    pols = list(s["policies"])
    labels = {"quasi_random": "Quasi-random", "boundary_shear": "Boundary shear", "free_space": "Free space",
              "max_clearance": "Max clearance", "cluster_diffusion": "Cluster diffusion"}
    names = {"separation_gain": "Mean object separation gain", "jaw_gain": "Parallel-jaw quality gain",
             "suction_gain": "Suction quality gain", "overall_gain": "Overall quality gain"}
    x = np.arange(len(pols))

    def bars(metrics, width: float, figsize, ylabel: str, title: str, name: str) -> Path:
        """Mean +- standard error of `metrics` per policy, side by side, into out_dir/name."""
        fig, ax = plt.subplots(figsize=figsize)
        for k, m in enumerate(metrics):
            ax.bar(x + (k - (len(metrics) - 1) / 2) * width, [s["policies"][p][m]["mean"] for p in pols], width,
                   yerr=[s["policies"][p][m]["se"] for p in pols], capsize=2, label=names[m])
        ax.set_xticks(x, [labels[p] for p in pols])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.legend(fontsize=8)
        return save_png(fig, out_dir / name)

    return [bars(METRICS, 0.8 / len(METRICS), (9, 4), "gain",
                 f"Push policies on {s['heaps']} improvable heaps (Fig. 4.2 analogue)", "push_policies_fig4_2.png"),
            bars(("jaw_gain", "suction_gain"), 0.35, (8, 4), "quality gain",
                 "Parallel jaw vs suction (Fig. 4.3 analogue)", "push_policies_fig4_3.png")]


def planning_speed(heaps: int = 20, seed_start: int = 0, objects: int = 8, repeats: int = 3) -> dict:
    """CPU ms to plan one push per policy and source (full state, depth image + ground-truth masks)
    on `heaps` dropped heaps of `objects` objects (BinHeap15): median and max over heaps of the
    best of `repeats` (the heap's scene built once per source; its building is timed apart)."""
    from_scen = _scenario("BinHeap15")
    cam = PinholeCamera.from_config(from_scen.cameras["overhead"])
    ws = Workspace.from_scenario(from_scen)
    times = {(src, p): [] for src in ("state", "image") for p in POLICIES}
    build = {"state": [], "image": []}
    found = {(src, p): 0 for src in ("state", "image") for p in POLICIES}
    for seed in range(seed_start, seed_start + heaps):
        heap = generate_heap(copy.deepcopy(from_scen), objects, seed)
        inp = heap_grasp_inputs(copy.deepcopy(from_scen), heap)
        for src in ("state", "image"):
            for p in POLICIES:
                best = np.inf
                for _ in range(repeats):
                    c0 = time.process_time()
                    scene = (state_scene(inp.objects, ws) if src == "state" else
                             image_scene(inp.depth, inp.masks, cam, ws))
                    c1 = time.process_time()
                    push = plan_policy_push(p, scene, seed=seed)
                    best = min(best, time.process_time() - c1)
                    build[src].append(c1 - c0)
                times[(src, p)].append(1000 * best)
                found[(src, p)] += push is not None
    return {"heaps": heaps, "objects": objects,
            "build_ms": {k: float(1000 * np.median(v)) for k, v in build.items()},
            "plan_ms": {f"{s}/{p}": {"median": float(np.median(v)), "max": float(np.max(v)),
                                     "found": found[(s, p)]} for (s, p), v in times.items()}}


def push_example_figure(seed: int, out: Path, params: PushStudyConfig = PushStudyConfig(), policies=POLICIES) -> dict:
    """Fig. 4.4 / 4.5 style picture of heap `seed`: Algorithm 1 replayed (deterministic), then per
    policy the overhead image before (its push drawn as an arrow, tail = the jaw's start) and after
    the push, with the overall / jaw / suction gains. An entry of `policies` is a policy name or
    (label, policy, PolicyParams) for a variant. Returns the gains by name or label."""
    policies = [(p, p, None) if isinstance(p, str) else tuple(p) for p in policies]
    matplotlib.use("Agg")
    heap, _ = study_heap(seed, params)
    world = PushWorld(heap, params, cameras=True)
    world.advance(params.settle)
    sets = GraspSets(params, seed)
    reason, before, _ = grasp_until_stuck(world, sets, seed, params)
    if reason == "cleared":
        raise ValueError(f"heap {seed} was cleared by Algorithm 1's grasps: no push state to draw")
    snap = world.snapshot()
    cam = PinholeCamera.from_config(world.scenario.cameras["overhead"])
    ws = world.workspace
    half = 0.5 * np.asarray(ws.size_xy) + 0.03
    corners = np.array([[ws.center_xy[0] + sx * half[0], ws.center_xy[1] + sy * half[1], ws.floor_z]
                        for sx, sy in ((-1, -1), (1, 1))])
    (u0, v0), (u1, v1) = cam.project(corners)[0]
    crop = (slice(int(max(min(v0, v1), 0)), int(max(v0, v1))), slice(int(max(min(u0, u1), 0)), int(max(u0, u1))))

    def rgb():
        img = world.station.GetOutputPort("overhead.rgb_image").Eval(world.context)
        return np.array(img.data)[..., :3][crop]

    fig, axes = plt.subplots(2, len(policies), figsize=(3.2 * len(policies), 5.4))
    axes = np.atleast_2d(axes).reshape(2, len(policies))
    out_gains = {}
    for k, (label, p, pp) in enumerate(policies):
        world.restore(snap)
        img0 = rgb()
        rec = run_policy(world, snap, before, sets, p, seed, policy_params=pp)
        img1 = rgb()
        out_gains[label] = {m: rec[m] for m in METRICS}
        axes[0, k].imshow(img0)
        if rec["push"] is not None:
            uv, _ = cam.project(np.array([rec["push"]["start"], rec["push"]["end"]]))
            uv = uv - [crop[1].start, crop[0].start]
            axes[0, k].annotate("", xy=uv[1], xytext=uv[0],
                                arrowprops={"color": "blue", "width": 2.0, "headwidth": 8.0})
        axes[0, k].set_title(label.replace("_", " ") + ("" if rec["pushed"] else " (no push)"), fontsize=9)
        axes[1, k].imshow(img1)
        axes[1, k].set_title(f"dQo {rec['overall_gain']:+.2f} dQj {rec['jaw_gain']:+.2f} "
                             f"dQs {rec['suction_gain']:+.2f}\ndD {rec['separation_gain']:+.2f}", fontsize=8)
        for a in axes[:, k]:
            a.axis("off")
    fig.suptitle(f"heap {seed}: {before['objects']} objects, Q*o = {before['overall']:.2f} before "
                 f"(top: planned push; bottom: after)", fontsize=10)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, out, dpi=100)
    return out_gains


def quality_noise(heap_recs: list[dict], seeds=(0, 1, 2, 3, 4), params: PushStudyConfig = PushStudyConfig()) -> dict:
    """How much Q*_o of a fixed state moves with the grasp sample alone: each record's before-push
    state (its stored poses) scored with GraspSets of several seeds. Returns per heap the values and
    overall the mean standard deviation and the share of heaps whose Q*_o differs between seeds."""
    out = []
    for rec in heap_recs:
        heap = heap_from_dict(rec["heap"])
        world = PushWorld(heap, params)
        world.set_state(rec["state"])
        q = [GraspSets(params, seed=int(rec["seed"]) * 1000 + s).qualities(world)["overall"] for s in seeds]
        out.append({"seed": int(rec["seed"]), "overall": q, "recorded": rec["before"]["overall"]})
    sd = [float(np.std(r["overall"])) for r in out]
    return {"heaps": out, "mean_sd": float(np.mean(sd)) if sd else 0.0,
            "share_varying": float(np.mean([s > 0 for s in sd])) if sd else 0.0}
