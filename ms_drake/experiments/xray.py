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

`--protocol xray_ycb`: the same heaps (target first, the lid, sigma 4 cm, Bullet + polish, H = 10)
with the reference's kind of occluders (line 1503: "46 YCB objects and 13 packaged YCB objects",
household objects the network never saw): drawn uniformly (with replacement) from every YCB model
the occupancy network never saw -- the set `ycb_unseen` (the YCB models outside the committed
`ycb` subset, all of them test split; tools/convert_objects.py --exclude-set ycb) and the test
split of `ycb` -- and 13 packaged objects, the first 13 packaged objects of the `procedural` test
split (a box or cylinder on a cardboard backing; not YCB models: no YCB model with a backing
exists here). The pool is 52 YCB models + 13 packaged (`xray_ycb_occluders`), against the
reference's 46 + 13; `xray` draws from 9 YCB models and 22 random_urdfs blobs (4-20 cm).

`--protocol xray_occluded`: the reference's heaps as its text gives them, with `xray_ycb`'s
occluders. Section 8.3 (lines 1454-1455): a heap centre, then "2D offsets for each object from a 2D
truncated gaussian", the target dropped first -- the target is offset like every other object, not
placed at the centre -- with the spread of the other heaps here (sigma 8 cm); and the closing
summary (Ch. 8.5): heaps "that fully occlude the target object", so an attempt counts only if the
target's seen fraction from the overhead camera is 0 (`XRAY_OCCLUDED_HEAPS`; about 17 % of drops
qualify, so a heap takes about 4-5 drops with the pre-polish screen of
`HeapParams.prescreen_margin`, ~8 CPU-s). Here large occluders also lie away from the target,
the case the reference gives for X-Ray's margin over Largest (lines 1518-1520).

`--protocol xray_small`: the `xray_occluded` heaps (the same occluders, spread, hidden target and
random draws) with a smaller target, `XRAY_SMALL_TARGET` (4.5 x 4.5 x 0.5 cm: the 1:1 training box
at 1.5 times its size, where the lid is 2 times; the learned estimator scales its input by 1.5).
The reference's simulated X-Ray heaps do not name their target; its training targets are 3 cm
boxes, too narrow for the 3 cm suction cup here, and the lid leaves the cup 1.5 cm to spare on
each side, so a partly covered lid is usually still graspable. With 7.5 mm to spare, a target
partly covered by a thin or small object often has no grasp, the case the reference gives for
X-Ray's margin (lines 1514-1517: "a robust grasp is often not available on the target object").

`--protocol xray_tiny`: the same heaps with a 3.5 x 3.5 x 0.5 cm target (`XRAY_TINY_TARGET`: the
1:1 training box at 7 / 6 of its size, the nearest to the reference's 3 cm training targets that
the 3 cm cup still seals on, with 2.5 mm to spare a side): how X-Ray's margin grows as the target
shrinks (6, 4.5, 3.5 cm).

`--protocol xray_compact`: heaps dropped with the settings of the reference's own occupancy-dataset
generator (the configuration published with its code, sd-maskrcnn `cfg/partials/states_dist.yaml`,
which Section 8.3 describes in words): a heap centre uniform in +-10 cm, every object's planar offset
uniform in +-2.5 cm around it (the target, dropped first, too), each released from 20 cm above the
bin floor (`XRAY_COMPACT_HEAPS`), in the reference's 40 x 50 cm bin (BinHeap15's is 50 x 40 cm).
The 4.5 cm target, `xray_ycb`'s occluders, the target fully hidden at the start, H = 10, as
`xray_small`. The other protocols release each object 1 cm above what lies under it and spread the
offsets at sigma 4-8 cm; these heaps are piles around one point, the target at their bottom.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ms_drake.objects import get_object_set
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import HeapParams, generate_heap

