"""Bin selectors (Ch. 7.4), X-Ray (Ch. 8.4), the oracle and the PolicySelector system."""

import copy

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from ms_drake.objects import get_object
from ms_drake.geometry import PinholeCamera
from ms_drake.perception.masks import object_labels
from ms_drake.perception.occupancy import OccupancyEstimator, TargetBox
from ms_drake.geometry import Workspace
from ms_drake.perception.segmentation import Segmenter
from ms_drake.perception.target import TargetDetector
from ms_drake.policies import (POLICIES, PolicyError, PolicySelector, SelectorParams, priority_largest,
                               priority_xray, select_action, termination, xray_scores)
from ms_drake.pushing import PushPlanner
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.types import Action, ActionOutcome, Grasp, InstanceMasks, OccupancyMap, Push, TargetEstimate

H, W = 60, 80


def masks():
    """Four objects: the target t (small), big, mid, small."""
    m = np.zeros((4, H, W), bool)
    m[0, 5:10, 5:10] = True  # t: 25 px
    m[1, 20:50, 0:40] = True  # big: 1200 px
    m[2, 0:20, 50:80] = True  # mid: 600 px
    m[3, 40:55, 60:75] = True  # small: 225 px
    return InstanceMasks(m, ("t", "big", "mid", "small"), np.ones(4))


M = masks()
TARGET = TargetEstimate(True, M.masks[0], 0.95, 0)
HIDDEN = TargetEstimate(False, np.zeros((H, W), bool))


def grasps(**q):
    return tuple(Grasp("suction", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), quality=v, object_id=k) for k, v in q.items())


PUSHES = tuple(Push((0.0, 0.0, 0.01), (0.1, 0.0, 0.01), k) for k in ("t", "big", "mid", "small"))


def outcome(kind, removed="", success=True, oid="big", message=""):
    a = Action(kind, grasp=grasps(**{oid: 0.5})[0] if kind == "grasp" else None,
               push=PUSHES[1] if kind == "push" else None)
    return ActionOutcome(a, success, removed, message)


def chosen(action):
    return (action.grasp or action.push).object_id if action.kind in ("grasp", "push") else action.reason


def test_largest_first_with_and_without_pushing():
    # The target is grasped first when its grasp exceeds t_thresh.
    assert chosen(select_action("largest", M, TARGET, grasps(t=0.2, big=0.9))) == "t"
    # Otherwise the others by visible area.
    assert chosen(select_action("largest", M, TARGET, grasps(t=0.1, big=0.5, mid=0.9))) == "big"
    assert chosen(select_action("largest", M, TARGET, grasps(t=0.1, big=0.1, mid=0.2))) == "mid"
    # With pushing, non-targets need t_high = 0.3: big (0.25) is skipped for mid (0.35).
    assert chosen(select_action("largest_push", M, TARGET, grasps(t=0.1, big=0.25, mid=0.35))) == "mid"
    # No grasp qualifies: push the first object of the priority list (the target) ...
    a = select_action("largest_push", M, TARGET, grasps(t=0.1, big=0.25), PUSHES)
    assert a.kind == "push" and chosen(a) == "t"
    # ... or, without a valid push on it, the next one; without pushing the search ends.
    assert chosen(select_action("largest_push", M, TARGET, grasps(t=0.1), PUSHES[2:])) == "mid"
    assert select_action("largest", M, TARGET, grasps(t=0.1, big=0.1), PUSHES).reason == "no_action"
    assert priority_largest(M, HIDDEN) == [1, 2, 3, 0]


