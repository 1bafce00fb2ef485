"""The five push policies of Ch. 4 (full state and depth image) and the PushPolicySystem."""

import copy

import numpy as np
import pytest
import trimesh
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.experiments.rollout import build_search
from ms_drake.policies.bin_search import BinSearchConfig, load_bin_search_config, set_initial_conditions
from ms_drake.geometry import PinholeCamera, Workspace, world_points
from ms_drake.perception.masks import object_labels
from ms_drake.perception.segmentation import Segmenter
from ms_drake.pushing import (
    POLICIES,
    PolicyParams,
    PushError,
    PushPolicySystem,
    image_scene,
    plan_policy_push,
    state_scene,
)
from ms_drake.pushing.policies import _jaw_half, closest_pair, clusters
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import InstanceMasks, ObjectGeometry

CAM = PinholeCamera(640, 480, 685.0, 685.0, 319.5, 239.5, RigidTransform(RollPitchYaw(np.pi, 0, 0), [0, 0, 0.8]))
BIN = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)
P = PolicyParams()


def box(oid, x, y, sx=0.06, sy=0.04, sz=0.04):
    m = trimesh.creation.box([sx, sy, sz])
    X = np.eye(4)
    X[:3, 3] = [x, y, sz / 2]
    return ObjectGeometry(oid, np.asarray(m.vertices), np.asarray(m.faces), X, 0.1)


def depth_of(objects):
    """Depth image and masks of axis-aligned boxes (ObjectGeometry) seen by CAM."""
    v, u = np.mgrid[0:CAM.height, 0:CAM.width]
    d = np.full(u.shape, 0.8)
    for _ in range(12):
        x, y = (u - CAM.cx) / CAM.fx * d, -(v - CAM.cy) / CAM.fy * d
        h = np.zeros_like(d)
        for o in objects:
            lo, hi = o.vertices.min(axis=0) + o.X_WO[:3, 3], o.vertices.max(axis=0) + o.X_WO[:3, 3]
            h = np.maximum(h, np.where((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]), hi[2], 0.0))
        d = 0.8 - h
    Pw = world_points(CAM, d)
    masks = []
    for o in objects:
        lo, hi = o.vertices.min(axis=0) + o.X_WO[:3, 3], o.vertices.max(axis=0) + o.X_WO[:3, 3]
        masks.append((Pw[..., 0] >= lo[0] - 1e-3) & (Pw[..., 0] <= hi[0] + 1e-3) & (Pw[..., 1] >= lo[1] - 1e-3)
                     & (Pw[..., 1] <= hi[1] + 1e-3) & (Pw[..., 2] > 0.004))
    return d, InstanceMasks(np.stack(masks), tuple(o.id for o in objects), np.ones(len(objects)))


TOUCHING = (box("a", -0.03, 0.0), box("b", 0.03, 0.0))


def _dir(push):
    s, e = np.array(push.start[:2]), np.array(push.end[:2])
    return (e - s) / np.linalg.norm(e - s)


def _scenes(objects):
    d, masks = depth_of(objects)
    return {"state": state_scene(objects, BIN), "image": image_scene(d, masks, CAM, BIN)}


@pytest.mark.parametrize("source", ["state", "image"])
def test_clearance_of_two_touching_boxes(source):
    sc = _scenes(TOUCHING)[source]
    assert sc.clearance(0, np.array([1.0, 0.0]), 0.1) < 0.01  # into its neighbour
    assert sc.clearance(0, np.array([-1.0, 0.0]), 0.1) == pytest.approx(0.1, abs=0.005)  # away from it
    # Toward the -x wall from a box whose left face is 0.19 m from it.
    assert sc.clearance(0, np.array([-1.0, 0.0]), 0.3) == pytest.approx(0.19, abs=0.01)


@pytest.mark.parametrize("source", ["state", "image"])
def test_boundary_shear_pushes_along_the_boundary(source):
    push = plan_policy_push("boundary_shear", _scenes(TOUCHING)[source], P)
    assert push is not None and push.object_id in ("a", "b")
    d = _dir(push)
    assert abs(d[0]) < 1e-6 and abs(abs(d[1]) - 1.0) < 1e-6  # perpendicular to the line of centres
    c = np.array([-0.03, 0.0]) if push.object_id == "a" else np.array([0.03, 0.0])
    s = np.array(push.start[:2])
    assert abs((c - s)[0]) < 5e-3 and (c - s) @ d > P.gripper_radius  # through the centre (image: its pixels), from behind


