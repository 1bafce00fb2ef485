"""The heap protocols of Table 8.2 (ms_drake.experiments.xray): `xray`, `xray_hidden`, `xray_ycb`,
`xray_occluded`, `xray_small`, `xray_tiny`, `xray_compact`."""

import dataclasses
import functools

import numpy as np
import pytest

from ms_drake.experiments.rollout import SearchParams, build_search
from ms_drake.experiments.xray import (
    PROTOCOLS,
    XRAY_HEAPS,
    XRAY_OCCLUDED_HEAPS,
    XRAY_SMALL_TARGET,
    XRAY_TARGET,
    XRAY_TINY_TARGET,
    _names,
    xray_heap,
    xray_heap_settings,
    xray_target,
    xray_occluders,
    xray_ycb_occluders,
)
from ms_drake.objects import get_object, get_object_set
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapError, HeapParams, generate_heap, sample_drop_plan, set_heap_poses
from ms_drake.station.robots import set_arm_positions


def test_protocols_name_the_hidden_variant():
    assert PROTOCOLS == ("ch7", "xray", "xray_hidden", "xray_ycb", "xray_occluded", "xray_small", "xray_tiny",
                         "xray_compact")


def test_xray_hidden_heap_starts_with_the_target_hidden_from_the_station_camera():
    heap = xray_heap(6001, protocol="xray_hidden")
    assert heap.target == XRAY_TARGET and heap.target_index == 0
    assert heap.visible_ratios[0] == 0.0
    # what the search's own camera and target detector see: no target
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap, SearchParams(policy="largest", horizon=1,
                                                                                        time_step=0.01))
    ctx = system.diagram.CreateDefaultContext()
    set_heap_poses(system.station, ctx, heap)
    set_arm_positions(system.plant, system.plant.GetMyMutableContextFromRoot(ctx), "floating",
                      system.controller.initial_commands())
    det = system.controller.GetSubsystemByName("target_detector")
    target = det.get_output_port(0).Eval(det.GetMyContextFromRoot(ctx))
    assert not target.visible and not target.mask.any()


def test_an_impossible_visibility_request_ends_in_a_clear_error():
    params = dataclasses.replace(XRAY_HEAPS, max_target_seen=-1.0, max_attempts=2)
    with pytest.raises(HeapError, match=r"max_target_seen=-1\.0.*2 attempts|2 attempts.*max_target_seen=-1\.0"):
        generate_heap(load_scenario(None, "BinHeap15"), 3, 7, params=params,
                      names_fn=lambda rng: _names(rng, 2), target_first=True)


def test_xray_ycb_occluders_are_unseen_ycb_models_and_packaged_objects():
    pool = xray_ycb_occluders()
    assert len(pool) == len(set(pool))
    sets = [name.split("/")[0] for name in pool]
    assert sets.count("procedural") == 13 and all(n.startswith("procedural/packaged_") for n in pool[-13:])
    ycb_unseen = get_object_set("ycb_unseen")
    assert {o.name for o in ycb_unseen.objects}.isdisjoint(get_object_set("ycb").names())
    assert {f"ycb_unseen/{n}" for n in ycb_unseen.names()} <= set(pool)
    # never in the occupancy network's training heaps, which draw from the train splits
    assert all(get_object(n).split == "test" for n in pool)
    assert set(pool).isdisjoint(xray_occluders()[9:])  # no random_urdfs blob (xray's pool: ycb test, then blobs)


def test_xray_ycb_heap_holds_the_target_under_14_occluders_of_its_pool_and_is_deterministic():
    heap = xray_heap(5000, protocol="xray_ycb")
    names = [o.name for o in heap.objects]
    assert len(names) == 15 and names[0] == XRAY_TARGET == heap.target and heap.target_index == 0
    assert set(names[1:]) <= set(xray_ycb_occluders())
    # a pure function of the seed (a small heap, twice); the xray protocol draws from its own pool
    small = [xray_heap(5001, occluders=3, protocol="xray_ycb") for _ in range(2)]
    assert small[0].objects == small[1].objects and small[0].visible_ratios == small[1].visible_ratios
    assert set(_names(np.random.default_rng([5000, 0]), 14)[1:]) <= set(xray_occluders())
    with pytest.raises(ValueError, match="xray_ycb"):
        xray_heap(5000, protocol="ch7")


