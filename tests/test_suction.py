"""SuctionCup: holds a box when sealed on a flat face within the gap, not when tilted / far /
off, keeps its full pull while the lip reaches a tilted face and leaks beyond, and releases on
command (unit: FixValue + Eval; diagram: pick and release with a floating cup). A box held by its
vertical face on the Fetch: tests/test_shelf_suction.py."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from ms_drake.paths import make_parser
from ms_drake.station.robots import add_floating_gripper, add_gripper
from ms_drake.station.suction import BODY_INDEX, GAP, HOLDING, SuctionCup, add_suction_cup
from test_grippers import add_ground, box_sdf


def plate_sdf(mass=0.08, size=(0.08, 0.08, 0.004)):
    """A thin plate (a packaged object's backing): 8 x 8 cm, 4 mm thick."""
    return box_sdf(mass).replace("0.05 0.05 0.05", " ".join(map(str, size)))


def _scene(X_W_cup: RigidTransform, box_xyz=(0, 0, 0.025), sdf=None):
    """Suction cup welded at X_W_cup (its body frame) above a free 5 cm box (or the model `sdf`,
    its body named box); returns evaluated inputs."""
    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
    parser = make_parser(plant)
    cup = add_gripper(plant, parser, "suction_cup", plant.world_frame(), X_W_cup)
    (box,) = parser.AddModelsFromString(sdf or box_sdf(0.2), "sdf")
    plant.Finalize()
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    body = plant.GetBodyByName("box", box)
    plant.SetFreeBodyPose(pc, body, RigidTransform(list(box_xyz)))
    poses = plant.get_body_poses_output_port().Eval(pc)
    query = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
    frame = plant.GetFrameByName("tcp", cup)
    system = SuctionCup(plant, frame.body(), frame.GetFixedPoseInBodyFrame(), radius=0.015)
    return system, poses, query, int(body.index())


def _eval(system, poses, query, on):
    ctx = system.CreateDefaultContext()
    system.GetInputPort("suction").FixValue(ctx, [1.0 if on else 0.0])
    system.GetInputPort("body_poses").FixValue(ctx, poses)
    system.GetInputPort("query_object").FixValue(ctx, query)
    return system.GetOutputPort("suction_state").Eval(ctx), system.GetOutputPort("spatial_forces").Eval(ctx)


def _cup_above(gap, tilt=0.0, dx=0.0):
    lip = 0.112  # suction_cup tcp along z
    R = RollPitchYaw(np.pi + tilt, 0, 0)
    # place the cup so that its lip centre is `gap` above the box top (z = 0.05)
    X = RigidTransform(R, [dx, 0, 0.05 + gap])
    return X @ RigidTransform([0, 0, -lip])


def test_holds_when_sealed_on_flat_face():
    system, poses, query, box = _scene(_cup_above(0.002))
    state, forces = _eval(system, poses, query, on=True)
    assert state[HOLDING] == 1 and state[BODY_INDEX] == box and state[GAP] == pytest.approx(0.002, abs=1e-6)
    assert len(forces) == 2
    on_box = next(f for f in forces if int(f.body_index) == box)
    f = on_box.F_Bq_W.translational()
    assert f[2] > 0 and np.linalg.norm(f[:2]) < 1e-9  # pulls the box up, towards the cup
    assert np.linalg.norm(f) == pytest.approx(40.0)  # the full vacuum pull: the lip reaches the face all round
    total = sum(x.F_Bq_W.translational() for x in forces)
    np.testing.assert_allclose(total, 0, atol=1e-9)  # action = reaction


@pytest.mark.parametrize("press", [0.001, 0.0025, 0.0035])
def test_holds_a_thin_plate_with_the_lip_pressed_into_it(press):
    """The lip pressed 1-3.5 mm into a 4 mm plate (top at z = 0.05): sealed, pulling it up. The
    distance's gradient at the cup centre points to the plate's far side once the centre is past
    the plate's middle (2 mm); the seal's normal is read from outside the face."""
    system, poses, query, plate = _scene(_cup_above(-press), box_xyz=(0, 0, 0.048), sdf=plate_sdf())
    state, forces = _eval(system, poses, query, on=True)
    assert state[HOLDING] == 1 and state[BODY_INDEX] == plate
    on_plate = next(f for f in forces if int(f.body_index) == plate)
    assert on_plate.F_Bq_W.translational()[2] == pytest.approx(40.0)


@pytest.mark.parametrize("case", ["off", "too_far", "tilted", "over_edge"])
def test_no_hold(case):
    X = {"off": _cup_above(0.001), "too_far": _cup_above(0.02), "tilted": _cup_above(0.001, tilt=0.6),
         "over_edge": _cup_above(0.001, dx=0.03)}[case]
    system, poses, query, _ = _scene(X)
    state, forces = _eval(system, poses, query, on=case != "off")
    assert state[HOLDING] == 0 and state[BODY_INDEX] == -1 and np.isnan(state[GAP])
    assert len(forces) == 0


@pytest.mark.parametrize("gap, tilt, fraction", [(0.001, 0.2, 1.0), (0.007, 0.2, 0.5), (0.009, 0.2, 0.0)])
def test_pull_while_the_lip_reaches_a_tilted_face(gap, tilt, fraction):
    """A face tilted 11.5 degrees against the cup: the far lip stands off gap + r sin(tilt); the full
    40 N while that is within max_gap (8 mm), half at 10 mm, none beyond 12 mm (the seal leaks)."""
    system, poses, query, box = _scene(_cup_above(gap, tilt=tilt))
    state, forces = _eval(system, poses, query, on=True)
    far = gap + 0.015 * np.sin(tilt)
    assert system.pull_fraction(far) == pytest.approx(fraction, abs=0.02)
    if fraction == 0.0:
        assert state[HOLDING] == 0 and len(forces) == 0
        return
    on_box = next(f for f in forces if int(f.body_index) == box)
    assert state[HOLDING] == 1 and np.linalg.norm(on_box.F_Bq_W.translational()) == pytest.approx(40.0 * fraction, rel=0.03)


def test_bad_parameters_name_the_value():
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), DiagramBuilder())
    cup = add_gripper(plant, make_parser(plant), "suction_cup", plant.world_frame(), RigidTransform())
    plant.Finalize()
    frame = plant.GetFrameByName("tcp", cup)
    with pytest.raises(ValueError, match="seal_tolerance"):
        SuctionCup(plant, frame.body(), frame.GetFixedPoseInBodyFrame(), radius=0.015, seal_tolerance=0.0)


