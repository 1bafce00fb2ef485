"""Bin heaps (App. C.3; Ch. 5.3-5.4): sample, drop, settle, pick the target, save as data.

Generation of heap `seed` with N objects:
1. N objects drawn uniformly (with replacement) from the object set / split;
2. a heap centre from a truncated 2D Gaussian around the bin centre (sigma 3 cm, |c| <= 6 cm),
   planar offsets per object from a truncated 2D Gaussian (sigma 8 cm) kept inside the bin,
   uniformly random orientations (`center_uniform` / `offset_uniform`: uniform draws instead);
3. the objects are dropped one by one, each released `drop_gap` (1 cm) above the top of
   whatever already lies under its footprint, or from `drop_height` above the bin floor if that
   is set and higher (objects not yet dropped wait far away, parked);
   objects whose footprints overlap no earlier waiting object fall together in one wave, a new
   wave every `wave_time` (30 ms); an object also waits while something under its footprint
   still moves faster than `landed_speed` (0.5 m/s: still falling), for at most `max_wait`
   (0.2 s). The release height is taken over objects that may still be in the air: with waves
   this frequent and no wait, the highest release of a heap reaches 1.0-1.8 m above the floor
   (impacts at 4-6 m/s; a 2 cm cylinder falling 2.7 cm per 10 ms step passes through the 3 cm
   bin floor); with the wait it is 0.4-0.6 m (seeds 0-9);
4. simulated until settled: every `check_every` (30 ms) of simulated time the largest linear
   and angular speed of an object, averaged over those 30 ms (pose change / time: robust to
   the discrete solver's step-to-step chatter, see _mean_speeds), are compared with
   `settle_linear` / `settle_angular` (timeout `max_final_time` after the last drop). An
   object whose origin passes the bin's outer walls has left the bin for good and is taken out
   of the simulation at once (parked, its joint locked): left in, such objects fall off the
   1.6 x 1.2 m support table and keep falling, and the heap does not "settle" (3 of 200
   seeds). An object below the bin
   floor (or the support) has tunnelled: the attempt stops at once;
5. objects that left the bin (taken out, or resting with their origin outside the bin's inner
   box) are dropped again, each with a new orientation and planar position from step 2's
   distributions, released on top of the heap as in step 3 and settled, for at most
   `refill_rounds` rounds; an attempt that still misses objects is rejected (with
   refill_rounds = 0 they are removed from the heap instead); a heap whose state is not finite,
   that did not settle, or in which an object tunnelled is rejected and the seed is resampled
   (attempt k uses the RNG stream (seed, k)); the reason names the object still moving;
6. the target is the object with the smallest visible / amodal mask ratio: the modal mask is
   the object's pixels in the label image of the heap, the amodal mask the object rendered
   alone (every other object moved out of view).

Drop physics: `HeapParams.engine`. The default, "bullet", simulates the drop in the Bullet
Physics Engine as the reference did (ms_drake.scenes.bullet mirrors this module's Drake drop
world: same shapes, masses, frictions, drop plan, waves and settle tests; Drake then renders
and stores the heap): ~0.5 CPU-s per 15-object heap instead of ~3 (docs/results/foundation.md,
"Heaps"). Bullet heaps are rigid-contact heaps: reloaded into a bin station (compliant
objects) they overlap less at load than Drake-dropped ones (median 1.0 vs 3.1 mm) but relax by
1-2 mm (median object) in its first 0.5 s. Cylinders get a rolling friction of 1 mm (with
0.1 mm, 3 of 200 heaps keep a cylinder rolling for 5 s); the Bullet solver stops its (at most
50) iterations once the residual is below 1e-4. `polish_time` (e.g. 0.5 s) then settles the
Bullet heap in the compliant Drake drop world: ~1.3 CPU-s per heap, and the heaps fit the
station better than Drake-dropped ones (largest displacement in 0.5 s, median of 8 heaps: 1.6
vs 7 mm). engine="drake" is the Drake drop world below (~3 CPU-s), kept because the
search benchmarks' tables were run on its heaps (SEARCH_HEAPS).

Drake drop physics (documented choices, tuned for speed without losing validity; measured on
2026-11-22, commits bfc0d31 and 190443a): objects are compliant-hydroelastic here (E =
5 MPa, see ms_drake.objects.sdf) so that resting contacts are pressure patches and the heap
really comes to rest; discrete step `time_step` = 10 ms with Drake's "similar" convex contact
approximation (less CPU than "lagged" at equal validity). The free joints carry a small
angular damping (`angular_damping`) as rolling resistance, without which a cylinder rolls
across the bin for seconds (Drake has no rolling friction). The objects are the bin stations'
objects (the scenario's friction, E and Hunt-Crossley dissipation, 5 s/m): a higher dissipation
(50-100 s/m) costs 25-35 % less CPU but makes contacts viscous, so an object not yet supported
sinks or tips at a few mm/s, under the settle thresholds, and the "settled" heap moves in the
station (paired runs of 2026-11-22, commits bfc0d31 and 190443a). Loaded into a bin station
(compliant objects, the same E) a heap keeps its poses bit for bit.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import QuaternionFloatingJoint
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from ms_drake.errors import HeapError, ScenarioError
from ms_drake.geometry import PinholeCamera, silhouette
from ms_drake.objects import get_object, get_object_set
from ms_drake.paths import make_parser
from ms_drake.scenario import Scenario
from ms_drake.scenes.bullet import BulletDropWorld
from ms_drake.station import MakeStation
from ms_drake.station.station import (
    add_cameras,
    add_environment,
    object_model_name,
    station_objects,
)
from ms_drake.types import Heap, ObjectPose

FAR_AWAY = np.array([0.0, 0.0, -50.0])  # where objects go to be out of view
TUNNELLED = "an object tunnelled through the bin floor or the support"


@dataclass
class HeapParams:
    """Knobs of heap generation (defaults as the module docstring states)."""

    time_step: float = 0.01  # s, discrete step of the Drake drop world
    contact_approximation: str = "similar"  # Drake drop world (MultibodyPlantConfig.discrete_contact_approximation)
    angular_damping: float = 1e-4  # N m s: stops a small cylinder rolling in ~0.2 s, negligible for tumbling
    settle_linear: float = 0.05  # m/s (a 1-cm cylinder rolling at 5 cm/s turns at 5 rad/s)
    settle_angular: float = 5.0  # rad/s
    check_every: float = 0.03  # s of simulated time
    drop_gap: float = 0.01  # release height above what lies under the object
    wave_time: float = 0.03  # s between two waves of drops
    landed_speed: float = 0.5  # m/s: an object waits while something under it moves faster
    max_wait: float = 0.2  # s: ... but at most this long
    min_final_time: float = 0.1
    max_final_time: float = 5.0
    center_sigma: float = 0.03
    center_max: float = 0.06
    offset_sigma: float = 0.08
    # Uniform instead of Gaussian draws (None: the Gaussians above): the heap centre uniform in
    # +-center_uniform (m, each axis), the offsets uniform in +-offset_uniform (m, each axis)
    center_uniform: float | None = None
    offset_uniform: float | None = None
    # Release height of an object's lowest point above the bin floor (m), or drop_gap above what
    # lies under it if that is higher (None: always drop_gap above what lies under it)
    drop_height: float | None = None
    max_attempts: int = 5
    split: str = "all"
    render: bool = True
    engine: str = "bullet"  # "bullet" (ms_drake.scenes.bullet, as the reference) or "drake" (compliant hydroelastic)
    bullet_time_step: float = 1.0 / 240.0
    bullet_iterations: int = 50
    bullet_rolling_friction: float = 1e-3  # m (1e-4: 3 of 200 heaps had a cylinder still rolling after 5 s)
    # pybullet.setPhysicsEngineParameter; the solver stops its iterations once the residual is
    # below 1e-4 (~0.7x the CPU of always running 50, same validity and station fit, measured)
    bullet_parameters: dict = dataclasses.field(default_factory=lambda: {"solverResidualThreshold": 1e-4})
    # engine="bullet" only: then settle the heap in the compliant Drake drop world for at most this
    # many simulated seconds (0: no polish), so that it is at rest in Drake's contact model too
    polish_time: float = 0.0
    # target_first only: an attempt counts only if the target's seen fraction from the overhead
    # camera is at most this (1: any heap; 0: the target starts fully hidden)
    max_target_seen: float = 1.0
    # target_first only: the target lies at the heap's centre (True) or at an offset drawn like the
    # other objects' (False: the reference's Section 8.3 heaps, every object offset from the centre)
    target_at_centre: bool = True
    # engine="bullet" with a polish and max_target_seen < 1: an attempt whose target is seen more than
    # max_target_seen + this after the Bullet drop is rejected before the polish (which moves
    # objects by mm to cm), saving the polish's CPU on attempts that would be rejected anyway
    # (None: no screen, every attempt is polished; the screen changes which attempt a seed keeps)
    prescreen_margin: float | None = None
    # Objects that left the bin are dropped again (a new pose from step 2's distributions, released
    # on top of the heap) for at most this many rounds; an attempt that still misses one is
    # rejected and resampled, so a heap of N objects holds N (0: objects that leave are removed)
    refill_rounds: int = 5


#: Heaps of the search benchmarks (ms_drake.experiments): the Drake drop world, whose heaps are
#: at rest in the bin stations' own contact model and on which the Drake-heap rows of
#: docs/results/ch7_bin_search.md were run (a Bullet heap relaxes by mm to cm in the station
#: before the first action).
SEARCH_HEAPS = HeapParams(engine="drake")


@dataclass
class HeapDiagnostics:
    attempts: int
    removed: list
    settle_time: float
    rejected_reasons: list
    phases: dict = dataclasses.field(default_factory=dict)  # CPU s and simulated s per phase (last attempt)
    refills: int = 0  # re-drop rounds of the last attempt
    redropped: int = 0  # objects dropped again in them


@functools.lru_cache(maxsize=4096)
def _vertices(full_name: str) -> np.ndarray:
    """Convex-hull vertices of an object's mesh (object frame), for bounding boxes."""
    v = _mesh(full_name)[0]
    return v[ConvexHull(v).vertices] if len(v) > 64 else v


