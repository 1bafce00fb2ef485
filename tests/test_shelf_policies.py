"""Shelf policies (Ch. 9.4.3-9.4.4) and the ShelfPolicySelector system."""

import dataclasses

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from ms_drake.experiments.shelf import build_shelf_search
from ms_drake.foss import Foss
from ms_drake.policies.bin_selectors import PolicyError
from ms_drake.policies.shelf import (
    ORACLE_EXHAUSTIVE_SECONDS,
    ORACLE_WIDE_SECONDS,
    SHELF_POLICIES,
    ShelfPolicies,
    ShelfPolicyParams,
    ShelfPolicySelector,
    _View,
    exhaustive_push_plan,
    history_min,
    like_key,
    mask_extents,
    nil_effect,
    oracle_plan,
    push_locked,
    returns,
    segment,
    support_reduction,
    wide_plan,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import generate_shelf_scene
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.types import (
    Action,
    ActionOutcome,
    ShelfObject,
    ShelfOccupancy,
    ShelfScene,
)

W = 640


@pytest.fixture(scope="module")
def foss():
    return Foss(ShelfGeometry.from_scenario(load_scenario(None, "FetchShelf")))


def box(i, x, y, w=0.1, d=0.1, h=0.15):
    return ShelfObject(i, "box", x, y, w, d, h)


def under(foss, scene, object_id):
    """A distribution spread evenly over an object's mask columns."""
    seg = segment(foss.geometry, scene)
    k = [o.id for o in seg.known.objects].index(object_id)
    lo, hi = np.round(mask_extents(foss.geometry, seg)[k]).astype(int)
    p = np.zeros(W)
    p[lo:hi + 1] = 1.0
    return p / p.sum()


# A blocker in the middle, neighbours left and right: pushes move it a little, suction all the way.
SQUEEZED = ShelfScene((box("a", 0.0, -0.2, w=0.12), box("l", -0.2, -0.2), box("r", 0.2, -0.2)),
                      box("target", -0.22, 0.22, 0.06, 0.06, 0.06), 0)


def test_unknown_policy_names_the_choices(foss):
    with pytest.raises(PolicyError, match="random, dar, der3, bluction_dar, oracle_p, oracle_ps"):
        ShelfPolicySelector("xray", foss)
    with pytest.raises(PolicyError, match="psi"):
        ShelfPolicies("dar", foss, ShelfPolicyParams(psi=0.0))


def test_support_reduction_rewards_uncovering_the_mass(foss):
    dist = under(foss, SQUEEZED, "a")
    seg = segment(foss.geometry, SQUEEZED)
    pushes = [a for a in foss.push_actions(seg.known)]
    dr = dict(zip([(a.object_id, np.sign(a.dx)) for a in pushes], support_reduction(foss.geometry, seg, dist, pushes)))
    assert dr[("a", 1.0)] > 0.1 and dr[("a", -1.0)] > 0.1
    assert dr[("l", -1.0)] == pytest.approx(0.0, abs=1e-9)  # l's mask holds none of it
    suction = [a for a in foss.suction_actions(seg.known) if a.object_id == "a"]
    assert support_reduction(foss.geometry, seg, dist, suction).max() == pytest.approx(1.0)


def test_bluction_dar_weighs_suction_by_psi(foss):
    dist = under(foss, SQUEEZED, "a")
    cheap = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=1.0)).select(SQUEEZED, dist)
    dear = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=100.0)).select(SQUEEZED, dist)
    assert (cheap.shelf.kind, cheap.shelf.object_id) == ("suction", "a")
    assert (dear.shelf.kind, dear.shelf.object_id) == ("push", "a")
    dar = ShelfPolicies("dar", foss).select(SQUEEZED, dist)
    assert (dar.shelf.kind, dar.shelf.object_id) == ("push", "a")
    assert ShelfPolicies("der3", foss).select(SQUEEZED, dist).shelf.kind == "push"


def test_refused_actions_are_not_proposed_again(foss):
    dist = under(foss, SQUEEZED, "a")
    rules = ShelfPolicies("dar", foss)
    first = rules.select(SQUEEZED, dist)
    refused = ActionOutcome(first, False, message="collision")
    second = rules.select(SQUEEZED, dist, (refused,))
    assert second.kind == "shelf" and second.shelf != first.shelf
    # After an executed action the refusals are forgotten.
    assert rules.select(SQUEEZED, dist, (refused, ActionOutcome(second, True))).shelf == first.shelf


