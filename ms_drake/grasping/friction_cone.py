"""MFE and 6DFC: 6D friction limit surfaces of non-planar area contacts (Ch. 3).

Reference lines (mechanical-search-dissertation.txt):
- 358-362: the 6D friction cone (eq. 3.3.2): (w - f_C f_N)^T A (w - f_C f_N) <= f_C^2,
  0 <= f_C <= f_C,max, with f_N the normal wrench per unit closing force.
- 372-382: friction wrench sampling: k1 tuples (rotation axis omega uniform on S^2, centre c
  within radius r of the pressure centre) and k2 pure translations; the unit velocity at each
  triangle projected onto the triangle plane; w = - sum_t mu Ad_t f_N,t v_t.
- 384-388: least-squares fit of A (w^T A w = 1) after PCA; missing dimensions get axes of a
  small epsilon.
- 390-402: tangent-plane linearization z^T A x_i <= 1 at points x_i resampled evenly on the
  ellipsoid, then shifted by the normal wrench and scaled by the closing force:
  z^T A x_i - f_C (1 + f_N^T A x_i) <= 0.
- 426: MFE = the same ellipsoid at the maximal closing force only (f_C fixed to f_C,max).

Choices the text leaves open (recorded here):
- Pressure per triangle f_N,t: the REACH pressure p = k delta (n . a) integrated over the
  triangle (App. A.1.1), normalized to sum to 1 (unit closing force); velocities are taken at
  the triangle barycentres (the per-triangle adjoint Ad_t of line 382).
- r = the patch radius (largest barycentre distance from the pressure centre).
- Both w and -w are kept (the limit surface is symmetric), doubling the samples for free.
- Torques are divided by the patch radius before PCA and fitting so the six coordinates have
  comparable size; PCA keeps the directions whose singular value exceeds 1e-2 of the largest;
  epsilon = 1e-3 of the smallest fitted semi-axis.
- If the quadric fitted in d dimensions is not positive definite, the least-spread PCA direction
  joins the epsilon directions and the fit is repeated (a nearly flat direction makes the
  least-squares quadric ill-posed: a box edge patch gave indefinite fits in 6 of 10 perturbed
  trials without this). Only when no dimension works is it a "degenerate_fit" (quality 0).
- Resampling: directions +-e_i of the fitted subspace plus `planes` quasi-random symmetric
  directions of a fixed seed, mapped to the ellipsoid through its Cholesky factor; plus +-epsilon
  planes in the missing dimensions.
"""

from __future__ import annotations

import functools

import numpy as np

from ms_drake.grasping.geometry import Patch, cross
from ms_drake.grasping.wrench_qp import WrenchProblem


class DegenerateFit(ValueError):
    pass


def triangle_normal_forces(patch: Patch) -> np.ndarray:
    """f_N,t per unit closing force: int_T delta (n . a) dA = A_t * mean of vertex values."""
    f = patch.areas * patch.pressure_at_vertices().mean(axis=1)
    s = float(f.sum())
    if not np.isfinite(s) or s <= 0:
        raise DegenerateFit("zero pressure over the patch")
    return f / s


def _unit_rows(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-300), 0.0)


def sample_friction_wrenches(bary, normals_out, fN, origin, mu, k1, k2, radius, rng) -> np.ndarray:
    """(2 (k1 + k2), 6) friction wrenches about `origin` for unit closing force (lines 372-382)."""
    omega = _unit_rows(rng.normal(size=(k1, 3)))
    ball = _unit_rows(rng.normal(size=(k1, 3))) * (rng.random((k1, 1)) ** (1 / 3)) * radius
    centres = origin + ball
    # object velocity at each barycentre: omega x (b - c) = omega x b - omega x c  (k1, T, 3)
    v_rot = cross(omega[:, None, :], bary[None, :, :]) - cross(omega, centres)[:, None, :]
    v_trans = np.broadcast_to(_unit_rows(rng.normal(size=(k2, 3)))[:, None, :], (k2, len(bary), 3))
    v = np.concatenate([v_rot, v_trans], axis=0)
    n = normals_out[None]
    v = v - np.einsum("ktj,ktj->kt", v, n)[..., None] * n  # projected onto each triangle
    norm = np.sqrt(np.einsum("ktj,ktj->kt", v, v))
    w_t = np.where(norm > 1e-12, fN[None, :] / np.maximum(norm, 1e-300), 0.0)  # f_N,t / |v_t|
    # force on the object opposes its sliding: f_t = -mu f_N,t v_t / |v_t|; sum over triangles
    F = -mu * np.einsum("kt,ktj->kj", w_t, v)
    skew = _skew(bary - origin)  # (T, 3, 3): r_t x
    tau = -mu * np.einsum("kt,tij,ktj->ki", w_t, skew, v)
    w = np.concatenate([F, tau], axis=1)
    return np.vstack([w, -w])


