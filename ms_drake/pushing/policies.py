"""The five linear push policies of Ch. 4.4 (lines 644-692), from full state or from a depth image.

Every policy returns one `Push` (a segment at constant height, world frame) or None when it finds
no collision-free push. The height is `free_space.push_height`: half the object's height, at
least `min_push_height` (2 cm: the YuMi's fingertips and its IK's floor margin) and at most
`max_push_height` above the floor. The policies see the scene through a `PushScene`: per object its centre
(centre of mass from full state; the centroid of its segmented points from an image, Ch. 4.4
"the centroid of the segmented cluster"), its footprint (xy of its hull vertices / of its points)
and its height range, and a clearance checker:

  * `StateChecker` (full state: object meshes and poses): object-object checks with coal on the
    objects' convex hulls (GJK distance, conservative advancement along the push direction, 5 mm
    resolution); the closed jaw is a coal cylinder from the push height up;
  * `ImageChecker` (depth image + instance masks): a top-down grid of the bin (4 mm) labelled with
    the mask of every point; an object's cells are shifted along the direction until they meet
    another object's cells or a wall (the "image clearance check"); the jaw is a disc of cells.

Both: the bin walls bound every object's motion (its footprint stays inside the inner box) and
the jaw stays inside the walls (pushes are clipped to the bin): its fingers' disc, and its palm,
which rides below the wall tops across the push direction (`palm_half_length`).

Policies (the reference's steps; our choices where it is silent, recorded here):
  quasi_random       a random object, a random direction, a fixed push (`PolicyParams.fixed_travel`)
                     through its centre, clipped to the bin; no collision check (the baseline);
  boundary_shear     the two objects with the closest centres c_i, c_j; four pushes along the
                     perpendicular to c_i c_j (each object, both senses); the collision-free one
                     closest (cosine) to the object's direction of free space (one object alone:
                     the free-space push);
  free_space         the same two objects; each object's free-space point p (below); directions
                     from c toward p turned in 10-degree steps up to 90 degrees, the first
                     collision-free one per object; of the two, the object nearer its p;
  max_clearance      every object, 16 directions: forward clearance / backward clearance (Chang,
                     Smith and Fox); the collision-free push with the largest ratio;
  cluster_diffusion  clusters of 1-3 objects by agglomerating the closest centres (a cluster stops
                     growing at 3 objects; centres more than `cluster_distance` apart stay apart); each object of a cluster of >= 2 pushed from the cluster centre
                     through its own centre; the collision-free push with the largest cosine to
                     the object's direction of free space (singletons only: the free-space
                     direction itself).
Free-space point p_i (line 648): the point of a 1 cm grid of the bin maximising
min(distance to the other objects' centres, distance to the walls) - `l2_penalty` |p - c_i|^2.
"Collision-free": the jaw's start (`start_gap` behind the object's footprint, where it descends)
touches no other object and lies inside the walls, and the object can move at least
`min_clearance` along the direction.
Push length: the object is pushed min(clearance, `max_travel`) (free space: also at most the
distance to p along the direction); the jaw starts `start_gap` behind the object's footprint.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import coal
import numpy as np
from scipy.spatial import ConvexHull, QhullError

from ms_drake.geometry import PinholeCamera, Workspace, depth_array, preprocess_depth, transform_points
from ms_drake.pushing.free_space import MAX_PUSH_HEIGHT, MIN_PUSH_HEIGHT, PushError, push_height
from ms_drake.types import InstanceMasks, ObjectGeometry, Push

POLICIES = ("quasi_random", "boundary_shear", "free_space", "max_clearance", "cluster_diffusion")


def check_push_policy(policy: str) -> str:
    if policy not in POLICIES:
        raise PushError(f"push policy {policy!r} unknown; choose one of {', '.join(POLICIES)}")
    return policy


@dataclass(frozen=True)
class PolicyParams:
    gripper_radius: float = 0.025  # the closed jaw's fingers seen from above (as PushParams)
    # The jaw's palm (13 x 5 cm, ParallelJawConfig) lies ~5 cm above the push height, its long
    # side across the push (PrimitiveBackend: the broad side leads), below the 12-cm walls: it
    # must stay inside the bin too (half extents with 5 mm margin).
    palm_half_length: float = 0.07
    palm_half_width: float = 0.03
    start_gap: float = 0.005  # jaw start behind the object's footprint
    max_travel: float = 0.10  # object displacement cap
    fixed_travel: float = 0.08  # quasi-random's fixed push
    # Ablation: quasi-random's push only as far as the object is free to move (its clearance,
    # at most fixed_travel) and with the jaw's start free, like the other policies' pushes; the
    # (object, direction) is drawn again, up to `checked_draws` times, while no such push exists.
    quasi_random_checked: bool = False
    checked_draws: int = 16
    min_clearance: float = 0.01
    directions: int = 16  # maximum clearance ratio
    angle_step: float = np.radians(10.0)  # free space
    max_angle: float = np.radians(90.0)
    l2_penalty: float = 2.0  # 1/m: free-space point regulariser
    grid: float = 0.01  # m: free-space point grid
    min_push_height: float = MIN_PUSH_HEIGHT  # tool centre above the floor (free_space.push_height)
    max_push_height: float = MAX_PUSH_HEIGHT
    resolution: float = 0.004  # image grid cell
    min_height: float = 0.004  # image points this far above the floor are objects
    max_cluster: int = 3
    cluster_distance: float = 0.12  # m: clusters whose centres are farther apart are not merged

    def __post_init__(self):
        for name in ("gripper_radius", "max_travel", "fixed_travel", "grid", "resolution"):
            if not getattr(self, name) > 0:
                raise PushError(f"PolicyParams.{name} must be > 0, got {getattr(self, name)}")
        if self.checked_draws < 1:
            raise PushError(f"PolicyParams.checked_draws must be >= 1, got {self.checked_draws}")
        if self.directions < 4:
            raise PushError(f"PolicyParams.directions must be >= 4, got {self.directions}")
        push_height(0.0, 0.0, self.min_push_height, self.max_push_height)


@dataclass(frozen=True, eq=False)
class PushObject:
    id: str
    center: np.ndarray  # (3,) world
    footprint: np.ndarray  # (K, 2) world xy
    bottom: float
    top: float


@dataclass(eq=False)
class PushScene:
    objects: list
    workspace: Workspace
    checker: object  # StateChecker | ImageChecker
    _free: dict = field(default_factory=dict)

    def wall_clearance(self, i: int, d: np.ndarray) -> float:
        """How far object i's footprint moves along unit d before it meets a wall."""
        ws = self.workspace
        lo = np.asarray(ws.center_xy) - 0.5 * np.asarray(ws.size_xy)
        hi = np.asarray(ws.center_xy) + 0.5 * np.asarray(ws.size_xy)
        fp = self.objects[i].footprint
        t = np.inf
        for k in range(2):
            if d[k] > 1e-9:
                t = min(t, float(np.min((hi[k] - fp[:, k]) / d[k])))
            elif d[k] < -1e-9:
                t = min(t, float(np.min((lo[k] - fp[:, k]) / d[k])))
        return max(t, 0.0)

    def clearance(self, i: int, d: np.ndarray, limit: float) -> float:
        limit = min(self.wall_clearance(i, d), limit)
        return min(self.checker.clearance(self, i, d, limit), limit) if limit > 0 else 0.0

    def free_point(self, i: int, params: PolicyParams) -> np.ndarray:
        """The free-space point p_i (module docstring)."""
        if i in self._free:
            return self._free[i]
        ws = self.workspace
        half = 0.5 * np.asarray(ws.size_xy)
        cx, cy = ws.center_xy
        xs = np.arange(cx - half[0] + 0.5 * params.grid, cx + half[0], params.grid)
        ys = np.arange(cy - half[1] + 0.5 * params.grid, cy + half[1], params.grid)
        P = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        wall = np.minimum(half[0] - np.abs(P[:, 0] - cx), half[1] - np.abs(P[:, 1] - cy))
        others = np.array([o.center[:2] for k, o in enumerate(self.objects) if k != i]).reshape(-1, 2)
        near = np.min(np.linalg.norm(P[:, None, :] - others[None], axis=-1), axis=1) if len(others) else np.inf
        c = self.objects[i].center[:2]
        score = np.minimum(near, wall) - params.l2_penalty * np.sum((P - c) ** 2, axis=1)
        self._free[i] = P[int(np.argmax(score))]
        return self._free[i]

    def free_direction(self, i: int, params: PolicyParams) -> np.ndarray:
        return _unit(self.free_point(i, params) - self.objects[i].center[:2])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else np.array([1.0, 0.0])


