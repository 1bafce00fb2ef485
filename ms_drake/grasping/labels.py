"""Physics-labelled grasp sets and the AP / AR evaluation of the contact models (Table 2.1).

Three resumable stages, each appending JSON lines to a file (a rerun skips what is done):

1. `generate_labels`: per object (registry name), antipodal grasps sampled on its mesh in its
   canonical upright pose (gravity -z), axes within a 35-degree cone of the surface normal,
   centres jittered by up to `center_noise` (the reference adds uniform noise within the pad
   width, line 190), the jaws opened to the gripper's full 10 cm, each simulated `trials` times with
   `simulate_grasp` under seeded perturbations. Label = success rate; positive when >= 0.5.
2. `predict`: every model's quality for every grasp under `param_sets` random parameter sets
   drawn as in the reference (line 229: mu ~ U(0.3, 1.5); torsional friction ~ U(0.001, 0.02) m
   for the soft point model -- the text's U(0.01, 1) is a dimensionless coefficient, ours is a
   length; material constant ~ U(1e-4, 1e-2) m/N for the area models), non-robust and robust.
3. `loo_table`: leave-one-object-out selection of the parameter set (the best mean AP over the
   other objects), then AP (scikit-learn average_precision_score) and AR (recall averaged over
   the thresholds 0.0, 0.1, ..., 1.0, predicting success when quality >= threshold) on the
   held-out object, averaged over objects. AP is averaged over objects having both outcomes,
   AR over objects having at least one success.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from sklearn.metrics import average_precision_score

from ms_drake.grasping.evaluator import MODELS, GraspEvaluator
from ms_drake.grasping.grasp import ParallelJawGrasp
from ms_drake.grasping.meshes import object_mesh
from ms_drake.grasping.physics import label_grasp
from ms_drake.grasping.samplers import sample_antipodal_grasps
from ms_drake.objects import available_sets, get_object, get_object_set
from ms_drake.robots import PadConfig

THRESHOLDS = np.round(np.arange(0.0, 1.01, 0.1), 2)


def _read_jsonl(path: Path) -> list[dict]:
    if not Path(path).is_file():
        return []
    out = []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if line:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by an interrupted run
                continue
    return out


def _append(path: Path, row: dict):
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(row, separators=(",", ":")) + "\n")
        f.flush()


def _keys_hash(rows) -> str:
    """Identifies the label set (and its order) a prediction row was computed on."""
    return hashlib.sha1(json.dumps([[r["object"], r["index"]] for r in rows]).encode()).hexdigest()


def default_label_objects(count: int = 24, max_min_extent: float = 0.075) -> list[str]:
    """`count` graspable objects (smallest extent <= max_min_extent), alternating over the
    available sets and, in the procedural set, over boxes, cylinders and packaged objects."""
    pools = []
    for name in available_sets():
        objs = [o for o in get_object_set(name).objects if min(o.extents) <= max_min_extent]
        if name == "procedural":
            for kind in ("box", "cylinder", "packaged"):
                pools.append([o.full_name for o in objs if o.name.startswith(kind)])
        else:
            pools.append([o.full_name for o in objs])
    out, i = [], 0
    while len(out) < count and any(i < len(p) for p in pools):
        for p in pools:
            if i < len(p) and len(out) < count:
                out.append(p[i])
        i += 1
    return out


def _object(full_name: str):
    return get_object(full_name), object_mesh(full_name)


def label_pose(mesh) -> np.ndarray:
    """Canonical upright pose, lifted so the object sits above z = 0.2 m (the jaws never meet a
    table: the grasp is simulated in free space, see physics.py)."""
    X = np.eye(4)
    X[2, 3] = 0.2 - float(mesh.bounds[0, 2])
    return X


def generate_labels(objects: list[str], out: Path, grasps_per_object: int = 45, trials: int = 2,
                    seed: int = 0, closing_force: float = 10.0, friction: float = 0.8, pad: PadConfig | None = None,
                    max_width: float = 0.1, center_noise: float = 0.01, sampler_friction: float = 0.7,
                    log=print) -> Path:
    pad = pad or PadConfig()
    done = {(r["object"], r["index"]) for r in _read_jsonl(out)}
    for k, name in enumerate(objects):
        spec, mesh = _object(name)
        X = label_pose(mesh)
        grasps = sample_antipodal_grasps(mesh, X, grasps_per_object, friction=sampler_friction, max_width=max_width,
                                         seed=int(np.random.SeedSequence([seed, k]).generate_state(1)[0]),
                                         center_noise=center_noise, open_width=max_width)
        t0 = time.perf_counter()
        n_new = 0
        for i, g in enumerate(grasps):
            if (name, i) in done:
                continue
            outs = label_grasp(mesh, X, g, spec.mass, trials=trials,
                               seed=int(np.random.SeedSequence([seed, k, i]).generate_state(1)[0]),
                               closing_force=closing_force, friction=friction, com=spec.inertia.com, pad=pad)
            _append(out, {"object": name, "index": i, "center": g.center.tolist(), "axis": g.axis.tolist(),
                          "approach": g.approach.tolist(), "width": g.width, "X_WO": X.tolist(),
                          "mass": spec.mass, "com": list(spec.inertia.com),
                          "trials": [int(o.success) for o in outs], "label": float(np.mean([o.success for o in outs])),
                          "closing_force": closing_force, "friction": friction, "pad": asdict(pad)})
            n_new += 1
        if n_new:
            log(f"[labels] {name}: {n_new} grasps in {time.perf_counter() - t0:.0f} s")
    return Path(out)


def parameter_sets(model: str, count: int, seed: int = 0) -> list[dict]:
    """Random model parameters from the reference's ranges (line 229); set 0 is the default."""
    rng = np.random.default_rng([seed, MODELS.index(model)])
    sets = [{"friction": 0.8}]
    while len(sets) < count:
        p = {"friction": float(rng.uniform(0.3, 1.5))}
        if model == "soft_point":
            p["torsional_friction"] = float(rng.uniform(0.001, 0.02))
        if model in ("elliptical", "reach", "mfe", "6dfc"):
            p["material_constant"] = float(rng.uniform(1e-4, 1e-2))
        sets.append(p)
    return sets


