"""GraspPlanner LeafSystem: alone (FixValue / Eval) and in a diagram with a rendered camera."""

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo, ImageDepth32F
from test_grasp_samplers import _render_depth, overhead_camera, pose_xyz_yaw

from ms_drake.grasping import GraspEvaluator, ParallelJawGrasp, SuctionGrasp
from ms_drake.grasping.planner import GraspPlanner, ObjectGeometrySource
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.perception.segmentation import Segmenter
from ms_drake.types import InstanceMasks, ObjectGeometry

BOX = trimesh.creation.box(extents=(0.04, 0.06, 0.03))
CYL = trimesh.creation.cylinder(radius=0.02, height=0.05, sections=24)
# quality of the grasps planned on the hull of each object's visible points (box, cyl): as on the
# meshes, the 1 cm cup does not seal on the curved side
HULL_QUALITIES = {"soft_point": [1.0, 1.0], "reach": [1.0, 1.0], "suction": [1.0, 0.0]}


def _scene():
    K, X_WC = overhead_camera()
    X1 = pose_xyz_yaw(-0.03, 0.0, 0.015, 0.4)
    X2 = np.eye(4)
    X2[:3, :3] = RollPitchYaw(np.pi / 2, 0, 0).ToRotationMatrix().matrix()  # cylinder lying on its side
    X2[:3, 3] = [0.07, 0.01, 0.02]
    d1 = _render_depth(BOX, X1, K, X_WC, 96, 128)
    d2 = _render_depth(CYL, X2, K, X_WC, 96, 128)
    depth = np.minimum(d1, d2)
    masks = InstanceMasks(np.stack([np.isfinite(d1) & (d1 <= d2), np.isfinite(d2) & (d2 < d1)]),
                          ("box", "cyl"), np.ones(2))
    objects = (ObjectGeometry("box", BOX.vertices, BOX.faces, X1, 0.2),
               ObjectGeometry("cyl", CYL.vertices, CYL.faces, X2, 0.1))
    return K, X_WC, depth, masks, objects


def _image(depth):
    img = ImageDepth32F(depth.shape[1], depth.shape[0])
    img.mutable_data[:, :, 0] = np.where(np.isfinite(depth), depth, np.inf)
    return img


