"""The ms-drake command: every subcommand on tiny inputs, resume, and clear errors."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CLI = [sys.executable, "-m", "ms_drake.cli"]


def run(*args, check=True):
    p = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"exit {p.returncode}\n{p.stdout}\n{p.stderr}")
    return p


def test_demo_writes_images_and_recording(tmp_path):
    p = run("demo", "--out", tmp_path, "--objects", 4, "--seed", 2, "--horizon", 3)
    for f in ("overhead_rgb.png", "overhead_depth.png", "overhead_masks.png", "overhead_target.png",
              "heap.json", "meshcat_recording.html", "step_00.png", "search.gif"):
        assert (tmp_path / f).stat().st_size > 1000, f
    assert str(tmp_path) in p.stdout
    heap = json.loads((tmp_path / "heap.json").read_text())
    assert 1 <= len(heap["objects"]) <= 4 and heap["target"]
    res = json.loads((tmp_path / "search.json").read_text())
    assert res["policy"] == "xray" and 1 <= res["actions"] <= 3 and res["success"] == (res["failure"] == "")
    # from the camera alone: learned masks, template matching checked on the noisy overhead depth
    assert (res["config"]["segmenter"], res["config"]["detector"]) == ("learned", "template")
    assert res["config"]["scenario"] == "FloatingGripperBinPhoXi"
    steps = sorted(tmp_path.glob("step_*.png"))
    assert len(steps) in (res["actions"], res["actions"] + 1)  # one per chosen action (+ the final stop)
    import cv2

    img = cv2.imread(str(steps[0]))
    assert img.shape == (480, 3 * 640, 3) and img.std() > 5  # masks | occupancy | action panels


def test_scene_on_table_and_shelf(tmp_path):
    import cv2

    for name in ("PandaTable", "FetchShelf"):
        out = tmp_path / name
        run("scene", name, "--seed", 1, "--objects", 3, "--out", out, "--scenario-file", _no_robot_file(tmp_path))
        img = cv2.imread(str(out / "front_rgb.png"))
        assert img.shape == (480, 640, 3) and img.std() > 5


def _no_robot_file(tmp_path):
    """A copy of the shipped scenarios with robots removed (robots come with their own issue)."""
    import re

    from ms_drake.scenario import default_scenarios_file

    text = default_scenarios_file().read_text()
    text = re.sub(r"\n  robot: \{[^\n]*\}", "", text)
    p = tmp_path / "scenarios.yaml"
    p.write_text(text)
    return p


def test_heaps_resume_without_duplicates(tmp_path):
    out = tmp_path / "h.jsonl"
    run("heaps", "--objects", 2, "--count", 2, "--seed-start", 10, "--out", out)
    lines = out.read_text().splitlines()
    assert sorted(json.loads(x)["seed"] for x in lines) == [10, 11]
    # Simulate a run killed mid-write: a torn last line.
    out.write_text(out.read_text() + '{"seed": 12, "obj')
    p = run("heaps", "--objects", 2, "--count", 4, "--seed-start", 10, "--workers", 2, "--out", out)
    assert "resuming: 2 of 4" in p.stdout
    recs = [json.loads(x) for x in out.read_text().splitlines()]
    assert sorted(r["seed"] for r in recs) == [10, 11, 12, 13]
    for r in recs:
        assert {"seed", "objects", "target", "seconds"} <= set(r)
    # Same seed, same heap, whichever worker made it.
    again = tmp_path / "again.jsonl"
    run("heaps", "--objects", 2, "--count", 1, "--seed-start", 13, "--out", again)
    a = json.loads(again.read_text())
    b = [r for r in recs if r["seed"] == 13][0]
    assert a["objects"] == b["objects"]
    # The Drake drop world on request: another heap for the same seed.
    drake = tmp_path / "drake.jsonl"
    run("heaps", "--objects", 2, "--count", 1, "--seed-start", 13, "--engine", "drake", "--out", drake)
    assert json.loads(drake.read_text())["objects"] != b["objects"]
    assert json.loads(drake.read_text())["engine"] == "drake" and b["engine"] == "bullet"


def test_diagram(tmp_path):
    run("diagram", "BinHeap15", "--out", tmp_path / "d.dot")
    assert "digraph" in (tmp_path / "d.dot").read_text()
    if shutil.which("dot"):
        run("diagram", "BinHeap15", "--out", tmp_path / "d.svg")
        assert "<svg" in (tmp_path / "d.svg").read_text()
    else:
        p = run("diagram", "BinHeap15", "--out", tmp_path / "d.svg", check=False)
        assert p.returncode == 2 and "apt-get install graphviz" in p.stderr


@pytest.mark.parametrize("args,needle", [
    (["scene", "NoSuchScenario"], "no scenario named 'NoSuchScenario'"),
    (["heaps", "--objects", "0", "--out", "x.jsonl"], "--objects"),
    (["heaps", "--count", "1", "--out", "x.txt"], ".jsonl"),
    (["heaps", "--count", "1", "--object-set", "nope", "--out", "x.jsonl"], "unknown object set 'nope'"),
    (["heaps", "--count", "1", "--engine", "ode", "--out", "x.jsonl"], "--engine ode: use bullet or drake"),
    (["heaps", "--count", "1", "--engine", "drake", "--polish", "0.5", "--out", "x.jsonl"], "--polish: only with"),
    (["diagram", "--out", "x.gif"], ".svg, .png or .dot"),
    (["pick", "ur5_jaw"], "unknown pick task 'ur5_jaw'; choose one of yumi_jaw, yumi_suction, panda_jaw"),
    (["grasp", "--object", "procedural/no_such_box"], "no_such_box"),
    (["grasp", "--object", "procedural/box_000", "--model", "hertz"], "unknown grasp model"),
    (["data", "occupancy", "--count", "1", "--out", "d", "--ground-truth", "exact"],
     "--ground-truth 'exact': choose one of generator, posterior"),
    (["data", "occupancy", "--count", "1", "--out", "d", "--ground-truth", "posterior", "--best-match", "0.05"],
     "--best-match is a setting of the generator's ground truth"),
])
def test_bad_input_is_a_clear_error_without_traceback(tmp_path, args, needle):
    p = subprocess.run([*CLI, *args], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert p.returncode == 2
    assert needle in p.stderr
    assert "Traceback" not in p.stderr


HEAPS = Path(__file__).parent / "data" / "push_heaps_ycb"


@pytest.mark.parametrize("command", [["bench", "fidelity"], ["bench", "push-fidelity", "--heap-dir", HEAPS]])
def test_robot_benches_take_a_scenario_file(tmp_path, command):
    p = run(*command, "--scenario-file", tmp_path / "none.yaml", "--out", tmp_path / "r.jsonl", check=False)
    assert p.returncode == 2 and "none.yaml" in p.stderr and "Traceback" not in p.stderr
    p = run(*command, "--scenario-file", _no_robot_file(tmp_path), "--out", tmp_path / "r.jsonl", check=False)
    assert p.returncode == 2 and "YuMiBin" in p.stderr and "Traceback" not in p.stderr  # its YuMiBin has no robot
