"""Physics-label pipeline, AP / AR with leave-one-object-out selection, and the grasp CLI."""

import json

import numpy as np
import pytest
from sklearn.metrics import average_precision_score

from ms_drake.errors import ObjectSetError
from ms_drake.grasping import GraspError
from ms_drake.grasping import labels as L
from ms_drake.experiments.grasp_figure import grasp_figure


def test_average_recall_definition():
    y = np.array([1, 1, 0, 1])
    q = np.array([1.0, 0.5, 0.9, 0.0])
    # thresholds 0, .1, ..., 1: recall 1 at 0, 2/3 for 0.1..0.5, 1/3 for 0.6..1.0
    assert L.average_recall(y, q) == pytest.approx((1 + 5 * 2 / 3 + 5 * 1 / 3) / 11)
    assert np.isnan(L.average_recall(np.zeros(3), q[:3]))


def _write(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_leave_one_object_out_picks_the_parameters_that_generalize(tmp_path):
    rng = np.random.default_rng(0)
    objects = ["a", "b", "c", "d"]
    rows, keys = [], []
    for o in objects:
        for i in range(12):
            rows.append({"object": o, "index": i, "label": float(rng.random() < 0.5)})
            keys.append([o, i])
    y = np.array([r["label"] >= 0.5 for r in rows])
    good = np.where(y, 0.8, 0.2) + rng.normal(scale=0.05, size=len(y))  # informative
    noise = rng.random(len(y))  # uninformative
    preds = [{"model": "point", "param_index": k, "params": {"friction": f}, "robust": 0, "ms_per_grasp": 1.0,
              "quality": list(map(float, q)), "keys_sha1": L._keys_hash(rows)}
             for k, (f, q) in enumerate([(0.3, noise), (0.9, good)])]
    _write(tmp_path / "labels.jsonl", rows)
    _write(tmp_path / "pred.jsonl", preds)
    (row,) = L.loo_table(tmp_path / "labels.jsonl", tmp_path / "pred.jsonl")
    assert row["chosen_params"] == [{"friction": 0.9}]
    obj = np.array([k[0] for k in keys])
    expect = np.mean([average_precision_score(y[obj == o], good[obj == o]) for o in objects])
    assert row["AP"] == pytest.approx(expect)
    assert row["AR"] == pytest.approx(np.mean([L.average_recall(y[obj == o], good[obj == o]) for o in objects]))
    assert "| Point (non-robust) |" in L.format_table([row])


def test_labels_and_predictions_are_resumable(tmp_path):
    lab, pred = tmp_path / "l.jsonl", tmp_path / "p.jsonl"
    L.generate_labels(["procedural/box_000"], lab, grasps_per_object=2, trials=1, log=lambda s: None)
    rows = L._read_jsonl(lab)
    assert len(rows) == 2 and all(r["trials"][0] in (0, 1) for r in rows)
    L.generate_labels(["procedural/box_000"], lab, grasps_per_object=2, trials=1, log=lambda s: None)
    assert len(L._read_jsonl(lab)) == 2  # nothing redone
    L.predict(lab, pred, models=("soft_point",), param_sets=2, robust_samples=2, log=lambda s: None)
    P = L._read_jsonl(pred)
    assert len(P) == 4 and all(len(p["quality"]) == 2 for p in P)
    L.predict(lab, pred, models=("soft_point",), param_sets=2, robust_samples=2, log=lambda s: None)
    assert len(L._read_jsonl(pred)) == 4
    assert L.parameter_sets("reach", 3)[1]["material_constant"] > 0


def test_grasp_cli_writes_png_and_prints_table(tmp_path, capsys):
    png = grasp_figure(object="procedural/box_000", model="soft_point", samples=6, out=tmp_path, robust=2)
    assert png.is_file() and png.stat().st_size > 10_000
    data = json.loads((tmp_path / "procedural_box_000_soft_point.json").read_text())
    assert len(data["grasps"]) == 6 and all(0 <= g["quality"] <= 1 for g in data["grasps"])
    out = capsys.readouterr().out
    assert "quality" in out and "wrote" in out
    with pytest.raises(ObjectSetError, match="no object"):
        grasp_figure(object="no_such_thing", out=tmp_path)
    with pytest.raises(GraspError, match="unknown grasp model"):
        grasp_figure(object="procedural/box_000", model="hertz", out=tmp_path)


def test_object_mesh_is_watertight_for_every_set():
    from ms_drake.grasping.meshes import object_mesh
    from ms_drake.objects import available_sets, get_object_set

    for s in available_sets():
        for spec in get_object_set(s).objects[:3]:
            m = object_mesh(spec.full_name)
            assert m.is_watertight and m.volume > 0, spec.full_name
