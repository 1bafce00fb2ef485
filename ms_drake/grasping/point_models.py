"""Point, soft point and elliptical contact wrench sets (vertex form, physical units).

- Point contact (reference line 333, eq. 3.3.1): Coulomb cone around the inward normal,
  linearized by `edges` generators on its surface (an inner approximation), normal force
  0 <= f_n <= f_C: conv({0} u {f_C (n + mu (cos t1 + sin t2))}).
- Soft point contact (line 213; Fig. 3.2b): the 4D cone ||f_t||^2 / mu^2 + tau^2 / gamma^2
  <= f_n^2, 0 <= f_n <= f_C, gamma = `torsional_friction` in metres (torsion <= gamma f_n),
  linearized by the 18 ellipsoid samples at f_n = f_C (generators of the cone).
- Elliptical area contact (line 217, after Ciocarlie et al. 2007): an ellipse fitted to the
  patch (area second moments: a uniform ellipse has variance a^2 / 4 along its axis), Hertzian
  pressure p0 sqrt(1 - x^2/a^2 - y^2/b^2). Its maximal torsion is closed form,
      tau_max = mu N (3/8) a E(1 - b^2/a^2)    (a >= b, E the complete elliptic integral),
  from int p sqrt(x^2+y^2) dA = p0 a b (pi/16) 4 a E and N = int p dA = (2 pi / 3) p0 a b
  (circle: 3 pi mu N a / 16, Ciocarlie's value). The wrench set is the maximal ellipsoid
  (f_t,max = mu f_C, tau_max at N = f_C) plus the normal force 0 <= f_n <= f_C at the patch
  centroid along the fitted plane's normal.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ellipe

from ms_drake.grasping.geometry import MeshData, Patch, cross
from ms_drake.grasping.wrench_qp import WrenchProblem
from ms_drake.grasping.wrench_sets import (
    ellipsoid_generators,
    hull,
    sphere_samples,
    wrench,
)


def ray_contacts(data: MeshData, center, axis, width, approach=None, pad_span: float = 0.0,
                 step: float = 0.001):
    """Where the two jaws first touch the object along the grasp axis.

    Returns ((points (2,3), inward normals (2,3)), "") or (None, reason), reason in
    {"miss", "jaw_collision"}: a jaw whose first hit is an exit face starts inside the object;
    a jaw with no entry within the opening misses.

    pad_span > 0 (metres; needs `approach`): the pads reach that far beyond the centre along the
    approach (towards the fingertips). When the line through the centre misses, lines every
    `step` towards the fingertips are tried; the first that does not miss decides: a jaw
    collision there is one, else the contacts are those of the middle line of the run of lines
    (from that one on) where both jaws touch -- where a pad meets a thin object's side below the
    tool point."""
    center, axis = np.asarray(center, float), np.asarray(axis, float)
    found = _line_contacts(data, center[None], axis, width)[0]
    if found[0] is not None or found[1] != "miss" or pad_span <= 0:
        return found
    if approach is None:
        raise ValueError("ray_contacts: pad_span > 0 needs the approach direction")
    offsets = np.arange(1, int(np.floor(pad_span / step + 1e-9)) + 1) * step
    if not len(offsets):
        return found
    lines = _line_contacts(data, center[None] + offsets[:, None] * np.asarray(approach, float)[None], axis, width)
    first = next((k for k, (c, r) in enumerate(lines) if r != "miss"), None)
    if first is None:
        return None, "miss"
    if lines[first][0] is None:
        return lines[first]
    last = first
    while last + 1 < len(lines) and lines[last + 1][0] is not None:
        last += 1
    return lines[(first + last) // 2]


def _line_contacts(data: MeshData, centers: np.ndarray, axis: np.ndarray, width: float) -> list:
    """ray_contacts' answer for the lines through each of `centers` (M, 3) along `axis`, in one
    ray cast: [(contacts or None, reason), ...]."""
    M = len(centers)
    origins = np.concatenate([centers - 0.5 * width * axis, centers + 0.5 * width * axis])
    dirs = np.concatenate([np.repeat(axis[None], M, 0), np.repeat(-axis[None], M, 0)])
    t, n_out = data.raycast(origins, dirs, np.inf)
    out = []
    for k in range(M):
        i = [k, M + k]
        tk, nk, dk = t[i], n_out[i], dirs[i]
        if not np.all(np.isfinite(tk)):
            out.append((None, "miss"))
        elif np.any(np.sum(nk * dk, axis=1) >= 0):
            out.append((None, "jaw_collision"))
        elif np.any(tk > width):
            out.append((None, "miss"))
        else:
            out.append(((origins[i] + tk[:, None] * dk, -nk), ""))
    return out


def _tangents(n: np.ndarray):
    """(K, 3) unit normals -> two (K, 3) orthonormal tangent fields."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, cross(n, t1)