def _rot(v: np.ndarray, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


# --------------------------------------------------------------------------- full state (coal)
_HULLS: dict = {}


def _hull_of(vertices: np.ndarray) -> np.ndarray:
    v = np.ascontiguousarray(vertices, float)
    key = (v.shape, zlib.crc32(v.tobytes()))
    h = _HULLS.get(key)
    if h is None:
        if len(_HULLS) > 512:
            _HULLS.clear()
        try:
            h = v[ConvexHull(v).vertices] if len(v) > 4 else v
        except QhullError:
            h = v
        _HULLS[key] = h
    return h


def _com_of(geom: ObjectGeometry) -> np.ndarray:
    if geom.com is not None:
        return np.asarray(geom.com, float)
    v, f = np.asarray(geom.vertices, float), np.asarray(geom.faces, int)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    if abs(vol.sum()) < 1e-12:
        return v.mean(axis=0)
    return ((a + b + c) / 4.0 * vol[:, None]).sum(axis=0) / vol.sum()


def _convex(points: np.ndarray):
    """coal's convex hull of the points (qhull); a degenerate (flat) set: the box of its extents."""
    pts = np.ascontiguousarray(points, float)
    vec = coal.StdVec_Vec3s()
    for p in pts:
        vec.append(p)
    try:
        return coal.Convex.convexHull(vec, False, "")
    except RuntimeError:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        return coal.Box(*np.maximum(hi - lo, 1e-4))


class StateChecker:
    """coal clearance checks on the objects' convex hulls (world frame vertices, identity pose)."""

    def __init__(self, hulls_W: list):
        self.hulls = [np.asarray(h, float) for h in hulls_W]
        self.shapes = []
        for h in self.hulls:
            c = h.mean(axis=0)
            self.shapes.append((_convex(h - c), c))
        self._req = coal.DistanceRequest()
        self._d0: dict = {}  # (i, j) -> distance at rest (the same for every direction)
        self._radius: dict = {}  # i -> the footprint's bounding-circle radius about its centre
        self._eye = np.eye(3)

    def _distance(self, i: int, j: int, shift: np.ndarray) -> float:
        (a, ca), (b, cb) = self.shapes[i], self.shapes[j]
        res = coal.DistanceResult()
        d = coal.distance(a, coal.Transform3s(self._eye, ca + shift), b, coal.Transform3s(self._eye, cb),
                          self._req, res)
        return float(d)

    def _footprint_radius(self, scene: PushScene, i: int) -> float:
        if i not in self._radius:
            o = scene.objects[i]
            self._radius[i] = float(np.max(np.linalg.norm(o.footprint - o.center[:2], axis=1)))
        return self._radius[i]

    def clearance(self, scene: PushScene, i: int, d2: np.ndarray, limit: float, tol: float = 0.001,
                  step: float = 0.005) -> float:
        oi = scene.objects[i]
        d = np.array([d2[0], d2[1], 0.0])
        active = []
        for j, oj in enumerate(scene.objects):
            if j == i:
                continue
            # Footprints (bounding circles) that the sweep never reaches are skipped.
            rel = oj.center[:2] - oi.center[:2]
            ri, rj = self._footprint_radius(scene, i), self._footprint_radius(scene, j)
            along = float(rel @ d2)
            across = abs(float(rel[0] * d2[1] - rel[1] * d2[0]))
            if across > ri + rj or along < -(ri + rj) or along > limit + ri + rj:
                continue
            if (i, j) not in self._d0:
                self._d0[(i, j)] = self._distance(i, j, np.zeros(3))
            if self._d0[(i, j)] < tol:
                stacked = oi.bottom >= oj.top - 0.01 or oj.bottom >= oi.top - 0.01
                if stacked or along <= 0:
                    continue  # resting on / under it, or moving away from a touching neighbour
                return 0.0
            active.append(j)
        if not active:
            return float(limit)
        t = 0.0
        while t < limit:
            dist = min(self._distance(i, j, t * d) for j in active)
            if dist < tol:
                return max(t - step, 0.0) if dist <= 0 else t
            t += max(dist, step)
        return min(t, limit)

    def gripper_free(self, scene: PushScene, xy: np.ndarray, z: float, radius: float, skip: int = -1) -> bool:
        """The closed jaw (a cylinder of `radius` from z up above every object) touches no object
        other than `skip`."""
        h = max(o.top for o in scene.objects) + 0.05 - z
        cyl = coal.Cylinder(radius, max(h, 0.01))
        T = coal.Transform3s(np.eye(3), np.array([xy[0], xy[1], z + 0.5 * max(h, 0.01)]))
        req = coal.CollisionRequest()
        for k, (shape, c) in enumerate(self.shapes):
            if k == skip:
                continue
            o = scene.objects[k]
            if np.min(np.linalg.norm(o.footprint - xy, axis=1)) > radius + 0.02 and \
                    not _in_polygon(o.footprint, xy):
                continue
            res = coal.CollisionResult()
            if coal.collide(cyl, T, shape, coal.Transform3s(np.eye(3), c), req, res):
                return False
        return True


def _in_polygon(points: np.ndarray, xy: np.ndarray) -> bool:
    """xy inside the bounding box of the points (a cheap pre-test, never a false 'outside')."""
    return bool(np.all(xy >= points.min(axis=0)) and np.all(xy <= points.max(axis=0)))


def state_scene(objects, workspace: Workspace) -> PushScene:
    """A PushScene from full state: tuple[ObjectGeometry] (meshes, 4x4 world poses)."""
    objs, hulls = [], []
    for g in objects:
        X = np.asarray(g.X_WO, float)
        h = transform_points(X, _hull_of(np.asarray(g.vertices, float)))
        com = X[:3, :3] @ _com_of(g) + X[:3, 3]
        objs.append(PushObject(str(g.id), com, h[:, :2].copy(), float(h[:, 2].min()), float(h[:, 2].max())))
        hulls.append(h)
    return PushScene(objs, workspace, StateChecker(hulls))


# --------------------------------------------------------------------------- depth image
class ImageChecker:
    """Top-down grid of the bin: label per cell (-1 free), shifted-footprint clearance checks."""

    def __init__(self, workspace: Workspace, cells: list, res: float):
        self.res = res
        sx, sy = workspace.size_xy
        self.nx, self.ny = int(np.ceil(sx / res)), int(np.ceil(sy / res))
        self.x0 = workspace.center_xy[0] - 0.5 * self.nx * res
        self.y0 = workspace.center_xy[1] - 0.5 * self.ny * res
        self.labels = np.full((self.ny, self.nx), -1, int)
        self.cells = []
        for k, xy in enumerate(cells):
            j = np.clip(((xy[:, 0] - self.x0) / res).astype(int), 0, self.nx - 1)
            i = np.clip(((xy[:, 1] - self.y0) / res).astype(int), 0, self.ny - 1)
            lin = np.unique(i * self.nx + j)  # 1D unique: ~20x cheaper than unique rows
            ij = np.stack([lin // self.nx, lin % self.nx], axis=1)
            self.labels[ij[:, 0], ij[:, 1]] = k
            self.cells.append(ij)
        # An object's boundary cells (a 8-neighbour outside it): a shifted footprint first meets
        # another object with them (the shifts advance by at most one cell per step).
        pad = np.pad(self.labels, 1, constant_values=-1)
        for k, ij in enumerate(self.cells):
            I, J = ij[:, 0] + 1, ij[:, 1] + 1
            inner = np.ones(len(ij), bool)
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    inner &= pad[I + di, J + dj] == k
            self.cells[k] = ij[~inner] if (~inner).any() else ij

    def clearance(self, scene: PushScene, i: int, d2: np.ndarray, limit: float) -> float:
        ij = self.cells[i]
        ts = np.arange(self.res, limit + self.res, self.res)
        di = np.round(ts[:, None] * d2[1] / self.res).astype(int)
        dj = np.round(ts[:, None] * d2[0] / self.res).astype(int)
        I, J = ij[None, :, 0] + di, ij[None, :, 1] + dj
        inside = (I >= 0) & (I < self.ny) & (J >= 0) & (J < self.nx)
        lab = np.where(inside, self.labels[np.clip(I, 0, self.ny - 1), np.clip(J, 0, self.nx - 1)], -1)
        hit = np.any((lab >= 0) & (lab != i), axis=1)
        if not hit.any():
            return float(limit)
        return float(ts[int(np.argmax(hit))] - self.res)

    def gripper_free(self, scene: PushScene, xy: np.ndarray, z: float, radius: float, skip: int = -1) -> bool:
        """No cell of an object other than `skip` under the jaw's disc."""
        n = int(np.ceil(radius / self.res))
        off = np.arange(-n, n + 1)
        di, dj = np.meshgrid(off, off, indexing="ij")
        disc = (di ** 2 + dj ** 2) * self.res ** 2 <= radius ** 2
        i = int((xy[1] - self.y0) / self.res) + di[disc]
        j = int((xy[0] - self.x0) / self.res) + dj[disc]
        ok = (i >= 0) & (i < self.ny) & (j >= 0) & (j < self.nx)
        lab = self.labels[i[ok], j[ok]]
        return bool(not np.any((lab >= 0) & (lab != skip)))


def image_scene(depth, masks: InstanceMasks, camera: PinholeCamera, workspace: Workspace,
                params: PolicyParams = PolicyParams(), max_points: int = 400) -> PushScene:
    """A PushScene from a depth image (read through geometry.preprocess_depth) and instance masks
    (one object per mask)."""
    D = depth_array(preprocess_depth(depth))
    if len(masks) and masks.masks.shape[1:] != D.shape:
        raise PushError(f"masks are {masks.masks.shape[2]}x{masks.masks.shape[1]} but the depth image "
                        f"{D.shape[1]}x{D.shape[0]}; segment the same camera's image")
    if D.shape != (camera.height, camera.width):
        raise PushError(f"depth image is {D.shape[1]}x{D.shape[0]} but the camera is "
                        f"{camera.width}x{camera.height}; build the system from the same camera config")
    # Only the masked pixels are deprojected (world_points of the whole image costs ~10x more).
    any_mask = masks.masks.any(axis=0) if len(masks) else np.zeros(D.shape, bool)
    v, u = np.nonzero(any_mask)
    z = D[v, u]
    P_C = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=-1)
    pts_W = P_C @ camera.X_WC.rotation().matrix().T + camera.X_WC.translation()
    fg_pts = workspace.foreground(pts_W[None], params.min_height, margin=0.0)[0]
    objs, cells = [], []
    for k in range(len(masks)):
        sel = masks.masks[k][v, u] & fg_pts
        pts = pts_W[sel]
        if len(pts) < 3:
            continue
        cells.append(pts[:, :2])
        sub = pts[:: max(1, len(pts) // max_points)]
        objs.append(PushObject(str(masks.ids[k]), pts.mean(axis=0), sub[:, :2].copy(), workspace.floor_z,
                               float(np.percentile(pts[:, 2], 90))))
    return PushScene(objs, workspace, ImageChecker(workspace, cells, params.resolution))


# --------------------------------------------------------------------------- push construction
def _jaw_half(d: np.ndarray, params: PolicyParams) -> np.ndarray:
    """Per world axis, the half extent of the jaw's footprint (fingers' disc, palm across d)."""
    perp = np.array([-d[1], d[0]])
    palm = np.abs(perp) * params.palm_half_length + np.abs(d) * params.palm_half_width
    return np.maximum(palm, params.gripper_radius)


def _inside(scene: PushScene, xy: np.ndarray, radius) -> bool:
    ws = scene.workspace
    half = 0.5 * np.asarray(ws.size_xy) - radius
    return bool(np.all(np.abs(xy - np.asarray(ws.center_xy)) <= half + 1e-9))


def _clip_inside(scene: PushScene, xy: np.ndarray, radius) -> np.ndarray:
    ws = scene.workspace
    half = 0.5 * np.asarray(ws.size_xy) - radius
    c = np.asarray(ws.center_xy)
    return c + np.clip(xy - c, -half, half)


def make_push(scene: PushScene, i: int, d, travel: float, params: PolicyParams,
              check: bool = True) -> Push | None:
    """The jaw's segment that pushes object i by `travel` along unit d (None if not valid)."""
    o = scene.objects[i]
    d = _unit(d)
    c = o.center[:2]
    r = params.gripper_radius
    z = push_height(scene.workspace.floor_z, o.top, params.min_push_height, params.max_push_height)
    t_back = float(np.max((c - o.footprint) @ d))
    contact = t_back + r  # jaw centre distance behind c when it touches the footprint
    start = c - (contact + params.start_gap) * d
    jaw = _jaw_half(d, params)
    if check:
        # The jaw descends at the start: it must touch no other object there, and inside the walls.
        if not (_inside(scene, start, jaw) and scene.checker.gripper_free(scene, start, z, r, skip=i)):
            return None
    else:
        start = _clip_inside(scene, start, jaw)
    end = c + (travel - contact) * d
    # Clipped to the bin: the jaw (fingers and palm) stays inside the walls.
    L = float((end - start) @ d)
    half = 0.5 * np.asarray(scene.workspace.size_xy) - jaw
    cen = np.asarray(scene.workspace.center_xy)
    for k in range(2):
        if d[k] > 1e-9:
            L = min(L, float((cen[k] + half[k] - start[k]) / d[k]))
        elif d[k] < -1e-9:
            L = min(L, float((cen[k] - half[k] - start[k]) / d[k]))
    if L <= float((c - start) @ d) - contact + params.min_clearance:  # never reaches the object
        return None
    end = start + L * d
    return Push((float(start[0]), float(start[1]), z), (float(end[0]), float(end[1]), z), o.id)


def _try(scene, i, d, params, cap=None):
    """(push, clearance) of object i along d when collision-free, else (None, clearance)."""
    lim = params.max_travel if cap is None else min(cap, params.max_travel)
    clr = scene.clearance(i, d, lim)
    if clr < min(params.min_clearance, lim):
        return None, clr
    return make_push(scene, i, d, clr, params), clr


def closest_pair(scene: PushScene) -> tuple[int, int]:
    C = np.array([o.center[:2] for o in scene.objects])
    D = np.linalg.norm(C[:, None] - C[None], axis=-1) + np.diag(np.full(len(C), np.inf))
    i, j = np.unravel_index(int(np.argmin(D)), D.shape)
    return int(i), int(j)


def quasi_random(scene: PushScene, params: PolicyParams, rng) -> Push | None:
    """A random object pushed `fixed_travel` in a random direction through its centre, clipped to
    the bin only (lines 654-660); with params.quasi_random_checked the collision-free ablation."""
    for _ in range(params.checked_draws if params.quasi_random_checked else 1):
        i = int(rng.integers(len(scene.objects)))
        a = float(rng.uniform(0.0, 2 * np.pi))
        d = np.array([np.cos(a), np.sin(a)])
        if not params.quasi_random_checked:
            return make_push(scene, i, d, params.fixed_travel, params, check=False)
        push, _ = _try(scene, i, d, params, cap=params.fixed_travel)
        if push is not None:
            return push
    return None


def boundary_shear(scene: PushScene, params: PolicyParams, rng=None) -> Push | None:
    if len(scene.objects) == 1:
        return free_space(scene, params)
    i, j = closest_pair(scene)
    n = _unit(scene.objects[j].center[:2] - scene.objects[i].center[:2])
    perp = np.array([-n[1], n[0]])
    cands = []
    for k in (i, j):
        f = scene.free_direction(k, params)
        for s in (1.0, -1.0):
            cands.append((float(f @ (s * perp)), k, s * perp))
    for _, k, d in sorted(cands, key=lambda c: -c[0]):
        p, _ = _try(scene, k, d, params)
        if p is not None:
            return p
    return None


def free_space(scene: PushScene, params: PolicyParams, rng=None) -> Push | None:
    pair = closest_pair(scene) if len(scene.objects) > 1 else (0,)
    angles = [0.0]
    k = 1
    while k * params.angle_step <= params.max_angle + 1e-9:
        angles += [k * params.angle_step, -k * params.angle_step]
        k += 1
    options = []
    for i in pair:
        c, p = scene.objects[i].center[:2], scene.free_point(i, params)
        d0 = _unit(p - c)
        for a in angles:
            d = _rot(d0, a)
            push, _ = _try(scene, i, d, params, cap=max(float((p - c) @ d), params.min_clearance))
            if push is not None:
                options.append((float(np.linalg.norm(p - c)), i, push))
                break
    if not options:
        return None
    return min(options, key=lambda o: o[0])[2]


def max_clearance(scene: PushScene, params: PolicyParams, rng=None) -> Push | None:
    best, best_ratio = None, -np.inf
    n = int(params.directions)
    angles = 2 * np.pi * np.arange(n) / n
    dirs = np.column_stack([np.cos(angles), np.sin(angles)])
    if n % 2 == 0:  # exact opposites, so that a direction's backward clearance is another's forward one
        dirs[n // 2:] = -dirs[:n // 2]
    for i in range(len(scene.objects)):
        memo: dict = {}

        def clear(d):
            key = (round(float(d[0]), 12), round(float(d[1]), 12))
            if key not in memo:
                memo[key] = scene.clearance(i, d, params.max_travel)
            return memo[key]

        for d in dirs:
            back = max(clear(-d), params.resolution)
            if params.max_travel / back <= best_ratio:
                continue  # even the longest forward clearance would not beat the best ratio
            fwd = clear(d)
            if fwd < params.min_clearance:
                continue
            ratio = fwd / back
            if ratio > best_ratio:
                push = make_push(scene, i, d, fwd, params)
                if push is not None:
                    best, best_ratio = push, ratio
    return best


def clusters(scene: PushScene, max_size: int = 3, max_distance: float = np.inf) -> list[list[int]]:
    """Agglomerate the closest centres (cluster centroid distance, at most max_distance) into
    clusters of <= max_size."""
    C = np.array([o.center[:2] for o in scene.objects])
    groups = [[k] for k in range(len(C))]
    while True:
        best = None
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                if len(groups[a]) + len(groups[b]) > max_size:
                    continue
                dist = float(np.linalg.norm(C[groups[a]].mean(axis=0) - C[groups[b]].mean(axis=0)))
                if dist <= max_distance and (best is None or dist < best[0]):
                    best = (dist, a, b)
        if best is None:
            return groups
        _, a, b = best
        groups[a] = groups[a] + groups[b]
        del groups[b]


def cluster_diffusion(scene: PushScene, params: PolicyParams, rng=None) -> Push | None:
    C = np.array([o.center[:2] for o in scene.objects])
    cands = []
    groups = clusters(scene, params.max_cluster, params.cluster_distance)
    for g in groups:
        if len(g) < 2:
            continue
        m = C[g].mean(axis=0)
        for k in g:
            d = _unit(C[k] - m)
            cands.append((float(d @ scene.free_direction(k, params)), k, d))
    if not cands:
        cands = [(1.0, k, scene.free_direction(k, params)) for k in range(len(C))]
    for _, k, d in sorted(cands, key=lambda c: -c[0]):
        p, _ = _try(scene, k, d, params)
        if p is not None:
            return p
    return None


_POLICY_FNS = {"quasi_random": quasi_random, "boundary_shear": boundary_shear, "free_space": free_space,
               "max_clearance": max_clearance, "cluster_diffusion": cluster_diffusion}


def plan_policy_push(policy: str, scene: PushScene, params: PolicyParams = PolicyParams(),
                     seed=0) -> Push | None:
    """The push of `policy` in `scene` (None: no collision-free push, or no object)."""
    check_push_policy(policy)
    if not scene.objects:
        return None
    return _POLICY_FNS[policy](scene, params, np.random.default_rng(seed))
