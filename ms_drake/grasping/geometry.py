"""Mesh queries shared by the contact models: ray casting and jaw contact patches.

`MeshData.of(mesh)` caches, per trimesh.Trimesh object, everything the models need (triangle
arrays for vectorized Moller-Trumbore ray casting, watertightness, the volume centroid, a
manifold3d Manifold for CSG). The cache is keyed by object identity: do not mutate a mesh
after evaluating grasps on it (make a copy instead).

Contact patches (REACH, elliptical, MFE, 6DFC) follow Ch. 2.3.1 of the reference (lines
143-146): the patch is the constructive-solid-geometry intersection of the object with the
jaw pad polygon extruded along the closing direction, sliced at the first-contact distance
d_con and at d_con + d_def (d_def = kappa * f_C, saturated at the pad thickness). Choices the
text leaves open, recorded here:
- One prism spans both jaws (their pads face each other and share one outline when projected
  along the grasp axis), so a single manifold3d boolean serves the two jaws.
- A jaw's patch keeps the object faces that face that jaw (n . closing direction < 0): a face
  turned away from the jaw cannot be pressed by it.
- d_con is the smallest depth, along the closing direction, of the intersection volume; if the
  object already crosses the open jaw's pad (d_con ~ 0) the grasp is in collision.
- Pressure follows line 144: p = k * delta * (n . a) with delta = d_con + d_def - depth, the
  pad's penetration (largest at the first contact point, zero at the far slice).
"""

from __future__ import annotations

import atexit
import math
import weakref
from dataclasses import dataclass

import manifold3d as m3
import numpy as np

_CACHE: dict[int, tuple[weakref.ref, "MeshData"]] = {}
atexit.register(_CACHE.clear)  # free manifold3d objects before interpreter teardown (nanobind leak report)
_CACHE_MAX = 64
COLLISION_DEPTH = 1e-7  # m: an object this close to the open jaw's pad touches it already


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross for (..., 3) arrays with broadcasting, without np.cross's per-call overhead."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    out = np.empty(a.shape)
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


@dataclass
class Patch:
    """One jaw's contact patch in the object frame.

    triangles (P, 3, 3); normals (P, 3) outward object normals; areas (P,);
    penetration (P, 3): pad penetration delta at each vertex (m); closing (3,): the jaw's
    closing direction; d_con: first-contact distance from the open jaw (m).
    """

    triangles: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    penetration: np.ndarray
    closing: np.ndarray
    d_con: float

    @property
    def area(self) -> float:
        return float(self.areas.sum())

    def pressure_at_vertices(self) -> np.ndarray:
        """delta * (n . a) at each vertex (P, 3): the pressure up to the constant k (line 144)."""
        cos = np.abs(self.normals @ self.closing)
        return self.penetration * cos[:, None]