@dataclass(frozen=True)
class DropItem:
    """One planned drop: orientation, planar position (environment frame) and the rotated
    object's bounding box relative to its origin."""

    R: RotationMatrix
    xy: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def sample_drop_plan(names: list[str], scenario: Scenario, rng: np.random.Generator,
                     params: HeapParams, flat_first: bool = False) -> list[DropItem]:
    """Orientation and planar position of every object (step 2); flat_first: the first object
    lies as modelled (its thinnest extent along z for a flat target), turned by a random yaw, at
    the heap's centre (the others scatter around it) unless params.target_at_centre is False."""
    size = scenario.environment.resolved_size()
    if params.center_uniform is None:
        c = np.clip(rng.normal(0.0, params.center_sigma, 2), -params.center_max, params.center_max)
    else:
        c = rng.uniform(-params.center_uniform, params.center_uniform, 2)
    plan = []
    for k, name in enumerate(names):
        q = Rotation.random(random_state=rng).as_quat()  # x, y, z, w
        R = RotationMatrix(Quaternion(q[3], q[0], q[1], q[2]))
        if flat_first and k == 0:
            R = RotationMatrix.MakeZRotation(float(rng.uniform(0.0, 2.0 * np.pi)))
        v = _vertices(name) @ R.matrix().T
        lo, hi = v.min(axis=0), v.max(axis=0)
        half = np.maximum(0.5 * size[:2] - 0.5 * (hi - lo)[:2], 0.0)
        if params.offset_uniform is None:
            offset = rng.normal(0.0, params.offset_sigma, 2)
        else:
            offset = rng.uniform(-params.offset_uniform, params.offset_uniform, 2)
        if flat_first and k == 0 and params.target_at_centre:
            offset = np.zeros(2)
        xy = np.clip(c + offset, -half, half) - 0.5 * (hi + lo)[:2]
        plan.append(DropItem(R, xy, lo, hi))
    return plan


