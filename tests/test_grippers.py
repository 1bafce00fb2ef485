"""Gripper models: the compliant parallel jaw lifts 0.05-0.5 kg boxes, pad parameters are
configurable, the bluction tool has the reference's dimensions, every gripper welds to every arm."""

from pathlib import Path

import numpy as np
import pytest
from pydrake.geometry import Box, ProximityProperties, AddContactMaterial, AddRigidHydroelasticProperties
from pydrake.manipulation import SchunkWsgPositionController
from pydrake.math import RigidTransform
from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from ms_drake.errors import ScenarioError
from ms_drake.paths import make_parser, models_dir
from ms_drake.robots import BluctionConfig, PadConfig, ParallelJawConfig, gripper_spec
from ms_drake.station.grippers import parallel_jaw_sdf
from tools.write_models import write_environment_models, write_gripper_models
from ms_drake.robots import FLOATING_JOINTS, ROBOTS
from ms_drake.station.robots import add_arm_gripper, add_floating_gripper, add_robot, floating_gripper_positions


def box_sdf(mass, size=0.05, name="box"):
    i = mass * size * size / 6
    return f"""<?xml version="1.0"?><sdf version="1.9" xmlns:drake="http://drake.mit.edu"><model name="{name}">
<link name="{name}"><inertial><mass>{mass}</mass><inertia><ixx>{i}</ixx><iyy>{i}</iyy><izz>{i}</izz>
<ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia></inertial>
<visual name="v"><geometry><box><size>{size} {size} {size}</size></box></geometry></visual>
<collision name="c"><geometry><box><size>{size} {size} {size}</size></box></geometry>
<drake:proximity_properties><drake:rigid_hydroelastic/><drake:mu_static>0.8</drake:mu_static>
<drake:mu_dynamic>0.6</drake:mu_dynamic></drake:proximity_properties></collision></link></model></sdf>"""


def add_ground(plant):
    props = ProximityProperties()
    AddRigidHydroelasticProperties(0.01, props)
    AddContactMaterial(friction=CoulombFriction(0.8, 0.6), properties=props)
    plant.RegisterCollisionGeometry(plant.world_body(), RigidTransform([0, 0, -0.05]), Box(1, 1, 0.1),
                                    "ground", props)


