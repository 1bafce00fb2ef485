"""The scene-collision dataset of Ch. 6 (SceneCollisionNet's training data, line 1061).

`ms-drake data collision --count N --out DIR` writes shards ``shard_<k>_<split>.npz``, each
holding `SCENES_PER_SHARD` tabletop scenes (N is rounded up to whole shards). A scene:

1. n ~ U{10..20} mesh objects (the ycb and random_urdfs sets, one set per scene in turn) at
   stable, collision-free poses on the PandaTable station's table (ms_drake.scenes.tabletop,
   the table placement of the rearrangement station); an object that does not fit is left out
   (objects are dropped one at a time, at random, until the rest fit; at least `MIN_FIT`);
2. a point cloud of the scene: the depth image of the station's front camera, its extrinsics
   jittered around nominal (+-3 cm, +-3 deg, focal lengths +-3 %), rendered by Drake (VTK), back
   projected into the world and cropped to the volume above the table (`SCENE_BOUNDS`), then
   `SCENE_POINTS` points drawn from it;
3. a query object: a mesh of the scene's split, `OBJECT_POINTS` points on its closed surface (its
   own frame, grasping.meshes.object_mesh);
4. q = `TRAJECTORIES` x `POSES_PER_TRAJECTORY` = 64 x 32 = 2048 query poses along linear
   trajectories: start and end positions uniform over the table (and up to `QUERY_HEIGHT` above
   it), orientations uniform, positions interpolated linearly and orientations by slerp;
5. labels: collision of the query object's closed mesh at each pose with the scene's closed
   meshes and the table (coal, exact triangle-mesh intersection), or containment (a surface
   point of the query inside a scene mesh or the other way round: mesh-mesh intersection tests
   miss an object wholly inside another).

Splits by scene and by object: every fifth shard is a "test" shard (occupancy_data.shard_split)
whose scene and query objects come from the test splits of the object sets, the others from the
train splits. A shard is written atomically once all its scenes exist, so an interrupted run
resumes by skipping the shards on disk. Every random choice comes from numpy Generators seeded by
(seed, shard, scene).

Shard arrays (s scenes): ``scene_points`` (s, SCENE_POINTS, 3) float32 world frame [m],
``object_points`` (s, OBJECT_POINTS, 3) float32 object frame, ``poses`` (s, q, 4, 4) float32
world-from-object, ``labels`` (s, q) bool, ``X_WC`` (s, 4, 4) float32 camera poses, ``object_poses`` (s,
MAX_OBJECTS, 4, 4) float32 world-from-object of the scene objects (NaN rows past the last),
``objects`` (s,) comma-separated scene object names (in the order of object_poses), ``query`` (s,) query object names, ``seed`` (s,) scene
seeds.
"""

from __future__ import annotations

import copy
import os
import time
from pathlib import Path

import coal
import numpy as np
import trimesh
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from scipy.spatial.transform import Rotation, Slerp

from ms_drake.collision.scene_net import SCENE_BOUNDS
from ms_drake.errors import DatasetError, HeapError
from ms_drake.experiments.occupancy_data import HeapRenderer, shard_split
from ms_drake.experiments.segmentation_data import draw_sensor
from ms_drake.geometry import PinholeCamera, transform_points
from ms_drake.grasping.meshes import object_mesh
from ms_drake.objects import get_object_set
from ms_drake.parallel import run_jobs
from ms_drake.scenario import load_scenario
from ms_drake.scenes.tabletop import place_objects
from ms_drake.station.sensor_model import apply_depth_sensor

SCENARIO = "PandaTable"
OBJECT_SETS = ("ycb", "random_urdfs")
MIN_OBJECTS, MAX_OBJECTS = 10, 20
MIN_FIT = 8  # objects that must fit on the table for a scene to count
SCENES_PER_SHARD = 8
SCENE_POINTS = 8192
OBJECT_POINTS = 1024
TRAJECTORIES, POSES_PER_TRAJECTORY = 64, 32
QUERY_HEIGHT = 0.25  # m above the table top


