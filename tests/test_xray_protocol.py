"""The heap protocols of Table 8.2 (ms_drake.experiments.xray): `xray` and `xray_hidden`."""

import dataclasses

import pytest

from ms_drake.experiments.rollout import SearchParams, build_search
from ms_drake.experiments.xray import PROTOCOLS, XRAY_HEAPS, XRAY_TARGET, _names, xray_heap
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapError, generate_heap, set_heap_poses
from ms_drake.station.robots import set_arm_positions


def test_protocols_name_the_hidden_variant():
    assert PROTOCOLS == ("ch7", "xray", "xray_hidden")


def test_xray_hidden_heap_starts_with_the_target_hidden_from_the_station_camera():
    heap = xray_heap(6001, hidden=True)
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
