"""The scene-collision dataset of Ch. 6 (ms_drake.experiments.collision_data)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ms_drake.errors import DatasetError
from ms_drake.experiments.collision_data import (
    OBJECT_POINTS,
    POSES_PER_TRAJECTORY,
    SCENE_POINTS,
    TRAJECTORIES,
    SceneCollisions,
    load_collision_shards,
    make_scene,
    query_poses,
    write_collision_dataset,
)
from ms_drake.grasping.meshes import object_mesh
from ms_drake.objects import get_object_set


def _box_scene():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    X = np.eye(4)
    X[:3, 3] = [0.0, 0.0, 0.05]  # resting on the table top (z = 0)
    return SceneCollisions([box], [X], (np.array([0.0, 0.0, -0.025]), np.array([1.0, 0.8, 0.05])))


def _at(x, y, z):
    X = np.eye(4)
    X[:3, 3] = [x, y, z]
    return X


def test_labels_of_a_known_scene():
    scene = _box_scene()
    q = trimesh.creation.box([0.02, 0.02, 0.02])
    poses = np.stack([_at(0.3, 0.0, 0.2),     # free, above the table
                      _at(0.06, 0.0, 0.05),   # overlaps the box's side
                      _at(0.0, 0.0, 0.05),    # wholly inside the box (no surface crossing)
                      _at(0.3, 0.0, 0.0),     # half in the table
                      _at(0.12, 0.0, 0.05)])  # 1 cm beside the box
    assert scene.labels(q, poses).tolist() == [False, True, True, True, False]


def test_query_poses_are_linear_trajectories_over_the_table():
    rng = np.random.default_rng(0)
    P = query_poses(rng, 0.0, np.array([0.5, 0.4]))
    assert P.shape == (TRAJECTORIES * POSES_PER_TRAJECTORY, 4, 4)
    t = P[:, :3, 3].reshape(TRAJECTORIES, POSES_PER_TRAJECTORY, 3)
    steps = np.diff(t, axis=1)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[:, :1], steps.shape), atol=1e-9)  # straight, even steps
    assert np.all(np.abs(t[..., 0]) <= 0.5) and np.all(np.abs(t[..., 1]) <= 0.4) and np.all(t[..., 2] >= 0)
    R = P[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)


def test_a_scene_labels_agree_with_point_containment():
    s = make_scene(3, 0, 1, "train")
    assert s["scene_points"].shape == (SCENE_POINTS, 3) and s["object_points"].shape == (OBJECT_POINTS, 3)
    assert s["poses"].shape == (TRAJECTORIES * POSES_PER_TRAJECTORY, 4, 4) and s["labels"].dtype == bool
    assert 0.02 < s["labels"].mean() < 0.9
    assert s["scene_points"][:, 2].min() >= 0.0  # cropped to the volume above the table
    names = s["objects"].split(",")
    assert len(names) >= 8 and np.isfinite(s["object_poses"][:len(names)]).all()
    assert np.isnan(s["object_poses"][len(names):]).all()
    train = {o.full_name for o in get_object_set(s["query"].split("/")[0]).split("train")}
    assert s["query"] in train
    # an independent check: at poses labelled free, no surface point of the query lies in a scene
    # mesh or under the table top; most poses labelled in collision have such a point
    pts = np.c_[s["object_points"].astype(float), np.ones(OBJECT_POINTS)]
    meshes = [object_mesh(n) for n in names]
    idx = np.random.default_rng(0).choice(len(s["labels"]), 120, replace=False)
    inside = []
    for i in idx:
        p_W = (s["poses"][i].astype(float) @ pts.T).T
        hit = p_W[:, 2].min() < -1e-3
        for m, X in zip(meshes, s["object_poses"][:len(names)].astype(float)):
            if hit:
                break
            p_S = (np.linalg.inv(X) @ p_W.T).T[:, :3]
            hit = bool(m.contains(p_S).any())
        inside.append(hit)
    inside, labels = np.array(inside), s["labels"][idx]
    assert not np.any(inside & ~labels)
    assert inside[labels].mean() > 0.7


def test_writer_is_resumable_and_splits_by_object(tmp_path):
    res = write_collision_dataset(tmp_path, 2, seed=1, scenes_per_shard=1)
    assert res["written"] == 2 and res["scenes"] == 2 and res["queries"] == 2 * 2048
    again = write_collision_dataset(tmp_path, 2, seed=1, scenes_per_shard=1)
    assert again["written"] == 0 and again["skipped"] == 2
    train = load_collision_shards(tmp_path, "train")
    assert train["labels"].shape == (2, 2048) and train["scene_points"].dtype == np.float32
    test_names = {o.full_name for s in ("ycb", "random_urdfs") for o in get_object_set(s).split("test")}
    for row in train["objects"]:
        assert not set(row.split(",")) & test_names
    assert not set(train["query"]) & test_names
    with pytest.raises(DatasetError, match="no test shards"):
        load_collision_shards(tmp_path, "test")


def test_object_mesh_frames_are_the_placement_frames():
    # the scene's labels use object_mesh in the body frame the placements are given in
    m = object_mesh("ycb/077_rubiks_cube")
    assert m.is_watertight and np.linalg.norm(m.bounds.mean(axis=0)) < 0.05


def test_a_sensor_model_changes_the_cloud_and_nothing_else():
    clean = make_scene(3, 0, 1, "train")
    noisy = make_scene(3, 0, 1, "train", sensor="primesense")
    again = make_scene(3, 0, 1, "train", sensor="primesense")
    assert clean["sensor"] == "none" and noisy["sensor"] == "primesense"
    for key in ("objects", "query", "poses", "labels", "object_points", "X_WC"):
        assert np.array_equal(clean[key], noisy[key]), key
    assert np.array_equal(noisy["scene_points"], again["scene_points"])  # drawn from the seed
    assert not np.array_equal(clean["scene_points"], noisy["scene_points"])
    # the same surfaces, seen through the sensor: each noisy point lies near the clean cloud
    d, _ = cKDTree(clean["scene_points"]).query(noisy["scene_points"])
    assert np.median(d) < 0.01
    with pytest.raises(DatasetError, match="sensor 'kinect'"):
        write_collision_dataset("unused", 1, sensor="kinect")