def jitter_camera(nominal: PinholeCamera, rng: np.random.Generator) -> PinholeCamera:
    """The nominal camera with its pose and focal lengths jittered (module doc, step 2)."""
    p = nominal.X_WC.translation() + rng.uniform(-0.03, 0.03, 3)
    R = nominal.X_WC.rotation() @ RotationMatrix(RollPitchYaw(*np.deg2rad(rng.uniform(-3.0, 3.0, 3))))
    f = rng.uniform(0.97, 1.03, 2)
    return PinholeCamera(nominal.width, nominal.height, nominal.fx * f[0], nominal.fy * f[1], nominal.cx,
                         nominal.cy, RigidTransform(R, p))


def scene_cloud(depth: np.ndarray, cam: PinholeCamera, rng: np.random.Generator,
                count: int = SCENE_POINTS) -> np.ndarray:
    """(count, 3) world points drawn from the depth image's points inside SCENE_BOUNDS."""
    p_C = cam.deproject(depth).reshape(-1, 3)
    p_C = p_C[np.all(np.isfinite(p_C), axis=1)]
    X = cam.X_WC
    p_W = p_C @ X.rotation().matrix().T + X.translation()
    lo, hi = np.array(SCENE_BOUNDS).T
    p_W = p_W[np.all((p_W >= lo) & (p_W <= hi), axis=1)]
    if len(p_W) == 0:
        raise DatasetError("the camera sees no point above the table: check the PandaTable camera")
    return p_W[rng.choice(len(p_W), count, replace=len(p_W) < count)].astype(np.float32)


def _bvh(mesh: trimesh.Trimesh) -> coal.BVHModelOBBRSS:
    m = coal.BVHModelOBBRSS()
    m.beginModel(len(mesh.faces), len(mesh.vertices))
    m.addVertices(np.asarray(mesh.vertices, float))
    m.addTriangles(np.asarray(mesh.faces, np.int32))
    m.endModel()
    return m


def _transform(X: np.ndarray) -> coal.Transform3s:
    return coal.Transform3s(np.ascontiguousarray(X[:3, :3], float), np.ascontiguousarray(X[:3, 3], float))


