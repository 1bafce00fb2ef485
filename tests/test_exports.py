"""The package's main entry points, importable from `ms_drake` itself and loaded on first use."""

import subprocess
import sys

import pytest

import ms_drake

NAMES = ["load_scenario", "MakeStation", "generate_heap", "scenario_with_heap", "set_heap_poses",
         "MakeBinSearchController", "BinSearchConfig", "load_bin_search_config", "HeapConfig", "layout_heap", "SimulationInfo", "connect_controller",
         "MakeShelfSearchController", "ShelfSearchConfig", "MakeRearrangementController", "RearrangeParams",
         "rollout"]


@pytest.mark.parametrize("name", NAMES)
def test_entry_point_is_exported(name):
    value = getattr(ms_drake, name)
    assert callable(value) and value.__name__ == name
    assert name in ms_drake.__all__ and name in dir(ms_drake)
    exec(f"from ms_drake import {name}", {})


def test_import_ms_drake_stays_cheap():
    code = ("import sys, ms_drake; "
            "print(sorted(m for m in sys.modules if m.startswith(('ms_drake.', 'pydrake', 'torch'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'NoSuchThing'"):
        ms_drake.NoSuchThing  # noqa: B018
