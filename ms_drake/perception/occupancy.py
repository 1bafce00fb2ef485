"""Target occupancy distribution (Ch. 8.3, lines 1437-1480): the `OccupancyEstimator` LeafSystem.

The occupancy distribution rho (H, W) gives, per pixel, how likely the target's amodal mask
covers it given the observation. Backends share one interface, ``estimate(depth, target_mask)
-> (H, W) float`` (sums to 1, or all 0), so the learned network of a later issue plugs in.

``AnalyticOccupancy`` -- the ground-truth generator of Ch. 8.3.1. The target is a box of the
given size lying flat (thickness along the world z; the reference's dataset targets), or any
object given as a ``TargetMesh``: its own mesh in its resting orientation (in simulation, the
heap's true pose), whose silhouette (`mesh_silhouette`) is shifted and turned
like the box's, its height above the floor playing the box's thickness. Rotation bin 0 is the
given orientation and, with a known position, the grid is shifted (by less than a stride) so the
true placement is one of the placements: a visible target then always has at least its own
placement to match, up to the shift approximation below. Its placements are a 64 x 48 grid of
image translations (the reference: every 8 px of its 512 x 384 images; here the grid scales with
the image: every 10 px of 640 x 480) times 16 yaw rotations. Rotations span [0, pi) because the
box looks the same turned by pi (the reference does not say; 16 bins over 2 pi would count
every placement twice). A placement's modal mask is the part of the target that would be seen:
pixels of its silhouette where the observed surface is not above the target's top
(height(p) <= thickness + `height_tolerance`, heights from the depth image deprojected to the
world, above the bin floor). Placements whose modal mask matches the observed target modal
mask (IoU > 0.9, or both empty) are kept; their amodal masks (the silhouettes) are summed and
normalized. Choices where the text is silent (recorded here):
  * placements are restricted to the bin: the box centre's floor point (under the grid pixel)
    must lie inside the bin's inner box shrunk by half the box's short side -- the target is in
    the bin, and the bin walls would otherwise look like hiding places;
  * as in the reference, a placement is "shifted and rotated" in the image: the silhouette is
    computed once per rotation (the box placed under the principal point, projected with the
    camera; pixels whose centre falls inside, as a renderer samples them) and translated; the
    visible surface of the box is its top face;
  * a placement may overlap objects (the test is the image, not physics), as in the reference;
  * a TargetMesh pixel counts as seen where the observed surface is not above the target's
    highest point (its height in the resting orientation): one threshold for the whole
    silhouette, as for the box, so an occluder resting lower than the target's top on the
    target's own footprint is not told apart (rare; per-pixel heights would multiply the runs);
  * when the target is visible but no placement matches (the shift approximation far from the
    image centre, or a target that moved since the generator was built), the distribution falls
    back to the observed modal mask rather than all zeros ("when the object is fully visible,
    the distribution's support collapses to ... the modal segmentation mask").

Speed (the reference: 1.5 s per image): every silhouette is stored as row runs [x0, x1]. With
S the row-wise prefix sums of the "would be visible" image V (packed with V & M in one int32,
V + 2^16 (V & M)), the modal area and the intersection with the observed mask M of a
placement are sums of S[y, x1 + 1] - S[y, x0] over its runs: exact, and one vectorized gather
for all placements (placements that cannot match are skipped: a hidden target's centre pixel must
not see the floor; a seen target's silhouette must reach the observed mask). Silhouettes with
fewer columns than rows are stored as column runs (prefix sums of the transposed image). The sum
of the matched amodal masks is a difference image of the runs' endpoints integrated along rows.
tests/test_occupancy.py checks that all of this equals shifting every silhouette pixel by
pixel. sims/bench_occupancy.py measures it against `RenderedOccupancy`, the straightforward
implementation that renders a target-only depth image (Drake's VTK RgbdSensor) per placement.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from pydrake.common.value import AbstractValue
from pydrake.geometry import Box
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.tree import SpatialInertia, UnitInertia
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.sensors import ApplyCameraConfig, ImageDepth32F

from ms_drake.errors import PerceptionError
from ms_drake.geometry import PinholeCamera, Workspace, as_matrix4, depth_array, preprocess_depth
from ms_drake.objects import get_object
from ms_drake.perception.occupancy_net import LearnedOccupancy
from ms_drake.types import OccupancyMap, TargetEstimate


@dataclass(frozen=True)
class TargetBox:
    """Box target lying flat: `length` >= `width` in the floor plane, `thickness` along z [m]."""

    length: float
    width: float
    thickness: float

    def __post_init__(self):
        if min(self.length, self.width, self.thickness) <= 0 or self.width > self.length:
            raise PerceptionError(f"TargetBox{(self.length, self.width, self.thickness)}: give positive sizes "
                                  "with length >= width (metres), e.g. TargetBox(0.06, 0.03, 0.005)")

    @staticmethod
    def of(size) -> "TargetBox":
        """From a (length, width, thickness) triple (length and width are sorted)."""
        if isinstance(size, TargetBox):
            return size
        s = [float(v) for v in size]
        if len(s) != 3:
            raise PerceptionError(f"target size {size!r}: give (length, width, thickness) in metres")
        a, b = sorted(s[:2], reverse=True)
        return TargetBox(a, b, s[2])

    @staticmethod
    def from_object(full_name: str) -> "TargetBox":
        """The bounding box of a registry object lying on its largest face."""
        a, b, c = sorted(get_object(full_name).extents, reverse=True)
        return TargetBox(a, b, c)

    def mesh_vertices_faces(self):
        m = trimesh.creation.box(extents=(self.length, self.width, self.thickness))
        return np.asarray(m.vertices), np.asarray(m.faces)


@dataclass(frozen=True, eq=False)
class TargetMesh:
    """A target of any shape in a resting orientation (Ch. 8.3.1 renders "a target-only depth
    image" of the target itself). vertices (V, 3) / faces (F, 3): its surface in its own frame;
    R_WO: its orientation in the world, rotation bin 0 (the other bins turn it about the world
    z); p_WO: its position when known (simulation: the heap's true pose), which aligns the
    translation grid so that the true placement is one of the placements (None: the plain grid).
    The placement's anchor is the object frame's origin; the target rests on the floor (its
    lowest vertex at the floor)."""

    vertices: np.ndarray
    faces: np.ndarray
    R_WO: np.ndarray
    p_WO: np.ndarray | None = None

    def __post_init__(self):
        v, f, R = np.asarray(self.vertices, float), np.asarray(self.faces), np.asarray(self.R_WO, float)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 4 or f.ndim != 2 or f.shape[1] != 3 or R.shape != (3, 3) \
                or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise PerceptionError("TargetMesh needs vertices (V >= 4, 3), faces (F, 3) and a 3x3 rotation R_WO; "
                                  "build it with TargetMesh.from_object(full_name, X_WO)")

    @staticmethod
    def from_object(full_name: str, X_WO=None) -> "TargetMesh":
        """The registry object's mesh; X_WO (4x4 or RigidTransform): its pose (default: as modelled)."""
        m = get_object(full_name).trimesh()
        X = np.eye(4) if X_WO is None else as_matrix4(X_WO, "X_WO")
        return TargetMesh(np.asarray(m.vertices, float), np.asarray(m.faces), X[:3, :3],
                          None if X_WO is None else X[:3, 3].copy())


def _yaw(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def floor_points(camera: PinholeCamera, u: np.ndarray, v: np.ndarray, z: float) -> np.ndarray:
    """World points (N, 3) where the rays through pixels (u, v) meet the plane z."""
    d_C = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u, float)], axis=-1)
    R = camera.X_WC.rotation().matrix()
    o = camera.X_WC.translation()
    d_W = d_C @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z - o[2]) / d_W[:, 2]
    t = np.where(t > 0, t, np.nan)
    return o + t[:, None] * d_W


