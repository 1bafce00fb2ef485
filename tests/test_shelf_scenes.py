"""Shelf scenes (Ch. 9.4.1): the generator, its hidden-placement computation and Drake's renders."""

import copy

import numpy as np
import pytest

from ms_drake.errors import SceneError
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import (
    TARGET_SIZES,
    ShelfSceneParams,
    generate_shelf_scene,
    scene_from_dict,
    scene_to_dict,
)
from ms_drake.scenes.shelf_render import render_shelf_scene
from ms_drake.shelf_geometry import (
    Prisms,
    ShelfGeometry,
    exactly_hidden,
    hidden_placements,
    occluded,
    overlap,
    visible_fraction,
)
from ms_drake.types import ShelfObject, ShelfScene

RENDER_SEEDS = 12  # default run; the slow test renders 300


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, "FetchShelf")


@pytest.fixture(scope="module")
def geometry(scenario):
    return ShelfGeometry.from_scenario(scenario)


def test_same_seed_same_scene_and_distributions(geometry):
    a, b = generate_shelf_scene(geometry, 7), generate_shelf_scene(geometry, 7)
    assert a.scene == b.scene
    assert np.array_equal(a.occupancy.floor, b.occupancy.floor)
    assert np.array_equal(a.occupancy.image_x, b.occupancy.image_x)
    assert generate_shelf_scene(geometry, 8).scene != a.scene


@pytest.mark.parametrize("seed", range(12))
def test_generated_scene_meets_the_specification(geometry, seed):
    params = ShelfSceneParams()
    sample = generate_shelf_scene(geometry, seed)
    scene = sample.scene
    n = len(scene.objects)
    assert 2 <= n <= 12
    assert scene.seed == seed
    for o in scene.objects:
        assert o.kind in ("box", "cylinder")
        assert all(0.06 <= v <= 0.20 for v in (o.width, o.depth, o.height))
    bodies = Prisms.of(list(scene.objects) + [scene.target])
    # Everything on the floor, `gap` from the walls and from each other.
    assert np.all(np.abs(bodies.center) + bodies.extent <= geometry.half - params.gap + 1e-9)
    for i in range(len(bodies)):
        others = np.arange(len(bodies)) != i
        assert not overlap(bodies.center[i], bodies.half[i], bodies.radius[i] + params.gap - 1e-6,
                           bodies.center[others], bodies.half[others], bodies.radius[others]).any()
    t = scene.target
    assert (t.width, t.depth, t.height) == TARGET_SIZES["cube"]
    occluders = Prisms.of(scene.objects)
    assert visible_fraction(geometry, t, occluders) == 0.0
    assert exactly_hidden(geometry, occluders, (t.x, t.y), (t.width, t.depth, t.height))
    # Ground truth: both distributions are normalised and hold the target.
    occ = sample.occupancy
    assert occ.floor.sum() == pytest.approx(1.0) and occ.image_x.sum() == pytest.approx(1.0)
    i, j = round((t.y - occ.y0) / occ.step), round((t.x - occ.x0) / occ.step)
    assert occ.floor[i, j] > 0
    u, _, _ = geometry.project(np.array([[t.x, t.y - t.depth / 2, t.height / 2]]))
    assert occ.image_x[int(round(u[0]))] > 0


@pytest.mark.parametrize("name", ["flat", "tall"])
def test_other_target_heights(geometry, name):
    sample = generate_shelf_scene(geometry, 3, num_objects=8, target_size=TARGET_SIZES[name])
    t = sample.scene.target
    assert (t.width, t.depth, t.height) == TARGET_SIZES[name]
    assert visible_fraction(geometry, t, Prisms.of(sample.scene.objects)) == 0.0


