"""Forward kinematics of many configurations at once, in numpy, from a Drake MultibodyPlant.

MPPI checks T x H waypoints per call (300 x 40 = 12,000 at the reference's setting) and needs the
pose of every robot link at each: a loop over `plant.SetPositions` + `EvalBodyPoseInWorld` costs
tens of microseconds per configuration in Python. `BatchFK` reads the plant's kinematic tree once
(each joint's fixed frames on parent and child, its axis) and then composes the (N, 4, 4) poses
of the requested bodies with batched matrix products:

    X_WC = X_WP @ X_PF @ X_FM(q) @ inv(X_CM)

for the joint between parent body P and child body C (F: the joint's frame on the parent, M: on
the child). Revolute, prismatic and weld joints are supported (the robots of this project);
joints whose positions are not in `positions` keep their values from the context given at
construction (e.g. the gripper's fingers, another robot's arm). Free (floating) bodies keep the
context's pose. The result matches `plant.EvalBodyPoseInWorld` to round-off (tests/test_batch_fk.py).

`BatchFK.torch(q)` is the same kinematics as one torch graph (float64; torch imported there): each
joint's pose in its parent, X_PF @ X_FM(q) @ inv(X_CM), is M0 + sin(q) M1 + (1 - cos(q)) M2 for a
revolute joint (Rodrigues' formula with the fixed frames folded into three constant matrices) and
M0 + q M1 for a prismatic one, so a body costs one batched 4x4 product; collision checkers run it
next to their network without leaving torch.
"""

from __future__ import annotations

import numpy as np
from pydrake.multibody.tree import PrismaticJoint, RevoluteJoint, WeldJoint

from ms_drake.errors import MsDrakeError


class BatchFKError(MsDrakeError):
    """The batched forward kinematics cannot handle this plant or these inputs."""


