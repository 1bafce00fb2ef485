"""The learned shelf occupancy (Ch. 9.4.2): a training step, the shipped weights against a uniform
P(x) on held-out scenes, ShelfOccupancyEstimator("learned") alone (FixValue depth) and wired."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.experiments.shelf import SCENARIO, shelf_geometry, shelf_rollout
from ms_drake.policies.shelf_search import ShelfSearchConfig
from ms_drake.experiments.shelf_learning import (
    batch_arrays,
    make_optimizer,
    total_variation,
    train_steps,
)
from ms_drake.perception.shelf_occupancy import ShelfOccupancyEstimator
from ms_drake.perception.shelf_occupancy_net import (
    HEAD_SIZES,
    WORK_SHAPE,
    LearnedShelfOccupancy,
    NetConfig,
    default_weights,
    head_index,
    make_net,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import generate_shelf_scene
from ms_drake.scenes.shelf_render import render_shelf_scene

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def geometry():
    return shelf_geometry(SCENARIO)


@pytest.fixture(scope="module")
def held_out(geometry):
    """Three scenes from the test seed range (one per target height) with their depth renders."""
    scenario = load_scenario(None, SCENARIO)
    out = []
    for seed, size in zip((900001, 900002, 900003), HEAD_SIZES):
        sample = generate_shelf_scene(geometry, seed, None, size)
        out.append((sample, size, render_shelf_scene(scenario, sample.scene).depth))
    return out


def test_a_training_step_lowers_the_loss():
    torch.manual_seed(0)
    net = make_net(NetConfig(channels=(8, 8, 8, 8, 8), width=16, dilations=(1, 2)))
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, (4,) + WORK_SHAPE).astype(np.float32)
    gt = np.zeros((4, 3, 640), np.float32)
    for i in range(4):
        gt[i, :, 100 * i + 40:100 * i + 200] = 1 / 160
    gt[0, 2] = 0  # an empty head is left out of the loss
    x, y = batch_arrays(depth, gt)
    losses = train_steps(net, make_optimizer(net, lr=1e-2), x, y, steps=15)
    assert np.isfinite(losses).all() and losses[-1] < 0.9 * losses[0]


def test_head_index():
    assert [head_index(s) for s in HEAD_SIZES] == [0, 1, 2]
    assert head_index((0.05, 0.05, 0.1)) == 2


def test_shipped_weights_beat_uniform(held_out):
    assert default_weights().exists(), "models/weights/shelf_occupancy.pt: see models/weights/shelf_occupancy.md"
    model = LearnedShelfOccupancy()
    for sample, size, depth in held_out:
        p = model.predict(depth, size)
        q = sample.occupancy.image_x
        assert p.shape == (640,) and abs(p.sum() - 1) < 1e-4
        assert total_variation(p, q) < total_variation(np.full(640, 1 / 640), q) - 0.1


def test_estimator_learned_alone(geometry, held_out):
    _, size, depth = held_out[0]
    est = ShelfOccupancyEstimator(geometry, size, backend="learned")
    context = est.CreateDefaultContext()
    image = ImageDepth32F(640, 480)
    image.mutable_data[:, :, 0] = depth
    est.GetInputPort("depth_image").FixValue(context, image)
    occ = est.GetOutputPort("occupancy").Eval(context)
    assert occ.image_x.shape == (640,) and abs(occ.image_x.sum() - 1) < 1e-4 and occ.floor.shape == (0, 0)
    assert np.allclose(occ.image_x, LearnedShelfOccupancy().predict(depth, size))
    with pytest.raises(Exception, match="connect the depth_image input"):
        est.GetOutputPort("occupancy").Eval(est.CreateDefaultContext())


def test_learned_perception_wired_to_foss():
    r = shelf_rollout(ShelfSearchConfig(policy="dar", perception="learned"), 4, 3)
    assert r["perception"] == "learned" and r["steps"] >= 1 and np.isfinite(r["perception_ms"])
