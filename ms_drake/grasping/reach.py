"""REACH: per-triangle limit-surface constraints from closed-form integrals (Ch. 2, App. A).

Reference lines (mechanical-search-dissertation.txt):
- 143-146: patch = CSG intersection of the extruded pad with the object, sliced at d_con and
  d_con + d_def, d_def = kappa f_C; pressure p = k delta (n . a).
- 148-165: per-triangle wrench in the triangle frame (origin at the barycentre, z along the
  face normal, x towards the first vertex); tau_x = tau_y = 0 there; the 3D ellipsoidal friction
  limit surface (eq. 2.3.1) couples the tangential force (f_t,max = mu f_z,max) and the
  torsion tau_z,max.
- 167-183 and App. A (1782-1865): barycentric integration of the linear pressure
  p_i = a_i x + b_i y + d_i; closed forms of f_z,max (A.1.1), tau_x, tau_y and the lower bound
  tau_z,max >= (|tau_x| + |tau_y|) / sqrt(2) (A.1.4, with its proof). The text drops mu in
  A.1.4; line 163 (A.1.3) shows the bound carries mu, so we multiply by mu.
- 183-185: k from f_C = sum_i f_z,max,i; the ellipsoid linearized with j = 18 samples, m = 23
  constraints per triangle; the 10 largest triangles per contact.

How we count the 23 constraints: each triangle's wrench set is (normal segment) + (limit
ellipsoid), written in vertex form as s * w_N + sum_j alpha_j w_j with the 18 ellipsoid sample
wrenches w_j: alpha_j >= 0 (18 rows), sum_j alpha_j = 1 (1), 0 <= s <= 1 i.e.
0 <= f_z <= f_z,max (2), and tau_x = tau_y = 0 in the triangle frame (2, built into the
generators) -- 23. The ellipsoid is the one at the maximal normal force (Ch. 3 line 420 says
REACH's constraints have "a similar form to the soft point contact model", i.e. the largest
ellipsoid, and 6DFC's improvement is precisely the coupling to f_z).

k is normalized over the triangles kept (the n of line 183), so the kept triangles carry the
whole closing force.
"""

from __future__ import annotations

import numpy as np

from ms_drake.grasping.geometry import Patch, cross
from ms_drake.grasping.wrench_qp import WrenchProblem
from ms_drake.grasping.wrench_sets import sphere_samples


def triangle_frames(tri: np.ndarray, normals: np.ndarray):
    """Triangle frames of line 144: origin at the barycentre, z along the face normal, x towards
    the first vertex. Returns (barycentres (P,3), x (P,3), y (P,3), local xy coords (P,3,2))."""
    bary = tri.mean(axis=1)
    x = tri[:, 0] - bary
    x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)
    y = cross(normals, x)
    rel = tri - bary[:, None, :]
    xy = np.stack([np.einsum("pvk,pk->pv", rel, x), np.einsum("pvk,pk->pv", rel, y)], axis=2)
    return bary, x, y, xy


def pressure_plane(xy: np.ndarray, p_vertices: np.ndarray) -> np.ndarray:
    """Coefficients (a, b, d) of the linear pressure p = a x + b y + d matching the vertex values
    (P, 3) in each triangle frame (line 171; d is the pressure at the barycentre)."""
    M = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    return np.linalg.solve(M, p_vertices[..., None])[..., 0]


def fz_max(area, abd, xy, k=1.0):
    """App. A.1.1 (lines 1790-1799): f_z,max = A k / 3 (a (x1+x2+x3) + b (y1+y2+y3) + 3 d)."""
    a, b, d = abd[:, 0], abd[:, 1], abd[:, 2]
    X, Y = xy[..., 0], xy[..., 1]
    return area * k / 3.0 * (a * X.sum(1) + b * Y.sum(1) + 3.0 * d)


def tau_x_max(area, abd, xy, k=1.0):
    """App. A.1.4 (lines 1832-1838): (tau_x)_max = int_A k y (a x + b y + d) dA."""
    a, b, d = abd[:, 0], abd[:, 1], abd[:, 2]
    x1, x2, x3 = xy[:, 0, 0], xy[:, 1, 0], xy[:, 2, 0]
    y1, y2, y3 = xy[:, 0, 1], xy[:, 1, 1], xy[:, 2, 1]
    s = (2 * a * x1 * y1 + a * x1 * y2 + a * x1 * y3 + a * x2 * y1 + 2 * a * x2 * y2
         + a * x2 * y3 + a * x3 * y1 + a * x3 * y2 + 2 * a * x3 * y3 + 2 * b * y1 ** 2
         + 2 * b * y1 * y2 + 2 * b * y1 * y3 + 2 * b * y2 ** 2 + 2 * b * y2 * y3 + 2 * b * y3 ** 2
         + 4 * d * y1 + 4 * d * y2 + 4 * d * y3)
    return area * k / 12.0 * s