def pose_matrix(q) -> np.ndarray:
    """4x4 world-from-object of an ObjectPose's q = (w, x, y, z, px, py, pz)."""
    X = np.eye(4)
    w, x, y, z = q[:4]
    X[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    X[:3, 3] = q[4:7]
    return X


def query_poses(rng: np.random.Generator, table_top: float, half: np.ndarray,
                trajectories: int = TRAJECTORIES, per: int = POSES_PER_TRAJECTORY) -> np.ndarray:
    """(trajectories * per, 4, 4) world-from-object poses along linear trajectories (module doc, step 4)."""
    out = np.empty((trajectories, per, 4, 4))
    s = np.linspace(0.0, 1.0, per)
    for t in range(trajectories):
        ends = np.column_stack([rng.uniform(-half[0], half[0], 2), rng.uniform(-half[1], half[1], 2),
                                table_top + rng.uniform(0.0, QUERY_HEIGHT, 2)])
        rots = Rotation.random(2, random_state=rng)
        R = Slerp([0.0, 1.0], rots)(s).as_matrix()
        out[t] = np.eye(4)
        out[t, :, :3, :3] = R
        out[t, :, :3, 3] = ends[0] + s[:, None] * (ends[1] - ends[0])
    return out.reshape(-1, 4, 4)


class SceneCollisions:
    """Exact collision of a query mesh at many poses with a fixed set of meshes (scene objects and
    the table), with coal (module doc, step 5)."""

    def __init__(self, meshes: list[trimesh.Trimesh], poses: list[np.ndarray], table: tuple[np.ndarray, np.ndarray]):
        self.meshes = meshes
        self.poses = [np.asarray(X, float) for X in poses]
        self.bvhs = [_bvh(m) for m in meshes]
        self.table_center, self.table_size = (np.asarray(v, float) for v in table)
        self.table = coal.Box(*self.table_size)
        self.request = coal.CollisionRequest()

    def labels(self, query: trimesh.Trimesh, poses: np.ndarray) -> np.ndarray:
        """Bool (len(poses),): the query mesh at each pose collides with the scene."""
        qb = _bvh(query)
        radius = float(np.linalg.norm(query.vertices, axis=1).max())
        out = np.zeros(len(poses), bool)
        T_table = np.eye(4)
        T_table[:3, 3] = self.table_center
        centres = [X[:3, :3] @ m.bounding_sphere.primitive.center + X[:3, 3] for m, X in zip(self.meshes, self.poses)]
        radii = [m.bounding_sphere.primitive.radius for m in self.meshes]
        for i, X in enumerate(poses):
            Tq = _transform(X)
            res = coal.CollisionResult()
            if coal.collide(qb, Tq, self.table, _transform(T_table), self.request, res):
                out[i] = True
                continue
            for bvh, Xs, c, r in zip(self.bvhs, self.poses, centres, radii):
                if np.linalg.norm(X[:3, 3] - c) > r + radius:
                    continue
                res = coal.CollisionResult()
                if coal.collide(qb, Tq, bvh, _transform(Xs), self.request, res):
                    out[i] = True
                    break
        # containment: one of the query's vertices inside a scene mesh, or a scene mesh's vertex inside the query
        v = np.asarray(query.vertices[:1])
        for m, Xs in zip(self.meshes, self.poses):
            todo = np.nonzero(~out)[0]
            if len(todo) == 0:
                break
            p_W = np.einsum("nij,j->ni", poses[todo, :3, :3], v[0]) + poses[todo, :3, 3]
            Xinv = np.linalg.inv(Xs)
            p_S = transform_points(Xinv, p_W)
            out[todo[m.contains(p_S)]] = True
            todo = np.nonzero(~out)[0]
            if len(todo) == 0:
                break
            s_W = Xs[:3, :3] @ m.vertices[0] + Xs[:3, 3]
            inv = np.linalg.inv(poses[todo])
            s_Q = np.einsum("nij,j->ni", inv[:, :3, :3], s_W) + inv[:, :3, 3]
            out[todo[query.contains(s_Q)]] = True
        return out


def make_scene(seed: int, shard: int, j: int, split: str, scenario=None, sensor: str = "none") -> dict:
    """Scene j of shard `shard` (module doc): arrays of one scene. sensor: none | random | a preset
    (module doc, step 2); with one, also `sensor` (the preset drawn)."""
    scenario = scenario or load_scenario(None, SCENARIO)
    rng = np.random.default_rng([seed, shard, j])
    oset = get_object_set(OBJECT_SETS[(shard * SCENES_PER_SHARD + j) % len(OBJECT_SETS)])
    pool = [o.full_name for o in oset.split(split)]
    if len(pool) < 2:
        raise DatasetError(f"object set {oset.name!r} has {len(pool)} objects in split {split!r}: need >= 2")
    n = int(rng.integers(MIN_OBJECTS, MAX_OBJECTS + 1))
    names = [pool[i] for i in rng.choice(len(pool), n, replace=n > len(pool))]
    while True:  # an object set too crowded for the table loses objects one at a time (module doc)
        try:
            heap = place_objects(scenario, names, int(rng.integers(2**31)), max_tries=100)
            break
        except HeapError:
            if len(names) <= MIN_FIT:
                raise DatasetError(f"scene ({seed}, {shard}, {j}): {len(names)} objects of {oset.name!r} do not fit "
                                   "on the table") from None
            names.pop(int(rng.integers(len(names))))
    cam = jitter_camera(PinholeCamera.from_config(scenario.cameras["front"]), rng)
    depth = HeapRenderer(scenario, heap).depth(cam)
    drawn, cloud_rng = "none", copy.deepcopy(rng)
    cloud = scene_cloud(depth, cam, rng)  # the clean cloud's draws move `rng` on, sensor or not
    if sensor != "none":
        drawn, params, srng = draw_sensor(sensor, seed, shard, j, 0)
        cloud = scene_cloud(apply_depth_sensor(depth, params, srng, cam.fx, cam.fy, cam.cx, cam.cy), cam, cloud_rng)
    query_name = pool[int(rng.integers(len(pool)))]
    query = object_mesh(query_name)  # its own frame: object_points and poses use it
    size = scenario.environment.resolved_size()
    top = float(scenario.environment.position[2])
    table = (np.asarray(scenario.environment.position, float) - [0.0, 0.0, size[2] / 2], size)  # top at z = top
    poses = query_poses(rng, top, np.asarray(size[:2]) / 2)
    meshes = [object_mesh(o.name) for o in heap.objects]
    X_objects = [pose_matrix(o.q) for o in heap.objects]
    labels = SceneCollisions(meshes, X_objects, table).labels(query, poses)
    object_poses = np.full((MAX_OBJECTS, 4, 4), np.nan, np.float32)
    object_poses[:len(X_objects)] = X_objects
    pts, _ = trimesh.sample.sample_surface(query, OBJECT_POINTS, seed=int(rng.integers(2**31)))
    return {"scene_points": cloud, "object_points": np.asarray(pts, np.float32), "poses": poses.astype(np.float32),
            "labels": labels, "X_WC": cam.X_WC.GetAsMatrix4().astype(np.float32), "object_poses": object_poses,
            "objects": ",".join(o.name for o in heap.objects), "query": query_name, "seed": j, "sensor": drawn}


def shard_path(out, k: int) -> Path:
    return Path(out) / f"shard_{k:05d}_{shard_split(k)}.npz"


def shard_job(job: tuple) -> dict:
    """(out, k, seed, scenes[, sensor]) -> write shard k; module-level for the worker pool."""
    out, k, seed, scenes, *rest = job
    sensor = rest[0] if rest else "none"
    t0 = time.process_time()
    scenario = load_scenario(None, SCENARIO)
    rows = [make_scene(seed, k, j, shard_split(k), scenario, sensor) for j in range(scenes)]
    arrays = {key: np.stack([r[key] for r in rows]) for key in rows[0]}
    path = shard_path(out, k)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)
    return {"shard": k, "scenes": scenes, "queries": int(arrays["labels"].size),
            "positive": float(arrays["labels"].mean()), "cpu": time.process_time() - t0}


