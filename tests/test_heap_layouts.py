"""The named heap layouts of the bin search (ms_drake.scenes.layouts): compact (Table 8.2),
ycb_hidden, lid, bin_set and bin_set_bullet."""

import dataclasses
import functools

import numpy as np
import pytest

from ms_drake.errors import HeapError
from ms_drake.experiments.rollout import build_search
from ms_drake.objects import get_object, get_object_set
from ms_drake.policies.bin_search import BinSearchConfig
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap, sample_drop_plan, set_heap_poses
from ms_drake.scenes.layouts import (
    HEAP_LAYOUTS,
    LID_TARGET,
    SMALL_TARGET,
    HeapConfig,
    _names,
    cached_heap,
    layout_heap,
    occluder_pool,
)
from ms_drake.station.robots import set_arm_positions


def test_the_layouts_and_a_bad_one():
    assert list(HEAP_LAYOUTS) == ["compact", "ycb_hidden", "lid", "bin_set", "bin_set_bullet"]
    assert all(layout.description for layout in HEAP_LAYOUTS.values())
    with pytest.raises(HeapError, match="heap layout 'xray' unknown; choose one of compact"):
        HeapConfig("xray")
    with pytest.raises(HeapError, match="1..60"):
        HeapConfig("compact", 0)


def test_the_household_occluders_are_unseen_ycb_models_and_packaged_objects():
    pool = occluder_pool("unseen_household")
    assert len(pool) == len(set(pool))
    assert [n.split("/")[0] for n in pool].count("procedural") == 13
    assert all(n.startswith("procedural/packaged_") for n in pool[-13:])
    ycb_unseen = get_object_set("ycb_unseen")
    assert {o.name for o in ycb_unseen.objects}.isdisjoint(get_object_set("ycb").names())
    assert {f"ycb_unseen/{n}" for n in ycb_unseen.names()} <= set(pool)
    # never in the occupancy network's training heaps, which draw from the train splits
    assert all(get_object(n).split == "test" for n in pool)
    assert set(pool).isdisjoint(occluder_pool("unseen_mesh")[9:])  # no random_urdfs blob


def test_a_hidden_target_layout_starts_with_the_target_hidden_from_the_station_camera():
    heap = layout_heap(HeapConfig("ycb_hidden", 14), 5002)
    assert heap.target == SMALL_TARGET and heap.target_index == 0 and heap.visible_ratios[0] == 0.0
    assert {o.name for o in heap.objects[1:]} <= set(occluder_pool("unseen_household"))
    # what the search's own camera and target detector see: no target
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap, BinSearchConfig(policy="largest"))
    ctx = system.diagram.CreateDefaultContext()
    set_heap_poses(system.station, ctx, heap)
    set_arm_positions(system.plant, system.plant.GetMyMutableContextFromRoot(ctx), "floating",
                      system.controller.initial_commands())
    det = system.controller.GetSubsystemByName("target_detector")
    target = det.get_output_port(0).Eval(det.GetMyContextFromRoot(ctx))
    assert not target.visible and not target.mask.any()


def test_an_impossible_visibility_request_ends_in_a_clear_error():
    params = dataclasses.replace(HEAP_LAYOUTS["lid"].params, max_target_seen=-1.0, max_attempts=2)
    with pytest.raises(HeapError, match=r"max_target_seen=-1\.0.*2 attempts|2 attempts.*max_target_seen=-1\.0"):
        generate_heap(load_scenario(None, "BinHeap15"), 3, 7, params=params, target_first=True,
                      names_fn=lambda rng: _names(rng, 2, occluder_pool("unseen_mesh"), LID_TARGET))


def test_a_lid_heap_is_a_pure_function_of_its_seed_and_cached_once(tmp_path):
    small = [layout_heap(HeapConfig("lid", 3), 5001) for _ in range(2)]
    assert small[0].objects == small[1].objects and small[0].visible_ratios == small[1].visible_ratios
    assert small[0].target == LID_TARGET and small[0].target_index == 0
    assert cached_heap(HeapConfig("lid", 3), 5001, tmp_path).objects == small[0].objects
    assert [f.name for f in tmp_path.iterdir()] == ["heap_lid_N3_s5001.json"]
    assert cached_heap(HeapConfig("lid", 3), 5001, tmp_path).objects == small[0].objects  # read back


def test_the_target_is_offset_like_the_others_only_when_not_at_centre():
    scenario = load_scenario(None, "BinHeap15")
    names = _names(np.random.default_rng(0), 5, occluder_pool("unseen_mesh"), LID_TARGET)
    centred = sample_drop_plan(names, scenario, np.random.default_rng(1), HeapParams(), flat_first=True)
    spread = sample_drop_plan(names, scenario, np.random.default_rng(1), HeapParams(target_at_centre=False),
                              flat_first=True)
    # the same draws: the occluders are where they were, the target moves off the centre
    assert all(np.allclose(a.xy, b.xy) for a, b in zip(centred[1:], spread[1:]))
    assert not np.allclose(centred[0].xy, spread[0].xy)


def test_compact_heaps_drop_every_object_near_one_point_from_20_cm():
    layout = HEAP_LAYOUTS["compact"]
    params = layout.params
    assert (params.center_uniform, params.offset_uniform, params.drop_height) == (0.10, 0.025, 0.20)
    assert layout.target == SMALL_TARGET and get_object(SMALL_TARGET).extents == pytest.approx((0.045, 0.045, 0.005))
    scenario = load_scenario(None, "BinHeap15")
    pool = occluder_pool(layout.pool)
    names = _names(np.random.default_rng(3), 14, pool, SMALL_TARGET)
    for seed in range(5):
        plan = sample_drop_plan(names, scenario, np.random.default_rng(seed), params, flat_first=True)
        # an item's xy is its origin's: its box centre is the heap centre + an offset within +-2.5 cm
        centres = np.array([it.xy + 0.5 * (it.lo + it.hi)[:2] for it in plan])
        assert np.ptp(centres, axis=0).max() <= 0.05 + 1e-9
        assert np.abs(centres.mean(axis=0)).max() <= 0.10 + 0.025
    heap, diag = generate_heap(scenario, 15, 9001, params=params, target_first=True, return_diagnostics=True,
                               names_fn=functools.partial(_names, occluders=14, pool=pool, target=SMALL_TARGET))
    assert diag.phases["max_drop"] >= 0.20  # released from 20 cm (or higher, over the pile)
    assert heap.target_index == 0 and heap.visible_ratios[0] == 0.0
    assert len(diag.rejected_reasons) == diag.attempts - 1  # every rejected attempt is on record
    q = heap.objects[0].q
    assert 0.0 < q[6] < 0.01  # the 5 mm target lies on the bin floor, nothing went through it
    assert heap.objects == layout_heap(HeapConfig("compact", 14), 9001).objects
