"""Shelf search in FOSS: rollouts, the resumable bench, Table 9.1, `ms-drake bench shelf` and `data shelf`."""

import json
import subprocess
import sys

import numpy as np
import pytest

from ms_drake.errors import MsDrakeError
from ms_drake.experiments.harness import read_records
from ms_drake.experiments.shelf import (
    plot_shelf,
    run_shelf_bench,
    shelf_geometry,
    shelf_records,
    shelf_rollout,
    shelf_table,
)
from ms_drake.policies.shelf import ORACLE_EXHAUSTIVE_SECONDS, ORACLE_WIDE_SECONDS
from ms_drake.policies.shelf_search import ShelfSearchAblation, ShelfSearchConfig
from ms_drake.scenes.shelf import generate_shelf_scene, scene_from_dict

CLI = [sys.executable, "-m", "ms_drake.cli"]
TIMINGS = {"scene_ms", "perception_ms", "decision_ms", "decision_ms_max", "foss_ms", "seconds", "cpu_seconds", "pid"}


def run(*args, check=True):
    p = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600, check=False)
    if check and p.returncode != 0:
        raise AssertionError(f"exit {p.returncode}\n{p.stdout}\n{p.stderr}")
    return p


def cfg(policy, **kw):
    return ShelfSearchConfig(policy=policy, **kw)


def budget(r):
    return r["config"]["oracle_seconds"]


def test_rollout_record_is_reproducible():
    a = shelf_rollout(cfg("bluction_dar"), 6, 3)
    b = shelf_rollout(cfg("bluction_dar"), 6, 3)
    assert {k: v for k, v in a.items() if k not in TIMINGS} == {k: v for k, v in b.items() if k not in TIMINGS}
    assert {"seed", "occluders", "policy", "success", "steps", "config"} <= set(a)
    assert a["config"] == cfg("bluction_dar").record() and "seed" not in a["config"]
    assert a["success"] and a["visible_fraction"] >= 0.8 and a["failure"] == ""
    assert a["steps"] == a["pushes"] + a["suctions"] + a["refused"] <= 12
    assert a["cost"] == a["pushes"] + 1.3 * a["suctions"]


def test_horizon_ends_a_search():
    full = shelf_rollout(cfg("bluction_dar"), 6, 3)
    assert full["steps"] >= 2
    cut = shelf_rollout(cfg("bluction_dar", horizon=1), 6, 3)
    assert (cut["success"], cut["steps"], cut["failure"]) == (False, 1, "horizon")


def test_bench_resumes_and_summarizes(tmp_path):
    out = tmp_path / "dar.jsonl"
    s = run_shelf_bench(cfg("dar"), [4, 6], 2, 10, out)
    recs = read_records(out)
    assert sorted((r["occluders"], r["seed"]) for r in recs) == [(4, 10), (4, 11), (6, 10), (6, 11)]
    assert s["all"]["rollouts"] == 4 and s["resumed"] == 0
    s = run_shelf_bench(cfg("dar"), [4, 6], 3, 10, out)
    assert len(read_records(out)) == 6 and s["resumed"] == 4 and s[4]["rollouts"] == 3
    table = shelf_table(shelf_records([out]))
    assert "| DAR |" in table and "| 4 (3) | success |" in table and "All (6)" in table
    assert plot_shelf(shelf_records([out]), tmp_path).exists()


def test_records_without_a_config_are_refused_naming_the_line(tmp_path):
    out = tmp_path / "old.jsonl"
    out.write_text(json.dumps({"seed": 0, "objects": 4, "policy": "dar", "fidelity": "foss"}) + "\n")
    with pytest.raises(MsDrakeError, match=r"old.jsonl.*line 1.*config"):
        run_shelf_bench(cfg("dar"), [4], 1, 0, out)