@pytest.mark.parametrize("model", ["soft_point", "reach", "suction"])
def test_planner_alone(model):
    K, X_WC, depth, masks, objects = _scene()
    info = CameraInfo(128, 96, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    params = {"friction": 0.8, "cup_radius": 0.01} if model == "suction" else {"friction": 0.8}
    planner = GraspPlanner(info, X_WC, model=model, num_samples=8, evaluator_params=params)
    ctx = planner.CreateDefaultContext()
    planner.GetInputPort("depth_image").FixValue(ctx, _image(depth))
    planner.GetInputPort("masks").FixValue(ctx, masks)
    planner.GetInputPort("objects").FixValue(ctx, objects)
    grasps = planner.GetOutputPort("grasps").Eval(ctx)
    assert [g.object_id for g in grasps] == ["box", "cyl"]
    for g, X in zip(grasps, (objects[0].X_WO, objects[1].X_WO)):
        # a 1 cm cup does not seal on the 2 cm radius (24-facet) cylinder's curved side
        assert g.model == model and g.quality == (0.0 if (model, g.object_id) == ("suction", "cyl") else 1.0)
        assert np.linalg.norm(np.asarray(g.center)[:2] - X[:2, 3]) < 0.04
    # the chosen grasp really is as good as claimed under the same model
    if model == "suction":
        ev, chosen = SuctionEvaluator(**params), SuctionGrasp(grasps[0].center, grasps[0].approach)
    else:
        ev, chosen = GraspEvaluator(model, **params), ParallelJawGrasp.from_grasp(grasps[0])
    assert ev.quality(BOX, objects[0].X_WO, chosen, 0.2) == 1.0
    # lifts: the nominal model's verdict on each chosen grasp (robust_samples=0 here: = quality > 0)
    for g, o in zip(grasps, objects):
        chosen = SuctionGrasp(g.center, g.approach) if model == "suction" else ParallelJawGrasp.from_grasp(g)
        assert g.lifts is (ev.quality({"box": BOX, "cyl": CYL}[g.object_id], o.X_WO, chosen, o.mass) > 0.0)
    # with robust trials, quality is their fraction and lifts still the unperturbed verdict
    robust = GraspPlanner(info, X_WC, model=model, num_samples=8, robust_samples=4, evaluator_params=params)
    for g, o in zip(robust.plan(depth, masks, objects), objects):
        chosen = SuctionGrasp(g.center, g.approach) if model == "suction" else ParallelJawGrasp.from_grasp(g)
        assert g.lifts is (ev.quality({"box": BOX, "cyl": CYL}[g.object_id], o.X_WO, chosen, o.mass, 0) > 0.0)
        assert g.quality in (0.0, 0.25, 0.5, 0.75, 1.0)
    # without meshes (hardware): hull of the visible points, still one grasp per object
    planner.GetInputPort("objects").FixValue(ctx, ())
    hw = planner.GetOutputPort("grasps").Eval(ctx)
    assert [g.object_id for g in hw] == ["box", "cyl"]
    assert [g.quality for g in hw] == HULL_QUALITIES[model]
    # an empty mask set gives no grasps
    planner.GetInputPort("masks").FixValue(ctx, InstanceMasks.empty(96, 128))
    assert planner.GetOutputPort("grasps").Eval(ctx) == ()


def test_planner_in_diagram_with_rendered_depth():
    from pydrake.geometry import (
        Box,
        ClippingRange,
        ColorRenderCamera,
        Cylinder,
        DepthRange,
        DepthRenderCamera,
        MakeRenderEngineVtk,
        RenderCameraCore,
        RenderEngineVtkParams,
    )
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.multibody.tree import SpatialInertia
    from pydrake.systems.sensors import RgbdSensor

    b = DiagramBuilder()
    plant, sg = AddMultibodyPlantSceneGraph(b, 0.0)
    sg.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
    box = plant.AddRigidBody("box", SpatialInertia.SolidBoxWithMass(0.2, 0.04, 0.06, 0.03))
    cyl = plant.AddRigidBody("cyl", SpatialInertia.SolidCylinderWithMass(0.1, 0.02, 0.05, [0, 0, 1]))
    plant.RegisterVisualGeometry(box, RigidTransform(), Box(0.04, 0.06, 0.03), "box", [0.6, 0.5, 0.4, 1])
    plant.RegisterVisualGeometry(cyl, RigidTransform(), Cylinder(0.02, 0.05), "cyl", [0.4, 0.5, 0.6, 1])
    plant.Finalize()
    info = CameraInfo(128, 96, 300.0, 300.0, 63.5, 47.5)
    core = RenderCameraCore("vtk", info, ClippingRange(0.01, 3.0), RigidTransform())
    X_WC = RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 0.5])
    cam = b.AddSystem(RgbdSensor(plant.GetBodyFrameIdOrThrow(plant.world_body().index()), X_WC,
                                 ColorRenderCamera(core, False), DepthRenderCamera(core, DepthRange(0.02, 2.0))))
    b.Connect(sg.get_query_output_port(), cam.query_object_input_port())
    labels = {int(box.index()): "box", int(cyl.index()): "cyl"}

    to_masks = b.AddSystem(Segmenter("ground_truth", label_to_id=labels, min_pixels=1))
    b.Connect(cam.label_image_output_port(), to_masks.GetInputPort("label_image"))
    geo = b.AddSystem(ObjectGeometrySource({"box": (box, BOX, 0.2, None), "cyl": (cyl, CYL, 0.1, None)}))
    b.Connect(plant.get_body_poses_output_port(), geo.get_input_port(0))
    planner = b.AddSystem(GraspPlanner(info, X_WC, model="6dfc", num_samples=6, evaluator_params={"friction": 0.8}))
    b.Connect(cam.depth_image_32F_output_port(), planner.GetInputPort("depth_image"))
    b.Connect(to_masks.GetOutputPort("masks"), planner.GetInputPort("masks"))
    b.Connect(geo.get_output_port(0), planner.GetInputPort("objects"))
    diagram = b.Build()
    ctx = diagram.CreateDefaultContext()
    pc = plant.GetMyContextFromRoot(ctx)
    plant.SetFreeBodyPose(pc, box, RigidTransform(RollPitchYaw(0, 0, 0.4), [-0.03, 0.0, 0.015]))
    plant.SetFreeBodyPose(pc, cyl, RigidTransform(RollPitchYaw(np.pi / 2, 0, 0), [0.07, 0.01, 0.02]))
    grasps = planner.GetOutputPort("grasps").Eval(planner.GetMyContextFromRoot(ctx))
    assert sorted(g.object_id for g in grasps) == ["box", "cyl"]
    centers = {g.object_id: np.asarray(g.center) for g in grasps}
    assert np.linalg.norm(centers["box"][:2] - [-0.03, 0.0]) < 0.04
    assert np.linalg.norm(centers["cyl"][:2] - [0.07, 0.01]) < 0.04
    assert all(g.quality == 1.0 and g.model == "6dfc" for g in grasps)


def test_object_geometry_source_alone():
    from pydrake.multibody.plant import MultibodyPlant
    from pydrake.multibody.tree import SpatialInertia

    plant = MultibodyPlant(0.0)
    box = plant.AddRigidBody("box", SpatialInertia.SolidBoxWithMass(0.2, 0.04, 0.06, 0.03))
    plant.Finalize()
    src = ObjectGeometrySource({"box": (box, BOX, 0.2, (0.0, 0.0, 0.001))})
    ctx = src.CreateDefaultContext()
    X = RigidTransform(RollPitchYaw(0, 0, 0.3), [0.1, -0.2, 0.05])
    poses = [RigidTransform() for _ in range(plant.num_bodies())]
    poses[int(box.index())] = X
    src.GetInputPort("body_poses").FixValue(ctx, poses)
    (g,) = src.GetOutputPort("objects").Eval(ctx)
    assert g.id == "box" and g.mass == 0.2 and g.com == (0.0, 0.0, 0.001)
    assert np.allclose(g.X_WO, X.GetAsMatrix4()) and len(g.faces) == len(BOX.faces)


def test_planner_rejects_bad_parameters():
    from ms_drake.grasping import GraspError

    info = CameraInfo(128, 96, 300.0, 300.0, 63.5, 47.5)
    with pytest.raises(GraspError, match="candidate_pool"):
        GraspPlanner(info, model="soft_point", candidate_pool=0)
    with pytest.raises(GraspError, match="jaw_margin"):
        GraspPlanner(info, model="soft_point", jaw_margin=0.2)
    with pytest.raises(GraspError, match="unknown"):
        GraspPlanner(info, model="bogus")
    with pytest.raises(GraspError, match="jaw_contact 'tip' unknown; choose one of center, pad"):
        GraspPlanner(info, model="soft_point", jaw_contact="tip")
    with pytest.raises(GraspError, match="pad_span must be >= 0"):
        GraspPlanner(info, model="soft_point", evaluator_params={"pad_span": -0.01})
