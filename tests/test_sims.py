"""sims/: the scripts a user runs (at most 15), each with a docstring that says what it shows and
how to run it, each run here with its smallest arguments (in this process, so the imports are
paid once). The two search-diagram scripts only show their usage here: tests/test_search_diagram.py
and tests/test_shelf_search_diagram.py run them against the benches action by action."""

import ast
import json
import runpy
import sys
from pathlib import Path

import pytest

import ms_drake.cli
from ms_drake.experiments.picks import TASKS

ROOT = Path(__file__).resolve().parents[1]
SIMS = ROOT / "sims"

# script -> its smallest run ("TMP" is a fresh folder) and a file that run writes (None: stdout only)
RUNS = {
    "bin_search_diagram": (["--help"], None),
    "shelf_search_diagram": (["--help"], None),
    "station_reach": (["--scenario", "PandaBin", "--heaps", "1", "--objects", "5", "--out", "TMP/reach.jsonl"],
                      "reach.jsonl"),
    "grasp_labels": (["all", "--objects", "2", "--grasps", "2", "--trials", "1", "--param-sets", "1", "--robust", "1",
                      "--labels", "TMP/labels.jsonl", "--predictions", "TMP/predictions.jsonl"], "predictions.jsonl"),
    "push_policies": (["speed", "--heaps", "1", "--objects", "3", "--out", "TMP/speed.json"], "speed.json"),
    "push_ablation": ([str(ROOT / "tests/data/push_heaps_ycb"), "--heaps", "1", "--out", "TMP/ablation.jsonl"],
                      "ablation.jsonl"),
    "bench_segmentation": (["--heaps", "1", "--cache", "TMP/cache"], None),
    "bench_occupancy": (["--heaps", "1", "--render-images", "0", "--cache", "TMP/cache"], None),
    "shelf_lift_example": (["--occluders", "4", "--seed", "0", "--max-panels", "2", "--out", "TMP/lift.png"],
                           "lift.png"),
    "shelf_exhaustive": (["--occluders", "4", "--seed", "0", "--depth", "1", "--out", "TMP/plan.json"], "plan.json"),
    "pick_panda_jaw": (["--html", "TMP/panda_jaw.html"], "panda_jaw.html"),
}
PICKS = ("fetch_push", "fetch_suction", "panda_jaw", "yumi_jaw", "yumi_suction")  # sims/pick_<task>.py


def _scripts() -> list[str]:
    return sorted(p.stem for p in SIMS.glob("*.py"))


def _run(name: str, args: list[str]) -> int:
    """Run sims/<name>.py as `python sims/<name>.py ARGS` would; its exit code."""
    saved = sys.argv
    sys.argv = [str(SIMS / f"{name}.py"), *args]
    try:
        runpy.run_path(str(SIMS / f"{name}.py"), run_name="__main__")
        return 0
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = saved


def test_sims_holds_the_scripts_a_user_runs_and_each_is_tested_here():
    assert len(_scripts()) <= 15
    assert set(_scripts()) == set(RUNS) | {f"pick_{t}" for t in PICKS}


@pytest.mark.parametrize("name", _scripts())
def test_every_script_says_what_it_shows_and_how_to_run_it(name):
    doc = ast.get_docstring(ast.parse((SIMS / f"{name}.py").read_text()))
    assert doc, f"sims/{name}.py has no module docstring"
    assert f"sims/{name}.py" in doc, f"sims/{name}.py's docstring shows no command line"
    assert len(doc.splitlines()[0].split()) >= 5, f"sims/{name}.py's docstring says too little of what it shows"


@pytest.mark.parametrize("name", sorted(RUNS))
def test_the_script_runs_with_its_smallest_arguments(name, tmp_path, capsys):
    args, writes = RUNS[name]
    code = _run(name, [a.replace("TMP", str(tmp_path)) for a in args])
    out = capsys.readouterr()
    assert code == 0, out.err[-2000:]
    assert out.out.strip()
    if writes is not None:
        assert (tmp_path / writes).stat().st_size > 0
    if writes and writes.endswith(".json"):
        json.loads((tmp_path / writes).read_text())


@pytest.mark.parametrize("task", PICKS)
def test_each_pick_script_runs_its_pick(task, monkeypatch):
    """The pick scripts are `ms-drake pick TASK` (tests/test_picks.py runs every task; the
    panda_jaw script runs for real above)."""
    assert task in TASKS
    seen = []
    monkeypatch.setattr(ms_drake.cli, "main", lambda: seen.append(list(sys.argv)))
    assert _run(f"pick_{task}", ["--speed", "0.2"]) == 0
    (argv,) = seen
    assert argv[1:3] == ["pick", task] and argv[-2:] == ["--speed", "0.2"]
