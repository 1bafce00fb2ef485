"""Shelf geometry below every capability (Ch. 9): the shelf interior and camera of a shelf
scenario, upright boxes and cylinders on its floor, ray casts from the camera, the target's
visible fraction and the placements where a target is fully hidden (Ch. 9.4.1).

Shelf frame S: the environment frame of a shelf scenario (ms_drake.station.environments): inner
[-X/2, X/2] x [-Y/2, Y/2] x [0, Z], the open front at y = -Y/2 facing the camera.

Objects are vertical prisms standing on the floor: boxes axis-aligned with the shelf and
cylinders. Seen from above each is a rounded rectangle (half-extents (a, b), corner radius r; a
box has r = 0, a cylinder a = b = 0), which keeps the simulator's collision, contact and sweep
computations closed-form: the Minkowski sum of two rounded rectangles is a rounded rectangle, and
so is a rounded rectangle swept along an axis.

Hidden placements follow the reference's pipeline (CGAL replaced by shapely):
1. the 2D visibility polygon V of the floor from the camera's floor point, the objects taken as
   walls of infinite height: the interior minus the objects' shadows (shapely);
2. V's Minkowski sum with the target's footprint F, V + F = V u U_edges hull(edge + F) (exact for
   a convex F containing its centre), and the objects' sums with F (convex: hulls of vertex sums);
   candidate centres are the points of a floor grid outside both;
3. 3D ray casts from the camera to points of the target's top face at every candidate. A point
   hidden from the camera (which is above every object) hides every point below it, since the ray
   to the lower point runs lower everywhere; so the target is hidden iff its top face is. The face
   points of all candidates lie on the same grid: each is cast once, and a candidate is hidden iff
   every grid point of its face is (a grid erosion by the face).
A placement also needs the whole target inside the camera's view (in the image, below the shelf
top's front edge), since a target hidden only by being out of view could never be revealed.
`exactly_hidden` checks one placement without sampling: a top face at height h is hidden iff it
lies in the union of the objects' shadows on the plane z = h, each the convex hull of a
footprint and its copy scaled about the camera's floor point by (z_cam - h) / (z_cam - h_object).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import shapely

from ms_drake.errors import SceneError
from ms_drake.geometry import PinholeCamera
from ms_drake.types import ShelfObject, ShelfOccupancy

#: Sides of the polygon standing in for a cylinder's circle in shapely computations (inscribed:
#: its shadows are slightly smaller than the cylinder's, so "hidden" stays conservative).
CIRCLE_SIDES = 32


@dataclass(frozen=True, eq=False)
class ShelfGeometry:
    """The shelf's inner size (X, Y, Z), the camera and the shelf frame's origin in the world."""

    size: tuple[float, float, float]
    camera: PinholeCamera
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        X_WC = self.camera.X_WC
        object.__setattr__(self, "_R_CS", X_WC.rotation().matrix().T.copy())
        object.__setattr__(self, "_eye", X_WC.translation() - np.asarray(self.origin, float))
        eye = self._eye
        half = 0.5 * np.asarray(self.size, float)
        if not (eye[1] < -half[1] and eye[2] > 0):
            raise SceneError(f"shelf camera at {np.round(eye, 3).tolist()} (shelf frame): it must be in front of "
                             f"the open front (y < {-half[1]:.3f}) and above the floor; move the camera's X_PB")

    @staticmethod
    def from_scenario(scenario, camera: str = "front") -> "ShelfGeometry":
        """The geometry of a shelf scenario (e.g. FetchShelf) seen by its camera `camera`."""
        env = scenario.environment
        if env.type != "shelf":
            raise SceneError(f"environment.type is {env.type!r}: shelf scenes need a shelf scenario (e.g. FetchShelf)")
        if camera not in scenario.cameras:
            raise SceneError(f"camera {camera!r} is not in the scenario's cameras "
                             f"({', '.join(scenario.cameras) or 'none'}); pass one of them")
        size = tuple(float(v) for v in env.resolved_size())
        return ShelfGeometry(size, PinholeCamera.from_config(scenario.cameras[camera]),
                             tuple(float(v) for v in env.position))

    @property
    def eye(self) -> np.ndarray:
        """The camera's position in the shelf frame."""
        return self._eye

    @property
    def half(self) -> np.ndarray:
        return 0.5 * np.asarray(self.size[:2], float)

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel u, v and depth z of shelf-frame points p (..., 3)."""
        q = (p - self._eye) @ self._R_CS.T
        z = q[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        cam = self.camera
        return cam.fx * q[..., 0] / zs + cam.cx, cam.fy * q[..., 1] / zs + cam.cy, z

    def in_view(self, p: np.ndarray) -> np.ndarray:
        """Bool (...): the camera would see shelf-frame points p (..., 3) with nothing on the
        shelf: in front of the camera, inside the image, and seen through the open front (the ray
        crosses the front plane between the side walls, floor and top)."""
        u, v, z = self.project(p)
        cam = self.camera
        ok = (z > 1e-3) & (u >= -0.5) & (u < cam.width - 0.5) & (v >= -0.5) & (v < cam.height - 0.5)
        e = self._eye
        s = (-0.5 * self.size[1] - e[1]) / np.where(np.abs(p[..., 1] - e[1]) < 1e-12, 1e-12, p[..., 1] - e[1])
        x = e[0] + s * (p[..., 0] - e[0])
        zc = e[2] + s * (p[..., 2] - e[2])
        return ok & (np.abs(x) <= 0.5 * self.size[0]) & (zc >= 0) & (zc <= self.size[2])


@dataclass(frozen=True, eq=False)
class Prisms:
    """Vertical prisms as arrays: footprint centres (n, 2), half-extents (n, 2) and corner radii
    (n,) of their rounded rectangles, heights (n,)."""

    center: np.ndarray
    half: np.ndarray
    radius: np.ndarray
    height: np.ndarray

    @staticmethod
    def of(objects) -> "Prisms":
        n = len(objects)
        center, half = np.zeros((n, 2)), np.zeros((n, 2))
        radius, height = np.zeros(n), np.zeros(n)
        for k, o in enumerate(objects):
            center[k] = o.x, o.y
            height[k] = o.height
            if o.kind == "box":
                half[k] = 0.5 * o.width, 0.5 * o.depth
            else:
                radius[k] = 0.5 * o.width
        return Prisms(center, half, radius, height)

    def __len__(self) -> int:
        return len(self.radius)

    @property
    def extent(self) -> np.ndarray:
        """Half-extents (n, 2) of the footprints' bounding boxes."""
        return self.half + self.radius[:, None]

    def take(self, index) -> "Prisms":
        return Prisms(self.center[index], self.half[index], self.radius[index], self.height[index])

    def footprints(self, circumscribed: bool = False) -> np.ndarray:
        """The footprints as shapely polygons (n,); a cylinder's circle becomes a regular
        CIRCLE_SIDES-gon, inscribed (inside the circle) or circumscribed (around it)."""
        out = np.empty(len(self), object)
        box = self.radius == 0
        lo, hi = self.center - self.half, self.center + self.half
        out[box] = shapely.box(lo[box, 0], lo[box, 1], hi[box, 0], hi[box, 1])
        if (~box).any():
            out[~box] = circle_polygons(self.center[~box], self.radius[~box], circumscribed)
        return out