def _parking(j: int) -> RigidTransform:
    return RigidTransform(FAR_AWAY + [3.0 * j, 100.0, 0.0])


class _DropWorld:
    """A plant with the bin, the objects and (optionally) the scenario's first camera."""

    def __init__(self, scenario: Scenario, names: list[str], params: HeapParams):
        builder = DiagramBuilder()
        # engine="drake": compliant-hydroelastic objects, as in the bin stations. With
        # engine="bullet" this plant only mirrors shapes and renders: rigid objects without
        # contact spheres and no hydroelastic meshes (cheaper to build).
        hydro = params.engine == "drake"
        cfg = MultibodyPlantConfig(time_step=params.time_step,
                                   contact_model="hydroelastic_with_fallback" if hydro else "point",
                                   discrete_contact_approximation=params.contact_approximation)
        plant, sg = AddMultibodyPlant(cfg, builder)
        sg.set_config(scenario.scene_graph_config)
        parser = make_parser(plant)
        add_environment(plant, scenario, parser, dropoffs=False)  # heaps never depend on the drop-off trays
        instances = []
        for k, full in enumerate(names):
            sdf = get_object(full).sdf(object_model_name(k, full), friction=scenario.objects.friction,
                                       compliance="compliant" if hydro else "rigid", contact_spheres=False)
            instances += parser.AddModelsFromString(sdf, "sdf")
        self.joints = []
        for k, mi in enumerate(instances):  # free joints with a little rolling resistance
            body = plant.GetBodyByName("body", mi)
            self.joints.append(plant.AddJoint(QuaternionFloatingJoint(
                f"free_{k}", plant.world_frame(), body.body_frame(), angular_damping=params.angular_damping)))
        self.left: list[int] = []  # objects taken out of the simulation because they left the bin
        plant.Finalize()
        self.sensor = None
        if params.render and scenario.cameras:
            cam = next(iter(scenario.cameras.values()))
            cam = copy.copy(cam)
            cam.rgb = False
            add_cameras(builder, [cam], plant, sg)
            self.sensor = builder.GetSubsystemByName(f"rgbd_sensor_{cam.name}")

            self.camera = PinholeCamera.from_config(cam)
        self.diagram = builder.Build()
        self.plant, self.scene_graph = plant, sg
        self.objects = station_objects(plant)
        self.bodies = [plant.get_body(o.body_index) for o in self.objects]
        self.simulator = Simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)

    def take_out(self, i: int) -> None:
        """Object i left the bin: park it far away and lock its joint (a locked body leaves the
        contact problem, and it cannot fall off the support table and keep the heap 'moving')."""
        self.plant.SetFreeBodyPose(self.plant_context, self.bodies[i], _parking(i))
        self.plant.SetFreeBodySpatialVelocity(self.plant_context, self.bodies[i], _zero_velocity())
        self.joints[i].Lock(self.plant_context)
        self.left.append(i)

    def put_back(self, i: int) -> None:
        """Object i (taken out) joins the simulation again, parked until it is dropped."""
        self.joints[i].Unlock(self.plant_context)
        self.left.remove(i)

    def set_poses(self, poses):
        for b, X in zip(self.bodies, poses):
            self.plant.SetFreeBodyPose(self.plant_context, b, X)
            self.plant.SetFreeBodySpatialVelocity(self.plant_context, b, _zero_velocity())

    def free_body_q(self, i: int) -> tuple:
        """(qw, qx, qy, qz, x, y, z) of object i, as stored in the plant."""
        q = self.plant.GetPositions(self.plant_context, self.objects[i].model_instance)
        return tuple(float(v) for v in q)

    def poses(self) -> list[RigidTransform]:
        return [self.plant.GetFreeBodyPose(self.plant_context, b) for b in self.bodies]

    # The engine interface of _drop_in_waves (shared with ms_drake.scenes.bullet.BulletDropWorld).
    def time(self) -> float:
        return self.simulator.get_context().get_time()

    def pose(self, i: int) -> RigidTransform:
        return self.plant.GetFreeBodyPose(self.plant_context, self.bodies[i])

    def set_pose(self, i: int, X: RigidTransform) -> None:
        """Object i at X with zero velocity."""
        self.plant.SetFreeBodyPose(self.plant_context, self.bodies[i], X)
        self.plant.SetFreeBodySpatialVelocity(self.plant_context, self.bodies[i], _zero_velocity())

    def park(self, i: int) -> None:
        """Object i waits far away (at rest)."""
        self.set_pose(i, _parking(i))

    def velocities(self) -> np.ndarray:
        """(N, 6): angular, linear velocity per object."""
        return self.plant.GetVelocities(self.plant_context).reshape(-1, 6)

    def advance_to(self, t: float) -> bool:
        return _advance(self.simulator, t, self.plant, self.plant_context)

    def max_speeds(self, which: list[int] | None = None) -> tuple[float, float]:
        """Largest (linear, angular) speed of the objects `which` (default: all)."""
        v = self.velocities()
        v = v[which] if which is not None else v
        return float(np.abs(v[:, 3:]).max(initial=0.0)), float(np.abs(v[:, :3]).max(initial=0.0))

    def label_image(self) -> np.ndarray:
        sc = self.sensor.GetMyContextFromRoot(self.context)
        return np.array(self.sensor.label_image_output_port().Eval(sc).data)[:, :, 0].copy()

    def depth_image(self) -> np.ndarray:
        sc = self.sensor.GetMyContextFromRoot(self.context)
        return np.array(self.sensor.depth_image_32F_output_port().Eval(sc).data)[:, :, 0].copy()


