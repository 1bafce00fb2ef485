"""One shelf search on the Fetch as plain Drake: the Diagram (station + controller + the search's
end) built with DiagramBuilder, its initial conditions set by one call, and Simulator.AdvanceTo,
which returns when the search is over. Prints one JSON line: seed, success, actions (how many),
action_kinds, actions_taken ([kind, object, dx, dy] each), outcomes, stop_reason
("target_visible", "horizon", "no_action", or "timeout" when T passed first), visible_fraction,
sim_seconds. `ms-drake bench shelf-physics` (run_shelf_physics) runs the same Diagram and records
the same actions.

    .venv/bin/python sims/shelf_search_diagram.py --scenario FetchShelf --seed 0 --policy bluction_dar
"""

from __future__ import annotations

import argparse
import json

from pydrake.systems.analysis import ApplySimulatorConfig, Simulator, SimulatorStatus
from pydrake.systems.framework import DiagramBuilder

from ms_drake.experiments.shelf_physics import (
    search_horizon,
    set_initial_conditions,
    shelf_physics_scenario,
    shelf_scene_objects,
    shelf_simulation_info,
)
from ms_drake.geometry import PinholeCamera
from ms_drake.policies.shelf_search import MakeShelfSearchController, ShelfSearchConfig, connect_controller
from ms_drake.policies.shelf_termination import ShelfSearchTermination, connect_termination
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import DEFAULT_TARGET, generate_shelf_scene
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.station import MakeStation, get_plant


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="FetchShelf", help="scenario name (a shelf station; default FetchShelf)")
    ap.add_argument("--seed", type=int, required=True, help="the scene's seed (and the policy's)")
    ap.add_argument("--policy", default="bluction_dar", help="shelf policy (ms_drake.policies.shelf.SHELF_POLICIES)")
    ap.add_argument("--occluders", type=int, default=None, help="occluders (2-12; default drawn from the seed)")
    ap.add_argument("--horizon", type=int, default=None, help="action budget H (default 2n)")
    ap.add_argument("--perception", default="ground_truth", choices=("ground_truth", "depth"))
    ap.add_argument("--max-sim-time", type=float, default=None, help="T [s] (default 60 s + 45 s per action of H)")
    args = ap.parse_args(argv)

    scenario = shelf_physics_scenario(load_scenario(None, args.scenario))
    scene = generate_shelf_scene(ShelfGeometry.from_scenario(scenario), args.seed, args.occluders, DEFAULT_TARGET).scene
    params = ShelfSearchConfig(policy=args.policy, horizon=args.horizon, seed=args.seed, perception=args.perception)
    horizon = search_horizon(params, scene)

    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, extra_objects=shelf_scene_objects(scene)))
    sim = shelf_simulation_info(get_plant(station), scene)
    # with depth perception the controller reads only the camera ports (as on the hardware station)
    controller = builder.AddSystem(MakeShelfSearchController(scenario, params,
                                                             sim=None if args.perception == "depth" else sim))
    connect_controller(builder, controller, station)
    camera = PinholeCamera.from_config(scenario.cameras[params.camera])
    end = builder.AddSystem(ShelfSearchTermination(camera, sim.bodies[sim.target_id], horizon, params.period))
    connect_termination(builder, end, station, controller, params.camera)
    diagram = builder.Build()

    simulator = Simulator(diagram)
    ApplySimulatorConfig(scenario.simulator_config, simulator)
    context = simulator.get_mutable_context()
    set_initial_conditions(diagram, context, scene)
    status = simulator.AdvanceTo(args.max_sim_time or 60.0 + 45.0 * horizon)

    termination = end.GetOutputPort("termination").Eval(end.GetMyContextFromRoot(context))
    history = controller.GetOutputPort("history").Eval(controller.GetMyContextFromRoot(context))
    stopped = status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
    out = dict(seed=args.seed, policy=args.policy, perception=args.perception,
               success=bool(stopped and termination.success), actions=len(history),
               action_kinds=[o.action.shelf.kind for o in history],
               actions_taken=[[o.action.shelf.kind, o.action.shelf.object_id, round(o.action.shelf.dx, 4),
                               round(o.action.shelf.dy, 4)] for o in history],
               outcomes=[o.message for o in history],
               stop_reason=termination.reason if stopped else "timeout",
               visible_fraction=float(end.GetOutputPort("visibility").Eval(end.GetMyContextFromRoot(context))[0]),
               sim_seconds=float(context.get_time()))
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
