"""SceneCollisionNet (ms_drake.collision.scene_net): encoders, queries, mined loss, a training step."""

import numpy as np
import pytest
import torch
import trimesh

from ms_drake.collision.scene_net import (
    SCENE_BOUNDS,
    CollisionNetError,
    NetConfig,
    farthest_points,
    grid_shape,
    make_net,
    mined_loss,
    voxel_centres,
)
from ms_drake.experiments.collision_data import SceneCollisions, query_poses


def test_voxel_grid_covers_the_table_volume():
    cfg = NetConfig()
    assert grid_shape(cfg) == (10, 8, 5)
    c = voxel_centres(cfg)
    assert c.shape == (400, 3)
    lo, hi = np.array(SCENE_BOUNDS).T
    assert np.all(c > lo) and np.all(c < hi)


def test_points_go_to_the_voxel_that_holds_them():
    torch.manual_seed(0)
    net = make_net()
    lo, hi = np.array(SCENE_BOUNDS).T
    p = torch.tensor(np.random.default_rng(0).uniform(lo, hi, (500, 3)), dtype=torch.float32)
    idx = net.voxel_index(p)
    assert torch.all((p - net.centres[idx]).abs() <= 0.05 + 1e-6)
    # outside the grid: clamped to the nearest border voxel
    far = torch.tensor([[5.0, 5.0, 5.0]])
    assert torch.allclose(net.centres[net.voxel_index(far)], torch.tensor([[0.45, 0.35, 0.45]]))


def test_scene_features_pool_per_voxel_and_ignore_point_order():
    torch.manual_seed(0)
    net = make_net().eval()
    pts = torch.tensor(np.random.default_rng(1).uniform([-0.3, -0.3, 0], [0.3, 0.3, 0.2], (800, 3)), dtype=torch.float32)
    with torch.no_grad():
        a = net.scene_features(pts)
        b = net.scene_features(pts[torch.randperm(len(pts))])
    assert a.shape == (400, NetConfig().voxel_features)
    assert torch.allclose(a, b, atol=1e-5)


def test_farthest_points_spread_out():
    pts = torch.cat([torch.randn(200, 3) * 0.001, torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]])])
    chosen = set(farthest_points(pts, 4).tolist())
    assert {200, 201, 202} <= chosen
    with pytest.raises(CollisionNetError):
        farthest_points(torch.zeros(0, 3), 4)


def test_queries_in_a_batch_equal_queries_one_by_one():
    torch.manual_seed(0)
    net = make_net().eval()
    rng = np.random.default_rng(2)
    scene = torch.tensor(rng.uniform([-0.4, -0.3, 0], [0.4, 0.3, 0.2], (1000, 3)), dtype=torch.float32)
    obj = torch.tensor(rng.normal(0, 0.03, (300, 3)), dtype=torch.float32)
    poses = torch.tensor(query_poses(rng, 0.0, np.array([0.5, 0.4]), trajectories=2, per=8), dtype=torch.float32)
    with torch.no_grad():
        code = net.encode(scene, obj)
        batch = net.query(code, poses)
        single = torch.stack([net.query(code, poses[i:i + 1])[0] for i in range(len(poses))])
        full = net(scene, obj, poses)
    assert torch.allclose(batch, single, atol=1e-5) and torch.allclose(batch, full, atol=1e-5)


def test_mined_loss_takes_the_hardest_queries():
    logits = torch.tensor([5.0, -5.0, 0.0, 3.0, -3.0, 0.5, 1.0, -1.0, 2.0, -2.0])
    labels = torch.tensor([0, 1, 1, 1, 0, 0, 1, 0, 1, 0])
    per = torch.nn.functional.binary_cross_entropy_with_logits(logits, labels.float(), reduction="none")
    assert mined_loss(logits, labels, hard=0.2, random=0.0).item() == pytest.approx(per.topk(2).values.mean().item())
    full = mined_loss(logits, labels, hard=1.0, random=0.0).item()
    assert full == pytest.approx(per.mean().item())
    with pytest.raises(CollisionNetError):
        mined_loss(logits, labels, hard=0.0)


def test_a_training_step_lowers_the_loss_on_a_fixed_scene():
    torch.manual_seed(0)
    rng = np.random.default_rng(3)
    box = trimesh.creation.box([0.2, 0.2, 0.15])
    X = np.eye(4)
    X[:3, 3] = [0.0, 0.0, 0.075]
    scene = SceneCollisions([box], [X], (np.array([0.0, 0.0, -0.025]), np.array([1.0, 0.8, 0.05])))
    query = trimesh.creation.box([0.06, 0.04, 0.04])
    poses = query_poses(rng, 0.0, np.array([0.3, 0.3]), trajectories=16, per=16)
    labels = torch.tensor(scene.labels(query, poses))
    assert 0.1 < labels.float().mean() < 0.9
    scene_pts = torch.tensor(trimesh.sample.sample_surface(box, 2000, seed=1)[0] + X[:3, 3], dtype=torch.float32)
    obj_pts = torch.tensor(trimesh.sample.sample_surface(query, 256, seed=2)[0], dtype=torch.float32)
    P = torch.tensor(poses, dtype=torch.float32)
    net = make_net()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def loss():
        return torch.nn.functional.binary_cross_entropy_with_logits(net(scene_pts, obj_pts, P), labels.float())

    with torch.no_grad():
        before = loss().item()
    for _ in range(40):
        opt.zero_grad()
        mined_loss(net(scene_pts, obj_pts, P), labels).backward()
        opt.step()
    with torch.no_grad():
        after = loss().item()
    assert after < 0.7 * before


