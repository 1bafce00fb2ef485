"""Every public function that takes a pose accepts a pydrake RigidTransform and a 4x4 array, with
the same result; a NaN pose, a 3x3 array and a non-pose raise an error naming the argument."""

import dataclasses
import functools

import numpy as np
import pytest
import trimesh
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.sensors import CameraInfo, ImageDepth32F

from ms_drake.execution import PrimitiveBackend
from ms_drake.experiments.heap_grasps import graspable_size
from ms_drake.experiments.picks import TASKS, build_run, plan_task, task_tool_pose
from ms_drake.geometry import PinholeCamera, Workspace, as_matrix4, as_rigid_transform
from ms_drake.grasping import GraspEvaluator, ParallelJawGrasp, SuctionGrasp
from ms_drake.grasping.physics import simulate_grasp
from ms_drake.grasping.planner import GraspPlanner
from ms_drake.grasping.samplers import (sample_antipodal_grasps, sample_antipodal_grasps_depth,
                                        sample_suction_grasps, sample_suction_grasps_depth)
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.paths import make_parser
from ms_drake.perception.masks import AmodalMasks
from ms_drake.perception.occupancy import TargetMesh
from ms_drake.planning import approach_pose, make_ik_diagram, plan_cartesian_line
from ms_drake.planning.sequences import arm_ik, plan_pick, plan_push
from ms_drake.robots import ROBOTS
from ms_drake.scenario import load_scenario
from ms_drake.scenes.bullet import BulletDropWorld
from ms_drake.station import station_objects
from ms_drake.station.labels import DepthLabelImage
from ms_drake.station.robots import add_floating_gripper, add_gripper, add_robot, floating_gripper_positions
from ms_drake.station.suction import SuctionCup
from ms_drake.types import Action, InstanceMasks, ObjectGeometry, Push
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


# name -> (argument name as the error names it, the pose, the call with that pose); the other
# arguments are fixed
CASES = {
    "GraspEvaluator.evaluate": ("X_WO", X_WO, lambda X: GraspEvaluator("soft_point").evaluate(BOX, X, JAW, 0.2)),
    "GraspEvaluator.quality (robust)": ("X_WO", X_WO, lambda X: GraspEvaluator("reach").quality(
        BOX, X, JAW, 0.2, robust_samples=3, seed=1)),
    "SuctionEvaluator.evaluate": ("X_WO", X_WO, lambda X: SuctionEvaluator().evaluate(BOX, X, CUP, 0.2)),
    "SuctionEvaluator.quality (robust)": ("X_WO", X_WO, lambda X: SuctionEvaluator().quality(
        BOX, X, CUP, 0.2, robust_samples=3, seed=1)),
    "sample_antipodal_grasps": ("X_WO", X_WO, lambda X: sample_antipodal_grasps(BOX, X, 5, seed=1)),
    "sample_suction_grasps": ("X_WO", X_WO, lambda X: sample_suction_grasps(BOX, X, 5, seed=1)),
    "sample_antipodal_grasps_depth": ("X_WC", X_WC, lambda X: sample_antipodal_grasps_depth(
        DEPTH, K, X, MASK, 5, seed=1)),
    "sample_suction_grasps_depth": ("X_WC", X_WC, lambda X: sample_suction_grasps_depth(DEPTH, K, X, MASK, 5, seed=1)),
    "simulate_grasp": ("X_WO", X_WO, _sim_outcome),
    "GraspPlanner(X_WC)": ("X_WC", X_WC, lambda X: _planner(X_WC=X).plan(
        DEPTH, InstanceMasks(MASK[None], ("box",), np.ones(1)))),
    "GraspPlanner.plan(X_WC)": ("X_WC", X_WC, lambda X: _planner().plan(
        DEPTH, InstanceMasks(MASK[None], ("box",), np.ones(1)), X_WC=X)),
    "GraspPlanner.jaw_candidates": ("X_WC", X_WC, lambda X: _planner().jaw_candidates(DEPTH, MASK, X, 1, K)),
    "ObjectGeometry.X_WO in GraspPlanner.plan": ("X_WO", X_WO, _plan_with_object_pose),
}



# ----------------------------------------------------------------------- planning, station, scenes
@functools.cache
def _panda():
    """The Panda's tcp IK on the PandaTable station (robot, grippers, table) and a reachable tool
    pose: the panda_jaw pick task's."""
    scenario = load_scenario(None, "PandaTable")
    ik, limits, q_home, keep = arm_ik(scenario, "panda")
    return ik, limits, q_home, keep, task_tool_pose(TASKS["panda_jaw"])


def _ik():
    ik, limits, q_home, _, _ = _panda()
    return ik, limits, q_home