def test_hidden_placements_match_ray_casts_and_the_exact_check(geometry):
    """Every placement the grid computation keeps is hidden by dense ray casts of its whole surface;
    placements it drops that are free and in view are seen by some ray; the exact polygon check
    agrees on nearly all kept placements (they differ only within the sampling resolution)."""
    rng = np.random.default_rng(0)
    size = TARGET_SIZES["cube"]
    agree, total = 0, 0
    for seed in (1, 4, 9):
        scene = generate_shelf_scene(geometry, seed, num_objects=8).scene
        occluders = Prisms.of(scene.objects)
        hidden = hidden_placements(geometry, occluders, size)
        kept = hidden.centers
        assert len(kept) > 0
        for c in kept[rng.choice(len(kept), min(25, len(kept)), replace=False)]:
            t = ShelfObject("t", "box", c[0], c[1], *size)
            assert visible_fraction(geometry, t, occluders, samples=16) == 0.0
            agree += exactly_hidden(geometry, occluders, c, size, margin=0.0)
            total += 1
        X, Y = np.meshgrid(*hidden.grid.xy())
        dropped = np.stack([X[~hidden.mask], Y[~hidden.mask]], axis=1)
        free = ~overlap(dropped[:, None], np.array(size[:2]) / 2 + 0.003, 0.0, occluders.center[None],
                        occluders.half[None], occluders.radius[None], tol=0.0).any(axis=1)  # the default clearance
        free &= np.all(np.abs(dropped) + np.array(size[:2]) / 2 <= geometry.half - 0.003, axis=1)
        for c in dropped[free][rng.choice(free.sum(), 25, replace=False)]:
            t = ShelfObject("t", "box", c[0], c[1], *size)
            corners = np.array([[c[0] + sx * size[0] / 2, c[1] + sy * size[1] / 2, z]
                                for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, size[2])])
            if geometry.in_view(corners).all():
                assert visible_fraction(geometry, t, occluders, samples=16) > 0.0
    assert agree / total > 0.95


def test_occluded_ray_casts_on_a_hand_made_scene(geometry):
    wall = Prisms.of([ShelfObject("w", "box", 0.0, 0.0, 0.4, 0.05, 0.15)])
    behind_low = np.array([[0.0, 0.15, 0.05]])
    behind_high = np.array([[0.0, 0.15, 0.5]])
    in_front = np.array([[0.0, -0.15, 0.05]])
    assert occluded(geometry.eye, behind_low, wall)[0]
    assert not occluded(geometry.eye, behind_high, wall)[0]  # the ray passes over the wall
    assert not occluded(geometry.eye, in_front, wall)[0]
    can = Prisms.of([ShelfObject("c", "cylinder", 0.0, 0.0, 0.1, 0.1, 0.15)])
    assert occluded(geometry.eye, behind_low, can)[0]
    assert not occluded(geometry.eye, np.array([[0.2, 0.15, 0.05]]), can)[0]


def test_round_trip_through_dicts(geometry):
    scene = generate_shelf_scene(geometry, 2).scene
    assert scene_from_dict(scene_to_dict(scene)) == scene


def test_bad_requests_raise_clear_errors(geometry, scenario):
    with pytest.raises(SceneError, match="num_objects=13"):
        generate_shelf_scene(geometry, 0, num_objects=13)
    with pytest.raises(SceneError, match="does not fit"):
        generate_shelf_scene(geometry, 0, target_size=(0.7, 0.1, 0.1))
    with pytest.raises(SceneError, match="target_size"):
        generate_shelf_scene(geometry, 0, target_size=(0.06, 0.06))
    bin_scenario = load_scenario(None, "BinHeap15")
    with pytest.raises(SceneError, match="shelf scenario"):
        ShelfGeometry.from_scenario(bin_scenario)
    with pytest.raises(SceneError, match="camera 'side'"):
        ShelfGeometry.from_scenario(scenario, camera="side")


def test_impossible_hiding_place_ends_after_bounded_tries(geometry):
    # Two occluders cannot hide a 25 cm cube: the generator gives up after scene_tries scenes.
    params = ShelfSceneParams(scene_tries=5)
    with pytest.raises(SceneError, match="no placement hides a 0.25 x 0.25 x 0.25 m target behind 2 occluders in 5"):
        generate_shelf_scene(geometry, 0, num_objects=2, target_size=(0.25, 0.25, 0.25), params=params)


def _assert_target_unseen(scenario, geometry, seed):
    sample = generate_shelf_scene(geometry, seed)
    render = render_shelf_scene(scenario, sample.scene)
    assert not render.mask("target").any(), f"seed {seed}: target pixels in the label image"
    assert np.isfinite(render.depth).any()


def test_drake_renders_no_target_pixel(scenario, geometry):
    # The target alone is in view (so the check below can fail) ...
    sample = generate_shelf_scene(geometry, 0)
    alone = render_shelf_scene(scenario, ShelfScene((), sample.scene.target, 0))
    assert alone.mask("target").sum() > 200
    # ... and hidden in the generated scenes.
    for seed in range(RENDER_SEEDS):
        _assert_target_unseen(scenario, geometry, seed)


@pytest.mark.slow
def test_drake_renders_no_target_pixel_on_300_seeds(scenario, geometry):
    for seed in range(1000, 1300):
        _assert_target_unseen(scenario, geometry, seed)


def test_render_needs_a_shelf_scenario(geometry):
    scene = generate_shelf_scene(geometry, 0).scene
    s = copy.deepcopy(load_scenario(None, "BinHeap15"))
    with pytest.raises(SceneError, match="shelf scenario"):
        render_shelf_scene(s, scene)
