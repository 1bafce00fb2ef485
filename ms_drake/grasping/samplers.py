"""Grasp samplers: antipodal parallel-jaw grasps on meshes, point clouds and depth images
(restricted to an object mask), and suction grasps on meshes and depth images.

Mesh sampler (reference lines 189-190, the Dex-Net recipe): pick a surface point (area
weighted), shoot a ray into the object along a direction inside the friction cone about the
inward normal, take the exit point as the second contact, keep the pair when it is antipodal
(the axis lies inside both friction cones) and narrower than the gripper; add uniform noise to
the centre if asked ("grasps within the gripper pad width ... by adding uniform noise");
discard grasps within a distance threshold of one already kept.

Depth sampler (Dex-Net 2.0 style, top-down): contacts are pairs of mask-boundary pixels whose
2D outward normals are antipodal within the friction cone; the grasp centre is the midpoint
deprojected at the shallowest depth along the segment plus `grasp_depth`; the approach is the
camera's optical axis. Point-cloud sampler: the same antipodal test in 3D on points with
normals (KD-tree neighbours within the maximal width).

Every sampler takes a seed; outputs are world-frame `ParallelJawGrasp` / `SuctionGrasp`.
"""

from __future__ import annotations

import numpy as np

from ms_drake.grasping.geometry import MeshData, cross
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp, SuctionGrasp


