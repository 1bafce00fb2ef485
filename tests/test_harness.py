"""The bin-search benchmark harness: `ms-drake bench search` on tiny heaps, resume, failures, plots."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import pytest

from ms_drake.errors import HeapError
from ms_drake.experiments.harness import (
    cached_heap,
    failed_grasps,
    failure_classes,
    final_records,
    heap_generator_key,
    paired_comparison,
    read_records,
    run_bench,
    summarize,
)
from ms_drake.paths import code_version
from ms_drake.perception.occupancy_net import default_weights
from ms_drake.scenes.heaps import heap_digest, load_heap
from ms_drake.types import Heap, ObjectPose

CLI = [sys.executable, "-m", "ms_drake.cli"]


def run(*args, check=True):
    p = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600, check=False)
    if check and p.returncode != 0:
        raise AssertionError(f"exit {p.returncode}\n{p.stdout}\n{p.stderr}")
    return p


def test_bench_search_writes_resumes_and_summarizes(tmp_path):
    out = tmp_path / "r.jsonl"
    p = run("bench", "search", "--policy", "largest", "--objects", 2, "--heaps", 1, "--seed-start", 5,
            "--horizon", 3, "--out", out)
    recs = read_records(out)
    assert [r["seed"] for r in recs] == [5]
    r = recs[0]
    assert {"seed", "policy", "success", "actions", "action_kinds", "failure", "seconds"} <= set(r)
    assert r["policy"] == "largest" and len(r["action_kinds"]) == r["actions"]
    assert len(r["grasp_kinds"]) == len(r["action_successes"]) == r["actions"]
    assert r["grasp_kinds"][0] in ("parallel_jaw", "suction") and r["action_successes"] == [True]
    assert r["grasp_objects"] == ["target"] and 0.15 < r["grasp_qualities"][0] <= 1.0  # the target's grasp
    # heap 5 (grasp sets, the primitive mode's default planner): the first grasp extracts the target
    assert (r["success"], r["actions"], r["action_kinds"], r["failure"], r["grasp_successes"]) == \
        (True, 1, ["grasp"], "", 1)
    assert "success" in p.stdout and "SEM" in p.stdout and "quartiles" in p.stdout
    # Interrupted run: a torn last line; the rerun keeps seed 5, drops the torn line, runs seed 6 only.
    out.write_text(out.read_text() + '{"seed": 6, "pol')
    p = run("bench", "search", "--policy", "largest", "--objects", 2, "--heaps", 2, "--seed-start", 5,
            "--horizon", 3, "--out", out, "--heap-dir", tmp_path / "heaps")
    assert "resuming: 1 of 2" in p.stdout
    assert [f.name for f in (tmp_path / "heaps").iterdir()] == ["heap_N2_s6.json"]  # cached for other policies
    recs = read_records(out)
    assert sorted(x["seed"] for x in recs) == [5, 6]
    assert recs[0] == r  # the finished result was not lost or redone
    # Each record names the heap it searched: the digest of the cached heap file.
    assert recs[1]["heap_digest"] == heap_digest(load_heap(tmp_path / "heaps" / "heap_N2_s6.json"))
    assert recs[1]["code"] == code_version() != ""  # the commit that ran it
    p = run("bench", "plot", out, "--out", tmp_path / "plots")
    for f in ("cumulative_successes.png", "actions_histogram.png"):
        assert (tmp_path / "plots" / f).stat().st_size > 5000
    # --skip-failed is an option of the run: kept in its record, not resumed from the others
    p = run("bench", "search", "--policy", "largest", "--objects", 2, "--heaps", 1, "--seed-start", 5,
            "--horizon", 3, "--out", out, "--skip-failed")
    assert "resuming" not in p.stdout
    assert [x["skip_failed"] for x in read_records(out)] == [False, False, True]


def test_a_failing_rollout_is_named_and_the_benchmark_goes_on(tmp_path):
    out = tmp_path / "f.jsonl"
    # horizon 0 is refused inside the worker (SelectorParams): each rollout fails, none is lost.
    s = run_bench("random", 2, 2, 0, out, workers=1, horizon=0)
    recs = read_records(out)
    assert [x["failure"] for x in recs] == ["worker_died", "worker_died"] and "horizon" in recs[0]["error"]
    assert s["rollouts"] == 2 and s["success_rate"] == 0.0 and s["failures"] == {"worker_died": 2}


def test_summary_statistics():
    recs = [dict(seed=k, policy="p", objects=3, fidelity="primitive", success=k % 2 == 0, actions=k % 4 + 1,
                 failure="" if k % 2 == 0 else "horizon", seconds=1.0) for k in range(40)]
    s = summarize(recs)
    assert s["success_rate"] == 0.5 and s["success_ci"][0] < 0.5 < s["success_ci"][1]
    assert np.isclose(s["mean_actions"], 2.5) and s["actions_ci"][0] < 2.5 < s["actions_ci"][1]
    assert s["quartiles"] == (1.75, 2.5, 3.25) and s["failures"] == {"horizon": 20}
    assert s["success_quartiles"] == (1.0, 2.0, 3.0)  # successes: even k, actions 1 or 3
    assert np.isclose(s["sem_actions"], np.std([k % 4 + 1 for k in range(40)], ddof=1) / np.sqrt(40))
    # A retried rollout replaces its failed line.
    assert final_records(recs[:1] + [dict(recs[0], success=False)])[0]["success"] is False


def test_failures_in_the_reference_s_three_modes():
    """Lines 1326-1328: (1) no action (every want-of-action stop, pushes that never made a grasp),
    (2) the target removed, (3) the budget; the simulator's failures are "other"."""
    fails = ["grasps_below_threshold"] * 5 + ["too_many_pushes"] * 3 + ["target_never_visible", "target_removed",
                                                                       "horizon", "sim_blew_up"]
    recs = [dict(success=False, failure=f) for f in fails] + [dict(success=True, failure="")] * 88
    c = failure_classes(recs)
    assert c["rollouts"] == 100 and c["failures"] == 12 and c["failure_share"] == 0.12
    assert c["no_action"] == {"count": 9, "share": 0.75}
    assert [c[k]["count"] for k in ("target_removed", "horizon", "other")] == [1, 1, 1]
    assert failure_classes([dict(success=True)])["no_action"]["count"] == 0