def _ik_solve(X):
    ik, _, q_home = _ik()
    return ik.solve(X, q_seed=q_home)


def _line(X):
    ik, limits, q_home = _ik()
    q = ik.solve(_panda()[4], q_seed=q_home).q
    plan = plan_cartesian_line(ik, X, [0.0, 0.0, 0.03], q, limits)
    return plan.success, plan.status, plan.qs


def _pick_plan(plan):
    return (plan.success, plan.status, plan.X_target, sorted(plan.commands),
            None if plan.timeline is None else (plan.timeline.duration, plan.timeline.final()))


def _pick(X):
    ik, limits, q_home = _ik()
    return _pick_plan(plan_pick(ik, limits, q_home, X, "panda", "panda_jaw", "parallel_jaw", from_home=False))


def _push(X):
    ik, limits, q_home = _ik()
    return _pick_plan(plan_push(ik, limits, q_home, X, (1.0, 0.0, 0.0), 0.05, "panda", from_home=False))


def _plant_pose(add, frame):
    """World pose of `frame` after add(plant, parser) on a fresh plant."""
    plant = MultibodyPlant(0.0)
    parser = make_parser(plant)
    add(plant, parser)
    plant.Finalize()
    return plant.GetFrameByName(frame).CalcPoseInWorld(plant.CreateDefaultContext())


def _ik_diagram_root(X):
    _, plant, robot, _ = make_ik_diagram("panda", X_WR=X)
    return plant.GetFrameByName(ROBOTS["panda"].root, robot).CalcPoseInWorld(plant.CreateDefaultContext())


def _robot_root(X):
    return _plant_pose(lambda plant, parser: add_robot(plant, parser, "panda", X), ROBOTS["panda"].root)


def _gripper_body(X):
    return _plant_pose(lambda plant, parser: add_gripper(plant, parser, "parallel_jaw", plant.world_frame(), X),
                       "body")


def _floating_origin(X):
    return _plant_pose(lambda plant, parser: add_floating_gripper(plant, parser, "parallel_jaw", X),
                       "floating_origin_link")


@functools.cache
def _label_scene():
    import test_depth_labels as d

    sg = d._scene()
    labeler = d._inspector_labeler(sg)
    depth, _ = d._analytic_depth_and_labels()
    return sg, labeler, depth, d._poses(sg, labeler), d.X_WC


def _label_from(X):
    _, labeler, depth, poses, _ = _label_scene()
    return labeler.label(depth, X, poses, 0.1, 3.0)


def _label_with_pose(X):
    """The label image with the first geometry's pose given as X."""
    _, labeler, depth, poses, X_WC_labels = _label_scene()
    first = labeler.geometry_ids[0]
    return labeler.label(depth, X_WC_labels, {**poses, first: X}, 0.1, 3.0)


def _label_image_system(X):
    sg, labeler, depth, _, _ = _label_scene()
    context = sg.CreateDefaultContext()
    system = DepthLabelImage(labeler, sg.world_frame_id(), X, 0.1, 3.0)
    sctx = system.CreateDefaultContext()
    img = ImageDepth32F(depth.shape[1], depth.shape[0])
    np.asarray(img.mutable_data)[:, :, 0] = depth
    system.GetInputPort("depth_image").FixValue(sctx, img)
    system.GetInputPort("query_object").FixValue(sctx, AbstractValue.Make(sg.get_query_output_port().Eval(context)))
    return np.array(system.GetOutputPort("label_image").Eval(sctx).data)


def _suction_cup(X):
    plant = MultibodyPlant(0.0)
    cup = plant.AddRigidBody("cup", SpatialInertia.SolidBoxWithMass(0.1, 0.02, 0.02, 0.02))
    plant.Finalize()
    return SuctionCup(plant, cup, X, radius=0.01)._X_BC  # the cup frame it keeps


@functools.cache
def _bullet():
    from ms_drake.scenes.heaps import HeapParams, _DropWorld

    world = _DropWorld(load_scenario(None, "BinHeap15"), ["procedural/box_003"], HeapParams(render=False))
    return world, BulletDropWorld(world)


def _bullet_pose(X):
    _, bw = _bullet()
    bw.set_pose(0, X)
    return bw.pose(0)


def _amodal(X):
    cam = PinholeCamera(128, 96, K[0, 0], K[1, 1], K[0, 2], K[1, 2], RigidTransform(X_WC))
    return AmodalMasks(cam, [("box", 1, BOX)]).masks_for([RigidTransform(), X]).masks


@functools.cache
def _pick_run_inputs():
    scenario, plan, X_object = plan_task(TASKS["panda_jaw"], from_home=False)
    return scenario, plan, X_object


