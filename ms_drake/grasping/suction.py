"""Suction grasp quality: seal feasibility and wrench resistance of a suction contact.

The reference uses suction grasps in Ch. 4, 7, 8 and 9 with the Dex-Net 3.0 model (Mahler et
al. 2018, cited as [165]); SPEC.md asks for "seal feasibility (local planarity under the cup)
and wrench resistance". Our version, with the choices recorded:

Seal: the cup lip is a circle of radius r around the contact, perpendicular to the approach.
`perimeter` rays are cast along the approach onto the surface; the seal forms when every ray
hits, the lip heights along the approach lie within `seal_tolerance` of their best-fit plane
(planarity) and within `max_deflection` of the contact (the bellows' travel), and no spring of
Dex-Net 3.0's cup model -- perimeter springs between neighbouring lip points and flexion springs
from the cone apex (a 45-degree cone, apex one radius behind the contact) to the lip -- changes
length by more than `max_stretch`.

Wrench resistance (Dex-Net 3.0's suction contact model, linearized): in the contact frame
(z = approach, into the object) the cup applies w = (f_x, f_y, f_z, tau_x, tau_y, tau_z) with
the lip normal force f_N = V + f_z >= 0 (vacuum V pulls, f_z pushes, f_z <= V), and
  sqrt(3) |f_x|, sqrt(3) |f_y| <= mu f_N       (friction)
  sqrt(3) |tau_z| <= r mu f_N                  (torsional friction)
  sqrt(2) |tau_x|, sqrt(2) |tau_y| <= pi r kappa   (elastic restoring moment of the cup)
The gravity wrench is resisted when eq. 3.3.3's residual is ~0 (same QP as the jaw models,
on Drake's MathematicalProgram). Quality = seal AND resisted; robust = mean over trials that
perturb the contact point (sigma_t), approach (sigma_r), friction and mass.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
from scipy.spatial.transform import Rotation

from ms_drake.grasping import wrench_qp
from ms_drake.grasping.evaluator import GRAVITY, GraspQuality, prepare_trials
from ms_drake.grasping.geometry import MeshData
from ms_drake.grasping.grasp import GraspError, SuctionGrasp
from ms_drake.grasping.wrench_qp import WrenchProblem
from ms_drake.grasping.wrench_sets import normalizer, tangent_basis
from ms_drake.types import Grasp


class SuctionEvaluator:
    """Suction grasp quality (see module docstring).

    vacuum_force V (N); cup_radius r (m); friction mu; stiffness kappa (N: elastic moment
    limit pi r kappa); seal_tolerance, max_deflection (m); max_stretch (fraction)."""

    def __init__(self, vacuum_force: float = 30.0, cup_radius: float = 0.015, friction: float = 0.5,
                 stiffness: float = 5.0, seal_tolerance: float = 0.002, max_deflection: float = 0.008,
                 max_stretch: float = 0.1, perimeter: int = 16, sigma_t: float = 0.003, sigma_r: float = 0.05,
                 sigma_friction: float = 0.1, sigma_mass: float = 0.1, solver: str = "clarabel"):
        for name, v in (("vacuum_force", vacuum_force), ("cup_radius", cup_radius), ("friction", friction),
                        ("stiffness", stiffness), ("seal_tolerance", seal_tolerance),
                        ("max_deflection", max_deflection), ("max_stretch", max_stretch)):
            if not (np.isfinite(v) and v > 0):
                raise GraspError(f"SuctionEvaluator {name} must be a positive number, got {v!r}")
        if perimeter < 6:
            raise GraspError(f"SuctionEvaluator perimeter must be >= 6 lip points, got {perimeter}")
        self.vacuum_force, self.cup_radius, self.friction = float(vacuum_force), float(cup_radius), float(friction)
        self.stiffness, self.seal_tolerance, self.max_deflection = float(stiffness), seal_tolerance, max_deflection
        self.max_stretch, self.perimeter = max_stretch, perimeter
        self.sigma_t, self.sigma_r, self.sigma_friction, self.sigma_mass = sigma_t, sigma_r, sigma_friction, sigma_mass
        self.solver = solver
        self.model = "suction"

    def quality(self, mesh, X_WO, grasp: SuctionGrasp, mass: float, robust_samples: int = 0, seed: int = 0,
                com=None) -> float:
        return self.evaluate(mesh, X_WO, grasp, mass, robust_samples, seed, com).quality

    def evaluate(self, mesh, X_WO, grasp: SuctionGrasp, mass: float, robust_samples: int = 0, seed: int = 0,
                 com=None) -> GraspQuality:
        """Quality with its reason (miss | no_seal | resisted | slips | solver_failed |
        non_watertight_mesh). X_WO: object pose (RigidTransform or 4x4 array); grasp: SuctionGrasp or
        a types.Grasp of kind "suction" (world frame). Programming errors raise TypeError /
        ValueError naming the argument, as GraspEvaluator.evaluate."""
        if isinstance(grasp, Grasp) and grasp.kind == "suction":
            grasp = SuctionGrasp(grasp.center, grasp.approach)
        if not isinstance(grasp, SuctionGrasp):
            raise TypeError(f"grasp must be a SuctionGrasp or a suction types.Grasp, got {grasp!r}")
        setup = prepare_trials(mesh, X_WO, mass, robust_samples, com)
        if setup is None:
            return GraspQuality(0.0, "non_watertight_mesh")
        X, mass, n, data, com_O, R_OW = (setup.X, setup.mass, setup.n, setup.data, setup.com_O, setup.R_OW)
        p_O = R_OW @ (grasp.point - X[:3, 3])
        a_O = R_OW @ grasp.approach
        g_O = R_OW @ np.array([0.0, 0.0, -1.0])
        if n == 0:
            ok, reason, res = self._trial(data, p_O, a_O, com_O, g_O, self.friction, mass)
            return GraspQuality(float(ok), reason, res, 1, {reason: 1})
        outs = []
        for i in range(n):
            rng = np.random.default_rng([int(seed), i])
            p = p_O + rng.normal(scale=self.sigma_t, size=3)
            a = Rotation.from_rotvec(rng.normal(scale=self.sigma_r, size=3)).as_matrix() @ a_O
            mu = max(0.05, self.friction + rng.normal(scale=self.sigma_friction))
            m = mass * max(0.1, 1 + rng.normal(scale=self.sigma_mass))
            outs.append(self._trial(data, p, a, com_O, g_O, mu, m))
        counts = Counter(o[1] for o in outs)
        return GraspQuality(float(np.mean([o[0] for o in outs])), counts.most_common(1)[0][0],
                            float(np.median([o[2] for o in outs])), len(outs), dict(counts))

    # ----------------------------------------------------------------------------------
    def seal(self, data: MeshData, point, approach):
        """(contact point, lip points) when the cup seals, else (None, reason)."""
        back = 0.05
        t, _ = data.raycast((point - back * approach)[None], approach[None], np.inf)
        if not np.isfinite(t[0]) or abs(t[0] - back) > 0.01:
            return None, "miss"
        contact = point - back * approach + t[0] * approach
        t1, t2 = tangent_basis(approach)
        th = 2 * np.pi * np.arange(self.perimeter) / self.perimeter
        ring = contact + self.cup_radius * (np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2)
        tl, _ = data.raycast(ring - back * approach, np.broadcast_to(approach, ring.shape),
                             back + 2 * self.max_deflection)
        if not np.all(np.isfinite(tl)):
            return None, "no_seal"
        heights = tl - back  # along the approach, relative to the contact
        if np.max(np.abs(heights)) > self.max_deflection:
            return None, "no_seal"
        lip = ring + heights[:, None] * approach
        # planarity: heights vs their best-fit plane over the ring
        M = np.column_stack([np.cos(th), np.sin(th), np.ones_like(th)])
        coef, *_ = np.linalg.lstsq(M, heights, rcond=None)
        if np.max(np.abs(M @ coef - heights)) > self.seal_tolerance:
            return None, "no_seal"
        chord = 2 * self.cup_radius * np.sin(np.pi / self.perimeter)
        stretch = np.linalg.norm(np.roll(lip, -1, axis=0) - lip, axis=1) / chord - 1
        # flexion springs from the cone apex (one radius behind the contact, a 45-degree cup)
        apex = contact - self.cup_radius * approach
        flex = np.linalg.norm(lip - apex, axis=1) / (np.sqrt(2.0) * self.cup_radius) - 1
        if max(np.max(np.abs(stretch)), np.max(np.abs(flex))) > self.max_stretch:
            return None, "no_seal"
        return (contact, lip), ""

    def contact_problem(self, contact, approach, com, g_dir, mu, mass, length) -> WrenchProblem:
        """Halfspace wrench set of the cup, normalized like the jaw models."""
        W = normalizer(mass, GRAVITY, length)
        V, r = self.vacuum_force, self.cup_radius
        s3, s2 = np.sqrt(3.0), np.sqrt(2.0)
        # variables x: contact-frame wrench (fx, fy, fz, tx, ty, tz) in physical units, scaled
        rows, hi = [], []
        for sgn in (1.0, -1.0):
            rows += [[s3 * sgn, 0, -mu, 0, 0, 0],  # sqrt3 |fx| <= mu (V + fz)
                     [0, s3 * sgn, -mu, 0, 0, 0],  # sqrt3 |fy| <= mu (V + fz)
                     [0, 0, -r * mu, 0, 0, s3 * sgn],  # sqrt3 |tz| <= r mu (V + fz)
                     [0, 0, 0, s2 * sgn, 0, 0],  # sqrt2 |tx| <= pi r kappa
                     [0, 0, 0, 0, s2 * sgn, 0]]  # sqrt2 |ty| <= pi r kappa
            hi += [mu * V, mu * V, r * mu * V, np.pi * r * self.stiffness, np.pi * r * self.stiffness]
        A = np.asarray(rows, float)
        hi = np.asarray(hi, float)
        t1, t2 = tangent_basis(approach)
        R = np.column_stack([t1, t2, approach])
        Ad = np.zeros((6, 6))
        Ad[:3, :3] = R
        Ad[3:, 3:] = R
        rr = contact - com
        Ad[3:, :3] = np.array([[0, -rr[2], rr[1]], [rr[2], 0, -rr[0]], [-rr[1], rr[0], 0]]) @ R
        D = 1.0 / W  # x = D x' keeps the variables O(1)
        G = (W[:, None] * Ad) * D[None, :]
        A = A * D[None, :]
        scale = np.linalg.norm(A, axis=1)
        lb = np.array([-np.inf, -np.inf, -V, -np.inf, -np.inf, -np.inf]) / D
        ub = np.array([np.inf, np.inf, V, np.inf, np.inf, np.inf]) / D
        t = np.concatenate([g_dir, np.zeros(3)])
        return WrenchProblem(G=G, t=t, A=A / scale[:, None], lo=np.full(len(hi), -np.inf), hi=hi / scale,
                             lb=lb, ub=ub)

    def _trial(self, data, point, approach, com, g_dir, mu, mass):
        approach = approach / np.linalg.norm(approach)
        sealed, reason = self.seal(data, point, approach)
        if sealed is None:
            return False, reason, float("inf")
        contact, _ = sealed
        p = self.contact_problem(contact, approach, com, g_dir, mu, mass, data.length_scale)
        r = wrench_qp.solve(p, self.solver)
        if not r.success:
            return False, "solver_failed", float("inf")
        return r.resisted, ("resisted" if r.resisted else "slips"), r.residual