def test_oracle_budgets_keep_their_records_and_columns(tmp_path):
    out = tmp_path / "oracle.jsonl"
    run_shelf_bench(cfg("oracle_p"), [4], 2, 0, out)  # the default budget
    s = run_shelf_bench(cfg("oracle_p", oracle_seconds=0.0), [4], 2, 0, out)
    assert s["resumed"] == 0  # the default run's records are not this run's
    recs = read_records(out)
    assert sorted(budget(r) for r in recs) == [0.0, 0.0, ORACLE_EXHAUSTIVE_SECONDS, ORACLE_EXHAUSTIVE_SECONDS]
    assert run_shelf_bench(cfg("oracle_p", oracle_seconds=0.0), [4], 2, 0, out)["resumed"] == 2
    table = shelf_table(shelf_records([out]))
    assert "| Oracle-P | Oracle-P (staged search only) |" in table
    assert run_shelf_bench(cfg("dar"), [4], 1, 0, out)["all"]["rollouts"] == 1
    assert {budget(r) for r in read_records(out) if r["policy"] == "dar"} == {0.0}
    with pytest.raises(MsDrakeError, match="only for the oracles"):
        cfg("dar", oracle_seconds=30.0)
    # Oracle-P+S: its wide search's default budget, its own column without it
    run_shelf_bench(cfg("oracle_ps"), [4], 1, 0, out)
    run_shelf_bench(cfg("oracle_ps", oracle_seconds=0.0), [4], 1, 0, out)
    assert sorted(budget(r) for r in read_records(out) if r["policy"] == "oracle_ps") == [0.0, ORACLE_WIDE_SECONDS]
    assert "| Oracle-P+S | Oracle-P+S (staged search only) |" in shelf_table(shelf_records([out]))


def test_oracle_target_pushes_keep_their_records_and_columns(tmp_path):
    out = tmp_path / "oracle.jsonl"
    plain = cfg("oracle_p", oracle_seconds=0.0)
    pushing = cfg("oracle_p", oracle_seconds=0.0, ablation=ShelfSearchAblation(oracle_push_target=True))
    run_shelf_bench(plain, [6], 1, 43, out)  # 6 / 43: push-locked
    s = run_shelf_bench(pushing, [6], 1, 43, out)
    assert s["resumed"] == 0 and s["all"]["success_rate"] == 1.0
    recs = read_records(out)
    assert [(r["config"]["ablation"]["oracle_push_target"], r["success"]) for r in recs] == [(False, False),
                                                                                             (True, True)]
    assert run_shelf_bench(pushing, [6], 1, 43, out)["resumed"] == 1
    assert ("| Oracle-P (staged search only) | Oracle-P (staged search only), target pushed |"
            in shelf_table(shelf_records([out])))
    with pytest.raises(MsDrakeError, match="ablation.oracle_push_target: only for the oracles"):
        cfg("bluction_dar", ablation=ShelfSearchAblation(oracle_push_target=True))


def test_suction_lift_rules_keep_their_records_and_columns(tmp_path):
    out = tmp_path / "bdar.jsonl"
    floor = cfg("bluction_dar", ablation=ShelfSearchAblation(suction_lift="floor"))
    run_shelf_bench(cfg("bluction_dar"), [8], 2, 0, out)
    s = run_shelf_bench(floor, [8], 2, 0, out)
    assert s["resumed"] == 0
    assert sorted(r["config"]["ablation"]["suction_lift"] for r in read_records(out)) == ["floor", "floor", "over",
                                                                                         "over"]
    assert run_shelf_bench(floor, [8], 2, 0, out)["resumed"] == 2
    assert "| Bluction-DAR | Bluction-DAR, suction lift floor |" in shelf_table(shelf_records([out]))
    with pytest.raises(MsDrakeError, match="over, floor"):
        ShelfSearchAblation(suction_lift="top")


def test_stations_keep_their_records_and_columns(tmp_path):
    """The reference's physical shelf (FetchWideShelf, 0.8 x 0.5 m) beside the simulated one: its
    scenes use its width, its records name it, resume apart and get a column of their own."""
    out = tmp_path / "stations.jsonl"
    wide = shelf_geometry("FetchWideShelf")
    assert np.allclose(2 * wide.half[:2], [0.8, 0.5]) and np.allclose(2 * shelf_geometry().half[:2], [0.6, 0.6])
    run_shelf_bench(cfg("bluction_dar"), [8], 1, 0, out)
    s = run_shelf_bench(cfg("bluction_dar"), [8], 1, 0, out, scenario_name="FetchWideShelf")
    assert s["resumed"] == 0
    recs = read_records(out)
    assert [r["scenario"] for r in recs] == ["FetchShelf", "FetchWideShelf"]
    assert run_shelf_bench(cfg("bluction_dar"), [8], 1, 0, out, scenario_name="FetchWideShelf")["resumed"] == 1
    assert "| Bluction-DAR | Bluction-DAR, FetchWideShelf |" in shelf_table(shelf_records([out]))
    # the wide shelf's scene spreads beyond the 0.6 m shelf's walls
    scene = generate_shelf_scene(wide, 0, 12).scene
    assert max(abs(o.x) + o.width / 2 for o in scene.objects) > 0.3