def _zero_velocity():
    return SpatialVelocity(np.zeros(3), np.zeros(3))


@functools.lru_cache(maxsize=4096)
def _mesh(full_name: str):
    m = get_object(full_name).trimesh()
    return np.asarray(m.vertices), np.asarray(m.faces)


def visible_ratios(world: _DropWorld, names: list[str], present: list[int], camera) -> tuple[np.ndarray, np.ndarray]:
    """(modal, amodal) pixel counts of the objects `present`: modal from the label image,
    amodal from the object's mesh projected through the camera (ms_drake.perception.masks)."""
    labels = world.label_image()
    poses = world.poses()
    modal, amodal = [], []
    for i in present:
        modal.append((labels == int(world.objects[i].body_index)).sum())
        v, f = _mesh(names[i])
        X = poses[i]
        amodal.append(silhouette(camera, v @ X.rotation().matrix().T + X.translation(), f).sum())
    return np.array(modal, float), np.array(amodal, float)


def _advance(sim, t: float, plant, plant_context) -> bool:
    """Advance; False when the state became non-finite or the solver gave up."""
    try:
        sim.AdvanceTo(t)
    except RuntimeError:  # SceneGraph rejects NaN poses; the contact solver may fail to converge
        return False
    return bool(np.all(np.isfinite(plant.GetPositions(plant_context))))


