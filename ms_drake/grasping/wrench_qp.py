"""The wrench-resistance quadratic program of eq. 3.3.3 (reference lines 404-408).

    min_z || G z + t ||^2   s.t.   F z <= h

G maps the contact variables z to wrenches on the object about its centre of mass, t is the
gravity wrench. A grasp resists gravity when the optimal residual is ~0.

Every contact model in ms_drake produces a `WrenchProblem`: variables x with box bounds,
linear rows lo <= A x <= hi (equality when lo == hi), and the wrench map G. Units are
normalized so the QP is well scaled whatever the object: forces are divided by the weight m g
and torques by m g L (L = half the object's bounding-box diagonal), so t has unit norm.

Two solvers answer the same question:
- `WrenchQP`: Drake MathematicalProgram, built ONCE per problem structure (number of
  variables and rows) and updated per grasp with UpdateCoefficients / set_bounds, solved by an
  explicitly chosen solver (Clarabel by default: interior point, accurate to ~1e-8 here; OSQP
  is available and slightly faster but only accurate to its eps tolerances). The residual y
  enters as 6 extra variables with the equality y - G x = t, so the Hessian is the 6x6
  identity and the solve scales with the number of constraint rows, not n^2.
- Vertex-form problems (point, soft point, elliptical, REACH: each contact's wrench set is a
  Minkowski sum of convex hulls of generator wrenches, conv(V) or conv({0} u V)) have two exact
  fast paths answering the same QP -- the optimal residual is the distance from -t to the grasp
  wrench space GWS = sum_b conv(V_b):
  * `solve_support` ("auto" beyond 64 generators, i.e. REACH): fully corrective Frank-Wolfe on that distance using
    the GWS support function h(d) = sum_b max_{v in V_b} v . d (one matrix-vector product per
    iteration); the small subproblem over the active support points is a scipy NNLS. It stops as
    soon as the residual is below the tolerance (resisted) or the Frank-Wolfe lower bound
    (s + t) . y/|y| exceeds it (slips), otherwise at convergence (finite for polytopes).
  * `solve_nnls` ("auto" up to 64 generators: point, soft point, elliptical): the whole
    problem as one scipy NNLS (rows become equalities with one slack per
    inequality, weighted by `ROW_WEIGHT`); residual zero in one <=> zero in the other.
  tests/test_grasp_qp.py checks both against the MathematicalProgram decisions and residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.solvers import (
    ClarabelSolver,
    MathematicalProgram,
    OsqpSolver,
    Solve,
    SolverOptions,
)
from scipy.optimize import nnls

RESIST_TOLERANCE = 1e-3  # residual, as a fraction of the weight, below which gravity is resisted
ROW_WEIGHT = 10.0
SOLVERS = ("auto", "support", "nnls", "clarabel", "osqp")


@dataclass
class WrenchProblem:
    """min ||G x + t||^2  s.t.  lb <= x <= ub,  lo <= A x <= hi   (normalized units)."""

    G: np.ndarray  # (6, n)
    t: np.ndarray  # (6,)
    A: np.ndarray  # (m, n)
    lo: np.ndarray  # (m,)
    hi: np.ndarray  # (m,)
    lb: np.ndarray  # (n,)
    ub: np.ndarray  # (n,)
    # vertex form: (first column, end column, includes the origin) per convex-hull block
    blocks: list | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.G.shape[1], self.A.shape[0]

    def is_vertex_form(self) -> bool:
        """All variables >= 0 and unbounded above (so NNLS applies)."""
        return bool(np.all(self.lb == 0) and np.all(np.isinf(self.ub)))

    def is_hull_sum(self) -> bool:
        """A Minkowski sum of convex hulls of generator columns (so solve_support applies)."""
        return self.blocks is not None and sum(e - b for b, e, _ in self.blocks) == self.G.shape[1]

    def residual(self, x: np.ndarray) -> float:
        return float(np.linalg.norm(self.G @ x + self.t))

    def violation(self, x: np.ndarray) -> float:
        ax = self.A @ x
        v = [0.0]
        if len(ax):
            v.append(float(np.max(np.maximum(ax - self.hi, self.lo - ax))))
        v.append(float(np.max(np.maximum(x - self.ub, self.lb - x), initial=0.0)))
        return max(v)


@dataclass
class QPResult:
    success: bool
    residual: float  # ||G x + t|| in units of the weight
    violation: float
    x: np.ndarray | None
    solver: str

    @property
    def resisted(self) -> bool:
        return self.success and self.residual <= RESIST_TOLERANCE and self.violation <= RESIST_TOLERANCE


def stack(blocks: list[WrenchProblem], t: np.ndarray) -> WrenchProblem:
    """Concatenate per-contact problems (block-diagonal rows, side-by-side wrench maps)."""
    G = np.hstack([b.G for b in blocks])
    n = G.shape[1]
    m = sum(b.A.shape[0] for b in blocks)
    A = np.zeros((m, n))
    r = c = 0
    for b in blocks:
        A[r:r + b.A.shape[0], c:c + b.A.shape[1]] = b.A
        r += b.A.shape[0]
        c += b.A.shape[1]
    cat = lambda name: np.concatenate([getattr(b, name) for b in blocks])  # noqa: E731
    hull_blocks, c = [], 0
    for b in blocks:
        if b.blocks is None:
            hull_blocks = None
            break
        hull_blocks.extend((c + s, c + e, o) for s, e, o in b.blocks)
        c += b.G.shape[1]
    return WrenchProblem(G, np.asarray(t, float), A, cat("lo"), cat("hi"), cat("lb"), cat("ub"), hull_blocks)


class WrenchQP:
    """Eq. 3.3.3 as a Drake MathematicalProgram, built once for a given (n, m) and re-solved.

    solver: "clarabel" (default) or "osqp".
    """

    def __init__(self, n: int, m: int, solver: str = "clarabel"):
        self.n, self.m = n, m
        prog = MathematicalProgram()
        self.x = prog.NewContinuousVariables(n, "x")
        self.y = prog.NewContinuousVariables(6, "y")
        prog.AddQuadraticCost(2.0 * np.eye(6), np.zeros(6), 0.0, self.y, is_convex=True)
        self.bounds = prog.AddBoundingBoxConstraint(np.zeros(n), np.full(n, np.inf), self.x)
        self.rows = (prog.AddLinearConstraint(np.zeros((m, n)), np.full(m, -np.inf), np.zeros(m), self.x)
                     if m else None)
        self.eq = prog.AddLinearEqualityConstraint(np.hstack([np.eye(6), np.zeros((6, n))]), np.zeros(6),
                                                   np.concatenate([self.y, self.x]))
        self.prog = prog
        self.options = SolverOptions()
        if solver == "osqp":
            self.solver = OsqpSolver()
            sid = self.solver.solver_id()
            for k, v in (("verbose", 0), ("eps_abs", 1e-6), ("eps_rel", 1e-6), ("max_iter", 50000)):
                self.options.SetOption(sid, k, v)
        elif solver == "clarabel":
            self.solver = ClarabelSolver()
        else:
            raise ValueError(f"WrenchQP solver must be 'clarabel' or 'osqp', got {solver!r}")
        self.name = solver

    def solve(self, p: WrenchProblem) -> QPResult:
        assert p.shape == (self.n, self.m), (p.shape, (self.n, self.m))
        self.bounds.evaluator().set_bounds(p.lb, p.ub)
        if self.rows is not None:
            self.rows.evaluator().UpdateCoefficients(p.A, p.lo, p.hi)
        self.eq.evaluator().UpdateCoefficients(np.hstack([np.eye(6), -p.G]), p.t)
        res = self.solver.Solve(self.prog, None, self.options)
        if not res.is_success():
            return QPResult(False, float("inf"), float("inf"), None, self.name)
        x = res.GetSolution(self.x)
        return QPResult(True, p.residual(x), p.violation(x), x, self.name)


_QP_CACHE: dict[tuple[int, int, str], WrenchQP] = {}


def solve_mp(p: WrenchProblem, solver: str = "clarabel") -> QPResult:
    """Solve with the cached MathematicalProgram of this structure (built on first use)."""
    key = (*p.shape, solver)
    qp = _QP_CACHE.get(key)
    if qp is None:
        if len(_QP_CACHE) > 256:
            _QP_CACHE.clear()
        qp = _QP_CACHE[key] = WrenchQP(*p.shape, solver=solver)
    return qp.solve(p)


def solve_mp_naive(p: WrenchProblem) -> QPResult:
    """The slow baseline for benchmarks: build a fresh program and call pydrake's Solve()
    (automatic solver choice) for every grasp, with the dense cost ||G x + t||^2."""
    prog = MathematicalProgram()
    x = prog.NewContinuousVariables(p.G.shape[1], "x")
    prog.AddQuadraticCost(2 * p.G.T @ p.G, 2 * p.G.T @ p.t, float(p.t @ p.t), x, is_convex=True)
    prog.AddBoundingBoxConstraint(p.lb, p.ub, x)
    if p.A.shape[0]:
        prog.AddLinearConstraint(p.A, p.lo, p.hi, x)
    res = Solve(prog)
    if not res.is_success():
        return QPResult(False, float("inf"), float("inf"), None, "naive")
    xs = res.GetSolution(x)
    return QPResult(True, p.residual(xs), p.violation(xs), xs, "naive:" + res.get_solver_id().name())


def solve_nnls(p: WrenchProblem) -> QPResult:
    """Exact feasibility by scipy's non-negative least squares (vertex-form problems only).

    Each equality row becomes one weighted row, each one-sided inequality one weighted row with
    its own slack variable >= 0; the wrench rows keep unit weight."""
    if not p.is_vertex_form():
        raise ValueError("solve_nnls needs all variables >= 0 with no upper bounds")
    n, m = p.shape
    rows, rhs, slack_sign = [], [], []
    for i in range(m):
        sides = [(p.hi[i], 0.0)] if p.lo[i] == p.hi[i] else (
            ([(p.hi[i], 1.0)] if np.isfinite(p.hi[i]) else []) + ([(p.lo[i], -1.0)] if np.isfinite(p.lo[i]) else []))
        for value, sign in sides:
            rows.append(p.A[i])
            rhs.append(value)
            slack_sign.append(sign)
    slack_cols = [k for k, s in enumerate(slack_sign) if s != 0.0]
    M = np.zeros((6 + len(rows), n + len(slack_cols)))
    M[:6, :n] = p.G
    b = np.concatenate([-p.t, ROW_WEIGHT * np.asarray(rhs, float)])
    if rows:
        M[6:, :n] = ROW_WEIGHT * np.asarray(rows)
        for j, k in enumerate(slack_cols):
            M[6 + k, n + j] = ROW_WEIGHT * slack_sign[k]
    try:
        sol, _ = nnls(M, b, maxiter=50 * M.shape[1])
    except RuntimeError:
        return QPResult(False, float("inf"), float("inf"), None, "nnls")
    x = sol[:n]
    return QPResult(True, p.residual(x), p.violation(x), x, "nnls")


def _min_norm_in_hull(S: np.ndarray, t: np.ndarray) -> np.ndarray:
    """lambda in the simplex minimizing ||S lambda + t|| (S: (6, m) with small m)."""
    m = S.shape[1]
    if m == 1:
        return np.ones(1)
    rho = 1e3 * max(1.0, float(np.abs(S).max()), float(np.abs(t).max()))
    M = np.vstack([S, np.full((1, m), rho)])
    lam, _ = nnls(M, np.concatenate([-t, [rho]]), maxiter=50 * m)
    total = lam.sum()
    return lam / total if total > 0 else np.full(m, 1.0 / m)


def solve_support(p: WrenchProblem, tol: float = RESIST_TOLERANCE, max_iter: int = 200,
                  early_exit: bool = True) -> QPResult:
    """Distance from -t to the Minkowski sum of hulls by fully corrective Frank-Wolfe. With
    early_exit the iteration stops once the resist decision is certain (residual <= tol, or the
    lower bound > tol); without it, at convergence (the exact QP optimum)."""
    if not p.is_hull_sum():
        raise ValueError("solve_support needs a Minkowski sum of convex hulls (WrenchProblem.blocks)")
    G, t = p.G, p.t
    B = len(p.blocks)
    kmax = max(e - s for s, e, _ in p.blocks) + 1
    idx = np.full((B, kmax), -1, dtype=np.int64)  # column indices, -1 = padding, last slot = origin
    with_origin = np.zeros(B, bool)
    for i, (s0, e0, o) in enumerate(p.blocks):
        idx[i, : e0 - s0] = np.arange(s0, e0)
        with_origin[i] = o
    valid = idx >= 0
    origin_slot = np.zeros((B, kmax), bool)
    origin_slot[with_origin, -1] = True
    safe = np.where(valid, idx, 0)

    def support(d):
        vals = G.T @ d
        v = np.where(valid, vals[safe], -np.inf)
        v = np.where(origin_slot, 0.0, v)
        pick = np.argmax(v, axis=1)
        cols = idx[np.arange(B), pick]  # -1 where the origin wins
        chosen = cols[cols >= 0]
        return G[:, chosen].sum(axis=1), chosen

    s, cols = support(-t)
    S, C = [s], [cols]
    r, lam = np.inf, np.ones(1)
    for _ in range(max_iter):
        Sm = np.column_stack(S)
        lam = _min_norm_in_hull(Sm, t)
        y = Sm @ lam + t
        r = float(np.linalg.norm(y))
        if r <= (tol if early_exit else 1e-12):
            break
        s, cols = support(-y)
        lower = float((s + t) @ y) / r
        if (early_exit and lower > tol) or r - lower <= 1e-10 * max(1.0, r):
            break
        keep = lam > 1e-12
        S = [S[i] for i in np.nonzero(keep)[0]] + [s]
        C = [C[i] for i in np.nonzero(keep)[0]] + [cols]
    x = np.zeros(G.shape[1])
    for w, cols in zip(lam, C[: len(lam)]):
        x[cols] += w
    return QPResult(True, r, p.violation(x), x, "support")


def solve(p: WrenchProblem, solver: str = "auto") -> QPResult:
    """Solve eq. 3.3.3. "auto": for Minkowski sums of hulls (point, soft point, elliptical,
    REACH) one NNLS when there are <= 64 generators, the support-function path beyond; Clarabel
    on the MathematicalProgram otherwise (MFE, 6DFC)."""
    if solver == "auto":  # one NNLS is fastest for small hull sums, Frank-Wolfe for large ones
        solver = ("nnls" if p.G.shape[1] <= 64 else "support") if p.is_hull_sum() else "clarabel"
    if solver == "support":
        return solve_support(p)
    if solver == "nnls":
        return solve_nnls(p)
    if solver == "naive":
        return solve_mp_naive(p)
    return solve_mp(p, solver)