@pytest.mark.parametrize("source", ["state", "image"])
def test_max_clearance_picks_the_direction_with_most_clearance(source):
    # Two boxes 6 cm apart along x (the jaw fits between them): the best ratio pushes one away
    # from the other (forward: 10 cm capped, backward: the 6-cm gap).
    objs = (box("a", 0.0, 0.0, 0.06, 0.06), box("b", -0.12, 0.0, 0.06, 0.06))
    sc = _scenes(objs)[source]
    push = plan_policy_push("max_clearance", sc, P)
    assert push is not None
    d = _dir(push)
    assert d[0] > 0.9 if push.object_id == "a" else d[0] < -0.9  # away from the other box
    # Its ratio is the largest of the 16 directions of its object.
    i = [o.id for o in sc.objects].index(push.object_id)
    best = max(sc.clearance(i, np.array([np.cos(a), np.sin(a)]), P.max_travel) /
               max(sc.clearance(i, -np.array([np.cos(a), np.sin(a)]), P.max_travel), P.resolution)
               for a in 2 * np.pi * np.arange(16) / 16)
    got = sc.clearance(i, d, P.max_travel) / max(sc.clearance(i, -d, P.max_travel), P.resolution)
    assert got == pytest.approx(best, rel=0.05)


@pytest.mark.parametrize("source", ["state", "image"])
def test_free_space_pushes_the_pair_toward_free_space(source):
    # Two touching boxes near the -x wall: free space lies toward +x.
    objs = (box("a", -0.15, 0.0), box("b", -0.09, 0.0))
    sc = _scenes(objs)[source]
    assert sorted(closest_pair(sc)) == [0, 1]
    push = plan_policy_push("free_space", sc, P)
    assert push is not None
    i = [o.id for o in sc.objects].index(push.object_id)
    want = sc.free_point(i, P) - sc.objects[i].center[:2]
    assert _dir(push) @ want / np.linalg.norm(want) > np.cos(np.radians(91))


def test_cluster_diffusion_pushes_away_from_the_cluster_centre():
    # a and b 6 cm apart (the jaw fits between them), c far off.
    objs = (box("a", -0.12, 0.0), box("b", 0.0, 0.0), box("c", 0.17, 0.12))
    sc = state_scene(objs, BIN)
    assert sorted(sorted(g) for g in clusters(sc, 3, P.cluster_distance)) == [[0, 1], [2]]
    assert sorted(sorted(g) for g in clusters(sc, 3)) == [[0, 1, 2]]
    assert sorted(sorted(g) for g in clusters(sc, 2)) == [[0, 1], [2]]
    push = plan_policy_push("cluster_diffusion", sc, P)
    assert push is not None and push.object_id in ("a", "b")
    m = np.array([-0.06, 0.0])
    c = np.array([-0.12, 0.0]) if push.object_id == "a" else np.array([0.0, 0.0])
    assert _dir(push) @ (c - m) / np.linalg.norm(c - m) > 0.99


def test_quasi_random_is_seeded_and_clipped_to_the_bin():
    sc = state_scene(TOUCHING, BIN)
    a = [plan_policy_push("quasi_random", sc, P, seed=s) for s in range(20)]
    assert a == [plan_policy_push("quasi_random", sc, P, seed=s) for s in range(20)]
    assert len({p.start for p in a}) > 10
    for p in a:
        half = np.array(BIN.size_xy) / 2 - _jaw_half(_dir(p), P)  # fingers and palm inside the walls
        assert np.all(np.abs(p.start[:2]) <= half + 1e-9) and np.all(np.abs(p.end[:2]) <= half + 1e-9)


def _object_travel(sc, push):
    """How far the push moves its object along the push (make_push's geometry)."""
    i = [o.id for o in sc.objects].index(push.object_id)
    o, d = sc.objects[i], _dir(push)
    contact = float(np.max((o.center[:2] - o.footprint) @ d)) + P.gripper_radius
    return i, d, float((np.array(push.end[:2]) - o.center[:2]) @ d) + contact


def test_quasi_random_checked_pushes_only_as_far_as_the_object_is_free():
    sc = state_scene(TOUCHING, BIN)
    checked = PolicyParams(quasi_random_checked=True)
    over = 0
    for s in range(30):
        free = plan_policy_push("quasi_random", sc, checked, seed=s)
        assert free == plan_policy_push("quasi_random", sc, checked, seed=s)
        assert free is not None  # two boxes in an open bin: some draw has room
        i, d, travel = _object_travel(sc, free)
        assert 0.0 < travel <= min(sc.clearance(i, d, 1.0), P.fixed_travel) + 1e-6
        i, d, travel = _object_travel(sc, plan_policy_push("quasi_random", sc, P, seed=s))
        over += travel > sc.clearance(i, d, 1.0) + 1e-3  # the baseline drives into the neighbour or a wall
    assert over >= 5
    with pytest.raises(PushError, match="checked_draws"):
        PolicyParams(quasi_random_checked=True, checked_draws=0)