def _footprints_overlap(a: DropItem, b: DropItem) -> bool:
    return bool(np.all(a.xy + a.lo[:2] < b.xy + b.hi[:2]) and np.all(a.xy + a.hi[:2] > b.xy + b.lo[:2]))


def _tunnelled(rel: np.ndarray, size: np.ndarray, wall: float) -> np.ndarray:
    """Object origins (environment frame, rows) below the bin floor inside its footprint, or
    below the support table (whose top is a wall thickness under the bin floor)."""
    over_bin = np.all(np.abs(rel[:, :2]) <= 0.5 * size[:2] + 1e-3, axis=1)
    return (over_bin & (rel[:, 2] < -0.02)) | (rel[:, 2] < -wall - 0.06)


def _outside(world, n: int, origin: np.ndarray, size: np.ndarray) -> list[int]:
    """Objects taken out of the simulation or whose origin is not over the bin's inner box."""
    out = []
    for i in range(n):
        p = world.pose(i).translation() - origin
        if i in world.left or not np.all(np.abs(p[:2]) <= 0.5 * size[:2] + 1e-3):
            out.append(i)
    return out


def _take_out_leavers(world: _DropWorld, placed: list[int], origin: np.ndarray, size: np.ndarray,
                      wall: float) -> bool:
    """Objects whose origin is beyond the bin's outer walls have left it for good: take them out
    of the simulation (they are removed from the heap anyway). Returns True when an object
    tunnelled (the attempt is lost: stop at once instead of simulating its fall)."""
    for i in placed:
        if i not in world.left:
            p = world.pose(i).translation() - origin
            if _tunnelled(p[None], size, wall)[0]:
                return True
            if np.any(np.abs(p[:2]) > 0.5 * size[:2] + wall):
                world.take_out(i)
    return False


def _mean_speeds(before: list[RigidTransform], after: list[RigidTransform], dt: float,
                 skip: list[int]) -> tuple[float, float]:
    """Largest (linear, angular) speed of the objects averaged over `dt`: displacement of the
    origin and rotation angle between two poses, over dt. The final settle test uses these and
    not the instantaneous velocities: a thin object lying flat (a 4 mm cardboard backing, E
    down to 0.25 MPa) can chatter in the discrete solver, its velocity flipping sign every
    10 ms step (+-7 cm/s, +-0.8 rad/s) while its pose stays within 1 mm for seconds; that was
    a heap that "did not settle" (seeds 40 and 133 of 200)."""
    lin = ang = 0.0
    for i, (a, b) in enumerate(zip(before, after)):
        if i in skip:
            continue
        lin = max(lin, float(np.linalg.norm(b.translation() - a.translation())) / dt)
        ang = max(ang, float(a.rotation().InvertAndCompose(b.rotation()).ToAngleAxis().angle()) / dt)
    return lin, ang


def _drop_in_waves(world: _DropWorld, names: list[str], plan: list[DropItem], origin: np.ndarray,
                   size: np.ndarray, wall: float, params: HeapParams,
                   phases: dict | None = None, drop: list[int] | None = None) -> tuple[bool, float, str]:
    """Steps 3-4. Objects are dropped in drop order, each released `drop_gap` above the top of
    whatever already lies under its footprint, so impacts are slow and nothing tunnels.
    Objects whose footprints overlap no earlier object still waiting are released together
    in one "wave" (equivalent to dropping them one by one, in a fraction of the simulated
    time); objects that wait are parked far away. `phases` (if given) receives the CPU and
    simulated seconds of the waves and of the final settle. drop: the objects to drop (default all);
    the others lie where they are (a re-drop onto a heap)."""
    phases = {} if phases is None else phases
    cpu0 = time.process_time()
    t = world.time()
    waiting = list(range(len(plan))) if drop is None else list(drop)
    placed: list[int] = [i for i in range(len(plan)) if i not in waiting and i not in world.left]
    for j in waiting:
        world.park(j)
    blocked_since: dict[int, float] = {}
    while waiting:
        boxes, moving = [], []
        vel = world.velocities()
        for j in placed:
            if j in world.left:
                continue
            X = world.pose(j)
            v = _vertices(names[j]) @ X.rotation().matrix().T + (X.translation() - origin)
            boxes.append((v.min(axis=0), v.max(axis=0)))
            moving.append(bool(np.abs(vel[j, 3:]).max() > params.landed_speed))
        wave = []
        for pos, k in enumerate(waiting):
            it = plan[k]
            if any(_footprints_overlap(it, plan[j]) for j in waiting[:pos]):
                continue
            under = [m for (lo, hi), m in zip(boxes, moving)
                     if np.all(it.xy + it.lo[:2] < hi[:2]) and np.all(it.xy + it.hi[:2] > lo[:2])]
            if any(under) and t - blocked_since.setdefault(k, t) < params.max_wait:
                continue  # what lies under it is still falling: release it once that has landed
            wave.append(k)
        for k in wave:
            it = plan[k]
            top = max([hi[2] for lo, hi in boxes
                       if np.all(it.xy + it.lo[:2] < hi[:2]) and np.all(it.xy + it.hi[:2] > lo[:2])], default=0.0)
            z = max(top + params.drop_gap, params.drop_height or 0.0)  # release height of its lowest point
            p = np.array([it.xy[0], it.xy[1], z - it.lo[2]])
            phases["max_drop"] = max(phases.get("max_drop", 0.0), z)
            world.set_pose(k, RigidTransform(it.R, origin + p))
        placed += wave
        waiting = [k for k in waiting if k not in wave]
        for j in waiting:
            world.park(j)
        t_wave = t
        while t - t_wave < params.wave_time:
            t += params.check_every
            if not world.advance_to(t):
                return False, t, "the simulation blew up (non-finite state)"
            if _take_out_leavers(world, placed, origin, size, wall):
                return False, t, TUNNELLED
    t_waves = t
    phases.update(waves_cpu=time.process_time() - cpu0, waves_sim=t_waves)
    ok, t, reason = _settle(world, names, placed, origin, size, wall, params, params.max_final_time,
                            params.min_final_time, phases, "final")
    return ok, t, reason


