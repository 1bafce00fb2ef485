"""Linear push toward the most free point of the bin (Ch. 7.3.2, lines 1262-1264; Ch. 4.4).

The reference: "selects p' as the most free point in the bin ... the signed distance transform
of a binary mask of the bin walls and objects, finding the pixel with the maximum signed
distance value, and deprojecting that pixel back into R^3. Given an object to push, p is then
selected so that the gripper is not in collision at p, the line from p to p' passes through the
object's center of mass, and the push direction is as close as possible to the direction of the
most free point in the bin. ... quality 1 if a valid push exists and 0 if not."

How it is done here (choices recorded where the text is silent):
  * the binary mask is a top-down metric grid of the bin floor (`resolution`, 4 mm), not the
    image: every depth pixel deprojected to the world that lies inside the bin above the floor
    (> `min_height`) marks its cell as an object; cells outside the inner box are walls. A 3x3
    closing fills sampling gaps. The grid is metric, so distances are metres whatever the
    camera's perspective;
  * signed distance = distance to the nearest obstacle cell for free cells, minus the distance to
    the nearest free cell for obstacle cells (scipy's exact Euclidean distance transform);
  * the object's centre of mass is approximated by the centroid of its segmented points
    (Ch. 4.4: "the centroid of the segmented cluster");
  * candidate directions start at the direction from the centre to p' and turn away from it in
    `angle_step` steps up to `max_angle`; the first that yields a valid push is taken ("as
    close as possible"). For a direction d, the start p = c - t d is the first point behind the
    object's footprint where the closed gripper (a disc of `gripper_radius` + `clearance` seen
    from above, as it descends vertically) touches no obstacle; the end is the point of the line
    nearest to p', at most `max_length` from p and with the gripper still `gripper_radius` off the
    walls; the push must carry the gripper at least `min_travel` past the object's centre;
  * the push runs at constant height: `push_height`, as every push policy's.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

from ms_drake.errors import MsDrakeError
from ms_drake.geometry import PinholeCamera, Workspace, depth_array, preprocess_depth, world_points
from ms_drake.types import InstanceMasks, Push


class PushError(MsDrakeError, ValueError):
    """A push planner was configured or fed with impossible values."""


# The lowest tool-centre height of a push above the bin floor [m]. The YuMi's closed jaw reaches
# 1.5 cm below its tool centre and its IK keeps the fingertips 5 mm off the floor, so the arm
# cannot execute a push whose tool centre is below 2 cm (the floating jaw of the primitive mode
# would press its fingertips into the floor there).
MIN_PUSH_HEIGHT = 0.02
MAX_PUSH_HEIGHT = 0.03


def push_height(floor_z: float, object_top: float, min_height: float = MIN_PUSH_HEIGHT,
                max_height: float = MAX_PUSH_HEIGHT) -> float:
    """World z of the tool centre for pushing an object whose top is at `object_top`: half the
    object's height above the floor, clamped to [min_height, max_height] above it. Every push
    planner (PushPlanner's free-space push and the Ch. 4 policies) takes its height from here."""
    if not 0.0 <= min_height <= max_height:
        raise PushError(f"push heights: give 0 <= min_push_height <= max_push_height, got {min_height} and "
                        f"{max_height}")
    return float(floor_z) + float(np.clip(0.5 * (float(object_top) - float(floor_z)), min_height, max_height))


@dataclass(frozen=True)
class PushParams:
    gripper_radius: float = 0.025  # closed parallel jaw seen from above (fingers 36 x 20 mm + pads)
    clearance: float = 0.005
    resolution: float = 0.004  # m per cell of the top-down grid
    min_height: float = 0.004  # points higher above the floor are objects
    angle_step: float = np.radians(10.0)
    max_angle: float = np.radians(90.0)
    max_length: float = 0.20
    min_travel: float = 0.03
    max_backoff: float = 0.12  # how far behind the object's footprint a start is searched
    min_push_height: float = MIN_PUSH_HEIGHT  # tool centre above the floor (push_height)
    max_push_height: float = MAX_PUSH_HEIGHT

    def __post_init__(self):
        for name in ("gripper_radius", "resolution", "max_length"):
            if getattr(self, name) <= 0:
                raise PushError(f"PushParams.{name} must be > 0, got {getattr(self, name)}")
        push_height(0.0, 0.0, self.min_push_height, self.max_push_height)


@dataclass(frozen=True, eq=False)
class ObstacleMap:
    """Top-down grid of the bin: `occupied` (ny, nx) bool (objects and walls), `sdf` (ny, nx) signed
    distance [m]; cell (i, j) has centre (x0 + (j + 0.5) res, y0 + (i + 0.5) res); walls lie outside."""

    occupied: np.ndarray
    sdf: np.ndarray
    x0: float
    y0: float
    resolution: float
    floor_z: float

    def cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        j = np.floor((xy[..., 0] - self.x0) / self.resolution).astype(int)
        i = np.floor((xy[..., 1] - self.y0) / self.resolution).astype(int)
        return i, j

    def center(self, i, j) -> np.ndarray:
        return np.stack([self.x0 + (np.asarray(j) + 0.5) * self.resolution,
                         self.y0 + (np.asarray(i) + 0.5) * self.resolution], axis=-1)

    def signed_distance(self, xy: np.ndarray) -> np.ndarray:
        """Signed distance at points (..., 2); points outside the grid are inside a wall (-inf)."""
        i, j = self.cell(xy)
        ok = (i >= 0) & (i < self.sdf.shape[0]) & (j >= 0) & (j < self.sdf.shape[1])
        out = np.full(i.shape, -np.inf)
        out[ok] = self.sdf[i[ok], j[ok]]
        return out

    def most_free_point(self) -> np.ndarray:
        i, j = np.unravel_index(int(np.argmax(self.sdf)), self.sdf.shape)
        return self.center(i, j)


def obstacle_map(P_W: np.ndarray, workspace: Workspace, params: PushParams = PushParams()) -> ObstacleMap:
    """The top-down obstacle grid and its signed distance from an organized world cloud (H, W, 3)."""
    res = params.resolution
    sx, sy = workspace.size_xy
    # One wall cell around the inner box.
    nx, ny = int(np.ceil(sx / res)) + 2, int(np.ceil(sy / res)) + 2
    x0 = workspace.center_xy[0] - 0.5 * nx * res
    y0 = workspace.center_xy[1] - 0.5 * ny * res
    occ = np.zeros((ny, nx), np.uint8)
    fg = workspace.foreground(P_W, params.min_height, margin=0.0)
    pts = P_W[fg]
    j = np.clip(((pts[:, 0] - x0) / res).astype(int), 0, nx - 1)
    i = np.clip(((pts[:, 1] - y0) / res).astype(int), 0, ny - 1)
    occ[i, j] = 1
    occ = cv2.morphologyEx(occ, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    cx = x0 + (np.arange(nx) + 0.5) * res
    cy = y0 + (np.arange(ny) + 0.5) * res
    wall = ~(workspace.inside_xy(np.stack(np.meshgrid(cx, cy), axis=-1)))
    occupied = occ.astype(bool) | wall
    free_d = distance_transform_edt(~occupied) * res
    occ_d = distance_transform_edt(occupied) * res
    sdf = np.where(occupied, -occ_d, free_d)
    return ObstacleMap(occupied, sdf, float(x0), float(y0), res, workspace.floor_z)


def _rot(v: np.ndarray, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def plan_free_space_push(omap: ObstacleMap, object_points: np.ndarray, params: PushParams = PushParams(),
              object_id: str = "") -> Push | None:
    """The push of one object (its world points (N, 3) from its mask), or None if none is valid."""
    if len(object_points) < 3:
        return None
    c = object_points[:, :2].mean(axis=0)
    z = push_height(omap.floor_z, float(np.percentile(object_points[:, 2], 90)), params.min_push_height,
                    params.max_push_height)
    target = omap.most_free_point()
    d0 = target - c
    if np.linalg.norm(d0) < 1e-6:
        d0 = np.array([1.0, 0.0])
    d0 = d0 / np.linalg.norm(d0)
    r_start = params.gripper_radius + params.clearance
    step = 0.5 * omap.resolution
    angles = [0.0]
    k = 1
    while k * params.angle_step <= params.max_angle + 1e-9:
        angles += [k * params.angle_step, -k * params.angle_step]
        k += 1
    for a in angles:
        d = _rot(d0, a)
        # Start: behind the footprint along -d, first point where the gripper disc is free.
        t_exit = float(np.max((c - object_points[:, :2]) @ d))
        ts = t_exit + np.arange(0.0, params.max_backoff + step, step)
        starts = c[None, :] - ts[:, None] * d[None, :]
        ok = omap.signed_distance(starts) >= r_start
        if not ok.any():
            continue
        t = ts[int(np.argmax(ok))]
        p = c - t * d
        # End: the point of the line nearest to the free point, capped, gripper off the walls.
        L = min(float((target - p) @ d), params.max_length)
        ls = np.arange(t + params.min_travel, L + step, step)
        if len(ls) == 0:
            continue
        ends = p[None, :] + ls[:, None] * d[None, :]
        walls_ok = _inside_walls(omap, ends, params.gripper_radius)
        if not walls_ok[0]:
            continue
        last = len(ls) if walls_ok.all() else int(np.argmin(walls_ok))
        e = p + ls[last - 1] * d
        return Push((float(p[0]), float(p[1]), z), (float(e[0]), float(e[1]), z), object_id)
    return None


def _inside_walls(omap: ObstacleMap, xy: np.ndarray, radius: float) -> np.ndarray:
    """Points whose disc of `radius` stays inside the bin's inner box (objects are pushed, walls not)."""
    ny, nx = omap.sdf.shape
    lo = np.array([omap.x0, omap.y0]) + omap.resolution  # inner box = grid minus the wall cell
    hi = np.array([omap.x0 + nx * omap.resolution, omap.y0 + ny * omap.resolution]) - omap.resolution
    return np.all((xy - radius >= lo) & (xy + radius <= hi), axis=-1)


def plan_pushes(depth, masks: InstanceMasks, camera: PinholeCamera, workspace: Workspace,
                params: PushParams = PushParams()) -> tuple[Push, ...]:
    """A push for every mask that has a valid one (ids from the masks), in mask order; the depth is
    read through geometry.preprocess_depth."""
    D = depth_array(preprocess_depth(depth))
    if len(masks) and masks.masks.shape[1:] != D.shape:
        raise PushError(f"masks are {masks.masks.shape[2]}x{masks.masks.shape[1]} but the depth image "
                        f"{D.shape[1]}x{D.shape[0]}; segment the same camera's image")
    P_W = world_points(camera, D)
    omap = obstacle_map(P_W, workspace, params)
    out = []
    for k in range(len(masks)):
        pts = P_W[masks.masks[k]]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        push = plan_free_space_push(omap, pts, params, masks.ids[k])
        if push is not None:
            out.append(push)
    return tuple(out)
