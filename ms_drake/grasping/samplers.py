"""Grasp samplers: antipodal parallel-jaw grasps on meshes, point clouds and depth images
(restricted to an object mask), and suction grasps on meshes and depth images.

Mesh sampler (reference lines 189-190, the Dex-Net recipe): pick a surface point (area
weighted), shoot a ray into the object along a direction inside the friction cone about the
inward normal, take the exit point as the second contact, keep the pair when it is antipodal
(the axis lies inside both friction cones) and narrower than the gripper; add uniform noise to
the centre if asked ("grasps within the gripper pad width ... by adding uniform noise");
discard grasps within a distance threshold of one already kept.

Depth sampler (Dex-Net 2.0 style, top-down): the masked points binned into a world height map;
contacts are pairs of footprint-boundary cells whose 2D outward normals are antipodal within the
friction cone; the grasp centre goes half-way down the object's visible side, above whatever the
fingers land on (see `sample_antipodal_grasps_depth`); the approach is world -z. Point-cloud
sampler: the same antipodal test in 3D on points with normals (KD-tree neighbours within the
maximal width).

Every sampler takes a seed; outputs are world-frame `ParallelJawGrasp` / `SuctionGrasp`.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ms_drake.geometry import as_matrix4, transform_points
from ms_drake.grasping.geometry import MeshData, cross
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp, SuctionGrasp
from ms_drake.jit import njit_cached


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
    """Up to `count` antipodal grasps on a mesh posed at X_WO (RigidTransform or 4x4 array), in
    the world frame.

    approach: preferred world approach direction (made orthogonal to each axis), None = random.
    Width = contact distance + 2 jaw_margin (capped at max_width), or `open_width` when given
    (a gripper that always opens fully); contacts farther apart than max_width - 2 jaw_margin
    are rejected."""
    if count < 0 or not (max_width > 0) or not (friction > 0):
        raise GraspError(f"sample_antipodal_grasps needs count >= 0, max_width > 0, friction > 0 "
                         f"(got {count}, {max_width}, {friction})")
    data = MeshData.of(mesh)
    rng = np.random.default_rng(seed)
    X = as_matrix4(X_WO, "X_WO")
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
    max_approach_angle limits the angle between the approach and world -z (pi = any). X_WO:
    the mesh's pose (RigidTransform or 4x4 array)."""
    data = MeshData.of(mesh)
    rng = np.random.default_rng(seed)
    X = as_matrix4(X_WO, "X_WO")
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


def height_map(points_W: np.ndarray, lo: np.ndarray, shape: tuple[int, int], cell: float) -> np.ndarray:
    """(rows, cols) grid of the highest world z of `points_W` (N, 3) per cell; row = y, col = x,
    cell (r, c) covers x in lo[0] + [c, c + 1) cell, y in lo[1] + [r, r + 1) cell; -inf = empty."""
    H = np.full(shape, -np.inf)
    c = np.floor((points_W[:, 0] - lo[0]) / cell).astype(int)
    r = np.floor((points_W[:, 1] - lo[1]) / cell).astype(int)
    ok = (r >= 0) & (r < shape[0]) & (c >= 0) & (c < shape[1])
    np.maximum.at(H, (r[ok], c[ok]), points_W[ok, 2])
    return H


def _rect_top(H: np.ndarray, rc: np.ndarray, u: np.ndarray, along: tuple[float, float], half_across: float) -> float:
    """The highest surface (world z) of height map H in the rectangle from `along[0]` to
    `along[1]` cells along unit grid direction `u` from cell `rc` (col, row), +-half_across cells
    across; -inf when it holds no measured surface."""
    return _rect_top_kernel(H, float(rc[0]), float(rc[1]), float(u[0]), float(u[1]), float(along[0]),
                            float(along[1]), float(half_across))