def contacts_problem(points, normals_in, com, mu, closing_force, W, torsion: float = 0.0, edges: int = 8,
                     samples: int = 18) -> WrenchProblem:
    """All point (torsion = 0: `edges`-edge linearized Coulomb cone) or soft point (torsion =
    gamma: 18-sample elliptical limit-surface cone) contacts as one normalized hull-sum problem:
    per contact conv({0} u {f_C (n + mu (u_x t1 + u_y t2)), with torsion gamma u_z f_C about n})."""
    K = len(points)
    t1, t2 = _tangents(normals_in)
    if torsion > 0:
        u = sphere_samples(samples)
    else:
        th = 2 * np.pi * np.arange(edges) / edges
        u = np.column_stack([np.cos(th), np.sin(th), np.zeros(edges)])
    J = len(u)
    tangential = u[None, :, 0:1] * t1[:, None, :] + u[None, :, 1:2] * t2[:, None, :]
    f = closing_force * (normals_in[:, None, :] + mu * tangential)
    tau = cross((points - com)[:, None, :], f) + (closing_force * torsion) * u[None, :, 2:3] * normals_in[:, None, :]
    G = (np.concatenate([f, tau], axis=2).reshape(K * J, 6) * W).T
    A = np.zeros((K, K * J))
    for k in range(K):
        A[k, k * J:(k + 1) * J] = 1.0
    return WrenchProblem(G=G, t=np.zeros(6), A=A, lo=np.full(K, -np.inf), hi=np.ones(K), lb=np.zeros(K * J),
                         ub=np.full(K * J, np.inf), blocks=[(k * J, (k + 1) * J, True) for k in range(K)])


def fit_ellipse(patch: Patch):
    """(centroid, inward normal, a, b, t1, t2) of the ellipse with the patch's area moments."""
    tri, areas = patch.triangles, patch.areas
    A = areas.sum()
    cent = (areas[:, None] * tri.mean(axis=1)).sum(axis=0) / A
    rel = tri - cent
    s = rel.sum(axis=1)
    # E[x x^T] over a uniform triangle = (sum_i v_i v_i^T + s s^T) / 12 (about `cent`)
    M = (np.einsum("p,pvi,pvj->ij", areas, rel, rel) + np.einsum("p,pi,pj->ij", areas, s, s)) / (12.0 * A)
    ev, V = np.linalg.eigh(M)
    n = V[:, 0]
    if n @ patch.closing < 0:
        n = -n
    a = 2.0 * np.sqrt(max(ev[2], 0.0))
    b = 2.0 * np.sqrt(max(ev[1], 0.0))
    return cent, n, a, b, V[:, 2], cross(n, V[:, 2])


def elliptical_torsion(mu, normal_force, a, b):
    """tau_max of a Hertzian ellipse (a >= b): mu N (3/8) a E(1 - b^2/a^2)."""
    m = 1.0 - (b / a) ** 2 if a > 0 else 0.0
    return mu * normal_force * 3.0 / 8.0 * a * ellipe(m)


def elliptical_contact(patch: Patch, com, mu, closing_force, samples: int = 18) -> list[WrenchProblem]:
    cent, n_in, a, b, t1, t2 = fit_ellipse(patch)
    if not (a > 1e-6 and np.isfinite(a)):
        raise ValueError("degenerate ellipse fit")
    tau = elliptical_torsion(mu, closing_force, a, b)
    normal = hull(wrench(cent[None], (closing_force * n_in)[None], com), include_origin=True)
    fric = hull(ellipsoid_generators(cent, n_in, com, mu * closing_force, tau, sphere_samples(samples), t1, t2),
                include_origin=False)
    return [normal, fric]