def tau_y_max(area, abd, xy, k=1.0):
    """App. A.1.4 (lines 1839-1843): (tau_y)_max = int_A k x (a x + b y + d) dA."""
    a, b, d = abd[:, 0], abd[:, 1], abd[:, 2]
    x1, x2, x3 = xy[:, 0, 0], xy[:, 1, 0], xy[:, 2, 0]
    y1, y2, y3 = xy[:, 0, 1], xy[:, 1, 1], xy[:, 2, 1]
    s = (2 * a * x1 ** 2 + 2 * a * x1 * x2 + 2 * a * x1 * x3 + 2 * a * x2 ** 2 + 2 * a * x2 * x3
         + 2 * a * x3 ** 2 + 2 * b * x1 * y1 + b * x1 * y2 + b * x1 * y3 + b * x2 * y1
         + 2 * b * x2 * y2 + b * x2 * y3 + b * x3 * y1 + b * x3 * y2 + 2 * b * x3 * y3
         + 4 * d * x1 + 4 * d * x2 + 4 * d * x3)
    return area * k / 12.0 * s


def tau_z_lower_bound(area, abd, xy, mu, k=1.0):
    """App. A.1.4 (lines 1826-1830, proposition 1847-1865): mu k / sqrt(2) (|tau_y| + |tau_x|),
    a lower bound of the maximal torsion mu int k p sqrt(x^2 + y^2) dA for p > 0."""
    return mu / np.sqrt(2.0) * (np.abs(tau_y_max(area, abd, xy, k)) + np.abs(tau_x_max(area, abd, xy, k)))


def reach_contact(patch: Patch, com: np.ndarray, mu: float, closing_force: float,
                  max_triangles: int = 10, samples: int = 18) -> list[WrenchProblem]:
    """The vertex-form wrench set (physical units, about `com`) of one REACH contact: per kept
    triangle a normal segment [0, f_z,max] and the 18-sample max-force limit ellipsoid (one
    WrenchProblem whose `blocks` are these 2 T hulls)."""
    order = np.argsort(-patch.areas)[:max_triangles]
    tri, normals, areas = patch.triangles[order], patch.normals[order], patch.areas[order]
    p_vert = patch.pressure_at_vertices()[order]
    bary, ex, ey, xy = triangle_frames(tri, normals)
    abd = pressure_plane(xy, p_vert)
    f1 = fz_max(areas, abd, xy)  # with k = 1
    total = float(f1.sum())
    if not np.isfinite(total) or total <= 0:
        raise ZeroDivisionError("zero pressure over the kept triangles")
    k = closing_force / total  # line 183: f_C = sum_i f_z,max
    fz = f1 * k
    tz = tau_z_lower_bound(areas, abd, xy, mu, k)
    u = sphere_samples(samples)
    n_in = -normals
    T, J = len(tri), len(u)
    # normal segment generators (6, T) and ellipsoid generators (6, T, J), about `com`
    fN = fz[:, None] * n_in
    normal = np.vstack([fN.T, cross(bary - com, fN).T])
    f_fric = mu * fz[:, None, None] * (u[None, :, 0:1] * ex[:, None, :] + u[None, :, 1:2] * ey[:, None, :])
    tau = cross((bary - com)[:, None, :], f_fric) + tz[:, None, None] * u[None, :, 2:3] * n_in[:, None, :]
    ell = np.concatenate([f_fric, tau], axis=2)  # (T, J, 6)
    # columns per triangle: [normal, J ellipsoid samples]; blocks: the segment (with the
    # origin) and the ellipsoid hull (without)
    G = np.concatenate([normal.T[:, None, :], ell], axis=1).reshape(T * (J + 1), 6).T
    n = G.shape[1]
    A = np.zeros((2 * T, n))
    lo = np.empty(2 * T)
    blocks = []
    for i in range(T):
        c0 = i * (J + 1)
        A[2 * i, c0] = 1.0
        A[2 * i + 1, c0 + 1: c0 + 1 + J] = 1.0
        lo[2 * i], lo[2 * i + 1] = -np.inf, 1.0
        blocks += [(c0, c0 + 1, True), (c0 + 1, c0 + 1 + J, False)]
    return [WrenchProblem(G=G, t=np.zeros(6), A=A, lo=lo, hi=np.ones(2 * T), lb=np.zeros(n),
                          ub=np.full(n, np.inf), blocks=blocks)]
