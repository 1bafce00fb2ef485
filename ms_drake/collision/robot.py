"""Robot-scene collision checking from a point cloud (Ch. 6.3.2, line 1067), for batches of
configurations: what MPPI needs at every waypoint.

`RobotSceneCollision` samples points once from each checked link's collision geometry (Drake's
SceneGraph shapes: meshes, boxes, cylinders, spheres, capsules) in the link's frame and registers
them with a `SceneChecker` (so with the network the link features are computed once per robot, as
in the reference); at run time `BatchFK` gives every link's pose at every configuration and one
checker query per link answers all of them. An object in hand is another point set attached to a
body at a fixed pose (`attach`). The table is checked analytically: a configuration collides when
any link point falls below `table_top` (the scene cloud's table points are removed before the
checker sees them). The robot's self-collisions are Drake's: `DrakeCollision` asks the plant's
SceneGraph about a few configurations (it loops in Python, so MPPI calls it on the chosen
trajectory only; ms_drake.planning.mppi's `verify`).
"""

from __future__ import annotations

import numpy as np
import trimesh
from pydrake.geometry import Box, Capsule, Convex, Cylinder, Mesh, Sphere

from ms_drake.collision.checker import SceneChecker
from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.planning.batch_fk import BatchFK


def shape_mesh(shape) -> trimesh.Trimesh:
    """A trimesh of a Drake shape in its geometry frame."""
    if isinstance(shape, (Mesh, Convex)):
        source = shape.source()
        if not source.is_path():
            raise CollisionNetError(f"cannot sample points on an in-memory Drake {type(shape).__name__}")
        mesh = trimesh.load(str(source.path()), force="mesh")
        mesh.vertices = mesh.vertices * np.asarray(shape.scale3())
        return mesh
    if isinstance(shape, Box):
        return trimesh.creation.box([shape.width(), shape.depth(), shape.height()])
    if isinstance(shape, Cylinder):
        return trimesh.creation.cylinder(shape.radius(), shape.length())
    if isinstance(shape, Sphere):
        return trimesh.creation.icosphere(2, shape.radius())
    if isinstance(shape, Capsule):
        return trimesh.creation.capsule(shape.length(), shape.radius())
    raise CollisionNetError(f"cannot sample points on a Drake {type(shape).__name__}")


def body_points(plant, inspector, body, count: int = 256, seed: int = 0) -> np.ndarray:
    """(count, 3) points on `body`'s proximity geometry, in the body frame (area-weighted)."""
    parts = []
    for gid in plant.GetCollisionGeometriesForBody(body):
        mesh = shape_mesh(inspector.GetShape(gid))
        X_BG = inspector.GetPoseInFrame(gid).GetAsMatrix4()
        parts.append(mesh.apply_transform(X_BG))
    if not parts:
        raise CollisionNetError(f"body {body.name()!r} has no collision geometry to sample")
    mesh = trimesh.util.concatenate(parts)
    pts, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(pts, np.float32)


class RobotSceneCollision:
    """P(collision) of a robot's links (+ an object in hand) with a scene cloud, per configuration.

    plant: a finalized plant registered with a SceneGraph; inspector: that SceneGraph's inspector
    (`scene_graph.model_inspector()`, or the plant's geometry query port's `inspector()`); context: the plant's
    context holding the positions a batch does not supply; positions: the plant position indices a
    configuration gives (the arm's joints); bodies: the bodies to check (names with
    `model_instance`, or Body objects); checker: a SceneChecker on the scene cloud.
    """

    def __init__(self, plant, inspector, context, positions, bodies, checker: SceneChecker,
                 model_instance=None, table_top: float | None = 0.0, points_per_body: int = 256, seed: int = 0,
                 threshold: float = 0.5):
        self.bodies = [plant.GetBodyByName(b, model_instance) if isinstance(b, str) else b for b in bodies]
        self.checker, self.table_top, self.threshold = checker, table_top, threshold
        self.names = []
        self.points = []
        for k, body in enumerate(self.bodies):
            pts = body_points(plant, inspector, body, points_per_body, seed + k)
            name = f"link:{body.name()}"
            checker.add(name, pts)
            self.names.append(name)
            self.points.append(pts)
        self.attached: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
        self._plant, self._context, self._positions = plant, context, positions
        self._fk = BatchFK(plant, context, positions, self.bodies)

    def attach(self, name: str, points: np.ndarray, body, X_BO: np.ndarray) -> None:
        """Check `points` (object frame) held rigidly at X_BO (4x4) in `body` (one of the checked bodies)."""
        index = next((k for k, b in enumerate(self.bodies) if b.index() == body.index()), None)
        if index is None:
            raise CollisionNetError(f"attach: body {body.name()!r} is not one of the checked bodies "
                                    f"({', '.join(b.name() for b in self.bodies)})")
        self.checker.add(f"held:{name}", points)
        self.attached[name] = (index, np.asarray(X_BO, float), np.asarray(points, float))

    def detach(self, name: str) -> None:
        self.attached.pop(name, None)

    def probabilities(self, q: np.ndarray) -> np.ndarray:
        """(N,) the largest P(collision) over the checked links and held objects at each configuration."""
        X = self._fk(q)  # (N, B, 4, 4)
        p = np.zeros(len(X))
        for k, name in enumerate(self.names):
            p = np.maximum(p, self.checker.query(name, X[:, k]))
            if self.table_top is not None:
                z_min = (X[:, k, 2, :3] @ self.points[k].T.astype(float)).min(axis=1) + X[:, k, 2, 3]
                p[z_min < self.table_top] = 1.0
        for name, (k, X_BO, pts) in self.attached.items():
            XO = X[:, k] @ X_BO
            p = np.maximum(p, self.checker.query(f"held:{name}", XO))
        return p

    def collides(self, q: np.ndarray) -> np.ndarray:
        """(N,) bool: some link or held object collides at that configuration."""
        return self.probabilities(q) > self.threshold


class DrakeCollision:
    """Collisions of the given model instances' geometry (the robot and its gripper) with anything
    in the plant's SceneGraph -- themselves (self-collision), the table, modelled objects -- one
    configuration at a time: `__call__(q (N, n)) -> (N,) bool`. Pairs the plant filters (adjacent
    links) do not count; pairs between other bodies (objects resting on the table) are ignored."""

    def __init__(self, plant, diagram_context, positions, instances):
        self.plant = plant
        self.plant_context = plant.GetMyMutableContextFromRoot(diagram_context)
        self.positions = np.asarray(positions, int)
        self.ids = {g for inst in instances for b in plant.GetBodyIndices(inst)
                    for g in plant.GetCollisionGeometriesForBody(plant.get_body(b))}

    def __call__(self, q: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        full = self.plant.GetPositions(self.plant_context).copy()
        out = np.zeros(len(q), bool)
        port = self.plant.get_geometry_query_input_port()
        for i, qi in enumerate(q):
            full[self.positions] = qi
            self.plant.SetPositions(self.plant_context, full)
            pairs = port.Eval(self.plant_context).ComputePointPairPenetration()
            out[i] = any(p.id_A in self.ids or p.id_B in self.ids for p in pairs)
        return out
