"""Free-space linear push (Ch. 7.3.2) and the PushPlanner -- alone and wired to a station."""

import copy

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.geometry import PinholeCamera
from ms_drake.perception.masks import object_labels
from ms_drake.geometry import Workspace, world_points
from ms_drake.perception.segmentation import Segmenter
from ms_drake.pushing import PushError, PushParams, PushPlanner, obstacle_map, plan_free_space_push, plan_pushes
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import InstanceMasks, Push

CAM = PinholeCamera(640, 480, 685.0, 685.0, 319.5, 239.5, RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 0.8]))
BIN = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)
P = PushParams()


def heightfield_depth(height) -> np.ndarray:
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    d = np.full(u.shape, 0.8)
    for _ in range(12):
        d = 0.8 - height((u - CAM.cx) / CAM.fx * d, -(v - CAM.cy) / CAM.fy * d)
    return d


def box(x0, x1, y0, y1, h):
    return lambda x, y: np.where((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1), h, 0.0)


def scene(*boxes):
    d = heightfield_depth(lambda x, y: np.max([b(x, y) for b in boxes], axis=0))
    Pw = world_points(CAM, d)
    masks = []
    for b in boxes:
        masks.append(b(Pw[..., 0], Pw[..., 1]) > 0)
    return d, Pw, InstanceMasks(np.stack(masks), tuple(f"o{k}" for k in range(len(boxes))), np.ones(len(boxes)))


def check_push(push: Push, omap, c: np.ndarray):
    s, e = np.array(push.start[:2]), np.array(push.end[:2])
    d = (e - s) / np.linalg.norm(e - s)
    assert omap.signed_distance(s[None])[0] >= P.gripper_radius + P.clearance  # the gripper lands free
    assert (c - s) @ d > 0 and (e - c) @ d >= P.min_travel - 1e-9  # it starts behind and passes the centre
    dist = abs(d[0] * (c - s)[1] - d[1] * (c - s)[0])
    assert dist < 1e-6  # the push line runs through the centre
    half = np.array(BIN.size_xy) / 2
    assert np.all(np.abs(e) <= half - P.gripper_radius + 1e-9)  # the gripper stays off the walls
    assert push.start[2] == push.end[2]
    return d


def test_push_goes_through_the_centre_toward_the_most_free_point():
    d, Pw, masks = scene(box(-0.18, -0.10, -0.04, 0.04, 0.04))
    omap = obstacle_map(Pw, BIN)
    free = omap.most_free_point()
    assert free[0] > 0.0  # the most free point is on the empty side
    push = plan_free_space_push(omap, Pw[masks.masks[0]], P, "o0")
    c = Pw[masks.masks[0]][:, :2].mean(axis=0)
    direction = check_push(push, omap, c)
    want = (free - c) / np.linalg.norm(free - c)
    assert direction @ want > np.cos(np.radians(1.0))  # straight at the free point: its start is free
    assert push.object_id == "o0" and push.start[2] == pytest.approx(0.02)  # half the 4-cm height
    # The SDF: positive in free space, negative inside objects and walls.
    assert omap.signed_distance(np.array([[-0.14, 0.0], [0.3, 0.0]])).max() < 0


def test_push_turns_away_when_the_straight_start_is_blocked():
    # An object against the -x wall: behind it (toward -x) the gripper would hit the wall.
    d, Pw, masks = scene(box(-0.25, -0.17, -0.04, 0.04, 0.04))
    omap = obstacle_map(Pw, BIN)
    push = plan_free_space_push(omap, Pw[masks.masks[0]], P)
    c = Pw[masks.masks[0]][:, :2].mean(axis=0)
    direction = check_push(push, omap, c)
    want = (omap.most_free_point() - c)
    want /= np.linalg.norm(want)
    assert direction @ want < np.cos(np.radians(25.0))


def test_no_push_in_a_full_bin_and_bad_params():
    d, Pw, masks = scene(box(-0.3, 0.3, -0.3, 0.3, 0.05))
    assert plan_pushes(d, masks, CAM, BIN) == ()
    with pytest.raises(PushError, match="gripper_radius"):
        PushParams(gripper_radius=0.0)
    with pytest.raises(PushError, match="same camera"):
        plan_pushes(d, InstanceMasks(np.zeros((1, 10, 10), bool), ("a",), np.ones(1)), CAM, BIN)


def test_push_planner_alone():
    d, Pw, masks = scene(box(-0.18, -0.10, -0.04, 0.04, 0.04), box(0.05, 0.12, 0.05, 0.12, 0.03))
    planner = PushPlanner(CAM, BIN)
    ctx = planner.CreateDefaultContext()
    img = ImageDepth32F(640, 480)
    np.array(img.mutable_data, copy=False)[:, :, 0] = d
    planner.GetInputPort("depth_image").FixValue(ctx, img)
    planner.GetInputPort("masks").FixValue(ctx, masks)
    pushes = planner.GetOutputPort("pushes").Eval(ctx)
    assert [p.object_id for p in pushes] == ["o0", "o1"]
    omap = obstacle_map(Pw, BIN)
    for p, m in zip(pushes, masks.masks):
        check_push(p, omap, Pw[m][:, :2].mean(axis=0))


def test_push_planner_wired_to_a_station(bin_scenario, small_heap):
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(get_plant(station))))
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    ws = Workspace.from_scenario(s)
    planner = builder.AddSystem(PushPlanner(cam, ws))
    builder.Connect(station.GetOutputPort("overhead.label_image"), seg.GetInputPort("label_image"))
    builder.Connect(station.GetOutputPort("overhead.depth_image"), planner.GetInputPort("depth_image"))
    builder.Connect(seg.GetOutputPort("masks"), planner.GetInputPort("masks"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    masks = seg.GetOutputPort("masks").Eval(seg.GetMyContextFromRoot(ctx))
    pushes = planner.GetOutputPort("pushes").Eval(planner.GetMyContextFromRoot(ctx))
    assert 1 <= len(pushes) <= len(masks)
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(station.GetMyContextFromRoot(ctx)).data)
    Pw = world_points(cam, depth[:, :, 0].astype(float))
    omap = obstacle_map(Pw, ws)
    for p in pushes:
        m = masks.masks[masks.ids.index(p.object_id)]
        pts = Pw[m]
        check_push(p, omap, pts[np.all(np.isfinite(pts), axis=1)][:, :2].mean(axis=0))