def test_bad_bench_input(tmp_path):
    p = run("bench", "search", "--policy", "nope", "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "unknown policy" in p.stderr and "largest" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--fidelity", "fast", "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "primitive" in p.stderr
    p = run("bench", "plot", tmp_path / "missing.jsonl", check=False)
    assert p.returncode == 2 and "no such result file" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--grasp-planner", "dexnet", "--out", tmp_path / "x.jsonl",
            check=False)
    assert p.returncode == 2 and "--grasp-planner 'dexnet'" in p.stderr and "indexed, image" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--heap-engine", "physx", "--out", tmp_path / "x.jsonl",
            check=False)
    assert p.returncode == 2 and "--heap-engine 'physx'" in p.stderr and "drake, bullet" in p.stderr
    p = run("bench", "search", "--policy", "xray", "--protocol", "xray", "--heap-engine", "bullet",
            "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "only with --protocol ch7" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--grasp-outcome", "coin", "--out", tmp_path / "x.jsonl",
            check=False)
    assert p.returncode == 2 and "--grasp-outcome 'coin'" in p.stderr and "draw, threshold" in p.stderr


def test_a_run_resumes_only_the_records_of_its_own_grasp_planner(tmp_path):
    out = tmp_path / "g.jsonl"
    assert run_bench("largest", 2, 1, 5, out, horizon=3)["ran"] == 1  # primitive default: the grasp sets
    s = run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image")
    assert s["resumed"] == 0 and s["ran"] == 1
    recs = read_records(out)
    assert [r["grasp_planner"] for r in recs] == ["indexed", "image"]
    s = run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image", grasp_outcome="threshold")
    assert s["resumed"] == 0 and s["ran"] == 1  # another grasp outcome: its own record
    assert [r["grasp_outcome"] for r in read_records(out)] == ["draw", "draw", "threshold"]
    s = run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image", grasp_samples=3)
    assert s["resumed"] == 0 and s["ran"] == 1  # other planner samples: its own record
    assert [r["grasp_samples"] for r in read_records(out)] == [8, 8, 8, 3]
    assert run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image", grasp_samples=3)["ran"] == 0
    s = run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image", grasp_samples=3, skip_failed=True)
    assert s["resumed"] == 0 and s["ran"] == 1  # failed objects passed over: its own record
    assert [r["skip_failed"] for r in read_records(out)] == [False, False, False, False, True]
    s = run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image", grasp_samples=3, jaw_contact="pad")
    assert s["resumed"] == 0 and s["ran"] == 1  # the pad rule: its own record
    assert [r["jaw_contact"] for r in read_records(out)] == ["center"] * 5 + ["pad"]
    with pytest.raises(ValueError, match="jaw contact 'tip' unknown; choose one of center, pad"):
        run_bench("largest", 2, 1, 5, out, horizon=3, jaw_contact="tip")
    assert run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="indexed")["resumed"] == 1
    # a record without the key predates the grasp sets: it was searched with the image planner
    # (and one without grasp_samples with the default 8 candidates)
    old = {k: v for k, v in recs[1].items() if k not in ("grasp_planner", "grasp_samples")}
    out.write_text(json.dumps(old) + "\n")
    assert run_bench("largest", 2, 1, 5, out, horizon=3, grasp_planner="image")["ran"] == 0
    assert run_bench("largest", 2, 1, 5, out, horizon=3)["ran"] == 1


