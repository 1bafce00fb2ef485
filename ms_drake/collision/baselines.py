"""Point-cloud collision baselines of Table 6.1 (lines 1116-1124), for held-out queries.

Both see what the network sees: the scene's point cloud (world frame) and the query object's
points (its own frame); neither reads the true meshes.

- `CoalReconstruction`: the scene cloud's points above the table top are split into connected
  clusters (points closer than `link` are joined: scipy's cKDTree pairs + connected components),
  each cluster's convex hull (scipy / qhull via trimesh) becomes a coal convex shape, the table a
  coal box, and the query object the convex hull of its points; a query is a coal collision test
  of the hull at the pose against every cluster hull whose bounding sphere it reaches, and the
  table. Convex hulls over-fill concave and merged clusters (false positives); a cloud seen from
  one side leaves the hidden back open (the hull still closes it).
- `PointDistance` (the signed-distance baseline): a query collides when a point of the object at
  the pose lies within `margin` of a scene point (cKDTree), or below the table top.
"""

from __future__ import annotations

import coal
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.geometry import coal_convex, transform_points

BASELINES = ("coal_reconstruction", "sdf")


def _convex(points: np.ndarray) -> coal.Convex | None:
    try:
        hull = trimesh.convex.convex_hull(points)
    except Exception:  # noqa: BLE001 - qhull fails on flat or tiny clusters: skip them
        return None
    if len(hull.faces) < 4:
        return None
    return coal_convex(hull.vertices, hull.faces)


def clusters(points: np.ndarray, link: float = 0.01, min_points: int = 10) -> list[np.ndarray]:
    """Connected clusters of points (pairs closer than `link` joined); clusters under min_points dropped."""
    if len(points) == 0:
        return []
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    k, lab = connected_components(graph, directed=False)
    return [points[lab == i] for i in range(k) if (lab == i).sum() >= min_points]


class CoalReconstruction:
    """Coal collision checks against convex hulls of the scene cloud's clusters (module doc)."""

    def __init__(self, scene_points: np.ndarray, object_points: np.ndarray, table_top: float = 0.0,
                 table_size=(1.0, 0.8, 0.05), link: float = 0.01):
        above = scene_points[scene_points[:, 2] > table_top + 0.003]
        self.parts = []
        for c in clusters(above, link):
            shape = _convex(c)
            if shape is not None:
                centre = c.mean(axis=0)
                self.parts.append((shape, centre, float(np.linalg.norm(c - centre, axis=1).max())))
        self.object = _convex(object_points)
        if self.object is None:
            raise CollisionNetError("the query object's points have no 3D convex hull")
        self.radius = float(np.linalg.norm(object_points, axis=1).max())
        self.table = coal.Box(*map(float, table_size))
        self.T_table = coal.Transform3s(np.eye(3), np.array([0.0, 0.0, table_top - table_size[2] / 2]))
        self.request = coal.CollisionRequest()
        self.identity = coal.Transform3s()

    def query(self, poses: np.ndarray) -> np.ndarray:
        out = np.zeros(len(poses), bool)
        for i, X in enumerate(np.asarray(poses, float)):
            T = coal.Transform3s(np.ascontiguousarray(X[:3, :3]), np.ascontiguousarray(X[:3, 3]))
            if coal.collide(self.object, T, self.table, self.T_table, self.request, coal.CollisionResult()):
                out[i] = True
                continue
            for shape, c, r in self.parts:
                if np.linalg.norm(X[:3, 3] - c) <= r + self.radius and coal.collide(
                        self.object, T, shape, self.identity, self.request, coal.CollisionResult()):
                    out[i] = True
                    break
        return out


class PointDistance:
    """Collision when an object point comes within `margin` of a scene point or under the table (module doc)."""

    def __init__(self, scene_points: np.ndarray, object_points: np.ndarray, table_top: float = 0.0,
                 margin: float = 0.01):
        above = scene_points[scene_points[:, 2] > table_top + 0.003]
        self.tree = cKDTree(above)
        self.points = np.asarray(object_points, float)
        self.table_top, self.margin = table_top, margin

    def query(self, poses: np.ndarray) -> np.ndarray:
        out = np.zeros(len(poses), bool)
        for i, X in enumerate(np.asarray(poses, float)):
            p = transform_points(X, self.points)
            out[i] = p[:, 2].min() < self.table_top or bool(
                np.isfinite(self.tree.query(p, k=1, distance_upper_bound=self.margin)[0]).any())
        return out


def make_baseline(method: str, scene_points: np.ndarray, object_points: np.ndarray):
    if method == "coal_reconstruction":
        return CoalReconstruction(scene_points, object_points)
    if method == "sdf":
        return PointDistance(scene_points, object_points)
    raise CollisionNetError(f"collision baseline {method!r} unknown; choose one of {', '.join(BASELINES)}")
