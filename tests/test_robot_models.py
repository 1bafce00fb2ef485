"""Converted robot models: they parse with package:// URIs, keep limits, and match the source FK.

The reference poses in tests/data/fk_<robot>.json were computed from the SOURCE models (MuJoCo for
the MJCF sources, Drake's URDF parser for the Panda URDF) by tools/convert_robots.py;
this test needs only our converted files.
"""

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JointIndex

from ms_drake.paths import make_parser, models_dir

DATA = Path(__file__).parent / "data"
ROBOTS = ["panda", "yumi", "fetch"]
JOINTS = {  # joint types of each model, with the floating base that Finalize adds
    "panda": {"revolute": 7, "quaternion_floating": 1},
    "yumi": {"revolute": 14, "quaternion_floating": 1},
    "fetch": {"revolute": 10, "prismatic": 3, "weld": 1, "quaternion_floating": 1},
}


def _load(robot):
    plant = MultibodyPlant(0.0)
    parser = make_parser(plant)
    (model,) = parser.AddModels(str(models_dir() / "robots" / robot / f"{robot}.sdf"))
    plant.Finalize()
    return plant, model


@pytest.mark.parametrize("robot", ROBOTS)
def test_fk_matches_source(robot):
    ref = json.loads((DATA / f"fk_{robot}.json").read_text())
    plant, model = _load(robot)
    root = plant.GetFrameByName(ref["root"], model)
    checked = 0
    for cfg in ref["configs"]:
        ctx = plant.CreateDefaultContext()
        for name, value in cfg["q"].items():
            joint = plant.GetJointByName(name, model)
            q = plant.GetPositions(ctx).copy()
            q[joint.position_start()] = value
            plant.SetPositions(ctx, q)
        for frame_name, X in cfg["X_root_frame"].items():
            X_ref = np.array(X)
            X_ours = plant.GetFrameByName(frame_name, model).CalcPose(ctx, root).GetAsMatrix4()
            err_p = np.linalg.norm(X_ours[:3, 3] - X_ref[:3, 3])
            err_R = np.linalg.norm(X_ours[:3, :3] - X_ref[:3, :3])
            assert err_p < ref["tolerance_m"], f"{robot} {frame_name} q={cfg['q']}: {err_p * 1e3:.3f} mm"
            assert err_R < 1e-3, f"{robot} {frame_name}: rotation error {err_R:.2e}"
            checked += 1
    assert checked >= 4 * 8


@pytest.mark.parametrize("robot", ROBOTS)
def test_model_is_well_formed(robot):
    plant, model = _load(robot)
    text = (models_dir() / "robots" / robot / f"{robot}.sdf").read_text()
    assert "package://drake_models" not in text and "package://ms_drake_models/robots/" in text
    assert ".stl" not in text.lower() and ".dae" not in text.lower()
    assert "drake:declare_convex" in text
    assert (models_dir() / "robots" / robot / "NOTICE").read_text().count("Licen") >= 1
    # the model's joints (Finalize adds the floating base); every revolute and prismatic joint has
    # finite velocity limits
    joints = [plant.get_joint(JointIndex(i)) for i in range(plant.num_joints())]
    assert Counter(j.type_name() for j in joints) == JOINTS[robot]
    for j in joints:
        assert j.num_velocities() == {"revolute": 1, "prismatic": 1, "weld": 0, "quaternion_floating": 6}[j.type_name()]
    for j in (j for j in joints if j.type_name() in ("revolute", "prismatic")):
        assert np.isfinite(j.velocity_upper_limits()[0]), j.name()
    # positive mass and a valid spatial inertia on every body
    ctx = plant.CreateDefaultContext()
    total = sum(plant.get_body(b).get_mass(ctx) for b in plant.GetBodyIndices(model))
    assert total > 5.0
    for b in plant.GetBodyIndices(model):
        body = plant.get_body(b)
        assert body.get_mass(ctx) > 0 and body.CalcSpatialInertiaInBodyFrame(ctx).IsPhysicallyValid(), body.name()


