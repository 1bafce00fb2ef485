"""Grasp sets: pre-computed jaw and suction grasps per object with their robust quality (the
Dex-Net 1.0-style database the reference indexes in its bin simulations, lines 1262-1264).

    gs = compute_grasp_set("procedural/box_003")          # soft point, 200 jaw + 200 suction
    gs.save(grasp_set_path("procedural/box_003"))
    sets = load_grasp_sets(["procedural/box_003", ...])   # name -> GraspSet (absent: none stored)

Object frame throughout. Jaw grasps: antipodal pairs from the mesh sampler (any direction,
ms_drake.grasping.samplers.sample_antipodal_grasps), each stored with `APPROACHES` approach
directions about its axis (the reference direction `jaw_ref` turned by 2 pi k / APPROACHES), and
one robust quality per approach. Suction grasps: surface points (area weighted, deduplicated at
3 mm) with their outward normals; the cup approaches along minus the normal.

Quality (our choice; the reference's Dex-Net 1.0 metric is gravity-free): the robust quality of
`contact model` (soft point by default; any GraspEvaluator model, e.g. reach or 6dfc) with
gravity along the grasp's approach, i.e. the object posed so that the approach points down
(world -z): the object hangs from the gripper that lifted it straight back along its approach.
At run time the planner accepts approaches within a tilt limit of world -z, so the stored figure
is the quality at zero tilt. Robust trials: `robust_samples` perturbations (pose, friction,
mass) as GraspEvaluator / SuctionEvaluator, seeded by (seed, grasp index, approach).

Storage: geometry in float16 (~0.1 mm at 0.2 m), qualities in uint8 (percent), the parameters
alongside so a run with other parameters does not take a stale file for its own
(`GraspSet.params`); one compressed npz per object while a set is computed (`GraspSet.save`),
then one `pack.npz` per object set (`pack_grasp_sets`, zero-quality grasps left out), which
`load_grasp_set` reads.
"""

from __future__ import annotations

import functools
import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ms_drake.grasping.evaluator import MODELS, GraspEvaluator
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp
from ms_drake.grasping.meshes import object_mesh
from ms_drake.grasping.samplers import sample_antipodal_grasps, sample_suction_grasps
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.objects import get_object
from ms_drake.paths import models_dir

APPROACHES = 4
FORMAT = 1


def grasp_set_dir(set_name: str) -> Path:
    """The default folder of a set's grasp files: next to its meshes (models/objects/<set>/grasps)."""
    return models_dir() / "objects" / set_name / "grasps"


def grasp_set_path(full_name: str, root: str | Path | None = None) -> Path:
    """<root or the set's grasp folder>/<name>.npz for the object `<set>/<name>`."""
    set_name, _, name = full_name.partition("/")
    if not name:
        raise GraspError(f"object name {full_name!r} must be '<set>/<name>', e.g. 'procedural/box_003'")
    return Path(root if root is not None else grasp_set_dir(set_name)) / f"{name}.npz"


