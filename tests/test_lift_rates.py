"""Lift rates of a station in physics: counted from full-fidelity records, written and read back as
YAML, and drawn from by the primitive backend and the search that stands for the station."""

import gzip
import json
import subprocess
import sys

import numpy as np
import pytest

from ms_drake.execution import PrimitiveBackend
from ms_drake.execution.lift_rates import (
    PRIOR_ATTEMPTS,
    LiftRateError,
    LiftRates,
    check_rates,
    count_attempts,
    default_lift_rates_file,
    load_lift_rates,
    write_lift_rates,
)
from ms_drake.experiments.rollout import build_search
from ms_drake.geometry import Workspace
from ms_drake.policies.bin_search import config_scenario, load_bin_search_config
from ms_drake.scenes.layouts import HeapConfig, layout_heap
from ms_drake.types import Action, Grasp

WS = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)


def search_record(kinds, qualities, successes, scenario="PandaBin", fidelity="full"):
    return {"seed": 1, "fidelity": fidelity, "config": {"scenario": scenario}, "grasp_kinds": kinds,
            "grasp_qualities": qualities, "action_successes": successes, "error": ""}


def test_counts_from_search_and_fidelity_records_and_the_shrunk_rate(tmp_path):
    search = tmp_path / "full.jsonl"
    search.write_text(json.dumps(search_record(["parallel_jaw", "", "parallel_jaw", "parallel_jaw"],
                                               [1.0, 0.0, 0.25, 1.0], [True, True, False, True])) + "\n")
    replays = tmp_path / "fidelity.jsonl.gz"
    with gzip.open(replays, "wt") as f:
        f.write(json.dumps({"kind": "attempt", "scenario": "PandaBin", "grasp": "parallel_jaw", "quality": 0.25,
                            "full_lifted": True}) + "\n")
        f.write(json.dumps({"kind": "heap", "seed": 1}) + "\n")
    rates = count_attempts([search, replays], "PandaBin")
    assert rates.counts == {"parallel_jaw": {1.0: [2, 2], 0.25: [1, 2]}}  # the push ("") is no grasp
    assert rates.overall("parallel_jaw") == (3, 4)
    p = 3 / 4
    assert rates.rate("parallel_jaw", 0.25) == pytest.approx((1 + PRIOR_ATTEMPTS * p) / (2 + PRIOR_ATTEMPTS))
    assert rates.rate("parallel_jaw", 0.5) == pytest.approx(p)  # an unmeasured level: the kind's rate
    assert rates.rate("suction", 1.0) is None  # an unmeasured kind: no rate (the draw keeps the quality)


def test_bad_records_name_the_file_and_line(tmp_path):
    other = tmp_path / "yumi.jsonl"
    other.write_text(json.dumps(search_record(["suction"], [1.0], [True], scenario="YuMiBin")) + "\n")
    with pytest.raises(LiftRateError, match=r"yumi.jsonl:1: a record of station 'YuMiBin', not 'PandaBin'"):
        count_attempts([other], "PandaBin")
    prim = tmp_path / "prim.jsonl"
    prim.write_text(json.dumps(search_record(["suction"], [1.0], [True], fidelity="primitive")) + "\n")
    with pytest.raises(LiftRateError, match="prim.jsonl:1: a 'primitive' search"):
        count_attempts([prim], "PandaBin")
    with pytest.raises(LiftRateError, match="missing.jsonl: no such file"):
        count_attempts([tmp_path / "missing.jsonl"], "PandaBin")


def test_yaml_round_trip_keeps_other_stations(tmp_path):
    path = tmp_path / "rates.yaml"
    a = LiftRates({"parallel_jaw": {0.5: [3, 4], 1.0: [9, 10]}}, source="a")
    b = LiftRates({"suction": {1.0: [5, 5]}}, source="b")
    write_lift_rates(path, "PandaBin", a)
    write_lift_rates(path, "YuMiBin", b)
    write_lift_rates(path, "PandaBin", a)  # replaced, not duplicated
    assert load_lift_rates("PandaBin", path).counts == a.counts
    assert load_lift_rates("YuMiBin", path).counts == b.counts and load_lift_rates("YuMiBin", path).source == "b"
    assert load_lift_rates("FetchShelf", path) is None
    path.write_text("PandaBin:\n  parallel_jaw:\n    - {quality: 0.5}\n")
    with pytest.raises(LiftRateError, match="PandaBin.parallel_jaw: a row"):
        load_lift_rates("PandaBin", path)


