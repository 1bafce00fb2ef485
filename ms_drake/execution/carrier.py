"""ObjectCarrier: the primitive mode's hand that takes a removed object out of the bin, in physics.

The primitive mode decides a grasp's outcome with the contact models (execution.PrimitiveBackend);
the object it lifts must then leave the scene. The carrier does that inside the Diagram, as the
robot does in full fidelity: it carries each newly removed object straight up above the bin's
walls, across to the nearer drop-off tray (station.environments.dropoff_points) and releases it
there, out of the overhead camera's view (the next action waits until the object has left the
view, not for the release). The carrying is an external force on the object's body
(the plant's `applied_spatial_force` input): a critically damped spring-damper on the object's
centre of mass towards a point moving along that path, with gravity compensated and its spin
damped, so the object moves as if held, and whatever rests on it slides off as from a real lift.

Ports (declared first):
  inputs
    removed                  tuple[str] of object ids (the ActionExecutor's `removed`)
    body_poses               list[RigidTransform] by body index (the station's)
    body_spatial_velocities  list[SpatialVelocity] by body index (the station's)
  outputs
    applied_spatial_force    list[ExternallyAppliedSpatialForce] -> the station's input of that name
    carrying                 1-vector: 1 while a carried object is still in the camera's view (or
                             not yet picked up) (-> ActionExecutor.carrying, which chooses no action
                             until the scene is clear); without a camera, until its release

State: each carry's start time and start point, latched by a periodic update (`period`); a removed
id not yet latched counts as carrying. Everything follows from the state, the time and the poses,
so a rollout stays reproducible.
"""

from __future__ import annotations

import copy

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialForce, SpatialVelocity
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import BasicVector, LeafSystem

from ms_drake.errors import MsDrakeError

GRAVITY = 9.81


class CarrierError(MsDrakeError, ValueError):
    """An ObjectCarrier was built without somewhere to carry objects to, or with bad gains."""


def _smooth(s: float) -> tuple[float, float]:
    """Cosine profile on [0, 1]: position fraction and its derivative w.r.t. s."""
    s = min(max(s, 0.0), 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * s), 0.5 * np.pi * np.sin(np.pi * s)


