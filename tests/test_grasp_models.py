"""Contact models: analytic cases, App. A integrals, bad input."""

import numpy as np
import pytest
import trimesh

from ms_drake.grasping import MODELS, GraspEvaluator, GraspError, ParallelJawGrasp, PadGeometry
from ms_drake.grasping.evaluator import GRAVITY
from ms_drake.grasping.friction_cone import DegenerateFit, fit_ellipsoid
from ms_drake.grasping.geometry import MeshData, jaw_patches
from ms_drake.grasping.point_models import elliptical_torsion
from ms_drake.grasping.reach import (fz_max, pressure_plane, reach_contact, tau_x_max, tau_y_max,
                                     tau_z_lower_bound, triangle_frames)

BOX = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
I4 = np.eye(4)
CENTER = ParallelJawGrasp([0, 0, 0], [1, 0, 0], [0, 0, -1], 0.08)


def pose(rpy=(0, 0, 0), xyz=(0, 0, 0)):
    from scipy.spatial.transform import Rotation

    X = np.eye(4)
    X[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    X[:3, 3] = xyz
    return X


@pytest.mark.parametrize("model", MODELS)
def test_centre_grasp_resists_and_bad_grasps_fail(model):
    ev = GraspEvaluator(model, friction=0.5, closing_force=10.0)
    r = ev.evaluate(BOX, I4, CENTER, 0.3)
    assert (r.quality, r.reason) == (1.0, "resisted")
    miss = ParallelJawGrasp([0, 0, 0.2], [1, 0, 0], [0, 0, -1], 0.08)
    assert ev.evaluate(BOX, I4, miss, 0.3).reason == "miss"
    narrow = ParallelJawGrasp([0, 0, 0], [1, 0, 0], [0, 0, -1], 0.03)  # jaws start inside the box
    assert ev.evaluate(BOX, I4, narrow, 0.3).reason == "jaw_collision"
    # too heavy for 2 * mu * f_C = 10 N of friction
    assert ev.evaluate(BOX, I4, CENTER, 3.0).reason == "slips"


@pytest.mark.parametrize("model", MODELS)
def test_world_pose_is_applied(model):
    """The same grasp expressed in the world of a moved object gives the same answer; a grasp
    left behind at the old place misses."""
    ev = GraspEvaluator(model)
    X = pose((0, 0, 0.7), (0.3, -0.2, 0.1))
    g_world = CENTER.transformed(X)
    assert ev.quality(BOX, X, g_world, 0.3) == 1.0
    assert ev.evaluate(BOX, X, CENTER, 0.3).reason == "miss"


def test_point_contact_friction_limit():
    """Horizontal axis through the COM: resisted iff the weight is below 2 mu f_C (the 8-edge
    inscribed cone loses at most 1 - cos(pi/8) = 8 % of that)."""
    ev = GraspEvaluator("point", friction=0.5, closing_force=10.0)
    limit = 2 * 0.5 * 10.0 / GRAVITY
    assert ev.quality(BOX, I4, CENTER, 0.9 * limit) == 1.0
    assert ev.quality(BOX, I4, CENTER, 1.05 * limit) == 0.0


def test_soft_point_torsion_against_point():
    """Axis offset from the COM by d along y: gravity twists the object about the axis. Point
    contacts have no torsion and fail; soft contacts hold while the limit surface allows it:
    (m g / (2 mu f_C))^2 + (m g d / (2 gamma f_C))^2 <= 1."""
    d = 0.01
    g = ParallelJawGrasp([0, d, 0], [1, 0, 0], [0, 0, -1], 0.08)
    m = 0.2
    mg = m * GRAVITY
    assert GraspEvaluator("point", 0.5, 10.0).quality(BOX, I4, g, m) == 0.0
    gamma_needed = mg * d / (2 * 10.0 * np.sqrt(1 - (mg / (2 * 0.5 * 10.0)) ** 2))
    ok = GraspEvaluator("soft_point", 0.5, 10.0, torsional_friction=1.3 * gamma_needed)
    bad = GraspEvaluator("soft_point", 0.5, 10.0, torsional_friction=0.8 * gamma_needed)
    assert ok.quality(BOX, I4, g, m) == 1.0
    assert bad.quality(BOX, I4, g, m) == 0.0


@pytest.mark.parametrize("model", ["elliptical", "reach", "mfe", "6dfc"])
def test_area_models_resist_torsion_that_point_contacts_cannot(model):
    """A face-centred but COM-offset grasp: area contacts produce torsion, point contacts none."""
    g = ParallelJawGrasp([0, 0.01, 0], [1, 0, 0], [0, 0, -1], 0.08)
    assert GraspEvaluator("point").quality(BOX, I4, g, 0.1) == 0.0
    assert GraspEvaluator(model, material_constant=5e-4).quality(BOX, I4, g, 0.1) == 1.0


def test_6dfc_varies_closing_force_but_mfe_does_not():
    """Jaws on the top and bottom faces: only unequal normal forces can hold the weight. 6DFC
    lets each contact's f_C vary in [0, f_C,max]; MFE fixes both at the maximum (eq. 3.3.2 vs
    line 426), so the two normal forces cancel and the object slips."""
    g = ParallelJawGrasp([0, 0.0, 0], [0, 0, 1], [1, 0, 0], 0.08)
    assert GraspEvaluator("6dfc").quality(BOX, I4, g, 0.3) == 1.0
    assert GraspEvaluator("mfe").evaluate(BOX, I4, g, 0.3).reason == "slips"


def test_robust_quality_is_seeded_mean():
    ev = GraspEvaluator("soft_point", sigma_t=0.004)
    g = ParallelJawGrasp([0, 0, 0.021], [1, 0, 0], [0, 0, -1], 0.08)  # near the top edge
    q1 = ev.evaluate(BOX, I4, g, 0.3, robust_samples=10, seed=4)
    q2 = ev.evaluate(BOX, I4, g, 0.3, robust_samples=10, seed=4)
    assert q1 == q2 and q1.trials == 10 and sum(q1.reasons.values()) == 10
    assert 0.0 < q1.quality < 1.0  # some perturbed grasps leave the box's top edge
    assert q1.quality == pytest.approx(q1.reasons.get("resisted", 0) / 10)
    qs = {ev.quality(BOX, I4, g, 0.3, robust_samples=10, seed=s) for s in range(6)}
    assert len(qs) > 1


# ----------------------------------------------------------------------------- bad input
def test_an_open_or_empty_mesh_gives_zero_and_bad_arguments_raise():
    ev = GraspEvaluator("reach")
    open_box = BOX.copy()
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    assert not open_box.is_watertight
    for mesh in (open_box, trimesh.Trimesh()):
        r = ev.evaluate(mesh, I4, CENTER, 0.3)
        assert (r.quality, r.reason) == (0.0, "non_watertight_mesh")
    with pytest.raises(ValueError, match="X_WO has non-finite entries"):
        ev.evaluate(BOX, np.full((4, 4), np.nan), CENTER, 0.3)
    for mass in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="mass must be a positive number"):
            ev.evaluate(BOX, I4, CENTER, mass)


