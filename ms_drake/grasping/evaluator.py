"""GraspEvaluator: grasp quality under six contact models, deterministic or robust.

    ev = GraspEvaluator("6dfc", friction=0.5, closing_force=10.0)
    q = ev.quality(mesh, X_WO, grasp, mass)               # 1.0 / 0.0
    q = ev.quality(mesh, X_WO, grasp, mass, robust_samples=10, seed=3)   # in [0, 1]
    r = ev.evaluate(...)                                  # GraspQuality(quality, reason, ...)

A trial succeeds when the contacts can resist gravity (world -z, centre of mass at the mesh's
volume centroid unless `com` is given): the QP of eq. 3.3.3 (wrench_qp.py) has residual below
RESIST_TOLERANCE of the weight. Robust quality (lines 124 and 464-470 of the reference) is the
mean over N trials, each perturbing the grasp pose (translation ~ N(0, sigma_t^2 I), rotation
vector ~ N(0, sigma_r^2 I) about the grasp centre), the friction coefficient
(mu + N(0, sigma_friction^2), at least 0.05) and the mass (m (1 + N(0, sigma_mass^2)), at least
0.1 m), trial i drawing from numpy.random.default_rng([seed, i]).

The object pose X_WO is a pydrake RigidTransform or a 4x4 array. Programming errors raise a
TypeError / ValueError naming the argument (a pose that is not a rigid transform, a NaN grasp,
mass <= 0, robust_samples < 0); physical outcomes give a quality and the trial's `reason`:
  resisted | slips | miss | jaw_collision | non_watertight_mesh | zero_area_patch |
  degenerate_fit | solver_failed
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ms_drake.geometry import as_matrix4
from ms_drake.grasping import wrench_qp
from ms_drake.grasping.friction_cone import cone_contact
from ms_drake.grasping.geometry import MeshData, jaw_patches
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp
from ms_drake.grasping.point_models import (
    contacts_problem,
    elliptical_contact,
    ray_contacts,
)
from ms_drake.grasping.reach import reach_contact
from ms_drake.grasping.wrench_qp import SOLVERS, WrenchProblem, stack
from ms_drake.grasping.wrench_sets import normalizer
from ms_drake.robots import CLOSING_FORCE

MODELS = ("point", "soft_point", "elliptical", "reach", "mfe", "6dfc")
AREA_MODELS = ("elliptical", "reach", "mfe", "6dfc")
GRAVITY = 9.81


@dataclass(frozen=True)
class PadGeometry:
    """The compliant jaw pad seen by the area models: a planar polygon (metres, in the jaw frame:
    x along the gripper approach, y = axis x approach, origin on the grasp axis) and its
    thickness, which caps the deformation depth d_def. Default: 20 x 20 mm, 6 mm thick (close
    to the YuMi smart gripper's compliant fingertips)."""

    polygon: tuple[tuple[float, float], ...] = ((-0.01, -0.01), (0.01, -0.01), (0.01, 0.01), (-0.01, 0.01))
    depth: float = 0.006

    def __post_init__(self):
        poly = np.asarray(self.polygon, float)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.all(np.isfinite(poly)):
            raise GraspError(f"PadGeometry.polygon must be >= 3 (x, y) points in metres, got {self.polygon!r}")
        x, y = poly[:, 0], poly[:, 1]
        area = 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        if area <= 1e-10:
            raise GraspError("PadGeometry.polygon must be counter-clockwise with non-zero area, got "
                             f"{self.polygon!r} (signed area {area:.3g} m^2); reverse the point order")
        if not (self.depth > 0):
            raise GraspError(f"PadGeometry.depth (pad thickness, m) must be > 0, got {self.depth!r}")


def _check_trial_inputs(mass, robust_samples, com):
    """(mass, robust_samples, com or None) checked: GraspError (a ValueError) naming the argument."""
    if not isinstance(mass, (int, float, np.integer, np.floating)) or not (np.isfinite(mass) and mass > 0):
        raise GraspError(f"mass must be a positive number of kilograms, got {mass!r}")
    if not isinstance(robust_samples, (int, np.integer)):
        raise TypeError(f"robust_samples must be an int, got {type(robust_samples).__name__}")
    m, n = float(mass), int(robust_samples)
    if n < 0:
        raise GraspError(f"robust_samples must be >= 0 (0: the nominal grasp only), got {robust_samples!r}")
    if com is not None:
        com = np.asarray(com, dtype=float).reshape(-1)
        if com.shape != (3,) or not np.all(np.isfinite(com)):
            raise GraspError(f"com must be a finite 3-vector (object frame, m) or None, got {com!r}")
    return m, n, com


@dataclass(frozen=True)
class TrialSetup:
    """What every evaluator starts from: the checked object pose X (4x4), mass, robust trial count
    n, the mesh data, the object-frame centre of mass and the world-to-object rotation R_OW."""

    X: np.ndarray
    mass: float
    n: int
    data: MeshData
    com_O: np.ndarray
    R_OW: np.ndarray


def prepare_trials(mesh, X_WO, mass, robust_samples, com) -> TrialSetup | None:
    """The checks every evaluator starts with: programming errors raise naming the argument
    (as_matrix4, _check_trial_inputs); a mesh that is not watertight is a physical outcome, None."""
    X = as_matrix4(X_WO, "X_WO")
    mass, n, com = _check_trial_inputs(mass, robust_samples, com)
    data = MeshData.of(mesh)
    if not data.watertight:
        return None
    return TrialSetup(X, mass, n, data, data.centroid if com is None else com, X[:3, :3].T)


@dataclass(frozen=True)
class GraspQuality:
    """Result of GraspEvaluator.evaluate. quality in [0, 1]; reason: the nominal trial's outcome
    (or the most common one over robust trials); reasons: outcome counts over the trials."""

    quality: float
    reason: str
    residual: float = float("inf")
    trials: int = 1
    reasons: dict = field(default_factory=dict)

    def __float__(self):
        return float(self.quality)


class GraspEvaluator:
    """Grasp quality under one contact model.

    model: point | soft_point | elliptical | reach | mfe | 6dfc
    friction: Coulomb coefficient mu; closing_force: f_C (N), the jaws' maximal closing force.
    Model parameters (keyword):
      torsional_friction (m, soft point: |tau| <= torsional_friction * f_n), default 0.005
      material_constant kappa (m/N, area models: d_def = kappa f_C, capped at the pad depth),
        default 2e-4
      pad: PadGeometry (or pad_polygon=..., pad_depth=...)
      cone_edges (point: generators of the linearized cone), default 8
      ellipsoid_samples (soft point, elliptical, REACH), default 18
      max_triangles (REACH), default 10
      k1, k2 (MFE/6DFC rotation and translation samples), default 60, 30
      cone_planes (MFE/6DFC extra tangent planes), default 64
      solver: auto | support | nnls | clarabel | osqp | naive (auto: the support-function path for
        point / soft point / elliptical / REACH, Clarabel on the MathematicalProgram for MFE / 6DFC)
      sigma_t (m), sigma_r (rad), sigma_friction, sigma_mass (relative): robust perturbations,
        default 0.003, 0.05, 0.1, 0.1
      pad_span (m, point / soft point): how far the pads reach beyond the grasp centre towards the
        fingertips; when the line through the centre misses the object the contacts are sought
        on lines down to there (point_models.ray_contacts: a thin object under the tool point
        meets the pads' lower part). Default 0: the centre line only. The area models intersect
        the pad polygon itself.
    """

    def __init__(self, model: str = "6dfc", friction: float = 0.5, closing_force: float = CLOSING_FORCE, *,
                 torsional_friction: float = 0.005, material_constant: float = 2e-4,
                 pad: PadGeometry | None = None, pad_polygon=None, pad_depth: float | None = None,
                 cone_edges: int = 8, ellipsoid_samples: int = 18, max_triangles: int = 10,
                 k1: int = 60, k2: int = 30, cone_planes: int = 64, solver: str = "auto",
                 sigma_t: float = 0.003, sigma_r: float = 0.05, sigma_friction: float = 0.1,
                 sigma_mass: float = 0.1, pad_span: float = 0.0):
        if model not in MODELS:
            raise GraspError(f"unknown grasp model {model!r}; choose one of {', '.join(MODELS)}")
        if solver not in SOLVERS and solver != "naive":
            raise GraspError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
        for name, v in (("friction", friction), ("closing_force", closing_force),
                        ("torsional_friction", torsional_friction), ("material_constant", material_constant)):
            if not (np.isfinite(v) and v > 0):
                raise GraspError(f"GraspEvaluator {name} must be a positive number, got {v!r}")
        for name, v in (("sigma_t", sigma_t), ("sigma_r", sigma_r), ("sigma_friction", sigma_friction),
                        ("sigma_mass", sigma_mass), ("pad_span", pad_span)):
            if not (np.isfinite(v) and v >= 0):
                raise GraspError(f"GraspEvaluator {name} must be >= 0, got {v!r}")
        if pad is None:
            base = PadGeometry()
            pad = PadGeometry(tuple(map(tuple, pad_polygon)) if pad_polygon is not None else base.polygon,
                              pad_depth if pad_depth is not None else base.depth)
        if cone_edges < 3 or ellipsoid_samples < 6 or max_triangles < 1 or k1 < 1 or k2 < 0 or cone_planes < 0:
            raise GraspError("cone_edges >= 3, ellipsoid_samples >= 6, max_triangles >= 1, k1 >= 1, k2 >= 0, "
                             "cone_planes >= 0 are required")
        self.model = model
        self.friction = float(friction)
        self.closing_force = float(closing_force)
        self.torsional_friction = float(torsional_friction)
        self.material_constant = float(material_constant)
        self.pad = pad
        self.cone_edges, self.ellipsoid_samples, self.max_triangles = cone_edges, ellipsoid_samples, max_triangles
        self.k1, self.k2, self.cone_planes = k1, k2, cone_planes
        self.solver = solver
        self.sigma_t, self.sigma_r = float(sigma_t), float(sigma_r)
        self.sigma_friction, self.sigma_mass = float(sigma_friction), float(sigma_mass)
        self.pad_span = float(pad_span)

    def __repr__(self):
        return (f"GraspEvaluator({self.model!r}, friction={self.friction}, closing_force={self.closing_force}, "
                f"torsional_friction={self.torsional_friction}, material_constant={self.material_constant})")

    @property
    def deformation(self) -> float:
        """d_def = kappa f_C saturated at the pad thickness (line 143)."""
        return min(self.material_constant * self.closing_force, self.pad.depth)

    # ------------------------------------------------------------------ public API
    def quality(self, mesh, X_WO, grasp: ParallelJawGrasp, mass: float, robust_samples: int = 0,
                seed: int = 0, com=None) -> float:
        """1.0 / 0.0 (robust_samples = 0) or the mean over robust trials, never NaN (see `evaluate`)."""
        return self.evaluate(mesh, X_WO, grasp, mass, robust_samples, seed, com).quality

    def evaluate(self, mesh, X_WO, grasp: ParallelJawGrasp, mass: float, robust_samples: int = 0,
                 seed: int = 0, com=None) -> GraspQuality:
        """Quality with its reason. mesh: trimesh.Trimesh in the object frame; X_WO: object pose
        (RigidTransform or 4x4 array); grasp: world frame (ParallelJawGrasp or types.Grasp); mass
        (kg); com: object-frame centre of mass (default: the mesh's volume centroid). Raises
        TypeError / ValueError on programming errors (see the module docstring)."""
        if not isinstance(grasp, ParallelJawGrasp):
            grasp = ParallelJawGrasp.from_grasp(grasp)
        setup = prepare_trials(mesh, X_WO, mass, robust_samples, com)
        if setup is None:
            return GraspQuality(0.0, "non_watertight_mesh")
        X, mass, n, data, com_O, R_OW = (setup.X, setup.mass, setup.n, setup.data, setup.com_O, setup.R_OW)
        X_OW = np.eye(4)
        X_OW[:3, :3] = R_OW
        X_OW[:3, 3] = -R_OW @ X[:3, 3]
        g_O = R_OW @ np.array([0.0, 0.0, -1.0])
        grasp_O = grasp.transformed(X_OW)
        if n == 0:
            ok, reason, res = self._trial(data, grasp_O, com_O, g_O, self.friction, mass, int(seed))
            return GraspQuality(1.0 if ok else 0.0, reason, res, 1, {reason: 1})
        outcomes = []
        for i in range(n):
            rng = np.random.default_rng([int(seed), i])
            g_i, mu_i, m_i = self._perturb(grasp_O, mass, rng)
            outcomes.append(self._trial(data, g_i, com_O, g_O, mu_i, m_i, rng))
        counts = Counter(o[1] for o in outcomes)
        q = float(np.mean([o[0] for o in outcomes]))
        return GraspQuality(q, counts.most_common(1)[0][0], float(np.median([o[2] for o in outcomes])),
                            n, dict(counts))

    # ------------------------------------------------------------------ internals
    def _perturb(self, g: ParallelJawGrasp, mass: float, rng):
        dt = rng.normal(scale=self.sigma_t, size=3)
        R = Rotation.from_rotvec(rng.normal(scale=self.sigma_r, size=3)).as_matrix()
        mu = max(0.05, self.friction + rng.normal(scale=self.sigma_friction))
        m = mass * max(0.1, 1.0 + rng.normal(scale=self.sigma_mass))
        return ParallelJawGrasp(g.center + dt, R @ g.axis, R @ g.approach, g.width), mu, m

    def contact_problem(self, data: MeshData, g: ParallelJawGrasp, com, g_dir, mu, mass, rng):
        """The normalized WrenchProblem of one trial, or (None, reason). rng: seed or Generator
        (used by MFE / 6DFC wrench sampling)."""
        W = normalizer(mass, GRAVITY, data.length_scale)
        t = np.concatenate([g_dir, np.zeros(3)])  # gravity wrench about the COM / (m g)
        blocks: list[WrenchProblem] = []
        if self.model in ("point", "soft_point"):
            contacts, reason = ray_contacts(data, g.center, g.axis, g.width, g.approach, self.pad_span)
            if contacts is None:
                return None, reason
            torsion = self.torsional_friction if self.model == "soft_point" else 0.0
            p = contacts_problem(contacts[0], contacts[1], com, mu, self.closing_force, W, torsion,
                                 self.cone_edges, self.ellipsoid_samples)
            p.t = t
            return p, ""
        try:
            patches, reason = jaw_patches(data, g.center, g.axis, g.approach, g.width, self.pad.polygon,
                                          self.deformation)
        except ValueError:  # manifold3d refused the mesh as a solid
            return None, "non_watertight_mesh"
        if patches is None:
            return None, reason
        try:
            for patch in patches:
                if self.model == "elliptical":
                    blocks.extend(elliptical_contact(patch, com, mu, self.closing_force, self.ellipsoid_samples))
                elif self.model == "reach":
                    blocks.extend(reach_contact(patch, com, mu, self.closing_force, self.max_triangles,
                                                self.ellipsoid_samples))
                else:
                    rng = np.random.default_rng(rng)  # a seed or a Generator; created only here
                    blocks.append(cone_contact(patch, com, mu, self.closing_force, W, rng, self.k1, self.k2,
                                               self.cone_planes, cone=self.model == "6dfc"))
        except (ValueError, ZeroDivisionError, np.linalg.LinAlgError):
            return None, "degenerate_fit"
        if self.model not in ("mfe", "6dfc"):
            for b in blocks:  # vertex form: generators in physical units -> normalized
                b.G = W[:, None] * b.G
        p = stack(blocks, t)
        if not (np.all(np.isfinite(p.G)) and np.all(np.isfinite(p.A)) and not np.any(np.isnan(p.hi))):
            return None, "degenerate_fit"
        return p, ""

    def _trial(self, data, g, com, g_dir, mu, mass, rng):
        p, reason = self.contact_problem(data, g, com, g_dir, mu, mass, rng)
        if p is None:
            return False, reason, float("inf")
        r = wrench_qp.solve(p, self.solver)
        if not r.success:
            return False, "solver_failed", float("inf")
        return r.resisted, ("resisted" if r.resisted else "slips"), r.residual