def test_the_primitive_draw_follows_the_lift_rate_not_the_quality():
    grasp = Action("grasp", grasp=Grasp("parallel_jaw", (0, 0, 0.02), (0, 0, -1), quality=0.25, object_id="a"))
    rates = LiftRates({"parallel_jaw": {0.25: [95, 100]}})
    calibrated = PrimitiveBackend({"a": 1}, WS, tcp_offset=0.1, seed=3, lift_rates=rates)
    plain = PrimitiveBackend({"a": 1}, WS, tcp_offset=0.1, seed=3)
    lifted = [calibrated.outcome(grasp, None, None, k, ())[0].success for k in range(300)]
    assert np.mean(lifted) > 0.85  # p = the rate, ~0.94
    assert np.mean([plain.outcome(grasp, None, None, k, ())[0].success for k in range(300)]) < 0.4  # p = 0.25


def test_the_command_prints_and_writes_the_table(tmp_path):
    rec = tmp_path / "full.jsonl"
    rec.write_text(json.dumps(search_record(["parallel_jaw"] * 3, [1.0, 1.0, 0.5], [True, False, True])) + "\n")
    out = tmp_path / "rates.yaml"
    run = subprocess.run([sys.executable, "-m", "ms_drake.cli", "bench", "lift-rates", str(rec), "--station",
                          "PandaBin", "--out", str(out)], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr
    assert "parallel_jaw" in run.stdout and "1 / 2" in run.stdout
    assert load_lift_rates("PandaBin", out).counts == {"parallel_jaw": {1.0: [1, 2], 0.5: [1, 1]}}
    bad = subprocess.run([sys.executable, "-m", "ms_drake.cli", "bench", "lift-rates", str(rec), "--station",
                          "YuMiBin"], capture_output=True, text=True, check=False)
    assert bad.returncode == 2 and "not 'YuMiBin'" in bad.stderr


def test_the_check_compares_the_rates_and_the_quality_on_other_attempts():
    rates = LiftRates({"suction": {0.25: [9, 10], 1.0: [10, 10]}})
    attempts = [("suction", 0.25, True)] * 8 + [("suction", 0.25, False)] * 2 + [("suction", 1.0, True)] * 10
    c = check_rates(rates, attempts)
    assert c["attempts"] == 20 and c["lifted"] == pytest.approx(0.9)
    assert c["quality"]["predicted"] == pytest.approx((10 * 0.25 + 10) / 20)
    assert c["rates"]["agreement_likelier"] == pytest.approx(0.9)  # always "lifts"
    assert c["quality"]["agreement_likelier"] == pytest.approx(0.6)  # the 0.25s "fail"
    assert c["rates"]["agreement_draw"] > c["quality"]["agreement_draw"]


def test_shipped_rates_are_read_for_the_station_the_search_stands_for():
    shipped = load_lift_rates("PandaBin")
    assert shipped is not None and shipped.overall("parallel_jaw")[1] >= 50, \
        f"{default_lift_rates_file()} should hold PandaBin's measured jaw attempts"
    assert shipped.rate("suction", 1.0) is None  # the Panda has no cup
    assert load_lift_rates("EmptyBin") is None


def test_a_primitive_search_standing_for_a_robot_draws_from_its_lift_rates():
    # The controller of a primitive search standing for the Panda executes with the Panda's
    # shipped rates; standing for no robot, with the qualities.
    heap = layout_heap(HeapConfig(layout="bin_set", objects=4), 0)
    for reach, expect in (("PandaBin", True), ("", False)):
        cfg = load_bin_search_config("ch7", [f"reach={reach}", "heap.objects=4"])
        system = build_search(config_scenario(cfg), heap, cfg)
        backend = system.controller.GetSubsystemByName("action_executor").backend
        assert (backend.lift_rates is not None) == expect
        if expect:
            assert backend.lift_rates.counts == load_lift_rates("PandaBin").counts
