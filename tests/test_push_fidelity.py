"""The push study's full fidelity: one box pushed by the YuMi and by the primitive mode, an
unreachable push, the agreement measure."""

import numpy as np
import pytest
from pydrake.math import RotationMatrix

from ms_drake.experiments.push_fidelity import (
    FidelityPair,
    agreement,
    gain_sign,
    summarize_fidelity,
    wilson,
    yaw_change,
)
from ms_drake.experiments.push_study import PushWorld, PushStudyConfig, _mesh
from ms_drake.scenes.heaps import heap_to_dict
from ms_drake.types import Heap, ObjectPose

BOX = "procedural/box_117"  # 5.3 x 4.5 x 3.4 cm
X0, Y0 = -0.06, -0.05  # in the YuMi's reach (the bin centre is at 0.45 m from its base)


def _motion(center, dist, left=False):
    return {"center": list(center), "dist": dist, "left": left, "dxy": [0.0, 0.0], "yaw": 0.0}


def test_agreement_by_hand():
    # 2 cm + 25 % of the primitive displacement: a 10 cm push may end 4.5 cm apart, not 5.
    p = {"a": _motion([0.10, 0.0], 0.10), "b": _motion([0.3, 0.3], 0.0, left=True)}
    ok, per = agreement(p, {"a": _motion([0.144, 0.0], 0.144), "b": _motion([9.0, 9.0], 1.0, left=True)})
    assert ok and per["a"]["tol"] == pytest.approx(0.045) and per["b"]["ok"]
    assert not agreement(p, {"a": _motion([0.151, 0.0], 0.15), "b": _motion([9.0, 9.0], 1.0, left=True)})[0]
    # leaving the bin in one execution only disagrees, wherever the centres are
    assert not agreement(p, {"a": _motion([0.10, 0.0], 0.1), "b": _motion([0.3, 0.3], 0.0, left=False)})[0]
    assert gain_sign(0.25) == 1 and gain_sign(-1e-12) == 0 and gain_sign(-0.5) == -1
    lo, hi = wilson(8, 10)
    assert 0.49 < lo < 0.5 and 0.94 < hi < 0.95  # the textbook Wilson interval of 8/10


def test_yaw_change():
    R0 = RotationMatrix.MakeXRotation(0.3).matrix()
    assert yaw_change(R0, RotationMatrix.MakeZRotation(0.5).matrix() @ R0) == pytest.approx(0.5)
    # rolling about a horizontal axis has no yaw
    assert yaw_change(R0, RotationMatrix.MakeYRotation(1.0).matrix() @ R0) == pytest.approx(0.0, abs=1e-9)