def _settle(world, names: list[str], placed: list[int], origin: np.ndarray, size: np.ndarray, wall: float,
            params: HeapParams, max_time: float, min_time: float, phases: dict, phase: str) -> tuple[bool, float, str]:
    """Simulate until the speeds averaged over each `check_every` are below the settle
    thresholds (at least `min_time`, at most `max_time`); phases[phase + '_cpu' / '_sim']."""
    cpu1 = time.process_time()
    t = t0 = world.time()
    t_end, t_min = t + max_time, t + min_time

    def done(ok, reason=""):
        phases.update({f"{phase}_cpu": time.process_time() - cpu1, f"{phase}_sim": t - t0})
        return ok, t, reason

    before = world.poses()
    while t < t_end:
        t += params.check_every
        if not world.advance_to(t):
            return done(False, "the simulation blew up (non-finite state)")
        if _take_out_leavers(world, placed, origin, size, wall):
            return done(False, TUNNELLED)
        now = world.poses()
        lin, ang = _mean_speeds(before, now, params.check_every, world.left)
        before = now
        if t >= t_min and lin < params.settle_linear and ang < params.settle_angular:
            return done(True)
    v = world.velocities()
    k = int(np.argmax(np.maximum(np.abs(v[:, 3:]).max(axis=1) / params.settle_linear,
                                 np.abs(v[:, :3]).max(axis=1) / params.settle_angular)))
    return done(False, f"did not settle within {max_time} s ({phase}; {names[k]} still "
                       f"moving at {np.abs(v[k, 3:]).max():.3f} m/s, {np.abs(v[k, :3]).max():.2f} rad/s)")


def _target_seen(world, names, origin, size) -> float:
    """Seen fraction from the overhead camera of object 0 (the target), 1 if it is not over the bin."""
    rel = world.poses()[0].translation() - origin
    if 0 in world.left or np.any(np.abs(rel[:2]) > 0.5 * size[:2]):
        return 1.0
    modal, amodal = visible_ratios(world, names, [0], world.camera)
    return float(min(modal[0] / amodal[0], 1.0)) if amodal[0] > 0 else 1.0