class MeshData:
    """Cached arrays of one mesh (object frame)."""

    def __init__(self, mesh):
        self.mesh = mesh
        self.vertices = np.asarray(mesh.vertices, dtype=float)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        tri = self.vertices[self.faces]
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        nrm = cross(self.e1, self.e2)
        norm = np.linalg.norm(nrm, axis=1)
        self.areas = 0.5 * norm
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normals = np.where(norm[:, None] > 0, nrm / norm[:, None], 0.0)
        self.watertight = bool(len(self.faces) > 0 and mesh.is_watertight)
        self.volume = float(mesh.volume) if self.watertight else 0.0
        if self.watertight and self.volume > 0:
            self.centroid = np.asarray(mesh.center_mass, dtype=float)
        elif len(self.vertices):
            self.centroid = self.vertices.mean(axis=0)
        else:
            self.centroid = np.zeros(3)
        if len(self.vertices):
            lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        else:
            lo = hi = np.zeros(3)
        self.length_scale = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        self.bbox_center, self.bbox_diagonal = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo)) + 1e-6
        # bounding spheres of the triangles, to cull ray candidates
        self.tri_center = tri.mean(axis=1)
        self.tri_radius = np.linalg.norm(tri - self.tri_center[:, None, :], axis=2).max(axis=1) + 1e-12
        self._manifold = None
        self._face_normal_by_id = None

    @staticmethod
    def of(mesh) -> "MeshData":
        key = id(mesh)
        hit = _CACHE.get(key)
        if hit is not None and hit[0]() is mesh:
            return hit[1]
        data = MeshData(mesh)
        if len(_CACHE) >= _CACHE_MAX:
            for k in [k for k, (r, _) in _CACHE.items() if r() is None] or list(_CACHE)[: _CACHE_MAX // 2]:
                _CACHE.pop(k, None)
        _CACHE[key] = (weakref.ref(mesh), data)
        return data

    # ---------------------------------------------------------------- rays
    def raycast(self, origins: np.ndarray, directions: np.ndarray, max_distance) -> tuple[np.ndarray, np.ndarray]:
        """First hit of each ray: (t (R,), outward normal at the hit (R, 3)); t = inf and the
        normal NaN when nothing is hit within (0, max_distance].

        Uses manifold3d's BVH ray cast (~5 us a ray) when the mesh is a valid solid, else a
        vectorized Moller-Trumbore over all triangles."""
        origins = np.atleast_2d(np.asarray(origins, float))
        directions = np.atleast_2d(np.asarray(directions, float))
        R = len(origins)
        maxd = np.broadcast_to(np.asarray(max_distance, float), (R,))
        try:
            m = self.manifold()
        except ValueError:
            m = None
        t_out = np.full(R, np.inf)
        n_out = np.full((R, 3), np.nan)
        if m is None:
            t, face = self.raycast_triangles(origins, directions, maxd)
            hit = face >= 0
            t_out[hit], n_out[hit] = t[hit], self.normals[face[hit]]
            return t_out, n_out
        cx, cy, cz = self.bbox_center
        step = self.bbox_diagonal / 8.0  # manifold3d tests the triangles in a segment's bounding
        for r, (o, d) in enumerate(zip(origins.tolist(), directions.tolist())):  # box: keep it small
            L = float(maxd[r])
            if L == np.inf:
                L = math.sqrt((o[0] - cx) ** 2 + (o[1] - cy) ** 2 + (o[2] - cz) ** 2) + self.bbox_diagonal
            a = 0.0
            while a < L:
                b = min(L, a + step)
                hit = None
                for h in m.ray_cast((o[0] + a * d[0], o[1] + a * d[1], o[2] + a * d[2]),
                                    (o[0] + b * d[0], o[1] + b * d[1], o[2] + b * d[2])):
                    dist = a + h.distance * (b - a)
                    if dist > 1e-9:
                        hit = (dist, h.normal)
                        break
                if hit is not None:
                    t_out[r], n_out[r] = hit
                    break
                a = b
        return t_out, n_out

    def raycast_triangles(self, origins: np.ndarray, directions: np.ndarray, max_distance):
        """First hit of each ray (Moller-Trumbore, vectorized over the triangles whose bounding
        sphere meets the ray's line). Returns (t, face index or -1)."""
        origins = np.atleast_2d(np.asarray(origins, float))
        directions = np.atleast_2d(np.asarray(directions, float))
        R = len(origins)
        maxd = np.broadcast_to(np.asarray(max_distance, float), (R,))
        t_out = np.full(R, np.inf)
        f_out = np.full(R, -1, dtype=np.int64)
        if len(self.faces) == 0:
            return t_out, f_out
        for r in range(R):
            o, d = origins[r], directions[r]
            rel = self.tri_center - o
            along = rel @ d
            perp2 = np.einsum("ij,ij->i", rel, rel) - along * along
            cand = np.nonzero((perp2 <= self.tri_radius ** 2) & (along >= -self.tri_radius))[0]
            if len(cand) == 0:
                continue
            e1, e2, v0 = self.e1[cand], self.e2[cand], self.v0[cand]
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                p = cross(d, e2)
                det = np.einsum("ij,ij->i", p, e1)
                inv = 1.0 / det
                s = o - v0
                u = np.einsum("ij,ij->i", s, p) * inv
                q = cross(s, e1)
                v = (q @ d) * inv
                t = np.einsum("ij,ij->i", e2, q) * inv
                eps = 1e-12
                ok = (np.abs(det) > 1e-18) & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 1e-9)
            if not ok.any():
                continue
            t = np.where(ok, t, np.inf)
            k = int(np.argmin(t))
            if t[k] <= maxd[r]:
                t_out[r], f_out[r] = t[k], cand[k]
        return t_out, f_out

    # ---------------------------------------------------------------- CSG
    def manifold(self):
        """The mesh as a manifold3d Manifold (built once; raises ValueError if not a valid solid)."""
        if self._manifold is None:
            if getattr(self, "_manifold_error", None):
                raise ValueError(self._manifold_error)
            m = m3.Manifold(m3.Mesh64(vert_properties=self.vertices, tri_verts=self.faces.astype(np.uint64)))
            if m.status() != m3.Error.NoError or m.is_empty():
                self._manifold_error = f"mesh is not a valid closed solid for CSG ({m.status()})"
                raise ValueError(self._manifold_error)
            m = m.as_original()
            own = m.to_mesh64()
            vp = np.asarray(own.vert_properties)[:, :3]
            tri = vp[np.asarray(own.tri_verts, dtype=np.int64)]
            n = cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            fid = np.asarray(own.face_id, dtype=np.int64)
            table = np.zeros((int(fid.max()) + 1 if len(fid) else 1, 3))
            table[fid] = n
            self._face_normal_by_id = table
            self._manifold = m
        return self._manifold


