"""The bin-search benchmark harness: `ms-drake bench search` on tiny heaps, resume, failures, plots."""

import subprocess
import sys

import numpy as np

from ms_drake.experiments.harness import (
    final_records,
    read_records,
    run_bench,
    summarize,
)

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
    assert r["policy"] == "largest" and 1 <= r["actions"] <= 3 and len(r["action_kinds"]) == r["actions"]
    assert r["success"] == (r["failure"] == "")
    assert "success" in p.stdout and "SEM" in p.stdout and "quartiles" in p.stdout
    # Interrupted run: a torn last line; the rerun keeps seed 5, drops the torn line, runs seed 6 only.
    out.write_text(out.read_text() + '{"seed": 6, "pol')
    p = run("bench", "search", "--policy", "largest", "--objects", 2, "--heaps", 2, "--seed-start", 5,
            "--horizon", 3, "--out", out)
    assert "resuming: 1 of 2" in p.stdout
    recs = read_records(out)
    assert sorted(x["seed"] for x in recs) == [5, 6]
    assert recs[0] == r  # the finished result was not lost or redone
    p = run("bench", "plot", out, "--out", tmp_path / "plots")
    for f in ("cumulative_successes.png", "actions_histogram.png"):
        assert (tmp_path / "plots" / f).stat().st_size > 5000


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
    assert np.isclose(s["sem_actions"], np.std([k % 4 + 1 for k in range(40)], ddof=1) / np.sqrt(40))
    # A retried rollout replaces its failed line.
    assert final_records(recs[:1] + [dict(recs[0], success=False)])[0]["success"] is False


def test_bad_bench_input(tmp_path):
    p = run("bench", "search", "--policy", "nope", "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "unknown policy" in p.stderr and "largest" in p.stderr
    p = run("bench", "search", "--policy", "largest", "--fidelity", "fast", "--out", tmp_path / "x.jsonl", check=False)
    assert p.returncode == 2 and "primitive" in p.stderr
    p = run("bench", "plot", tmp_path / "missing.jsonl", check=False)
    assert p.returncode == 2 and "no such result file" in p.stderr