def _random_in_cone(axis: np.ndarray, half_angle: float, rng) -> np.ndarray:
    """A direction uniformly distributed (in solid angle) within the cone about unit `axis`."""
    cos_max = np.cos(half_angle)
    z = rng.uniform(cos_max, 1.0)
    phi = rng.uniform(0, 2 * np.pi)
    r = np.sqrt(max(0.0, 1 - z * z))
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = np.cross(axis, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(axis, t1)
    return z * axis + r * (np.cos(phi) * t1 + np.sin(phi) * t2)


def _approach_for(axis: np.ndarray, preferred, rng) -> np.ndarray:
    """The preferred approach made orthogonal to the axis, or a random orthogonal direction."""
    if preferred is not None:
        a = np.asarray(preferred, float)
        a = a - np.dot(a, axis) * axis
        if np.linalg.norm(a) > 0.2:
            return a / np.linalg.norm(a)
    helper = rng.normal(size=3)
    a = helper - np.dot(helper, axis) * axis
    return a / np.linalg.norm(a)


def _is_duplicate(center, axis, kept, dist, angle) -> bool:
    cos_a = np.cos(angle)
    for c, a in kept:
        if np.linalg.norm(center - c) < dist and abs(np.dot(axis, a)) > cos_a:
            return True
    return False


def sample_surface(data: MeshData, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """`count` points (area weighted) and their outward face normals, object frame."""
    p = data.areas / data.areas.sum()
    faces = rng.choice(len(p), size=count, p=p)
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    u, v = 1 - s, s * (1 - r2)
    pts = data.v0[faces] + u[:, None] * data.e1[faces] + v[:, None] * data.e2[faces]
    return pts, data.normals[faces]


def sample_antipodal_grasps(mesh, X_WO, count: int, friction: float = 0.5, max_width: float = 0.1,
                            min_width: float = 0.0, seed: int = 0, approach=(0.0, 0.0, -1.0),
                            center_noise: float = 0.0, jaw_margin: float = 0.01,
                            dedupe_distance: float = 0.004, dedupe_angle: float = 0.2,
                            max_attempts: int | None = None, open_width: float | None = None) -> list[ParallelJawGrasp]:
    """Up to `count` antipodal grasps on a mesh posed at X_WO (world frame).

    approach: preferred world approach direction (made orthogonal to each axis), None = random.
    Width = contact distance + 2 jaw_margin (capped at max_width), or `open_width` when given
    (a gripper that always opens fully); contacts farther apart than max_width - 2 jaw_margin
    are rejected."""
    if count < 0 or not (max_width > 0) or not (friction > 0):
        raise GraspError(f"sample_antipodal_grasps needs count >= 0, max_width > 0, friction > 0 "
                         f"(got {count}, {max_width}, {friction})")
    data = MeshData.of(mesh)
    rng = np.random.default_rng(seed)
    X = np.asarray(X_WO, float)
    R = X[:3, :3]
    pref = None if approach is None else R.T @ np.asarray(approach, float)
    half = np.arctan(friction)
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    out: list[ParallelJawGrasp] = []
    attempts = max_attempts if max_attempts is not None else 40 * max(count, 1)
    batch = 64
    done = 0
    while len(out) < count and done < attempts:
        pts, nrm = sample_surface(data, batch, rng)
        dirs = np.array([_random_in_cone(-n, half, rng) for n in nrm])
        dist, n_hit = data.raycast(pts + 1e-7 * dirs, dirs, np.inf)
        for i in range(batch):
            done += 1
            if len(out) >= count or done > attempts:
                break
            if not np.isfinite(dist[i]):
                continue
            n2 = n_hit[i]
            if np.dot(n2, dirs[i]) <= np.cos(half):  # exit normal must be in the cone about the axis
                continue
            d = dist[i]
            if d < min_width or d > max_width - 2 * jaw_margin:
                continue
            axis = dirs[i]
            center = pts[i] + 0.5 * d * axis
            if center_noise > 0:
                center = center + rng.uniform(-center_noise, center_noise, size=3)
            if _is_duplicate(center, axis, kept, dedupe_distance, dedupe_angle):
                continue
            kept.append((center, axis))
            ap = _approach_for(axis, pref, rng)
            g = ParallelJawGrasp(center, axis, ap, open_width or min(max_width, d + 2 * jaw_margin))
            out.append(g.transformed(X))
    return out


def sample_suction_grasps(mesh, X_WO, count: int, seed: int = 0, max_approach_angle: float = np.pi,
                          dedupe_distance: float = 0.003) -> list[SuctionGrasp]:
    """Suction grasps: surface points (area weighted) approached along minus the normal;
    max_approach_angle limits the angle between the approach and world -z (pi = any)."""
    data = MeshData.of(mesh)
    rng = np.random.default_rng(seed)
    X = np.asarray(X_WO, float)
    out, kept = [], []
    tries = 0
    while len(out) < count and tries < 40 * max(count, 1):
        pts, nrm = sample_surface(data, 64, rng)
        for p, n in zip(pts, nrm):
            tries += 1
            pw, aw = X[:3, :3] @ p + X[:3, 3], -(X[:3, :3] @ n)
            if np.dot(aw, [0, 0, -1.0]) < np.cos(max_approach_angle) - 1e-12:
                continue
            if any(np.linalg.norm(pw - k) < dedupe_distance for k in kept):
                continue
            kept.append(pw)
            out.append(SuctionGrasp(pw, aw))
            if len(out) >= count:
                break
    return out


# --------------------------------------------------------------------------- point clouds
def sample_antipodal_grasps_point_cloud(points: np.ndarray, normals: np.ndarray, count: int,
                                        friction: float = 0.5, max_width: float = 0.1, seed: int = 0,
                                        approach=(0.0, 0.0, -1.0), jaw_margin: float = 0.01,
                                        dedupe_distance: float = 0.004, dedupe_angle: float = 0.2,
                                        min_width: float = 0.002) -> list[ParallelJawGrasp]:
    """Antipodal pairs among world-frame points with outward unit normals (N, 3)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    if len(points) < 2:
        return []
    rng = np.random.default_rng(seed)
    tree = cKDTree(points)
    cos_h = np.cos(np.arctan(friction))
    out, kept = [], []
    order = rng.permutation(len(points))
    for i in order[: 40 * max(count, 1)]:
        if len(out) >= count:
            break
        nb = np.asarray(tree.query_ball_point(points[i], max_width - 2 * jaw_margin), dtype=int)
        if len(nb) == 0:
            continue
        v = points[nb] - points[i]
        d = np.linalg.norm(v, axis=1)
        ok = d > min_width
        v = v[ok] / d[ok, None]
        nb, d = nb[ok], d[ok]
        good = (v @ -normals[i] >= cos_h) & (np.sum(v * normals[nb], axis=1) >= cos_h)
        if not np.any(good):
            continue
        j = rng.choice(np.nonzero(good)[0])
        axis, w = v[j], d[j]
        center = points[i] + 0.5 * w * axis
        if _is_duplicate(center, axis, kept, dedupe_distance, dedupe_angle):
            continue
        kept.append((center, axis))
        out.append(ParallelJawGrasp(center, axis, _approach_for(axis, approach, rng),
                                    min(max_width, w + 2 * jaw_margin)))
    return out


def depth_to_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of a depth image (metres; invalid depth -> nan)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=-1)


def depth_normals(points_C: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame unit normals from image-space gradients, facing the camera."""
    dx = np.gradient(points_C, axis=1)
    dy = np.gradient(points_C, axis=0)
    n = cross(dx, dy)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    flip = np.sum(n * points_C, axis=-1, keepdims=True) > 0  # must point back at the camera
    return np.where(flip, -n, n)


def _mask_boundary_normals(mask: np.ndarray):
    """Boundary pixels (rows, cols) of a mask and their 2D outward normals (d_col, d_row)."""
    import cv2

    m = mask.astype(np.uint8)
    eroded = cv2.erode(m, np.ones((3, 3), np.uint8))
    boundary = (m > 0) & (eroded == 0)
    blur = cv2.GaussianBlur(m.astype(np.float32), (7, 7), 1.5)
    gy, gx = np.gradient(blur)
    rows, cols = np.nonzero(boundary)
    n = -np.stack([gx[rows, cols], gy[rows, cols]], axis=1)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-6
    return rows[ok], cols[ok], n[ok] / norm[ok, None]


def sample_antipodal_grasps_depth(depth: np.ndarray, K: np.ndarray, X_WC: np.ndarray, mask: np.ndarray,
                                  count: int, friction: float = 0.5, max_width: float = 0.1, seed: int = 0,
                                  grasp_depth: float = 0.01, jaw_margin: float = 0.01,
                                  dedupe_distance: float = 0.004, dedupe_angle: float = 0.2) -> list[ParallelJawGrasp]:
    """Top-down antipodal grasps on the object under `mask` (H, W bool) of a depth image.

    K: 3x3 intrinsics; X_WC: 4x4 camera pose (camera z = optical axis). World frame output."""
    if depth.shape != mask.shape:
        raise GraspError(f"depth image {depth.shape} and mask {mask.shape} must have the same shape")
    rng = np.random.default_rng(seed)
    valid = mask & np.isfinite(depth) & (depth > 0)
    if valid.sum() < 4:
        return []
    rows, cols, n2d = _mask_boundary_normals(valid)
    if len(rows) < 2:
        return []
    cos_h = np.cos(np.arctan(friction))
    R, t = X_WC[:3, :3], X_WC[:3, 3]
    out, kept = [], []
    px = np.stack([cols, rows], axis=1).astype(float)
    for i in rng.permutation(len(rows))[: 40 * max(count, 1)]:
        if len(out) >= count:
            break
        v = px - px[i]
        d = np.linalg.norm(v, axis=1)
        ok = d > 1
        vu = np.where(ok[:, None], v / np.maximum(d, 1e-9)[:, None], 0)
        good = ok & (vu @ -n2d[i] >= cos_h) & (np.sum(vu * n2d, axis=1) >= cos_h)
        if not np.any(good):
            continue
        j = rng.choice(np.nonzero(good)[0])
        # sample the segment between the two contacts for the shallowest visible surface
        steps = int(d[j]) + 2
        s = np.linspace(0, 1, steps)
        seg = np.round(px[i] + s[:, None] * (px[j] - px[i])).astype(int)
        zs = depth[seg[:, 1], seg[:, 0]]
        zs = zs[valid[seg[:, 1], seg[:, 0]]]
        if len(zs) == 0:
            continue
        z = float(np.min(zs)) + grasp_depth
        mid = 0.5 * (px[i] + px[j])
        pc = np.array([(mid[0] - K[0, 2]) * z / K[0, 0], (mid[1] - K[1, 2]) * z / K[1, 1], z])
        a_c = np.array([(px[j, 0] - px[i, 0]) * z / K[0, 0], (px[j, 1] - px[i, 1]) * z / K[1, 1], 0.0])
        width = float(np.linalg.norm(a_c))
        if width < 1e-4 or width > max_width - 2 * jaw_margin:
            continue
        center = R @ pc + t
        axis = R @ (a_c / width)
        if _is_duplicate(center, axis, kept, dedupe_distance, dedupe_angle):
            continue
        kept.append((center, axis))
        out.append(ParallelJawGrasp(center, axis, R[:, 2], min(max_width, width + 2 * jaw_margin)))
    return out


def sample_suction_grasps_depth(depth: np.ndarray, K: np.ndarray, X_WC: np.ndarray, mask: np.ndarray,
                                count: int, seed: int = 0, dedupe_distance: float = 0.003):
    """Suction grasps at mask pixels: point = deprojected pixel, approach = minus the depth normal."""
    rng = np.random.default_rng(seed)
    valid = mask & np.isfinite(depth) & (depth > 0)
    P = depth_to_points(depth, K)
    N = depth_normals(P)
    ok = valid & np.all(np.isfinite(N), axis=-1)
    rows, cols = np.nonzero(ok)
    R, t = X_WC[:3, :3], X_WC[:3, 3]
    out, kept = [], []
    for i in rng.permutation(len(rows))[: 40 * max(count, 1)]:
        if len(out) >= count:
            break
        p = R @ P[rows[i], cols[i]] + t
        if any(np.linalg.norm(p - k) < dedupe_distance for k in kept):
            continue
        kept.append(p)
        out.append(SuctionGrasp(p, -(R @ N[rows[i], cols[i]])))
    return out