def convex_silhouette(camera: PinholeCamera, vertices_W: np.ndarray) -> np.ndarray:
    """(H, W) bool silhouette of a convex body (all vertices in front of the camera): the pixels
    whose centre lies inside the convex hull of the projected vertices -- the pixel-centre rule
    of a renderer, so a small target's mask is not grown by the rasterizer's edge pixels."""
    uv, z = camera.project(vertices_W)
    if np.any(z <= 1e-3):
        raise PerceptionError("the target box must lie in front of the camera")
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(float)  # counter-clockwise in image
    lo = np.maximum(np.floor(hull.min(axis=0)).astype(int), 0)
    hi = np.minimum(np.ceil(hull.max(axis=0)).astype(int) + 1, [camera.width, camera.height])
    mask = np.zeros((camera.height, camera.width), bool)
    if np.any(hi <= lo):
        return mask
    v, u = np.mgrid[lo[1]:hi[1], lo[0]:hi[0]]
    inside = np.ones(u.shape, bool)
    a, b = hull, np.roll(hull, -1, axis=0)
    area = np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1])
    sign = 1.0 if area > 0 else -1.0
    for (x0, y0), (x1, y1) in zip(a, b):
        inside &= sign * ((x1 - x0) * (v - y0) - (y1 - y0) * (u - x0)) >= 0
    mask[lo[1]:hi[1], lo[0]:hi[0]] = inside
    return mask


