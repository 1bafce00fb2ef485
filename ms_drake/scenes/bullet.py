"""A Bullet (pybullet) mirror of a Drake drop world, for fast heap generation.

The reference generated its heaps with the Bullet Physics Engine (App. C.3, line 1987; Ch. 5,
line 861): objects dropped one by one and simulated until all velocities vanish. Drake's
compliant-hydroelastic drop world (ms_drake.scenes.heaps) does the same but costs ~2 CPU-s per
simulated second for a 15-object heap (the SAP solve of ~470 contact polygons); Bullet's
rigid-body solver with persistent contact manifolds costs a few CPU-ms for the same heap.

`BulletDropWorld` is built from the *Drake* plant of a `_DropWorld`: every proximity geometry
of the plant (box, cylinder, sphere, capsule; meshes as their convex hulls) becomes a Bullet
collision shape, in the same place, with the Drake body's mass and inertia (Bullet's body frame
is the principal frame at the centre of mass, so the Drake body pose is X_WB = X_WC X_CB) and
the geometry's Coulomb friction (Bullet multiplies the two frictions of a pair, Drake takes
2 mu1 mu2 / (mu1 + mu2): each shape gets sqrt(mu), exact when both sides share mu, as the
scenarios' objects and bin do). Anything not attached to an object body is static. So the
objects, bin, support table and their dimensions have one source: the Drake models.

Bodies are created when released and removed when they leave the bin (`take_out`); objects
that wait are not in the Bullet world at all. The interface is the one `_drop_in_waves` uses
(pose, set_pose, park, velocities, max_speeds, advance_to, take_out, put_back, left), so both engines run
the same drop plan, waves and settle tests.

Choices where the reference is silent (measured on 2026-11-22, commit d4dc7e0; the heaps' figures:
docs/results/foundation.md):
time step 1/240 s (Bullet's default), 50 solver iterations, restitution 0, a small rolling and
spinning friction (`rolling_friction` m) in place of the Drake world's angular damping so that
cylinders stop rolling, and Bullet's sleeping disabled (the settle test decides rest).
"""

from __future__ import annotations

import contextlib
import os

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.geometry import Box, Capsule, Cylinder, Role, Sphere
from pydrake.math import RigidTransform, RotationMatrix

from ms_drake.geometry import as_rigid_transform


@contextlib.contextmanager
def _stderr_silenced():
    """Silence file descriptor 2 (pybullet's C code prints its build time there on import)."""
    saved, null = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(null)


with _stderr_silenced():
    import pybullet as pb

_PARK = np.array([0.0, 0.0, -50.0])


def _quat_xyzw(R: RotationMatrix) -> list[float]:
    q = R.ToQuaternion()
    return [q.x(), q.y(), q.z(), q.w()]


def _rotation(q_xyzw) -> RotationMatrix:
    x, y, z, w = q_xyzw
    return RotationMatrix(Quaternion(w, x, y, z))