def _run_object_pose(X):
    scenario, plan, _ = _pick_run_inputs()
    run = build_run(scenario, plan, [X])
    body = run.plant.get_body(station_objects(run.plant)[0].body_index)
    return run.plant.GetDefaultFloatingBaseBodyPose(body)


def _push_outcome(X):
    """A push after which object "b" (the target, body 2) is at X: below the bin, it was removed."""
    backend = PrimitiveBackend({"a": 1, "b": 2}, Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12), tcp_offset=0.1,
                               target_id="b")
    push = Action("push", push=Push((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), "a"))
    return backend.outcome(push, None, [RigidTransform(), RigidTransform([0.0, 0.0, 0.02]), X], 0, ())


BOX_TOP = RigidTransform(RollPitchYaw(np.pi, 0, 0), [0.5, 0.0, 0.03]).GetAsMatrix4()  # a tool pose above a table
CASES.update({
    "approach_pose": ("X_WT", BOX_TOP, lambda X: approach_pose(X, 0.1)),
    "ArmIk.solve": ("X_WT", BOX_TOP, _ik_solve),
    "plan_cartesian_line": ("X_start", BOX_TOP, _line),
    "plan_pick": ("X_grasp", BOX_TOP, _pick),
    "plan_push": ("X_start", BOX_TOP, _push),
    "make_ik_diagram": ("X_WR", X_WO, _ik_diagram_root),
    "add_robot": ("X_WR", X_WO, _robot_root),
    "add_gripper": ("X_FG", X_WO, _gripper_body),
    "add_floating_gripper": ("X_WB", X_WO, _floating_origin),
    "floating_gripper_positions": ("X_WG", X_WO, floating_gripper_positions),
    "DepthLabeler.label(X_WC)": ("X_WC", RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 1]).GetAsMatrix4(),
                                 _label_from),
    "DepthLabeler.label(poses)": ("poses\\[<GeometryId value=\\d+>\\]", RigidTransform([-0.1213, 0.0037, 0.1]).GetAsMatrix4(),
                                  _label_with_pose),
    "DepthLabelImage(X_PC)": ("X_PC", RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 1]).GetAsMatrix4(),
                              _label_image_system),
    "SuctionCup(X_BC)": ("X_BC", X_WO, _suction_cup),
    "BulletDropWorld.set_pose": ("X_WB", pose_xyz_yaw(0.5, 0.0, 0.2, 0.3), _bullet_pose),
    "TargetMesh.from_object": ("X_WO", X_WO, lambda X: TargetMesh.from_object("procedural/box_003", X)),
    "AmodalMasks.masks_for": ("poses\\[1\\]", X_WO, _amodal),
    "graspable_size": ("X_WO", X_WO, lambda X: graspable_size(BOX.vertices, X, 0.1)),
    "PrimitiveBackend.outcome(poses)": ("poses\\[2\\]", RigidTransform([0.5, 0.0, -0.2]).GetAsMatrix4(),
                                        _push_outcome),
    "build_run(object_poses)": ("object_poses\\[0\\]", RigidTransform([-0.15, 0.0, 0.03]).GetAsMatrix4(),
                                _run_object_pose),
})


@pytest.mark.parametrize("name", CASES)
def test_rigid_transform_and_matrix_give_the_same_result(name):
    _, X, call = CASES[name]
    from_matrix = call(X.copy())
    assert plain(call(RigidTransform(X))) == plain(from_matrix)
    assert plain(call(X.tolist())) == plain(from_matrix)  # any 4x4 array-like


@pytest.mark.parametrize("name", CASES)
def test_a_bad_pose_raises_naming_the_argument(name):
    arg, _, call = CASES[name]
    with pytest.raises(ValueError, match=f"{arg}.*non-finite"):
        call(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match=f"{arg}.*4x4.*shape \\(3, 3\\)"):
        call(np.eye(3))
    with pytest.raises(TypeError, match=f"{arg} must be a pydrake RigidTransform or a 4x4 array, got str"):
        call("identity")


def test_the_pose_check():
    X = X_WO
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


def test_pinhole_camera_from_config_takes_the_parent_pose_as_either_type():
    from ms_drake.geometry import PinholeCamera
    from ms_drake.scenario import load_scenario

    cfg = load_scenario(None, "BinHeap15").cameras["overhead"]
    X_WP = RigidTransform([0.1, -0.2, 0.3])
    a = PinholeCamera.from_config(cfg, X_WP)
    b = PinholeCamera.from_config(cfg, X_WP.GetAsMatrix4())
    np.testing.assert_allclose(a.X_WC.GetAsMatrix4(), b.X_WC.GetAsMatrix4())
    with pytest.raises(ValueError, match="X_WP"):
        PinholeCamera.from_config(cfg, np.eye(3))