def test_arm_joint_counts():
    plant, _ = _load("yumi")
    assert plant.num_positions() == 7 + 7 + 7  # two arms + floating base quaternion/position
    plant, _ = _load("fetch")
    names = {plant.get_joint(JointIndex(i)).name() for i in range(plant.num_joints())}
    for n in ["base_x", "base_y", "base_yaw", "torso_lift_joint", "head_pan_joint", "head_tilt_joint",
              "shoulder_pan_joint", "wrist_roll_joint"]:
        assert n in names


@pytest.mark.parametrize("robot", ROBOTS)
def test_robot_renders_with_vtk(robot):
    """Cameras render the robots: Drake's VTK engine needs OBJ normals; the robot fills pixels."""
    from pydrake.geometry import (ClippingRange, DepthRange, DepthRenderCamera, MakeRenderEngineVtk,
                                  RenderCameraCore, RenderEngineVtkParams, SceneGraph)
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.sensors import CameraInfo, RgbdSensor

    from ms_drake.robots import ROBOTS as SPECS
    from ms_drake.station.robots import add_arm_gripper, add_robot

    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlantSceneGraph(builder, 0.0)
    parser = make_parser(plant)
    r = add_robot(plant, parser, robot)
    for arm in SPECS[robot].arms:
        add_arm_gripper(plant, parser, r, robot, arm, model_name=f"{arm}_gripper")
    plant.Finalize()
    sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    eye, target = np.array([2.5, 0.0, 0.6]), np.array([0.0, 0.0, 0.5])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0, 0, 1])
    x /= np.linalg.norm(x)
    X_WC = RigidTransform(RotationMatrix(np.stack([x, np.cross(z, x), z], 1)), eye)
    core = RenderCameraCore("vtk", CameraInfo(64, 64, np.pi / 3), ClippingRange(0.05, 10), RigidTransform())
    cam = builder.AddSystem(RgbdSensor(SceneGraph.world_frame_id(), X_WC, DepthRenderCamera(core, DepthRange(0.05, 10))))
    builder.Connect(sg.get_query_output_port(), cam.query_object_input_port())
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    depth = cam.depth_image_32F_output_port().Eval(cam.GetMyContextFromRoot(ctx)).data
    assert np.isfinite(depth).mean() > 0.02  # the robot covers part of the image


def test_robot_converter_is_importable_and_checks_its_arguments(capsys):
    """tools/convert_robots.py (dev time, not installed) loads without its converter-only
    dependencies and refuses an unknown robot with an argparse error."""
    from tools.convert_robots import main

    with pytest.raises(SystemExit) as e:
        main(["--robot", "ur5"])
    assert e.value.code == 2
    assert "invalid choice: 'ur5'" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["floating_base", "parallel_jaw", "suction_cup", "bluction"])
def test_self_contained_model_parses_from_text_as_from_file(name):
    """station.robots._add_file parses self-contained SDFs from their text (sdformat rebuilds its
    schema per file read): the same bodies, joints, masses, geometries and frames as the file."""
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
    from pydrake.systems.framework import DiagramBuilder

    from ms_drake.station.robots import _add_file

    def build(text):
        builder = DiagramBuilder()
        plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.001), builder)
        parser = make_parser(plant)
        path = models_dir() / "grippers" / f"{name}.sdf"
        model = _add_file(parser, path) if text else parser.AddModels(str(path))[0]
        plant.Finalize()
        inspector = sg.model_inspector()
        bodies = [(plant.get_body(b).name(), round(plant.get_body(b).default_mass(), 9))
                  for b in plant.GetBodyIndices(model)]
        joints = sorted((plant.get_joint(j).name(), plant.get_joint(j).type_name()) for j in plant.GetJointIndices(model))
        geoms = sorted((inspector.GetName(g), inspector.GetShape(g).__class__.__name__)
                       for b in plant.GetBodyIndices(model) for g in plant.GetCollisionGeometriesForBody(plant.get_body(b)))
        frames = sorted(plant.get_frame(f).name() for f in plant.GetFrameIndices(model))
        return bodies, joints, geoms, frames

    from_text, from_file = build(True), build(False)
    assert from_text == from_file
    assert from_text[0]  # the model has bodies