def circle_polygons(center: np.ndarray, radius: np.ndarray, circumscribed: bool = False) -> np.ndarray:
    """Regular CIRCLE_SIDES-gons (shapely, (n,)) for circles (centres (n, 2), radii (n,))."""
    a = np.linspace(0, 2 * np.pi, CIRCLE_SIDES + 1)
    a[-1] = 0.0
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    if circumscribed:
        ring = ring / math.cos(math.pi / CIRCLE_SIDES)
    return shapely.polygons(center[:, None, :] + radius[:, None, None] * ring[None])


def overlap(c1, h1, r1, c2, h2, r2, tol: float = 1e-6) -> np.ndarray:
    """Bool (broadcast): rounded rectangles (centre, half-extents, radius) overlap by more than `tol`."""
    A = np.abs(c2 - c1) - (h1 + h2)
    R = r1 + r2
    d = np.hypot(np.maximum(A[..., 0], 0.0), np.maximum(A[..., 1], 0.0))
    return (d < R - tol) | ((A[..., 0] < -tol) & (A[..., 1] < -tol))


def contact_distance(c_move, h_move, r_move, c_fix, h_fix, r_fix, direction: float) -> np.ndarray:
    """How far (broadcast, >= 0, inf if never) a rounded rectangle moving along `direction` * x
    travels before it touches a fixed one; bodies behind it or beside it give inf."""
    dx = direction * (c_fix[..., 0] - c_move[..., 0])
    dy = np.abs(c_fix[..., 1] - c_move[..., 1])
    A = h_move[..., 0] + h_fix[..., 0]
    B = h_move[..., 1] + h_fix[..., 1]
    R = r_move + r_fix
    over = np.clip(dy - B, 0.0, None)
    reach = np.where(over < R, np.sqrt(np.clip(R * R - over * over, 0.0, None)), -np.inf)
    reach = np.where(dy <= B, R, reach)  # beside the flat part: the full radius
    gap = dx - A - reach
    return np.where(np.isfinite(reach) & (dx > 0) & (gap > -1e-6), np.maximum(gap, 0.0), np.inf)


