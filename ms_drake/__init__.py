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
"""

__version__ = "0.1.0"