def generate_heap(scenario: Scenario, num_objects: int, seed: int, object_set: str | None = None,
                  params: HeapParams | None = None, return_diagnostics: bool = False, names_fn=None,
                  target_first: bool = False):
    """Generate heap `seed` of `num_objects` objects into the scenario's bin (see module doc).
    names_fn(rng) -> full names: draws the objects instead of step 1 (in drop order);
    target_first: the first object dropped is the target (instead of step 6's choice), lying flat
    as modelled with a random yaw at the heap's centre, and an attempt in which it leaves the bin
    is rejected."""
    params = params or HeapParams()
    if params.engine not in ("drake", "bullet"):
        raise HeapError(f"HeapParams.engine={params.engine!r}: use 'drake' or 'bullet'")
    if scenario.environment.type != "bin":
        raise ScenarioError(f"heaps need a bin environment; scenario has environment.type="
                            f"{scenario.environment.type!r}")
    if num_objects < 1:
        raise HeapError(f"num_objects={num_objects}: a heap needs at least 1 object")
    set_name = object_set or scenario.objects.set
    oset = get_object_set(set_name)
    pool = oset.split(params.split)
    size = scenario.environment.resolved_size()
    mean_footprint = np.mean([o.extents[0] * o.extents[1] for o in pool]) if pool else 1.0
    # Generous bound: a heap may be several layers deep, but not deeper than 4x the wall height.
    capacity = int(4 * size[0] * size[1] / max(mean_footprint, 1e-6) * max(1.0, size[2] / 0.05))
    if num_objects > capacity:
        raise HeapError(f"{num_objects} objects of set {set_name!r} do not fit a {size[0]:.2f} x {size[1]:.2f} m "
                        f"bin (at most ~{capacity}); use fewer objects or a larger environment.size")
    t0 = time.perf_counter()
    reasons = []
    origin = np.asarray(scenario.environment.position, float)
    for attempt in range(params.max_attempts):
        rng = np.random.default_rng([seed, attempt])
        names = (list(names_fn(rng)) if names_fn is not None else
                 [o.full_name for o in oset.sample(num_objects, rng, params.split)])
        polish = params.engine == "bullet" and params.polish_time > 0
        world = _DropWorld(scenario, names, dataclasses.replace(params, engine="drake") if polish else params)
        plan = sample_drop_plan(names, scenario, rng, params, flat_first=target_first)
        phases = {}
        wall = scenario.environment.wall_thickness
        if params.engine == "bullet":
            engine = BulletDropWorld(world, params.bullet_time_step, params.bullet_iterations,
                                     params.bullet_rolling_friction, params.bullet_parameters)
        else:
            engine = world
        ok, settle_t, reason = _drop_in_waves(engine, names, plan, origin, size, wall, params, phases)
        refills = redropped = 0
        while ok and refills < params.refill_rounds:
            out = _outside(engine, len(names), origin, size)
            if target_first and 0 in out:
                break  # the flat target is not dropped again: the attempt is rejected below
            if not out:
                break
            refills, redropped = refills + 1, redropped + len(out)
            for i in out:
                if i not in engine.left:
                    engine.take_out(i)
                engine.put_back(i)
            for i, it in zip(out, sample_drop_plan([names[i] for i in out], scenario, rng, params)):
                plan[i] = it
            ok, settle_t, reason = _drop_in_waves(engine, names, plan, origin, size, wall, params, phases, drop=out)
        if ok and params.refill_rounds > 0 and _outside(engine, len(names), origin, size):
            ok, reason = False, f"objects still outside the bin after {refills} re-drop rounds"
        if engine is not world:  # the settled poses into the Drake world (rendering, saving)
            for i in range(len(names)):
                if i in engine.left:
                    world.take_out(i)
                else:
                    world.set_pose(i, engine.pose(i))
            engine.close()
            if (ok and polish and target_first and params.prescreen_margin is not None and params.max_target_seen < 1.0
                    and world.sensor is not None):
                seen = _target_seen(world, names, origin, size)
                if seen > params.max_target_seen + params.prescreen_margin:
                    reasons.append(f"attempt {attempt}: the target is {100 * seen:.0f} % seen after the drop, before "
                                   f"the polish (HeapParams.max_target_seen={params.max_target_seen}, "
                                   f"prescreen_margin={params.prescreen_margin})")
                    continue
            if ok and polish:  # best effort: the heap stands as Bullet left it if it has not settled
                ok, _, reason = _settle(world, names, list(range(len(names))), origin, size, wall, params,
                                        params.polish_time, params.min_final_time, phases, "polish")
                ok = ok or not reason.startswith(("the simulation blew up", TUNNELLED))
        poses = world.poses()
        rel = np.array([X.translation() - origin for X in poses])
        left = np.isin(np.arange(len(names)), world.left)
        rel[left] = 0.5 * size + 1.0  # taken out of the simulation: outside the bin, not tunnelled
        over_bin = np.all(np.abs(rel[:, :2]) <= 0.5 * size[:2] + 1e-3, axis=1)
        if ok and np.any(_tunnelled(rel, size, wall)):
            ok, reason = False, TUNNELLED
        if not ok:
            reasons.append(f"attempt {attempt}: {reason}")
            continue
        inside = over_bin & (rel[:, 2] < size[2] + 0.5)
        present = [i for i in range(len(names)) if inside[i]]
        removed = [names[i] for i in range(len(names)) if not inside[i]]
        if not present:
            reasons.append(f"attempt {attempt}: every object left the bin")
            continue
        if target_first and 0 not in present:
            reasons.append(f"attempt {attempt}: the target ({names[0]}, dropped first) left the bin")
            continue
        ratios = np.ones(len(present))
        target_k = -1
        if world.sensor is not None:
            modal, amodal = visible_ratios(world, names, present, world.camera)
            ratios = np.where(amodal > 0, np.minimum(modal / np.maximum(amodal, 1), 1.0), 1.0)
            target_k = int(np.argmin(ratios))
        if target_first:
            target_k = present.index(0)
            if ratios[target_k] > params.max_target_seen:
                reasons.append(f"attempt {attempt}: the target is {100 * ratios[target_k]:.0f} % seen "
                               f"(HeapParams.max_target_seen={params.max_target_seen})")
                continue
        objects = tuple(ObjectPose(names[i], world.free_body_q(i)) for i in present)
        heap = Heap(seed=seed, environment="bin", objects=objects,
                    target=objects[target_k].name if target_k >= 0 else "", target_index=target_k,
                    visible_ratios=tuple(float(r) for r in ratios), seconds=time.perf_counter() - t0)
        if return_diagnostics:
            return heap, HeapDiagnostics(attempt + 1, removed, settle_t, reasons, phases, refills, redropped)
        return heap
    raise HeapError(f"heap seed {seed}: no valid heap in {params.max_attempts} attempts ({'; '.join(reasons)})")


