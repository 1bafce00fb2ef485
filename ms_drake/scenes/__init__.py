"""Scenes: bin heaps (drop simulation), shelf scenes, table scenes."""

from ms_drake.scenes.heaps import (  # noqa: F401
    SEARCH_HEAPS,
    HeapParams,
    generate_heap,
    heap_from_dict,
    heap_to_dict,
    load_heap,
    save_heap,
    scenario_with_heap,
    set_heap_poses,
)
