"""A bin mechanical search as a user writes it: build the Diagram, simulate it with Drake.

    python sims/bin_search_diagram.py --scenario FloatingGripperBin --seed 3 --policy largest
    python sims/bin_search_diagram.py --scenario PandaBin --seed 3 --policy largest --fidelity full

Prints one JSON line (seed, success, actions, action_kinds, stop_reason, grasp_objects); with the same scenario,
seed and policy it is the record of `ms-drake bench search` action by action (the same heap: N =
15 objects, or the target and 14 others for X-Ray, as `bench search` draws them).
"""

from __future__ import annotations

import argparse
import json

from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.policies.bin_search import (
    BinSearchParams,
    MakeBinSearchController,
    SimulationInfo,
    connect_controller,
    search_scenario,
    set_initial_conditions,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes import SEARCH_HEAPS, generate_heap
from ms_drake.station import MakeStation


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="FloatingGripperBin", help="a bin scenario of diagrams/scenarios.yaml")
    ap.add_argument("--scenario-file", default=None, help="the scenario file (default: diagrams/scenarios.yaml)")
    ap.add_argument("--seed", type=int, default=0, help="the heap's seed (and the controller's)")
    ap.add_argument("--policy", default="largest", help="largest | xray | random | preempted_random | ...")
    ap.add_argument("--fidelity", default="primitive", choices=("primitive", "full"))
    ap.add_argument("--objects", type=int, default=15, help="objects in the heap (N)")
    a = ap.parse_args(argv)

    scenario = load_scenario(a.scenario_file, a.scenario)
    heap = generate_heap(load_scenario(a.scenario_file, "BinHeap15"), a.objects, a.seed, params=SEARCH_HEAPS)

    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(search_scenario(scenario, heap, a.fidelity, a.policy),
                                            target_index=heap.target_index))
    controller = builder.AddSystem(MakeBinSearchController(
        scenario, BinSearchParams(policy=a.policy, fidelity=a.fidelity, horizon=2 * len(heap.objects), seed=a.seed),
        sim=SimulationInfo.from_station(station, heap.target_index)))
    connect_controller(builder, controller, station)
    diagram = builder.Build()

    simulator = Simulator(diagram)
    set_initial_conditions(diagram, simulator.get_mutable_context(), heap)
    simulator.AdvanceTo(600.0)  # the search ends the simulation itself

    context = simulator.get_context()
    status = controller.GetOutputPort("status").Eval(controller.GetMyContextFromRoot(context))
    history = controller.GetOutputPort("history").Eval(controller.GetMyContextFromRoot(context))
    grasped = [o.action.grasp.object_id if o.action.kind == "grasp" else "" for o in history]
    out = {"seed": a.seed, "success": status.stop_reason == "success", "actions": len(history),
           "action_kinds": [o.action.kind for o in history], "stop_reason": status.stop_reason,
           "grasp_objects": ["target" if g and g == controller.target_id else g for g in grasped]}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