def jaw_frame(center, axis, approach, width):
    """Rotation (columns x = approach, y = z x x, z = axis) and origin of jaw 1's open pad."""
    z = np.asarray(axis, float)
    x = np.asarray(approach, float) - np.dot(approach, z) * z
    x /= np.linalg.norm(x)
    y = cross(z, x)
    R = np.column_stack([x, y, z])
    origin = np.asarray(center, float) - 0.5 * width * z
    return R, origin


def clip_below(tri: np.ndarray, dist: np.ndarray):
    """Clip triangles to the half-space dist <= 0, where dist (P, 3) is an affine function's value
    at the vertices. Returns (triangles (Q, 3, 3), dist at their vertices (Q, 3), parent (Q,))."""
    inside = dist <= 0
    n_in = inside.sum(axis=1)
    if len(n_in) == 0 or n_in.min() == 3:
        return tri, dist, np.arange(len(tri))
    full = np.nonzero(n_in == 3)[0]
    idx = np.nonzero((n_in == 1) | (n_in == 2))[0]
    if len(idx) == 0:
        return tri[full], dist[full], full
    t, d, ins = tri[idx], dist[idx], inside[idx]
    one = n_in[idx] == 1
    # roll each triangle so that its odd vertex (the lone inside one when one vertex is in, the
    # lone outside one when two are) comes first; rolling keeps the winding.
    odd = np.argmax(np.where(one[:, None], ins, ~ins), axis=1)
    order = (odd[:, None] + np.arange(3)[None]) % 3
    rows = np.arange(len(idx))[:, None]
    t, d = t[rows, order], d[rows, order]
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    da, db, dc = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    pab = a + np.divide(da, da - db, out=np.zeros_like(da), where=da != db) * (b - a)
    pac = a + np.divide(da, da - dc, out=np.zeros_like(da), where=da != dc) * (c - a)
    z = np.zeros(len(idx))
    two = ~one
    # one vertex in: keep the corner (a, pab, pac); two in: the quad (pab, b, c, pac) as 2 triangles
    out_t = [tri[full], np.stack([a, pab, pac], axis=1)[one],
             np.stack([pab, b, c], axis=1)[two], np.stack([pab, c, pac], axis=1)[two]]
    out_d = [dist[full], np.column_stack([da[:, 0], z, z])[one],
             np.column_stack([z, db[:, 0], dc[:, 0]])[two], np.column_stack([z, dc[:, 0], z])[two]]
    return np.concatenate(out_t), np.concatenate(out_d), np.concatenate([full, idx[one], idx[two], idx[two]])