class BulletDropWorld:
    """Bullet world mirroring `world` (a ms_drake.scenes.heaps._DropWorld); see module doc."""

    def __init__(self, world, time_step: float = 1.0 / 240.0, solver_iterations: int = 50,
                 rolling_friction: float = 1e-3, engine_parameters: dict | None = None):
        self.pb = pb
        self.cid = pb.connect(pb.DIRECT)
        c = dict(physicsClientId=self.cid)
        pb.setGravity(0.0, 0.0, -9.81, **c)
        pb.setPhysicsEngineParameter(fixedTimeStep=time_step, numSolverIterations=solver_iterations,
                                     numSubSteps=0, **(engine_parameters or {}), **c)
        self.time_step = time_step
        self.rolling = rolling_friction
        self.t = 0.0
        self.steps = 0
        plant = world.plant
        inspector = world.scene_graph.model_inspector()
        query = plant.get_geometry_query_input_port().Eval(world.plant_context)
        object_frames = {plant.GetBodyFrameIdOrThrow(b.index()): i for i, b in enumerate(world.bodies)}
        self._shapes: list[tuple | None] = [None] * len(world.bodies)  # per object: (shape id, X_BC, mass, I)
        parts: list[list] = [[] for _ in world.bodies]
        static = []
        for gid in inspector.GetAllGeometryIds(Role.kProximity):
            frame = inspector.GetFrameId(gid)
            if frame in object_frames:
                parts[object_frames[frame]].append((inspector.GetShape(gid), inspector.GetPoseInFrame(gid), gid))
            else:
                static.append((inspector.GetShape(gid), query.GetPoseInWorld(gid), gid))
        for shape, X_WG, gid in static:
            col = self._shape(shape, RigidTransform(), inspector, gid)
            body = pb.createMultiBody(0.0, col, -1, list(X_WG.translation()), _quat_xyzw(X_WG.rotation()), **c)
            pb.changeDynamics(body, -1, lateralFriction=self._mu(inspector, gid), restitution=0.0, **c)
        for i, body in enumerate(world.bodies):
            M = body.default_spatial_inertia()
            mass = float(M.get_mass())
            com = np.asarray(M.get_com())
            I_com = M.Shift(com).CalcRotationalInertia().CopyToFullMatrix3()
            moments, axes = np.linalg.eigh(I_com)
            if np.linalg.det(axes) < 0:
                axes[:, 0] *= -1
            X_BC = RigidTransform(RotationMatrix(axes), com)
            X_CB = X_BC.inverse()
            if not parts[i]:
                raise ValueError(f"object {i} ({body.name()}) has no proximity geometry")
            mus = [self._mu(inspector, gid) for *_, gid in parts[i]]
            self._shapes[i] = (self._compound([(s, X_CB @ X_BG) for s, X_BG, _ in parts[i]], inspector,
                                              [g for *_, g in parts[i]]),
                               X_BC, mass, np.maximum(moments, 1e-9), float(np.mean(mus)))
        self.n = len(world.bodies)
        self._body = [None] * self.n  # Bullet body ids of released objects
        self.left: list[int] = []

    # -- construction helpers ---------------------------------------------------------------
    @staticmethod
    def _mu(inspector, gid) -> float:
        props = inspector.GetProximityProperties(gid)
        if props is not None and props.HasProperty("material", "coulomb_friction"):
            return float(np.sqrt(props.GetProperty("material", "coulomb_friction").dynamic_friction()))
        return float(np.sqrt(0.5))

    def _shape(self, shape, X, inspector, gid) -> int:
        return self._compound([(shape, X)], inspector, [gid])

    def _compound(self, items, inspector, gids) -> int:
        pb, c = self.pb, dict(physicsClientId=self.cid)
        if len(items) == 1:
            shape, X = items[0]
            return pb.createCollisionShape(**self._kwargs(shape), collisionFramePosition=list(X.translation()),
                                           collisionFrameOrientation=_quat_xyzw(X.rotation()), **c)
        kw = [self._kwargs(s, as_file=True) for s, _ in items]
        if any("vertices" in k for k in kw):
            raise ValueError("BulletDropWorld: a body with several geometries of which one is a mesh that is not "
                             "an .obj file; use engine='drake' for this object set")
        return pb.createCollisionShapeArray(
            shapeTypes=[k["shapeType"] for k in kw], radii=[k.get("radius", 0.0) for k in kw],
            halfExtents=[k.get("halfExtents", [0.0] * 3) for k in kw], lengths=[k.get("height", 0.0) for k in kw],
            fileNames=[k.get("fileName", "") for k in kw], meshScales=[k.get("meshScale", [1.0] * 3) for k in kw],
            collisionFramePositions=[list(X.translation()) for _, X in items],
            collisionFrameOrientations=[_quat_xyzw(X.rotation()) for _, X in items], **c)

    def _kwargs(self, shape, as_file: bool = False) -> dict:
        pb = self.pb
        if isinstance(shape, Box):
            return dict(shapeType=pb.GEOM_BOX, halfExtents=[shape.width() / 2, shape.depth() / 2, shape.height() / 2])
        if isinstance(shape, Cylinder):
            return dict(shapeType=pb.GEOM_CYLINDER, radius=shape.radius(), height=shape.length())
        if isinstance(shape, Sphere):
            return dict(shapeType=pb.GEOM_SPHERE, radius=shape.radius())
        if isinstance(shape, Capsule):
            return dict(shapeType=pb.GEOM_CAPSULE, radius=shape.radius(), height=shape.length())
        if hasattr(shape, "GetConvexHull"):  # Mesh / Convex: Bullet takes the convex hull of the vertices
            src = shape.source()
            if as_file and src.is_path() and str(src.path()).lower().endswith(".obj"):
                return dict(shapeType=pb.GEOM_MESH, fileName=str(src.path()), meshScale=list(shape.scale3()))
            hull = shape.GetConvexHull()
            v = np.array([hull.vertex(k) for k in range(hull.num_vertices())])
            return dict(shapeType=pb.GEOM_MESH, vertices=v.tolist())
        raise ValueError(f"BulletDropWorld: Drake shape {type(shape).__name__} has no Bullet counterpart; "
                         "use engine='drake'")

    # -- the interface of _drop_in_waves -----------------------------------------------------
    def time(self) -> float:
        return self.t

    def set_pose(self, i: int, X_WB: RigidTransform) -> None:
        """Release object i at X_WB (RigidTransform or 4x4 array) with zero velocity (creating its
        Bullet body)."""
        X_WB = as_rigid_transform(X_WB, "X_WB")
        pb, c = self.pb, dict(physicsClientId=self.cid)
        col, X_BC, mass, moments, mu = self._shapes[i]
        X_WC = X_WB @ X_BC
        if self._body[i] is None:
            self._body[i] = pb.createMultiBody(mass, col, -1, list(X_WC.translation()), _quat_xyzw(X_WC.rotation()),
                                               useMaximalCoordinates=True, **c)
            pb.changeDynamics(self._body[i], -1, mass=mass, localInertiaDiagonal=list(moments), lateralFriction=mu, restitution=0.0,
                              rollingFriction=self.rolling, spinningFriction=self.rolling,
                              activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING, **c)
        else:
            pb.resetBasePositionAndOrientation(self._body[i], list(X_WC.translation()), _quat_xyzw(X_WC.rotation()), **c)
        pb.resetBaseVelocity(self._body[i], [0.0] * 3, [0.0] * 3, **c)

    def park(self, i: int) -> None:
        """Object i waits: it is not in the Bullet world."""
        if self._body[i] is not None:
            self.pb.removeBody(self._body[i], physicsClientId=self.cid)
            self._body[i] = None

    def take_out(self, i: int) -> None:
        self.park(i)
        self.left.append(i)

    def put_back(self, i: int) -> None:
        """Object i (taken out) may be dropped again (set_pose creates its body)."""
        self.left.remove(i)

    def pose(self, i: int) -> RigidTransform:
        """X_WB of object i (a parked object: far below the world)."""
        if self._body[i] is None:
            return RigidTransform(_PARK + [3.0 * i, 100.0, 0.0])
        p, q = self.pb.getBasePositionAndOrientation(self._body[i], physicsClientId=self.cid)
        return RigidTransform(_rotation(q), np.asarray(p)) @ self._shapes[i][1].inverse()

    def poses(self) -> list[RigidTransform]:
        return [self.pose(i) for i in range(self.n)]

    def velocities(self) -> np.ndarray:
        """(N, 6): angular, linear velocity (of the centre of mass) per object; 0 when parked."""
        v = np.zeros((self.n, 6))
        for i, b in enumerate(self._body):
            if b is not None:
                lin, ang = self.pb.getBaseVelocity(b, physicsClientId=self.cid)
                v[i, :3], v[i, 3:] = ang, lin
        return v

    def max_speeds(self, which: list[int] | None = None) -> tuple[float, float]:
        v = self.velocities()
        v = v[which] if which is not None else v
        return float(np.abs(v[:, 3:]).max(initial=0.0)), float(np.abs(v[:, :3]).max(initial=0.0))

    def advance_to(self, t: float) -> bool:
        target = int(round(t / self.time_step))  # whole steps since the start: no drift
        for _ in range(target - self.steps):
            self.pb.stepSimulation(physicsClientId=self.cid)
        self.steps = max(self.steps, target)
        self.t = t
        return all(np.all(np.isfinite(self.pb.getBasePositionAndOrientation(b, physicsClientId=self.cid)[0]))
                   for b in self._body if b is not None)

    def close(self) -> None:
        if self.cid is not None:
            self.pb.disconnect(physicsClientId=self.cid)
            self.cid = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