def test_a_run_resumes_only_the_records_of_its_own_occupancy_estimator(tmp_path):
    out, weights = tmp_path / "w.jsonl", tmp_path / "tuned.pt"
    shutil.copy(default_weights(), weights)
    assert run_bench("xray", 2, 1, 5, out, horizon=1, grasp_planner="image")["ran"] == 1
    s = run_bench("xray", 2, 1, 5, out, horizon=1, grasp_planner="image", occupancy_weights=str(weights))
    assert s["resumed"] == 0 and s["ran"] == 1
    assert [r["occupancy_weights"] for r in read_records(out)] == ["", str(weights)]
    assert run_bench("xray", 2, 1, 5, out, horizon=1, grasp_planner="image", occupancy_weights=str(weights))["ran"] == 0
    assert run_bench("xray", 2, 1, 5, out, horizon=1, grasp_planner="image", occupancy="analytic_image")["ran"] == 1
    assert [r["occupancy"] for r in read_records(out)] == ["learned", "learned", "analytic_image"]
    p = run("bench", "search", "--policy", "xray", "--occupancy", "analytic_image", "--occupancy-weights", weights,
            "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "without --occupancy-weights" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--occupancy-weights", weights, "--out", tmp_path / "x.jsonl",
            check=False)
    assert p.returncode == 2 and "the largest policy reads no occupancy" in p.stderr
    p = run("bench", "search", "--policy", "xray", "--occupancy-weights", tmp_path / "none.pt", "--out",
            tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "none.pt not found" in p.stderr


def test_bullet_heaps_are_cached_and_matched_apart_from_drake_heaps(tmp_path):
    out, heaps = tmp_path / "e.jsonl", tmp_path / "heaps"
    assert run_bench("largest", 2, 1, 5, out, horizon=3, heap_dir=str(heaps))["ran"] == 1
    s = run_bench("largest", 2, 1, 5, out, horizon=3, heap_dir=str(heaps), heap_engine="bullet")
    assert s["resumed"] == 0 and s["ran"] == 1
    assert sorted(f.name for f in heaps.iterdir()) == ["heap_N2_s5.json", "heap_bullet_N2_s5.json"]
    assert [r["heap_engine"] for r in read_records(out)] == ["drake", "bullet"]
    assert run_bench("largest", 2, 1, 5, out, horizon=3, heap_dir=str(heaps), heap_engine="bullet")["ran"] == 0
    a, b = (json.loads((heaps / f).read_text()) for f in ("heap_N2_s5.json", "heap_bullet_N2_s5.json"))
    assert a["objects"] != b["objects"]  # two drop simulations of the same seed
    # Each file keeps its generator's key; a cache made with other settings is refused, by name.
    assert a["generator"] == heap_generator_key(2, "ch7", "drake") != b["generator"]
    assert cached_heap(2, 5, str(heaps)).objects == load_heap(heaps / "heap_N2_s5.json").objects
    (heaps / "heap_N2_s5.json").write_text(json.dumps(dict(a, generator="0123456789abcdef")))
    with pytest.raises(HeapError, match="heap_N2_s5.json: this cached heap was made with other generator settings"):
        cached_heap(2, 5, str(heaps))
    (heaps / "heap_N2_s5.json").write_text(json.dumps({k: v for k, v in a.items() if k != "generator"}))
    assert cached_heap(2, 5, str(heaps)).objects == load_heap(heaps / "heap_N2_s5.json").objects  # older files load


def test_truncating_a_record_to_a_smaller_budget():
    from ms_drake.experiments.harness import truncate_record

    def rec(actions, success=False, failure="horizon"):
        return dict(seed=1, policy="largest", objects=5, success=success, actions=actions,
                    action_kinds=["grasp"] * actions, failure=failure, stop_reason=failure or "success")

    assert truncate_record(rec(4, True, ""), 10) == rec(4, True, "")  # ended within the budget
    assert truncate_record(rec(10, True, ""), 10) == rec(10, True, "")  # succeeded with the last action
    assert truncate_record(rec(7, False, "too_many_pushes"), 10)["failure"] == "too_many_pushes"
    cut = truncate_record(rec(14, True, ""), 10)  # succeeded later: a horizon failure at H
    assert (cut["success"], cut["actions"], cut["failure"], len(cut["action_kinds"]), cut["truncated_from"]) == \
        (False, 10, "horizon", 10, 14)
    assert truncate_record(rec(10, False, "grasps_below_threshold"), 10)["failure"] == "horizon"
    assert truncate_record(rec(10, False, "target_removed"), 10)["failure"] == "target_removed"


def test_a_rollout_cut_at_a_smaller_budget_equals_a_run_with_that_budget():
    from ms_drake.experiments.harness import truncate_record
    from ms_drake.experiments.rollout import rollout
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import generate_heap

    keys = ("success", "actions", "action_kinds", "failure")
    seed = 14  # a heap whose random search takes more than three grasps
    heap = generate_heap(load_scenario(None, "BinHeap15"), 5, seed=seed)
    long = rollout("random", 5, seed, heap=heap, horizon=8, grasp_planner="image").record()
    assert long["actions"] >= 4 and long["action_kinds"] == ["grasp"] * long["actions"]
    for h in (2, 3):
        short = rollout("random", 5, seed, heap=heap, horizon=h, grasp_planner="image").record()
        assert {k: short[k] for k in keys} == {k: truncate_record(long, h)[k] for k in keys}


def test_a_killed_two_worker_run_resumes(tmp_path):
    """sims/bench_search.py with a pool of 2: kill the whole run after its first result, rerun the
    same command: every seed once, the first result kept; heaps made by the workers, each once."""
    import json
    import os
    import signal
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    cmd = [sys.executable, str(root / "sims" / "bench_search.py"), "--objects", "2", "--heaps", "3",
           "--seed-start", "40", "--policies", "largest", "--horizon", "2", "--workers", "2", "--out", str(tmp_path)]
    out = tmp_path / "largest_N2_H2.jsonl"
    p = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        t0 = time.time()
        while not (out.exists() and out.read_text().strip()) and time.time() - t0 < 300 and p.poll() is None:
            time.sleep(0.2)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    first = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    assert 1 <= len(first) <= 3
    rerun = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stdout, stderr = rerun.communicate(timeout=600)
    assert rerun.returncode == 0, stderr
    recs = read_records(out)
    assert sorted(x["seed"] for x in recs) == [40, 41, 42] and recs[:len(first)] == first
    # every rollout ran in a pool worker: the killed run's in its workers, the rest in fresh ones
    assert p.pid not in {x["pid"] for x in first}
    assert not {x["pid"] for x in recs[len(first):]} & ({rerun.pid} | {x["pid"] for x in first})
    assert sorted(f.name for f in (tmp_path / "heaps").iterdir()) == [f"heap_N2_s{k}.json" for k in (40, 41, 42)]
    assert "| largest | 2 | 2 |" in stdout


def test_recorded_searches_replay_and_a_changed_record_is_named(tmp_path):
    out, heaps = tmp_path / "r.jsonl", tmp_path / "heaps"
    run("bench", "search", "--policy", "largest", "--objects", 2, "--heaps", 2, "--seed-start", 5, "--horizon", 3,
        "--out", out, "--heap-dir", heaps)
    p = run("bench", "replay", out, "--heap-dir", heaps)
    assert "largest seed 5: same; heap same" in p.stdout and "2 of 2 records replay" in p.stdout
    recs = read_records(out)
    assert all(r["horizon"] == 3 for r in recs)
    # A record that no longer matches what the code does: its outcome flipped, its heap another.
    recs[1] = dict(recs[1], action_successes=[not x for x in recs[1]["action_successes"]], heap_digest="0" * 16)
    out.write_text("".join(json.dumps(r) + "\n" for r in recs))
    p = run("bench", "replay", out, "--heap-dir", heaps, "--seed", 6, check=False)
    assert p.returncode == 1 and "largest seed 6: DIFFERS in action_successes; heap DIFFERS" in p.stdout
    assert "0 of 1 records replay" in p.stdout
    # The heaps alone, without the searches: seed 5's heap is the recorded one, seed 6's digest is not.
    p = run("bench", "replay", out, "--heap-dir", heaps, "--heaps-only", check=False)
    assert p.returncode == 1 and "largest seed 5: heap same" in p.stdout and "largest seed 6: heap DIFFERS" in p.stdout
    assert "1 of 2 records' heaps are the recorded ones" in p.stdout
    p = run("bench", "replay", out, "--seed", 9, check=False)
    assert p.returncode == 2 and "no finished record of seed(s) 9" in p.stderr


def test_heap_digest_names_the_state_and_pairing_refuses_different_heaps(tmp_path):
    q = (1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.05)
    heap = Heap(seed=3, environment="bin", objects=(ObjectPose("ycb/a", q), ObjectPose("ycb/b", q)))
    moved = Heap(seed=3, environment="bin", objects=(ObjectPose("ycb/a", q), ObjectPose("ycb/b", q[:6] + (0.0501,))))
    assert heap_digest(heap) == heap_digest(Heap(seed=3, environment="bin", objects=heap.objects))
    assert heap_digest(moved) != heap_digest(heap)
    rec = lambda seed, ok, digest: dict(seed=seed, policy="p", objects=2, fidelity="primitive", success=ok,
                                        actions=1, heap_digest=digest)
    a = [rec(3, True, heap_digest(heap)), rec(4, True, "x")]
    b = [rec(3, False, heap_digest(heap)), rec(4, False, "x")]
    assert paired_comparison(a, b)["only_a"] == [3, 4]
    b[0]["heap_digest"] = heap_digest(moved)  # seed 3 searched another heap in run B
    with pytest.raises(HeapError, match="different heaps on 1 seed.*3"):
        paired_comparison(a, b)
    # Records without digests (older files) are compared as before.
    assert paired_comparison([dict(r, heap_digest="") for r in a], b)["heaps"] == 2
    fa, fb = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    fa.write_text("".join(json.dumps(r) + "\n" for r in a))
    fb.write_text("".join(json.dumps(r) + "\n" for r in b))
    p = run("bench", "paired", fa, fb, check=False)
    assert p.returncode == 2 and "different heaps" in p.stderr and "--heap-dir" in p.stderr


def test_code_version_names_the_checkout_s_commit():
    root = Path(__file__).resolve().parent.parent
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True)
    if head.returncode != 0 or not (root / "ms_drake" / "paths.py").exists():
        pytest.skip("not a git checkout of ms_drake")
    v = code_version()
    assert v.split("+")[0] == head.stdout.strip() and v in (head.stdout.strip(), head.stdout.strip() + "+dirty")


