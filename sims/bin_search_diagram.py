"""A bin mechanical search as a user writes it: build the Diagram, simulate it with Drake.

    python sims/bin_search_diagram.py --seed 3 --policy xray                       # Table 8.2's setting
    python sims/bin_search_diagram.py --seed 3 --config ch7 --set heap.objects=10  # Ch. 7's
    python sims/bin_search_diagram.py --scenario PandaBin --seed 3 --fidelity full

Prints one JSON line (seed, success, actions, action_kinds, stop_reason, grasp_objects); with the
same options and seed it is the record of `ms-drake bench search` action by action (the same heap
and the same controller).
"""

import argparse
import json

from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.policies.bin_search import (
    MakeBinSearchController,
    SimulationInfo,
    config_scenario,
    connect_controller,
    load_bin_search_config,
    search_scenario,
    set_initial_conditions,
)
from ms_drake.scenes.layouts import layout_heap
from ms_drake.station import MakeStation


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="the heap's seed (and the controller's)")
    ap.add_argument("--policy", default=None, help="xray (default) | largest | random | preempted_random | ...")
    ap.add_argument("--fidelity", default=None, choices=("primitive", "full"))
    ap.add_argument("--scenario", default=None, help="a bin scenario of diagrams/scenarios.yaml")
    ap.add_argument("--scenario-file", default=None, help="the scenario file (default: diagrams/scenarios.yaml)")
    ap.add_argument("--config", default=None, help="a named setting (table_8_2, ch7) or a BinSearchConfig YAML file")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE override, e.g. heap.objects=10")
    a = ap.parse_args(argv)
    named = {k: v for k, v in dict(policy=a.policy, fidelity=a.fidelity, scenario=a.scenario,
                                   scenario_file=a.scenario_file).items() if v is not None}
    config = load_bin_search_config(a.config, a.set, **named, seed=a.seed)

    scenario = config_scenario(config)         # FloatingGripperBin unless the config names another station
    heap = layout_heap(config.heap, a.seed)    # the objects, their poses and the target, as data

    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(search_scenario(scenario, heap, config), target_index=heap.target_index))
    controller = builder.AddSystem(MakeBinSearchController(
        scenario, config, sim=SimulationInfo.from_station(station, heap.target_index)))
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
