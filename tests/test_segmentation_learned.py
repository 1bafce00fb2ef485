"""Learned depth segmentation (Ch. 5): the dataset writer, the targets and grouping, a training step,
the shipped weights against Euclidean clustering, and Segmenter("learned") alone and wired."""

import copy
import json

import numpy as np
import pytest
from pycocotools import mask as mask_utils
from pycocotools.coco import COCO
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.errors import DatasetError, PerceptionError
from ms_drake.experiments.segmentation_data import (
    draw_sensor,
    load_working,
    sensor_model,
    write_segmentation_dataset,
)
from ms_drake.experiments.segmentation_learning import (
    bench_image,
    bench_job,
    make_batch,
    make_optimizer,
    train_steps,
)
from ms_drake.perception.masks import object_labels
from ms_drake.perception.segmentation import Segmenter, coco_mask_metrics, coco_metrics
from ms_drake.perception.segmentation_net import (
    WORK_SHAPE,
    NetConfig,
    class_targets,
    default_weights,
    full_resolution_masks,
    instances_from_probabilities,
    make_net,
    working_inputs,
)
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant

HELD_OUT = range(900_000, 900_008)  # images for the weights test, outside the benchmark's seeds


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("seg")
    res = write_segmentation_dataset(out, 10, seed=3, views=2, heaps_per_shard=1)
    return out, res


def test_writer_coco_files_and_split_by_object(tiny_dataset):
    out, res = tiny_dataset
    assert res["written"] == 5 and not res["failed"] and res["images"] == 10
    names = sorted(p.name for p in out.glob("shard_*.npz"))
    assert names[-1] == "shard_00004_test.npz" and all(n.endswith("_train.npz") for n in names[:-1])
    objects = {}
    for split in ("train", "test"):
        coco = COCO(str(out / f"coco_{split}.json"))
        assert coco.getImgIds() and coco.getAnnIds()
        objects[split] = {a["object"] for a in coco.dataset["annotations"]}
        # Every annotation decodes to its image's label pixels.
        for img in coco.dataset["images"][:2]:
            shard, i = img["file_name"].split("#")
            labels = np.load(out / shard)["labels"][int(i)]
            for k, ann in enumerate(coco.loadAnns(coco.getAnnIds(imgIds=img["id"]))):
                m = coco.annToMask(ann).astype(bool)
                assert m.sum() >= 20 and np.array_equal(m, labels == k + 1)
                assert ann["object"] == img["objects"][k]
    assert objects["train"] and objects["test"] and not objects["train"] & objects["test"]
    # Resume: a second run writes nothing.
    again = write_segmentation_dataset(out, 10, seed=3, views=2, heaps_per_shard=1)
    assert again["written"] == 0 and again["skipped"] == 5
    w = load_working(out, "train")
    assert w["x"].shape == (8, 2, *WORK_SHAPE) and w["lab"].shape == (8, *WORK_SHAPE) and w["lab"].max() >= 1
    with pytest.raises(DatasetError, match="no test shards"):
        load_working(out / "nothing", "test")