def occlusion_matrix(eye: np.ndarray, points: np.ndarray, prisms: Prisms) -> np.ndarray:
    """Bool (P, n): the segment from `eye` to point p (P, 3) passes through prism i (the end point
    itself excluded). Vectorised slab tests (boxes) and circle intersections (cylinders); the
    segment's lowest point inside a footprint decides whether it passes under the prism's top. The
    eye must be above every prism (as the shelf camera is)."""
    P, n = len(points), len(prisms)
    out = np.zeros((P, n), bool)
    if n == 0 or P == 0:
        return out
    if np.any(prisms.height >= eye[2]):
        raise ValueError(f"occlusion: the eye at z={eye[2]:.3f} must be above every prism "
                         f"(tallest {prisms.height.max():.3f})")
    tall = prisms.height > points[:, 2].min()  # a segment descends: lower prisms pass beneath it
    o = eye[:2]
    D = points[:, :2] - o  # (P, 2)
    dz = (points[:, 2] - eye[2])[:, None]
    end = 1.0 - 1e-9

    def blocked(s_in, s_out, h):
        b = np.minimum(s_out, end)
        return (np.maximum(s_in, 0.0) < b) & (eye[2] + b * dz < h[None])

    box = tall & (prisms.radius == 0)
    if box.any():
        lo = prisms.center[box] - prisms.half[box]
        hi = prisms.center[box] + prisms.half[box]
        s_in, s_out = None, None
        for ax in (0, 1):
            d = D[:, ax]
            inv = (1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d))[:, None]
            t1 = (lo[None, :, ax] - o[ax]) * inv
            t2 = (hi[None, :, ax] - o[ax]) * inv
            lo_t, hi_t = np.minimum(t1, t2), np.maximum(t1, t2)
            s_in = lo_t if s_in is None else np.maximum(s_in, lo_t)
            s_out = hi_t if s_out is None else np.minimum(s_out, hi_t)
        out[:, box] = blocked(s_in, s_out, prisms.height[box])
    cyl = tall & (prisms.radius > 0)
    if cyl.any():
        c = prisms.center[cyl]
        r = prisms.radius[cyl]
        f = o - c  # (nc, 2)
        a = np.einsum("pi,pi->p", D, D)[:, None]
        b = 2.0 * D @ f.T  # (P, nc)
        cc = np.einsum("ci,ci->c", f, f) - r * r
        disc = b * b - 4 * a * cc[None]
        sq = np.sqrt(np.clip(disc, 0.0, None))
        hit = disc > 0
        s_in = np.where(hit, (-b - sq) / (2 * a), np.inf)
        s_out = np.where(hit, (-b + sq) / (2 * a), -np.inf)
        out[:, cyl] = blocked(s_in, s_out, prisms.height[cyl])
    return out