def test_an_action_that_moved_nothing_is_not_repeated_on_the_unchanged_object(foss):
    dist = under(foss, SQUEEZED, "a")
    on_robot = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=1.0, nil_move=0.01))
    first = on_robot.select(SQUEEZED, dist)
    assert (first.shelf.kind, first.shelf.object_id) == ("suction", "a")
    # Executed in SQUEEZED (its Action.scene); "a" then lies 4 mm from where it was: a nil effect.
    done = ActionOutcome(Action("shelf", shelf=first.shelf, scene=SQUEEZED), True, message="agree=1")
    a = SQUEEZED.object("a")
    nudged = ShelfScene((a.moved(a.x + 0.004, a.y),) + SQUEEZED.objects[1:], SQUEEZED.target, 0)
    assert nil_effect((done,), nudged, 0.01) == {like_key(first.shelf)}
    again = on_robot.select(nudged, dist, (done,))
    assert again.kind == "shelf" and like_key(again.shelf) != like_key(first.shelf)
    # FOSS's rules (nil_move 0) and an action without its scene (FOSS's rollouts) keep the suction.
    assert like_key(ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=1.0)).select(
        nudged, dist, (done,)).shelf) == like_key(first.shelf)
    assert nil_effect((ActionOutcome(first, True),), nudged, 0.01) == set()
    # Once the object has changed (moved 5 cm since), the action may come back.
    moved = ShelfScene((a.moved(a.x + 0.05, a.y),) + SQUEEZED.objects[1:], SQUEEZED.target, 0)
    later = ActionOutcome(Action("shelf", shelf=again.shelf, scene=nudged), True, message="agree=1")
    assert nil_effect((done, later), moved, 0.01) == set()
    # An action that moved its object 3 cm had an effect; a plan failure executed nothing.
    assert nil_effect((done,), moved, 0.01) == set()
    failed = ActionOutcome(Action("shelf", shelf=first.shelf, scene=SQUEEZED), False, message="plan_failed:unreachable")
    assert nil_effect((failed,), nudged, 0.01) == set()


def test_the_nil_rule_compares_centres_not_footprint_sizes(foss):
    # A toppled object observed again: its footprint (rotated bounding box) 3 cm wider, its centre
    # 2 mm off. The action moved it 2 mm: nil, however the footprint's size changed.
    dist = under(foss, SQUEEZED, "a")
    first = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=1.0)).select(SQUEEZED, dist)
    done = ActionOutcome(Action("shelf", shelf=first.shelf, scene=SQUEEZED), True, message="agree=1")
    a = SQUEEZED.object("a")
    lying = ShelfObject("a", a.kind, a.x + 0.002, a.y, a.width + 0.03, a.depth - 0.02, a.height - 0.05)
    resized = ShelfScene((lying,) + SQUEEZED.objects[1:], SQUEEZED.target, 0)
    assert nil_effect((done,), resized, 0.01) == {like_key(first.shelf)}


def test_actions_moving_their_object_less_than_min_move_are_not_proposed(foss):
    dist = under(foss, SQUEEZED, "a")
    rules = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=100.0))
    best = rules.select(SQUEEZED, dist).shelf
    assert best.kind == "push"  # a short push to the neighbour
    m = rules.displacement(SQUEEZED, best) + 1e-3
    other = ShelfPolicies("bluction_dar", foss, ShelfPolicyParams(psi=100.0, min_move=m)).select(SQUEEZED, dist)
    assert other.kind == "shelf" and other.shelf != best
    assert rules.displacement(SQUEEZED, other.shelf) >= m


