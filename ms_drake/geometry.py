"""Shared geometry below every capability: the pinhole camera model and the bin workspace.

- `PinholeCamera`: intrinsics + world pose of a camera (Drake convention: +z forward, +x right,
  +y down), built from a `CameraConfig`; projects points, deprojects depth images, draws a mesh's
  silhouette.
- `Workspace`: the bin's inner box in the world, read from a bin scenario.
- `depth_array`, `world_points`: depth images as arrays and as world points.
- `preprocess_depth`: the one preprocessing of a sensor's depth image (hole filling) that every
  learned model and every depth baseline applies before it reads depth. It lives here, below
  perception, grasping and pushing, because all three consume depth.

Only numpy, cv2 and pydrake value types are imported here, so every layer may import it.
"""

from __future__ import annotations

from dataclasses import dataclass

import coal
import cv2
import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.systems.sensors import CameraConfig

from ms_drake.errors import PerceptionError


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics and world pose of a colour/label camera (Drake convention: +z forward,
    +x right, +y down)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    X_WC: RigidTransform

    @staticmethod
    def from_config(cfg: CameraConfig, X_WP: RigidTransform | None = None) -> "PinholeCamera":
        color, _ = cfg.MakeCameras()
        intr = color.core().intrinsics()
        X_PB = cfg.X_PB.GetDeterministicValue()
        X_BC = cfg.X_BC.GetDeterministicValue()
        X_WP = RigidTransform() if X_WP is None else as_rigid_transform(X_WP, "X_WP")
        X_WC = X_WP @ X_PB @ X_BC
        return PinholeCamera(intr.width(), intr.height(), intr.focal_x(), intr.focal_y(),
                             intr.center_x(), intr.center_y(), X_WC)

    def project(self, p_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) and depths (N,) of world points (N, 3)."""
        X_CW = self.X_WC.inverse()
        p_C = (X_CW.rotation().matrix() @ p_W.T).T + X_CW.translation()
        z = p_C[:, 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        uv = np.stack([self.fx * p_C[:, 0] / zs + self.cx, self.fy * p_C[:, 1] / zs + self.cy], axis=1)
        return uv, z

    def deproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W, 3) points in the camera frame from a depth image (metres; NaN where invalid)."""
        v, u = np.mgrid[0:self.height, 0:self.width]
        z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
        return np.stack([(u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z], axis=-1)


def silhouette(camera: PinholeCamera, vertices_W: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(H, W) bool mask of a mesh's projection (triangles behind the camera are dropped)."""
    uv, z = camera.project(vertices_W)
    mask = np.zeros((camera.height, camera.width), np.uint8)
    ok = np.all(z[faces] > 1e-3, axis=1)
    # fillPoly takes integer pixel coords; use 4 bits of sub-pixel precision (shift=4).
    # (fillPoly would XOR overlapping triangles, so each is filled on its own.)
    tris = np.round(uv[faces[ok]] * 16).astype(np.int32)  # pixel centres at integer coordinates
    for tri in tris:
        cv2.fillConvexPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


@dataclass(frozen=True)
class Workspace:
    """The bin's inner box in the world: floor top at `floor_z`, inner x/y extents centred on
    `center_xy`, walls `wall_height` high. `Workspace.from_scenario(scenario)` reads it from the
    scenario's environment (ms_drake.station.environments conventions)."""

    center_xy: tuple[float, float]
    size_xy: tuple[float, float]
    floor_z: float
    wall_height: float

    @staticmethod
    def from_scenario(scenario) -> "Workspace":
        env = scenario.environment
        if env.type != "bin":
            raise PerceptionError(f"environment.type is {env.type!r}: bin segmentation, occupancy and pushing "
                                  "need a bin scenario (e.g. BinHeap15)")
        size = env.resolved_size()
        pos = np.asarray(env.position, float)
        return Workspace((float(pos[0]), float(pos[1])), (float(size[0]), float(size[1])), float(pos[2]),
                         float(size[2]))

    def inside_xy(self, p: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Bool array: points (..., >=2) whose x, y lie inside the inner box shrunk by `margin`."""
        half = 0.5 * np.asarray(self.size_xy) - margin
        d = np.abs(p[..., :2] - np.asarray(self.center_xy))
        return np.all(d <= half, axis=-1)

    def foreground(self, P_W: np.ndarray, min_height: float = 0.004, margin: float = 0.004) -> np.ndarray:
        """(H, W) bool: valid points inside the bin, above the floor by `min_height` (the bin removed)."""
        ok = np.all(np.isfinite(P_W), axis=-1)
        z = np.where(ok, P_W[..., 2], -np.inf) - self.floor_z
        return ok & self.inside_xy(np.where(ok[..., None], P_W, 0.0), margin) & (z > min_height)


def depth_array(depth) -> np.ndarray:
    """(H, W) float depth in metres from an ImageDepth32F or array; 0 / inf / NaN -> NaN."""
    d = np.asarray(depth.data if hasattr(depth, "data") else depth, dtype=np.float64)
    d = d[..., 0] if d.ndim == 3 else d
    return np.where(np.isfinite(d) & (d > 0), d, np.nan)


#: Radius (px) of cv2.inpaint's neighbourhood in `preprocess_depth`.
INPAINT_RADIUS = 3


def depth_holes(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels a depth sensor returned nothing for (0, negative or NaN). +inf,
    Drake's "farther than the clipping range", is not a hole: nothing is there to fill in."""
    d = np.asarray(depth)
    return ~(d > 0) & ~np.isposinf(d)


def preprocess_depth(depth) -> np.ndarray:
    """The depth image every learned model and depth baseline reads: (H, W) float32 metres with the
    sensor's holes (`depth_holes`) filled by OpenCV inpainting (Navier-Stokes, radius
    `INPAINT_RADIUS` px) of the depth normalised to [0, 1] over its valid range, as the reference
    filled its real images' missing depth (dissertation line 879; the ``perception`` package's
    depth inpainting). A depth image without holes (every clean render) is returned with its values
    unchanged; +inf pixels stay +inf. `depth`: an ImageDepth32F or an (H, W[, 1]) array."""
    d = np.asarray(depth.data if hasattr(depth, "data") else depth, np.float32)
    d = d[..., 0] if d.ndim == 3 else d
    holes = depth_holes(d)
    valid = np.isfinite(d) & (d > 0)
    if not holes.any() or not valid.any():
        return d
    lo, hi = float(d[valid].min()), float(d[valid].max())
    span = max(hi - lo, 1e-6)
    norm = np.where(valid, (d - lo) / span, np.where(holes, 0.0, 1.0)).astype(np.float32)
    filled = cv2.inpaint(norm, holes.astype(np.uint8), INPAINT_RADIUS, cv2.INPAINT_NS)
    out = d.copy()
    out[holes] = lo + np.clip(filled[holes], 0.0, 1.0) * span
    return out


def world_points(camera: PinholeCamera, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) world points of a depth image (NaN where invalid)."""
    if depth.shape != (camera.height, camera.width):
        raise PerceptionError(f"depth image is {depth.shape[1]}x{depth.shape[0]} but the camera is "
                              f"{camera.width}x{camera.height}; build the system from the same camera config")
    P_C = camera.deproject(depth)
    R = camera.X_WC.rotation().matrix()
    return P_C @ R.T + camera.X_WC.translation()


def transform_points(X: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points P (..., 3) in frame A mapped by the 4x4 pose X = X_BA to frame B. The transposed
    rotation is copied to a C-contiguous block first: numpy 2.4 multiplies (N, 3) by a C-contiguous
    3x3 in 0.2 ms for 10^5 points, by the strided slice of a 4x4 or a transposed (F-ordered) 3x3
    through OpenBLAS in 0.5 ms with one thread and 7-40 ms of CPU with two (its threads spin)."""
    return P @ np.ascontiguousarray(X[:3, :3].T) + X[:3, 3]


def transform_from_rpy_xyz(rpy, xyz) -> RigidTransform:
    """RigidTransform from Drake roll-pitch-yaw angles [rad] and a translation [m] (the robot
    tables store weld transforms as these plain tuples)."""
    return RigidTransform(RollPitchYaw(*rpy), np.asarray(xyz, float))


#: Largest |R^T R - I| entry accepted in a pose's rotation block (poses read from files or built
#: from float32 data are rotations only to a few ulps of float32).
POSE_TOLERANCE = 1e-6


def as_matrix4(X, name: str = "pose") -> np.ndarray:
    """A pose given as a pydrake `RigidTransform` or as a 4x4 homogeneous matrix (any array-like),
    as a new (4, 4) float array. Raises TypeError when `X` is neither, ValueError when it is not
    4x4, not finite, or not a rigid transform (rotation block not a proper rotation within
    POSE_TOLERANCE, bottom row not [0, 0, 0, 1]); the message names the argument `name`."""
    if isinstance(X, RigidTransform):
        M = np.array(X.GetAsMatrix4(), order="C")  # row-major like any other array: the same sums
    else:
        if X is None or isinstance(X, (str, bytes, dict)):
            raise TypeError(f"{name} must be a pydrake RigidTransform or a 4x4 array, got {type(X).__name__}")
        try:
            M = np.array(X, dtype=float)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be a pydrake RigidTransform or a 4x4 array, got {type(X).__name__}") from None
        if M.shape != (4, 4):
            raise ValueError(f"{name} must be a RigidTransform or a 4x4 homogeneous matrix, got an array of "
                             f"shape {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{name} has non-finite entries (NaN or inf):\n{M}")
    (a, b, c, _), (d, e, f, _), (g, h, i, _), last = M.tolist()  # plain floats: a few us a pose
    err = max(abs(a * a + d * d + g * g - 1), abs(b * b + e * e + h * h - 1), abs(c * c + f * f + i * i - 1),
              abs(a * b + d * e + g * h), abs(a * c + d * f + g * i), abs(b * c + e * f + h * i))  # R^T R - I
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if err > POSE_TOLERANCE or det <= 0 or last != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"{name} is not a rigid transform: its rotation block must be a proper rotation "
                         f"(|R^T R - I| = {err:.2g}, det = {det:.3g}) and its last row [0, 0, 0, 1], got\n{M}")
    return M


def as_rigid_transform(X, name: str = "pose") -> RigidTransform:
    """A pose given as a pydrake `RigidTransform` or a 4x4 homogeneous matrix, as a RigidTransform
    (checked as `as_matrix4` does; the same errors, naming `name`)."""
    M = as_matrix4(X, name)
    return X if isinstance(X, RigidTransform) else RigidTransform(M)


def coal_convex(vertices, faces) -> coal.Convex:
    """A coal.Convex of a closed convex polyhedron given by its vertices (n, 3) and triangles (m, 3)."""
    verts = coal.StdVec_Vec3s()
    for v in np.asarray(vertices, float):
        verts.append(v)
    tris = coal.StdVec_Triangle()
    for f in np.asarray(faces, int):
        tris.append(coal.Triangle(int(f[0]), int(f[1]), int(f[2])))
    return coal.Convex(verts, tris)
