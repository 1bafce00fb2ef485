"""sims/shelf_search_diagram.py (the shelf search as plain Drake: DiagramBuilder, the initial
conditions, Simulator.AdvanceTo) run as a subprocess agrees action by action with the benchmark's
record (run_shelf_physics, as `ms-drake bench shelf-physics` writes it) on small scenes: the target
revealed, the horizon reached, and the depth-perception controller."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ms_drake.experiments.shelf_physics import shelf_physics_rollout
from ms_drake.policies.shelf_search import ShelfSearchConfig

SCRIPT = Path(__file__).resolve().parent.parent / "sims" / "shelf_search_diagram.py"
STOP = {"": "target_visible", "horizon": "horizon", "no_action": "no_action", "timeout": "timeout"}


def _script(**kw) -> dict:
    args = [sys.executable, str(SCRIPT), "--scenario", "FetchShelf"]
    for k, v in kw.items():
        if v is not None:
            args += [f"--{k.replace('_', '-')}", str(v)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 1, done.stdout
    return json.loads(lines[0])


@pytest.mark.parametrize("policy, seed, occluders, horizon, perception, stop", [
    ("bluction_dar", 0, 2, None, "ground_truth", "target_visible"),
    ("der3", 22, 6, 1, "ground_truth", "horizon"),
    ("der3", 13, 2, None, "depth", "target_visible"),
])
def test_script_agrees_with_the_benchmark(policy, seed, occluders, horizon, perception, stop):
    out = _script(seed=seed, policy=policy, occluders=occluders, horizon=horizon, perception=perception)
    rec = shelf_physics_rollout(ShelfSearchConfig(policy=policy, horizon=horizon, perception=perception), seed,
                                occluders).record
    assert out["seed"] == rec["seed"] == seed
    assert out["stop_reason"] == STOP[rec["failure"]] == stop
    assert out["success"] == rec["success"] == (stop == "target_visible")
    assert out["actions"] == rec["actions"] and out["actions_taken"] == rec["actions_taken"]
    assert out["action_kinds"] == [a[0] for a in rec["actions_taken"]]
    if perception == "ground_truth":  # with depth the record's outcomes are judged by the truth afterwards
        assert out["outcomes"] == rec["outcomes"]
    assert out["visible_fraction"] == rec["visible_fraction"] and out["sim_seconds"] == rec["sim_seconds"]


def test_idle_step_monitor_keeps_frames_and_changes_nothing():
    """run_shelf_physics's read-only monitor (IdleStepRecorder): one frame per idle step judged, the
    chosen action on all but the last; the record is the same with and without it."""
    plain = shelf_physics_rollout(ShelfSearchConfig(), 0, 2).record
    res = shelf_physics_rollout(ShelfSearchConfig(), 0, 2, keep_frames=True)
    timing = {"seconds", "cpu_seconds", "pid"}
    assert {k: v for k, v in res.record.items() if k not in timing} == \
        {k: v for k, v in plain.items() if k not in timing}
    assert [f.step for f in res.frames] == list(range(plain["steps"] + 1))
    assert [[f.action.shelf.kind, f.action.shelf.object_id] for f in res.frames[:-1]] == \
        [a[:2] for a in plain["actions_taken"]]
    assert res.frames[-1].action is None and res.frames[-1].visible == plain["visible_fraction"]
    assert res.frames[0].rgb.ndim == 3 and res.frames[0].depth.ndim == 2
