"""Cartesian straight-line motions (approach, lift, push lines of ms_drake.planning.sequences) as a
sequence of IK solves.

The tool frame moves along a straight line with a fixed orientation; every `step` metres the arm
IK is solved seeded with the previous solution and no random restarts, so the joint path stays
continuous (a jump larger than `max_joint_step` rad between successive solves counts as a
failure: the line would pass a singularity or a branch change). The joint path is then timed by
`plan_path_motion` under the arm's joint limits and the tool's Cartesian speed limit.
A line that cannot be followed returns `CartesianPlan(success=False, status="unreachable", ...)`
with the fraction of the line that was solved; nothing raises.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform

from ms_drake.geometry import as_rigid_transform
from ms_drake.planning.ik import ArmIk
from ms_drake.planning.trajectories import JointTrajectory, plan_path_motion
from ms_drake.types import JointLimits


@dataclass(frozen=True, eq=False)
class CartesianPlan:
    success: bool
    status: str  # ok | unreachable | collision
    qs: np.ndarray  # (N, dof) joint path (the solved prefix when unsuccessful)
    trajectory: JointTrajectory | None = None
    fraction: float = 0.0  # of the line solved


def plan_cartesian_line(ik: ArmIk, X_start: RigidTransform, displacement, q_start, limits: JointLimits,
                        step: float = 0.01, max_joint_step: float = 0.3, axis_only: bool = False,
                        max_speed: float = 0.25) -> CartesianPlan:
    """Move the tool from X_start (RigidTransform or 4x4 array) by `displacement` (world frame,
    metres) along a straight line."""
    X_start = as_rigid_transform(X_start, "X_start")
    d = np.asarray(displacement, float)
    length = float(np.linalg.norm(d))
    n = max(1, int(np.ceil(length / step)))
    qs = [np.asarray(q_start, float)]
    restarts, ik.restarts = ik.restarts, 0
    try:
        for k in range(1, n + 1):
            X = RigidTransform(X_start.rotation(), X_start.translation() + d * k / n)
            res = ik.solve(X, q_seed=qs[-1], axis_only=axis_only)
            if not res.success or np.max(np.abs(res.q - qs[-1])) > max_joint_step:
                status = res.status if not res.success else "unreachable"
                return CartesianPlan(False, status, np.array(qs), None, (k - 1) / n)
            qs.append(res.q)
    finally:
        ik.restarts = restarts
    Q = np.array(qs)
    return CartesianPlan(True, "ok", Q, plan_path_motion(Q, limits, length, max_speed=max_speed), 1.0)


def approach_pose(X_WT: RigidTransform, distance: float) -> RigidTransform:
    """The pre-grasp pose `distance` back along the tool's approach axis (its +z); X_WT:
    RigidTransform or 4x4 array."""
    X_WT = as_rigid_transform(X_WT, "X_WT")
    z = X_WT.rotation().matrix()[:, 2]
    return RigidTransform(X_WT.rotation(), X_WT.translation() - distance * z)


def ik_pose(ik: ArmIk, q_arm) -> RigidTransform:
    """Tool pose at arm joints q_arm (other joints at their current values)."""
    old = ik.plant.GetPositions(ik.context).copy()
    q = old.copy()
    q[ik.idx] = q_arm
    ik.plant.SetPositions(ik.context, q)
    X = ik.frame.CalcPoseInWorld(ik.context)
    ik.plant.SetPositions(ik.context, old)
    return X