def mesh_silhouette(camera: PinholeCamera, vertices_W: np.ndarray, faces: np.ndarray, supersample: int = 4) -> np.ndarray:
    """(H, W) bool silhouette of a mesh (in front of the camera) by the area rule: pixels at least
    half covered, from a `supersample`-times finer rasterization of its triangles (a renderer's
    pixel-centre rule within 1 / supersample pixel; masks.silhouette fills every pixel a triangle
    touches, a 1-px wider mask, i.e. ~10 % more pixels for a 3 x 8 cm target 0.8 m away)."""
    uv, z = camera.project(vertices_W)
    if np.any(z <= 1e-3):
        raise PerceptionError("the target must lie in front of the camera")
    k = int(supersample)
    lo = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, [camera.width, camera.height])
    mask = np.zeros((camera.height, camera.width), bool)
    if np.any(hi <= lo):
        return mask
    w, h = hi - lo
    fine = np.zeros((h * k, w * k), np.uint8)
    # Fine pixel (i, j) has its centre at fine coordinate (i, j); image pixel u spans fine pixels
    # k u .. k u + k - 1, whose middle is k u + (k - 1) / 2.
    pts = np.round(((uv - lo) * k + (k - 1) / 2.0) * 16).astype(np.int32)
    for tri in pts[faces]:
        cv2.fillConvexPoly(fine, tri, 1, lineType=cv2.LINE_8, shift=4)
    cover = fine.reshape(h, k, w, k).mean(axis=(1, 3))
    mask[lo[1]:hi[1], lo[0]:hi[0]] = cover >= 0.5
    return mask


def _runs(mask: np.ndarray, anchor: tuple[int, int]) -> np.ndarray:
    """Row runs (dy, dx0, dx1) (inclusive ends) of a bool mask relative to pixel `anchor` = (u, v)."""
    d = np.diff(np.pad(mask.astype(np.int8), ((0, 0), (1, 1))), axis=1)
    ys, x0 = np.nonzero(d == 1)  # row-major order: the starts and ends of a row pair up in order
    _, x1 = np.nonzero(d == -1)
    return np.stack([ys - anchor[1], x0 - anchor[0], x1 - 1 - anchor[0]], axis=1).astype(np.int64)