def test_random_selectors_are_seeded_and_preempted_prefers_the_target():
    g = grasps(t=0.5, big=0.5, mid=0.5, small=0.5)
    picks = {chosen(select_action("random", M, TARGET, g, params=SelectorParams(seed=s))) for s in range(30)}
    assert picks == {"t", "big", "mid", "small"}  # no preference: over 30 seeds it picks each object
    assert all(chosen(select_action("preempted_random", M, TARGET, g, params=SelectorParams(seed=s))) == "t"
               for s in range(10))
    g = grasps(t=0.1, big=0.5, mid=0.5, small=0.5)
    picks = [chosen(select_action("preempted_random", M, TARGET, g, params=SelectorParams(seed=s)))
             for s in range(30)]
    assert set(picks) == {"big", "mid", "small"}
    again = [chosen(select_action("preempted_random", M, TARGET, g, params=SelectorParams(seed=s)))
             for s in range(30)]
    assert picks == again  # reproducible from the seed (and the step number)
    hist = (outcome("grasp", "x"),)
    later = [chosen(select_action("preempted_random", M, TARGET, g, history=hist, params=SelectorParams(seed=s)))
             for s in range(30)]
    assert later != picks  # a new step draws a new order
    a = select_action("preempted_random_push", M, TARGET, grasps(t=0.1, big=0.2), PUSHES)
    assert a.kind == "push" and chosen(a) == "t"


def test_xray_grasps_the_mask_covering_the_occupancy():
    rho = np.zeros((H, W))
    rho[0:20, 45:80] = 1.0  # mostly under "mid" (and a strip of floor)
    occ = OccupancyMap(rho / rho.sum())
    s = xray_scores(M, occ)
    assert s.argmax() == 2 and s[1] == 0
    g = grasps(t=0.0, big=0.9, mid=0.5, small=0.9)
    assert chosen(select_action("xray", M, HIDDEN, g, occupancy=occ)) == "mid"
    # Its grasp below threshold: the next best score, then by area when scores tie (zero).
    assert chosen(select_action("xray", M, HIDDEN, grasps(big=0.9, mid=0.1, small=0.9), occupancy=occ)) == "big"
    assert priority_xray(M, OccupancyMap(np.zeros((H, W)))) == [1, 2, 3, 0]
    with pytest.raises(PolicyError, match="occupancy"):
        select_action("xray", M, HIDDEN, g)


def test_xray_expected_weighs_each_mask_by_its_grasp_quality():
    rho = np.zeros((H, W))
    rho[0:20, 45:80] = 0.6  # under "mid"
    rho[40:55, 60:75] = 0.4  # under "small"
    occ = OccupancyMap(rho / rho.sum())
    s = xray_scores(M, occ)
    assert s[2] > s[3] > 0
    g = grasps(big=0.9, mid=0.2, small=0.9)  # scores 0.71 and 0.18: times quality 0.14 and 0.16
    # X-Ray takes the mask that covers the most occupancy, whatever its grasp's chance of lifting;
    # the expected variant takes the one whose score x quality is highest.
    assert chosen(select_action("xray", M, HIDDEN, g, occupancy=occ)) == "mid"
    assert chosen(select_action("xray_expected", M, HIDDEN, g, occupancy=occ)) == "small"
    assert chosen(select_action("xray_expected", M, HIDDEN, grasps(big=0.9, mid=0.9, small=0.9), occupancy=occ)) == "mid"
    # a seen target with a grasp still comes first, and a mask without a grasp scores 0
    assert chosen(select_action("xray_expected", M, TARGET, grasps(t=0.6, mid=0.9), occupancy=occ)) == "t"
    assert priority_xray(M, occ, weights=[0.0, 1.0, 0.0, 1.0])[:2] == [3, 1]
    with pytest.raises(PolicyError, match="occupancy"):
        select_action("xray_expected", M, HIDDEN, g)


def test_oracle_uses_the_true_target():
    amodal = np.zeros((H, W), bool)
    amodal[42:52, 62:70] = True  # the target hides under "small"
    hidden = InstanceMasks(M.masks[1:], M.ids[1:], np.ones(3))
    g = grasps(big=0.9, mid=0.9, small=0.5)
    assert chosen(select_action("oracle", hidden, HIDDEN, g, target_id="t", target_amodal=amodal)) == "small"
    assert chosen(select_action("largest", hidden, HIDDEN, g)) == "big"
    # Visible and graspable: the true target first, whatever the detector says.
    assert chosen(select_action("oracle", M, HIDDEN, grasps(t=0.2, small=0.9), target_id="t",
                                target_amodal=amodal)) == "t"


