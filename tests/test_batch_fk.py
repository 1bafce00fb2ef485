"""BatchFK (ms_drake.planning.batch_fk): batched link poses equal Drake's own forward kinematics."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import MultibodyPlant

from ms_drake.paths import make_parser
from ms_drake.planning.batch_fk import BatchFK, BatchFKError
from ms_drake.station.robots import add_arm_gripper, add_robot


def _plant(robot, arm, with_gripper=True):
    plant = MultibodyPlant(0.0)
    parser = make_parser(plant)
    inst = add_robot(plant, parser, robot, X_WR=RigidTransform(RollPitchYaw(0, 0, 0.3), [0.1, -0.2, 0.05]))
    if with_gripper:
        add_arm_gripper(plant, parser, inst, robot, arm)
    plant.Finalize()
    return plant, inst


@pytest.mark.parametrize("robot, arm", [("panda", "panda"), ("yumi", "yumi_right")])
def test_batched_poses_match_drake(robot, arm):
    plant, inst = _plant(robot, arm)
    ctx = plant.CreateDefaultContext()
    rng = np.random.default_rng(0)
    q_full = plant.GetPositions(ctx)
    q_full[:] = rng.uniform(-0.5, 0.5, len(q_full)) * 0.05  # every position off zero, the fingers too
    plant.SetPositions(ctx, q_full)
    arm_positions = [plant.GetJointByName(n).position_start() for n in _arm_joints(plant, inst)]
    bodies = [plant.get_body(b) for b in plant.GetBodyIndices(inst)] + [
        plant.get_body(b) for m in range(plant.num_model_instances()) if m > 1 and m != int(inst)
        for b in plant.GetBodyIndices(type(inst)(m))]
    fk = BatchFK(plant, ctx, arm_positions, bodies)
    lower, upper = plant.GetPositionLowerLimits()[arm_positions], plant.GetPositionUpperLimits()[arm_positions]
    qs = rng.uniform(np.maximum(lower, -3), np.minimum(upper, 3), (6, len(arm_positions)))
    X = fk(qs)
    assert X.shape == (6, len(bodies), 4, 4)
    np.testing.assert_allclose(fk.torch(qs).numpy(), X, rtol=0, atol=1e-12)  # the torch graph: the same poses
    for i, qa in enumerate(qs):
        q = q_full.copy()
        q[arm_positions] = qa
        plant.SetPositions(ctx, q)
        for j, b in enumerate(bodies):
            assert np.allclose(X[i, j], plant.EvalBodyPoseInWorld(ctx, b).GetAsMatrix4(), atol=1e-9), b.name()


def _arm_joints(plant, inst):
    return [plant.get_joint(j).name() for j in plant.GetJointIndices(inst) if plant.get_joint(j).num_positions() == 1]


def test_wrong_batch_width_is_a_clear_error():
    plant, inst = _plant("panda", "panda", with_gripper=False)
    ctx = plant.CreateDefaultContext()
    fk = BatchFK(plant, ctx, [0, 1], ["panda_link3"], inst)
    with pytest.raises(BatchFKError, match="takes 2 positions"):
        fk(np.zeros((3, 7)))
    with pytest.raises(BatchFKError, match=r"must be \(N, 2\)"):
        fk.torch(np.zeros((3, 7)))