def triangle_areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def is_convex_ccw(polygon) -> bool:
    p = np.asarray(polygon, float)
    e = np.roll(p, -1, axis=0) - p
    turn = e[:, 0] * np.roll(e, -1, axis=0)[:, 1] - e[:, 1] * np.roll(e, -1, axis=0)[:, 0]
    return bool(np.all(turn >= -1e-15))


def jaw_patches(data: MeshData, center, axis, approach, width, pad_polygon, d_def: float):
    """Contact patches of the two jaws: `jaw_patches_clip` for convex pads (exact and fast),
    the manifold3d CSG boolean `jaw_patches_csg` for any other polygon. Same results (tested)."""
    if is_convex_ccw(pad_polygon):
        return jaw_patches_clip(data, center, axis, approach, width, pad_polygon, d_def)
    return jaw_patches_csg(data, center, axis, approach, width, pad_polygon, d_def)


def _patches_from_pieces(tri, depth1, normals, width, d_con, d_def, closing_axis):
    """Facing filter + slab clipping [d_con, d_con + d_def] for both jaws (object frame)."""
    patches = []
    for jaw, closing in ((0, closing_axis), (1, -closing_axis)):
        facing = normals @ closing < 0
        d = depth1[facing] if jaw == 0 else width - depth1[facing]
        t, dd, parent = clip_below(tri[facing], d - (d_con[jaw] + d_def))
        areas = triangle_areas(t)
        good = areas > 1e-14
        if good.sum() == 0 or areas[good].sum() < 1e-10:
            return None, "zero_area_patch"
        patches.append(Patch(t[good], normals[facing][parent[good]], areas[good],
                             np.maximum(-dd[good], 0.0), closing.copy(), d_con[jaw]))
    return tuple(patches), ""


def _inside(data: MeshData, point, direction) -> bool:
    """Is `point` inside the (closed) mesh? The first face hit along `direction` is an exit."""
    t, n = data.raycast(np.asarray(point)[None], np.asarray(direction)[None], np.inf)
    return bool(np.isfinite(t[0]) and n[0] @ direction > 0)


