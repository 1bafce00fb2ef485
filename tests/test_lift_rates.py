"""Lift rates of a station in physics: counted from full-fidelity records per gripper kind and
quality, and checked against the quality alone on other attempts."""

import gzip
import json
import subprocess
import sys

import pytest

from ms_drake.execution.lift_rates import (
    PRIOR_ATTEMPTS,
    LiftRateError,
    LiftRates,
    check_rates,
    count_attempts,
)


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


def test_the_command_prints_the_table_and_the_check(tmp_path):
    rec = tmp_path / "full.jsonl"
    rec.write_text(json.dumps(search_record(["parallel_jaw"] * 3, [1.0, 1.0, 0.5], [True, False, True])) + "\n")
    run = subprocess.run([sys.executable, "-m", "ms_drake.cli", "bench", "lift-rates", str(rec), "--station",
                          "PandaBin", "--check", str(rec)], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr
    assert "parallel_jaw" in run.stdout and "1 / 2" in run.stdout and "Brier score" in run.stdout
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
    assert c["rates"]["brier"] < c["quality"]["brier"]