def test_paired_comparison_gives_the_difference_with_a_bootstrap_interval():
    rec = lambda seed, ok: dict(seed=seed, policy="p", objects=2, fidelity="primitive", success=ok, actions=1)
    a = [rec(k, k % 4 != 0) for k in range(200)]  # 75 %
    b = [rec(k, k % 2 == 0) for k in range(200)]  # 50 %
    c = paired_comparison(a, b)
    assert c["diff"] == pytest.approx(25.0)
    lo, hi = c["diff_ci"]
    assert lo < 25.0 < hi and 10.0 < lo and hi < 40.0  # a paired interval around the difference
    assert paired_comparison(a, b)["diff_ci"] == c["diff_ci"]  # seeded
    assert paired_comparison(a, a)["diff_ci"] == (0.0, 0.0)


def test_failed_grasps_counts_where_the_failed_grasps_went():
    recs = [{"grasp_objects": ["a", "a", "a", "target", "", "target"], "action_successes": [False, False, True, False, True, True],
             "grasp_qualities": [0.25, 0.25, 0.5, 0.5, 0.0, 1.0]},
            {"action_kinds": ["grasp"], "action_successes": [False]}]  # a record without grasp_objects
    f = failed_grasps(recs)
    assert (f["rollouts"], f["grasps"], f["failed"], f["failed_on_target"], f["failed_retries"]) == (1, 5, 3, 1, 1)
    assert f["failed_by_quality"] == {"0.25": 2, "0.50": 1}
    assert f["by_object"] == {"a": [3, 2], "target": [2, 1]}
    f = failed_grasps([{"grasp_objects": ["obj03__ycb__037_scissors", "obj07__ycb__037_scissors"],
                        "action_successes": [False, True], "grasp_qualities": [0.25, 1.0]}])
    assert f["by_object"] == {"ycb__037_scissors": [2, 1]}
