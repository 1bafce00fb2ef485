"""The bin-search benchmark harness: `ms-drake bench search` on tiny heaps, resume, failures, plots."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

import pytest

from ms_drake.errors import HeapError
from ms_drake.experiments.harness import (
    failed_grasps,
    failure_classes,
    final_records,
    paired_comparison,
    read_records,
    run_bench,
    summarize,
)
from ms_drake.policies.bin_search import BinSearchConfig, load_bin_search_config
from ms_drake.scenes.layouts import HeapConfig, cached_heap, heap_generator_key
from ms_drake.paths import code_version
from ms_drake.scenes.heaps import heap_digest, load_heap
from ms_drake.types import Heap, ObjectPose

CLI = [sys.executable, "-m", "ms_drake.cli"]
TINY = ["--config", "ch7", "--set", "heap.objects=2", "--set", "horizon=3"]  # Ch. 7's setting on 2-object heaps


def tiny(**fields) -> BinSearchConfig:
    """The Ch. 7 setting on 2-object heaps, H = 3, with `fields` (ablation: a dict) changed."""
    ablation = fields.pop("ablation", {})
    cfg = load_bin_search_config("ch7", policy=fields.pop("policy", "largest"), horizon=fields.pop("horizon", 3),
                                 heap=HeapConfig(fields.pop("layout", "bin_set"), 2), **fields)
    cfg.ablation = type(cfg.ablation)(**{**cfg.ablation.__dict__, **ablation})
    return BinSearchConfig(**cfg.to_dict())


def run(*args, check=True):
    p = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600, check=False)
    if check and p.returncode != 0:
        raise AssertionError(f"exit {p.returncode}\n{p.stdout}\n{p.stderr}")
    return p


def test_bench_search_writes_resumes_and_summarizes(tmp_path):
    out = tmp_path / "r.jsonl"
    p = run("bench", "search", "--policy", "largest", *TINY, "--heaps", 1, "--seed-start", 5, "--out", out)
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
    p = run("bench", "search", "--policy", "largest", *TINY, "--heaps", 2, "--seed-start", 5,
            "--out", out, "--heap-dir", tmp_path / "heaps")
    assert "resuming: 1 of 2" in p.stdout
    assert [f.name for f in (tmp_path / "heaps").iterdir()] == ["heap_bin_set_N2_s6.json"]  # cached for other policies
    recs = read_records(out)
    assert sorted(x["seed"] for x in recs) == [5, 6]
    assert recs[0] == r  # the finished result was not lost or redone
    # Each record names the heap it searched: the digest of the cached heap file.
    assert recs[1]["heap_digest"] == heap_digest(load_heap(tmp_path / "heaps" / "heap_bin_set_N2_s6.json"))
    assert recs[1]["code"] == code_version() != ""  # the commit that ran it
    p = run("bench", "plot", out, "--out", tmp_path / "plots")
    for f in ("cumulative_successes.png", "actions_histogram.png"):
        assert (tmp_path / "plots" / f).stat().st_size > 5000
    # an ablation switch is part of the run's config: kept in its record, not resumed from the others
    p = run("bench", "search", "--policy", "largest", *TINY, "--heaps", 1, "--seed-start", 5,
            "--out", out, "--set", "ablation.skip_failed=true")
    assert "resuming" not in p.stdout
    assert [x["config"]["ablation"]["skip_failed"] for x in read_records(out)] == [False, False, True]
    # the whole config is in each record: a replay needs nothing else
    assert BinSearchConfig(**recs[0]["config"]) == dataclasses.replace(tiny(), seed=0)


def test_a_failing_rollout_is_named_and_the_benchmark_goes_on(tmp_path):
    out = tmp_path / "f.jsonl"
    # a scenario file that is not there fails inside the worker: each rollout fails, none is lost.
    cfg = tiny(policy="random")
    cfg.scenario_file = str(tmp_path / "gone.yaml")
    s = run_bench(cfg, 2, 0, out, workers=1)
    recs = read_records(out)
    assert [x["failure"] for x in recs] == ["worker_died", "worker_died"] and "gone.yaml" in recs[0]["error"]
    assert s["rollouts"] == 2 and s["success_rate"] == 0.0 and s["failures"] == {"worker_died": 2}


def test_summary_statistics():
    recs = [dict(seed=k, policy="p", objects=3, fidelity="primitive", success=k % 2 == 0, actions=k % 4 + 1,
                 failure="" if k % 2 == 0 else "horizon", seconds=1.0, config={"policy": "p"}) for k in range(40)]
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
    for setting, message in [("grasp_planner=dexnet", "grasp_planner 'dexnet' unknown; choose one of indexed, image"),
                             ("heap.layout=pile", "heap layout 'pile' unknown; choose one of compact"),
                             ("ablation.grasp_outcome=coin", "ablation.grasp_outcome 'coin' unknown; choose one of"),
                             ("heap.colour=red", "The fields ['colour'] were unknown"),
                             ("horizon", "write KEY=VALUE")]:
        p = run("bench", "search", "--policy", "largest", "--set", setting, "--out", tmp_path / "x.jsonl", check=False)
        assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr, (setting, p.stderr)
    p = run("bench", "search", "--policy", "largest", "--config", "table_9_9", "--out", tmp_path / "x.jsonl",
            check=False)
    assert p.returncode == 2 and "no such file or named setting" in p.stderr and "ch7" in p.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("heap: {objects: many}\n")
    p = run("bench", "search", "--policy", "largest", "--config", bad, "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and str(bad) in p.stderr and "Traceback" not in p.stderr


def test_the_defaults_are_table_8_2_s_setting_and_a_config_round_trips(tmp_path):
    from pydrake.common.yaml import yaml_dump_typed

    cfg = BinSearchConfig()
    assert (cfg.heap.layout, cfg.heap.objects, cfg.horizon, cfg.grasp_planner, cfg.grasp_samples) == \
        ("compact", 14, 10, "image", 32)
    assert (cfg.ablation.grasp_outcome, cfg.ablation.jaw_contact, cfg.segmenter) == ("nominal", "pad", "ground_truth")
    assert load_bin_search_config("table_8_2") == cfg
    ch7 = load_bin_search_config("ch7", ["heap.objects=10", "ablation.skip_failed=true"])
    assert (ch7.heap.layout, ch7.heap.objects, ch7.grasp_planner, ch7.ablation.grasp_outcome) == \
        ("bin_set", 10, "indexed", "draw") and ch7.ablation.skip_failed
    f = tmp_path / "mine.yaml"
    f.write_text(yaml_dump_typed(ch7))
    assert load_bin_search_config(f) == ch7 == BinSearchConfig(**ch7.to_dict())
    p = run("bench", "config", "--config", f, "--set", "horizon=7")
    assert "horizon: 7" in p.stdout and "layout: bin_set" in p.stdout and "compact:" in p.stdout


def test_a_run_resumes_only_the_records_of_its_own_config(tmp_path):
    out = tmp_path / "g.jsonl"
    assert run_bench(tiny(), 1, 5, out)["ran"] == 1
    for changed in (tiny(grasp_planner="image"), tiny(grasp_planner="image", grasp_samples=3),
                    tiny(ablation={"skip_failed": True}), tiny(ablation={"grasp_outcome": "threshold"})):
        s = run_bench(changed, 1, 5, out)
        assert (s["ran"], s["resumed"]) == (1, 0)
        assert run_bench(changed, 1, 5, out)["ran"] == 0  # the same config again: resumed
    recs = read_records(out)
    assert [(r["config"]["grasp_planner"], r["config"]["grasp_samples"], r["config"]["ablation"]["skip_failed"],
             r["config"]["ablation"]["grasp_outcome"]) for r in recs] == [
        ("indexed", 8, False, "draw"), ("image", 8, False, "draw"), ("image", 3, False, "draw"),
        ("indexed", 8, True, "draw"), ("indexed", 8, False, "threshold")]
    assert run_bench(tiny(), 1, 5, out)["resumed"] == 1
    assert len(final_records(recs)) == 5


def test_a_record_without_a_config_is_named(tmp_path):
    out = tmp_path / "old.jsonl"
    out.write_text(json.dumps(dict(seed=1, policy="largest", objects=2, success=True, actions=1)) + "\n")
    p = run("bench", "search", "--policy", "largest", *TINY, "--heaps", 1, "--out", out, check=False)
    assert p.returncode == 2 and "line 1: the record has no 'config'" in p.stderr


def test_heap_layouts_are_cached_apart_and_a_cache_of_other_settings_is_refused(tmp_path):
    out, heaps = tmp_path / "e.jsonl", tmp_path / "heaps"
    assert run_bench(tiny(), 1, 5, out, heap_dir=str(heaps))["ran"] == 1
    s = run_bench(tiny(layout="bin_set_bullet"), 1, 5, out, heap_dir=str(heaps))
    assert s["resumed"] == 0 and s["ran"] == 1
    assert sorted(f.name for f in heaps.iterdir()) == ["heap_bin_set_N2_s5.json", "heap_bin_set_bullet_N2_s5.json"]
    assert [r["config"]["heap"]["layout"] for r in read_records(out)] == ["bin_set", "bin_set_bullet"]
    assert run_bench(tiny(layout="bin_set_bullet"), 1, 5, out, heap_dir=str(heaps))["ran"] == 0
    a, b = (json.loads((heaps / f).read_text()) for f in ("heap_bin_set_N2_s5.json", "heap_bin_set_bullet_N2_s5.json"))
    assert a["objects"] != b["objects"]  # two drop simulations of the same seed
    # Each file keeps its generator's key; a cache made with other settings is refused, by name.
    assert a["generator"] == heap_generator_key(HeapConfig("bin_set", 2)) != b["generator"]
    assert cached_heap(HeapConfig("bin_set", 2), 5, heaps).objects == load_heap(heaps / "heap_bin_set_N2_s5.json").objects
    (heaps / "heap_bin_set_N2_s5.json").write_text(json.dumps(dict(a, generator="0123456789abcdef")))
    with pytest.raises(HeapError, match="heap_bin_set_N2_s5.json: this cached heap was made with other generator"):
        cached_heap(HeapConfig("bin_set", 2), 5, heaps)


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
    cfg = load_bin_search_config("ch7", policy="random", grasp_planner="image", horizon=8)
    long = rollout(cfg, seed, heap=heap).record()
    assert long["actions"] >= 4 and long["action_kinds"] == ["grasp"] * long["actions"]
    for h in (2, 3):
        short = rollout(dataclasses.replace(cfg, horizon=h), seed, heap=heap).record()
        assert {k: short[k] for k in keys} == {k: truncate_record(long, h)[k] for k in keys}


def test_a_killed_two_worker_run_resumes(tmp_path):
    """`bench search --workers 2`: kill the whole run after its first result, rerun the same
    command: every seed once, the first result kept; heaps made by the workers, each once."""
    import os
    import signal
    import time

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "largest.jsonl"
    cmd = [*CLI, "bench", "search", "--policy", "largest", "--config", "ch7", "--set", "heap.objects=2", "--set",
           "horizon=2", "--heaps", "3", "--seed-start", "40", "--workers", "2", "--out", str(out),
           "--heap-dir", str(tmp_path / "heaps")]
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
    assert sorted(f.name for f in (tmp_path / "heaps").iterdir()) == [f"heap_bin_set_N2_s{k}.json" for k in (40, 41, 42)]
    assert stdout.startswith(f"resuming: {len(first)} of 3") and "3 rollouts" in stdout


def test_recorded_searches_replay_and_a_changed_record_is_named(tmp_path):
    out, heaps = tmp_path / "r.jsonl", tmp_path / "heaps"
    run("bench", "search", "--policy", "largest", *TINY, "--heaps", 2, "--seed-start", 5, "--out", out, "--heap-dir", heaps)
    p = run("bench", "replay", out, "--heap-dir", heaps)
    assert "largest seed 5: same; heap same" in p.stdout and "2 of 2 records replay" in p.stdout
    recs = read_records(out)
    assert all(r["config"]["horizon"] == 3 for r in recs)
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
                                        actions=1, heap_digest=digest, config={})
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
    rec = lambda seed, ok: dict(seed=seed, policy="p", objects=2, fidelity="primitive", success=ok, actions=1,
                                config={})
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


def test_the_camera_setting_searches_from_the_camera_alone():
    """The named setting "camera": learned masks, template target matching (its size check on the
    depth) and learned occupancy on the overhead camera's depth through the PhoXi-like sensor model;
    one whole search runs."""
    from ms_drake.experiments.rollout import build_search, run_search
    from ms_drake.policies.bin_search import config_scenario
    from ms_drake.scenes.layouts import layout_heap

    cfg = load_bin_search_config("camera", ["heap.objects=6"], seed=3)
    assert (cfg.segmenter, cfg.detector, cfg.ablation.occupancy, cfg.policy) == ("learned", "template", "learned",
                                                                                 "xray")
    heap = layout_heap(cfg.heap, 3)
    system = build_search(config_scenario(cfg), heap, cfg)
    parts = {name: system.controller.GetSubsystemByName(name) for name in ("segmenter", "target_detector",
                                                                          "occupancy_estimator")}
    assert parts["segmenter"].backend == "learned" and parts["target_detector"].backend == "template"
    assert parts["target_detector"].matcher.extent_max is not None  # the templates carry the target's size
    assert type(parts["occupancy_estimator"].backend).__name__ == "LearnedOccupancy"
    assert system.station.HasSubsystemNamed("depth_sensor_overhead")  # the sensor model is in the camera
    res = run_search(system, heap, cfg)
    assert res.actions >= 1 and res.failure != "sim_blew_up" and res.record()["config"]["scenario"] == \
        "FloatingGripperBinPhoXi"