XRAY_TARGET = "targets/lid"
XRAY_SMALL_TARGET = "targets/square45"
XRAY_TINY_TARGET = "targets/square35"
XRAY_OBJECTS = 14
XRAY_HORIZON = 10
XRAY_OCCLUDER_SETS = ("ycb", "random_urdfs")
XRAY_YCB_SETS = ("ycb_unseen", "ycb")  # every object of the first (all test split), the test split of the others
XRAY_YCB_PACKAGED = 13  # packaged occluders, as the reference's 13 packaged YCB objects
PROTOCOLS = ("ch7", "xray", "xray_hidden", "xray_ycb", "xray_occluded", "xray_small", "xray_tiny", "xray_compact")
XRAY_PROTOCOLS = ("xray", "xray_hidden", "xray_ycb", "xray_occluded", "xray_small", "xray_tiny", "xray_compact")
XRAY_HEAPS = HeapParams(engine="bullet", polish_time=0.5, offset_sigma=0.04)
XRAY_HIDDEN_HEAPS = dataclasses.replace(XRAY_HEAPS, max_target_seen=0.0, max_attempts=80)
XRAY_OCCLUDED_HEAPS = dataclasses.replace(XRAY_HIDDEN_HEAPS, offset_sigma=0.08, target_at_centre=False,
                                          prescreen_margin=0.15)
XRAY_COMPACT_HEAPS = dataclasses.replace(XRAY_OCCLUDED_HEAPS, center_uniform=0.10, offset_uniform=0.025,
                                         drop_height=0.20)
_HEAP_PARAMS = {"xray": XRAY_HEAPS, "xray_hidden": XRAY_HIDDEN_HEAPS, "xray_ycb": XRAY_HEAPS,
                "xray_occluded": XRAY_OCCLUDED_HEAPS, "xray_small": XRAY_OCCLUDED_HEAPS,
                "xray_tiny": XRAY_OCCLUDED_HEAPS, "xray_compact": XRAY_COMPACT_HEAPS}
_TARGETS = {"xray_small": XRAY_SMALL_TARGET, "xray_tiny": XRAY_TINY_TARGET, "xray_compact": XRAY_SMALL_TARGET}


@functools.cache
def xray_occluders() -> tuple[str, ...]:
    """Full names of the protocol's occluders (test splits of the mesh sets)."""
    return tuple(o.full_name for s in XRAY_OCCLUDER_SETS for o in get_object_set(s).split("test"))


@functools.cache
def xray_ycb_occluders() -> tuple[str, ...]:
    """Full names of the `xray_ycb` protocol's occluders: the YCB models the occupancy network
    never saw (all of `ycb_unseen`, the test split of `ycb`), then `XRAY_YCB_PACKAGED` packaged
    objects of the procedural test split (in index order)."""
    ycb = [o.full_name for s in XRAY_YCB_SETS for o in get_object_set(s).split("test")]
    packaged = [o.full_name for o in get_object_set("procedural").split("test") if o.name.startswith("packaged_")]
    return tuple(ycb + packaged[:XRAY_YCB_PACKAGED])


def _names(rng: np.random.Generator, occluders: int, pool: tuple[str, ...] | None = None,
           target: str = XRAY_TARGET) -> list[str]:
    pool = pool if pool is not None else xray_occluders()
    return [target] + [pool[i] for i in rng.integers(0, len(pool), size=occluders)]


def xray_target(protocol: str) -> str:
    """The full name of an X-Ray heap protocol's target."""
    return _TARGETS.get(protocol, XRAY_TARGET)


def xray_heap_settings(protocol: str) -> tuple[HeapParams, tuple[str, ...]]:
    """(HeapParams, occluder pool) of an X-Ray heap protocol: what its heaps are generated with."""
    if protocol not in XRAY_PROTOCOLS:
        raise ValueError(f"protocol {protocol!r} is not an X-Ray heap protocol; choose one of "
                         f"{', '.join(XRAY_PROTOCOLS)}")
    pool = xray_ycb_occluders() if protocol in ("xray_ycb", "xray_occluded", "xray_small", "xray_tiny",
                                                "xray_compact") \
        else xray_occluders()
    return _HEAP_PARAMS[protocol], pool


def xray_heap(seed: int, occluders: int = XRAY_OBJECTS, protocol: str = "xray"):
    """Heap `seed` of a protocol of XRAY_PROTOCOLS: the target dropped first, then `occluders`
    unseen mesh objects (`xray`, and `xray_hidden`: only a heap whose target starts fully hidden)
    or unseen YCB and packaged objects (`xray_ycb`; `xray_occluded`: spread as Section 8.3's heaps,
    the target fully hidden; `xray_small` and `xray_tiny`: those with the smaller targets;
    `xray_compact`: dropped as the reference's generator configuration gives)."""
    params, pool = xray_heap_settings(protocol)
    return generate_heap(load_scenario(None, "BinHeap15"), occluders + 1, seed, params=params,
                         names_fn=functools.partial(_names, occluders=occluders, pool=pool,
                                                    target=xray_target(protocol)), target_first=True)