@njit_cached
def _rect_top_kernel(H, r0, r1, u0, u1, a_lo, a_hi, half_across):
    # the cells of rc + a u + b perp for a in arange(a_lo, a_hi + 0.5), b in -floor(h)..floor(h),
    # rounded half to even (np.round): the same cells, in the same float arithmetic, as numpy would
    na = max(0, int(np.ceil(a_hi + 0.5 - a_lo)))
    hb = np.floor(half_across)
    nb = max(0, int(np.ceil(hb + 0.5 + hb)))
    best, hit = -np.inf, False
    for i in range(na):
        a = a_lo + i * 1.0
        x0, y0 = r0 + a * u0, r1 + a * u1
        for j in range(nb):
            b = -hb + j * 1.0
            c, r = int(np.rint(x0 + b * -u1)), int(np.rint(y0 + b * u0))
            if 0 <= c < H.shape[1] and 0 <= r < H.shape[0]:
                if not hit or H[r, c] > best:
                    best = H[r, c]
                hit = True
    return best


def _edge_under_pad(foot: np.ndarray, rc: np.ndarray, inward: np.ndarray, half: float, depth: float) -> bool:
    """True when the footprint holds the segment `half` cells to either side of contact `rc`
    (perpendicular to the unit direction `inward`) pushed `depth` cells inwards: the contact is
    on an edge the pad can press on, not a corner (whose smoothed normal points diagonally)."""
    return _edge_under_pad_kernel(foot, float(rc[0]), float(rc[1]), float(inward[0]), float(inward[1]),
                                  float(half), float(depth))


@njit_cached
def _edge_under_pad_kernel(foot, r0, r1, in0, in1, half, depth):
    # five points t in np.linspace(-half, half, 5) along perp = (-in1, in0)
    step = (half - -half) / 4
    x0, y0 = r0 + depth * in0, r1 + depth * in1
    for k in range(5):
        t = half if k == 4 else k * step + -half
        c, r = int(np.rint(x0 + t * -in1)), int(np.rint(y0 + t * in0))
        if not (0 <= c < foot.shape[1] and 0 <= r < foot.shape[0]) or not foot[r, c]:
            return False
    return True


