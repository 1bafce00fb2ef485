"""simulate_grasp: compliant hydroelastic jaws close, lift and report (one plant per call); its
CancelWeight system alone and wired to a plant."""

import numpy as np
import pytest
import trimesh

from ms_drake.grasping import GraspError, ParallelJawGrasp
from ms_drake.errors import ScenarioError
from ms_drake.grasping.physics import CancelWeight, label_grasp, simulate_grasp
from ms_drake.robots import PadConfig

BOX = trimesh.creation.box(extents=(0.04, 0.06, 0.03))
X = np.eye(4)
X[2, 3] = 0.1
CENTER = ParallelJawGrasp([0, 0, 0.1], [1, 0, 0], [0, 0, -1], 0.07)


def test_friction_limit_decides_the_lift():
    """Two pads squeezing with f_C and the station pad's mu (1.0 static) hold at most
    2 mu f_C / g = 2.04 kg."""
    light = simulate_grasp(BOX, X, CENTER, 0.8, closing_force=10.0)
    heavy = simulate_grasp(BOX, X, CENTER, 2.5, closing_force=10.0)
    assert light.success and light.contact and light.lifted > 0.07 and light.slip < 1e-3
    assert not heavy.success and heavy.contact and heavy.slip > 0.02


def test_miss_and_seeded_perturbations():
    miss = ParallelJawGrasp([0, 0, 0.2], [1, 0, 0], [0, 0, -1], 0.07)
    out = simulate_grasp(BOX, X, miss, 0.3)
    assert not out.success and not out.contact
    a = label_grasp(BOX, X, CENTER, 0.3, trials=2, seed=5)
    b = label_grasp(BOX, X, CENTER, 0.3, trials=2, seed=5)
    assert [o.slip for o in a] == [o.slip for o in b]  # same seed, same physics
    assert all(o.success for o in a)


def test_polygon_pad_and_bad_input():
    hexagon = tuple((0.01 * np.cos(t), 0.01 * np.sin(t)) for t in np.linspace(0, 2 * np.pi, 7)[:-1])
    out = simulate_grasp(BOX, X, CENTER, 0.3, pad=PadConfig(polygon=hexagon, hydroelastic_modulus=3e5))
    assert out.success
    with pytest.raises(ScenarioError, match="PadConfig.thickness"):
        PadConfig(thickness=0.0)
    open_box = BOX.copy()
    open_box.update_faces(np.arange(12) != 0)
    with pytest.raises(GraspError, match="watertight"):
        simulate_grasp(open_box, X, CENTER, 0.3)


def test_the_physics_pad_is_the_station_jaws_pad():
    from ms_drake.grasping.physics import _pad_shape
    from ms_drake.robots import ParallelJawConfig

    pad = ParallelJawConfig().pads
    shape, X_FP = _pad_shape(pad)  # the default rectangle: a box, `length` along the approach
    assert (shape.width(), shape.depth(), shape.height()) == (pad.length, pad.width, pad.thickness)
    np.testing.assert_allclose(X_FP.translation(), [0, 0, -0.5 * pad.thickness])


def test_cancel_weight_alone_pushes_up_until_its_time():
    from pydrake.multibody.tree import BodyIndex

    cancel = CancelWeight(BodyIndex(3), [0.01, 0.0, 0.02], [0.0, 0.0, -4.9], until=0.35)
    ctx = cancel.CreateDefaultContext()
    (F,) = cancel.GetOutputPort("forces").Eval(ctx)
    assert F.body_index == BodyIndex(3)
    np.testing.assert_array_equal(F.p_BoBq_B, [0.01, 0.0, 0.02])
    np.testing.assert_array_equal(F.F_Bq_W.translational(), [0.0, 0.0, 4.9])
    np.testing.assert_array_equal(F.F_Bq_W.rotational(), np.zeros(3))
    ctx.SetTime(0.35)
    (F,) = cancel.GetOutputPort("forces").Eval(ctx)
    np.testing.assert_array_equal(F.F_Bq_W.translational(), np.zeros(3))


def test_cancel_weight_wired_holds_a_free_body_until_its_time():
    """A free body with its weight cancelled for 0.2 s stays put, then falls freely."""
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
    from pydrake.multibody.tree import SpatialInertia
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1e-3), builder)
    body = plant.AddRigidBody("ball", SpatialInertia.SolidSphereWithMass(0.5, 0.02))
    plant.Finalize()
    weight = 0.5 * plant.gravity_field().gravity_vector()
    cancel = builder.AddSystem(CancelWeight(body.index(), np.zeros(3), weight, until=0.2))
    builder.Connect(cancel.get_output_port(), plant.get_applied_spatial_force_input_port())
    diagram = builder.Build()
    sim = Simulator(diagram)
    pc = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
    plant.SetFreeBodyPose(pc, body, RigidTransform([0, 0, 1.0]))
    sim.AdvanceTo(0.2)
    assert plant.EvalBodyPoseInWorld(pc, body).translation()[2] == pytest.approx(1.0, abs=1e-9)
    sim.AdvanceTo(0.4)
    fall = 0.5 * 9.81 * 0.2 ** 2  # 0.2 s of free fall
    assert 1.0 - plant.EvalBodyPoseInWorld(pc, body).translation()[2] == pytest.approx(fall, rel=0.02)
