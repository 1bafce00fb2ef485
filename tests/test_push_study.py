"""The Ch. 4 push study: metrics, the physics push, determinism, the summary."""

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion  # noqa: F401

from ms_drake.experiments.push_study import (
    METRICS,
    GraspSets,
    PushStudyAblation,
    PushStudyConfig,
    PushWorld,
    _mesh,
    format_push_table,
    mean_separation,
    run_policy,
    separation_gain,
    state_metrics,
    study_heap,
    summarize_push,
    write_push_heaps,
)
from ms_drake.errors import MsDrakeError
from ms_drake.geometry import Workspace
from ms_drake.pushing import POLICIES
from ms_drake.types import Heap, ObjectPose

BIN = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)
BOX = "procedural/box_117"  # 5.3 x 4.5 x 3.4 cm


def test_mean_separation_by_hand():
    # One object at the centre: D is its distance to the nearest wall (0.2 m, the y walls).
    assert mean_separation(np.array([[0.0, 0.0]]), BIN) == pytest.approx(0.2)
    # Two objects 0.1 m apart on the x axis: (0.1 + 0.2 + 0.2) / (1 + 2).
    assert mean_separation(np.array([[-0.05, 0.0], [0.05, 0.0]]), BIN) == pytest.approx(0.5 / 3)
    assert separation_gain(0.1, 0.2) == pytest.approx(0.5) and separation_gain(0.2, 0.1) == pytest.approx(-0.5)
    assert separation_gain(0.0, 0.0) == 0.0


