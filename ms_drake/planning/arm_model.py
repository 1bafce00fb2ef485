"""An arm's bodies as point sets with batched forward kinematics, and Drake's own collision check
of the robot against itself and the environment, for sampling planners (MPPI, Ch. 6.3.2).

    model = ArmModel(ik)                       # ik: an ArmIk on a robot + gripper + environment plant
    poses = model.link_poses(qs)               # {body name: (n, 4, 4) world-from-body} for n configurations
    model.points["panda_link5"]                # (m, 3) points on the body's collision geometry, body frame
    model.self_collides(qs)                    # (n,) bool: robot-robot or robot-environment contact (Drake)

- Points: `points_per_body` points sampled (seeded) on the surface of each collision geometry of
  every body that the arm's joints move (meshes / convex meshes read with trimesh, boxes,
  cylinders and spheres from trimesh primitives), in the body frame: the reference's "points
  pre-sampled from the 3D mesh of each link", featurised once per robot by the scene checker.
- Forward kinematics: numpy over a batch (ms_drake.planning.batch_fk.BatchFK over the moving
  bodies); bodies held by a joint that is not one of the arm's (the gripper's fingers) keep the
  positions they have in the plant's context. Matches `plant.EvalBodyPoseInWorld` to 1e-9
  (tests/test_rearrange.py).
  `link_poses_torch` is the same in torch (one graph with a network checker).
- `self_collides`: the plant's geometry on its own context (SceneGraph's `HasCollisions`: robot
  against itself with adjacent links filtered, and against the environment's table), one
  configuration at a time; callers check lazily (few configurations).
"""

from __future__ import annotations

import numpy as np
import trimesh
from pydrake.geometry import Box, Convex, Cylinder, Mesh, Sphere
from pydrake.multibody.tree import RevoluteJoint

from ms_drake.geometry import transform_points
from ms_drake.errors import MsDrakeError
from ms_drake.planning.batch_fk import BatchFK


class ArmModelError(MsDrakeError, ValueError):
    """The arm model cannot be built from the given plant (names what is missing)."""


def _shape_points(shape, n: int, rng: np.random.Generator) -> np.ndarray | None:
    if isinstance(shape, (Mesh, Convex)):
        mesh = trimesh.load(str(shape.source().path()), force="mesh")
        mesh.apply_scale(np.asarray(shape.scale3(), float))
        if isinstance(shape, Convex):
            mesh = mesh.convex_hull
    elif isinstance(shape, Box):
        mesh = trimesh.creation.box([shape.width(), shape.depth(), shape.height()])
    elif isinstance(shape, Cylinder):
        mesh = trimesh.creation.cylinder(shape.radius(), shape.length())
    elif isinstance(shape, Sphere):
        mesh = trimesh.creation.icosphere(radius=shape.radius())
    else:
        return None
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2 ** 31)))
    return np.asarray(pts, float)


class ArmModel:
    """Point sets, batched forward kinematics and Drake collision checks of the arm of `ik` (module doc)."""

    def __init__(self, ik, points_per_body: int = 256, seed: int = 0):
        self.ik = ik
        plant, ctx = ik.plant, ik.context
        self.plant, self.context = plant, ctx
        self.idx = np.asarray(ik.idx)
        self.q_fixed = plant.GetPositions(ctx).copy()  # the other joints (gripper open) as in the context
        first = ik.joints[0].parent_body()
        self.base_name = first.name()
        self.X_W_base = plant.EvalBodyPoseInWorld(ctx, first).GetAsMatrix4()
        # Moving bodies: everything outboard of the first arm joint's parent (arm links, gripper).
        children = {}
        for joint_index in plant.GetJointIndices():
            joint = plant.get_joint(joint_index)
            children.setdefault(int(joint.parent_body().index()), []).append(joint.child_body())
        moving, frontier = [], [first]
        while frontier:
            for child in children.get(int(frontier.pop(0).index()), []):
                moving.append(child)
                frontier.append(child)
        moving_ids = {b.index() for b in moving}
        found = [j for j in ik.joints if isinstance(j, RevoluteJoint) and j.child_body().index() in moving_ids]
        if len(found) != len(ik.joints):
            raise ArmModelError(f"ArmModel: {len(ik.joints)} arm joints but only {len(found)} revolute joints "
                                f"found below {self.base_name!r}")
        self._fk = BatchFK(plant, ctx, self.idx, moving)
        self.body_names = tuple(b.name() for b in moving)
        # Points on each moving body's collision geometry.
        rng = np.random.default_rng(seed)
        inspector = plant.get_geometry_query_input_port().Eval(ctx).inspector()
        self.points = {}
        for name, body in zip(self.body_names, moving):
            sets = []
            for gid in plant.GetCollisionGeometriesForBody(body):
                pts = _shape_points(inspector.GetShape(gid), points_per_body, rng)
                if pts is None:
                    continue
                X_BG = inspector.GetPoseInFrame(gid).GetAsMatrix4()
                sets.append(transform_points(X_BG, pts))
            if sets:
                P = np.concatenate(sets)
                if len(P) > points_per_body:
                    P = P[rng.choice(len(P), points_per_body, replace=False)]
                self.points[name] = P
        self._query = None

    @property
    def num_positions(self) -> int:
        return len(self.idx)

    def link_poses(self, qs: np.ndarray) -> dict[str, np.ndarray]:
        """{body name: (n, 4, 4) world-from-body} for n arm configurations qs (n, dof)."""
        qs = np.atleast_2d(np.asarray(qs, float))
        if qs.shape[1] != self.num_positions:
            raise ArmModelError(f"configurations must have {self.num_positions} joints, got shape {qs.shape}")
        X = self._fk(qs)
        poses = {self.base_name: np.broadcast_to(self.X_W_base, (len(qs), 4, 4))}
        poses.update({name: X[:, k] for k, name in enumerate(self.body_names)})
        return poses

    def link_poses_torch(self, qs):
        """(n, len(body_names), 4, 4) float64 torch world-from-body poses of the moving bodies, in
        the order of `body_names`, for configurations qs (n, dof): link_poses as one torch graph."""
        return self._fk.torch(qs)

    def tool_pose(self, q) -> np.ndarray:
        """4x4 world-from-tool (the ik's frame) at arm configuration q."""
        q_all = self.q_fixed.copy()
        q_all[self.idx] = q
        self.plant.SetPositions(self.context, q_all)
        return self.ik.frame.CalcPoseInWorld(self.context).GetAsMatrix4()

    def self_collides(self, qs: np.ndarray) -> np.ndarray:
        """(n,) bool: the robot touches itself or the environment at each configuration (Drake's geometry)."""
        qs = np.atleast_2d(np.asarray(qs, float))
        out = np.zeros(len(qs), bool)
        q_all = self.q_fixed.copy()
        for i, q in enumerate(qs):
            q_all[self.idx] = q
            self.plant.SetPositions(self.context, q_all)
            out[i] = self.plant.get_geometry_query_input_port().Eval(self.context).HasCollisions()
        self.plant.SetPositions(self.context, self.q_fixed)
        return out