def write_collision_dataset(out, count: int, seed: int = 0, workers: int = 1, use_ray: bool = False,
                            ray_address: str | None = None, progress=None, scenes_per_shard: int = SCENES_PER_SHARD,
                            sensor: str = "none") -> dict:
    """Write ceil(count / scenes_per_shard) shards into `out`, skipping those on disk (resumable).
    sensor: the depth sensor model of the scene clouds (module doc, step 2)."""
    if count < 1:
        raise DatasetError(f"count={count}: write at least one scene")
    draw_sensor(sensor, seed, 0, 0, 0)  # an unknown sensor fails here, before any worker starts
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    shards = -(-count // scenes_per_shard)
    jobs = [(str(out), k, seed, scenes_per_shard, sensor) for k in range(shards) if not shard_path(out, k).exists()]
    res = {"written": 0, "skipped": shards - len(jobs), "scenes": 0, "queries": 0, "positive": [], "cpu": 0.0,
           "failed": []}
    for r in run_jobs(shard_job, jobs, workers=workers, use_ray=use_ray, ray_address=ray_address):
        if r.ok:
            res["written"] += 1
            res["scenes"] += r.value["scenes"]
            res["queries"] += r.value["queries"]
            res["positive"].append(r.value["positive"])
            res["cpu"] += r.value["cpu"]
        else:
            res["failed"].append((r.job[1], r.error))
        if progress is not None:
            progress(r)
    res["positive"] = float(np.mean(res["positive"])) if res["positive"] else float("nan")
    return res


def load_collision_shards(folder, split: str) -> dict:
    """The arrays of every shard of `split` in `folder`, concatenated along the scene axis."""
    files = sorted(Path(folder).glob(f"shard_*_{split}.npz"))
    if not files:
        raise DatasetError(f"no {split} shards in {folder}: write them with `ms-drake data collision --out {folder}`")
    parts = [dict(np.load(f)) for f in files]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