def test_a_candidate_leading_back_to_an_observed_scene_is_not_proposed(foss):
    # "a" stands 1 mm from "r"; a suction takes it 19 cm left, and the push to the neighbour would
    # take it back: a two-step cycle of states.
    start = ShelfScene((box("a", 0.089, -0.175, w=0.12), box("l", -0.3, -0.175), box("r", 0.2, -0.175)),
                       box("target", 0.09, 0.2, 0.06, 0.06, 0.06), 0)
    away, = (a for a in foss.actions(segment(foss.geometry, start).known)
             if (a.kind, a.object_id) == ("suction", "a") and np.allclose((a.dx, a.dy), (-0.191, 0.075)))
    left = foss.moved(start, away)
    done = (ActionOutcome(Action("shelf", shelf=away, scene=start), True, message="agree=1"),)
    dist = under(foss, left, "a")
    was = start.object("a")
    params = ShelfPolicyParams(psi=100.0, min_move=0.01, nil_move=0.01)
    back = ShelfPolicies("bluction_dar", foss, params).select(left, dist, done)
    assert back.shelf.kind == "push" and back.shelf.dx > 0  # without the rule: the return
    rules = ShelfPolicies("bluction_dar", foss, dataclasses.replace(params, revisit=0.01))
    assert np.hypot(*np.subtract(rules.predicted_centre(left, back.shelf), (was.x, was.y))) < 0.01
    other = rules.select(left, dist, done)
    assert other.kind == "shelf" and other.shelf != back.shelf and "revisit 1]" in other.reason
    assert np.hypot(*np.subtract(rules.predicted_centre(left, other.shelf), (was.x, was.y))) >= 0.01
    # Without the suction in the history (or in FOSS, revisit 0) the push is a new state.
    assert rules.select(left, dist).shelf == back.shelf
    assert returns(done, left, 0.01)["a"] == [(was.x, was.y), (left.object("a").x, left.object("a").y)]


def test_random_is_seeded(foss):
    dist = under(foss, SQUEEZED, "a")
    a = [ShelfPolicies("random", foss, ShelfPolicyParams(seed=s)).select(SQUEEZED, dist).shelf for s in range(6)]
    assert a[0] == ShelfPolicies("random", foss, ShelfPolicyParams(seed=0)).select(SQUEEZED, dist).shelf
    assert len(set(a)) > 1


def test_distribution_policies_do_not_see_hidden_objects(foss):
    hidden = box("hidden", 0.0, 0.03, w=0.06, d=0.06, h=0.06)
    wall = box("wall", 0.0, -0.05, w=0.3, d=0.05, h=0.2)
    seg = segment(foss.geometry, ShelfScene((wall, hidden), box("target", 0.2, 0.22, 0.06, 0.06, 0.06)))
    assert [o.id for o in seg.known.objects] == ["wall"]


def test_history_min():
    a = ShelfOccupancy(np.ones((2, 2)) / 4, np.array([0.5, 0.5, 0.0, 0.0]))
    b = ShelfOccupancy(np.array([[0.5, 0.5], [0.0, 0.0]]), np.array([0.0, 0.5, 0.5, 0.0]))
    assert history_min(a, None) is a
    m = history_min(a, b)
    assert np.allclose(m.image_x, [0.0, 1.0, 0.0, 0.0]) and np.allclose(m.floor, [[0.5, 0.5], [0.0, 0.0]])
    empty = history_min(ShelfOccupancy(a.floor, np.array([1.0, 0, 0, 0])), b)
    assert np.allclose(empty.image_x, [1.0, 0, 0, 0])  # an empty minimum keeps P_t


def test_oracles_on_hand_made_scenes(foss):
    target = box("target", 0.0, 0.12, 0.06, 0.06, 0.06)
    # One blocker with room on its right: a single push clears the view.
    easy = ShelfScene((box("b", -0.02, 0.0, w=0.14, h=0.2),), target, 0)
    assert not foss.revealed(easy)
    plan = oracle_plan(foss, easy, suction=False, budget=2)
    assert len(plan) == 1 and plan[0].kind == "push"
    # The blocker squeezed between two boxes (no room for the blade): only suction clears the view.
    squeezed = ShelfScene((box("b", 0.0, 0.0, w=0.2, h=0.2), box("l", -0.155, 0.0), box("r", 0.155, 0.0)),
                          target, 0)
    assert not foss.revealed(squeezed)
    assert oracle_plan(foss, squeezed, suction=False, budget=6) is None
    plan = oracle_plan(foss, squeezed, suction=True, budget=6)
    assert [(a.kind, a.object_id) for a in plan] == [("suction", "b")]
    stop = ShelfPolicies("oracle_p", foss).select(squeezed, None)
    assert stop.kind == "stop" and "no push sequence can take b out of the view" in stop.reason