class _Path:
    """Waypoints joined by smooth legs at `speed` (each at least `min_leg` s)."""

    def __init__(self, points, speeds, min_leg: float = 0.1):
        self.points = [np.asarray(p, float) for p in points]
        legs = [max(float(np.linalg.norm(b - a)) / v, min_leg) for a, b, v in zip(self.points, self.points[1:], speeds)]
        self.t = np.concatenate([[0.0], np.cumsum(legs)])

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Point and velocity at time t from the start."""
        if t >= self.t[-1]:
            return self.points[-1], np.zeros(3)
        k = max(int(np.searchsorted(self.t, t, side="right") - 1), 0)
        T = self.t[k + 1] - self.t[k]
        f, df = _smooth((t - self.t[k]) / T)
        a, b = self.points[k], self.points[k + 1]
        return a + f * (b - a), (b - a) * df / T


class ObjectCarrier(LeafSystem):
    """plant: the station's (finalized) MultibodyPlant, for the objects' masses and inertias;
    objects: {object id: body index}; dropoffs: world points on the trays' floors (the nearer in
    y takes an object); travel_z: the carrying height (above the bin's walls and the objects on
    them); release_height: how far above a tray's floor the object is let go [m]. camera: the
    PinholeCamera whose view a carried object must leave before the next action (radii: object
    id -> bounding radius [m], default 0.15). lift_speed [m/s] up out of the bin and down into the
    tray, speed [m/s] across; omega [rad/s] (the spring's natural frequency; damping ratio 1), spin_damping
    [1/s], max_accel [m/s^2] (the force's bound besides gravity), period [s] (latching rate),
    hold [s] (time held still above the tray before the release)."""

    def __init__(self, plant, objects: dict, dropoffs, travel_z: float, release_height: float = 0.12,
                 camera=None, radii: dict | None = None, lift_speed: float = 1.0, speed: float = 2.0,
                 omega: float = 25.0, spin_damping: float = 20.0, max_accel: float = 80.0,
                 period: float = 0.05, hold: float = 0.1):
        super().__init__()
        if not dropoffs:
            raise CarrierError("ObjectCarrier needs at least one drop-off point (a bin environment's trays: "
                               "station.environments.dropoff_points(scenario.environment))")
        if min(omega, speed, lift_speed, period) <= 0:
            raise CarrierError(f"speeds, omega and period must be > 0 (got {lift_speed}, {speed}, {omega}, {period})")
        self.camera = camera
        self.radii = {str(k): float(v) for k, v in (radii or {}).items()}
        self.lift_speed = float(lift_speed)
        self.objects = {str(k): int(v) for k, v in objects.items()}
        self.dropoffs = [np.asarray(p, float) for p in dropoffs]
        self.travel_z, self.release_height = float(travel_z), float(release_height)
        self.speed, self.omega, self.spin_damping = float(speed), float(omega), float(spin_damping)
        self.max_accel, self.period, self.hold = float(max_accel), float(period), float(hold)
        ctx = plant.CreateDefaultContext()
        self._inertia = {}  # body index -> (mass, com in B, rotational inertia about the com in B)
        for b in self.objects.values():
            body = plant.get_body(BodyIndex(b))
            M = body.CalcSpatialInertiaInBodyFrame(ctx)
            com = np.asarray(M.get_com())
            I_cm = M.Shift(com).CalcRotationalInertia().CopyToFullMatrix3()
            self._inertia[b] = (float(M.get_mass()), com, I_cm)
        # Ports first.
        self.removed_port = self.DeclareAbstractInputPort("removed", AbstractValue.Make(()))
        self.poses_port = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self.velocities_port = self.DeclareAbstractInputPort("body_spatial_velocities",
                                                             AbstractValue.Make([SpatialVelocity()]))
        self._carries = self.DeclareAbstractState(AbstractValue.Make({}))
        self.DeclareAbstractOutputPort("applied_spatial_force",
                                       lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]), self._calc_forces)
        self.DeclareVectorOutputPort("carrying", BasicVector(1), self._calc_carrying)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self._latch)

    # ------------------------------------------------------------------ the path of one carry
    def path(self, start) -> _Path:
        """The carry from `start` (world point): up, across to the nearer tray, down to the release."""
        p0 = np.asarray(start, float)
        tray = min(self.dropoffs, key=lambda d: (abs(d[1] - p0[1]), -d[1]))
        z = max(self.travel_z, p0[2])
        release = np.array([tray[0], tray[1], tray[2] + self.release_height])
        return _Path([p0, [p0[0], p0[1], z], [tray[0], tray[1], z], release],
                     [self.lift_speed, self.speed, self.lift_speed])

    def release_time(self, start) -> float:
        """Time from the start of a carry to its release [s]."""
        return self.path(start).duration + self.hold

    # ------------------------------------------------------------------ update / outputs
    def _com(self, b: int, poses) -> np.ndarray:
        return poses[b].multiply(self._inertia[b][1])

    def _latch(self, context, state):
        carries = context.get_abstract_state(self._carries).get_value()
        removed = self.removed_port.Eval(context) if self.removed_port.HasValue(context) else ()
        new = [r for r in removed if r in self.objects and r not in carries]
        if not new:
            return
        poses = self.poses_port.Eval(context)
        carries = copy.copy(carries)
        for r in new:
            p0 = self._com(self.objects[r], poses)
            carries[r] = (float(context.get_time()), tuple(float(v) for v in p0))
        state.get_mutable_abstract_state(self._carries).set_value(carries)

    def in_view(self, oid: str, poses) -> bool:
        """Whether object `oid` (its centre of mass and bounding radius) may be in the camera's
        image (always True without a camera)."""
        if self.camera is None:
            return True
        c = self.camera
        uv, z = c.project(self._com(self.objects[oid], poses)[None, :])
        if z[0] <= 1e-6:
            return False
        m = max(c.fx, c.fy) * self.radii.get(oid, 0.15) / z[0]
        return bool(-m <= uv[0, 0] <= c.width + m and -m <= uv[0, 1] <= c.height + m)

    def _calc_carrying(self, context, output):
        carries = context.get_abstract_state(self._carries).get_value()
        removed = self.removed_port.Eval(context) if self.removed_port.HasValue(context) else ()
        t = context.get_time()
        busy = any(r in self.objects and r not in carries for r in removed)
        if not busy:
            on_way = [oid for oid, (t0, p0) in carries.items() if t < t0 + self.release_time(p0)]
            if on_way:
                poses = self.poses_port.Eval(context)
                busy = any(self.in_view(oid, poses) for oid in on_way)
        output.SetAtIndex(0, 1.0 if busy else 0.0)

    def _calc_forces(self, context, output):
        carries = context.get_abstract_state(self._carries).get_value()
        t = context.get_time()
        forces = []
        if carries:
            poses = self.poses_port.Eval(context)
            vels = self.velocities_port.Eval(context)
        for oid, (t0, p0) in carries.items():
            if t >= t0 + self.release_time(p0):
                continue  # released
            b = self.objects[oid]
            m, com_B, I_B = self._inertia[b]
            X = poses[b]
            R = X.rotation().matrix()
            V = vels[b]
            w = np.asarray(V.rotational())
            p = X.multiply(com_B)
            v = np.asarray(V.translational()) + np.cross(w, R @ com_B)
            p_d, v_d = self.path(p0)(t - t0)
            a = self.omega ** 2 * (p_d - p) + 2.0 * self.omega * (v_d - v)
            n = np.linalg.norm(a)
            if n > self.max_accel:
                a *= self.max_accel / n
            f = m * (a + np.array([0.0, 0.0, GRAVITY]))
            tau = -self.spin_damping * (R @ I_B @ R.T) @ w
            F = ExternallyAppliedSpatialForce()
            F.body_index = BodyIndex(b)
            F.p_BoBq_B = com_B
            F.F_Bq_W = SpatialForce(tau, f)
            forces.append(F)
        output.set_value(forces)


__all__ = ["CarrierError", "ObjectCarrier"]
