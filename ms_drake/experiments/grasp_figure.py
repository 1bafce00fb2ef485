"""Grasps on one object, scored and drawn like Fig. 2.1 (bottom): the `ms-drake grasp` command.

    ms-drake grasp --object procedural/box_000 --model 6dfc --samples 100 --out grasp_out

Writes <out>/<object>_<model>.png (the mesh with each grasp's axis coloured red -> yellow ->
green by robust quality) and <out>/<object>_<model>.json, and prints the grasp table.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from ms_drake.errors import ObjectSetError
from ms_drake.grasping.evaluator import GraspEvaluator
from ms_drake.grasping.grasp import GraspError
from ms_drake.grasping.meshes import object_mesh
from ms_drake.grasping.samplers import sample_antipodal_grasps
from ms_drake.objects import available_sets, get_object, get_object_set


def resolve_object(name: str):
    """An ObjectSpec from '<set>/<name>' or a bare name searched in every available set."""
    if "/" in name:
        return get_object(name)
    for s in available_sets():
        try:
            return get_object_set(s).get(name)
        except ObjectSetError:
            continue
    raise ObjectSetError(f"no object called {name!r} in the sets {', '.join(available_sets())}; "
                         "use '<set>/<name>', e.g. 'procedural/box_000'")


def render_grasps(mesh, grasps, qualities, path: Path, title: str = ""):
    """PNG of the mesh with grasp axes (jaw to jaw) coloured by quality (RdYlGn)."""
    matplotlib.use("Agg")

    fig = plt.figure(figsize=(6, 6), dpi=120)
    ax = fig.add_subplot(111, projection="3d")
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    ax.add_collection3d(Poly3DCollection(tri, facecolor=(0.75, 0.75, 0.78, 0.35), edgecolor=(0.4, 0.4, 0.45, 0.25),
                                         linewidths=0.3))
    cmap = plt.get_cmap("RdYlGn")
    segs = [np.stack([g.center - 0.5 * g.width * g.axis, g.center + 0.5 * g.width * g.axis]) for g in grasps]
    order = np.argsort(qualities)  # best drawn last (on top)
    if segs:
        lc = Line3DCollection([segs[i] for i in order], colors=[cmap(qualities[i]) for i in order], linewidths=1.6)
        ax.add_collection3d(lc)
        pts = np.array([g.center for g in grasps])
        ax.scatter(pts[order, 0], pts[order, 1], pts[order, 2], c=[cmap(qualities[i]) for i in order], s=6)
    lo, hi = mesh.bounds
    c, r = 0.5 * (lo + hi), 0.6 * float(np.max(hi - lo)) + 0.02
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(title, fontsize=9)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 1))
    fig.colorbar(sm, ax=ax, shrink=0.6, label="grasp quality")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return path


def grasp_figure(object: str, model: str = "6dfc", samples: int = 100, out: Path = Path("grasp_out"),
                 robust: int = 10, friction: float = 0.8, closing_force: float = 10.0, seed: int = 0) -> Path:
    """Sample grasps on an object, score them with a contact model, write a PNG and print the table."""

    if samples < 1:
        raise GraspError(f"--samples must be >= 1, got {samples}")
    spec = resolve_object(object)

    ev = GraspEvaluator(model, friction=friction, closing_force=closing_force)
    mesh = object_mesh(spec.full_name)
    X = np.eye(4)
    grasps = sample_antipodal_grasps(mesh, X, samples, friction=friction, max_width=0.1, seed=seed,
                                     center_noise=0.005)
    t0 = time.perf_counter()
    results = [ev.evaluate(mesh, X, g, spec.mass, robust, seed=seed + i, com=spec.inertia.com)
               for i, g in enumerate(grasps)]
    ms = 1e3 * (time.perf_counter() - t0) / max(len(grasps), 1)
    q = np.array([r.quality for r in results])
    stem = f"{spec.full_name.replace('/', '_')}_{model}"
    png = render_grasps(mesh, grasps, q, Path(out) / f"{stem}.png",
                        f"{spec.full_name}  model={model}  robust N={robust}  ({len(grasps)} grasps)")
    rows = [{"center": g.center.round(5).tolist(), "axis": g.axis.round(4).tolist(), "width": round(g.width, 4),
             "quality": r.quality, "reason": r.reason} for g, r in zip(grasps, results)]
    (Path(out) / f"{stem}.json").write_text(json.dumps({"object": spec.full_name, "model": model, "robust": robust,
                                                         "ms_per_grasp": ms, "grasps": rows}, indent=1))
    print(f"{spec.full_name}: {len(grasps)} grasps, model {model}, robust N={robust}, {ms:.1f} ms/grasp")
    print(f"{'#':>3}  {'quality':>7}  {'width':>6}  {'center [m]':<28} reason")
    for i in np.argsort(-q, kind="stable")[:15]:
        c = ", ".join(f"{v:+.3f}" for v in grasps[i].center)
        print(f"{i:>3}  {q[i]:7.2f}  {grasps[i].width:6.3f}  ({c})  {results[i].reason}")
    hist = np.histogram(q, bins=[0, 0.3, 0.7, 1.01])[0]
    print(f"low (<0.3): {hist[0]}   medium: {hist[1]}   high (>=0.7): {hist[2]}   mean {q.mean() if len(q) else 0:.2f}")
    print(f"wrote {png}")
    return png
