"""Named heap layouts: what a bin search's heaps are made of and how they are dropped.

A heap is a pure function of its `HeapConfig` (a layout name and an object count) and its seed.
The layouts (`HEAP_LAYOUTS`, `ms-drake bench search --set heap.layout=NAME`):

- ``compact`` (default; Table 8.2): the reference's occupancy-dataset generator settings
  (published with its code, sd-maskrcnn ``cfg/partials/states_dist.yaml``; Section 8.3 describes
  them in words): a heap centre uniform in +-10 cm, every object's planar offset uniform in
  +-2.5 cm around it, each released from 20 cm above the bin floor. The target, a 4.5 x 4.5 x
  0.5 cm box (``targets/square45``), is dropped first, then N occluders drawn uniformly (with
  replacement) from the household objects the occupancy network never saw (every YCB model
  outside the training subset, the test split of that subset, and 13 packaged objects); only a
  heap whose target starts fully hidden from the overhead camera counts.
- ``ycb_hidden``: the reference's heaps as its text gives them (Section 8.3): the same target
  and occluders, every object offset from the heap centre by a truncated Gaussian (sigma 8 cm),
  each released 1 cm above what lies under it; the target starts fully hidden.
- ``lid``: the target a 6 x 6 x 0.5 cm lid at the heap's centre, N occluders from the test splits
  of the mesh sets (YCB and random_urdfs) falling around it (sigma 4 cm): the target is usually
  partly visible (the demo's heaps).
- ``bin_set`` (Ch. 7, Fig. 7.4 and Table C.1): N objects of the bin scenario's object set dropped
  in the compliant Drake drop world (sigma 8 cm); the target is the most occluded of them.
- ``bin_set_bullet``: the same heaps dropped with Bullet (~4x cheaper per heap, other heaps).

The target-first layouts are dropped with Bullet, as the reference, then settled for up to 0.5 s
in the compliant Drake drop world (in the Drake drop world alone the 5 mm target tunnels through
the floor under the heap). `objects` counts the occluders of a target-first layout (N = 14 in
Table 8.2) and every object of a ``bin_set`` heap (N = 15 in Ch. 7).

`cached_heap` keeps heaps in a folder so that several policies search the very same heaps.
"""


import dataclasses
import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ms_drake.errors import HeapError
from ms_drake.objects import get_object_set
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, HeapParams, generate_heap, heap_to_dict, load_heap

LID_TARGET = "targets/lid"
SMALL_TARGET = "targets/square45"
HEAP_SCENARIO = "BinHeap15"  # the bin every layout drops into
_TARGET_FIRST = HeapParams(engine="bullet", polish_time=0.5, offset_sigma=0.04)
_HIDDEN = dataclasses.replace(_TARGET_FIRST, max_target_seen=0.0, max_attempts=80, offset_sigma=0.08,
                              target_at_centre=False, prescreen_margin=0.15)


@dataclass(frozen=True)
class HeapLayout:
    """One named layout: its drop settings, where its objects come from and its target."""

    description: str
    params: HeapParams
    pool: str  # "bin_set" (the bin scenario's object set) | "unseen_mesh" | "unseen_household"
    target: str = ""  # dropped first; "" = the most occluded of the objects


HEAP_LAYOUTS = {
    "compact": HeapLayout("Table 8.2: the 4.5 cm target under N unseen household objects, dropped as the "
                          "reference's generator settings (+-2.5 cm around a centre, from 20 cm), target hidden",
                          dataclasses.replace(_HIDDEN, center_uniform=0.10, offset_uniform=0.025, drop_height=0.20),
                          "unseen_household", SMALL_TARGET),
    "ycb_hidden": HeapLayout("the 4.5 cm target under N unseen household objects spread at sigma 8 cm, "
                             "target hidden", _HIDDEN, "unseen_household", SMALL_TARGET),
    "lid": HeapLayout("the 6 cm lid at the heap's centre under N unseen mesh objects (sigma 4 cm)",
                      _TARGET_FIRST, "unseen_mesh", LID_TARGET),
    "bin_set": HeapLayout("Ch. 7: N objects of the bin's object set, Drake drop world; the target is the most "
                          "occluded", SEARCH_HEAPS, "bin_set"),
    "bin_set_bullet": HeapLayout("bin_set's objects dropped with Bullet (other heaps, ~4x cheaper)",
                                 HeapParams(engine="bullet"), "bin_set"),
}
PACKAGED_OCCLUDERS = 13  # as the reference's 13 packaged YCB objects