def _turn(ref: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """ref (orthogonal to axis) turned by `angle` about axis, rows."""
    return np.cos(angle) * ref + np.sin(angle) * np.cross(axis, ref)


@dataclass(frozen=True)
class GraspSet:
    """One object's grasps (object frame). jaw_quality: (n, APPROACHES); approach k of jaw grasp
    i is `jaw_approaches()[i, k]`."""

    object: str
    model: str
    jaw_center: np.ndarray  # (n, 3)
    jaw_axis: np.ndarray  # (n, 3) unit
    jaw_ref: np.ndarray  # (n, 3) unit, orthogonal to the axis: approach 0
    jaw_width: np.ndarray  # (n,)
    jaw_quality: np.ndarray  # (n, APPROACHES) in [0, 1]
    suction_point: np.ndarray  # (m, 3)
    suction_normal: np.ndarray  # (m, 3) unit, outward
    suction_quality: np.ndarray  # (m,) in [0, 1]
    params: dict = field(default_factory=dict)

    def jaw_approaches(self) -> np.ndarray:
        """(n, APPROACHES, 3) approach directions."""
        k = self.jaw_quality.shape[1]
        return np.stack([_turn(self.jaw_ref, self.jaw_axis, 2 * np.pi * j / k) for j in range(k)], axis=1)

    def save(self, path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(
            tmp, object=self.object, model=self.model, params=json.dumps(self.params, sort_keys=True),
            jaw_center=self.jaw_center.astype(np.float16), jaw_axis=self.jaw_axis.astype(np.float16),
            jaw_ref=self.jaw_ref.astype(np.float16), jaw_width=self.jaw_width.astype(np.float16),
            jaw_quality=np.round(100 * self.jaw_quality).astype(np.uint8),
            suction_point=self.suction_point.astype(np.float16),
            suction_normal=self.suction_normal.astype(np.float16),
            suction_quality=np.round(100 * self.suction_quality).astype(np.uint8))
        tmp.replace(path)

    @staticmethod
    def load(path) -> GraspSet:
        with np.load(Path(path)) as z:
            return _from_arrays(str(z["object"]), str(z["model"]), json.loads(str(z["params"])), z["jaw_center"],
                                z["jaw_axis"], z["jaw_ref"], z["jaw_width"], z["jaw_quality"], z["suction_point"],
                                z["suction_normal"], z["suction_quality"])

    def __len__(self) -> int:
        return len(self.jaw_center) + len(self.suction_point)


def _unit(a) -> np.ndarray:
    a = np.asarray(a, float).reshape(-1, 3)
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


def _from_arrays(name, model, params, jc, ja, jr, jw, jq, sp, sn, sq) -> GraspSet:
    """A GraspSet from stored arrays (float16 geometry, uint8 percent qualities)."""
    axis = _unit(ja)
    ref = np.asarray(jr, float).reshape(-1, 3)
    ref = _unit(ref - np.sum(ref * axis, axis=1, keepdims=True) * axis)  # orthogonal again after float16
    return GraspSet(name, model, np.asarray(jc, float).reshape(-1, 3), axis, ref, np.asarray(jw, float),
                    np.asarray(jq, float).reshape(len(axis), APPROACHES) / 100.0,
                    np.asarray(sp, float).reshape(-1, 3), _unit(sn), np.asarray(sq, float) / 100.0, params)


def _down(direction: np.ndarray) -> np.ndarray:
    """A 4x4 pose whose rotation takes `direction` (object frame) to world -z."""
    R, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [direction])
    X = np.eye(4)
    X[:3, :3] = R.as_matrix()
    return X


def grasp_set_params(model: str = "soft_point", jaw: int = 200, suction: int = 200, robust_samples: int = 4,
                     seed: int = 0, max_width: float = 0.1, evaluator_params: dict | None = None) -> dict:
    """The parameters of a grasp set (what a stored file is checked against)."""
    if model not in MODELS:
        raise GraspError(f"grasp set model {model!r} unknown; choose one of {', '.join(MODELS)}")
    if jaw < 0 or suction < 0 or robust_samples < 1:
        raise GraspError(f"grasp set needs jaw >= 0, suction >= 0, robust_samples >= 1 "
                         f"(got {jaw}, {suction}, {robust_samples})")
    return {"format": FORMAT, "model": model, "jaw": int(jaw), "suction": int(suction),
            "robust_samples": int(robust_samples), "seed": int(seed), "max_width": float(max_width),
            "approaches": APPROACHES, "evaluator_params": dict(evaluator_params or {})}


def compute_grasp_set(full_name: str, **kw) -> GraspSet:
    """The grasp set of object `<set>/<name>` (keywords: grasp_set_params)."""
    p = grasp_set_params(**kw)
    spec = get_object(full_name)
    mesh = object_mesh(full_name)
    mass, com = spec.mass, np.asarray(spec.inertia.com, float)
    seed = (p["seed"] * 1_000_003 + zlib.crc32(full_name.encode())) % (2 ** 31 - 1)
    ev = GraspEvaluator(p["model"], **p["evaluator_params"])
    sev = SuctionEvaluator()
    n = p["robust_samples"]
    jaws = sample_antipodal_grasps(mesh, np.eye(4), p["jaw"], friction=ev.friction, max_width=p["max_width"],
                                   seed=seed, approach=None)
    jq = np.zeros((len(jaws), APPROACHES))
    for i, g in enumerate(jaws):
        for k in range(APPROACHES):
            ap = _turn(g.approach[None], g.axis[None], 2 * np.pi * k / APPROACHES)[0]
            X = _down(ap)
            gw = ParallelJawGrasp(g.center, g.axis, ap, g.width).transformed(X)
            jq[i, k] = ev.quality(mesh, X, gw, mass, n, seed + 7919 * i + k, com)
    sucs = sample_suction_grasps(mesh, np.eye(4), p["suction"], seed=seed + 1)
    sq = np.zeros(len(sucs))
    for i, g in enumerate(sucs):
        X = _down(g.approach)
        sq[i] = sev.quality(mesh, X, g.transformed(X), mass, n, seed + 104729 + i, com)
    arr = lambda rows: np.asarray(rows, float).reshape(-1, 3)
    return GraspSet(full_name, p["model"], arr([g.center for g in jaws]), arr([g.axis for g in jaws]),
                    arr([g.approach for g in jaws]), np.array([g.width for g in jaws], float), jq,
                    arr([g.point for g in sucs]), -arr([g.approach for g in sucs]), sq, p)


PACK = "pack.npz"
_FIELDS = ("jaw_center", "jaw_axis", "jaw_ref", "jaw_width", "suction_point", "suction_normal")


def pack_grasp_sets(folder: str | Path, names: list[str]) -> Path:
    """One file `<folder>/pack.npz` with the grasp sets of `names` (their per-object files in the
    folder, or an earlier pack's entries), grasps of zero quality left out (the planner never uses
    them: IndexedGraspPlanner.min_quality > 0). The per-object files are removed afterwards. A
    few hundred ~8 KB files take whole file-system blocks each; one pack takes ~40 % of that."""
    folder = Path(folder)
    sets = []
    for n in names:
        gs = load_grasp_set(n, folder)
        if gs is None:
            raise GraspError(f"pack_grasp_sets: no grasp set of {n!r} in {folder}; run `ms-drake data grasps` first")
        sets.append(gs)
    params = {json.dumps(gs.params, sort_keys=True) for gs in sets}
    if len(params) > 1:
        raise GraspError(f"pack_grasp_sets: the sets in {folder} were made with different parameters; "
                         "recompute them with one `ms-drake data grasps` command")
    parts = {k: [] for k in (*_FIELDS, "jaw_quality", "suction_quality")}
    jaw_n, suc_n = [], []
    for gs in sets:
        keep_j = np.round(100 * gs.jaw_quality).max(axis=1) > 0 if len(gs.jaw_center) else np.zeros(0, bool)
        keep_s = np.round(100 * gs.suction_quality) > 0
        for k in _FIELDS:
            v = getattr(gs, k)
            parts[k].append(v[keep_j] if k.startswith("jaw") else v[keep_s])
        parts["jaw_quality"].append(gs.jaw_quality[keep_j])
        parts["suction_quality"].append(gs.suction_quality[keep_s])
        jaw_n.append(int(keep_j.sum()))
        suc_n.append(int(keep_s.sum()))
    arrays = {k: np.concatenate(v).astype(np.float16) for k, v in parts.items() if k in _FIELDS}
    arrays["jaw_quality"] = np.round(100 * np.concatenate(parts["jaw_quality"]).reshape(-1, APPROACHES)).astype(np.uint8)
    arrays["suction_quality"] = np.round(100 * np.concatenate(parts["suction_quality"])).astype(np.uint8)
    path = folder / PACK
    tmp = folder / "pack.tmp.npz"
    np.savez_compressed(tmp, objects=np.array([gs.object for gs in sets]), models=np.array([gs.model for gs in sets]),
                        jaw_count=np.array(jaw_n, np.int32), suction_count=np.array(suc_n, np.int32),
                        params=next(iter(params)) if params else "{}", **arrays)
    tmp.replace(path)
    _pack.cache_clear()
    for n in names:
        grasp_set_path(n, folder).unlink(missing_ok=True)
    return path


@functools.lru_cache(maxsize=16)
def _pack(path: str, mtime: float) -> dict:
    """{full name: GraspSet} of a pack file."""
    with np.load(path) as z:
        a = {k: z[k] for k in z.files}
    params = json.loads(str(a["params"]))
    j0 = np.concatenate([[0], np.cumsum(a["jaw_count"])])
    s0 = np.concatenate([[0], np.cumsum(a["suction_count"])])
    out = {}
    for i, (name, model) in enumerate(zip(a["objects"], a["models"])):
        js, ss = slice(j0[i], j0[i + 1]), slice(s0[i], s0[i + 1])
        out[str(name)] = _from_arrays(str(name), str(model), params, a["jaw_center"][js], a["jaw_axis"][js],
                                      a["jaw_ref"][js], a["jaw_width"][js], a["jaw_quality"][js],
                                      a["suction_point"][ss], a["suction_normal"][ss], a["suction_quality"][ss])
    return out


@functools.lru_cache(maxsize=4096)
def _load_cached(path: str, mtime: float) -> GraspSet:
    return GraspSet.load(path)


def load_grasp_set(full_name: str, root: str | Path | None = None) -> GraspSet | None:
    """The stored grasp set of an object (its own file, else its entry in the folder's pack.npz),
    or None when it has none (cached by file and mtime)."""
    path = grasp_set_path(full_name, root)
    if path.is_file():
        return _load_cached(str(path), path.stat().st_mtime)
    pack = path.parent / PACK
    if pack.is_file():
        return _pack(str(pack), pack.stat().st_mtime).get(full_name)
    return None


def load_grasp_sets(names, root: str | Path | None = None) -> dict[str, GraspSet]:
    """{full name: GraspSet} of the names that have a stored set."""
    out = {}
    for n in names:
        gs = load_grasp_set(n, root)
        if gs is not None:
            out[n] = gs
    return out