def jaw_pick(mass, force_limit=30.0, sdf_text=None):
    """Floating jaw: open above a box, descend, close with a force limit, lift 10 cm, hold."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=2e-3, discrete_contact_approximation="sap",
                                                      contact_model="hydroelastic_with_fallback"), builder)
    parser = make_parser(plant)
    base, grip = add_floating_gripper(plant, parser, "parallel_jaw")
    (box,) = parser.AddModelsFromString(box_sdf(mass), "sdf")
    add_ground(plant)
    plant.Finalize()
    tcp_z = plant.GetFrameByName("tcp", grip).GetFixedPoseInBodyFrame().translation()[2]
    z_grasp = 0.025 + tcp_z  # tcp at the box centre, gripper pointing down (roll = pi)
    times = [0, 0.5, 1.0, 1.6, 2.6, 3.2]
    zs = [z_grasp + 0.1, z_grasp + 0.1, z_grasp, z_grasp, z_grasp + 0.1, z_grasp + 0.1]
    Q = np.array([[0, 0, z, np.pi, 0, 0] for z in zs]).T
    src = builder.AddSystem(TrajectorySource(
        PiecewisePolynomial.CubicShapePreserving(times, Q, zero_end_point_derivatives=True), 1))
    builder.Connect(src.get_output_port(), plant.get_desired_state_input_port(base))
    wsg = builder.AddSystem(SchunkWsgPositionController(default_force_limit=force_limit))
    builder.Connect(plant.get_state_output_port(grip), wsg.get_state_input_port())
    builder.Connect(wsg.get_generalized_force_output_port(), plant.get_actuation_input_port(grip))
    width = builder.AddSystem(TrajectorySource(
        PiecewisePolynomial.FirstOrderHold([0, 1.0, 1.5, 4], np.array([[0.09, 0.09, 0.0, 0.0]]))))
    builder.Connect(width.get_output_port(), wsg.get_desired_position_input_port())
    limit = builder.AddSystem(ConstantVectorSource([force_limit]))
    builder.Connect(limit.get_output_port(), wsg.get_force_limit_input_port())
    diagram = builder.Build()
    sim = Simulator(diagram)
    pc = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    plant.SetPositions(pc, base, Q[:, 0])
    plant.SetPositions(pc, grip, [-0.045, 0.045])
    body = plant.GetBodyByName("box", box)
    plant.SetFreeBodyPose(pc, body, RigidTransform([0, 0, 0.025]))
    sim.AdvanceTo(2.6)
    z_lifted = plant.GetFreeBodyPose(pc, body).translation()[2]
    sim.AdvanceTo(3.2)
    X_end = plant.GetFreeBodyPose(pc, body)
    X_tcp = plant.GetFrameByName("tcp", grip).CalcPoseInWorld(pc)
    return z_lifted, X_end, X_tcp, plant.GetPositions(pc, grip)


@pytest.mark.parametrize("mass", [0.05, 0.5])
def test_parallel_jaw_lifts_box(mass):
    z_lifted, X_end, X_tcp, fingers = jaw_pick(mass)
    assert z_lifted > 0.025 + 0.09, f"box not lifted: z={z_lifted:.4f}"
    assert X_end.translation()[2] > 0.025 + 0.09
    # the box stayed in hand: still centred between the pads, fingers closed on its 5 cm width
    assert np.linalg.norm(X_end.translation() - X_tcp.translation()) < 0.01
    assert 0.045 < fingers[1] - fingers[0] < 0.0505


def test_pads_are_configurable_and_polygon_pads_parse(tmp_path):
    soft = ParallelJawConfig(pads=PadConfig(hydroelastic_modulus=1e5, mu_static=0.5, mu_dynamic=0.4,
                                            relaxation_time=0.05))
    text = parallel_jaw_sdf(soft)
    assert "<drake:hydroelastic_modulus>100000</drake:hydroelastic_modulus>" in text
    assert "<drake:mu_static>0.5</drake:mu_static>" in text and "<drake:relaxation_time>0.05<" in text
    hexagon = tuple((0.012 * np.cos(a), 0.015 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False))
    poly = ParallelJawConfig(pads=PadConfig(polygon=hexagon))
    text = parallel_jaw_sdf(poly, mesh_dir=tmp_path)
    assert "drake:declare_convex" in text and list(tmp_path.glob("pad_*.obj"))
    builder = DiagramBuilder()  # with a SceneGraph, so the compliant convex pad is meshed
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3, contact_model="hydroelastic_with_fallback"),
                                 builder)
    make_parser(plant).AddModelsFromString(text, "sdf")
    plant.Finalize()
    builder.Build()
    assert plant.num_actuators() == 2
    with pytest.raises(ScenarioError, match="mu_dynamic"):
        PadConfig(mu_static=0.3, mu_dynamic=0.5)
    with pytest.raises(ScenarioError, match="convex"):
        parallel_jaw_sdf(ParallelJawConfig(pads=PadConfig(polygon=((0, 0), (0.01, 0), (0.002, 0.002), (0, 0.01)))),
                         mesh_dir=tmp_path)


def test_default_files_are_generated_from_the_dataclasses(tmp_path):
    written = write_gripper_models(tmp_path)
    assert sorted(f.name for f in written) == ["bluction.sdf", "floating_base.sdf", "parallel_jaw.sdf", "suction_cup.sdf"]
    for f in written:
        assert f.read_text() == (models_dir() / "grippers" / f.name).read_text(), \
            f"{f.name} is stale: run `python -m tools.write_models`"


def test_environment_files_are_generated_from_the_generator(tmp_path):
    written = [Path(f) for f in write_environment_models(tmp_path)]
    assert sorted(f.name for f in written) == ["bin.sdf", "shelf.sdf", "table.sdf"]
    for f in written:
        assert f.read_text() == (models_dir() / "environments" / f.name).read_text(), \
            f"{f.name} is stale: run `python -m tools.write_models`"


def test_bluction_dimensions_and_blade_rotation():
    c = BluctionConfig()
    assert (c.shaft_length, c.shaft_diameter, c.blade_width, c.blade_height, c.cup_diameter) == \
        (0.40, 0.03, 0.065, 0.075, 0.03)
    plant = MultibodyPlant(1e-3)
    (m,) = make_parser(plant).AddModels(str(models_dir() / "grippers" / "bluction.sdf"))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("body", m))
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    tcp = plant.GetFrameByName("tcp", m).CalcPoseInWorld(ctx).translation()
    assert tcp[2] == pytest.approx(0.40 + c.cup_height)
    blade = plant.GetFrameByName("blade_tcp", m)
    down = blade.CalcPoseInWorld(ctx).translation()
    plant.GetJointByName("blade_joint", m).set_angle(ctx, np.pi)
    up = blade.CalcPoseInWorld(ctx).translation()
    assert down[1] < -0.03 and up[1] > 0.03  # blade swings from below the shaft to above it
    assert plant.get_joint_actuator(plant.GetJointActuatorIndices(m)[0]).effort_limit() > 0


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_every_arm_takes_its_default_gripper(robot):
    plant = MultibodyPlant(1e-3)
    parser = make_parser(plant)
    r = add_robot(plant, parser, robot)
    grippers = {arm: add_arm_gripper(plant, parser, r, robot, arm, model_name=f"{arm}_gripper")
                for arm in ROBOTS[robot].arms}
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    for arm, g in grippers.items():
        spec = ROBOTS[robot].arms[arm]
        for j in spec.joints:
            plant.GetJointByName(j, r)
        X_FT = plant.GetFrameByName("tcp", g).CalcPose(ctx, plant.GetFrameByName(spec.flange, r))
        # the tool centre point lies ahead of the flange along the flange's outward axis
        axis = 0 if robot == "fetch" else 2
        assert X_FT.translation()[axis] > 0.08
    assert gripper_spec(ROBOTS[robot].arms[next(iter(ROBOTS[robot].arms))].default_gripper)


def test_floating_gripper_has_six_actuated_joints():
    plant = MultibodyPlant(1e-3)
    base, grip = add_floating_gripper(plant, make_parser(plant), "bluction")
    plant.Finalize()
    assert plant.num_positions(base) == 6 and plant.num_actuated_dofs(base) == 6
    names = [plant.get_joint(j).name() for j in plant.GetJointIndices(base) if plant.get_joint(j).num_positions()]
    assert names == list(FLOATING_JOINTS)
    ctx = plant.CreateDefaultContext()
    plant.SetPositions(ctx, base, [0.1, 0.2, 0.3, np.pi, 0, 0])
    X = plant.GetFrameByName("body", grip).CalcPoseInWorld(ctx)
    np.testing.assert_allclose(X.translation(), [0.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(X.rotation().matrix()[:, 2], [0, 0, -1], atol=1e-12)
    from pydrake.math import RollPitchYaw
    target = RigidTransform(RollPitchYaw(0.3, -0.7, 2.0), [0.2, -0.1, 0.4])
    plant.SetPositions(ctx, base, floating_gripper_positions(target))
    X = plant.GetFrameByName("body", grip).CalcPoseInWorld(ctx)
    np.testing.assert_allclose(X.GetAsMatrix4(), target.GetAsMatrix4(), atol=1e-12)


def test_unknown_names_list_the_valid_ones():
    plant = MultibodyPlant(1e-3)
    with pytest.raises(ScenarioError, match="valid robots: fetch, panda, yumi"):
        add_robot(plant, make_parser(plant), "ur5")
    with pytest.raises(ScenarioError, match="valid grippers: bluction, parallel_jaw, suction_cup"):
        gripper_spec("robotiq")


@pytest.mark.parametrize("thickness, limit", [(0.005, 10.0), (0.02, 30.0)])
def test_jaw_driver_grips_a_thin_part_near_its_force_limit(thickness, limit):
    """The station's jaw driver gains (JawDriver) close on a 5 mm plate with about the grasp
    models' 10 N and on a 2 cm one with 30 N, as a force-limited gripper does; Drake's WSG default
    gain (200 N/m) would squeeze them with 1 and 4 N."""
    from ms_drake.scenario import JawDriver

    d = JawDriver()
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-2, discrete_contact_approximation="sap",
                                                      contact_model="hydroelastic_with_fallback"), builder)
    parser = make_parser(plant)
    base, grip = add_floating_gripper(plant, parser, "parallel_jaw")
    sdf = box_sdf(0.1, name="plate").replace("<size>0.05 0.05 0.05</size>", f"<size>{thickness} 0.05 0.05</size>")
    (plate,) = parser.AddModelsFromString(sdf, "sdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("plate", plate), RigidTransform([0, 0, 0.3]))
    plant.Finalize()
    tcp_z = plant.GetFrameByName("tcp", grip).GetFixedPoseInBodyFrame().translation()[2]
    q_base = np.array([0, 0, 0.3 + tcp_z, np.pi, 0, 0])  # tcp at the plate's centre, pointing down
    src = builder.AddSystem(ConstantVectorSource(np.concatenate([q_base, np.zeros(6)])))
    builder.Connect(src.get_output_port(), plant.get_desired_state_input_port(base))
    wsg = builder.AddSystem(SchunkWsgPositionController(kp_command=d.kp_command, kd_command=d.kd_command,
                                                        default_force_limit=limit))
    builder.Connect(plant.get_state_output_port(grip), wsg.get_state_input_port())
    builder.Connect(wsg.get_generalized_force_output_port(), plant.get_actuation_input_port(grip))
    builder.Connect(builder.AddSystem(ConstantVectorSource([0.0])).get_output_port(),
                    wsg.get_desired_position_input_port())
    builder.Connect(builder.AddSystem(ConstantVectorSource([limit])).get_output_port(),
                    wsg.get_force_limit_input_port())
    diagram = builder.Build()
    sim = Simulator(diagram)
    pc = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    plant.SetPositions(pc, base, q_base)
    plant.SetPositions(pc, grip, [-0.03, 0.03])
    sim.AdvanceTo(1.0)
    opening = float(np.diff(plant.GetPositions(pc, grip))[0])
    force = float(wsg.get_grip_force_output_port().Eval(wsg.GetMyContextFromRoot(sim.get_context()))[0])
    assert thickness - 0.002 < opening < thickness + 0.0015, opening  # closed on the plate
    assert force == pytest.approx(min(limit, d.kp_command * opening), rel=0.05), force
    assert force > 0.85 * limit, force
    assert 200.0 * opening < 0.15 * limit  # what the WSG default gain would have squeezed with