# ---------------------------------------------------------------------------------------------
# Heaps as data


def heap_to_dict(heap: Heap) -> dict:
    d = dataclasses.asdict(heap)
    d["objects"] = [{"name": o.name, "q": list(o.q)} for o in heap.objects]
    return d


def heap_from_dict(d: dict) -> Heap:
    objs = tuple(ObjectPose(o["name"], tuple(float(v) for v in o["q"])) for o in d["objects"])
    return Heap(seed=int(d["seed"]), environment=d.get("environment", "bin"), objects=objs,
                target=d.get("target", ""), target_index=int(d.get("target_index", -1)),
                visible_ratios=tuple(d.get("visible_ratios", ())), seconds=float(d.get("seconds", 0.0)))


def heap_digest(heap: Heap) -> str:
    """A short fingerprint of the heap's state: its object names and poses (to 1e-9). Two heaps
    with the same digest start every search from the same state, so a benchmark record keeps it
    (`heap_digest`) and paired comparisons check that both records searched the same heap."""
    text = "|".join(f"{o.name}:" + ",".join(f"{v:.9f}" for v in o.q) for o in heap.objects)
    return hashlib.sha256(f"{heap.environment}|{text}".encode()).hexdigest()[:16]


def save_heap(heap: Heap, path) -> None:
    Path(path).write_text(json.dumps(heap_to_dict(heap)))


def load_heap(path) -> Heap:
    return heap_from_dict(json.loads(Path(path).read_text()))


def scenario_with_heap(scenario: Scenario, heap: Heap) -> Scenario:
    """A copy of `scenario` whose objects are exactly the heap's objects (in order)."""
    s = copy.deepcopy(scenario)
    s.objects.names = heap.object_names()
    s.objects.count = len(heap.objects)
    return s


def set_heap_poses(station, context, heap: Heap) -> None:
    """Put the heap's objects at their saved poses (zero velocity) in a station context made
    from `scenario_with_heap(...)`; fixtures (welded by the station) stay where they are."""
    plant = station.GetSubsystemByName("plant")
    pc = plant.GetMyMutableContextFromRoot(context)
    objs = station_objects(plant)
    if [o.full_name for o in objs] != heap.object_names():
        raise HeapError("the station's objects differ from the heap's; build it from scenario_with_heap(scenario, heap)")
    for o, op in zip(objs, heap.objects):
        if plant.num_positions(o.model_instance) == 0:  # a fixture, welded where the station put it
            continue
        plant.SetPositions(pc, o.model_instance, np.asarray(op.q))
        plant.SetVelocities(pc, o.model_instance, np.zeros(6))


def station_check(scenario: Scenario, heap: Heap, seconds: float = 0.5) -> dict:
    """How a heap behaves in a station's own physics: build `scenario_with_heap(scenario, heap)`
    (cameras off), load the heap, and report the deepest penetration between any two geometries
    at load (m), and the largest / median displacement of an object's origin after `seconds` of
    simulation (m)."""

    s = scenario_with_heap(scenario, heap)
    s.cameras = {}
    station = MakeStation(s)
    sim = Simulator(station)
    ctx = sim.get_mutable_context()
    set_heap_poses(station, ctx, heap)
    plant = station.GetSubsystemByName("plant")
    pc = plant.GetMyContextFromRoot(ctx)
    query = station.GetOutputPort("query_object").Eval(ctx)
    pen = max([p.depth for p in query.ComputePointPairPenetration()], default=0.0)
    bodies = [plant.get_body(o.body_index) for o in station_objects(plant)]
    p0 = [plant.EvalBodyPoseInWorld(pc, b).translation().copy() for b in bodies]
    sim.AdvanceTo(seconds)
    moved = [float(np.linalg.norm(plant.EvalBodyPoseInWorld(pc, b).translation() - p)) for b, p in zip(bodies, p0)]
    return {"max_penetration": float(pen), "max_displacement": max(moved, default=0.0),
            "median_displacement": float(np.median(moved)) if moved else 0.0, "displacements": moved}
