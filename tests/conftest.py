"""Shared fixtures: scenarios from diagrams/scenarios.yaml, small heaps."""

import copy
import sys
from pathlib import Path

import pytest

# tools/ (dev-time converters and model writers, not installed) is imported from the checkout.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ms_drake.scenario import load_scenario


@pytest.fixture(scope="session")
def bin_scenario():
    return load_scenario(None, "BinHeap15")


def no_robot(scenario):
    s = copy.deepcopy(scenario)
    s.robot.name = ""
    s.robot.grippers = []
    return s


@pytest.fixture(scope="session")
def small_heap(bin_scenario):
    from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap

    return generate_heap(bin_scenario, 4, seed=3, params=SEARCH_HEAPS)  # as the search benchmarks