def test_oracle_estimate_counts_only_what_hides_the_target(foss):
    target = box("target", 0.0, 0.12, 0.06, 0.06, 0.06)
    tall = box("tall", -0.02, 0.0, w=0.14, h=0.2)
    low = box("low", 0.0, -0.2, w=0.1, h=0.04)  # in the overhead triangle, under the camera's rays
    scene = ShelfScene((tall, low), target, 0)
    view = _View(foss, target)
    cols, sets = view.blockers(scene)
    assert [scene.objects[c].id for c in cols] == ["tall"]
    assert sets.tolist() == [1]  # removing "tall" alone reveals the target
    assert foss.revealed(ShelfScene((low,), target, 0))
    plan = oracle_plan(foss, scene, suction=False, budget=4)
    assert [a.object_id for a in plan] == ["tall"]


def test_oracle_solves_a_scene_the_triangle_search_lost(foss):
    # 10 occluders, seed 58: the search on the overhead triangle stopped at its 8 s bound without a
    # plan (docs/results/ch9_shelf.md); the view-ray estimates find a 2-action plan.
    scene = generate_shelf_scene(foss.geometry, 58, num_objects=10).scene
    plan = oracle_plan(foss, scene, suction=True, budget=20)
    assert plan is not None and len(plan) <= 3
    s = scene
    for a in plan:
        s, outcome = foss.step(s, a)
        assert outcome.success, outcome.message
    assert foss.revealed(s)


def test_push_locked(foss, monkeypatch):
    target = box("target", 0.0, 0.12, 0.06, 0.06, 0.06)
    # b's row is full from wall to wall: b cannot leave the middle, whatever moves first.
    full = ShelfScene((box("b", 0.0, 0.0, w=0.2, h=0.2), box("l", -0.1995, 0.0, w=0.198),
                       box("r", 0.1995, 0.0, w=0.198)), target, 0)
    assert not foss.revealed(full) and push_locked(foss, full) == ["b"]
    with monkeypatch.context() as m:  # no search at all, exhaustive or not
        m.setattr(foss, "push_actions", lambda *a, **k: pytest.fail("searched a push-locked scene"))
        assert oracle_plan(foss, full, suction=False, budget=6, exhaustive_seconds=60.0) is None
        stop = ShelfPolicies("oracle_p", foss).select(full, None)
    assert stop.kind == "stop" and "no push sequence can take b out of the view" in stop.reason
    # r 10.1 cm nearer the front no longer shares b's row (it can pass b): b may go right, out of the view.
    free = ShelfScene(full.objects[:2] + (box("r", 0.1995, -0.101, w=0.198),), target, 0)
    assert push_locked(foss, free) == []
    # Generated: 6 occluders, seed 0: the 16.5 cm box in front of the target can reach x in
    # [0.104, 0.218] m only (the wall; the 19 cm cylinder of its row, itself held by the others).
    scene = generate_shelf_scene(foss.geometry, 0, num_objects=6).scene
    assert push_locked(foss, scene) == ["occ05"]
    assert oracle_plan(foss, scene, suction=True, budget=12) is not None


def test_an_oracle_that_pushes_the_target_solves_a_push_locked_scene(foss):
    """6 occluders, seed 43: occ00 cannot leave the target's view by pushes (push_locked), but the
    target itself can be pushed out from behind it once its neighbours make room."""
    scene = generate_shelf_scene(foss.geometry, 43, num_objects=6).scene
    assert push_locked(foss, scene) == ["occ00"]
    assert oracle_plan(foss, scene, suction=False, budget=12) is None
    plan = oracle_plan(foss, scene, suction=False, budget=12, push_target=True)
    assert plan is not None and {a.kind for a in plan} == {"push"} and "target" in {a.object_id for a in plan}
    s = scene
    for a in plan:
        s, outcome = foss.step(s, a)
        assert outcome.success, outcome.message
    assert foss.revealed(s) and s.target.x != scene.target.x
    # through the selector: its first action, and the plan's later states reuse the plan
    policies = ShelfPolicies("oracle_p", foss, ShelfPolicyParams(oracle_push_target=True))
    action = policies.select(scene, None)
    assert action.kind == "shelf" and action.shelf == plan[0]
    assert ShelfPolicies("oracle_p", foss).select(scene, None).kind == "stop"