def _synthetic_shard(path, seed):
    """A shard in `ms-drake data collision`'s format: one box on the table, a small box query."""
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box([0.2, 0.2, 0.15])
    X = np.eye(4)
    X[:3, :3] = trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1])[:3, :3]
    X[:3, 3] = [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 0.075]
    scene = SceneCollisions([box], [X], (np.array([0.0, 0.0, -0.025]), np.array([1.0, 0.8, 0.05])))
    query = trimesh.creation.box([0.06, 0.04, 0.04])
    poses = query_poses(rng, 0.0, np.array([0.3, 0.3]), trajectories=8, per=16)
    pts = trimesh.sample.sample_surface(box, 1000, seed=seed)[0] @ X[:3, :3].T + X[:3, 3]
    np.savez_compressed(path, scene_points=pts[None].astype(np.float32),
                        object_points=trimesh.sample.sample_surface(query, 128, seed=seed)[0][None].astype(np.float32),
                        poses=poses[None].astype(np.float32), labels=scene.labels(query, poses)[None],
                        objects=np.array(["box"]), query=np.array(["small_box"]), seed=np.array([seed]))


def test_training_resumes_and_evaluation_reports_the_table_keys(tmp_path):
    from ms_drake.experiments.collision_learning import (  # noqa: PLC0415 - keeps torch-free imports above
        evaluate_collision,
        train_collision,
    )
    from ms_drake.collision.checker import load_collision_net  # noqa: PLC0415

    for k in range(3):
        _synthetic_shard(tmp_path / f"shard_{k:05d}_train.npz", k)
    _synthetic_shard(tmp_path / "shard_00004_test.npz", 9)
    out = tmp_path / "w.pt"
    meta = train_collision(tmp_path, out, epochs=2, seed=0, lr=3e-3)
    assert meta["epochs_done"] == 2 and meta["train_scenes"] == 3 and out.exists()
    assert out.with_suffix(".ckpt").exists()
    again = train_collision(tmp_path, out, epochs=2, seed=0, lr=3e-3)  # resumes: nothing left to do
    assert again["epochs_done"] == 2 and again["history"] == meta["history"]
    net, ck = load_collision_net(out)
    assert ck["meta"]["train_queries"] == 3 * 128
    r = evaluate_collision(net, tmp_path)
    assert r["queries"] == 128 and 0.0 <= r["accuracy"] <= 1.0 and r["us_per_query"] > 0
    assert {"accuracy", "ap", "us_per_query", "queries"} <= set(r)


def test_train_command_takes_the_device_and_writes_weights_that_load_on_the_cpu(tmp_path):
    from typer.testing import CliRunner  # noqa: PLC0415

    from ms_drake.cli import app  # noqa: PLC0415
    from ms_drake.collision.checker import load_collision_net  # noqa: PLC0415

    for k in range(2):
        _synthetic_shard(tmp_path / f"shard_{k:05d}_train.npz", k)
    out = tmp_path / "w" / "c.pt"
    r = CliRunner().invoke(app, ["train", "collision", "--data", str(tmp_path), "--epochs", "1", "--hidden", "16",
                                 "--voxel-features", "16", "--device", "cpu", "--out", str(out)])
    assert r.exit_code == 0, r.output
    net, ck = load_collision_net(out, device="cpu")
    assert ck["meta"]["device"] == "cpu" and "--device" not in ck["meta"]["command"]  # the default is not spelled out
    assert all(t.device.type == "cpu" for t in ck["model"].values())


def test_a_classifier_on_frozen_encoders_keeps_them_and_learns_its_own_layers(tmp_path):
    from ms_drake.collision.checker import load_collision_net  # noqa: PLC0415
    from ms_drake.collision.scene_net import NetConfig  # noqa: PLC0415
    from ms_drake.errors import DatasetError  # noqa: PLC0415
    from ms_drake.experiments.collision_learning import ENCODERS, train_collision  # noqa: PLC0415

    for k in range(2):
        _synthetic_shard(tmp_path / f"shard_{k:05d}_train.npz", k)
    big = tmp_path / "big.pt"
    train_collision(tmp_path, big, epochs=1, seed=0, lr=3e-3, config=NetConfig(hidden=32, voxel_features=16))
    small = tmp_path / "small.pt"
    meta = train_collision(tmp_path, small, epochs=2, seed=1, lr=3e-3, encoders=big,
                           config=NetConfig(hidden=8, query_layers=0, voxel_features=16))
    assert meta["encoders"] == str(big)
    (a, _), (b, _) = load_collision_net(big), load_collision_net(small)
    for name in ENCODERS:  # copied and not trained
        for (ka, va), (kb, vb) in zip(getattr(a, name).state_dict().items(), getattr(b, name).state_dict().items()):
            assert ka == kb and torch.equal(va, vb)
    assert b.first_pose.weight.shape == (8, 9)  # its own, smaller classifier
    with pytest.raises(DatasetError, match="--voxel-features"):
        train_collision(tmp_path, tmp_path / "bad.pt", epochs=1, encoders=big, config=NetConfig(voxel_features=32))


