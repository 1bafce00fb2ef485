"""`ms-drake data grasps`: the grasp sets of an object set (ms_drake.grasping.grasp_sets), one
npz per object, resumable, in parallel, with a manifest (manifest.json: the command, the
parameters, per object the grasp counts and the CPU seconds) and a README in the folder.

An object whose stored set (file or pack entry) has the run's parameters is kept (resume); any
other is recomputed.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from ms_drake.grasping.grasp_sets import (
    compute_grasp_set,
    grasp_set_dir,
    grasp_set_params,
    grasp_set_path,
    load_grasp_set,
    pack_grasp_sets,
)
from ms_drake.objects import get_object_set
from ms_drake.parallel import run_jobs
from ms_drake.paths import code_version


def _job(job: tuple) -> dict:
    """(full name, out folder, params) -> the object's manifest row; module-level for pickling."""
    name, out, params = job
    t = time.process_time()
    kw = {k: params[k] for k in ("model", "jaw", "suction", "robust_samples", "seed", "max_width", "evaluator_params")}
    gs = compute_grasp_set(name, **kw)
    cpu = time.process_time() - t
    gs.save(Path(out) / f"{name.split('/', 1)[1]}.npz")
    return {"object": name, "jaw": len(gs.jaw_center), "suction": len(gs.suction_point),
            "jaw_above_0.5": int((gs.jaw_quality.max(axis=1) > 0.5).sum()) if len(gs.jaw_center) else 0,
            "suction_above_0.5": int((gs.suction_quality > 0.5).sum()), "cpu_s": round(cpu, 3)}


def _current(out: Path, name: str, params: dict) -> bool:
    """The object has a stored set (its own file or the folder's pack) made with `params`."""
    try:
        gs = load_grasp_set(name, out)
    except (OSError, ValueError, KeyError):
        return False
    return gs is not None and gs.params == json.loads(json.dumps(params))


def write_grasp_sets(set_name: str, out: str | Path | None = None, workers: int = 1, limit: int | None = None,
                     command: str = "", progress=None, **kw) -> dict:
    """Grasp sets of every object of `set_name` (the first `limit`) into `out` (default: the set's
    folder next to its meshes); returns the manifest. kw: grasp_set_params keywords."""
    params = grasp_set_params(**kw)
    out = Path(out) if out is not None else grasp_set_dir(set_name)
    out.mkdir(parents=True, exist_ok=True)
    names = [o.full_name for o in get_object_set(set_name).objects][:limit]
    man_path = out / "manifest.json"
    manifest = json.loads(man_path.read_text()) if man_path.is_file() else {}
    rows = {r["object"]: r for r in manifest.get("objects", [])} if manifest.get("params") == params else {}
    todo = [n for n in names if not (_current(out, n, params) and n in rows)]
    t0 = time.perf_counter()
    errors = []

    def save():
        man = {"set": set_name, "command": command if todo or not manifest.get("command") else manifest["command"],
               "params": params, "commit": code_version() if todo or not manifest.get("commit") else manifest["commit"],
               "machine": f"{platform.node()} {os.cpu_count()} cores", "objects": [rows[n] for n in names if n in rows]}
        cpu = [r["cpu_s"] for r in man["objects"]]
        if cpu:
            man["cpu_s_per_object"] = {"median": float(np.median(cpu)), "mean": float(np.mean(cpu)),
                                       "max": float(np.max(cpu)), "total": float(np.sum(cpu))}
        tmp = man_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(man, indent=1))
        tmp.replace(man_path)
        return man

    done = 0
    for r in run_jobs(_job, [(n, str(out), params) for n in todo], workers=workers):
        if r.ok:
            rows[r.value["object"]] = r.value
        else:
            errors.append(f"{r.job[0]}: {(r.error or '').strip().splitlines()[-1:]}")
        done += 1
        if done % 10 == 0:
            save()
        if progress is not None:
            progress(r)
    man = save()
    if not errors and all(n in rows for n in names) and (todo or any(grasp_set_path(n, out).is_file() for n in names)):
        pack_grasp_sets(out, names)  # one file per set (see pack_grasp_sets)
    (out / "README.md").write_text(
        f"# Grasp sets of the {set_name!r} objects\n\n"
        "pack.npz: every object's grasp set (ms_drake.grasping.grasp_sets: object-frame jaw grasps with "
        f"{params['approaches']} approaches about each axis and suction grasps, each with its robust "
        f"{params['model']} / suction quality, gravity along the approach; grasps of zero quality left "
        f"out), read by ms_drake.grasping.grasp_sets.load_grasp_set. Made by\n\n    {command}\n\n"
        f"at commit {man['commit']}; parameters and per-object CPU seconds in manifest.json.\n")
    man["errors"] = errors
    man["wall_s"] = time.perf_counter() - t0
    return man