def test_data_command_draws_sensor_presets_per_image_reproducibly(tmp_path, tiny_dataset):
    from typer.testing import CliRunner

    from ms_drake.cli import app
    from ms_drake.station.sensor_model import PRESETS

    # The draw: a function of (seed, shard, heap, view) alone; every preset comes up.
    draws = [draw_sensor("random", 5, k, j, v) for k in range(4) for j in range(2) for v in range(4)]
    assert {d[0] for d in draws} == set(PRESETS)
    again = draw_sensor("random", 5, 3, 1, 2)
    assert again[:2] == draws[-2][:2] and again[2].random() == draws[-2][2].random()
    jittered = [p for name, p, _ in draws if name == "l515"]
    assert jittered and all(p != PRESETS["l515"] for p in jittered)
    assert draw_sensor("phoxi", 5, 0, 0, 0)[1] == PRESETS["phoxi"]
    with pytest.raises(DatasetError, match="sensor"):
        draw_sensor("kinect", 0, 0, 0, 0)

    # The command: one heap, 4 views, each through its own preset; a rerun writes the same shard.
    z = []
    for run in ("a", "b"):
        r = CliRunner().invoke(app, ["data", "segmentation", "--count", "4", "--views", "4", "--heaps-per-shard", "1",
                                    "--seed", "3", "--sensor", "random", "--out", str(tmp_path / run)])
        assert r.exit_code == 0, r.output
        z.append(np.load(tmp_path / run / "shard_00000_train.npz"))
    assert len(set(z[0]["sensor"])) >= 2 and "none" in set(z[0]["sensor"])
    for key in ("sensor", "sensor_params", "depth", "x", "lab"):
        assert np.array_equal(z[0][key], z[1][key]), key
    # The same heap and camera as the data without sensors (tiny_dataset: seed 3); the holes are
    # filled before the network's inputs are made, as the station's consumers read the depth.
    clean = np.load(tiny_dataset[0] / "shard_00000_train.npz")
    assert "sensor" not in clean.files and np.array_equal(clean["labels"][:2], z[0]["labels"][:2])
    for name, depth, x in zip(z[0]["sensor"], z[0]["depth"], z[0]["x"]):
        if name == "none":
            assert not (depth == 0).any()
        else:
            assert (depth == 0).any()
        assert np.all(x[1] == 1.0)  # valid fraction: every pixel after hole filling
    assert CliRunner().invoke(app, ["data", "segmentation", "--count", "1", "--sensor", "kinect",
                                    "--out", str(tmp_path / "c")]).exit_code != 0


def test_sensor_model_noise_and_dropout():
    d = np.full((60, 80), 0.8, np.float32)
    d[20:40, 20:40] = 0.75
    rng = np.random.default_rng(0)
    assert np.array_equal(sensor_model(d, rng), d)
    noisy = sensor_model(d, rng, noise=0.001, dropout=0.1)
    lost = noisy == 0
    assert 0.05 < lost.mean() < 0.15
    assert 0.0008 < np.std((noisy - d)[~lost]) < 0.0012
    with pytest.raises(DatasetError, match="dropout"):
        write_segmentation_dataset("/nonexistent", 1, dropout=1.5)


def test_class_targets_mark_contacts_only():
    lab = np.zeros((20, 30), np.uint8)
    lab[5:15, 2:10] = 1
    lab[5:15, 10:18] = 2  # touches object 1 at column 9 | 10
    lab[5:15, 22:28] = 3  # alone
    c = class_targets(lab)
    assert set(np.unique(c[lab == 0])) == {0}
    assert (c[5:15, 8:12] == 2).all() and (c[:, :8] != 2).all() and (c[:, 12:] != 2).all()
    assert (c[lab == 3] == 1).all()


def test_grouping_splits_at_boundaries_and_scores():
    prob = np.zeros((3, 40, 60))
    prob[0] = 1.0
    for x0, x1 in ((5, 20), (22, 40)):
        prob[:, 10:30, x0:x1] = [[[0.0]], [[0.9]], [[0.1]]]
    prob[:, 10:30, 20:22] = [[[0.0]], [[0.1]], [[0.9]]]  # the boundary between them
    labels, scores = instances_from_probabilities(prob)
    assert len(scores) == 2 and np.allclose(scores, 0.9)
    assert set(np.unique(labels[10:30, 5:22])) == {1, 2} and (labels[prob[0] > 0.5] == 0).all()
    full = full_resolution_masks(np.zeros(WORK_SHAPE, np.int32), np.zeros(0))
    assert len(full) == 0 and full.masks.shape[1:] == (480, 640)


def test_training_steps_lower_the_loss_on_a_fixed_batch(tiny_dataset):
    import torch

    torch.manual_seed(0)
    w = load_working(tiny_dataset[0], "train")
    y = np.stack([class_targets(m) for m in w["lab"]])
    x, yb = make_batch(w["x"], y, np.arange(4), np.random.default_rng(0))
    assert x.shape == (4, 2, 96, 128) and yb.shape == (4, 96, 128) and (yb > 0).any()
    net = make_net(NetConfig(fine=4, base=8, levels=3))
    losses = train_steps(net, make_optimizer(net, lr=5e-3), x, yb, steps=25)
    assert losses[-1] < 0.6 * losses[0]


