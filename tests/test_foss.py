"""FOSS, the first-order shelf simulator: pushes, suction, refusals, visibility, and FossSystem."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource

from ms_drake.foss import Foss, FossParams, FossSystem
from ms_drake.foss.simulator import BLADE_THICKNESS, CONTACT_GAP
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import generate_shelf_scene
from ms_drake.shelf_geometry import Prisms, ShelfGeometry, overlap
from ms_drake.types import Action, ShelfAction, ShelfObject, ShelfScene


@pytest.fixture(scope="module")
def foss():
    return Foss(ShelfGeometry.from_scenario(load_scenario(None, "FetchShelf")))


def box(i, x, y, w=0.1, d=0.1, h=0.1):
    return ShelfObject(i, "box", x, y, w, d, h)


TARGET = box("target", 0.22, 0.24, 0.06, 0.06, 0.06)


def scene(*objects, target=TARGET):
    return ShelfScene(tuple(objects), target, 0)


def test_push_travels_until_it_touches_the_nearest_neighbour(foss):
    s = scene(box("a", -0.1, 0.0), box("b", 0.15, 0.0))
    pushes = {(a.object_id, np.sign(a.dx)): a for a in foss.push_actions(s)}
    a = pushes[("a", 1.0)]
    assert a.dx == pytest.approx(0.15 - CONTACT_GAP)
    new, out = foss.step(s, a)
    assert out.success
    assert new.object("a").x == pytest.approx(0.05 - CONTACT_GAP)
    assert new.object("b") == s.object("b")  # no multi-object pushes
    # Pushing further than the neighbour allows stops at it.
    far, out = foss.step(s, ShelfAction("push", "a", 0.3))
    assert out.success and far.object("a").x == pytest.approx(0.05 - CONTACT_GAP)
    # Left: until the wall.
    assert pushes[("a", -1.0)].dx == pytest.approx(-(0.3 - 0.15) + CONTACT_GAP)


def test_pushes_that_leave_room_for_the_blade(foss):
    s = scene(box("a", -0.1, 0.0), box("b", 0.15, 0.0))
    contact = {(a.object_id, a.dx) for a in foss.push_actions(s)}
    both = foss.push_actions(s, leave_room=True)
    assert contact <= {(a.object_id, a.dx) for a in both} and len(both) > len(contact)
    short = [a for a in both if a.object_id == "a" and 0 < a.dx < 0.15 - CONTACT_GAP - 1e-9]
    assert len(short) == 1
    new, out = foss.step(s, short[0])
    assert out.success
    gap = (new.object("b").x - 0.05) - (new.object("a").x + 0.05)
    assert gap > BLADE_THICKNESS
    # ... so "b" can still be pushed right, which a push of "a" to contact forbids.
    assert any(a.object_id == "b" and a.dx > 0 for a in foss.push_actions(new))
    touching, _ = foss.step(s, ShelfAction("push", "a", 0.3))
    assert not any(a.object_id == "b" and a.dx > 0 for a in foss.push_actions(touching))


def test_cylinders_touch_at_the_right_distance(foss):
    s = scene(ShelfObject("c", "cylinder", -0.1, 0.0, 0.1, 0.1, 0.1), ShelfObject("d", "cylinder", 0.1, 0.06, 0.1, 0.1, 0.1))
    new, out = foss.step(s, ShelfAction("push", "c", 0.3))
    assert out.success
    gap = np.hypot(new.object("d").x - new.object("c").x, 0.06) - 0.1
    assert 0 < gap <= CONTACT_GAP  # CONTACT_GAP along x; the circles' normal is oblique


def test_the_blade_must_fit(foss):
    # Against the left wall: no room for the blade on the left (push right), no room to move left.
    s = scene(box("a", -0.3 + 0.05 + BLADE_THICKNESS / 2, 0.0))
    assert [a for a in foss.push_actions(s) if a.object_id == "a"] == []
    _, out = foss.step(s, ShelfAction("push", "a", 0.1))
    assert not out.success and "blade" in out.message


def test_no_pushing_behind_other_objects(foss):
    # "a" stands behind "front": the blade's way in from the open front is blocked on both sides.
    s = scene(box("a", -0.1, 0.05), box("front", -0.1, -0.2, w=0.22, d=0.08))
    assert [a for a in foss.push_actions(s) if a.object_id == "a"] == []
    assert {a.object_id for a in foss.push_actions(s)} == {"front"}


def test_a_push_stops_at_the_hidden_target(foss):
    s = scene(box("a", -0.1, 0.0), target=box("target", 0.05, 0.0, 0.06, 0.06, 0.06))
    new, out = foss.step(s, ShelfAction("push", "a", 0.3))
    assert out.success
    assert new.object("a").x == pytest.approx(0.02 - 0.05 - CONTACT_GAP)


def test_suction_pick_and_place(foss):
    s = scene(box("f", 0.0, -0.2, w=0.1, d=0.08), box("g", -0.2, 0.1))
    new, out = foss.step(s, ShelfAction("suction", "f", 0.15, 0.0))
    assert out.success
    assert (new.object("f").x, new.object("f").y) == pytest.approx((0.15, -0.3 + 0.04))
    assert new.object("g") == s.object("g")
    # Onto another object, or off the shelf: refused, nothing moves.
    for a in (ShelfAction("suction", "f", -0.2, 0.32), ShelfAction("suction", "f", 0.3, 0.0),
              ShelfAction("suction", "f", 0.0, 0.55)):
        same, out = foss.step(s, a)
        assert not out.success and same is s


def test_suction_lifts_over_lower_objects_but_the_shaft_must_pass(foss):
    back = box("back", 0.0, 0.1, h=0.15)  # the cup seals 1.5 cm under its top, at z = 0.135
    low = box("low", 0.0, -0.2, h=0.10)  # the shaft at 0.135 +- 0.015 passes over it
    high = box("high", 0.0, -0.2, h=0.13)  # ... but not over this one
    ok = foss.suction_placements(scene(back, low), "back")
    assert len(ok) > 0
    _, out = foss.step(scene(back, low), ShelfAction("suction", "back", ok[0][0] - back.x, ok[0][1] - 0.05 + 0.3))
    assert out.success
    assert len(foss.suction_placements(scene(back, high), "back")) == 0
    assert all(a.object_id != "back" for a in foss.suction_actions(scene(back, high)))


def test_suction_lift_floor_needs_clear_sweeps(foss):
    """FossParams.for_suction_lift("floor"): lifted 2 cm only, so an object behind a lower one
    cannot be pulled out over it; the front object still can, and so can the back one once the
    sweep is clear."""
    floor = Foss(foss.geometry, FossParams.for_suction_lift("floor"))
    back = box("back", 0.0, 0.1, h=0.15)
    low = box("low", 0.0, -0.2, h=0.10)
    aside = box("low", 0.2, -0.2, h=0.10)  # the same object beside the sweep
    assert len(foss.suction_placements(scene(back, low), "back")) > 0
    assert len(floor.suction_placements(scene(back, low), "back")) == 0
    assert all(a.object_id != "back" for a in floor.suction_actions(scene(back, low)))
    assert len(floor.suction_placements(scene(back, low), "low")) > 0
    ok = floor.suction_placements(scene(back, aside), "back")
    assert len(ok) > 0
    _, out = floor.step(scene(back, aside), ShelfAction("suction", "back", ok[0][0] - back.x, ok[0][1] - 0.05 + 0.3))
    assert out.success
    _, out = floor.step(scene(back, low), ShelfAction("suction", "back", 0.2, 0.0))
    assert not out.success
    with pytest.raises(ValueError, match="over, floor"):
        FossParams.for_suction_lift("high")


def test_every_proposed_action_is_executed_as_proposed(foss):
    s = generate_shelf_scene(foss.geometry, 3, num_objects=8).scene
    actions = foss.actions(s)
    assert any(a.kind == "push" for a in actions) and any(a.kind == "suction" for a in actions)
    for a in actions[:: max(1, len(actions) // 40)]:
        new, out = foss.step(s, a)
        assert out.success, (a, out.message)
        assert new == foss.moved(s, a)
        bodies = Prisms.of(list(new.objects) + [new.target])
        for i in range(len(bodies)):
            others = np.arange(len(bodies)) != i
            assert not overlap(bodies.center[i], bodies.half[i], bodies.radius[i], bodies.center[others],
                               bodies.half[others], bodies.radius[others]).any()
        assert np.all(np.abs(bodies.center) + bodies.extent <= foss.geometry.half + 1e-9)


def test_unknown_objects_and_kinds_are_refused(foss):
    s = scene(box("a", 0.0, 0.0))
    for a in (ShelfAction("push", "zz", 0.1), ShelfAction("lift", "a", 0.1), Action("stop"),
              ShelfAction("suction", "target", 0.1, 0.1), ShelfAction("push", "a", 0.001)):
        same, out = foss.step(s, a)
        assert not out.success and same is s


def test_the_target_is_pushed_like_any_object_when_asked_for(foss):
    """Only a planner that knows the target proposes its pushes (target=True); FOSS executes them
    with the same rules (nearest neighbour, blade corridor), and the target's place changes."""
    s = scene(box("a", -0.1, 0.0), box("b", 0.05, 0.24))
    assert all(a.object_id != "target" for a in foss.push_actions(s))
    pushes = {(a.object_id, np.sign(a.dx)): a for a in foss.push_actions(s, target=True)}
    left, right = pushes[("target", -1.0)], pushes[("target", 1.0)]
    # to the left it stops at b (its right face at 0.10), to the right at the wall (0.30)
    assert left.dx == pytest.approx(0.10 - (0.22 - 0.03) + CONTACT_GAP)
    assert right.dx == pytest.approx(0.30 - 0.25 - CONTACT_GAP)
    new, out = foss.step(s, left)
    assert out.success and new.objects == s.objects
    assert new.target.x == pytest.approx(0.22 + left.dx) and new.target.y == s.target.y
    assert new == foss.moved(s, left)
    # a blade corridor blocked from the front refuses the push, as for any object
    blocked = scene(box("a", 0.18, 0.0, w=0.2))
    assert all(a.object_id != "target" for a in foss.push_actions(blocked, target=True))
    same, out = foss.step(blocked, ShelfAction("push", "target", -0.05))
    assert not out.success and same is blocked


