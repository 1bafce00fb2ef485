"""ms_drake: robot mechanical search in Drake.

The package in layers, lowest first; imports point down only (tests/test_layers.py enforces it):

    types geometry shelf_geometry errors paths parallel   value types, camera model, workspaces
    objects robots                                         object sets; Drake-free robot/gripper tables
    scenario                                               Drake-YAML scenarios and their validation
    station                                                MakeStation(scenario[, hardware]) and drivers
    perception grasping pushing planning scenes foss       capabilities (peers)
    execution                                              ActionExecutor and its backends
    policies                                               selectors and controller Diagram builders
    experiments                                            rollouts, benchmarks, demo, datasets
    cli                                                    the `ms-drake` command

See README.md for the set-up and the two commands (demo, tests).

The main entry points are importable from the package itself, e.g.
`from ms_drake import load_scenario, MakeStation, MakeBinSearchController`; each is imported on
first use (module `__getattr__`), so `import ms_drake` stays cheap.
"""

import importlib

__version__ = "0.1.0"

#: name -> the module that defines it
_EXPORTS = {
    "load_scenario": "ms_drake.scenario",
    "MakeStation": "ms_drake.station",
    "generate_heap": "ms_drake.scenes.heaps",
    "scenario_with_heap": "ms_drake.scenes.heaps",
    "set_heap_poses": "ms_drake.scenes.heaps",
    "MakeBinSearchController": "ms_drake.policies.bin_search",
    "BinSearchConfig": "ms_drake.policies.bin_search",
    "BinSearchAblation": "ms_drake.policies.bin_search",
    "load_bin_search_config": "ms_drake.policies.bin_search",
    "search_scenario": "ms_drake.policies.bin_search",
    "set_initial_conditions": "ms_drake.policies.bin_search",
    "HeapConfig": "ms_drake.scenes.layouts",
    "cached_heap": "ms_drake.scenes.layouts",
    "layout_heap": "ms_drake.scenes.layouts",
    "SimulationInfo": "ms_drake.policies.bin_search",
    "connect_controller": "ms_drake.policies.bin_search",
    "MakeShelfSearchController": "ms_drake.policies.shelf_search",
    "ShelfSearchConfig": "ms_drake.policies.shelf_search",
    "MakeRearrangementController": "ms_drake.policies.rearrange",
    "RearrangeParams": "ms_drake.policies.rearrange",
    "RearrangeSimInfo": "ms_drake.policies.rearrange",
    "rollout": "ms_drake.experiments.rollout",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'ms_drake' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
