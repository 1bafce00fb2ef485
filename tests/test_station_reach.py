"""ms_drake.experiments.station_reach: the summary of per-heap records and resuming from a file."""

import json

import pytest

from ms_drake.experiments.station_reach import format_summary, read_records, run_station_reach, summarize


def _rec(seed, diags):
    g = {"kind": "parallel_jaw", "object": "o", "quality": 1.0, "center": [0, 0, 0.05], "approach": [0, 0, -1],
         "axis": [0, 1, 0], "width": 0.04, "tilt_deg": 0.0}
    s = {"kind": "suction", **{k: v for k, v in g.items() if k != "kind"}}
    return {"seed": seed, "grasps": [g, s], "stations": {"YuMiBin": diags, "PandaBin": [diags[0], None]}}


def test_summarize_counts_per_station_and_kind(tmp_path):
    ok = {"reason": "ok", "step": "", "detail": ""}
    jl = {"reason": "joint_limits", "step": "pre_grasp", "detail": "unreachable"}
    recs = [_rec(1, [ok, jl]), _rec(2, [jl, jl])]
    s = summarize(recs)
    assert s["YuMiBin"]["parallel_jaw"]["reached"] == 1 and s["YuMiBin"]["parallel_jaw"]["of"] == 2
    assert s["YuMiBin"]["suction"]["reasons"] == {"joint_limits@pre_grasp": 2}
    assert "suction" not in s["PandaBin"]  # no suction cup: not counted
    assert "| PandaBin | jaw | 1/2 | 50.0 %" in format_summary(s, 2)
    p = tmp_path / "r.jsonl"
    p.write_text(json.dumps(recs[0]) + "\n" + '{"seed": 3, "cut')  # a line cut by an interrupted run
    assert [r["seed"] for r in read_records(p)] == [1]


def test_run_rejects_a_station_without_an_arm(tmp_path):
    with pytest.raises(ValueError, match="not a bin station with an arm"):
        run_station_reach(["FloatingGripperBin"], 1, 0, str(tmp_path / "r.jsonl"))