def test_cli_bench_shelf_and_table(tmp_path):
    out = tmp_path / "r.jsonl"
    p = run("bench", "shelf", "--policy", "oracle_p", "--occluders", 4, 6, "--scenes", 1, "--seed-start", 3,
            "--out", out)
    assert sorted(r["occluders"] for r in read_records(out)) == [4, 6]
    assert "oracle_p occluders all" in p.stdout
    p = run("bench", "shelf", "--policy", "oracle_p", "--occluders", 4, 6, "--scenes", 2, "--seed-start", 3,
            "--out", out)
    assert p.stdout.startswith(f"resuming: 2 of 4 scenes already in {out}; running the other 2")
    assert len(read_records(out)) == 4
    p = run("bench", "shelf", "--policy", "dar", "--occluders", 4, "x", "--out", out, check=False)
    assert p.returncode == 2 and "unexpected argument 'x'" in p.stderr
    p = run("bench", "shelf", "--policy", "dar", "--scenario", "NoShelf", "--out", out, check=False)
    assert p.returncode != 0 and "NoShelf" in p.stderr and "Traceback" not in p.stderr
    p = run("bench", "shelf", "--policy", "xray", "--out", out, check=False)
    assert p.returncode == 2 and "bluction_dar" in p.stderr
    p = run("bench", "shelf", "--policy", "dar", "--set", "oracle_seconds=10", "--out", out, check=False)
    assert p.returncode != 0 and "only for the oracles" in p.stderr and "scene/s" not in p.stderr
    p = run("bench", "shelf", "--policy", "dar", "--set", "ablation.lift=floor", "--out", out, check=False)
    assert p.returncode == 2 and "ablation.lift" in p.stderr and "Traceback" not in p.stderr
    # a config file and --set: the floor lift's records beside the default ones
    (tmp_path / "floor.yaml").write_text("ablation:\n  suction_lift: floor\n")
    run("bench", "shelf", "--policy", "oracle_p", "--occluders", 4, "--scenes", 1, "--seed-start", 3, "--out", out,
        "--config", tmp_path / "floor.yaml", "--set", "horizon=3")
    last = read_records(out)[-1]["config"]
    assert last["ablation"]["suction_lift"] == "floor" and last["horizon"] == 3 and last["policy"] == "oracle_p"
    p = run("bench", "shelf-table", out)
    assert "Oracle-P" in p.stdout and "suction lift floor" in p.stdout


def test_cli_data_shelf_writes_resumable_shards(tmp_path):
    out = tmp_path / "data"
    run("data", "shelf", "--count", 3, "--shard-size", 2, "--out", out)
    shards = sorted(out.glob("shard_*.npz"))
    assert [s.name for s in shards] == ["shard_00000.npz", "shard_00001.npz"]
    d = np.load(shards[0])
    assert d["depth"].shape == (2, 480, 640) and np.isfinite(d["depth"]).any()
    assert d["image_x"].shape == (2, 640) and np.allclose(d["image_x"].sum(axis=1), 1.0)
    assert np.allclose(d["floor"].sum(axis=(1, 2)), 1.0)
    scenes = [scene_from_dict(s) for s in json.loads(str(d["scenes"]))]
    assert [s.seed for s in scenes] == [0, 1] and list(d["target_height"]) == [0.06, 0.03]
    before = shards[1].stat().st_mtime_ns
    p = run("data", "shelf", "--count", 3, "--shard-size", 2, "--out", out, "--no-depth")
    assert "0 shards written, 2 already there" in p.stdout and shards[1].stat().st_mtime_ns == before
