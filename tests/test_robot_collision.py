"""RobotSceneCollision (ms_drake.collision.robot): the Panda's links against a scene cloud, an
object in hand, the table."""

import numpy as np
import pytest
import trimesh

from ms_drake.collision.checker import SceneChecker
from ms_drake.collision.robot import RobotSceneCollision
from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.planning.arm_model import ArmModel
from ms_drake.planning.sequences import arm_ik
from ms_drake.scenario import load_scenario


@pytest.fixture(scope="module")
def model():
    ik, _, q_home, keep = arm_ik(load_scenario(None, "PandaTable"), "panda")
    return ArmModel(ik, points_per_body=128), q_home, keep


def _cube_cloud(centre, size=0.08, n=3000):
    return (trimesh.sample.sample_surface(trimesh.creation.box([size] * 3), n, seed=3)[0] + centre).astype(np.float32)


def test_links_collide_with_a_cloud_where_the_hand_is_and_not_elsewhere(model):
    model, home, _ = model
    p_hand = model.link_poses(home[None])["panda_link7"][0, :3, 3]
    for cloud, expect in ((_cube_cloud(p_hand), True), (_cube_cloud(p_hand + [0.0, 0.6, 0.0]), False)):
        robot = RobotSceneCollision(model, SceneChecker("sdf", cloud), table_top=-0.5)
        assert robot.collides(home[None]).tolist() == [expect]
    q2 = home.copy()
    q2[0] += np.pi / 2  # the arm swung sideways into a cube where its hand then is
    p2 = model.link_poses(q2[None])["panda_link7"][0, :3, 3]
    robot = RobotSceneCollision(model, SceneChecker("sdf", _cube_cloud(p2)), table_top=-0.5)
    assert robot.collides(np.stack([home, q2])).tolist() == [False, True]
    with pytest.raises(CollisionNetError, match="no points in the arm model"):
        RobotSceneCollision(model, SceneChecker("sdf", _cube_cloud(p2)), bodies=["panda_link9"])


def test_table_and_object_in_hand(model):
    model, home, _ = model
    far = _cube_cloud(np.array([2.0, 2.0, 0.3]))
    X_WL = model.link_poses(home[None])["panda_link7"][0]
    robot = RobotSceneCollision(model, SceneChecker("sdf", far), table_top=X_WL[2, 3] - 0.02)
    assert robot.collides(home[None]).tolist() == [True]  # link7's points reach below that "table"
    robot = RobotSceneCollision(model, SceneChecker("sdf", far), table_top=0.0)
    assert robot.collides(home[None]).tolist() == [False]
    # an object held 0.5 m below link7 meets a cube there
    target = X_WL[:3, 3] + [0.0, 0.0, -0.5]
    robot = RobotSceneCollision(model, SceneChecker("sdf", _cube_cloud(target)), table_top=None)
    assert robot.collides(home[None]).tolist() == [False]
    X_WO = np.eye(4)
    X_WO[:3, 3] = target
    robot.attach("bar", _cube_cloud(np.zeros(3), 0.085, 500), "panda_link7", np.linalg.inv(X_WL) @ X_WO)
    assert robot.collides(home[None]).tolist() == [True]  # its faces 2.5 mm off the cube's
    robot.detach("bar")
    assert robot.collides(home[None]).tolist() == [False]
    with pytest.raises(CollisionNetError, match="not a body of the arm model"):
        robot.attach("bar", _cube_cloud(np.zeros(3)), "world", np.eye(4))


def test_network_path_answers_as_the_per_link_path(tmp_path):
    """The network's one-graph path (torch FK, table test first, all links in one pass) gives the
    per-link path's probabilities on MPPI's waypoints in a real scene with the shipped weights, so
    MPPI chooses the same waypoint; with an object in hand too."""
    from ms_drake.collision.checker import default_weights, load_collision_net  # noqa: PLC0415
    from ms_drake.experiments.mppi_bench import mppi_problem  # noqa: PLC0415
    from ms_drake.planning.mppi import MppiParams, mppi_step, rollouts  # noqa: PLC0415

    net = load_collision_net(default_weights("net"), "net")[0]
    robot, q0, goal, lo, hi, keep = mppi_problem(100000, "net", tmp_path, net)
    _, way = rollouts(q0, goal, lo, hi, MppiParams(), np.random.default_rng(0))
    Q = way.reshape(-1, 7)
    fast, slow = robot.probabilities(Q), robot.per_link_probabilities(Q)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-6)
    assert ((fast > 0.5) == (slow > 0.5)).all() and 0.05 < (fast > 0.5).mean() < 0.95
    net_only = RobotSceneCollision(robot.model, robot.checker, table_top=None)  # every query to the network
    p_net = net_only.probabilities(Q)
    np.testing.assert_allclose(p_net, net_only.per_link_probabilities(Q), rtol=0, atol=1e-6)
    assert 0 < (p_net > 0.5).sum() < len(Q)
    params = MppiParams(seed=5)
    a = mppi_step(q0, goal, robot.collides, lo, hi, params, np.random.default_rng(5))
    b = mppi_step(q0, goal, lambda qs: robot.per_link_probabilities(qs) > 0.5, lo, hi, params,
                  np.random.default_rng(5))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1]["path"], b[1]["path"])
    block = (trimesh.sample.sample_surface(trimesh.creation.box([0.05, 0.05, 0.12]), 400, seed=1)[0]).astype(np.float32)
    X_HO = np.eye(4)
    X_HO[2, 3] = 0.15
    robot.attach("block", block, "body", X_HO)
    held_fast, held_slow = robot.probabilities(Q), robot.per_link_probabilities(Q)
    np.testing.assert_allclose(held_fast, held_slow, rtol=0, atol=1e-6)
    assert (held_fast >= fast - 1e-12).all() and (held_fast > fast + 1e-3).any()  # the block adds collisions
    robot.detach("block")
    np.testing.assert_array_equal(robot.probabilities(Q), fast)