@pytest.mark.parametrize("model", MODELS)
def test_every_model_bad_input_is_zero_with_a_reason(model):
    """Every model, nominal and robust: a physical failure (open or flat mesh, jaws that miss)
    gives quality 0.0 (never NaN) and a reason the caller can read; a programming error (NaN
    grasp or pose, mass 0, robust_samples < 0) raises a ValueError naming the argument."""
    from ms_drake.types import Grasp

    ev = GraspEvaluator(model)
    open_box = BOX.copy()
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    flat = trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], [[0, 1, 2]], process=False)
    far = ParallelJawGrasp([0, 0, 0.3], [1, 0, 0], [0, 0, -1], 0.08)
    nan_grasp = Grasp("parallel_jaw", (np.nan, 0.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.08)
    cases = [
        ((open_box, I4, CENTER, 0.3), "non_watertight_mesh"),
        ((flat, I4, CENTER, 0.3), "non_watertight_mesh"),
        ((BOX, I4, far, 0.3), "miss"),
    ]
    for args, reason in cases:
        for n in (0, 3):
            r = ev.evaluate(*args, robust_samples=n, seed=1)
            assert (r.quality, r.reason) == (0.0, reason), (model, reason, n, r)
            assert ev.quality(*args, robust_samples=n) == 0.0
    errors = [
        ((BOX, I4, nan_grasp, 0.3), "ParallelJawGrasp.center must be a finite 3-vector"),
        ((BOX, np.full((4, 4), np.nan), CENTER, 0.3), "X_WO has non-finite entries"),
        ((BOX, I4, CENTER, 0.0), "mass must be a positive number"),
    ]
    for args, message in errors:
        for n in (0, 3):
            with pytest.raises(ValueError, match=message):
                ev.evaluate(*args, robust_samples=n, seed=1)
    with pytest.raises(ValueError, match="robust_samples must be >= 0"):
        ev.evaluate(BOX, I4, CENTER, 0.3, robust_samples=-1)


def test_zero_area_patch():
    """A jaw meeting a box edge with (almost) no deformation touches a line: zero area."""
    ev = GraspEvaluator("6dfc", material_constant=1e-13)
    X = pose((0, 0, np.pi / 4))
    r = ev.evaluate(BOX, X, CENTER, 0.3)
    assert (r.quality, r.reason) == (0.0, "zero_area_patch")


def test_degenerate_fit():
    with pytest.raises(DegenerateFit):
        fit_ellipsoid(np.zeros((20, 6)))
    # 6DFC with a single rotation sample and no translations: 2 wrenches cannot define a 6D fit
    r = GraspEvaluator("6dfc", k1=1, k2=0).evaluate(BOX, I4, CENTER, 0.3)
    assert (r.quality, r.reason) == (0.0, "degenerate_fit")


def test_user_errors_raise_clear_errors():
    with pytest.raises(GraspError, match="unknown grasp model"):
        GraspEvaluator("hertz")
    with pytest.raises(GraspError, match="friction"):
        GraspEvaluator("point", friction=-1)
    with pytest.raises(GraspError, match="parallel"):
        ParallelJawGrasp([0, 0, 0], [1, 0, 0], [2, 0, 0], 0.05)
    with pytest.raises(GraspError, match="counter-clockwise"):
        PadGeometry(polygon=((0, 0), (0, 0.01), (0.01, 0.01), (0.01, 0)))


# ----------------------------------------------------------------------------- App. A
def _quadrature(tri_xy, fn, n=300):
    """Integral of fn(x, y) over a 2D triangle: n^2 congruent sub-triangles, centroid rule."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = i + j <= n - 1
    down = i + j <= n - 2
    lam = np.concatenate([np.column_stack([i[up] + 1 / 3, j[up] + 1 / 3]),
                          np.column_stack([i[down] + 2 / 3, j[down] + 2 / 3])]) / n
    pts = tri_xy[0] * lam[:, :1] + tri_xy[1] * lam[:, 1:] + tri_xy[2] * (1 - lam.sum(1, keepdims=True))
    (ax, ay), (bx, by) = tri_xy[1] - tri_xy[0], tri_xy[2] - tri_xy[0]
    area = 0.5 * abs(ax * by - ay * bx)
    return fn(pts[:, 0], pts[:, 1]).sum() * area / n ** 2


def test_appendix_a_closed_forms_match_quadrature():
    rng = np.random.default_rng(0)
    for _ in range(5):
        tri = rng.normal(scale=0.01, size=(1, 3, 3))
        n = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
        n /= np.linalg.norm(n)
        _, _, _, xy = triangle_frames(tri, n[None])
        p_vert = rng.uniform(0.5, 2.0, size=(1, 3))
        abd = pressure_plane(xy, p_vert)
        area = np.array([0.5 * np.linalg.norm(np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0]))])
        a, b, d = abd[0]
        press = lambda x, y: a * x + b * y + d  # noqa: E731
        k = 3.7
        assert fz_max(area, abd, xy, k)[0] == pytest.approx(k * _quadrature(xy[0], press), rel=1e-3)
        assert tau_x_max(area, abd, xy, k)[0] == pytest.approx(
            k * _quadrature(xy[0], lambda x, y: y * press(x, y)), rel=1e-3, abs=1e-12)
        assert tau_y_max(area, abd, xy, k)[0] == pytest.approx(
            k * _quadrature(xy[0], lambda x, y: x * press(x, y)), rel=1e-3, abs=1e-12)
        mu = 0.6
        exact = mu * k * _quadrature(xy[0], lambda x, y: press(x, y) * np.hypot(x, y))
        lower = tau_z_lower_bound(area, abd, xy, mu, k)[0]
        assert 0 <= lower <= exact  # App. A proposition (lines 1847-1865)
        # pressure plane reproduces the vertex values
        assert np.allclose(xy[0] @ abd[0, :2] + abd[0, 2], p_vert[0])


def test_reach_structure_23_constraints_per_triangle():
    """18 ellipsoid weights >= 0, their sum = 1, 0 <= f_z <= f_z,max (and tau_x = tau_y = 0 by
    construction of the generators): 21 explicit + 2 implicit = 23 per triangle (line 185)."""
    ev = GraspEvaluator("reach", material_constant=5e-4)
    data = MeshData.of(BOX)
    patches, reason = jaw_patches(data, CENTER.center, CENTER.axis, CENTER.approach, CENTER.width,
                                  ev.pad.polygon, ev.deformation)
    assert reason == "" and len(patches) == 2
    (p,) = reach_contact(patches[0], data.centroid, 0.5, 10.0)
    n_tri = min(10, len(patches[0].areas))
    assert len(p.blocks) == 2 * n_tri and p.G.shape[1] == 19 * n_tri
    explicit = p.A.shape[0] + np.isfinite(p.lb).sum() + np.isfinite(p.ub).sum()
    assert explicit == 21 * n_tri
    # the normal generators carry f_z,max along each triangle's inward normal and sum to f_C
    order = np.argsort(-patches[0].areas)[:n_tri]
    fz = [p.G[:3, 19 * i] @ -patches[0].normals[order[i]] for i in range(n_tri)]
    assert sum(fz) == pytest.approx(10.0)  # k normalizes the kept triangles to f_C (line 183)
    # tau_x = tau_y = 0 in each triangle frame: ellipsoid torques about the barycentre lie along n
    bary = patches[0].triangles[order].mean(axis=1)
    for i in range(n_tri):
        cols = p.G[:, 19 * i + 1: 19 * i + 19]
        tau_b = cols[3:] - np.cross(bary[i] - data.centroid, cols[:3].T).T
        assert np.allclose(np.cross(tau_b.T, patches[0].normals[order[i]]), 0, atol=1e-12)


def test_patch_is_pad_square_and_pressure_peaks_at_first_contact():
    """Box face and a 20 x 20 mm pad: each patch is 4 cm^2 with d_def slab clipping nothing
    (a flat face is all at d_con); on a 45-degree-tilted box the pressure decreases away from
    the first-contact edge."""
    data = MeshData.of(BOX)
    pad = PadGeometry()
    patches, _ = jaw_patches(data, CENTER.center, CENTER.axis, CENTER.approach, CENTER.width, pad.polygon, 0.002)
    for p in patches:
        assert p.area == pytest.approx(4e-4, rel=1e-6)
        assert p.d_con == pytest.approx(0.015)
        assert np.allclose(p.penetration, 0.002)
    X = pose((0, 0, np.pi / 4))
    data_rot = MeshData.of(BOX.copy().apply_transform(X))
    patches, _ = jaw_patches(data_rot, CENTER.center, CENTER.axis, CENTER.approach, CENTER.width, pad.polygon, 0.002)
    p = patches[0]
    # the slab is 2 mm deep over a 45-degree wedge: each face strip is 2 mm * sqrt(2) wide
    assert p.area == pytest.approx(2 * 0.02 * 0.002 * np.sqrt(2), rel=1e-6)
    assert p.penetration.max() == pytest.approx(0.002) and p.penetration.min() == pytest.approx(0.0, abs=1e-12)


def test_elliptical_torsion_closed_form():
    """tau_max of a Hertzian ellipse against numerical integration."""
    a, b = 0.01, 0.004
    n = 801
    x, y = np.meshgrid(np.linspace(-a, a, n), np.linspace(-b, b, n))
    inside = (x / a) ** 2 + (y / b) ** 2 < 1
    p = np.where(inside, np.sqrt(np.clip(1 - (x / a) ** 2 - (y / b) ** 2, 0, None)), 0.0)
    N = p.sum()
    tau = (p * np.hypot(x, y)).sum()
    assert elliptical_torsion(1.0, 1.0, a, b) == pytest.approx(tau / N, rel=5e-3)
    assert elliptical_torsion(1.0, 1.0, a, a) == pytest.approx(3 * np.pi * a / 16)


def test_6dfc_planar_patch_fit_matches_limit_surface():
    """A flat square patch with uniform pressure: the fitted limit surface is 3D (f_x, f_y,
    tau_z) with force semi-axes mu (per unit closing force) and torsion ~ mu * mean radius."""
    from ms_drake.grasping.friction_cone import sample_friction_wrenches

    s = 0.02
    nx = 20
    g = np.linspace(-s / 2, s / 2, nx + 1)
    tris = []
    for i in range(nx):
        for j in range(nx):
            a, b, c, d = [g[i], g[j]], [g[i + 1], g[j]], [g[i + 1], g[j + 1]], [g[i], g[j + 1]]
            tris += [[a + [0], b + [0], c + [0]], [a + [0], c + [0], d + [0]]]
    tris = np.array(tris)
    bary = tris.mean(1)
    normals = np.tile([0, 0, 1.0], (len(tris), 1))
    fN = np.full(len(tris), 1.0 / len(tris))
    mu = 0.5
    w = sample_friction_wrenches(bary, normals, fN, np.zeros(3), mu, 400, 200, s / np.sqrt(2),
                                 np.random.default_rng(0))
    S = np.array([1, 1, 1, 1 / s, 1 / s, 1 / s])
    V_d, A_d, V_rest, eps = fit_ellipsoid(w * S)
    assert V_d.shape[1] == 3
    A = V_d @ A_d @ V_d.T
    fx_axis = 1 / np.sqrt(A[0, 0])
    tz_axis = 1 / np.sqrt(A[5, 5]) * s
    mean_r = 0.3826 * s  # mean distance from the centre of a square of side s
    assert fx_axis == pytest.approx(mu, rel=0.1)
    assert tz_axis == pytest.approx(mu * mean_r, rel=0.15)


def test_clipped_patches_equal_the_csg_boolean():
    """The fast triangle clipper and the manifold3d boolean give the same patches."""
    from ms_drake.grasping.geometry import jaw_patches_clip, jaw_patches_csg
    from ms_drake.grasping.samplers import sample_antipodal_grasps
    from ms_drake.objects import get_object

    meshes = [trimesh.creation.icosphere(subdivisions=2, radius=0.03),
              trimesh.creation.cylinder(radius=0.025, height=0.08, sections=20),
              get_object("procedural/packaged_002").trimesh()]
    pad = PadGeometry().polygon
    seen = set()
    for k, mesh in enumerate(meshes):
        data = MeshData.of(mesh)
        grasps = sample_antipodal_grasps(mesh, np.eye(4), 12, friction=0.8, max_width=0.12, seed=k,
                                         center_noise=0.012, approach=None)
        grasps.append(ParallelJawGrasp(data.centroid + [0, 0, 0.3], [1, 0, 0], [0, 0, -1], 0.1))  # miss
        grasps.append(ParallelJawGrasp(data.centroid, [1, 0, 0], [0, 0, -1], 0.01))  # collision
        for g in grasps:
            a, ra = jaw_patches_clip(data, g.center, g.axis, g.approach, g.width, pad, 0.003)
            b, rb = jaw_patches_csg(data, g.center, g.axis, g.approach, g.width, pad, 0.003)
            assert ra == rb, (k, g)
            seen.add(ra)
            if a is None:
                continue
            for pa, pb in zip(a, b):
                assert pa.area == pytest.approx(pb.area, rel=1e-5, abs=1e-11)
                assert pa.d_con == pytest.approx(pb.d_con, abs=1e-7)  # manifold3d snaps to ~1e-9
                fa = (pa.areas[:, None] * pa.pressure_at_vertices()).sum()
                fb = (pb.areas[:, None] * pb.pressure_at_vertices()).sum()
                assert fa == pytest.approx(fb, rel=1e-4, abs=1e-14)
    assert {"", "miss", "jaw_collision"} <= seen
