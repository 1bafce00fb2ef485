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
- `solve_nnls`: for problems whose variables are all >= 0 (the vertex (V-) representation the
  point, soft point, elliptical and REACH models use: convex combinations of generator
  wrenches), the same feasibility question is a non-negative least-squares problem: rows
  become equalities with one slack per inequality, weighted by `ROW_WEIGHT` relative to the
  wrench rows. Residual zero in one <=> residual zero in the other; tests/test_grasp_qp.py
  checks that the two decisions agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RESIST_TOLERANCE = 1e-3  # residual, as a fraction of the weight, below which gravity is resisted
ROW_WEIGHT = 10.0
SOLVERS = ("auto", "nnls", "clarabel", "osqp")


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

    @property
    def shape(self) -> tuple[int, int]:
        return self.G.shape[1], self.A.shape[0]

    def is_vertex_form(self) -> bool:
        """All variables >= 0 and unbounded above (so NNLS applies)."""
        return bool(np.all(self.lb == 0) and np.all(np.isinf(self.ub)))

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
    return WrenchProblem(G, np.asarray(t, float), A, cat("lo"), cat("hi"), cat("lb"), cat("ub"))


class WrenchQP:
    """Eq. 3.3.3 as a Drake MathematicalProgram, built once for a given (n, m) and re-solved.

    solver: "clarabel" (default) or "osqp".
    """

    def __init__(self, n: int, m: int, solver: str = "clarabel"):
        from pydrake.solvers import (ClarabelSolver, MathematicalProgram, OsqpSolver,
                                     SolverOptions)

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
    from pydrake.solvers import MathematicalProgram, Solve

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
    from scipy.optimize import nnls

    if not p.is_vertex_form():
        raise ValueError("solve_nnls needs all variables >= 0 with no upper bounds")
    n, m = p.shape
    rows, rhs, slack_sign = [], [], []
    for i in range(m):
        if p.lo[i] == p.hi[i]:
            rows.append(p.A[i]); rhs.append(p.hi[i]); slack_sign.append(0.0)
            continue
        if np.isfinite(p.hi[i]):
            rows.append(p.A[i]); rhs.append(p.hi[i]); slack_sign.append(1.0)
        if np.isfinite(p.lo[i]):
            rows.append(p.A[i]); rhs.append(p.lo[i]); slack_sign.append(-1.0)
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


def solve(p: WrenchProblem, solver: str = "auto") -> QPResult:
    """Solve eq. 3.3.3. "auto": NNLS for vertex-form problems, Clarabel otherwise."""
    if solver == "auto":
        solver = "nnls" if p.is_vertex_form() else "clarabel"
    if solver == "nnls":
        return solve_nnls(p)
    if solver == "naive":
        return solve_mp_naive(p)
    return solve_mp(p, solver)