def test_xray_occluded_heap_hides_the_target_among_xray_ycb_occluders():
    heap, diag = generate_heap(load_scenario(None, "BinHeap15"), 15, 5002, params=XRAY_OCCLUDED_HEAPS,
                               names_fn=lambda rng: _names(rng, 14, xray_ycb_occluders()), target_first=True,
                               return_diagnostics=True)
    again = xray_heap(5002, protocol="xray_occluded")
    assert heap.objects == again.objects and heap.visible_ratios == again.visible_ratios
    assert heap.target == XRAY_TARGET and heap.target_index == 0 and heap.visible_ratios[0] == 0.0
    assert {o.name for o in heap.objects[1:]} <= set(xray_ycb_occluders())
    # every rejected attempt is on record with its reason
    assert len(diag.rejected_reasons) == diag.attempts - 1


def test_the_target_is_offset_like_the_others_only_when_not_at_centre():
    scenario = load_scenario(None, "BinHeap15")
    names = _names(np.random.default_rng(0), 5)
    centred = sample_drop_plan(names, scenario, np.random.default_rng(1), HeapParams(), flat_first=True)
    spread = sample_drop_plan(names, scenario, np.random.default_rng(1), HeapParams(target_at_centre=False),
                              flat_first=True)
    # the same draws: the occluders are where they were, the target moves off the centre
    assert all(np.allclose(a.xy, b.xy) for a, b in zip(centred[1:], spread[1:]))
    assert not np.allclose(centred[0].xy, spread[0].xy)


def test_xray_small_heaps_are_the_xray_occluded_draws_with_the_smaller_target():
    small = get_object(XRAY_SMALL_TARGET)
    assert small.extents == pytest.approx((0.045, 0.045, 0.005))
    assert small.extents[0] < get_object(XRAY_TARGET).extents[0]
    # the same random draws as xray_occluded: the occluders' names and drop plan, another target
    a = _names(np.random.default_rng(5), 14, xray_ycb_occluders())
    b = _names(np.random.default_rng(5), 14, xray_ycb_occluders(), target=XRAY_SMALL_TARGET)
    assert a[1:] == b[1:] and a[0] == XRAY_TARGET and b[0] == XRAY_SMALL_TARGET
    # xray_tiny: the same heaps' settings with the 3.5 cm target
    assert get_object(XRAY_TINY_TARGET).extents == pytest.approx((0.035, 0.035, 0.005))
    assert xray_target("xray_tiny") == XRAY_TINY_TARGET and xray_target("xray_small") == XRAY_SMALL_TARGET
    assert xray_heap_settings("xray_tiny") == xray_heap_settings("xray_small")
    heap = xray_heap(5003, protocol="xray_small")
    assert heap.target == XRAY_SMALL_TARGET and heap.target_index == 0 and heap.visible_ratios[0] == 0.0
    assert {o.name for o in heap.objects[1:]} <= set(xray_ycb_occluders())


def test_xray_compact_heaps_drop_every_object_near_one_point_from_20_cm():
    params, pool = xray_heap_settings("xray_compact")
    assert (params.center_uniform, params.offset_uniform, params.drop_height) == (0.10, 0.025, 0.20)
    assert pool == xray_heap_settings("xray_small")[1] and xray_target("xray_compact") == XRAY_SMALL_TARGET
    scenario = load_scenario(None, "BinHeap15")
    names = _names(np.random.default_rng(3), 14, pool, target=XRAY_SMALL_TARGET)
    for seed in range(5):
        plan = sample_drop_plan(names, scenario, np.random.default_rng(seed), params, flat_first=True)
        # an item's xy is its origin's: its box centre is the heap centre + an offset within +-2.5 cm
        centres = np.array([it.xy + 0.5 * (it.lo + it.hi)[:2] for it in plan])
        assert np.ptp(centres, axis=0).max() <= 0.05 + 1e-9
        assert np.abs(centres.mean(axis=0)).max() <= 0.10 + 0.025
    heap, diag = generate_heap(scenario, 15, 9001, params=params, target_first=True, return_diagnostics=True,
                               names_fn=functools.partial(_names, occluders=14, pool=pool, target=XRAY_SMALL_TARGET))
    assert diag.phases["max_drop"] >= 0.20  # released from 20 cm (or higher, over the pile)
    assert heap.target_index == 0 and heap.visible_ratios[0] == 0.0
    q = heap.objects[0].q
    assert 0.0 < q[6] < 0.01  # the 5 mm target lies on the bin floor, nothing went through it