def test_exhaustive_push_search_finds_the_plans_the_bounded_oracle_misses(foss):
    """8 occluders, seed 89: one of Oracle-P's failures in Table 9.1 (its staged search ends
    without a plan); breadth first over every push there is a 6-push plan, and none of 5."""
    scene = generate_shelf_scene(foss.geometry, 89, num_objects=8).scene
    assert not push_locked(foss, scene)
    assert oracle_plan(foss, scene, suction=False, budget=16, max_seconds=0.5) is None
    plan = oracle_plan(foss, scene, suction=False, budget=16, max_seconds=0.5, exhaustive_seconds=120)
    assert plan is not None and len(plan) == 6 and {a.kind for a in plan} == {"push"}
    s = scene
    for a in plan:
        s, outcome = foss.step(s, a)
        assert outcome.success, outcome.message
    assert foss.revealed(s)
    assert exhaustive_push_plan(foss, scene, 5, 120) is None  # the plan is a shortest one
    # 6 occluders, seed 32: not push-locked by the row bound, but the reachable states run out
    # (442 of them) before any shows the target
    assert exhaustive_push_plan(foss, generate_shelf_scene(foss.geometry, 32, num_objects=6).scene, 12, 120) is None
    # the selector's parameter
    params = ShelfPolicyParams(oracle_max_seconds=0.5, oracle_exhaustive_seconds=0.0)
    assert ShelfPolicies("oracle_p", foss, params).select(scene, None).kind == "stop"
    action = ShelfPolicies("oracle_p", foss, dataclasses.replace(params, oracle_exhaustive_seconds=60)).select(scene, None)
    assert action.kind == "shelf" and action.shelf == plan[0]
    with pytest.raises(PolicyError, match="exhaustive_seconds"):
        oracle_plan(foss, scene, suction=False, budget=16, exhaustive_seconds=-1.0)


def test_oracle_ps_wide_search_is_its_last_stage(foss):
    """The wide search finds a plan on its own (from a scene the cheapest plan of which needs a
    suction), and is what Oracle-P+S falls back on when its staged search has no time left."""
    scene = generate_shelf_scene(foss.geometry, 0, num_objects=6).scene  # push-locked: needs the cup
    plan = wide_plan(foss, scene, budget=12, max_seconds=60)
    assert plan is not None and "suction" in {a.kind for a in plan}
    s = scene
    for a in plan:
        s, outcome = foss.step(s, a)
        assert outcome.success, outcome.message
    assert foss.revealed(s)
    # a staged search with no time finds nothing; the last stage, given time, finds the same plan
    assert oracle_plan(foss, scene, suction=True, budget=12, max_seconds=1e-9) is None
    assert oracle_plan(foss, scene, suction=True, budget=12, max_seconds=1e-9, exhaustive_seconds=60) == plan
    assert wide_plan(foss, scene, budget=12, max_seconds=1e-9) is None  # its own bound
    # the selector's default budget per oracle
    assert ShelfPolicies("oracle_ps", foss).last_stage_seconds == ORACLE_WIDE_SECONDS
    assert ShelfPolicies("oracle_p", foss).last_stage_seconds == ORACLE_EXHAUSTIVE_SECONDS
    assert ShelfPolicies("dar", foss).last_stage_seconds == 0.0
    zero = ShelfPolicies("oracle_ps", foss, ShelfPolicyParams(oracle_exhaustive_seconds=0.0))
    assert zero.last_stage_seconds == 0.0


def test_oracle_time_bound(foss, monkeypatch):
    target = box("target", 0.0, 0.12, 0.06, 0.06, 0.06)
    squeezed = ShelfScene((box("b", 0.0, 0.0, w=0.2, h=0.2), box("l", -0.155, 0.0), box("r", 0.155, 0.0)),
                          target, 0)
    with pytest.raises(PolicyError, match="max_seconds"):
        oracle_plan(foss, squeezed, suction=True, budget=6, max_seconds=0.0)
    # A bound too short for even one expansion: no plan, and no state expanded.
    assert oracle_plan(foss, squeezed, suction=True, budget=6) is not None
    expanded = []
    original = foss.push_actions

    def counted(*a, **k):
        expanded.append(1)
        return original(*a, **k)

    monkeypatch.setattr(foss, "push_actions", counted)
    assert oracle_plan(foss, squeezed, suction=True, budget=6, max_seconds=1e-9) is None
    assert not expanded
    assert exhaustive_push_plan(foss, squeezed, 6, max_seconds=1e-9) is None and len(expanded) <= 1