@dataclass(frozen=True)
class OccupancyGrid:
    """The placements: `grid` = (columns, rows) of image translations, `rotations` yaw bins over [0, pi)."""

    grid: tuple[int, int] = (64, 48)
    rotations: int = 16
    offset: tuple[int, int] = (0, 0)  # pixels (u, v) added to every node, within half a stride

    def strides(self, width: int, height: int) -> tuple[int, int]:
        return max(width // self.grid[0], 1), max(height // self.grid[1], 1)

    def pixels(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Grid pixel coordinates (u (cols,), v (rows,)): stride W // cols, centred, + offset."""
        gw, gh = self.grid
        if gw < 1 or gh < 1 or self.rotations < 1:
            raise PerceptionError(f"occupancy grid {self.grid} x {self.rotations} rotations: all must be >= 1")
        sx, sy = self.strides(width, height)
        if not (-(sx // 2) <= self.offset[0] <= (sx - 1) // 2 and -(sy // 2) <= self.offset[1] <= (sy - 1) // 2):
            raise PerceptionError(f"occupancy grid offset {self.offset}: keep it within half a stride ({sx}, {sy})")
        ox, oy = (width - sx * gw) // 2 + sx // 2, (height - sy * gh) // 2 + sy // 2
        return ox + self.offset[0] + sx * np.arange(gw), oy + self.offset[1] + sy * np.arange(gh)

    def aligned(self, u: float, v: float, width: int, height: int) -> "OccupancyGrid":
        """This grid shifted (by less than half a stride) so that pixel (u, v) is a node."""
        sx, sy = self.strides(width, height)
        base = OccupancyGrid(self.grid, self.rotations)
        us, vs = base.pixels(width, height)
        dx = int((round(u) - us[0] + sx // 2) % sx - sx // 2)
        dy = int((round(v) - vs[0] + sy // 2) % sy - sy // 2)
        return OccupancyGrid(self.grid, self.rotations, (dx, dy))

    def angles(self) -> np.ndarray:
        return np.pi * np.arange(self.rotations) / self.rotations


def _valid_placements(camera, workspace, box: TargetBox, grid: OccupancyGrid, anchor_height: float | None = None,
                      margin: float | None = None):
    """Grid pixels (u, v), anchor points (N, 3) and flat grid indices of the placements in the bin
    (anchor: the box centre, or a TargetMesh's origin at `anchor_height` above the floor, kept
    `margin` inside the walls; defaults: the box's half thickness and half width)."""
    us, vs = grid.pixels(camera.width, camera.height)
    U, Vv = np.meshgrid(us, vs)
    p = floor_points(camera, U.ravel().astype(float), Vv.ravel().astype(float),
                     workspace.floor_z + (0.5 * box.thickness if anchor_height is None else anchor_height))
    ok = np.all(np.isfinite(p), axis=1)
    ok[ok] = workspace.inside_xy(p[ok], margin=0.5 * box.width if margin is None else margin)
    return U.ravel()[ok], Vv.ravel()[ok], p[ok], np.flatnonzero(ok)


BEST_MATCH_MIN = 0.5  # AnalyticOccupancy(best_match=...): the least IoU a kept placement may have


class AnalyticOccupancy:
    """Ground-truth occupancy generator (see the module doc). Precomputes the placements and the
    per-rotation silhouettes once for a camera, workspace and target: a TargetBox (or its size)
    lying flat, or a TargetMesh (the target's own mesh in its resting orientation)."""

    name = "analytic"

    def __init__(self, camera: PinholeCamera, workspace: Workspace, target_size, grid: OccupancyGrid = OccupancyGrid(),
                 iou_threshold: float = 0.9, height_tolerance: float = 0.003, best_match: float | None = None):
        """best_match: when the target is seen and no placement passes `iou_threshold` (a partly
        covered target off the grid's 10 px / 11.25 degree steps), keep the placements whose IoU
        is within `best_match` of the best one (the best at least BEST_MATCH_MIN) instead of
        falling back to the observed modal mask; None: the fallback."""
        if best_match is not None and not 0.0 <= best_match < 1.0:
            raise PerceptionError(f"best_match={best_match!r}: give a margin in [0, 1) (e.g. 0.05) or None")
        self.camera, self.workspace = camera, workspace
        self.iou_threshold, self.height_tolerance = float(iou_threshold), float(height_tolerance)
        self.best_match = best_match
        self.mesh = target_size if isinstance(target_size, TargetMesh) else None
        anchor = (int(round(camera.cx)), int(round(camera.cy)))
        au, av = np.array([float(anchor[0])]), np.array([float(anchor[1])])
        if self.mesh is None:
            self.box = TargetBox.of(target_size)
            anchor_height, margin, self.top = 0.5 * self.box.thickness, 0.5 * self.box.width, self.box.thickness
            c = floor_points(camera, au, av, workspace.floor_z + anchor_height)[0]
            verts, _ = self.box.mesh_vertices_faces()
            self.angles = grid.angles()
            sils = [convex_silhouette(camera, verts @ _yaw(theta).T + c) for theta in self.angles]
        else:
            m = self.mesh
            V = np.asarray(m.vertices, float) @ np.asarray(m.R_WO, float).T  # resting, origin at 0
            anchor_height = float(-V[:, 2].min())
            ext = np.ptp(V, axis=0)
            self.box = TargetBox.of((ext[0], ext[1], ext[2]))  # its bounding box, for reference
            margin, self.top = 0.5 * float(min(ext[0], ext[1])), float(ext[2])
            c = floor_points(camera, au, av, workspace.floor_z + anchor_height)[0]
            faces = np.asarray(m.faces)

            def sil_at(theta):
                return mesh_silhouette(camera, V @ _yaw(theta).T + c, faces)

            # Turned by pi the target looks the same (boxes, cylinders)? Then [0, pi) as for
            # boxes, else the bins span [0, 2 pi) (our choice; the text says 16 bins).
            s0, s1 = sil_at(0.0), sil_at(np.pi)
            symmetric = (s0 & s1).sum() / max((s0 | s1).sum(), 1) > 0.95
            self.angles = grid.angles() * (1.0 if symmetric else 2.0)
            sils = [sil_at(theta) for theta in self.angles]
            if grid.offset == (0, 0) and m.p_WO is not None:
                uv, _ = camera.project(np.asarray(m.p_WO, float)[None])
                grid = grid.aligned(uv[0, 0], uv[0, 1], camera.width, camera.height)
        self.grid = grid
        self.gu, self.gv, _, self.grid_index = _valid_placements(camera, workspace, self.box, grid, anchor_height,
                                                                 margin)
        if len(self.gu) == 0:
            raise PerceptionError("AnalyticOccupancy: no placement of the target lies inside the bin in this camera's "
                                  "view; check the camera pose and the workspace")
        # Silhouette of the target under the principal point, per rotation, as runs: row runs, or
        # column runs when a silhouette has fewer columns than rows (an elongated target turned
        # near 90 degrees); a column run is stored as a row run of the transposed image.
        runs, self.transposed = [], np.zeros(len(self.angles), bool)
        for r, sil in enumerate(sils):
            rows, cols = _runs(sil, anchor), _runs(sil.T, anchor[::-1])
            self.transposed[r] = len(cols) < len(rows)
            runs.append(cols if self.transposed[r] else rows)
        self.runs_by_rotation = runs
        self.runs = np.concatenate(runs)
        self.run_transposed = np.concatenate([np.full(len(rr), self.transposed[r]) for r, rr in enumerate(runs)])
        self.run_starts = np.r_[0, np.cumsum([len(r) for r in runs])[:-1]]
        self.idx0, self.idx1 = self._spans(self.gu, self.gv)
        # Farthest silhouette pixel from the anchor (pixels), for pruning placements in `match`.
        self.reach = float(np.hypot(np.abs(self.runs[:, 0]).max(), np.abs(self.runs[:, 1:]).max()))
        # A hidden target cannot sit where its anchor pixel would be seen (when the anchor lies in
        # every rotation's silhouette; a box's centre always does).
        self.anchor_inside = all(bool(sil[anchor[1], anchor[0]]) for sil in sils)
        # World z of a pixel's point = depth * ray_z + camera z (the ray's z per unit depth).
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        R = camera.X_WC.rotation().matrix()
        self._ray_z = (R[2, 0] * (u - camera.cx) / camera.fx + R[2, 1] * (v - camera.cy) / camera.fy
                       + R[2, 2]).astype(np.float32)
        self._z0 = np.float32(camera.X_WC.translation()[2] - workspace.floor_z)
        self.last_matches = 0

    def _spans(self, gu: np.ndarray, gv: np.ndarray):
        """Flat prefix-sum indices of the run ends of every (placement, run): (n_placements, n_runs)
        arrays idx0, idx1 into [row prefix sums (H, W + 1), column prefix sums (W, H + 1)] (both 0
        where the run leaves the image)."""
        H, W = self.camera.height, self.camera.width
        t = self.run_transposed[None, :]
        # In the run's own frame (transposed for column runs): line, start, end.
        line = np.where(t, gu[:, None], gv[:, None]) + self.runs[None, :, 0]
        base = np.where(t, gv[:, None], gu[:, None])
        n_lines, n_cols = np.where(t, W, H), np.where(t, H, W)
        a = np.clip(base + self.runs[None, :, 1], 0, n_cols)
        b = np.clip(base + self.runs[None, :, 2] + 1, 0, n_cols)
        inside = (line >= 0) & (line < n_lines) & (b > a)
        offset = np.where(t, H * (W + 1), 0)
        idx0 = np.where(inside, offset + line * (n_cols + 1) + a, 0).astype(np.int32)
        idx1 = np.where(inside, offset + line * (n_cols + 1) + b, 0).astype(np.int32)
        return idx0, idx1

    def height_map(self, depth) -> np.ndarray:
        """(H, W) height of the observed surface above the bin floor (invalid depth -> 0)."""
        d = np.asarray(depth.data if hasattr(depth, "data") else depth, np.float32)
        d = d[..., 0] if d.ndim == 3 else d
        if d.shape != self._ray_z.shape:
            raise PerceptionError(f"depth image is {d.shape[1]}x{d.shape[0]}, the camera "
                                  f"{self.camera.width}x{self.camera.height}")
        h = d * self._ray_z + self._z0
        return np.where(np.isfinite(h) & (d > 0), h, np.float32(0.0))

    def match(self, depth, target_mask: np.ndarray) -> np.ndarray:
        """(n_placements, rotations) bool: placements whose modal mask matches `target_mask`."""
        H, W = self.camera.height, self.camera.width
        M = np.asarray(target_mask, bool)
        if M.shape != (H, W):
            raise PerceptionError(f"target mask is {M.shape[1]}x{M.shape[0]}, the camera {W}x{H}")
        V = self.height_map(depth) <= self.top + self.height_tolerance
        # int32 is exact: a row's prefix sum is < 2^10 + 2^26, a placement's sum < 2^13 + 2^29.
        packed = V.astype(np.int32) + ((V & M).astype(np.int32) << 16)
        m = int(M.sum())
        # Placements that can match at all: a hidden target's silhouette must not see the floor at
        # its own anchor pixel; a seen target's must cover > 90 % of the observed mask, so its
        # anchor lies within reach of the mask.
        if m == 0:
            cand = np.flatnonzero(~V[self.gv, self.gu]) if self.anchor_inside else np.arange(len(self.gu))
        else:
            ys, xs = np.nonzero(M)
            reach = self.reach + 0.5 * np.hypot(np.ptp(xs), np.ptp(ys)) + 1.0
            cand = np.flatnonzero(np.hypot(self.gu - xs.mean(), self.gv - ys.mean()) <= reach)
        out = np.zeros((len(self.gu), len(self.angles)), bool)
        if len(cand) == 0:
            return out
        Sf = np.zeros(H * (W + 1) + W * (H + 1), np.int32)
        np.cumsum(packed, axis=1, out=Sf[:H * (W + 1)].reshape(H, W + 1)[:, 1:])
        if self.transposed.any():
            np.cumsum(cv2.transpose(packed), axis=1, out=Sf[H * (W + 1):].reshape(W, H + 1)[:, 1:])
        sums = np.take(Sf, self.idx1[cand]) - np.take(Sf, self.idx0[cand])
        per_rot = np.add.reduceat(sums, self.run_starts, axis=1)
        modal, inter = per_rot & 0xFFFF, per_rot >> 16
        if m == 0:
            out[cand] = modal == 0
        else:
            iou = inter / np.maximum(modal + m - inter, 1)
            out[cand] = iou > self.iou_threshold
            best = float(iou.max())
            if self.best_match is not None and not out.any() and best >= BEST_MATCH_MIN:
                out[cand] = iou >= best - self.best_match
        return out

    def accumulate(self, matches: np.ndarray) -> np.ndarray:
        """Sum of the amodal masks of the matched placements, (H, W) counts (row runs and column
        runs each into their own difference image, see `_accumulate_runs`)."""
        H, W = self.camera.height, self.camera.width
        gw, gh = self.grid.grid
        us, vs = self.grid.pixels(W, H)
        counts = np.zeros((len(self.angles), gh * gw), np.int32)
        counts[:, self.grid_index] = matches.T
        counts = counts.reshape(-1, gh, gw)
        active = counts.reshape(len(counts), -1).any(axis=1)
        out = np.zeros((H, W))
        rows = [r for r in range(len(counts)) if active[r] and not self.transposed[r]]
        cols = [r for r in range(len(counts)) if active[r] and self.transposed[r]]
        if rows:
            out += _accumulate_runs([self.runs_by_rotation[r] for r in rows], counts[rows], us, vs, H, W)
        if cols:
            out += _accumulate_runs([self.runs_by_rotation[r] for r in cols],
                                    np.ascontiguousarray(counts[cols].transpose(0, 2, 1)), vs, us, W, H).T
        return out

    def estimate(self, depth, target_mask: np.ndarray) -> np.ndarray:
        matches = self.match(preprocess_depth(depth), target_mask)
        self.last_matches = int(matches.sum())
        return normalize_occupancy(self.accumulate(matches), target_mask)


def _accumulate_runs(runs_list, counts, us, vs, height: int, width: int) -> np.ndarray:
    """Sum over rotations of (counts[r] placed on the grid (us, vs)) convolved with the row runs
    runs_list[r]: every run adds +k at its start and -k after its end in a difference image, k =
    the matches of its rotation on the whole grid, added at once; then integrated along the rows.
    The difference image is kept phase-major, Dp[a, b, I, J] = D[sy I + a, sx J + b], so each
    addition is one contiguous (rows x cols) block."""
    gh, gw = counts.shape[1:]
    sx, sy = (int(us[1] - us[0]) if gw > 1 else 1), (int(vs[1] - vs[0]) if gh > 1 else 1)
    pad = max(int(np.abs(r).max()) for r in runs_list) + 2
    ox, oy = int(us[0]) + pad, int(vs[0]) + pad
    Hb, Wb = -(-(height + 2 * pad) // sy) + 1, -(-(width + 1 + 2 * pad) // sx) + 1
    Dp = np.zeros((sy, sx, Hb, Wb), np.int32)
    for k, runs in zip(counts, runs_list):
        ya, Ia = np.divmod(oy + runs[:, 0], sy)[::-1]
        xa, Ja = np.divmod(ox + runs[:, 1], sx)[::-1]
        xb, Jb = np.divmod(ox + runs[:, 2] + 1, sx)[::-1]
        for a, i0, b0, j0, b1, j1 in zip(ya, Ia, xa, Ja, xb, Jb):
            Dp[a, b0, i0:i0 + gh, j0:j0 + gw] += k
            Dp[a, b1, i0:i0 + gh, j1:j1 + gw] -= k
    D = Dp.transpose(2, 0, 3, 1).reshape(Hb * sy, Wb * sx)
    return np.cumsum(D, axis=1)[pad:pad + height, pad:pad + width].astype(float)


def normalize_occupancy(counts: np.ndarray, target_mask: np.ndarray | None = None) -> np.ndarray:
    """Counts -> distribution summing to 1; no match -> the observed target mask (if any) or all 0."""
    total = counts.sum()
    if total > 0:
        return counts / total
    if target_mask is not None and np.any(target_mask):
        m = np.asarray(target_mask, float)
        return m / m.sum()
    return np.zeros_like(counts, dtype=float)


class RenderedOccupancy:
    """The straightforward implementation, for validation and speed comparison: for every
    placement (the same grid and rotations; the box centre placed exactly on the floor point under
    the grid pixel), render a target-only depth image with Drake's VTK RgbdSensor, call a pixel
    visible when the target's depth is not behind the observed depth (+ tolerance), and compare
    with the observed mask as AnalyticOccupancy does."""

    name = "rendered"

    def __init__(self, scenario, target_size, camera_name: str | None = None, grid: OccupancyGrid = OccupancyGrid(),
                 iou_threshold: float = 0.9, height_tolerance: float = 0.003):
        cam_name = camera_name or next(iter(scenario.cameras))
        cfg = copy.copy(scenario.cameras[cam_name])
        cfg.rgb, cfg.label, cfg.depth = False, False, True
        self.camera = PinholeCamera.from_config(cfg)
        self.workspace = Workspace.from_scenario(scenario)
        self.box, self.grid = TargetBox.of(target_size), grid
        self.iou_threshold, self.height_tolerance = float(iou_threshold), float(height_tolerance)
        self.gu, self.gv, self.centers, _ = _valid_placements(self.camera, self.workspace, self.box, grid)
        builder = DiagramBuilder()
        plant, sg = AddMultibodyPlant(MultibodyPlantConfig(time_step=0.0), builder)
        body = plant.AddRigidBody("target", SpatialInertia(1.0, np.zeros(3), UnitInertia.SolidBox(
            self.box.length, self.box.width, self.box.thickness)))
        plant.RegisterVisualGeometry(body, RigidTransform(), Box(self.box.length, self.box.width, self.box.thickness),
                                     "target_visual", np.array([0.9, 0.1, 0.1, 1.0]))
        plant.Finalize()
        ApplyCameraConfig(config=cfg, builder=builder, plant=plant, scene_graph=sg)
        self.sensor = builder.GetSubsystemByName(f"rgbd_sensor_{cfg.name}")
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()
        self.plant, self.body = plant, body
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        self.sensor_context = self.sensor.GetMyContextFromRoot(self.context)
        self.renders = 0
        self.render_seconds = 0.0

    def render(self, center: np.ndarray, theta: float) -> np.ndarray:
        """Target-only depth image (H, W), inf where the target is not seen."""
        self.plant.SetFreeBodyPose(self.plant_context, self.body,
                                   RigidTransform(RotationMatrix.MakeZRotation(theta), center))
        t = time.perf_counter()
        img = self.sensor.depth_image_32F_output_port().Eval(self.sensor_context)
        d = np.array(img.data)[:, :, 0].astype(float)
        self.render_seconds += time.perf_counter() - t
        self.renders += 1
        return np.where(np.isfinite(d) & (d > 0), d, np.inf)

    def estimate(self, depth, target_mask: np.ndarray) -> np.ndarray:
        D = depth_array(preprocess_depth(depth))
        D = np.where(np.isfinite(D), D, np.inf)
        M = np.asarray(target_mask, bool)
        m = int(M.sum())
        acc = np.zeros(D.shape)
        for center in self.centers:
            for theta in self.grid.angles():
                T = self.render(center, theta)
                amodal = np.isfinite(T)
                modal = amodal & (T <= D + self.height_tolerance)
                n = int(modal.sum())
                if m == 0:
                    ok = n == 0
                else:
                    inter = int((modal & M).sum())
                    ok = inter / max(n + m - inter, 1) > self.iou_threshold
                if ok:
                    acc += amodal
        return normalize_occupancy(acc, M)


BACKENDS = ("analytic", "learned")


class OccupancyEstimator(LeafSystem):
    """Target occupancy distribution from the depth image and the observed target.

    Inputs ``depth_image`` (ImageDepth32F, metres) and ``target`` (TargetEstimate: its mask is the
    observed modal mask; all False when not visible); output ``occupancy`` (OccupancyMap).

    backend: an object with ``estimate(depth (H, W), target_mask (H, W) bool) -> (H, W)`` (e.g.
    AnalyticOccupancy, RenderedOccupancy, LearnedOccupancy), or a name: "analytic" with camera,
    workspace and target_size given; "learned" (ms_drake.perception.occupancy_net) with
    target_size (the target's size only, never its pose; keywords weights=, input_scaling=,
    device=).
    """

    def __init__(self, backend="analytic", camera: PinholeCamera | None = None, workspace: Workspace | None = None,
                 target_size=None, **kwargs):
        super().__init__()
        if isinstance(backend, str):
            if backend not in BACKENDS:
                raise PerceptionError(f"OccupancyEstimator backend {backend!r} unknown; choose one of "
                                      f"{', '.join(BACKENDS)} or pass an object with estimate(depth, mask)")
            if backend == "learned":
                if target_size is None:
                    raise PerceptionError("OccupancyEstimator('learned') needs target_size=(length, width, thickness) "
                                          "or a TargetBox / TargetMesh")
                backend = LearnedOccupancy(target_size, **kwargs)
            elif camera is None or workspace is None or target_size is None:
                raise PerceptionError("OccupancyEstimator('analytic') needs camera= (PinholeCamera.from_config), "
                                      "workspace= (Workspace.from_scenario) and target_size=(length, width, thickness)")
            else:
                backend = AnalyticOccupancy(camera, workspace, target_size, **kwargs)
        elif not hasattr(backend, "estimate"):
            raise PerceptionError("OccupancyEstimator backend must have estimate(depth, target_mask)")
        cam = camera or getattr(backend, "camera", None)
        w, h = (cam.width, cam.height) if cam is not None else (640, 480)
        # Ports first.
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.target_port = self.DeclareAbstractInputPort(
            "target", AbstractValue.Make(TargetEstimate(False, np.zeros((h, w), bool))))
        self.occupancy_port = self.DeclareAbstractOutputPort(
            "occupancy", lambda: AbstractValue.Make(OccupancyMap(np.zeros((h, w)))), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.backend = backend
        self.shape = (h, w)

    def _calc(self, context, output):
        if not self.depth_port.HasValue(context):
            raise PerceptionError("OccupancyEstimator: the depth_image input is not connected")
        target = self.target_port.Eval(context) if self.target_port.HasValue(context) else None
        mask = target.mask if (target is not None and target.visible) else np.zeros(self.shape, bool)
        output.set_value(OccupancyMap(self.backend.estimate(preprocess_depth(self.depth_port.Eval(context)), mask)))
