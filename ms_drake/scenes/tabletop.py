"""Table and shelf scenes: objects in stable resting poses, without collision.

Each object takes a stable pose of its mesh (trimesh's quasi-static stable poses, drawn by
their probability), a random yaw and a random position on the support surface; placements
whose footprints (shapely polygons of the convex hull's projection, grown by `clearance`)
overlap an earlier object are resampled. Used by the table (rearrangement) and shelf stations.
"""

from __future__ import annotations

import functools

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from shapely.geometry import MultiPoint
from shapely.geometry import box as shapely_box

from ms_drake.errors import HeapError
from ms_drake.objects import get_object
from ms_drake.scenario import Scenario
from ms_drake.types import Heap, ObjectPose


@functools.lru_cache(maxsize=1024)
def _stable_poses(full_name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(transforms (K,4,4), probabilities (K,), hull vertices) of the object's stable poses."""
    mesh = get_object(full_name).trimesh()
    hull = mesh.convex_hull
    T, p = hull.compute_stable_poses(n_samples=1, threshold=0.02)
    if len(T) == 0:
        T, p = np.eye(4)[None], np.ones(1)
    return np.asarray(T), np.asarray(p) / np.sum(p), np.asarray(hull.vertices)


def place_objects(scenario: Scenario, names: list[str], seed: int, clearance: float = 0.01,
                  margin: float = 0.03, max_tries: int = 200) -> Heap:
    """Objects `names` at stable, collision-free poses on the scenario's table or shelf floor."""
    env = scenario.environment
    size = env.resolved_size()
    origin = np.asarray(env.position, float)
    rng = np.random.default_rng([seed, 104729])
    area = shapely_box(-size[0] / 2 + margin, -size[1] / 2 + margin, size[0] / 2 - margin, size[1] / 2 - margin)
    placed = []
    objects = []
    for name in names:
        T, p, v = _stable_poses(name)
        for _ in range(max_tries):
            k = rng.choice(len(T), p=p)
            X_rest = RigidTransform(T[k])  # puts the object resting on z = 0
            yaw = RigidTransform(RotationMatrix(RollPitchYaw(0, 0, rng.uniform(-np.pi, np.pi))))
            X = yaw @ X_rest
            pts = v @ X.rotation().matrix().T + X.translation()
            xy0 = np.array([rng.uniform(area.bounds[0], area.bounds[2]), rng.uniform(area.bounds[1], area.bounds[3])])
            shift = xy0 - pts[:, :2].mean(axis=0)
            foot = MultiPoint([tuple(q) for q in pts[:, :2] + shift]).convex_hull
            if not area.contains(foot) or any(foot.buffer(clearance).intersects(f) for f in placed):
                continue
            placed.append(foot)
            X_W = RigidTransform(X.rotation(), origin + [shift[0] + X.translation()[0],
                                                         shift[1] + X.translation()[1],
                                                         X.translation()[2] - pts[:, 2].min() + 1e-4])
            quat = X_W.rotation().ToQuaternion()
            objects.append(ObjectPose(name, (quat.w(), quat.x(), quat.y(), quat.z(), *map(float, X_W.translation()))))
            break
        else:
            raise HeapError(f"cannot place {name} without collision on the {env.type} after {max_tries} tries; "
                            "use fewer or smaller objects")
    return Heap(seed=seed, environment=env.type, objects=tuple(objects))