def test_pushes_stay_in_the_bin_and_errors_name_the_choices():
    objs = (box("a", -0.2, -0.15), box("b", 0.2, 0.15), box("c", 0.0, 0.0, 0.1, 0.1, 0.05))
    for source, sc in _scenes(objs).items():
        for pol in POLICIES:
            p = plan_policy_push(pol, sc, P, seed=3)
            if p is None:
                continue
            half = np.array(BIN.size_xy) / 2 - _jaw_half(_dir(p), P)
            assert np.all(np.abs(p.end[:2]) <= half + 1e-9) and np.all(np.abs(p.start[:2]) <= half + 1e-9), \
                (source, pol)
            assert p.start[2] == p.end[2] and 0.0 < p.start[2] <= P.max_push_height
    with pytest.raises(PushError, match="quasi_random, boundary_shear, free_space, max_clearance, cluster_diffusion"):
        plan_policy_push("greedy", state_scene(objs, BIN))
    with pytest.raises(PushError, match="max_travel"):
        PolicyParams(max_travel=0.0)


def test_no_collision_free_push_when_boxed_in():
    # A box wedged between two walls and a neighbour: no direction is free for the jaw.
    objs = (box("a", -0.21, -0.17, 0.08, 0.06), box("b", -0.13, -0.17, 0.08, 0.06), box("c", -0.21, -0.11, 0.08, 0.06))
    sc = state_scene(objs, BIN)
    assert plan_policy_push("cluster_diffusion", state_scene(objs[:2], BIN), P) is None
    for pol in POLICIES:
        assert plan_policy_push(pol, sc, P) is None, pol
    # The same boxes apart: every policy plans a push, its jaw starting free of the other objects.
    apart = state_scene((objs[0], box("b", 0.05, 0.05, 0.08, 0.06), box("c", -0.15, 0.1, 0.08, 0.06)), BIN)
    for pol in POLICIES:
        p = plan_policy_push(pol, apart, P)
        assert p is not None, pol
        i = [o.id for o in apart.objects].index(p.object_id)
        assert apart.checker.gripper_free(apart, np.array(p.start[:2]), p.start[2], P.gripper_radius, skip=i), pol


@pytest.mark.parametrize("pol", POLICIES)
def test_planning_on_a_row_of_boxes(pol):
    # Six boxes in a zigzag row (their speed: docs/results/ch4_pushing.md): every plan
    # is None or a push of one of them, inside the bin, the same for the same seed.
    # Cluster diffusion finds no free push of a cluster in this touching row; the others always plan.
    objs = tuple(box(f"o{k}", -0.15 + 0.06 * k, 0.03 * (k % 2)) for k in range(6))
    for s in range(5):
        sc = state_scene(objs, BIN)
        p = plan_policy_push(pol, sc, P, seed=s)
        assert p == plan_policy_push(pol, state_scene(objs, BIN), P, seed=s)
        if pol == "cluster_diffusion":
            assert p is None
            continue
        assert p is not None and p.object_id in {o.id for o in objs}
        assert all(BIN.inside_xy(np.array([q[:2]]))[0] for q in (p.start, p.end))


def test_system_alone_state_and_image():
    d, masks = depth_of(TOUCHING)
    img = ImageDepth32F(640, 480)
    np.array(img.mutable_data, copy=False)[:, :, 0] = d
    for source in ("state", "image", "auto"):
        sysm = PushPolicySystem("boundary_shear", CAM, BIN, source=source)
        ctx = sysm.CreateDefaultContext()
        sysm.GetInputPort("depth_image").FixValue(ctx, img)
        sysm.GetInputPort("masks").FixValue(ctx, masks)
        if source != "image":
            sysm.GetInputPort("objects").FixValue(ctx, TOUCHING)
        pushes = sysm.GetOutputPort("pushes").Eval(ctx)
        assert len(pushes) == 1 and abs(_dir(pushes[0])[0]) < 1e-6
    with pytest.raises(PushError, match="choose one of"):
        PushPolicySystem("nope", CAM, BIN)
    with pytest.raises(PushError, match="source"):
        PushPolicySystem("free_space", CAM, BIN, source="lidar")