def _pair_heap():
    """Two boxes touching side by side (along x), 10 cm from the +y wall, resting on the floor."""
    v = np.asarray(_mesh(BOX).vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    z = -lo[2] + 0.001
    ex = hi[0] - lo[0]
    xa, xb = -0.5 * ex - 0.0005 - 0.5 * (hi[0] + lo[0]), 0.5 * ex + 0.0005 - 0.5 * (hi[0] + lo[0])
    y = 0.10 - 0.5 * (hi[1] + lo[1])
    objs = (ObjectPose(BOX, (1.0, 0.0, 0.0, 0.0, xa, y, z)), ObjectPose(BOX, (1.0, 0.0, 0.0, 0.0, xb, y, z)))
    return Heap(seed=0, environment="bin", objects=objs)


@pytest.fixture(scope="module")
def pair_world():
    w = PushWorld(_pair_heap(), PushStudyConfig())
    w.advance(0.3)
    return w


def test_boundary_shear_separates_two_touching_boxes(pair_world):
    w = pair_world
    snap = w.snapshot()
    sets = GraspSets(PushStudyConfig(), seed=0)
    before = state_metrics(w, sets)
    assert before["objects"] == 2
    rec = run_policy(w, snap, before, sets, "boundary_shear", seed=0)
    assert rec["pushed"] and rec["push"]["object"] in w.ids
    assert rec["separation_gain"] > 0.05  # pushed along the boundary, toward the bin's middle
    assert rec["left_bin"] == 0
    for m in METRICS[1:]:
        assert -1.0 <= rec[m] <= 1.0
    # The pushed box moved; the state is restored for the next policy.
    w.restore(snap)
    again = state_metrics(w, sets)
    assert again["D"] == pytest.approx(before["D"]) and again["overall"] == before["overall"]


def test_metrics_are_deterministic_under_a_seed(pair_world):
    w = pair_world
    snap = w.snapshot()
    out = []
    for _ in range(2):
        w.restore(snap)
        sets = GraspSets(PushStudyConfig(), seed=7)
        before = state_metrics(w, sets)
        out.append([run_policy(w, snap, before, sets, p, seed=7) for p in ("quasi_random", "free_space")])
    for a, b in zip(*out):
        assert a["push"] == b["push"]
        for m in METRICS:
            assert a[m] == b[m]


def test_grasp_sets_see_the_neighbour(pair_world):
    # A box's jaw grasps across the pair's shared side are pruned by the neighbour: its best jaw
    # quality with the neighbour is at most its best alone.
    w = pair_world
    w.restore(w.snapshot())
    sets = GraspSets(PushStudyConfig(), seed=0)
    both = sets.qualities(w)
    alone = sets.qualities(w, ids=[w.ids[0]])
    assert both["per_object"][w.ids[0]][0] <= alone["per_object"][w.ids[0]][0] + 1e-12
    assert 0.0 <= both["overall"] <= 1.0 and both["overall"] == max(both["jaw"], both["suction"])


def test_summary_means_and_anova():
    rows = []
    rng = np.random.default_rng(0)
    for s in range(20):
        for k, p in enumerate(POLICIES):
            rows.append({"seed": s, "policy": p, "pushed": True, "separation_gain": 0.01 * k + 0.01 * rng.random(),
                         "jaw_gain": 0.1, "suction_gain": 0.0, "overall_gain": 0.1 + 0.05 * (p == "free_space")})
    for r in rows:
        r["objects"] = 1 if r["seed"] < 5 else 4
    rows.append({"seed": 99, "policy": "free_space", "pushed": True, **{m: 1.0 for m in METRICS}})  # not common
    s = summarize_push(rows)
    assert s["by_objects"]["1"]["heaps"] == 5 and s["by_objects"][">=4"]["heaps"] == 15 and "2" not in s["by_objects"]
    assert s["by_objects"][">=4"]["free_space"] == pytest.approx(0.15)
    assert ">=4 (15)" in format_push_table(s)
    assert s["heaps"] == 20
    assert s["policies"]["free_space"]["overall_gain"]["mean"] == pytest.approx(0.15)
    assert s["policies"]["quasi_random"]["jaw_gain"]["se"] == pytest.approx(0.0)
    a = s["anova"]["separation_gain"]
    assert a["df"] == [4, 95] and a["p"] < 1e-6


def test_metrics_do_not_depend_on_the_states_measured_before(pair_world):
    # Grasp sets keyed by (seed, object, tilt bin): measuring after a push and then the start
    # state gives the start state's metrics of a fresh measurement.
    w = pair_world
    snap = w.snapshot()
    fresh = state_metrics(w, GraspSets(PushStudyConfig(), seed=3))
    used = GraspSets(PushStudyConfig(), seed=3)
    before = state_metrics(w, used)
    run_policy(w, snap, before, used, "quasi_random", seed=11)
    w.restore(snap)
    again = state_metrics(w, used)
    assert again["per_object"] == fresh["per_object"]
    assert (again["jaw"], again["suction"]) == (fresh["jaw"], fresh["suction"])


def test_mesh_object_heaps_score_and_collide_with_convex_parts():
    """PushStudyConfig.object_set: a household-mesh heap (YCB, convex collision parts) is drawn from
    that set, its grasps are scored on the closed meshes, and the collision check sees the convex
    parts (a neighbour pressed against an object prunes grasps there)."""
    params = PushStudyConfig(object_set="ycb", grasps=20, robust_samples=0)
    heap, n = study_heap(3, params)
    assert len(heap.objects) == n and all(o.name.startswith("ycb/") for o in heap.objects)
    cube = "ycb/077_rubiks_cube"
    v = np.asarray(_mesh(cube).vertices)
    assert _mesh(cube).is_watertight
    lo, hi = v.min(axis=0), v.max(axis=0)
    ex, z = hi[0] - lo[0], -lo[2] + 0.001
    cx, cy = 0.5 * (hi[0] + lo[0]), 0.5 * (hi[1] + lo[1])
    objs = tuple(ObjectPose(cube, (1.0, 0.0, 0.0, 0.0, x - cx, -cy, z)) for x in (-0.5 * ex - 0.0005, 0.5 * ex + 0.0005))
    w = PushWorld(Heap(seed=0, environment="bin", objects=objs), params)
    w.advance(0.2)
    sets = GraspSets(params, seed=0)
    both = sets.qualities(w)
    alone = sets.qualities(w, ids=[w.ids[0]])
    assert 0.0 < alone["overall"] <= 1.0  # a cube on the floor has a grasp
    assert both["per_object"][w.ids[0]][0] <= alone["per_object"][w.ids[0]][0] + 1e-12


def test_push_heaps_folder_keeps_one_config(tmp_path):
    procedural = asdict(PushStudyConfig(object_set="procedural"))
    (tmp_path / "heaps.jsonl").write_text(json.dumps({"seed": 0, "config": procedural, "stop": "cleared",
                                                      "improvable": False}) + "\n")
    with pytest.raises(MsDrakeError, match=r"heaps.jsonl, line 1: a heap of another config \(object_set='procedural'\)"):
        write_push_heaps(1, tmp_path, seed_start=0, params=PushStudyConfig())
    fast = PushStudyConfig(object_set="procedural", ablation=PushStudyAblation(transfer_speed=2.0))
    with pytest.raises(MsDrakeError, match="ablation="):
        write_push_heaps(1, tmp_path, seed_start=0, params=fast)
    (tmp_path / "heaps.jsonl").write_text('{"seed": 0, "object_set": "", "stop": "cleared", "improvable": false}\n')
    with pytest.raises(MsDrakeError, match="no config"):
        write_push_heaps(1, tmp_path, seed_start=0, params=PushStudyConfig())


def test_bench_rerun_from_the_stored_state(tmp_path):
    # The committed YCB records: the first improvable heap's quasi-random push re-executed from its
    # stored poses (no drop, no grasping), with the fast transfers.
    from ms_drake.experiments.push_study import improvable_records, read_jsonl, run_push_bench

    src = Path(__file__).resolve().parent / "data" / "push_heaps_ycb"
    rec = improvable_records(src, 1)[0]
    out = tmp_path / "rows.jsonl"
    fast = PushStudyConfig(ablation=PushStudyAblation(transfer_speed=2.0))
    s = run_push_bench("quasi_random", 1, 0, out, src, rerun=True, from_state=True, params=fast)
    assert s["rows"] == 1 and s["new"] == 1
    row = read_jsonl(out)[0]
    assert row["source"] == "state" and row["seed"] == rec["seed"] and row["cpu_s"] > 0
    assert row["config"]["ablation"]["transfer_speed"] == 2.0 and row["config"]["object_set"] == "ycb"
    # the state at rest scores as the data step scored it (same grasp samples, poses to 1 um)
    assert row["before"]["overall"] == pytest.approx(rec["before"]["overall"])
    assert row["pushed"] and row["push"]["object"] == rec["policies"]["quasi_random"]["push"]["object"]
    again = dict(rerun=True, from_state=True, params=fast)
    assert run_push_bench("quasi_random", 1, 0, out, src, **again)["new"] == 0  # resumes


def _tilted(deg: float) -> np.ndarray:
    """A pose of the box on its side tilted by `deg` about x (gravity in another tilt bin)."""
    a = np.radians(deg)
    X = np.eye(4)
    X[:3, :3] = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    X[:3, 3] = [0.0, 0.0, 0.05]
    return X


@pytest.mark.parametrize("sampling", ["object", "tilt_bin"])
def test_sampling_object_draws_the_same_grasps_in_every_tilt_bin(sampling):
    # "object": one draw per (seed, object) -- the same surface points and trial seed in two tilt
    # bins (common random numbers); "tilt_bin": a fresh draw per bin.
    sets = GraspSets(PushStudyConfig(ablation=PushStudyAblation(sampling=sampling)), seed=5)
    a, b = sets._sets("obj00", BOX, _tilted(0.0)), sets._sets("obj00", BOX, _tilted(8.0))
    assert a[3] != b[3]  # two tilt bins
    same_seed = a[4] == b[4]
    pa = {tuple(np.round(p, 9)) for p, _, _ in a[2]}
    pb = {tuple(np.round(p, 9)) for p, _, _ in b[2]}
    shared = len(pa & pb) / max(1, min(len(pa), len(pb)))
    if sampling == "object":
        assert same_seed and shared > 0.5  # the same draws (some filtered by each bin's approach limit)
    else:
        assert not same_seed and shared < 0.1


def test_sampling_names_are_checked():
    with pytest.raises(ValueError, match="sampling 'bins' unknown; choose one of 'tilt_bin', 'object'"):
        PushStudyAblation(sampling="bins")
    with pytest.raises(ValueError, match="compare_sampling"):
        PushStudyAblation(compare_sampling="x")
    with pytest.raises(ValueError, match="object_set 'toys' unknown"):
        PushStudyConfig(object_set="toys")


def test_compare_sampling_scores_the_same_push(pair_world):
    # The second sampling's gains ride on the same executed push: a push that moves nothing in the
    # second metric's view gives equal separation gains in both.
    w = pair_world
    snap = w.snapshot()
    p = PushStudyConfig(ablation=PushStudyAblation(sampling="object"))
    sets, alt = GraspSets(p, seed=2), GraspSets(PushStudyConfig(), seed=2)
    before, alt_before = state_metrics(w, sets), state_metrics(w, alt)
    rec = run_policy(w, snap, before, sets, "boundary_shear", seed=0, compare=(alt, alt_before))
    assert rec["pushed"] and set(METRICS) <= set(rec["compare"])
    assert rec["compare"]["separation_gain"] == pytest.approx(rec["separation_gain"])
    assert rec["compare"]["overall_gain"] == pytest.approx(rec["compare"]["after"]["overall"] - alt_before["overall"])


def test_motion_of_measures_displacement_and_rotation():
    from ms_drake.experiments.push_study import motion_of
    a = np.eye(4)
    b = _tilted(30.0)  # 30 degrees about x, 5 cm up
    m = motion_of({"o1": a, "o2": a}, {"o1": b, "o2": a}, "o1")
    assert m["pushed_tilt_deg"] == pytest.approx(30.0) and m["pushed_displacement"] == pytest.approx(0.05)
    assert m["max_tilt_deg"] == pytest.approx(30.0)
    yaw = np.eye(4)
    yaw[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # a quarter turn about the vertical: no tilt change
    assert motion_of({"o1": a}, {"o1": yaw}, "o1")["pushed_tilt_deg"] == pytest.approx(0.0, abs=1e-6)
    m = motion_of({"o1": a, "o2": a}, {"o2": b}, "o1")  # the pushed object left the bin
    assert m["pushed_displacement"] == 0.0 and m["max_displacement"] == pytest.approx(0.05)


def test_cli_push_heaps_names_a_bad_sampling(tmp_path):
    from typer.testing import CliRunner

    from ms_drake.cli import app

    r = CliRunner().invoke(app, ["data", "push-heaps", "--count", "1", "--out", str(tmp_path), "--set",
                                 "ablation.sampling=bins"])
    assert r.exit_code != 0 and "ablation.sampling 'bins' unknown; choose one of 'tilt_bin', 'object'" in r.output
    assert not (tmp_path / "heaps.jsonl").exists()
    r = CliRunner().invoke(app, ["bench", "push", "--policy", "quasi_random", "--out", str(tmp_path / "r.jsonl"),
                                 "--heap-dir", str(Path(__file__).resolve().parent / "data" / "push_heaps_ycb"),
                                 "--rerun", "--set", "grasps=3"])
    assert r.exit_code != 0 and "ablation switches" in r.output


def test_quasi_random_checked_reaches_the_planner():
    assert not PushStudyConfig().policy_params().quasi_random_checked
    assert PushStudyConfig(ablation=PushStudyAblation(quasi_random_checked=True)).policy_params().quasi_random_checked
