"""The wrench QP (eq. 3.3.3) on MathematicalProgram, and the NNLS fast path that must agree."""

import numpy as np
import pytest
import trimesh

from ms_drake.grasping import GraspEvaluator
from ms_drake.grasping import wrench_qp
from ms_drake.grasping.geometry import MeshData
from ms_drake.grasping.wrench_qp import RESIST_TOLERANCE, WrenchProblem, WrenchQP, solve


def _segment_problem(target):
    """x in conv({0, e_z}) must produce -t: feasible iff 0 <= -t_z <= 1 and the rest is 0."""
    G = np.zeros((6, 1))
    G[2, 0] = 1.0
    return WrenchProblem(G=G, t=np.asarray(target, float), A=np.ones((1, 1)), lo=np.array([-np.inf]),
                         hi=np.ones(1), lb=np.zeros(1), ub=np.full(1, np.inf))


def test_program_is_built_once_and_updated():
    wrench_qp._QP_CACHE.clear()
    r1 = wrench_qp.solve_mp(_segment_problem([0, 0, -0.5, 0, 0, 0]))
    qp = wrench_qp._QP_CACHE[(1, 1, "clarabel")]
    r2 = wrench_qp.solve_mp(_segment_problem([0, 0, -2.0, 0, 0, 0]))
    assert wrench_qp._QP_CACHE[(1, 1, "clarabel")] is qp and len(wrench_qp._QP_CACHE) == 1
    assert r1.resisted and r1.x[0] == pytest.approx(0.5, abs=1e-6)
    assert not r2.resisted and r2.residual == pytest.approx(1.0, abs=1e-5)  # best is x = 1


def test_failed_solve_is_reported():
    p = _segment_problem([0, 0, -0.5, 0, 0, 0])
    p.lo = np.array([2.0])  # 2 <= x <= 1: infeasible
    r = WrenchQP(1, 1).solve(p)
    assert not r.success and not r.resisted and r.residual == float("inf")


def _grasps(mesh, n, seed):
    from ms_drake.grasping.samplers import sample_antipodal_grasps

    return sample_antipodal_grasps(mesh, np.eye(4), n, friction=0.8, max_width=0.12, seed=seed,
                                   center_noise=0.004)


# Outcomes of the fixed grasps and masses of test_nnls_agrees_with_mathematical_program: no contact
# pair, resisted / slips under Clarabel, residual within a factor 3 of the tolerance (border).
QP_CASES = {
    "point": dict(no_contact=0, resisted=9, slips=71, border=0),
    "soft_point": dict(no_contact=0, resisted=19, slips=61, border=0),
    "elliptical": dict(no_contact=4, resisted=38, slips=38, border=1),
    "reach": dict(no_contact=4, resisted=21, slips=23, border=0),
}


@pytest.mark.parametrize("model", ["point", "soft_point", "elliptical", "reach"])
def test_nnls_agrees_with_mathematical_program(model):
    """Same WrenchProblem, four solvers (support function, NNLS, Clarabel, OSQP): identical resist decisions
    wherever the Clarabel residual is not within a factor 3 of the tolerance, and the stated
    number of each outcome."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=24)
    mesh2 = trimesh.creation.box(extents=(0.04, 0.07, 0.03))
    data = [MeshData.of(mesh), MeshData.of(mesh2)]
    ev = GraspEvaluator(model, friction=0.5, closing_force=10.0, material_constant=3e-4)
    n = dict(no_contact=0, resisted=0, slips=0, border=0)
    for k, d in enumerate(data):
        for g in _grasps(d.mesh, 6 if model == "reach" else 10, seed=k):
            # a COM on the grasp axis lets point contacts hold too (no torque about the axis)
            for mass, com in ((0.2, d.centroid), (0.9, d.centroid), (0.4, g.center), (1.5, g.center)):
                p, reason = ev.contact_problem(d, g, com, np.array([0, 0, -1.0]), 0.5, mass,
                                               np.random.default_rng(0))
                if p is None:
                    n["no_contact"] += 1
                    continue
                a = solve(p, "nnls")
                b = solve(p, "clarabel")
                c = solve(p, "osqp")
                f = solve(p, "support")
                assert a.success and b.success and f.success
                assert f.resisted == b.resisted or abs(np.log(max(b.residual, 1e-12) / RESIST_TOLERANCE)) < np.log(3)
                if b.resisted:
                    n["resisted"] += 1
                    assert b.residual < RESIST_TOLERANCE and f.residual < 3 * RESIST_TOLERANCE
                else:  # converged distance = the QP optimum
                    n["slips"] += 1
                    exact = wrench_qp.solve_support(p, early_exit=False)
                    assert exact.residual == pytest.approx(b.residual, rel=1e-4, abs=1e-6)
                    assert f.residual >= exact.residual - 1e-9
                if abs(np.log(max(b.residual, 1e-12) / RESIST_TOLERANCE)) < np.log(3):
                    n["border"] += 1
                    continue
                assert a.resisted == b.resisted, (g, mass, a.residual, b.residual)
                # OSQP (first order) converges within its iteration limit on every one of these
                assert c.success and c.resisted == b.resisted, (g, mass, c.residual, b.residual)
    assert n == QP_CASES[model]


def test_naive_path_agrees():
    mesh = trimesh.creation.box(extents=(0.04, 0.07, 0.03))
    for model in ("point", "6dfc"):
        fast = GraspEvaluator(model)
        naive = GraspEvaluator(model, solver="naive")
        for g in _grasps(mesh, 10, seed=3):
            assert fast.quality(mesh, np.eye(4), g, 0.4) == naive.quality(mesh, np.eye(4), g, 0.4)
