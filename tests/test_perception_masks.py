"""Perception basics: AmodalMasks, TargetAmodalMask, silhouettes, point clouds — alone and wired
(TargetAmodalMask in the oracle's bin-search controller)."""

import copy

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageLabel16I

from ms_drake.geometry import PinholeCamera, silhouette
from ms_drake.perception.masks import AmodalMasks, TargetAmodalMask, make_amodal_masks, object_labels
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.point_cloud import add_point_cloud, finite_points
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.types import InstanceMasks


def _label_image(arr):
    img = ImageLabel16I(arr.shape[1], arr.shape[0])
    np.array(img.mutable_data, copy=False)[:, :, 0] = arr
    return img


def test_amodal_masks_alone_match_a_box_projection():
    import trimesh

    cam = PinholeCamera(100, 80, 100.0, 100.0, 49.5, 39.5, RigidTransform([0, 0, -1.0]))  # looks along +z
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    system = AmodalMasks(cam, [("box", 0, box)])
    ctx = system.CreateDefaultContext()
    system.get_input_port(0).FixValue(ctx, AbstractValue.Make([RigidTransform()]))
    m = system.get_output_port(0).Eval(ctx).masks[0]
    # The front face at 0.9 m spans 0.2/0.9*100 = 22.2 px: ~22 x 22 pixels around the centre.
    assert 20 * 20 <= m.sum() <= 25 * 25
    assert m[40, 50] and not m[5, 5]


def test_masks_wired_in_a_station(bin_scenario):
    s = copy.deepcopy(bin_scenario)
    s.objects.count = 3
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    plant = get_plant(station)
    labels = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(plant)))
    builder.Connect(station.GetOutputPort("overhead.label_image"), labels.GetInputPort("label_image"))
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    amodal = builder.AddSystem(make_amodal_masks(plant, cam))
    builder.Connect(station.GetOutputPort("body_poses"), amodal.get_input_port(0))
    cloud = add_point_cloud(builder, station, "overhead", s.cameras["overhead"])
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    modal = labels.GetOutputPort("masks").Eval(labels.GetMyContextFromRoot(ctx))
    full = amodal.get_output_port(0).Eval(amodal.GetMyContextFromRoot(ctx))
    assert len(modal) == 3 and len(full) == 3
    for i, name in enumerate(full.ids):
        j = modal.ids.index(name)
        inter = (modal.masks[j] & full.masks[i]).sum()
        assert inter >= 0.97 * modal.masks[j].sum()  # visible part lies inside the silhouette
    pts = finite_points(cloud.get_output_port().Eval(cloud.GetMyContextFromRoot(ctx)))
    assert len(pts) > 100000
    # World-frame cloud: the bin floor (z = 0) and objects above it, nothing far below.
    assert np.percentile(pts[:, 2], 5) > -0.1 and np.percentile(pts[:, 2], 50) < 0.3


def test_silhouette_equals_rendering_the_object_alone(bin_scenario):
    for name in ["procedural/box_000", "procedural/cylinder_001", "procedural/packaged_002"]:
        s = copy.deepcopy(bin_scenario)
        s.objects.count = 0
        s.objects.names = [name]
        station = MakeStation(s)
        ctx = station.CreateDefaultContext()
        plant = get_plant(station)
        (o,) = station_objects(plant)
        labels = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[:, :, 0]
        rendered = labels == int(o.body_index)
        m = make_amodal_masks(plant, PinholeCamera.from_config(s.cameras["overhead"]))
        proj = m.masks_for(station.GetOutputPort("body_poses").Eval(ctx)).masks[0]
        iou = (rendered & proj).sum() / (rendered | proj).sum()
        assert iou > 0.95, (name, iou)


def test_silhouette_ignores_geometry_behind_the_camera():
    cam = PinholeCamera(50, 50, 50.0, 50.0, 24.5, 24.5, RigidTransform())
    v = np.array([[0, 0, -1.0], [0.1, 0, -1.0], [0, 0.1, -1.0]])
    assert not silhouette(cam, v, np.array([[0, 1, 2]])).any()


def test_target_amodal_mask_alone_picks_the_target_or_nothing():
    masks = np.zeros((2, 6, 8), bool)
    masks[0, 1:3, 1:3] = True
    masks[1, 3:5, 4:7] = True
    system = TargetAmodalMask("t")
    ctx = system.CreateDefaultContext()
    system.get_input_port().FixValue(ctx, InstanceMasks(masks, ("a", "t"), np.ones(2)))
    np.testing.assert_array_equal(system.get_output_port().Eval(ctx), masks[1])
    system.get_input_port().FixValue(ctx, InstanceMasks(masks[:1], ("a",), np.ones(1)))
    out = system.get_output_port().Eval(ctx)
    assert out.shape == (6, 8) and not out.any()  # the target was removed


def test_target_amodal_mask_wired_in_the_oracle_controller(small_heap):
    """The oracle's bin-search diagram: station body_poses -> AmodalMasks -> TargetAmodalMask ->
    PolicySelector.target_amodal; the mask is the target's silhouette at its pose in the plant."""
    from ms_drake.experiments.rollout import build_search
    from ms_drake.policies.bin_search import load_bin_search_config, set_initial_conditions
    from ms_drake.scenario import load_scenario

    system = build_search(load_scenario(None, "FloatingGripperBin"), small_heap,
                          load_bin_search_config("ch7", policy="oracle", seed=5))
    subsystems = {type(sub).__name__: sub for sub in system.controller.GetSystems()}
    pick, amodal, selector = subsystems["TargetAmodalMask"], subsystems["AmodalMasks"], subsystems["PolicySelector"]
    assert pick.target_id == system.target_id
    ctx = system.diagram.CreateDefaultContext()
    set_initial_conditions(system.diagram, ctx, small_heap)
    mask = pick.get_output_port().Eval(pick.GetMyContextFromRoot(ctx))
    full = amodal.get_output_port().Eval(amodal.GetMyContextFromRoot(ctx))
    assert mask.shape == (480, 640) and mask.dtype == bool and mask.sum() > 500
    np.testing.assert_array_equal(mask, full.masks[full.ids.index(system.target_id)])
    np.testing.assert_array_equal(selector.GetInputPort("target_amodal").Eval(selector.GetMyContextFromRoot(ctx)), mask)
    visible = system.output(ctx, "masks")  # the label image's masks: the target's visible part lies inside
    seen = visible.masks[visible.ids.index(system.target_id)]
    assert (seen & mask).sum() >= 0.97 * seen.sum() > 0
    # the target moved out of the camera's view (behind it): an empty mask of the image's size
    plant = system.plant
    body = next(o for o in station_objects(plant) if o.model_name == system.target_id).body_index
    plant.SetFreeBodyPose(plant.GetMyMutableContextFromRoot(ctx), plant.get_body(body),
                          RigidTransform([0.0, 0.0, 5.0]))
    gone = pick.get_output_port().Eval(pick.GetMyContextFromRoot(ctx))
    assert gone.shape == (480, 640) and not gone.any()
