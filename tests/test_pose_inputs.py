"""Every public function that takes a pose accepts a pydrake RigidTransform and a 4x4 array, with
the same result; a NaN pose, a 3x3 array and a non-pose raise an error naming the argument."""

import dataclasses

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform
from pydrake.systems.sensors import CameraInfo

from ms_drake.geometry import as_matrix4, as_rigid_transform
from ms_drake.grasping import GraspEvaluator, ParallelJawGrasp, SuctionGrasp
from ms_drake.grasping.physics import simulate_grasp
from ms_drake.grasping.planner import GraspPlanner
from ms_drake.grasping.samplers import (sample_antipodal_grasps, sample_antipodal_grasps_depth,
                                        sample_suction_grasps, sample_suction_grasps_depth)
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.types import InstanceMasks, ObjectGeometry
from test_grasp_samplers import _render_depth, overhead_camera, pose_xyz_yaw

BOX = trimesh.creation.box(extents=(0.04, 0.06, 0.03))
X_WO = pose_xyz_yaw(0.01, -0.02, 0.015, 0.3)  # the box on the floor, turned about z
K, X_WC = overhead_camera()
DEPTH = _render_depth(BOX, X_WO, K, X_WC, 96, 128)
MASK = np.isfinite(DEPTH)
# jaws closing across the box's 4 cm side, from above; a suction cup on its top face
JAW = ParallelJawGrasp(X_WO[:3, 3], X_WO[:3, 0], [0, 0, -1], 0.07)
CUP = SuctionGrasp(X_WO[:3, 3] + [0, 0, 0.015], [0, 0, -1])


def plain(x):
    """A value as nested tuples, for comparing results that hold arrays or RigidTransforms."""
    if isinstance(x, RigidTransform):
        return plain(x.GetAsMatrix4())
    if isinstance(x, np.ndarray):
        return tuple(plain(v) for v in x.tolist()) if x.ndim else x.item()
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__name__,) + tuple(plain(getattr(x, f.name)) for f in dataclasses.fields(x))
    if isinstance(x, (list, tuple)):
        return tuple(plain(v) for v in x)
    if isinstance(x, dict):
        return tuple(sorted((k, plain(v)) for k, v in x.items()))
    return x


def _planner(**kw):
    return GraspPlanner(CameraInfo(128, 96, K[0, 0], K[1, 1], K[0, 2], K[1, 2]), model="soft_point", num_samples=4,
                        **kw)


def _plan_with_object_pose(X):
    masks = InstanceMasks(MASK[None], ("box",), np.ones(1))
    return _planner(X_WC=X_WC).plan(DEPTH, masks, (ObjectGeometry("box", BOX.vertices, BOX.faces, X, 0.2),))


def _sim_outcome(X):
    out = simulate_grasp(BOX, X, JAW, 0.2)
    return dataclasses.replace(out, seconds=0.0)  # wall time: the one field that depends on the machine


# name -> (argument name, the call with that pose argument); the other arguments are fixed
CASES = {
    "GraspEvaluator.evaluate": ("X_WO", lambda X: GraspEvaluator("soft_point").evaluate(BOX, X, JAW, 0.2)),
    "GraspEvaluator.quality (robust)": ("X_WO", lambda X: GraspEvaluator("reach").quality(
        BOX, X, JAW, 0.2, robust_samples=3, seed=1)),
    "SuctionEvaluator.evaluate": ("X_WO", lambda X: SuctionEvaluator().evaluate(BOX, X, CUP, 0.2)),
    "SuctionEvaluator.quality (robust)": ("X_WO", lambda X: SuctionEvaluator().quality(
        BOX, X, CUP, 0.2, robust_samples=3, seed=1)),
    "sample_antipodal_grasps": ("X_WO", lambda X: sample_antipodal_grasps(BOX, X, 5, seed=1)),
    "sample_suction_grasps": ("X_WO", lambda X: sample_suction_grasps(BOX, X, 5, seed=1)),
    "sample_antipodal_grasps_depth": ("X_WC", lambda X: sample_antipodal_grasps_depth(DEPTH, K, X, MASK, 5, seed=1)),
    "sample_suction_grasps_depth": ("X_WC", lambda X: sample_suction_grasps_depth(DEPTH, K, X, MASK, 5, seed=1)),
    "simulate_grasp": ("X_WO", _sim_outcome),
    "GraspPlanner(X_WC)": ("X_WC", lambda X: _planner(X_WC=X).plan(
        DEPTH, InstanceMasks(MASK[None], ("box",), np.ones(1)))),
    "GraspPlanner.plan(X_WC)": ("X_WC", lambda X: _planner().plan(
        DEPTH, InstanceMasks(MASK[None], ("box",), np.ones(1)), X_WC=X)),
    "GraspPlanner.jaw_candidates": ("X_WC", lambda X: _planner().jaw_candidates(DEPTH, MASK, X, 1, K)),
    "ObjectGeometry.X_WO in GraspPlanner.plan": ("X_WO", _plan_with_object_pose),
}
# the pose each case is called with (X_WO or X_WC above)
POSES = {"X_WO": X_WO, "X_WC": X_WC}


@pytest.mark.parametrize("name", CASES)
def test_rigid_transform_and_matrix_give_the_same_result(name):
    arg, call = CASES[name]
    X = POSES[arg]
    from_matrix = call(X.copy())
    assert plain(call(RigidTransform(X))) == plain(from_matrix)
    assert plain(call(X.tolist())) == plain(from_matrix)  # any 4x4 array-like


@pytest.mark.parametrize("name", CASES)
def test_a_bad_pose_raises_naming_the_argument(name):
    arg, call = CASES[name]
    with pytest.raises(ValueError, match=f"{arg}.*non-finite"):
        call(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match=f"{arg}.*4x4.*shape \\(3, 3\\)"):
        call(np.eye(3))
    with pytest.raises(TypeError, match=f"{arg} must be a pydrake RigidTransform or a 4x4 array, got str"):
        call("identity")


def test_the_pose_check():
    X = POSES["X_WO"]
    np.testing.assert_array_equal(as_matrix4(RigidTransform(X)), X)
    assert as_rigid_transform(X).IsExactlyEqualTo(RigidTransform(X))
    scaled = X.copy()
    scaled[:3, :3] *= 1.01
    with pytest.raises(ValueError, match="X_AB is not a rigid transform"):
        as_matrix4(scaled, "X_AB")
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="det = -1"):
        as_rigid_transform(mirrored, "X_AB")
    bottom = np.eye(4)
    bottom[3, 0] = 1.0
    with pytest.raises(ValueError, match="last row"):
        as_matrix4(bottom, "X_AB")
    with pytest.raises(TypeError, match="X_AB must be a pydrake RigidTransform or a 4x4 array, got NoneType"):
        as_matrix4(None, "X_AB")