def _skew(r: np.ndarray) -> np.ndarray:
    S = np.zeros(r.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -r[..., 2], r[..., 1]
    S[..., 1, 0], S[..., 1, 2] = r[..., 2], -r[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -r[..., 1], r[..., 0]
    return S


@functools.cache
def _directions(d: int, count: int) -> np.ndarray:
    rng = np.random.default_rng(12345 + d)
    u = _unit_rows(rng.normal(size=(count // 2, d)))
    return np.vstack([np.eye(d), -np.eye(d), u, -u])


def fit_ellipsoid(samples: np.ndarray, rel_tol: float = 1e-2):
    """PCA + linear least squares fit of y^T A_d y = 1 (lines 384-388).

    The dimension d counts singular values above rel_tol of the largest. If the quadric fitted
    in d dimensions is not positive definite (the least-squares fit of a nearly flat direction
    is ill-posed), the least-spread direction is dropped and the fit repeated.
    Returns (V_d (6,d), A_d (d,d), V_rest (6,6-d), eps). Raises DegenerateFit."""
    if not np.all(np.isfinite(samples)):
        raise DegenerateFit("non-finite wrench samples")
    if len(samples) < 6:
        raise DegenerateFit("fewer wrench samples than dimensions")
    ev6, V6 = np.linalg.eigh(samples.T @ samples)  # PCA through the 6x6 scatter matrix
    s, Vt = np.sqrt(np.maximum(ev6[::-1], 0.0)), V6[:, ::-1].T
    if s[0] <= 1e-15:
        raise DegenerateFit("all friction wrench samples are zero")
    d = int(np.sum(s > rel_tol * s[0]))
    while d > 0:
        V_d = Vt[:d].T
        Y = samples @ V_d
        iu = np.triu_indices(d)
        design = Y[:, iu[0]] * Y[:, iu[1]] * np.where(iu[0] == iu[1], 1.0, 2.0)
        try:  # normal equations of the linear least squares (well conditioned after PCA)
            coef = np.linalg.solve(design.T @ design, design.sum(axis=0))
        except np.linalg.LinAlgError:
            coef, *_ = np.linalg.lstsq(design, np.ones(len(Y)), rcond=None)
        A = np.zeros((d, d))
        A[iu] = coef
        A = A + A.T - np.diag(np.diag(A))
        ev = np.linalg.eigvalsh(A)
        if ev[0] > 0 and np.all(np.isfinite(ev)):
            return V_d, A, Vt[d:].T, 1e-3 / np.sqrt(ev[-1])
        d -= 1
    raise DegenerateFit("no positive definite quadric fits the friction wrench samples")


def tangent_planes(V_d, A_d, V_rest, eps, planes: int):
    """Normals N (P, 6) and points X (P, 6) with x^T A x = 1 and N = A x (lines 390-398)."""
    d = A_d.shape[0]
    L = np.linalg.cholesky(A_d)  # A = L L^T, x = L^-T u  =>  x^T A x = |u|^2
    U = _directions(d, planes)
    Xd = np.linalg.solve(L.T, U.T).T
    X = Xd @ V_d.T
    N = (Xd @ A_d) @ V_d.T
    if V_rest.shape[1]:
        E = np.vstack([V_rest.T, -V_rest.T])
        X = np.vstack([X, eps * E])
        N = np.vstack([N, E / eps])
    return N, X


def cone_contact(patch: Patch, com: np.ndarray, mu: float, closing_force: float, W: np.ndarray,
                 rng, k1: int, k2: int, planes: int, cone: bool) -> WrenchProblem:
    """One contact's halfspace wrench set in normalized variables.

    cone=True (6DFC): variables z' (6, normalized wrench about the pressure centre) and
    phi = f_C / f_C,max in [0, 1]; rows n_i . S z - f_C (1 + n_i . S f_N) <= 0.
    cone=False (MFE): f_C = f_C,max fixed; variables z' only.
    """
    fN = triangle_normal_forces(patch)
    bary = patch.triangles.mean(axis=1)
    origin = fN @ bary  # pressure centre
    radius = max(float(np.max(np.linalg.norm(bary - origin, axis=1))), 1e-4)
    n_in = -patch.normals
    f_normal = np.concatenate([fN @ n_in, cross(bary - origin, fN[:, None] * n_in).sum(axis=0)])
    samples = sample_friction_wrenches(bary, patch.normals, fN, origin, mu, k1, k2, radius, rng)
    S = np.concatenate([np.ones(3), np.full(3, 1.0 / radius)])  # torque scaling for the fit
    V_d, A_d, V_rest, eps = fit_ellipsoid(samples * S)
    N, _ = tangent_planes(V_d, A_d, V_rest, eps, planes)
    # physical wrench z about `origin` = D z' with D = 1 / W; wrench about com = Ad z
    D = 1.0 / W
    Ad = np.eye(6)
    r = origin - com
    Ad[3:, :3] = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    G = (W[:, None] * Ad) * D[None, :]
    rows = (N * S[None, :]) * D[None, :]  # n . (S z) with z = D z'
    shift = 1.0 + N @ (S * f_normal)
    scale = np.linalg.norm(rows, axis=1)
    if cone:
        A = np.hstack([rows, -(closing_force * shift)[:, None]]) / scale[:, None]
        G = np.hstack([G, np.zeros((6, 1))])
        hi = np.zeros(len(rows))
        lb = np.concatenate([np.full(6, -np.inf), [0.0]])
        ub = np.concatenate([np.full(6, np.inf), [1.0]])
    else:
        A = rows / scale[:, None]
        hi = closing_force * shift / scale
        lb, ub = np.full(6, -np.inf), np.full(6, np.inf)
    return WrenchProblem(G=G, t=np.zeros(6), A=A, lo=np.full(len(hi), -np.inf), hi=hi, lb=lb, ub=ub)