@dataclass
class HeapConfig:
    """The heaps of a search: a layout of HEAP_LAYOUTS and N (see the module docstring)."""

    layout: str = "compact"
    objects: int = 14

    def __post_init__(self):
        if self.layout not in HEAP_LAYOUTS:
            raise HeapError(f"heap layout {self.layout!r} unknown; choose one of {', '.join(HEAP_LAYOUTS)}")
        if not 1 <= int(self.objects) <= 60:
            raise HeapError(f"heap objects must be 1..60, got {self.objects!r}")


@functools.cache
def occluder_pool(pool: str) -> tuple[str, ...]:
    """Full names of a target-first layout's occluders (objects the occupancy network never saw)."""
    if pool == "unseen_mesh":
        return tuple(o.full_name for s in ("ycb", "random_urdfs") for o in get_object_set(s).split("test"))
    ycb = [o.full_name for s in ("ycb_unseen", "ycb") for o in get_object_set(s).split("test")]
    packaged = [o.full_name for o in get_object_set("procedural").split("test") if o.name.startswith("packaged_")]
    return tuple(ycb + packaged[:PACKAGED_OCCLUDERS])


def _names(rng: np.random.Generator, occluders: int, pool: tuple[str, ...], target: str) -> list[str]:
    return [target] + [pool[i] for i in rng.integers(0, len(pool), size=occluders)]


def layout_heap(config: HeapConfig, seed: int):
    """Heap `seed` of `config` (generated: seconds of CPU; see cached_heap)."""
    layout = HEAP_LAYOUTS[config.layout]
    scenario = load_scenario(None, HEAP_SCENARIO)
    if not layout.target:
        return generate_heap(scenario, config.objects, seed, params=layout.params)
    names = functools.partial(_names, occluders=config.objects, pool=occluder_pool(layout.pool), target=layout.target)
    return generate_heap(scenario, config.objects + 1, seed, params=layout.params, names_fn=names, target_first=True)


def heap_generator_key(config: HeapConfig) -> str:
    """A fingerprint of what makes the heaps of `config`: the drop settings, the object pool and N.
    A cached heap file keeps it, so a cache left by other generator settings is refused."""
    layout = HEAP_LAYOUTS[config.layout]
    if layout.target:
        what = {"pool": list(occluder_pool(layout.pool)), "target": layout.target}
    else:
        objs = load_scenario(None, HEAP_SCENARIO).objects
        what = {"set": objs.set, "split": objs.split}
    text = json.dumps({"params": dataclasses.asdict(layout.params), "objects": int(config.objects), **what},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def cached_heap(config: HeapConfig, seed: int, heap_dir: str | Path | None = None):
    """Heap `seed` of `config`, read from / saved to `heap_dir` when given
    (heap_<layout>_N<N>_s<seed>.json, written atomically), so several policies search the very same
    heaps without regenerating them. A file made with other settings raises HeapError."""
    if heap_dir is None:
        return layout_heap(config, seed)
    path = Path(heap_dir) / f"heap_{config.layout}_N{config.objects}_s{seed}.json"
    key = heap_generator_key(config)
    if path.exists():
        made_by = json.loads(path.read_text()).get("generator")
        if made_by != key:
            raise HeapError(f"{path}: this cached heap was made with other generator settings (key {made_by}, "
                            f"today's {key}): its seed no longer names today's heap. Delete the file, or give "
                            "a fresh heap folder.")
        return load_heap(path)
    heap = layout_heap(config, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps({**heap_to_dict(heap), "generator": key}))
    os.replace(tmp, path)
    return heap