def test_oracle_follows_its_cached_plan(foss):
    scene = generate_shelf_scene(foss.geometry, 1, num_objects=8).scene
    rules = ShelfPolicies("oracle_ps", foss)
    first = rules.select(scene, None)
    assert first.kind == "shelf"
    plan_len = int(first.reason.split(": ")[1].split()[0])
    s, history = scene, ()
    for _ in range(plan_len):
        action = rules.select(s, None, history)
        s, outcome = foss.step(s, action)
        assert outcome.success
        history += (outcome,)
    assert foss.revealed(s) or rules.select(s, None, history).kind == "stop"


def test_selector_alone_keeps_the_history_minimum(foss):
    dist = under(foss, SQUEEZED, "a")
    sel = ShelfPolicySelector("bluction_dar", foss, period=1.0)
    context = sel.CreateDefaultContext()
    occ = ShelfOccupancy(np.zeros((2, 2)), dist)
    sel.GetInputPort("scene").FixValue(context, SQUEEZED)
    sel.GetInputPort("occupancy").FixValue(context, occ)
    action = sel.GetOutputPort("action").Eval(context)
    assert isinstance(action, Action) and action.kind == "shelf" and action.shelf.object_id == "a"
    assert np.array_equal(sel.GetOutputPort("occupancy_history").Eval(context).image_x, dist)
    Simulator(sel, context).AdvanceTo(1.5)  # stores P'_1 = P_1
    shifted = np.roll(dist, 10)
    sel.GetInputPort("occupancy").FixValue(context, ShelfOccupancy(np.zeros((2, 2)), shifted))
    expect = np.minimum(dist, shifted)
    got = sel.GetOutputPort("occupancy_history").Eval(context).image_x
    assert np.allclose(got, expect / expect.sum())
    lonely = ShelfPolicySelector("dar", foss)
    c = lonely.CreateDefaultContext()
    lonely.GetInputPort("scene").FixValue(c, SQUEEZED)
    with pytest.raises(PolicyError, match="occupancy"):
        lonely.GetOutputPort("action").Eval(c)


@pytest.mark.parametrize("policy", SHELF_POLICIES)
def test_selector_wired_in_the_search_diagram(foss, policy):
    scene = generate_shelf_scene(foss.geometry, 2, num_objects=4).scene
    diagram = build_shelf_search(foss, scene, policy)
    sim = Simulator(diagram)
    ctx = sim.get_context()
    for step in range(8):
        if diagram.GetOutputPort("visible_fraction").Eval(ctx)[0] >= 0.8:
            break
        assert diagram.GetOutputPort("action").Eval(ctx).kind == "shelf"
        sim.AdvanceTo(step + 1.5)
    history = diagram.GetOutputPort("history").Eval(ctx)
    assert len(history) == step
    if policy != "random":
        assert diagram.GetOutputPort("visible_fraction").Eval(ctx)[0] >= 0.8


def test_oracle_counts_the_objects_in_a_pick_sweep_when_the_lift_is_floor(foss):
    """With FOSS's "floor" lift the oracles' estimate (`_ways`) counts the objects in a picked
    object's sweep to the front among those that must move first; with "over" only the shaft's."""
    from ms_drake.foss import FossParams
    from ms_drake.policies.shelf import _ways

    floor = Foss(foss.geometry, FossParams.for_suction_lift("floor"))
    back, low = box("back", 0.0, 0.1), box("low", 0.0, -0.2, h=0.10)  # the shaft passes over "low"
    sc = ShelfScene((back, low), box("target", 0.22, 0.24, 0.06, 0.06, 0.06), 0)
    P, n = foss._bodies(sc)

    def pick_masks(f):
        anywhere = lambda cs: np.ones(len(cs), bool)  # noqa: E731 - any place is out of the way
        pushes = _ways(f, P, n, 0, anywhere, False)
        return [mask for mask, _, _ in _ways(f, P, n, 0, anywhere, True)[len(pushes):]]

    assert pick_masks(foss) == [0]  # lifted over "low": nothing needs to move first
    assert pick_masks(floor) == [1 << 1]  # lifted 2 cm: "low" is in the way