def predict(labels: Path, out: Path, models=MODELS, param_sets: int = 8, robust_samples: int = 10,
            closing_force: float = 10.0, seed: int = 0, log=print) -> Path:
    rows = _read_jsonl(labels)
    h = _keys_hash(rows)
    done = {(r["model"], r["param_index"], r["robust"]) for r in _read_jsonl(out) if r.get("keys_sha1") == h}
    meshes = {}
    for r in rows:
        if r["object"] not in meshes:
            meshes[r["object"]] = _object(r["object"])[1]
    grasps = [ParallelJawGrasp(r["center"], r["axis"], r["approach"], r["width"]) for r in rows]
    for model in models:
        for pi, params in enumerate(parameter_sets(model, param_sets, seed)):
            for robust in (0, robust_samples):
                if (model, pi, robust) in done:
                    continue
                ev = GraspEvaluator(model, closing_force=closing_force, **params)
                t0 = time.perf_counter()
                q, reasons = [], {}
                for j, (r, g) in enumerate(zip(rows, grasps)):
                    res = ev.evaluate(meshes[r["object"]], np.asarray(r["X_WO"]), g, r["mass"], robust,
                                      seed=j, com=r["com"])
                    q.append(round(float(res.quality), 4))
                    reasons[res.reason] = reasons.get(res.reason, 0) + 1
                ms = 1e3 * (time.perf_counter() - t0) / max(len(rows), 1)
                _append(out, {"model": model, "param_index": pi, "params": params, "robust": robust,
                              "ms_per_grasp": ms, "quality": q, "reasons": reasons, "keys_sha1": _keys_hash(rows)})
                log(f"[predict] {model} set {pi} robust={robust}: {ms:.1f} ms/grasp, reasons {reasons}")
    return Path(out)


def average_recall(y: np.ndarray, q: np.ndarray) -> float:
    """Recall averaged over thresholds 0.0..1.0 step 0.1 (success predicted when q >= t)."""
    pos = y > 0
    if not pos.any():
        return float("nan")
    return float(np.mean([np.mean(q[pos] >= t - 1e-9) for t in THRESHOLDS]))


def loo_table(labels: Path, predictions: Path) -> list[dict]:
    """Leave-one-object-out AP / AR per (model, robust) -- see the module docstring."""
    rows = _read_jsonl(labels)
    preds = [p for p in _read_jsonl(predictions) if p.get("keys_sha1") == _keys_hash(rows)]
    table = []
    groups: dict = {}
    for p in preds:
        groups.setdefault((p["model"], p["robust"]), []).append(p)
    for (model, robust), plist in sorted(groups.items(), key=lambda kv: (MODELS.index(kv[0][0]), kv[0][1])):
        y = np.array([r["label"] >= 0.5 for r in rows])
        obj = np.array([r["object"] for r in rows])
        Q = np.array([p["quality"] for p in plist])  # (P, G)
        names = sorted(set(obj))
        ap = np.full((len(plist), len(names)), np.nan)
        ar = np.full((len(plist), len(names)), np.nan)
        for j, o in enumerate(names):
            m = obj == o
            for i in range(len(plist)):
                if y[m].any() and not y[m].all():
                    ap[i, j] = average_precision_score(y[m], Q[i, m])
                ar[i, j] = average_recall(y[m], Q[i, m])
        held_ap, held_ar, chosen = [], [], []
        for j in range(len(names)):
            others = [jj for jj in range(len(names)) if jj != j]
            score = np.nanmean(ap[:, others], axis=1) if np.isfinite(ap[:, others]).any() else np.zeros(len(plist))
            best = int(np.nanargmax(score))
            chosen.append(best)
            held_ap.append(ap[best, j])
            held_ar.append(ar[best, j])
        table.append({
            "model": model, "robust": robust,
            "AP": float(np.nanmean(held_ap)), "AR": float(np.nanmean(held_ar)),
            "objects_ap": int(np.isfinite(held_ap).sum()), "objects_ar": int(np.isfinite(held_ar).sum()),
            "ms_per_grasp": float(np.mean([p["ms_per_grasp"] for p in plist])),
            "chosen_params": [plist[c]["params"] for c in sorted(set(chosen))],
            "pooled_AP_default": float(average_precision_score(y, Q[0])) if y.any() and not y.all() else float("nan"),
        })
    return table


def format_table(table: list[dict], n_grasps: int = 0, n_objects: int = 0) -> str:
    names = {"point": "Point", "soft_point": "Soft point", "elliptical": "Elliptical area", "reach": "REACH",
             "mfe": "MFE", "6dfc": "6DFC"}
    lines = ["| Model | AP | AR | ms / grasp |", "|---|---|---|---|"]
    for r in table:
        label = names[r["model"]] + (f" robust (N={r['robust']})" if r["robust"] else " (non-robust)")
        lines.append(f"| {label} | {r['AP']:.2f} | {r['AR']:.2f} | {r['ms_per_grasp']:.1f} |")
    if n_grasps:
        lines.append(f"\n{n_grasps} grasps on {n_objects} objects; AP over objects with both outcomes, "
                     "AR over objects with a success.")
    return "\n".join(lines)
