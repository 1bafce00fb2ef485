"""The heap protocol of Table 8.2 (Ch. 8.4.1, lines 1499-1512): `ms-drake bench search --protocol xray`.

A heap: the target (`XRAY_TARGET`, the "lid": the 1:1 box target of the occupancy training set
at twice its size, 6 x 6 x 0.5 cm, so the learned estimator uses input scaling; the training
boxes themselves are too narrow for the 3 cm suction cup and too flat for the jaw: with the 2:1
box, 4.2 x 2.1 cm, Largest and Random stopped on seed 5000 with the target in full view and no
grasp on it) is dropped first, then N = 14 objects drawn uniformly (with
replacement) from the *test* splits of the mesh sets (YCB and random_urdfs): occluders the
occupancy network never saw in training (ms_drake.experiments.occupancy_data draws training heaps
from the train splits). The target lies flat (random yaw) at the heap's centre, the occluders
fall around it (truncated Gaussian offsets, sigma 4 cm: half the 8 cm of the other heaps, so that
they pile on the target and it starts hidden or nearly so, as the reference's search lengths --
X-Ray's quartiles 3 / 5 / 6 actions -- imply; with 8 cm the target's seen fraction had median 0.21
and was 0 in 6.5 % of 320 heaps, and every policy took the target with its first action in half
of them; with 4 cm it was 0 in 4 of seeds 5000-5011 and below 0.1 in 7), and an attempt counts
only if the target stays in the bin. (Our choice: with the target scattered like the others, in
18 heaps of a first run Largest grasped the target with its first action in 12 -- it lay beside
the heap in view.) Dropped with Bullet, as the reference, then settled for up to 0.5 s in the
compliant Drake drop world (`XRAY_HEAPS`): in the Drake drop world alone (SEARCH_HEAPS) the 5 mm
target tunnels through the floor under the heap in every attempt (seeds 5000-5001), while the
polished Bullet heaps stay put in the station (largest displacement in 0.5 s: 7-11 mm, the
target's < 1 mm; seeds 5000-5002). Horizon H = 10; ground-truth segmentation and target masks,
as the reference.

`--protocol xray_hidden`: the same heaps, but an attempt counts only if the target starts fully
hidden from the overhead camera (its seen fraction is 0), as the reference's closing summary of
its heaps says ("heaps containing 15-25 objects that fully occlude the target object", Ch. 8.5).
Under `xray` the target's seen fraction is 0 in about one heap in eight, so a `xray_hidden` heap
takes about eight drops (`XRAY_HIDDEN_HEAPS.max_attempts` bounds them).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ms_drake.objects import get_object_set
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap

XRAY_TARGET = "targets/lid"
XRAY_OBJECTS = 14
XRAY_HORIZON = 10
XRAY_OCCLUDER_SETS = ("ycb", "random_urdfs")
PROTOCOLS = ("ch7", "xray", "xray_hidden")
XRAY_PROTOCOLS = ("xray", "xray_hidden")
XRAY_HEAPS = HeapParams(engine="bullet", polish_time=0.5, offset_sigma=0.04)
XRAY_HIDDEN_HEAPS = dataclasses.replace(XRAY_HEAPS, max_target_seen=0.0, max_attempts=80)


@functools.cache
def xray_occluders() -> tuple[str, ...]:
    """Full names of the protocol's occluders (test splits of the mesh sets)."""
    return tuple(o.full_name for s in XRAY_OCCLUDER_SETS for o in get_object_set(s).split("test"))


def _names(rng: np.random.Generator, occluders: int) -> list[str]:
    pool = xray_occluders()
    return [XRAY_TARGET] + [pool[i] for i in rng.integers(0, len(pool), size=occluders)]


def xray_heap(seed: int, occluders: int = XRAY_OBJECTS, hidden: bool = False):
    """Heap `seed` of the protocol: the target dropped first, then `occluders` unseen mesh objects;
    hidden: only a heap whose target starts fully hidden (protocol `xray_hidden`)."""
    return generate_heap(load_scenario(None, "BinHeap15"), occluders + 1, seed,
                         params=XRAY_HIDDEN_HEAPS if hidden else XRAY_HEAPS,
                         names_fn=functools.partial(_names, occluders=occluders), target_first=True)
