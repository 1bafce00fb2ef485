"""RobotSceneCollision and DrakeCollision (ms_drake.collision.robot): the Panda's links against a
scene cloud, an object in hand, the table, and Drake's own geometry."""

import numpy as np
import pytest
import trimesh
from pydrake.geometry import Box as DrakeBox
from pydrake.math import RigidTransform
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, CoulombFriction
from pydrake.systems.framework import DiagramBuilder

from ms_drake.collision.checker import SceneChecker
from ms_drake.collision.robot import DrakeCollision, RobotSceneCollision, body_points
from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.paths import make_parser
from ms_drake.robots import robot_spec
from ms_drake.station.robots import add_arm_gripper, add_robot

HOME = np.array(robot_spec("panda").arms["panda"].home)
LINKS = [f"panda_link{k}" for k in range(1, 8)]


def _panda(with_table=False):
    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlantSceneGraph(builder, 0.0)
    parser = make_parser(plant)
    inst = add_robot(plant, parser, "panda")
    grip = add_arm_gripper(plant, parser, inst, "panda", "panda")
    if with_table:  # a 1 x 1 m table whose top is at z = 0, in front of the robot
        plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0.5, 0.0, -0.025]),
                                        DrakeBox(1.0, 1.0, 0.05), "table", CoulombFriction(0.5, 0.5))
    plant.Finalize()
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    pctx = plant.GetMyMutableContextFromRoot(ctx)
    arm = [plant.GetJointByName(f"panda_joint{k}").position_start() for k in range(1, 8)]
    q = plant.GetPositions(pctx)
    q[arm] = HOME
    plant.SetPositions(pctx, q)
    return plant, sg, diagram, ctx, pctx, inst, grip, arm


def _cube_cloud(centre, size=0.08, n=3000):
    return (trimesh.sample.sample_surface(trimesh.creation.box([size] * 3), n, seed=3)[0] + centre).astype(np.float32)


def test_links_collide_with_a_cloud_where_the_hand_is_and_not_elsewhere():
    plant, sg, diagram, ctx, pctx, inst, grip, arm = _panda()
    link7 = plant.GetBodyByName("panda_link7", inst)
    p_hand = plant.EvalBodyPoseInWorld(pctx, link7).translation()
    for cloud, expect in ((_cube_cloud(p_hand), True), (_cube_cloud(p_hand + [0.0, 0.6, 0.0]), False)):
        checker = SceneChecker("sdf", cloud)
        robot = RobotSceneCollision(plant, sg.model_inspector(), pctx, arm, LINKS, checker, inst, table_top=-0.5)
        assert robot.collides(HOME[None]).tolist() == [expect]
    # a batch: HOME free, and the first joint turned so that the arm sweeps into a cube beside it
    q2 = HOME.copy()
    q2[0] = np.pi / 2
    plant.SetPositions(pctx, inst, q2)  # where link7 is then
    p2 = plant.EvalBodyPoseInWorld(pctx, link7).translation()
    robot = RobotSceneCollision(plant, sg.model_inspector(), pctx, arm, LINKS, SceneChecker("sdf", _cube_cloud(p2)), inst, table_top=-0.5)
    assert robot.collides(np.stack([HOME, q2])).tolist() == [False, True]


def test_table_and_object_in_hand():
    plant, sg, diagram, ctx, pctx, inst, grip, arm = _panda()
    far = _cube_cloud(np.array([2.0, 2.0, 0.3]))
    link7 = plant.GetBodyByName("panda_link7", inst)
    z_hand = plant.EvalBodyPoseInWorld(pctx, link7).translation()[2]
    robot = RobotSceneCollision(plant, sg.model_inspector(), pctx, arm, LINKS, SceneChecker("sdf", far), inst, table_top=z_hand - 0.02)
    assert robot.collides(HOME[None]).tolist() == [True]  # link7's points reach below that "table"
    robot = RobotSceneCollision(plant, sg.model_inspector(), pctx, arm, LINKS, SceneChecker("sdf", far), inst, table_top=0.0)
    assert robot.collides(HOME[None]).tolist() == [False]
    # an object held 0.5 m below link7 meets a cube there
    X_WL = plant.EvalBodyPoseInWorld(pctx, link7).GetAsMatrix4()
    target = X_WL[:3, 3] + [0.0, 0.0, -0.5]
    robot = RobotSceneCollision(plant, sg.model_inspector(), pctx, arm, LINKS, SceneChecker("sdf", _cube_cloud(target)), inst)
    assert robot.collides(HOME[None]).tolist() == [False]
    X_LO = np.linalg.inv(X_WL) @ np.block([[np.eye(3), target[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    robot.attach("bar", _cube_cloud(np.zeros(3), 0.085, 500), link7, X_LO)  # its faces 2.5 mm off the cube's
    assert robot.collides(HOME[None]).tolist() == [True]
    robot.detach("bar")
    assert robot.collides(HOME[None]).tolist() == [False]
    with pytest.raises(CollisionNetError, match="not one of the checked bodies"):
        robot.attach("bar", _cube_cloud(np.zeros(3)), plant.world_body(), np.eye(4))


def test_body_points_lie_on_the_link_geometry():
    plant, sg, *_ = _panda()
    link = plant.GetBodyByName("panda_link4")
    pts = body_points(plant, sg.model_inspector(), link, 200)
    assert pts.shape == (200, 3) and np.linalg.norm(pts, axis=1).max() < 0.25


def test_drake_collision_sees_the_table_and_not_resting_contact():
    plant, sg, diagram, ctx, pctx, inst, grip, arm = _panda(with_table=True)
    check = DrakeCollision(plant, ctx, arm, [inst, grip])
    low = HOME.copy()
    low[1], low[3] = 1.2, -1.0  # the arm bent down through the table in front of the robot
    assert check(np.stack([HOME, low])).tolist() == [False, True]
