"""ActionExecutor: alone (FixValue action, Eval outputs after unrestricted updates) and wired in the
controller diagram for one search step in each fidelity (primitive: floating gripper; full: YuMi)."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.execution import (
    ActionExecutor,
    ExecutionError,
    PrimitiveBackend,
    connect_executor,
    grasp_tool_pose,
)
from ms_drake.geometry import Workspace
from ms_drake.types import Action, Grasp, Push

WS = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)


def backend(seed=0):
    return PrimitiveBackend({"a": 1, "b": 2}, WS, tcp_offset=0.1, target_id="b", seed=seed)


def poses(a=(0.0, 0.0, 0.02), b=(0.05, 0.0, 0.02)):
    return [RigidTransform(), RigidTransform(list(a)), RigidTransform(list(b))]


def step(system, context, t):
    sim = Simulator(system, context)
    sim.AdvanceTo(t)
    return context


def test_executor_alone_latches_only_when_idle_and_records_outcomes():
    ex = ActionExecutor(backend(seed=3), period=0.05)
    ctx = ex.CreateDefaultContext()
    park = ex.GetOutputPort("floating.position").Eval(ctx)
    assert park[0] > 0.25 and abs(park[3] - np.pi) < 1e-9  # beside the bin, pointing down
    ex.poses_port.FixValue(ctx, poses())
    push = Action("push", push=Push((0.0, 0.0, 0.02), (0.1, 0.0, 0.02), "a"))
    fixed = ex.action_port.FixValue(ctx, push)
    step(ex, ctx, 0.3)
    st = ex.GetOutputPort("status").Eval(ctx)
    assert st.busy and st.steps == 0
    # A new action while busy is ignored: the push goes on.
    fixed.GetMutableData().set_value(Action("grasp", grasp=Grasp("parallel_jaw", (0, 0, 0.02), (0, 0, -1),
                                                                   quality=1.0, object_id="a")))
    q_mid = ex.GetOutputPort("floating.position").Eval(ctx).copy()
    assert np.linalg.norm(q_mid[:3] - park[:3]) > 0.05  # on its way to the push
    step(ex, ctx, 8.0)
    hist = ex.GetOutputPort("history").Eval(ctx)
    assert [o.action.kind for o in hist[:2]] == ["push", "grasp"]
    assert hist[0].success and hist[0].removed_object == ""
    assert hist[1].success and hist[1].removed_object == "a"  # quality 1: always lifted
    # the grasp stays on the fixed action input, so it is done again each time the executor is idle
    # (from the second on, it ends at its check: "a" is gone already and the scene is at rest)
    assert len(hist) == 42 and all(o.action.kind == "grasp" and o.success for o in hist[1:])
    assert "a" in ex.GetOutputPort("removed").Eval(ctx)
    assert ex.GetOutputPort("outcome").Eval(ctx) == hist[-1]  # the latest outcome
    np.testing.assert_allclose(ex.GetOutputPort("floating.position").Eval(ctx), park)  # parked again


def test_an_action_ends_once_the_scene_is_at_rest():
    grasp = Action("grasp", grasp=Grasp("parallel_jaw", (0, 0, 0.02), (0, 0, -1), quality=1.0, object_id="a"))

    def run(moving: bool, connected: bool = True, finger: bool = False, removed_moves: bool = False):
        ex = ActionExecutor(backend(), period=0.05)
        ctx = ex.CreateDefaultContext()
        ex.action_port.FixValue(ctx, grasp)
        sim = Simulator(ex, ctx)
        ends = None
        for k in range(1, 14):
            if connected:
                X = poses(a=(0.005 * k if removed_moves else 0.0, 0.0, 0.02),
                          b=(0.05 + (0.005 * k if moving else 0.0), 0.0, 0.02))
                # body 3: a robot body (not an object of the backend), chattering by 16 mm
                ex.poses_port.FixValue(ctx, X + [RigidTransform([0.3 + 0.016 * (k % 2 if finger else 0), 0.0, 0.2])])
            sim.AdvanceTo(0.05 * k)
            st = ex.GetOutputPort("status").Eval(ctx)
            if ends is None and st.steps == 1 and not st.busy:
                ends = 0.05 * k
        return ends

    assert run(moving=False) == pytest.approx(0.2)  # at rest: ends after still_time, not the 0.5 s settle
    assert run(moving=True) == pytest.approx(0.55)  # a body keeps moving 5 mm per update: the full settle
    assert run(moving=False, connected=False) == pytest.approx(0.55)  # no body poses: the full settle
    # only the heap is watched: neither a chattering robot body nor the lifted (removed) object
    assert run(moving=False, finger=True) == pytest.approx(0.2)
    assert run(moving=False, removed_moves=True) == pytest.approx(0.2)


def test_a_failed_grasp_on_a_scene_at_rest_ends_at_its_check():
    """A primitive grasp that lifts nothing leaves the scene as it was: when the action before it
    ended at rest, it ends at its check (one update); else it waits for rest as any action."""
    miss = Action("grasp", grasp=Grasp("parallel_jaw", (0, 0, 0.02), (0, 0, -1), quality=0.0, object_id="a"))

    def ends(moving_until: float):
        ex = ActionExecutor(backend(), period=0.05)
        ctx = ex.CreateDefaultContext()
        ex.action_port.FixValue(ctx, miss)
        sim, out, last = Simulator(ex, ctx), [], 0
        for k in range(1, 30):
            x = 0.005 * min(k, moving_until / 0.05)
            ex.poses_port.FixValue(ctx, poses(b=(0.05 + x, 0.0, 0.02)))
            sim.AdvanceTo(0.05 * k)
            st = ex.GetOutputPort("status").Eval(ctx)
            if st.steps > last and not st.busy:
                out.append(round(0.05 * k, 3))
                last = st.steps
        assert not any(o.success for o in ex.GetOutputPort("history").Eval(ctx))
        return out[:4]

    # at rest throughout: the first miss settles (0.2 s), the next ones take one update each (+ idle)
    assert ends(0.0) == [0.2, 0.3, 0.4, 0.5]
    # the heap moves for the first 0.6 s: the first miss runs its 0.5 s bound, not at rest, so the
    # second waits for rest too; from then on, one update each
    assert ends(0.6) == [0.55, 0.75, 0.85, 0.95]


def test_extracting_the_target_ends_the_action_at_its_check():
    """The target's successful grasp ends the search: no settle of the heap after it (the other
    objects keep moving here, which would otherwise run the full 0.5 s settle)."""
    def run(object_id):
        ex = ActionExecutor(backend(), period=0.05)
        ctx = ex.CreateDefaultContext()
        ex.action_port.FixValue(ctx, Action("grasp", grasp=Grasp("suction", (0, 0, 0.02), (0, 0, -1), quality=1.0,
                                                                 object_id=object_id)))
        sim = Simulator(ex, ctx)
        for k in range(1, 14):
            ex.poses_port.FixValue(ctx, poses(a=(0.005 * k, 0.0, 0.02), b=(0.05 + 0.005 * k, 0.0, 0.02)))
            sim.AdvanceTo(0.05 * k)
            st = ex.GetOutputPort("status").Eval(ctx)
            if st.steps == 1 and not st.busy:
                return 0.05 * k

    assert run("b") == pytest.approx(0.1)  # the target: idle at the check, one update after the start
    assert run("a") == pytest.approx(0.55)  # another object: the heap settles (here: the full bound)


def test_grasp_success_follows_quality_and_seed():
    def run(q, seed):
        b = backend(seed)
        a = Action("grasp", grasp=Grasp("suction", (0, 0, 0.02), (0, 0, -1), quality=q, object_id="a"))
        return [b.outcome(a, None, poses(), k, ())[0].success for k in range(200)]

    assert not any(run(0.0, 1)) and all(run(1.0, 1))
    half = run(0.5, 1)
    assert sum(half) == 99 and half == run(0.5, 1) and half != run(0.5, 2)


def test_stop_ends_and_accidental_target_removal_is_named():
    ex = ActionExecutor(backend(), period=0.05)
    ctx = ex.CreateDefaultContext()
    ex.poses_port.FixValue(ctx, poses())
    ex.action_port.FixValue(ctx, Action("stop", reason="horizon"))
    step(ex, ctx, 0.2)
    st = ex.GetOutputPort("status").Eval(ctx)
    assert st.done and st.stop_reason == "horizon" and st.steps == 0
    b = backend()
    out, gone = b.outcome(Action("push", push=Push((0, 0, 0), (0.1, 0, 0), "a")), None,
                          poses(b=(0.5, 0.0, -0.2)), 0, ())
    assert out.message == "target_removed" and out.removed_object == "b" and gone == ("b",)


def test_bad_actions_and_unconnected_input():
    ex = ActionExecutor(backend())
    ctx = ex.CreateDefaultContext()
    with pytest.raises(ExecutionError, match="connect the action input"):
        step(ex, ctx, 0.1)
    with pytest.raises(ExecutionError, match="kind 'shelf'"):
        backend().plan(Action("shelf"), backend().initial_commands(), 0)


def test_grasp_tool_pose_axes():
    X = grasp_tool_pose(Grasp("parallel_jaw", (0.1, 0.0, 0.05), (0, 0, -1), axis=(0, 1, 0)))
    R = X.rotation().matrix()
    np.testing.assert_allclose(R[:, 2], [0, 0, -1])
    np.testing.assert_allclose(R[:, 0], [0, 1, 0])
    assert np.isclose(np.linalg.det(R), 1.0)


@pytest.fixture(scope="module")
def heap5():
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap

    return generate_heap(load_scenario(None, "BinHeap15"), 4, seed=3, params=SEARCH_HEAPS)


def test_one_search_step_primitive(heap5):
    from ms_drake.experiments.rollout import build_search, run_search
    from ms_drake.policies.bin_search import load_bin_search_config
    from ms_drake.scenario import load_scenario

    params = load_bin_search_config("ch7", policy="largest", horizon=1, seed=0, grasp_planner="image")
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap5, params)
    res = run_search(system, heap5, params)
    # one grasp lifts an object other than the target; the horizon of 1 action ends the search
    assert (res.actions, res.action_kinds, res.grasp_successes) == (1, ["grasp"], 1)
    assert (res.success, res.stop_reason, res.failure) == (False, "horizon", "horizon")


def test_executor_wired_in_diagram_with_fixed_action():
    """Wired to a station: a push moves the floating gripper through the bin and back."""
    from ms_drake.scenario import load_scenario
    from ms_drake.station import MakeStation, get_plant

    s = load_scenario(None, "FloatingGripperBin")
    s.objects.count = 0
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    from ms_drake.execution import tcp_offset_of

    ex = builder.AddSystem(ActionExecutor(PrimitiveBackend({}, Workspace.from_scenario(s),
                                                           tcp_offset_of(get_plant(station)))))
    connect_executor(builder, ex, station)
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    ex.action_port.FixValue(ex.GetMyContextFromRoot(ctx),
                            Action("push", push=Push((-0.1, 0.0, 0.02), (0.05, 0.0, 0.02), "x")))
    sim = Simulator(diagram, ctx)
    lowest = np.inf
    for t in np.arange(0.25, 6.0, 0.25):
        sim.AdvanceTo(t)
        q = station.GetOutputPort("floating.position_measured").Eval(station.GetMyContextFromRoot(ctx))
        lowest = min(lowest, q[2])
    assert lowest < 0.02 + tcp_offset_of(get_plant(station)) + 0.02  # the tcp came down to the push height
    assert ex.GetOutputPort("history").Eval(ex.GetMyContextFromRoot(ctx))[0].action.kind == "push"


def test_one_search_step_full_yumi(heap5):
    from ms_drake.experiments.rollout import build_search, run_search
    from ms_drake.policies.bin_search import load_bin_search_config
    from ms_drake.scenario import load_scenario

    params = load_bin_search_config("ch7", policy="largest", fidelity="full", horizon=1, seed=0, grasp_planner="image")
    system = build_search(load_scenario(None, "YuMiBin"), heap5, params)
    res = run_search(system, heap5, params)
    # one grasp lifts an object other than the target; the horizon of 1 action ends the search
    assert (res.actions, res.action_kinds, res.grasp_successes) == (1, ["grasp"], 1)
    assert (res.success, res.stop_reason, res.failure) == (False, "horizon", "horizon")


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.0, -1.0), (1.0, 1.0), (-1.0, 2.0), (-3.0, -1.0)])
def test_the_primitive_push_leads_with_the_jaws_broad_side(direction):
    """Forward kinematics of the floating base (the chain Rx(roll) Ry(pitch) Rz(yaw)) at the commanded
    positions along the push: the tool points down and the jaw's closing axis (x of its body frame,
    along which its broad side lies) is perpendicular to the push direction, diagonal pushes included."""
    from pydrake.multibody.plant import MultibodyPlant

    from ms_drake.paths import make_parser
    from ms_drake.station.robots import add_floating_gripper

    plant = MultibodyPlant(1e-3)
    base, grip = add_floating_gripper(plant, make_parser(plant), "parallel_jaw")
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    d = np.array([*direction, 0.0]) / np.linalg.norm(direction)
    a = np.array([0.0, 0.0, 0.02])
    b = backend()
    motion = b.plan(Action("push", push=Push(tuple(a), tuple(a + 0.08 * d), "a")), {"floating.position": b.park}, 0)
    path = motion.commands["floating.position"]
    for t in np.linspace(path.t[1], path.t[4], 7):  # above the start, down, along the push, up
        q = path(t)
        assert abs(q[5]) <= 0.5 * np.pi + 1e-9  # the shorter of the two equivalent yaws
        plant.SetPositions(ctx, base, q)
        R = plant.GetFrameByName("body", grip).CalcPoseInWorld(ctx).rotation().matrix()
        assert R[:, 2] @ [0, 0, -1] == pytest.approx(1.0, abs=1e-9)  # tool pointing down
        assert abs(R[:, 0] @ d) < 1e-9  # closing axis across the push: the broad side leads


def test_fast_transfers_shorten_only_the_legs_between_park_and_above_the_push():
    push = Action("push", push=Push((0.0, 0.0, 0.02), (0.1, 0.0, 0.02), "a"))
    slow = backend()
    fast = PrimitiveBackend({"a": 1, "b": 2}, WS, tcp_offset=0.1, target_id="b", transfer_speed=2.0)
    hold = slow.initial_commands()
    ms, mf = slow.plan(push, hold, 0), fast.plan(push, hold, 0)
    ps, pf = ms.commands["floating.position"], mf.commands["floating.position"]
    legs_s, legs_f = np.diff(ps.t), np.diff(pf.t)
    assert legs_f[0] < 0.3 * legs_s[0] and legs_f[4] < 0.3 * legs_s[4]  # park -> above, above -> park
    np.testing.assert_allclose(legs_f[1:4], legs_s[1:4])  # down, along the segment, up: unchanged
    for a, b in zip(ps.points, pf.points):  # the same waypoints
        np.testing.assert_allclose(a, b)
    assert mf.duration < ms.duration - 1.0
    with pytest.raises(ValueError, match="transfer_speed"):
        PrimitiveBackend({}, WS, tcp_offset=0.1, transfer_speed=0.0)


def test_threshold_grasp_outcomes_are_deterministic_and_draws_follow_the_quality():
    def grasp(q):
        return Action("grasp", grasp=Grasp("suction", (0, 0, 0.02), (0, 0, -1), quality=q, object_id="a"))

    det = PrimitiveBackend({"a": 1, "b": 2}, WS, tcp_offset=0.1, target_id="b", seed=5, grasp_outcome="threshold")
    for q, lifted in ((0.25, False), (0.49, False), (0.5, True), (0.75, True)):
        outs = {det.outcome(grasp(q), None, poses(), step, ())[0].success for step in range(40)}
        assert outs == {lifted}  # the same at every step: a failed grasp fails again on the same state
    draw = backend(seed=5)
    lifted = [draw.outcome(grasp(0.25), None, poses(), step, ())[0].success for step in range(400)]
    assert 0.15 < np.mean(lifted) < 0.35  # p = quality
    failed = det.outcome(grasp(0.25), None, poses(), 0, ())[0]
    assert failed.removed_object == "" and failed.message == "grasp_failed"
    with pytest.raises(ExecutionError, match="grasp_outcome 'coin' unknown.*draw, threshold, checked, nominal"):
        PrimitiveBackend({}, WS, tcp_offset=0.1, grasp_outcome="coin")


def test_nominal_grasp_outcome_is_the_grasps_nominal_lift_verdict():
    def grasp(q, lifts):
        return Action("grasp", grasp=Grasp("suction", (0, 0, 0.02), (0, 0, -1), quality=q, object_id="a", lifts=lifts))

    nom = PrimitiveBackend({"a": 1, "b": 2}, WS, tcp_offset=0.1, target_id="b", seed=5, grasp_outcome="nominal")
    for q, lifts in ((0.25, True), (1.0, False), (0.0, False), (0.75, True)):
        outs = {nom.outcome(grasp(q, lifts), None, poses(), step, ())[0].success for step in range(20)}
        assert outs == {lifts}  # the verdict decides, not the robust quality, at every step
    with pytest.raises(ExecutionError, match="needs the grasp's nominal lift verdict.*grasp_planner='image'"):
        nom.outcome(grasp(1.0, None), None, poses(), 0, ())


def test_a_grasp_on_a_piece_lifts_its_object_and_on_no_object_lifts_nothing():
    def grasp(oid):
        return Action("grasp", grasp=Grasp("suction", (0, 0, 0.02), (0, 0, -1), quality=1.0, object_id=oid, lifts=True))

    nom = PrimitiveBackend({"a": 1, "b": 2}, WS, tcp_offset=0.1, target_id="b", seed=5, grasp_outcome="nominal")
    piece = nom.outcome(grasp("b@3"), None, poses(), 0, ())[0]  # a segmenter's second piece of the target
    assert (piece.success, piece.removed_object) == (True, "b")
    bin_mask = nom.outcome(grasp("seg_4"), None, poses(), 0, ())[0]  # a mask no object covers half of
    assert (bin_mask.success, bin_mask.removed_object, bin_mask.message) == (False, "", "no_object")


def test_the_full_jaw_grips_with_the_grasp_models_closing_force():
    from ms_drake.execution import FullBackend
    from ms_drake.grasping.evaluator import GraspEvaluator
    from ms_drake.robots import CLOSING_FORCE
    from ms_drake.scenario import load_scenario

    s = load_scenario(None, "YuMiBin")
    ws = Workspace.from_scenario(s)
    g = Grasp("parallel_jaw", (ws.center_xy[0], ws.center_xy[1], ws.floor_z + 0.03), (0, 0, -1), axis=(0, 1, 0),
              width=0.05, object_id="a")
    hold = FullBackend(s, {"a": 1}, ws).initial_commands()
    for force in (None, 25.0):
        fb = FullBackend(s, {"a": 1}, ws, **({} if force is None else {"grip_force": force}))
        motion = fb.plan(Action("grasp", grasp=g), hold, 0)
        assert not isinstance(motion, str), motion
        limits = {float(v[0]) for _, v in motion.commands["yumi_right_jaw.force_limit"].steps}
        assert limits == {CLOSING_FORCE if force is None else force}
    assert GraspEvaluator("soft_point").closing_force == CLOSING_FORCE  # the force the qualities assume
    with pytest.raises(ExecutionError, match="grip_force"):
        FullBackend(s, {"a": 1}, ws, grip_force=0.0)


def test_executor_state_copy_is_isolated_and_shallow():
    """Drake deep-copies abstract state on every update: _State's copy shares the frozen contents
    (no cost growing with the history) and replacing a field of the copy leaves the original."""
    import copy

    from ms_drake.execution.executor import _State
    from ms_drake.types import Action, ActionOutcome

    out = ActionOutcome(Action("stop", reason="x"), True)
    s = _State(history=(out,), hold={"a": np.zeros(3)}, removed=("o1",))
    c = copy.deepcopy(s)
    assert c is not s and c.history[0] is out
    c.history = c.history + (out,)
    c.removed = c.removed + ("o2",)
    c.hold = dict(c.hold, b=np.ones(1))
    c.phase = "executing"
    assert len(s.history) == 1 and s.removed == ("o1",) and set(s.hold) == {"a"} and s.phase == "idle"