def test_system_wired_to_a_station(bin_scenario, small_heap):
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(get_plant(station))))
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    ws = Workspace.from_scenario(s)
    systems = {p: builder.AddSystem(PushPolicySystem(p, cam, ws, source="image")) for p in POLICIES}
    builder.Connect(station.GetOutputPort("overhead.label_image"), seg.GetInputPort("label_image"))
    for sysm in systems.values():
        builder.Connect(station.GetOutputPort("overhead.depth_image"), sysm.GetInputPort("depth_image"))
        builder.Connect(seg.GetOutputPort("masks"), sysm.GetInputPort("masks"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    masks = seg.GetOutputPort("masks").Eval(seg.GetMyContextFromRoot(ctx))
    planned = 0
    half = np.array(ws.size_xy) / 2 - P.gripper_radius + 1e-9
    for sysm in systems.values():
        pushes = sysm.GetOutputPort("pushes").Eval(sysm.GetMyContextFromRoot(ctx))
        assert len(pushes) <= 1
        for push in pushes:
            planned += 1
            assert push.object_id in masks.ids
            assert np.all(np.abs(np.array(push.end[:2]) - ws.center_xy) <= half)
    assert planned >= 2  # quasi_random always pushes; a 4-object heap leaves room for others


def test_push_policy_in_the_bin_search_controller(small_heap):
    params = load_bin_search_config("ch7", ["ablation.time_step=0.01"], policy="largest_push", seed=5,
                                    push_policy="max_clearance")
    system = build_search(load_scenario(None, "FloatingGripperBin"), small_heap, params)
    sysm = system.controller.GetSubsystemByName("push_planner")
    assert isinstance(sysm, PushPolicySystem) and sysm.policy == "max_clearance"
    ctx = Simulator(system.diagram).get_mutable_context()
    set_initial_conditions(system.diagram, ctx, small_heap)
    pushes = system.output(ctx, "pushes")
    masks = system.output(ctx, "masks")
    assert len(pushes) == 1 and pushes[0].object_id in masks.ids
    with pytest.raises(PushError, match="choose one of quasi_random"):
        BinSearchConfig(policy="largest_push", push_policy="sideways")


def test_state_checks_use_the_convex_hull_not_its_box():
    # A thin bar turned 45 degrees and a small box inside the bar's axis-aligned bounding box but
    # clear of the bar itself: coal's hull distance sees the gap.
    bar = box("bar", 0.0, 0.0, 0.14, 0.02, 0.03)
    R = np.array([[np.cos(np.pi / 4), -np.sin(np.pi / 4), 0], [np.sin(np.pi / 4), np.cos(np.pi / 4), 0], [0, 0, 1]])
    X = bar.X_WO.copy()
    X[:3, :3] = R
    bar = ObjectGeometry("bar", bar.vertices, bar.faces, X, 0.1)
    small = box("s", 0.035, -0.035, 0.02, 0.02, 0.03)
    sc = state_scene((bar, small), BIN)
    assert sc.checker._distance(0, 1, np.zeros(3)) > 0.02
    assert sc.clearance(1, np.array([-1.0, 0.0]), 0.1) > 0.02  # it can slide under the bar's box corner


def test_every_planner_pushes_at_least_the_minimum_height_above_the_floor():
    """A 2 cm box would be pushed at 1 cm (half its height): every planner raises the tool centre
    to MIN_PUSH_HEIGHT (the YuMi's fingertips and IK floor margin); a 5 cm one at 2.5 cm."""
    from ms_drake.pushing import MIN_PUSH_HEIGHT, PushParams, plan_pushes, push_height

    assert MIN_PUSH_HEIGHT == 0.02 and P.min_push_height == PushParams().min_push_height == MIN_PUSH_HEIGHT
    assert push_height(0.1, 0.12) == pytest.approx(0.12) and push_height(0.1, 0.15) == pytest.approx(0.125)
    assert push_height(0.1, 0.3) == pytest.approx(0.1 + P.max_push_height)
    for sz, z in ((0.02, MIN_PUSH_HEIGHT), (0.05, 0.025)):
        objs = (box("a", -0.1, 0.0, sz=sz), box("b", 0.1, 0.05, sz=sz))
        d, masks = depth_of(objs)
        pushes = [plan_policy_push(pol, sc, P, seed=1) for sc in _scenes(objs).values() for pol in POLICIES]
        pushes += list(plan_pushes(d, masks, CAM, BIN))
        pushes = [p for p in pushes if p is not None]
        assert len(pushes) >= 8
        for p in pushes:
            assert p.start[2] == p.end[2] == pytest.approx(z, abs=2e-3)
    with pytest.raises(PushError, match="min_push_height"):
        PolicyParams(min_push_height=0.04)