def _axis_rotation(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations by `angles` (N,) about the unit `axis` (Rodrigues)."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


class BatchFK:
    """World poses of `bodies` for batches of the plant positions `positions` (module doc).

    plant: a finalized MultibodyPlant; context: its context holding the values of every other
    position; positions: indices into the plant's full q that a batch supplies (e.g. the arm's
    joints); bodies: the bodies (or their names, with `model_instance`) whose poses are returned.
    """

    def __init__(self, plant, context, positions, bodies, model_instance=None):
        self.plant = plant
        self.positions = np.asarray(positions, int)
        self.bodies = [plant.GetBodyByName(b, model_instance) if isinstance(b, str) else b for b in bodies]
        q0 = plant.GetPositions(context)
        slot = {int(p): k for k, p in enumerate(self.positions)}
        self._inboard = {int(plant.get_joint(j).child_body().index()): plant.get_joint(j)
                         for j in plant.GetJointIndices()}
        # The chain from the world to every requested body, root first, with what each joint needs.
        self.steps = []  # (child body index, parent body index, X_PF, X_CM^-1, kind, axis, batch slot or None, q0)
        seen = set()
        for body in self.bodies:
            chain = []
            b = body
            while b.index() != plant.world_body().index() and int(b.index()) not in seen:
                joint = self._inboard_joint(b)
                if joint is None:  # a free body: its pose from the context
                    chain.append((int(b.index()), None, plant.EvalBodyPoseInWorld(context, b).GetAsMatrix4(),
                                  None, "free", None, None, 0.0))
                    seen.add(int(b.index()))
                    break
                X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame().GetAsMatrix4()
                X_CM = joint.frame_on_child().GetFixedPoseInBodyFrame().GetAsMatrix4()
                if isinstance(joint, RevoluteJoint):
                    kind, axis = "revolute", np.asarray(joint.revolute_axis(), float)
                elif isinstance(joint, PrismaticJoint):
                    kind, axis = "prismatic", np.asarray(joint.translation_axis(), float)
                elif isinstance(joint, WeldJoint):
                    kind, axis = "weld", None
                    X_PF = X_PF @ joint.X_FM().GetAsMatrix4()
                else:
                    raise BatchFKError(f"joint {joint.name()!r} is a {type(joint).__name__}: BatchFK handles "
                                       "revolute, prismatic and weld joints")
                start = joint.position_start() if joint.num_positions() else -1
                chain.append((int(b.index()), int(joint.parent_body().index()), X_PF, np.linalg.inv(X_CM), kind,
                              axis, slot.get(start), float(q0[start]) if start >= 0 else 0.0))
                seen.add(int(b.index()))
                b = joint.parent_body()
            self.steps.extend(reversed(chain))
        self.world = int(plant.world_body().index())

    def _inboard_joint(self, body):
        return self._inboard.get(int(body.index()))

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """(N, len(bodies), 4, 4) world-from-body poses for q (N, len(positions))."""
        q = np.atleast_2d(np.asarray(q, float))
        if q.shape[1] != len(self.positions):
            raise BatchFKError(f"q has {q.shape[1]} columns; this BatchFK takes {len(self.positions)} positions")
        N = len(q)
        X = {self.world: np.broadcast_to(np.eye(4), (N, 4, 4))}
        for child, parent, X_PF, X_MC, kind, axis, k, q0 in self.steps:
            if kind == "free":
                X[child] = np.broadcast_to(X_PF, (N, 4, 4))
                continue
            value = q[:, k] if k is not None else np.full(N, q0)
            A = X[parent] @ X_PF
            if kind == "revolute":
                F = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
                F[:, :3, :3] = _axis_rotation(axis, value)
                A = A @ F
            elif kind == "prismatic":
                F = np.broadcast_to(np.eye(4), (N, 4, 4)).copy()
                F[:, :3, 3] = value[:, None] * axis
                A = A @ F
            X[child] = A @ X_MC
        return np.stack([X[int(b.index())] for b in self.bodies], axis=1)

    def _torch_steps(self):
        """The steps as constant torch matrices (M0, M1, M2) per joint (module doc), built once."""
        if getattr(self, "_tsteps", None) is None:
            import torch  # optional heavy dependency

            steps = []
            for child, parent, X_PF, X_MC, kind, axis, k, q0 in self.steps:
                if kind in ("free", "weld"):
                    M = (X_PF if kind == "free" else X_PF @ X_MC,)
                elif kind == "revolute":
                    a = axis / np.linalg.norm(axis)
                    K = np.zeros((4, 4))
                    K[:3, :3] = [[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]]
                    M = (X_PF @ X_MC, X_PF @ K @ X_MC, X_PF @ K @ K @ X_MC)
                else:  # prismatic
                    D = np.zeros((4, 4))
                    D[:3, 3] = axis
                    M = (X_PF @ X_MC, X_PF @ D @ X_MC)
                steps.append((child, parent, kind, k, q0, torch.tensor(np.concatenate(M, axis=1), dtype=torch.float64)))
            self._tsteps = steps
        return self._tsteps

    def torch(self, q):
        """(N, len(bodies), 4, 4) float64 torch poses for q (N, len(positions)), a torch tensor or array
        (module doc); the same values as calling the BatchFK, to round-off."""
        import torch  # optional heavy dependency

        q = torch.as_tensor(q, dtype=torch.float64)
        if q.ndim != 2 or q.shape[1] != len(self.positions):
            raise BatchFKError(f"q must be (N, {len(self.positions)}), got shape {tuple(q.shape)}")
        N = q.shape[0]
        X = {self.world: None}  # None: the identity
        for child, parent, kind, k, q0, M in self._torch_steps():
            P = X[parent]
            # P @ [M0 M1 M2]: one matrix product with the joint's constant matrices side by side
            A = M.expand(N, 4, M.shape[1]) if P is None or kind == "free" else torch.matmul(P, M)
            if kind in ("free", "weld"):
                X[child] = A
                continue
            v = (q[:, k] if k is not None else torch.full((N,), q0, dtype=torch.float64))[:, None, None]
            if kind == "prismatic":
                X[child] = A[:, :, :4] + v * A[:, :, 4:]
            else:
                X[child] = A[:, :, :4] + torch.sin(v) * A[:, :, 4:8] + (1.0 - torch.cos(v)) * A[:, :, 8:]
        return torch.stack([X[int(b.index())] for b in self.bodies], dim=1)