def occluded(eye: np.ndarray, points: np.ndarray, prisms: Prisms) -> np.ndarray:
    """Bool (P,): the segment from `eye` to each point (P, 3) passes through some prism."""
    return occlusion_matrix(eye, points, prisms).any(axis=1)


def surface_points(geometry: ShelfGeometry, prisms: Prisms, m: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Points on the camera-facing surfaces of prisms: (n, 3 m^2, 3) points and (n, 3 m^2) validity.
    A box: m x m cell centres on its top, its front (-y) and the side facing the camera (if any);
    a cylinder: m^2 points on its top disc and m x m on the half of its mantle facing the camera."""
    n = len(prisms)
    K = 3 * m * m
    pts = np.zeros((n, K, 3))
    valid = np.zeros((n, K), bool)
    g = (np.arange(m) + 0.5) / m
    a, b = (v.ravel() for v in np.meshgrid(g, g))  # m^2 fractions in (0, 1)
    eye = geometry.eye
    for k in range(n):
        cx, cy = prisms.center[k]
        h = prisms.height[k]
        faces = []
        if prisms.radius[k] == 0:
            hx, hy = prisms.half[k]
            x, y = cx - hx + 2 * hx * a, cy - hy + 2 * hy * b
            faces.append(np.stack([x, y, np.full(m * m, h)], 1))  # top
            faces.append(np.stack([x, np.full(m * m, cy - hy), h * b], 1))  # front
            if abs(eye[0] - cx) > hx:
                sx = cx + np.sign(eye[0] - cx) * hx
                faces.append(np.stack([np.full(m * m, sx), cy - hy + 2 * hy * a, h * b], 1))
        else:
            r = prisms.radius[k]
            rho, phi = r * np.sqrt(a), 2 * np.pi * b  # area-uniform on the disc
            faces.append(np.stack([cx + rho * np.cos(phi), cy + rho * np.sin(phi), np.full(m * m, h)], 1))
            toward = np.arctan2(eye[1] - cy, eye[0] - cx)
            th = toward + (a - 0.5) * np.pi
            faces.append(np.stack([cx + r * np.cos(th), cy + r * np.sin(th), h * b], 1))
        f = np.concatenate(faces)
        pts[k, :len(f)] = f
        valid[k, :len(f)] = True
    return pts, valid


def visible_surface(geometry: ShelfGeometry, prisms: Prisms, m: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """surface_points and which of them the camera sees ((n, K) bool): in view and not occluded by
    any *other* prism."""
    pts, valid = surface_points(geometry, prisms, m)
    n, K = valid.shape
    flat = pts.reshape(-1, 3)
    occ = occlusion_matrix(geometry.eye, flat, prisms).reshape(n, K, n)
    occ[np.arange(n), :, np.arange(n)] = False  # an object does not hide its own camera-facing surface
    seen = valid & geometry.in_view(pts) & ~occ.any(axis=2)
    return pts, seen


def box_corners(center: np.ndarray, size) -> np.ndarray:
    """(..., 8, 3) corners of boxes standing on the floor: footprint centres (..., 2), size (w, d, h)."""
    w, d, h = size
    s = np.array([[sx * w / 2, sy * d / 2, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, h)])
    c = np.concatenate([center, np.zeros(center.shape[:-1] + (1,))], axis=-1)
    return c[..., None, :] + s


def target_view_points(geometry: ShelfGeometry, target: ShelfObject, samples: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The points visible_fraction casts rays to: `samples` x `samples` on each camera-facing face
    of the target box (P, 3), and their weights (P,), each face's projected area shared by its points."""
    if target.kind != "box":
        raise ValueError(f"visible_fraction: target {target.id!r} is a {target.kind}; targets are boxes")
    eye = geometry.eye
    half = np.array([target.width, target.depth, target.height]) / 2
    center = np.array([target.x, target.y, half[2]])
    g = (np.arange(samples) + 0.5) / samples * 2 - 1
    gu, gv = np.meshgrid(g, g)
    pts, weights = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            fc = center + sign * half * n
            if np.dot(eye - fc, n) <= 0:
                continue
            u_ax, v_ax = [a for a in range(3) if a != axis]
            eu, ev = np.eye(3)[u_ax] * half[u_ax], np.eye(3)[v_ax] * half[v_ax]
            quad = np.array([fc - eu - ev, fc + eu - ev, fc + eu + ev, fc - eu + ev])
            u, v, _ = geometry.project(quad)
            area = 0.5 * abs(np.dot(u, np.roll(v, 1)) - np.dot(v, np.roll(u, 1)))
            p = fc + gu.reshape(-1, 1) * eu + gv.reshape(-1, 1) * ev
            pts.append(p)
            weights.append(np.full(len(p), area / len(p)))
    return np.concatenate(pts), np.concatenate(weights)


def visible_fraction(geometry: ShelfGeometry, target: ShelfObject, occluders: Prisms, samples: int = 8) -> float:
    """Fraction of the target's image area (its amodal silhouette) that the camera sees: points on
    each camera-facing face, weighted by the face's projected area (target_view_points), ray cast
    against the occluders (points out of view count as hidden). The target must be a box."""
    p, w = target_view_points(geometry, target, samples)
    seen = geometry.in_view(p) & ~occluded(geometry.eye, p, occluders)
    return float(np.dot(w, seen) / w.sum()) if w.sum() > 0 else 0.0


def coverage(spans: np.ndarray, width: int, weights: np.ndarray | None = None) -> np.ndarray:
    """(width,) how many of the column intervals `spans` (M, 2) cover each image column (optionally weighted)."""
    lo = np.clip(np.floor(spans[:, 0] + 0.5).astype(int), 0, width)
    hi = np.clip(np.floor(spans[:, 1] + 0.5).astype(int) + 1, 0, width)
    w = np.ones(len(spans)) if weights is None else weights
    diff = np.bincount(lo, w, minlength=width + 1) - np.bincount(hi, w, minlength=width + 1)
    return np.cumsum(diff[:width])


@dataclass(frozen=True, eq=False)
class FloorGrid:
    """Points (x0 + j * step, y0 + i * step), i < ny, j < nx, covering the shelf floor."""

    x0: float
    y0: float
    step: float
    nx: int
    ny: int

    @staticmethod
    def of(geometry: ShelfGeometry, step: float) -> "FloorGrid":
        if not step > 0:
            raise ValueError(f"grid step={step}: must be > 0 (e.g. 0.005 m)")
        hx, hy = geometry.half
        nx, ny = int(math.floor(2 * hx / step + 1e-9)) + 1, int(math.floor(2 * hy / step + 1e-9)) + 1
        return FloorGrid(-hx, -hy, step, nx, ny)

    def xy(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x0 + self.step * np.arange(self.nx), self.y0 + self.step * np.arange(self.ny)

    def points(self, mask: np.ndarray) -> np.ndarray:
        i, j = np.nonzero(mask)
        return np.stack([self.x0 + self.step * j, self.y0 + self.step * i], axis=1)


@dataclass(frozen=True, eq=False)
class HiddenPlacements:
    """Footprint centres (M, 2) where a target of `size` would be fully hidden and in view, as
    points of `grid` (`mask` (ny, nx)); `candidates` counts the centres left by the 2D step."""

    size: tuple[float, float, float]
    grid: FloorGrid
    mask: np.ndarray
    candidates: int

    @property
    def centers(self) -> np.ndarray:
        return self.grid.points(self.mask)

    def floor_distribution(self) -> np.ndarray:
        m = self.mask.astype(float)
        s = m.sum()
        return m / s if s > 0 else m

    def occupancy(self, geometry: ShelfGeometry) -> ShelfOccupancy:
        """The floor and image-x distributions as a ShelfOccupancy."""
        g = self.grid
        return ShelfOccupancy(self.floor_distribution(), self.image_x_distribution(geometry), g.x0, g.y0, g.step)

    def image_x_distribution(self, geometry: ShelfGeometry) -> np.ndarray:
        """P(x) over image columns: each placement covers the columns of its projected box."""
        c = self.centers
        width = geometry.camera.width
        if len(c) == 0:
            return np.zeros(width)
        u, _, _ = geometry.project(box_corners(c, self.size))
        cov = coverage(np.stack([u.min(axis=1), u.max(axis=1)], axis=1), width)
        return cov / cov.sum()


def _shadow_hulls(eye: np.ndarray, footprints: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Convex hulls of each footprint and its copy scaled by `scale` (n,) about the eye's floor point."""
    pts, idx = shapely.get_coordinates(footprints, return_index=True)
    o = eye[:2]
    far = o + (pts - o) * scale[idx, None]
    allp, alli = np.concatenate([pts, far]), np.concatenate([idx, idx])
    order = np.argsort(alli, kind="stable")
    return shapely.convex_hull(shapely.multipoints(allp[order], indices=alli[order]))


def visibility_polygon(geometry: ShelfGeometry, footprints: np.ndarray):
    """The part of the floor the camera sees with the objects as walls of infinite height (2D)."""
    hx, hy = geometry.half
    floor = shapely.box(-hx, -hy, hx, hy)
    if len(footprints) == 0:
        return floor
    ex, ey = geometry.eye[:2]
    reach = 2.0 * np.hypot(hx + abs(ex), hy - ey) / (-hy - ey)  # scaled copies land beyond the shelf
    shadows = _shadow_hulls(geometry.eye, footprints, np.full(len(footprints), reach))
    return shapely.difference(floor, shapely.union_all(shadows))


def _minkowski_with_box(polygon, half: np.ndarray):
    """polygon + [-a, a] x [-b, b] (exact: the polygon and the hulls of its edges swept by the box)."""
    if polygon.is_empty:
        return polygon
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
    rings = shapely.get_rings(shapely.get_parts(polygon))
    segs = []
    for r in rings:
        c = shapely.get_coordinates(r)
        segs.append(np.stack([c[:-1], c[1:]], axis=1))
    seg = np.concatenate(segs)  # (E, 2, 2)
    pts = (seg[:, :, None, :] + corners[None, None]).reshape(len(seg), 8, 2)
    hulls = shapely.convex_hull(shapely.multipoints(pts))
    return shapely.union_all(np.concatenate([[polygon], hulls]))


def hidden_placements(geometry: ShelfGeometry, occluders: Prisms, size, step: float = 0.005,
                      clearance: float = 0.003) -> HiddenPlacements:
    """Where a box target of `size` (w, d, h) could stand, `clearance` away from the walls and the
    occluders, fully hidden from the camera and fully in its view (module docstring, steps 1-3)."""
    w, d, h = (float(v) for v in size)
    grid = FloorGrid.of(geometry, step)
    xs, ys = grid.xy()
    half = np.array([w / 2, d / 2])
    room = geometry.half - half - clearance
    X, Y = np.meshgrid(xs, ys)
    cand = (np.abs(X) <= room[0] + 1e-9) & (np.abs(Y) <= room[1] + 1e-9)
    if len(occluders) == 0 or not cand.any():
        return HiddenPlacements((w, d, h), grid, np.zeros_like(cand), 0)
    # Step 2 for the objects: the target's footprint grown by the clearance overlaps one (closed
    # form, on the block of the grid around each object).
    grown = half + clearance
    for k in range(len(occluders)):
        lo = occluders.center[k] - occluders.extent[k] - grown
        hi = occluders.center[k] + occluders.extent[k] + grown
        j0, j1 = np.searchsorted(xs, [lo[0], hi[0]])
        i0, i1 = np.searchsorted(ys, [lo[1], hi[1]])
        if i0 >= i1 or j0 >= j1:
            continue
        block = np.stack(np.meshgrid(xs[j0:j1], ys[i0:i1]), axis=-1)
        hit = overlap(block, grown, 0.0, occluders.center[k], occluders.half[k], occluders.radius[k], tol=0.0)
        cand[i0:i1, j0:j1] &= ~hit
    ci, cj = np.nonzero(cand)
    # Steps 1-2: outside the visibility polygon's Minkowski sum with the footprint. Circumscribed
    # circles: this step may keep too many candidates for the ray casts, never too few.
    vis = visibility_polygon(geometry, occluders.footprints(circumscribed=True))
    excluded = _minkowski_with_box(vis, half)
    shapely.prepare(excluded)
    seen = shapely.contains_xy(excluded, xs[cj], ys[ci])
    cand[ci[seen], cj[seen]] = False
    n_cand = int(cand.sum())
    if n_cand == 0:
        return HiddenPlacements((w, d, h), grid, cand, 0)
    # Step 3: ray casts to the top-face points of every candidate, once per grid point.
    ka, kb = (int(math.ceil(v / step - 1e-6)) for v in half)
    kernel = np.ones((2 * kb + 1, 2 * ka + 1), np.uint8)
    face = cv2.dilate(cand.astype(np.uint8), kernel).astype(bool)
    fi, fj = np.nonzero(face)
    pts = np.stack([xs[fj], ys[fi], np.full(len(fi), h)], axis=1)
    hid = np.zeros_like(face)
    hid[fi, fj] = occluded(geometry.eye, pts, occluders)
    hidden = cand & cv2.erode(hid.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
    # The whole target in view: its corners are (view and target are convex).
    hi_, hj = np.nonzero(hidden)
    if len(hi_):
        corners = box_corners(np.stack([xs[hj], ys[hi_]], axis=1), (w, d, h))
        ok = geometry.in_view(corners).all(axis=1)
        hidden[hi_[~ok], hj[~ok]] = False
    return HiddenPlacements((w, d, h), grid, hidden, n_cand)


def exactly_hidden(geometry: ShelfGeometry, occluders: Prisms, center, size, margin: float = 0.002) -> bool:
    """True if a box target of `size` at footprint centre `center` is hidden with `margin` to spare
    (its footprint grown by `margin`, its top raised by it) and entirely in view; no sampling (see
    the module docstring)."""
    w, d, h = (float(v) for v in size)
    c = np.asarray(center, float)
    if not geometry.in_view(box_corners(c, (w, d, h))).all():
        return False
    top = h + margin
    ez = geometry.eye[2]
    tall = occluders.height > top
    if not tall.any():
        return False
    sub = occluders.take(tall)
    sigma = (ez - sub.height) / (ez - top)
    scale = np.where(sigma > 1e-3, 1.0 / np.maximum(sigma, 1e-3), 1e3)
    shade = shapely.union_all(_shadow_hulls(geometry.eye, sub.footprints(), scale))
    a, b = w / 2 + margin, d / 2 + margin
    return bool(shapely.contains(shade, shapely.box(c[0] - a, c[1] - b, c[0] + a, c[1] + b)))