@pytest.mark.skipif(not default_weights().is_file(), reason="no shipped segmentation weights")
def test_shipped_weights_beat_euclidean_clustering_on_held_out_images():
    gt, learned, eucl = [], [], []
    for backend, rows in (("learned", learned), ("euclidean", eucl)):
        rows += bench_job((backend, tuple(HELD_OUT), 0.0, 0.0, None))
    gt = [r["gt"] for r in learned]
    assert [r["gt"]["rles"] for r in eucl] == [g["rles"] for g in gt]  # the same images
    ap_learned = coco_metrics(gt, [r["dt"] for r in learned])["AP"]
    ap_eucl = coco_metrics(gt, [r["dt"] for r in eucl])["AP"]
    assert ap_learned > ap_eucl + 0.1, (ap_learned, ap_eucl)


def _depth_image(d: np.ndarray) -> ImageDepth32F:
    img = ImageDepth32F(d.shape[1], d.shape[0])
    np.array(img.mutable_data, copy=False)[:, :, 0] = d
    return img


@pytest.mark.skipif(not default_weights().is_file(), reason="no shipped segmentation weights")
def test_learned_segmenter_alone_with_a_fixed_depth_image():
    depth, gt, _ = bench_image(HELD_OUT[0])
    seg = Segmenter("learned")
    ctx = seg.CreateDefaultContext()
    with pytest.raises(PerceptionError, match="not connected"):
        seg.GetOutputPort("masks").Eval(ctx)
    seg.GetInputPort("depth_image").FixValue(ctx, _depth_image(depth))
    out = seg.GetOutputPort("masks").Eval(ctx)
    assert out.masks.shape[1:] == (480, 640) and len(out) >= 1
    assert np.all(np.diff(out.scores) <= 0) and ((0 < out.scores) & (out.scores <= 1)).all()
    assert not (out.masks.sum(axis=0) > 1).any()  # instances do not overlap
    assert coco_mask_metrics([gt], [out])["AP50"] > 0.3
    assert len(seg.learned.segment(np.zeros((480, 640), np.float32))) == 0  # nothing seen, nothing found
    with pytest.raises(PerceptionError, match="640x480"):
        working_inputs(np.ones((10, 10)))
    with pytest.raises(PerceptionError, match="not found"):
        Segmenter("learned", weights="/nonexistent/segmentation.pt")


@pytest.mark.skipif(not default_weights().is_file(), reason="no shipped segmentation weights")
def test_learned_segmenter_wired_to_a_station(bin_scenario, small_heap):
    s = scenario_with_heap(copy.deepcopy(bin_scenario), small_heap)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(s))
    seg = builder.AddSystem(Segmenter("learned"))
    builder.Connect(station.GetOutputPort("overhead.depth_image"), seg.GetInputPort("depth_image"))
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    set_heap_poses(station, ctx, small_heap)
    out = seg.GetOutputPort("masks").Eval(seg.GetMyContextFromRoot(ctx))
    labels = np.array(station.GetOutputPort("overhead.label_image").Eval(
        station.GetMyContextFromRoot(ctx)).data)[:, :, 0]
    from_labels = Segmenter("ground_truth", label_to_id=object_labels(get_plant(station))).segment(labels=labels)
    assert len(out) >= 1
    assert coco_mask_metrics([from_labels], [out])["AP50"] > 0.3


def test_coco_file_of_the_writer_is_pycocotools_json(tiny_dataset):
    c = json.loads((tiny_dataset[0] / "coco_test.json").read_text())
    assert c["categories"] == [{"id": 1, "name": "object"}]
    rle = dict(c["annotations"][0]["segmentation"])
    assert mask_utils.area(rle) == c["annotations"][0]["area"]