def _box_record():
    """A heap record with one box on the floor at (X0, Y0), settled in the primitive world."""
    v = np.asarray(_mesh(BOX).vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    q = (1.0, 0.0, 0.0, 0.0, X0 - 0.5 * (hi[0] + lo[0]), Y0 - 0.5 * (hi[1] + lo[1]), -lo[2] + 0.001)
    heap = Heap(seed=0, environment="bin", objects=(ObjectPose(BOX, q),))
    w = PushWorld(heap, PushStudyConfig())
    w.advance(0.3)
    return {"seed": 0, "heap": heap_to_dict(heap), "state": w.poses_record(), "improvable": True}


@pytest.fixture(scope="module")
def box_pair():
    return FidelityPair(_box_record())


def test_yumi_push_moves_the_box_as_the_primitive_does(box_pair):
    pair = box_pair
    # along +x, from 4.5 cm behind the centre to 3 cm past it, tcp 2.5 cm above the floor
    # (fingertips 1 cm above it)
    push = {"start": [X0 - 0.045, Y0, 0.025], "end": [X0 + 0.03, Y0, 0.025], "object": pair.ids[0]}
    row = pair.compare("quasi_random", push)
    assert row["status"] == "ok", row.get("plan_status")
    oid = pair.ids[0]
    full = row["full"]["motion"][oid]
    assert 0.04 < full["dxy"][0] < 0.08  # pushed forward by about the 7.5 cm segment minus the gap
    assert abs(full["dxy"][1]) < 0.01 and abs(full["yaw"]) < 0.1 and not full["left"]  # straight
    # The study's primitive jaw (5 ms) slides it the same way; the 10 ms step launches it (module
    # docstring), so only its forward motion is checked.
    m = row["primitive"]["motion"][oid]
    assert abs(m["dist"] - full["dist"]) < 0.01 and row["per_object"][oid]["gap"] < 0.01 and row["agree"] is True
    assert row["coarse"]["motion"][oid]["dxy"][0] > 0.04
    s = summarize_fidelity([row])
    assert s["status"] == {"ok": 1} and s["agree"]["k"] == 1 and s["agree"]["n"] == 1


def test_push_out_of_reach_is_unreachable(box_pair):
    # at the far wall (0.75 m from the YuMi's base) with the tool pointing down
    push = {"start": [0.20, 0.10, 0.03], "end": [0.22, 0.10, 0.03], "object": box_pair.ids[0]}
    row = box_pair.compare("quasi_random", push)
    assert row["status"] == "unreachable" and row["plan_status"] == "unreachable"
    assert row["agree"] is None and row["gain_sign_agree"] is None
    assert row["primitive"]["status"] == "ok"  # the floating jaw goes anywhere
    assert "coarse" not in row  # the diagnostic side only where the YuMi pushed
    s = summarize_fidelity([row])
    assert s["status"] == {"unreachable": 1} and s["agree"]["n"] == 0


def test_the_study_and_the_pushing_selectors_push_at_the_same_plant_step():
    from ms_drake.execution import PRIMITIVE_PUSH_TIME_STEP
    from ms_drake.policies.bin_search import BinSearchConfig, search_scenario
    from ms_drake.policies.bin_selectors import POLICIES as SELECTORS, PUSHING
    from ms_drake.scenario import load_scenario
    from ms_drake.types import Heap

    assert PushStudyConfig().time_step == PRIMITIVE_PUSH_TIME_STEP == 0.005
    station, heap = load_scenario(None, "FloatingGripperBin"), Heap(seed=0, environment="bin", objects=())
    for p in SELECTORS:
        step = search_scenario(station, heap, BinSearchConfig(policy=p)).plant_config.time_step
        assert step == (PRIMITIVE_PUSH_TIME_STEP if p in PUSHING else 0.01)


def test_a_push_the_home_branch_cannot_line_up_is_planned_from_another_ik_solution():
    # A push of the study's heaps (YCB seed 11, boundary shear) beside the bin's centre line: from
    # the IK solution above the start nearest the park configuration the arm cannot follow the
    # straight lines (it would jump between branches); from a solution of the 7-joint arm at the
    # push's start it can.
    from pydrake.math import RigidTransform

    from ms_drake.planning.cartesian import ik_pose
    from ms_drake.planning.sequences import arm_ik, plan_push
    from ms_drake.scenario import load_scenario

    ik, limits, q_home, keep = arm_ik(load_scenario(None, "YuMiBin"), "yumi_right", seed=0)
    a, b = np.array([-0.0600, 0.1020, 0.03]), np.array([-0.0554, 0.0720, 0.03])
    d = b - a
    R = RotationMatrix.MakeZRotation(np.arctan2(d[1], d[0]) + np.pi / 2) @ RotationMatrix.MakeXRotation(np.pi)
    X = RigidTransform(R, a)
    assert not plan_push(ik, limits, q_home, X, d, np.linalg.norm(d), "yumi_right", branches=0).success
    plan = plan_push(ik, limits, q_home, X, d, np.linalg.norm(d), "yumi_right")
    assert plan.success, plan.status
    tl = plan.timeline
    at_start = ik_pose(ik, tl.value(tl.marks["push"]))
    at_end = ik_pose(ik, tl.value(tl.marks["pushed"]))
    assert np.linalg.norm(at_start.translation() - a) < 3e-3 and np.linalg.norm(at_end.translation() - b) < 3e-3
    assert at_start.rotation().InvertAndCompose(R).ToAngleAxis().angle() < 0.02