def jaw_patches_clip(data: MeshData, center, axis, approach, width, pad_polygon, d_def: float):
    """The CSG patch computed by clipping the object's surface triangles to the pad prism
    (convex pad polygons, counter-clockwise): surface n prism is exactly the object-surface part
    of the boolean intersection. d_con is the smallest depth of that surface; a jaw collides when
    the surface crosses its open pad or its pad lies wholly inside the object."""
    R, origin = jaw_frame(center, axis, approach, width)
    poly = np.asarray(pad_polygon, float)
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    # cull with the triangles' bounding spheres against the prism's box (jaw frame: x approach,
    # y lateral, z depth from jaw 1), then with the candidates' exact bounds
    c = (data.tri_center - origin) @ R
    r = data.tri_radius
    box_lo, box_hi = np.array([lo[0], lo[1], 0.0]), np.array([hi[0], hi[1], width])
    near = np.nonzero(np.all((c + r[:, None] >= box_lo) & (c - r[:, None] <= box_hi), axis=1))[0]
    tri = (data.v0[near][:, None, :] + np.stack([np.zeros((len(near), 3)), data.e1[near], data.e2[near]], axis=1)
           - origin) @ R
    tmin, tmax = tri.min(axis=1), tri.max(axis=1)
    inb = np.all((tmax >= box_lo) & (tmin <= box_hi), axis=1)
    t, parent = tri[inb], near[inb]
    # signed distances to the footprint's edge planes (<= 0 inside), all at once: triangles
    # inside every plane are kept as they are, triangles outside one plane are dropped, only
    # the straddling rest is clipped edge by edge
    edges = [(a, b - a) for a, b in zip(poly, np.roll(poly, -1, axis=0))]
    D = np.stack([-(e[0] * (t[..., 1] - a[1]) - e[1] * (t[..., 0] - a[0])) for a, e in edges], axis=-1)
    inside_all = np.all(D <= 0, axis=(1, 2))
    outside_any = np.any(np.all(D > 0, axis=1), axis=1)
    straddle = ~inside_all & ~outside_any
    ts, ps = t[straddle], parent[straddle]
    for a, e in edges:
        if len(ts) == 0:
            break
        ts, _, par = clip_below(ts, -(e[0] * (ts[..., 1] - a[1]) - e[1] * (ts[..., 0] - a[0])))
        ps = ps[par]
    t = np.concatenate([t[inside_all], ts])
    parent = np.concatenate([parent[inside_all], ps])
    if len(t) == 0:
        pad_mid = R @ np.array([*poly.mean(axis=0), 0.5 * width]) + origin
        return None, ("jaw_collision" if _inside(data, pad_mid, R[:, 2]) else "miss")
    zmin, zmax = t[..., 2].min(axis=1), t[..., 2].max(axis=1)
    mid = poly.mean(axis=0)
    # the surface crosses an open pad's plane inside the footprint: that pad starts in the object
    if np.any((zmin < 0) & (zmax > 0)) or np.any((zmin < width) & (zmax > width)):
        return None, "jaw_collision"
    keep = (zmin >= 0) & (zmax <= width)
    keep[keep] = triangle_areas(t[keep]) > 0
    t, parent = t[keep], parent[keep]
    if len(t) == 0:
        pad_mid = R @ np.array([mid[0], mid[1], 0.5 * width]) + origin
        return None, ("jaw_collision" if _inside(data, pad_mid, R[:, 2]) else "miss")
    depth1 = t[..., 2]
    d_con = (float(depth1.min()), float((width - depth1).min()))
    c1 = R @ np.array([mid[0], mid[1], 0.0]) + origin
    c2 = c1 + width * R[:, 2]
    if min(d_con) < COLLISION_DEPTH or _inside(data, c1, R[:, 2]) or _inside(data, c2, -R[:, 2]):
        return None, "jaw_collision"
    tri_O = t @ R.T + origin
    return _patches_from_pieces(tri_O, depth1, data.normals[parent], width, d_con, d_def, R[:, 2])


def jaw_patches_csg(data: MeshData, center, axis, approach, width, pad_polygon, d_def: float):
    """Contact patches of the two jaws (object frame), or a failure reason.

    Returns ((patch1, patch2), "") on success or (None, reason) with reason in
    {"miss", "jaw_collision", "zero_area_patch"}. Jaw 1 starts at center - width/2 * axis and
    closes along +axis; jaw 2 starts at center + width/2 * axis and closes along -axis.
    """
    R, origin = jaw_frame(center, axis, approach, width)
    cs = m3.CrossSection([np.asarray(pad_polygon, float)])
    T = np.column_stack([R, origin])
    prism = m3.Manifold.extrude(cs, float(width)).transform(T)
    inter = data.manifold() ^ prism
    if inter.is_empty():
        return None, "miss"
    mg = inter.to_mesh64()
    verts = np.asarray(mg.vert_properties)[:, :3]
    tv = np.asarray(mg.tri_verts, dtype=np.int64)
    obj_id = data.manifold().original_id()
    keep = np.zeros(len(tv), bool)
    for k, oid in enumerate(mg.run_original_id):
        if oid == obj_id:
            keep[mg.run_index[k] // 3: mg.run_index[k + 1] // 3] = True
    axis = R[:, 2]
    depth1 = (verts - origin) @ axis
    d_con = (float(depth1.min()), float((width - depth1).min()))
    if min(d_con) < COLLISION_DEPTH:
        return None, "jaw_collision"
    fid = np.asarray(mg.face_id, dtype=np.int64)[keep]
    normals = data._face_normal_by_id[np.minimum(fid, len(data._face_normal_by_id) - 1)]
    return _patches_from_pieces(verts[tv[keep]], depth1[tv[keep]], normals, width, d_con, d_def, axis)
