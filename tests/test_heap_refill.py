"""Heaps hold N objects: objects that leave the bin are dropped again (HeapParams.refill_rounds)."""

import dataclasses

import numpy as np
import pytest

from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap


@pytest.fixture(scope="module")
def bin_scenario():
    return load_scenario(None, "BinHeap15")


def test_objects_that_leave_are_dropped_again_until_all_n_are_in(bin_scenario):
    seed = 1000  # a 15-object Bullet heap from which one object leaves the bin
    removed, d0 = generate_heap(bin_scenario, 15, seed, params=HeapParams(refill_rounds=0), return_diagnostics=True)
    assert len(removed.objects) == 14 and len(d0.removed) == 1 and d0.refills == 0
    heap, d = generate_heap(bin_scenario, 15, seed, params=HeapParams(), return_diagnostics=True)
    assert len(heap.objects) == 15 and d.removed == [] and d.attempts == 1
    assert d.refills >= 1 and d.redropped >= 1
    # the same draw of objects: the removed heap's objects are all in the full one
    assert sorted(o.name for o in removed.objects + tuple(type(removed.objects[0])(n, ()) for n in d0.removed)) \
        == sorted(o.name for o in heap.objects)
    # every object lies over the bin's inner box
    env = bin_scenario.environment
    size, origin = np.asarray(env.resolved_size()), np.asarray(env.position)
    xy = np.array([o.q[4:6] for o in heap.objects]) - origin[:2]
    assert np.all(np.abs(xy) <= 0.5 * size[:2] + 1e-3)
    # a heap from which nothing leaves is the same with and without re-drops
    a = generate_heap(bin_scenario, 15, 1002, params=HeapParams(refill_rounds=0))
    b = generate_heap(bin_scenario, 15, 1002, params=HeapParams())
    assert a.objects == b.objects


def test_refill_in_the_drake_drop_world(bin_scenario):
    params = dataclasses.replace(HeapParams(engine="drake"), render=False)
    heap, d = generate_heap(bin_scenario, 15, 1000, params=params, return_diagnostics=True)
    assert len(heap.objects) == 15 and d.removed == []