def test_best_grasp_per_object_and_termination_rules():
    jaw = Grasp("parallel_jaw", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.05, 0.2, "soft_point", "big")
    suction = Grasp("suction", (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), quality=0.4, object_id="big")
    a = select_action("largest", M, HIDDEN, (jaw, suction))
    assert a.kind == "grasp" and a.grasp.kind == "suction"

    g = grasps(big=0.9)
    p = SelectorParams(horizon=3)
    assert select_action("largest", M, HIDDEN, g, history=(outcome("grasp"),) * 3, params=p).reason == "horizon"
    assert select_action("largest", M, HIDDEN, g, history=(outcome("grasp"),) * 2, params=p).kind == "grasp"
    # More than three consecutive pushes end the search; a grasp in between resets the count.
    three = (outcome("push"),) * 3
    assert select_action("largest_push", M, HIDDEN, (), PUSHES, history=three).reason == "too_many_pushes"
    two = (outcome("push"),) * 2
    assert select_action("largest_push", M, HIDDEN, (), PUSHES, history=two).kind == "push"
    mixed = three + (outcome("grasp"),) + two
    assert select_action("largest_push", M, HIDDEN, (), PUSHES, history=mixed).kind == "push"
    # The target extracted by a grasp: success; removed by a push or another grasp: failure.
    assert termination((outcome("grasp", removed="t", oid="t"),), "t") == "success"
    assert termination((outcome("push", removed="t"),), "t") == "target_removed"
    assert termination((outcome("grasp", removed="big"), outcome("grasp", message="target_removed")), "t") \
        == "target_removed"
    assert select_action("largest", M, TARGET, g, history=(outcome("grasp", removed="t", oid="t"),),
                         target_id="t").reason == "success"
    assert select_action("largest", InstanceMasks.empty(H, W), HIDDEN).reason == "no_action"


def test_bad_selector_configuration():
    with pytest.raises(PolicyError, match="unknown policy"):
        PolicySelector("greedy")
    with pytest.raises(PolicyError, match="thresholds"):
        SelectorParams(t_thresh=1.5)
    with pytest.raises(PolicyError, match="horizon"):
        SelectorParams(horizon=0)


def test_policy_selector_alone():
    for policy in POLICIES:
        sel = PolicySelector(policy, SelectorParams(seed=3), target_id="t", width=W, height=H)
        ctx = sel.CreateDefaultContext()
        sel.GetInputPort("masks").FixValue(ctx, M)
        sel.GetInputPort("target").FixValue(ctx, TARGET)
        sel.GetInputPort("grasps").FixValue(ctx, grasps(t=0.1, big=0.2, mid=0.2, small=0.2))
        sel.GetInputPort("pushes").FixValue(ctx, PUSHES)
        if policy in ("xray", "xray_expected"):
            with pytest.raises(PolicyError, match="occupancy"):
                sel.GetOutputPort("action").Eval(ctx)
            sel.GetInputPort("occupancy").FixValue(ctx, OccupancyMap(M.masks[3] / M.masks[3].sum()))
        a = sel.GetOutputPort("action").Eval(ctx)
        assert isinstance(a, Action)
        # No grasp reaches t_thresh on the target: pushing selectors push it; X-Ray grasps "small",
        # where the occupancy lies; the others grasp "big" (the largest; the random ones by seed 3).
        assert (a.kind, chosen(a)) == (("push", "t") if policy.endswith("_push") else
                                       ("grasp", "small") if policy.startswith("xray") else ("grasp", "big")), policy
        sel.GetInputPort("history").FixValue(ctx, (outcome("grasp", removed="t", oid="t"),))
        assert sel.GetOutputPort("action").Eval(ctx).reason == "success"