def test_visible_fraction(foss):
    t = box("target", 0.0, 0.1, 0.06, 0.06, 0.06)
    assert foss.visible_fraction(scene(target=t)) == pytest.approx(1.0)
    assert foss.visible_fraction(scene(box("wall", 0.0, -0.05, w=0.3, d=0.05, h=0.2), target=t)) == 0.0
    half = foss.visible_fraction(scene(box("half", -0.1, -0.05, w=0.2, d=0.05, h=0.2), target=t))
    assert 0.1 < half < 0.9
    assert foss.revealed(scene(target=t)) and not foss.revealed(scene(box("w", 0.0, -0.05, 0.3, 0.05, 0.2), target=t))


def test_foss_system_alone(foss):
    s = scene(box("a", -0.1, 0.0), box("b", 0.15, 0.0))
    system = FossSystem(foss, s, period=0.5)
    context = system.CreateDefaultContext()
    assert system.GetOutputPort("scene").Eval(context) == s
    assert system.GetOutputPort("visible_fraction").Eval(context)[0] == pytest.approx(foss.visible_fraction(s))
    push = Action("shelf", shelf=ShelfAction("push", "a", 0.3))
    system.GetInputPort("action").FixValue(context, push)
    sim = Simulator(system, context)
    sim.AdvanceTo(0.75)  # the update at t = 0.5 applies the action
    moved = system.GetOutputPort("scene").Eval(context)
    assert moved.object("a").x == pytest.approx(0.05 - CONTACT_GAP)
    (outcome,) = system.GetOutputPort("history").Eval(context)
    assert outcome.success and outcome.action == push
    with pytest.raises(ValueError, match="target"):
        FossSystem(foss, ShelfScene((box("a", 0, 0),)))


def test_foss_system_in_a_diagram_applies_one_action_per_period(foss):
    s = scene(box("a", -0.1, 0.0), box("b", 0.15, 0.0))
    builder = DiagramBuilder()
    system = builder.AddSystem(FossSystem(foss, s, period=1.0))
    src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(
        Action("shelf", shelf=ShelfAction("push", "b", 0.02)))))
    builder.Connect(src.get_output_port(), system.GetInputPort("action"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = system.GetMyContextFromRoot(sim.get_context())
    sim.AdvanceTo(0.5)
    assert system.GetOutputPort("history").Eval(ctx) == ()
    sim.AdvanceTo(3.5)
    history = system.GetOutputPort("history").Eval(ctx)
    assert len(history) == 3 and all(o.success for o in history)
    assert system.GetOutputPort("scene").Eval(ctx).object("b").x == pytest.approx(0.21)