def sample_antipodal_grasps_depth(depth: np.ndarray, K: np.ndarray, X_WC: np.ndarray, mask: np.ndarray,
                                  count: int, friction: float = 0.5, max_width: float = 0.1, seed: int = 0,
                                  grasp_depth: float = 0.015, jaw_margin: float = 0.01,
                                  dedupe_distance: float = 0.004, dedupe_angle: float = 0.2,
                                  min_grasp_depth: float = 0.005, max_grasp_depth: float = 0.03,
                                  pad_below: float = 0.015, finger_thickness: float = 0.018,
                                  finger_width: float = 0.02, palm_above: float = 0.045,
                                  palm_size: tuple[float, float] = (0.13, 0.05), clearance: float = 0.005,
                                  cell: float = 0.002, prefer_center: bool = False,
                                  max_attempts: int | None = None, pad_contact: bool = False) -> list[ParallelJawGrasp]:
    """Top-down (approach = world -z) antipodal grasps on the object under `mask` (H, W bool) of a
    depth image. K: 3x3 intrinsics; X_WC: camera pose, RigidTransform or 4x4 array (camera z =
    optical axis). World frame.

    The visible points near the mask are binned into a world-frame height map (`cell` metres; the
    highest point per cell), so the geometry is metric and orthographic whatever the camera's
    perspective: the object's footprint is the cells holding its mask's points, contacts are pairs
    of footprint-boundary cells whose 2D outward normals are antipodal within the friction cone,
    the grasp axis is horizontal; both contacts must lie on an edge that stays inside the
    footprint +-0.4 finger_width across the axis (2 cells in), which drops corner-to-corner
    pairs whose smoothed normals look antipodal. (Pairing image-boundary pixels and deprojecting
    their midpoint does not work: for a tall object off the optical axis the mask spans its top
    and its side, and the midpoint lands up to 2 cm beside the object.)

    How deep the jaws go (the reference is silent; our choice): z_top is the object's highest
    point along the segment joining the contacts; z_free the highest surface where the fingers land
    (jaw_margin + finger_thickness beyond each contact, finger_width across). The centre goes
    half-way down the visible side, z_top - clip((z_top - z_free) / 2, min_grasp_depth,
    max_grasp_depth) (`grasp_depth` when no surface is seen there), then is raised so that the
    pads' lower edge (`pad_below` under the centre) stays above z_free and the palm (`palm_size`
    along the axis x across, its lower face `palm_above` over the centre) above everything under
    it; when that leaves less than min_grasp_depth under z_top the candidate is dropped (a
    neighbour, or an occluder lying on the mask's edge, is in the way). The defaults are the
    station's parallel jaw (ms_drake.station.grippers.ParallelJawConfig: fingers 12 mm + 6 mm
    pad thick and 20 mm wide, pads 30 mm long centred on the tool point, palm 130 x 50 mm
    45 mm above it). `clearance` (metres) is kept between the jaw and what the height map shows,
    vertically and around the palm's outline (the map is the visible surface only). Half-way
    down is where a lying cylinder is widest and where a tilted box's side faces are under both
    jaws; 1 cm under the highest point puts one jaw above a tilted top face.

    pad_contact: the depth test is on the pads, not the centre: a candidate stays when the pads'
    lower edge (`pad_below` under the centre) is min_grasp_depth under z_top, so an object that
    rises less than pad_below + clearance + min_grasp_depth above what lies beside it (a knife,
    scissors, a wrench lying flat) is held by the pads' lower part; score such grasps with
    GraspEvaluator(pad_span=pad_below), which finds the contacts there. Off (default): the centre
    must be min_grasp_depth under z_top.

    prefer_center: return the candidates sorted by the distance of their centre to the footprint's
    centroid (a proxy for the centre of mass: gravity's torque about the grasp axis is what the
    jaws' torsional friction must resist); otherwise in the order drawn. max_attempts: first
    contacts tried (default 15 per requested grasp)."""
    X_WC = as_matrix4(X_WC, "X_WC")
    if depth.shape != mask.shape:
        raise GraspError(f"depth image {depth.shape} and mask {mask.shape} must have the same shape")
    if not (cell > 0 and max_width > 0 and friction > 0) or count < 0:
        raise GraspError(f"sample_antipodal_grasps_depth needs count >= 0, cell > 0, max_width > 0, friction > 0 "
                         f"(got {count}, {cell}, {max_width}, {friction})")
    rng = np.random.default_rng(seed)
    finite = np.isfinite(depth) & (depth > 0)
    valid = mask & finite
    if valid.sum() < 4:
        return []
    # a window of the image around the mask wide enough for the fingers beside it
    reach = jaw_margin + finger_thickness
    margin = max(reach, 0.5 * palm_size[0]) + 3 * cell
    rows, cols = np.nonzero(valid)
    pad_px = int(np.ceil(margin * max(K[0, 0], K[1, 1]) / float(depth[valid].min()))) + 1
    r0, r1 = max(rows.min() - pad_px, 0), min(rows.max() + pad_px + 1, depth.shape[0])
    c0, c1 = max(cols.min() - pad_px, 0), min(cols.max() + pad_px + 1, depth.shape[1])
    sub = np.where(finite[r0:r1, c0:c1], depth[r0:r1, c0:c1], np.nan)
    v, u = np.mgrid[r0:r1, c0:c1]
    P_C = np.stack([(u - K[0, 2]) * sub / K[0, 0], (v - K[1, 2]) * sub / K[1, 1], sub], axis=-1)
    P_W = transform_points(X_WC, P_C)
    ok = np.isfinite(sub)
    obj = P_W[valid[r0:r1, c0:c1] & ok]
    # the neighbours: points off the mask dilated by 2 px (a silhouette's edge pixels can carry
    # the object's own depth without its label)

    near = cv2.dilate(valid[r0:r1, c0:c1].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    others = P_W[ok & ~near]
    lo = obj[:, :2].min(axis=0) - margin
    shape = tuple(int(x) for x in np.ceil((obj[:, :2].max(axis=0) + margin - lo) / cell)[::-1])
    H_obj = height_map(obj, lo, shape, cell)
    H_others = height_map(others, lo, shape, cell)
    H_all = np.maximum(H_obj, H_others)
    foot = np.isfinite(H_obj)
    foot = cv2.morphologyEx(foot.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    H_top = np.where(foot, np.where(np.isfinite(H_obj), H_obj, _fill_max(H_obj)), -np.inf)
    brow, bcol, n2d = _mask_boundary_normals(foot)
    if len(brow) < 2:
        return []
    cos_h = np.cos(np.arctan(friction))
    rc = np.stack([bcol, brow], axis=1).astype(float)
    centroid = np.array(np.nonzero(foot)[::-1], float).mean(axis=1)
    reach_c, half_c, margin_c = reach / cell, 0.5 * finger_width / cell, max(1.0, jaw_margin / cell)
    edge_c = 0.4 * finger_width / cell  # +-8 mm of edge under the 20 mm pad
    palm_a, palm_b = (0.5 * palm_size[0] + clearance) / cell, (0.5 * palm_size[1] + clearance) / cell
    wanted = count
    cands, kept = [], []
    for i in rng.permutation(len(brow))[: max_attempts or 15 * max(wanted, 1)]:
        if len(cands) >= wanted:
            break
        vv = rc - rc[i]
        d = np.linalg.norm(vv, axis=1)
        good = d > 1
        vu = np.where(good[:, None], vv / np.maximum(d, 1e-9)[:, None], 0)
        good &= (vu @ -n2d[i] >= cos_h) & (np.sum(vu * n2d, axis=1) >= cos_h)
        good &= (d + 1) * cell <= max_width - 2 * jaw_margin
        if not np.any(good):
            continue
        j = rng.choice(np.nonzero(good)[0])
        width = (d[j] + 1) * cell  # boundary cells' centres are half a cell inside the edges
        seg = np.round(rc[i] + np.linspace(0, 1, int(d[j]) + 2)[:, None] * (rc[j] - rc[i])).astype(int)
        zs = H_top[seg[:, 1], seg[:, 0]]
        zs = zs[np.isfinite(zs)]
        if len(zs) == 0:
            continue
        z_top = float(zs.max())
        u2 = vv[j] / d[j]
        if not (_edge_under_pad(foot, rc[i], u2, edge_c, 2) and _edge_under_pad(foot, rc[j], -u2, edge_c, 2)):
            continue
        # neighbours anywhere between the contact and the finger's back; the object itself only
        # where the finger is (an axis oblique to the edge passes over the object's own corner)
        z_free = max(_rect_top(H_others, rc[i], -u2, (1, reach_c), half_c),
                     _rect_top(H_others, rc[j], u2, (1, reach_c), half_c),
                     _rect_top(H_obj, rc[i], -u2, (margin_c, reach_c), half_c),
                     _rect_top(H_obj, rc[j], u2, (margin_c, reach_c), half_c))
        below = grasp_depth if not np.isfinite(z_free) else float(
            np.clip(0.5 * (z_top - z_free), min_grasp_depth, max_grasp_depth))
        z_palm = _rect_top(H_all, 0.5 * (rc[i] + rc[j]), u2, (-palm_a, palm_a), palm_b)
        z = max(z_top - below, z_free + pad_below + clearance, z_palm - palm_above + clearance)
        if z_top - (z - pad_below if pad_contact else z) < min_grasp_depth - 1e-9:
            continue
        mid = 0.5 * (rc[i] + rc[j]) + 0.5
        center = np.array([lo[0] + mid[0] * cell, lo[1] + mid[1] * cell, z])
        axis = np.array([u2[0], u2[1], 0.0])
        if _is_duplicate(center, axis, kept, dedupe_distance, dedupe_angle):
            continue
        kept.append((center, axis))
        dist_c = float(np.linalg.norm(0.5 * (rc[i] + rc[j]) - centroid))
        cands.append((dist_c, ParallelJawGrasp(center, axis, (0.0, 0.0, -1.0),
                                               min(max_width, width + 2 * jaw_margin))))
    if prefer_center:
        cands.sort(key=lambda x: x[0])
    return [g for _, g in cands[:count]]


def _fill_max(H: np.ndarray) -> np.ndarray:
    """Empty cells take the highest neighbour (3x3); the footprint's closing may add such cells."""
    return cv2.dilate(np.where(np.isfinite(H), H, -1e9).astype(np.float32), np.ones((3, 3), np.uint8))


def sample_suction_grasps_depth(depth: np.ndarray, K: np.ndarray, X_WC: np.ndarray, mask: np.ndarray,
                                count: int, seed: int = 0, dedupe_distance: float = 0.003,
                                cup_radius: float | None = None, clearance: float = 0.005,
                                cup_length: float = 0.112):
    """Suction grasps at mask pixels: point = deprojected pixel, approach = minus the depth normal.
    X_WC: camera pose (RigidTransform or 4x4 array). cup_radius: when given, a candidate is
    collision-free only if no seen point off the mask lies within `cup_radius` of its approach
    axis between `clearance` and `cup_length` (cup and stem) above the contact point along the
    axis (the cup would land on a neighbour: an object lying on the grasped one, or a taller one
    beside it); the others are dropped (the reference's simulated grasps are executed only when
    collision-free, line 1505)."""
    X_WC = as_matrix4(X_WC, "X_WC")
    rng = np.random.default_rng(seed)
    finite = np.isfinite(depth) & (depth > 0)
    valid = mask & finite
    R, t = X_WC[:3, :3], X_WC[:3, 3]
    rows, cols = np.nonzero(valid)
    if len(rows) == 0:
        return []
    # normals on the mask's window (+ 2 px: np.gradient's central differences at every mask pixel,
    # the same values as on the whole image)
    r0, r1 = max(rows.min() - 2, 0), min(rows.max() + 3, depth.shape[0])
    c0, c1 = max(cols.min() - 2, 0), min(cols.max() + 3, depth.shape[1])
    Kw = np.array(K, float)
    Kw[:2, 2] -= (c0, r0)
    P = depth_to_points(depth[r0:r1, c0:c1], Kw)
    N = depth_normals(P)
    ok = valid[r0:r1, c0:c1] & np.all(np.isfinite(N), axis=-1)
    rows, cols = np.nonzero(ok)
    others = None
    if cup_radius is not None:
        # seen points of everything else (world frame) that a cup's axis check can reach: within
        # cup_length + 2.2 cup_radius of a mask point (the balls of _cup_blocked)
        off = ~mask & finite
        Q = transform_points(X_WC, depth_to_points(depth, K)[off])
        obj = transform_points(X_WC, P[ok])
        reach = cup_length + 2.2 * cup_radius
        lo, hi = obj.min(axis=0) - reach, obj.max(axis=0) + reach
        # built for a few dozen ball queries: unbalanced and not compacted builds 2.5x faster, and
        # a ball query's answer does not depend on the tree's shape
        others = cKDTree(Q[np.all((Q >= lo) & (Q <= hi), axis=1)], balanced_tree=False, compact_nodes=False)
    out, picks = [], rng.permutation(len(rows))[: 40 * max(count, 1)]
    kept, n_kept = np.empty((len(picks), 3)), 0
    for i in picks:
        if len(out) >= count:
            break
        p = R @ P[rows[i], cols[i]] + t
        if n_kept and np.min(np.sum((kept[:n_kept] - p) ** 2, axis=1)) < dedupe_distance ** 2:
            continue
        kept[n_kept] = p
        n_kept += 1
        if others is not None and others.n and _cup_blocked(others, p, R @ N[rows[i], cols[i]], cup_radius,
                                                                clearance, cup_length):
            continue
        out.append(SuctionGrasp(p, -(R @ N[rows[i], cols[i]])))
    return out


def _cup_blocked(points, p: np.ndarray, normal: np.ndarray, radius: float, clearance: float,
                 length: float) -> bool:
    """Whether a point of `points` (an (M, 3) array or a scipy cKDTree of one) lies within `radius`
    of the axis through p along `normal` (the outward surface normal, towards the approaching
    cup), between `clearance` and `length` above p on it."""
    n = normal / np.linalg.norm(normal)
    if isinstance(points, cKDTree):  # only the points near the axis: balls every `radius` along it
        s = np.arange(clearance, length + radius, radius)
        near = points.query_ball_point(p + s[:, None] * n, 1.12 * radius)
        idx = np.unique(np.concatenate([np.asarray(i, int) for i in near])) if len(near) else []
        if not len(idx):
            return False
        points = points.data[idx]
    d = points - p
    h = d @ n
    up = (h > clearance) & (h < length)
    if not up.any():
        return False
    d, h = d[up], h[up]
    return bool(np.any(np.einsum("ij,ij->i", d, d) - h * h < radius * radius))