def test_oracle_selector_follows_the_amodal_target():
    """The true amodal masks (AmodalMasks' output): the hidden target lies under "small"."""
    sel = PolicySelector("oracle", SelectorParams(seed=3), target_id="t", width=W, height=H)
    ctx = sel.CreateDefaultContext()
    amodal = M.masks.copy()
    amodal[0] = False
    amodal[0, 42:52, 62:70] = True
    sel.GetInputPort("masks").FixValue(ctx, M)
    sel.GetInputPort("pushes").FixValue(ctx, PUSHES)
    sel.GetInputPort("target_amodal").FixValue(ctx, InstanceMasks(amodal, M.ids, np.ones(4)))
    sel.GetInputPort("target").FixValue(ctx, HIDDEN)
    sel.GetInputPort("grasps").FixValue(ctx, grasps(big=0.9, mid=0.9, small=0.5))
    a = sel.GetOutputPort("action").Eval(ctx)
    assert (a.kind, chosen(a)) == ("grasp", "small")


def test_selectors_wired_with_perception_and_planners(bin_scenario, small_heap):
    from ms_drake.grasping.planner import GraspPlanner, ObjectGeometrySource

    k = small_heap.target_index
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s, target_index=k))
    plant = get_plant(station)
    cfg = s.cameras["overhead"]
    cam = PinholeCamera.from_config(cfg)
    ws = Workspace.from_scenario(s)
    seg = builder.AddSystem(Segmenter("ground_truth", label_to_id=object_labels(plant)))
    det = builder.AddSystem(TargetDetector("color"))
    occ = builder.AddSystem(OccupancyEstimator("analytic", camera=cam, workspace=ws,
                                               target_size=TargetBox.from_object(small_heap.target)))
    pushes = builder.AddSystem(PushPlanner(cam, ws))
    color_cam, _ = cfg.MakeCameras()
    grasp = builder.AddSystem(GraspPlanner(color_cam.core().intrinsics(), cam.X_WC, model="soft_point", num_samples=4))
    geo = builder.AddSystem(ObjectGeometrySource({
        o.model_name: (plant.get_body(o.body_index), get_object(o.full_name).trimesh(), get_object(o.full_name).mass,
                       None) for o in station_objects(plant)}))
    target_id = station_objects(plant)[k].model_name
    selectors = {p: builder.AddSystem(PolicySelector(p, SelectorParams(seed=0, horizon=8), target_id=target_id))
                 for p in ("largest_push", "xray", "xray_expected")}
    depth, rgb, label = (station.GetOutputPort(f"overhead.{n}") for n in ("depth_image", "rgb_image", "label_image"))
    builder.Connect(label, seg.GetInputPort("label_image"))
    builder.Connect(rgb, det.GetInputPort("rgb_image"))
    builder.Connect(seg.GetOutputPort("masks"), det.GetInputPort("masks"))
    builder.Connect(depth, occ.GetInputPort("depth_image"))
    builder.Connect(det.GetOutputPort("target"), occ.GetInputPort("target"))
    builder.Connect(depth, pushes.GetInputPort("depth_image"))
    builder.Connect(seg.GetOutputPort("masks"), pushes.GetInputPort("masks"))
    builder.Connect(depth, grasp.GetInputPort("depth_image"))
    builder.Connect(seg.GetOutputPort("masks"), grasp.GetInputPort("masks"))
    builder.Connect(station.GetOutputPort("body_poses"), geo.GetInputPort("body_poses"))
    builder.Connect(geo.GetOutputPort("objects"), grasp.GetInputPort("objects"))
    for sel in selectors.values():
        builder.Connect(seg.GetOutputPort("masks"), sel.GetInputPort("masks"))
        builder.Connect(det.GetOutputPort("target"), sel.GetInputPort("target"))
        builder.Connect(occ.GetOutputPort("occupancy"), sel.GetInputPort("occupancy"))
        builder.Connect(grasp.GetOutputPort("grasps"), sel.GetInputPort("grasps"))
        builder.Connect(pushes.GetOutputPort("pushes"), sel.GetInputPort("pushes"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    masks = seg.GetOutputPort("masks").Eval(seg.GetMyContextFromRoot(ctx))
    candidates = grasp.GetOutputPort("grasps").Eval(grasp.GetMyContextFromRoot(ctx))
    # small_heap: a box (no grasp planned), the target cylinder (no grasp that holds), a packaged
    # object and a second cylinder (grasps that hold)
    box, target, packaged, cylinder = masks.ids
    assert target == target_id
    assert [(g.object_id, g.quality) for g in candidates] == [(target, 0.0), (packaged, 1.0), (cylinder, 1.0)]
    for name, sel in selectors.items():
        a = sel.GetOutputPort("action").Eval(sel.GetMyContextFromRoot(ctx))
        # every selector grasps the second cylinder (rank 2 of the priority lists; xray_expected: the
        # box has no grasp and the target's is 0, so its weighted scores rank the two graspable ones)
        assert (a.kind, chosen(a), a.grasp.quality) == ("grasp", cylinder, 1.0), (name, a.reason)


def test_a_failed_grasp_is_passed_over_on_its_state_when_retries_are_off():
    """retry_failed=False (the deterministic 'nominal' outcome): the grasp that just failed is not
    chosen again until an action succeeds; retry_failed=True (default) chooses it again."""
    g = grasps(t=0.1, big=0.5, mid=0.9)
    failed_big = outcome("grasp", success=False, oid="big")  # big's grasp (0.5 at the origin) failed
    no_retry = SelectorParams(retry_failed=False)
    assert chosen(select_action("largest", M, TARGET, g, history=(failed_big,))) == "big"
    assert chosen(select_action("largest", M, TARGET, g, history=(failed_big,), params=no_retry)) == "mid"
    # a re-plan more than 5 mm away is another grasp when it is better; no better, it is passed over
    # (a noisy camera's re-plan of the failed grasp)
    def moved(q):
        return tuple(Grasp("suction", (0.01, 0.0, 0.0), (0.0, 0.0, -1.0), quality=q, object_id="big")
                     if x.object_id == "big" else x for x in g)
    assert chosen(select_action("largest", M, TARGET, moved(0.75), history=(failed_big,), params=no_retry)) == "big"
    assert chosen(select_action("largest", M, TARGET, moved(0.5), history=(failed_big,), params=no_retry)) == "mid"
    # after a successful action the state changed: big's grasp may be tried again
    later = (failed_big, outcome("grasp", removed="small", oid="small"))
    assert chosen(select_action("largest", M, TARGET, g, history=later, params=no_retry)) == "big"
    # every grasp failed on this state: no action
    all_failed = tuple(outcome("grasp", success=False, oid=k) for k in ("big", "mid"))
    assert select_action("largest", M, TARGET, grasps(big=0.5, mid=0.5), history=all_failed,
                         params=no_retry).reason == "no_action"


def test_an_object_a_grasp_failed_on_is_passed_over_with_skip_failed():
    """skip_failed: every grasp on an object a grasp failed on is passed over until an action
    succeeds, even a grasp elsewhere on it; the target too."""
    g = grasps(t=0.1, big=0.5, mid=0.9)
    failed_big = outcome("grasp", success=False, oid="big")
    skip = SelectorParams(skip_failed=True)
    moved = tuple(Grasp("suction", (0.05, 0.0, 0.0), (0.0, 0.0, -1.0), quality=0.5, object_id="big") if x.object_id == "big"
                  else x for x in g)
    assert chosen(select_action("largest", M, TARGET, moved, history=(failed_big,))) == "big"
    assert chosen(select_action("largest", M, TARGET, moved, history=(failed_big,), params=skip)) == "mid"
    later = (failed_big, outcome("grasp", removed="small", oid="small"))
    assert chosen(select_action("largest", M, TARGET, moved, history=later, params=skip)) == "big"
    tg = grasps(t=0.6, big=0.5, mid=0.9)
    failed_t = outcome("grasp", success=False, oid="t")
    assert chosen(select_action("largest", M, TARGET, tg, history=(failed_t,))) == "t"
    assert chosen(select_action("largest", M, TARGET, tg, history=(failed_t,), params=skip)) == "big"
