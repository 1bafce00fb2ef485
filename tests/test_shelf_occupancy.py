"""ShelfOccupancyEstimator: the ground-truth backend alone and wired to FOSS; the learned backend's error
(missing weights; the learned backend itself: tests/test_shelf_occupancy_learned.py)."""

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from ms_drake.errors import PerceptionError
from ms_drake.foss import Foss, FossSystem
from ms_drake.perception.shelf_occupancy import ShelfOccupancyEstimator, ground_truth_occupancy
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import generate_shelf_scene
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.types import ShelfObject, ShelfScene


@pytest.fixture(scope="module")
def geometry():
    return ShelfGeometry.from_scenario(load_scenario(None, "FetchShelf"))


def cell(occ, x, y):
    return round((y - occ.y0) / occ.step), round((x - occ.x0) / occ.step)


def test_estimator_alone_gives_the_hidden_placements(geometry):
    sample = generate_shelf_scene(geometry, 5, num_objects=8)
    est = ShelfOccupancyEstimator(geometry)
    context = est.CreateDefaultContext()
    est.GetInputPort("scene").FixValue(context, sample.scene)
    occ = est.GetOutputPort("occupancy").Eval(context)
    assert occ.floor.sum() == pytest.approx(1.0) and occ.image_x.sum() == pytest.approx(1.0)
    assert occ.image_x.shape == (geometry.camera.width,)
    # The generator's placements keep 5 mm from the occluders, the estimator's touch them: a superset.
    assert np.all((occ.floor > 0) | (sample.occupancy.floor == 0))
    assert (occ.floor > 0).sum() > (sample.occupancy.floor > 0).sum()
    t = sample.scene.target
    assert occ.floor[cell(occ, t.x, t.y)] > 0
    # Without the target in the scene, the same distribution (the target is not used while hidden,
    # beyond keeping its true placement).
    assert np.array_equal(ground_truth_occupancy(geometry, sample.scene.without_target(), (0.06, 0.06, 0.06)).floor
                          > 0, occ.floor > 0)


def test_a_seen_target_collapses_the_distribution(geometry):
    t = ShelfObject("target", "box", 0.0, 0.1, 0.06, 0.06, 0.06)
    half_hidden = ShelfScene((ShelfObject("o", "box", -0.1, -0.05, 0.2, 0.05, 0.2),), t, 0)
    occ = ground_truth_occupancy(geometry, half_hidden)
    assert (occ.floor > 0).sum() == 1 and occ.floor[cell(occ, t.x, t.y)] == 1.0
    u, _, _ = geometry.project(np.array([[t.x, t.y - 0.03, 0.03]]))
    assert occ.image_x[int(round(u[0]))] > 0 and (occ.image_x > 0).sum() < 100


def test_no_occluders_no_hiding_place(geometry):
    occ = ground_truth_occupancy(geometry, ShelfScene(()), (0.06, 0.06, 0.06))
    assert occ.floor.sum() == 0 and occ.image_x.sum() == 0


def test_backends(geometry, tmp_path):
    with pytest.raises(PerceptionError, match=r"none.pt.*ms-drake train shelf-occupancy.*ground_truth"):
        ShelfOccupancyEstimator(geometry, backend="learned", weights=tmp_path / "none.pt")
    with pytest.raises(PerceptionError, match="ground_truth, learned"):
        ShelfOccupancyEstimator(geometry, backend="magic")
    with pytest.raises(PerceptionError, match="target_size"):
        ShelfOccupancyEstimator(geometry, target_size=(0.06, 0.06))
    est = ShelfOccupancyEstimator(geometry)
    with pytest.raises(PerceptionError, match="connect the scene input"):
        est.GetOutputPort("occupancy").Eval(est.CreateDefaultContext())


def test_estimator_wired_to_foss(geometry):
    sample = generate_shelf_scene(geometry, 11, num_objects=6)
    builder = DiagramBuilder()
    sim = builder.AddSystem(FossSystem(Foss(geometry), sample.scene))
    est = builder.AddSystem(ShelfOccupancyEstimator(geometry, target_size=(0.06, 0.06, 0.06)))
    builder.Connect(sim.GetOutputPort("scene"), est.GetInputPort("scene"))
    builder.ExportOutput(est.GetOutputPort("occupancy"), "occupancy")
    diagram = builder.Build()
    occ = diagram.GetOutputPort("occupancy").Eval(diagram.CreateDefaultContext())
    assert np.array_equal(occ.image_x, ground_truth_occupancy(geometry, sample.scene).image_x)