def test_pick_and_release_in_diagram():
    builder = DiagramBuilder()
    plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=2e-3, discrete_contact_approximation="sap",
                                                      contact_model="hydroelastic_with_fallback"), builder)
    parser = make_parser(plant)
    base, grip = add_floating_gripper(plant, parser, "suction_cup")
    (box,) = parser.AddModelsFromString(box_sdf(0.3), "sdf")
    add_ground(plant)
    plant.Finalize()
    zc = 0.05 + plant.GetFrameByName("tcp", grip).GetFixedPoseInBodyFrame().translation()[2]
    times = [0, 0.5, 1.0, 1.5, 2.5, 4.0]
    zs = [zc + 0.1, zc + 0.1, zc - 0.002, zc - 0.002, zc + 0.1, zc + 0.1]
    Q = np.array([[0, 0, z, np.pi, 0, 0] for z in zs]).T
    src = builder.AddSystem(TrajectorySource(
        PiecewisePolynomial.CubicShapePreserving(times, Q, zero_end_point_derivatives=True), 1))
    builder.Connect(src.get_output_port(), plant.get_desired_state_input_port(base))
    cup = add_suction_cup(builder, plant, sg, grip, radius=0.015)
    command = builder.AddSystem(TrajectorySource(
        PiecewisePolynomial.ZeroOrderHold([0, 1.2, 3.0, 5.0], np.array([[0.0, 1.0, 0.0, 0.0]]))))
    builder.Connect(command.get_output_port(), cup.GetInputPort("suction"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    plant.SetPositions(pc, base, Q[:, 0])
    body = plant.GetBodyByName("box", box)
    plant.SetFreeBodyPose(pc, body, RigidTransform([0.004, 0, 0.025]))
    state = cup.GetOutputPort("suction_state")
    sim.AdvanceTo(1.1)
    assert state.Eval(cup.GetMyContextFromRoot(ctx))[HOLDING] == 0  # vacuum still off
    sim.AdvanceTo(2.9)
    assert plant.GetFreeBodyPose(pc, body).translation()[2] > 0.025 + 0.09  # lifted 10 cm
    s = state.Eval(cup.GetMyContextFromRoot(ctx))
    assert s[HOLDING] == 1 and s[BODY_INDEX] == int(body.index())
    sim.AdvanceTo(4.0)  # vacuum off at t = 3: the box falls back to the ground
    assert plant.GetFreeBodyPose(pc, body).translation()[2] < 0.03
    assert state.Eval(cup.GetMyContextFromRoot(ctx))[HOLDING] == 0