def test_point_cloud_baselines_on_a_known_scene():
    from ms_drake.collision.baselines import BASELINES, clusters, make_baseline  # noqa: PLC0415

    box = trimesh.creation.box([0.2, 0.2, 0.15])
    X = np.eye(4)
    X[:3, 3] = [0.0, 0.0, 0.075]
    scene_pts = trimesh.sample.sample_surface(box, 4000, seed=1)[0] + X[:3, 3]
    assert len(clusters(scene_pts[scene_pts[:, 2] > 0.003], 0.02)) == 1
    obj = trimesh.sample.sample_surface(trimesh.creation.box([0.04, 0.04, 0.04]), 300, seed=2)[0]
    poses = np.stack([_at(0.3, 0.0, 0.1), _at(0.08, 0.0, 0.1), _at(0.0, 0.0, 0.3), _at(0.3, 0.2, 0.0)])
    for method in BASELINES:
        assert make_baseline(method, scene_pts, obj).query(poses).tolist() == [False, True, False, True], method
    with pytest.raises(CollisionNetError, match="coal_reconstruction"):
        make_baseline("voxblox", scene_pts, obj)


def test_scene_checker_answers_for_every_method_and_named_point_set(tmp_path):
    from ms_drake.collision.checker import METHODS, SceneChecker, load_collision_net  # noqa: PLC0415

    box = trimesh.creation.box([0.2, 0.2, 0.15])
    scene_pts = trimesh.sample.sample_surface(box, 4000, seed=1)[0] + [0.0, 0.0, 0.075]
    small = trimesh.sample.sample_surface(trimesh.creation.box([0.04, 0.04, 0.04]), 300, seed=2)[0]
    poses = np.stack([_at(0.3, 0.0, 0.1), _at(0.08, 0.0, 0.1), _at(0.0, 0.0, 0.3), _at(0.3, 0.2, 0.0)])
    for method in ("coal_reconstruction", "sdf"):
        checker = SceneChecker(method, scene_pts)
        checker.add("small", small)
        assert checker.collides("small", poses).tolist() == [False, True, False, True], method
    torch.manual_seed(0)
    net = make_net(NetConfig()).eval()
    checker = SceneChecker("net", scene_pts, net=net)
    checker.add("small", small)
    checker.add("big", small * 3.0)
    p_small, p_big = checker.query("small", poses), checker.query("big", poses)
    assert p_small.shape == (4,) and np.all((p_small >= 0) & (p_small <= 1))
    with torch.inference_mode():  # the checker's cached codes give the network's own answer
        direct = torch.sigmoid(net(torch.from_numpy(scene_pts.astype(np.float32)),
                                   torch.from_numpy(small.astype(np.float32)),
                                   torch.from_numpy(poses.astype(np.float32)))).numpy()
    assert np.allclose(p_small, direct, atol=1e-6) and not np.allclose(p_small, p_big)
    assert set(METHODS) == {"net", "pointnet_grid", "coal_reconstruction", "sdf"}
    with pytest.raises(CollisionNetError, match="not added; added: small, big"):
        checker.query("mug", poses)
    with pytest.raises(CollisionNetError, match="choose one of net, pointnet_grid"):
        SceneChecker("voxblox", scene_pts)
    with pytest.raises(CollisionNetError, match="not found: train them"):
        load_collision_net(tmp_path / "missing.pt")
    path = tmp_path / "grid.pt"
    torch.save(dict(model=net.state_dict(), config=dict(NetConfig().__dict__)), path)
    with pytest.raises(CollisionNetError, match="not a 'pointnet_grid' network"):
        load_collision_net(path, "pointnet_grid")


def _at(x, y, z):
    X = np.eye(4)
    X[:3, 3] = [x, y, z]
    return X


def test_pointnet_grid_ablation_has_no_3d_convolutions():
    torch.manual_seed(0)
    net = make_net(NetConfig(conv_layers=0)).eval()
    assert not any(isinstance(m, torch.nn.Conv3d) for m in net.modules())
    pts = torch.tensor(np.random.default_rng(4).uniform([-0.3, -0.3, 0], [0.3, 0.3, 0.2], (500, 3)), dtype=torch.float32)
    with torch.no_grad():
        f = net.scene_features(pts)
    empty = torch.ones(400, dtype=torch.bool)
    empty[net.voxel_index(pts)] = False
    assert torch.all(f[empty] == 0)  # a voxel without points sees nothing of its neighbours
    with pytest.raises(CollisionNetError, match="conv_layers=0"):
        make_net(NetConfig(conv_layers=0, point_features=32))
