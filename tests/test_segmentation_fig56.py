"""Learned segmentation, robustness and Fig. 5.6 tools: noisy benchmark images made from the cached
noise-free ones, and training on a subset of the objects (the other objects' pixels carry no loss)."""

import numpy as np
import pytest

from ms_drake.errors import DatasetError
from ms_drake.experiments.segmentation_data import write_segmentation_dataset
from ms_drake.experiments.segmentation_learning import (
    TrainingImages,
    bench_image,
    cached_bench_image,
    object_subset,
    train_segmentation,
)
from ms_drake.perception.segmentation_net import (
    IGNORE,
    class_targets,
    segmentation_loss,
)
from ms_drake.scenario import load_scenario

SEED = 900_100  # outside the benchmark's seeds


def test_noisy_image_from_the_clean_cache_equals_a_noisy_rendering(tmp_path):
    scenario = load_scenario(None, "BinHeap15")
    d0, gt0, _ = cached_bench_image(SEED, 0.0, 0.0, scenario, tmp_path)  # renders and caches
    assert (tmp_path / f"img_{SEED}_0_0.npz").exists()
    d1, gt1, _ = cached_bench_image(SEED, 0.002, 0.05, scenario, tmp_path)  # from the cache
    assert not (tmp_path / f"img_{SEED}_0.002_0.05.npz").exists()
    d2, gt2, _ = bench_image(SEED, 0.002, 0.05, scenario)  # rendered with the sensor model
    np.testing.assert_array_equal(d1, d2)
    assert gt1.ids == gt2.ids == gt0.ids
    np.testing.assert_array_equal(gt1.masks, gt2.masks)
    lost = d1 == 0
    assert 0.03 < lost.mean() < 0.07 and not (d0 == 0).any()
    assert 0.001 < np.std((d1 - d0)[~lost & np.isfinite(d0)]) < 0.003


def test_object_subsets_are_stratified_nested_and_seeded():
    names = [f"ycb/o{i}" for i in range(16)] + [f"procedural/p{i}" for i in range(300)]
    q, h, a = (object_subset(names, f, seed=0) for f in (0.25, 0.5, 1.0))
    assert q < h < a and a == set(names)
    assert sum(n.startswith("ycb/") for n in q) == 4 and sum(n.startswith("procedural/") for n in q) == 75
    assert object_subset(names, 0.25, seed=1) != q
    with pytest.raises(DatasetError, match="fraction"):
        object_subset(names, 0.0)


def test_ignored_pixels_carry_no_loss():
    import torch

    logits = torch.randn(1, 3, 4, 5)
    t = torch.zeros(1, 4, 5, dtype=torch.int64)
    t[0, :2] = 1
    t2 = t.clone()
    t2[0, 3] = IGNORE
    full = segmentation_loss(logits, t)
    part = segmentation_loss(logits[..., :3, :], t[:, :3])
    assert torch.isclose(segmentation_loss(logits, t2), part) and not torch.isclose(full, part)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("seg56")
    write_segmentation_dataset(out, 8, seed=5, views=2, heaps_per_shard=1)
    return out


def test_training_images_ignore_the_objects_outside_the_subset(tiny_dataset):
    full = TrainingImages(tiny_dataset)
    half = TrainingImages(tiny_dataset, object_fraction=0.5, object_seed=0)
    assert len(full.x) == len(half.x) > 0
    seen = {n for o in half.objects for n in o}
    assert half.object_counts()["objects_seen"] == len(seen) and 0 < len(half.kept) < len(seen)
    ignored = 0
    for i, names in enumerate(half.objects):
        lab = half.lab[i]
        for k, n in enumerate(names):
            px = lab == k + 1
            if n in half.kept:
                np.testing.assert_array_equal(half.y[i][px], class_targets(lab)[px])
            else:
                assert (half.y[i][px] == IGNORE).all()
                ignored += int(px.sum())
        np.testing.assert_array_equal(half.y[i][lab == 0], full.y[i][lab == 0])
    assert ignored > 0


def test_training_on_an_object_subset_records_it(tiny_dataset, tmp_path):
    meta = train_segmentation(tiny_dataset, tmp_path / "w.pt", epochs=1, batch=2, steps_per_epoch=2,
                              object_fraction=0.5, max_minutes=5)
    assert meta["object_fraction"] == 0.5 and 0 < meta["objects_trained"] < meta["objects_seen"]
    assert (tmp_path / "w.pt").exists() and np.isfinite(meta["history"][0]["loss"])


def test_sensor_augmentation_remakes_half_the_inputs_from_depth(tiny_dataset):
    from ms_drake.experiments.segmentation_learning import augmented_inputs

    images = TrainingImages(tiny_dataset, depth=True)
    assert images.depth.shape == (len(images.x), 480, 640)
    idx = np.arange(len(images.x))
    x = augmented_inputs(images, idx, np.random.default_rng(0), 0.002, 0.05)
    changed = [not np.allclose(x[j], images.x[j].astype(np.float32), atol=1e-2) for j in idx]
    assert 0 < sum(changed) < len(idx)
    for j in np.flatnonzero(changed):
        assert (x[j, 1] < 1).mean() > 0.05  # blocks with a missing pixel


def test_training_with_sensor_augmentation_records_it(tiny_dataset, tmp_path):
    meta = train_segmentation(tiny_dataset, tmp_path / "w.pt", epochs=1, batch=2, steps_per_epoch=2,
                              noise=0.002, dropout=0.05, max_minutes=5)
    assert meta["noise"] == 0.002 and meta["dropout"] == 0.05 and np.isfinite(meta["history"][0]["loss"])
