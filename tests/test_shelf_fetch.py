"""The Fetch at the shelf: its park pose leaves the front camera's view of the shelf free (the
station's initial pose and the controller's), and FetchFeasibleSelector chooses the policy's best
action that the Fetch's planner accepts (alone with fixed inputs, and in the controller Diagram)."""

import json

import cv2
import numpy as np
import pytest
from pydrake.multibody.tree import BodyIndex

from ms_drake.execution.shelf_backend import ShelfBackend, ShelfBody
from ms_drake.experiments.shelf_physics import (
    ShelfPhysicsError,
    _refused,
    _skipped,
    action_agreement,
    build_shelf_physics,
    physics_records,
    physics_table,
    physics_vs_foss,
    set_initial,
    shelf_physics_rollout,
    with_time_step,
)
from ms_drake.foss import Foss
from ms_drake.geometry import PinholeCamera
from ms_drake.perception.shelf_occupancy import ground_truth_occupancy
from ms_drake.policies.bin_search import ControllerError
from ms_drake.policies.shelf import ShelfPolicyParams
from ms_drake.policies.shelf_search import (
    FetchFeasibleSelector,
    MakeShelfSearchController,
    ShelfSearchAblation,
    ShelfSearchConfig,
    ShelfSimulationInfo,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.shelf import DEFAULT_TARGET, generate_shelf_scene
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.station import MakeStation, get_plant
from ms_drake.types import ShelfAction, ShelfObject, ShelfScene


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, "FetchShelf")


def _shelf_region(scenario, camera) -> np.ndarray:
    """Mask of the front image where the shelf's inside projects (its box, floor to top)."""
    hx, hy, h = 0.5 * np.asarray(scenario.environment.resolved_size(), float) * [1, 1, 2]
    origin = np.asarray(scenario.environment.position, float)
    pts = origin + np.array([[sx * hx, sy * hy, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, h)])
    uv, _ = camera.project(pts)
    mask = np.zeros((camera.height, camera.width), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
    return mask > 0


def _robot_pixels(plant, label, region) -> int:
    robot = [i for i in range(plant.num_bodies())
             if plant.GetModelInstanceName(plant.get_body(BodyIndex(i)).model_instance()).startswith("fetch")]
    assert len(robot) > 10  # the Fetch's links and the bluction tool's
    return int(np.count_nonzero(np.isin(label, robot) & region))


def test_station_initial_pose_leaves_the_shelf_in_view(scenario):
    station = MakeStation(scenario)
    ctx = station.CreateDefaultContext()
    label = np.asarray(station.GetOutputPort("front.label_image").Eval(ctx).data)[:, :, 0]
    camera = PinholeCamera.from_config(scenario.cameras["front"])
    region = _shelf_region(scenario, camera)
    assert region.sum() > 0.2 * region.size  # the shelf fills a good part of the image
    plant = get_plant(station)
    assert _robot_pixels(plant, label, region) == 0
    # clear of the robot's own links (a joint move of a few degrees from here collides with nothing)
    pc = plant.GetMyContextFromRoot(ctx)
    query = plant.get_geometry_query_input_port().Eval(pc)
    inspector = query.inspector()
    def robot_body(geometry_id):
        body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry_id))
        return body.name() if plant.GetModelInstanceName(body.model_instance()).startswith("fetch") else None

    near = [(robot_body(p.id_A), robot_body(p.id_B), p.distance)
            for p in query.ComputeSignedDistancePairwiseClosestPoints(0.015)]
    assert not [n for n in near if None not in n[:2]], near


def test_controller_park_pose_leaves_the_shelf_in_view(scenario):
    occ = ShelfObject("occ00", "box", 0.1, -0.1, 0.1, 0.08, 0.12)
    target = ShelfObject("target", "box", 0.1, 0.1, 0.06, 0.06, 0.06)
    scene = ShelfScene((occ,), target, 0)
    system = build_shelf_physics(scenario, scene, ShelfSearchConfig(policy="dar"))
    ctx = system.diagram.CreateDefaultContext()
    set_initial(system, ctx, scene)  # the controller's park pose, blade up
    label = np.asarray(system.station_output(ctx, "front.label_image").data)[:, :, 0]
    assert _robot_pixels(system.plant, label, _shelf_region(scenario, system.camera)) == 0
    # the objects are in view: the labeller sees the occluder
    assert np.count_nonzero(label == system.sim.bodies["occ00"].body_index) > 500


def _scene_with_backend(scenario, seed: int, occluders: int):
    geometry = ShelfGeometry.from_scenario(scenario)
    scene = generate_shelf_scene(geometry, seed, occluders, DEFAULT_TARGET).scene
    objs = list(scene.objects) + [scene.target]
    bodies = {o.id: ShelfBody(k, o) for k, o in enumerate(objs)}
    backend = ShelfBackend(scenario, bodies, scene.target.id)
    return scene, backend, geometry, ground_truth_occupancy(geometry, scene).image_x


@pytest.fixture(scope="module")
def hard_scene(scenario):
    """Seed 4, 10 occluders: Bluction-DAR's best action in FOSS (a suction) is out of the Fetch's
    reach, its second best is not."""
    return _scene_with_backend(scenario, 4, 10)


@pytest.fixture(scope="module")
def pull_out_scene(scenario):
    """Seed 25, 10 occluders: Bluction-DAR's best action in FOSS is a suction whose object the
    Fetch cannot lift and pull out."""
    return _scene_with_backend(scenario, 25, 10)


def test_feasible_selector_skips_what_the_fetch_cannot_do(hard_scene):
    scene, backend, geometry, dist = hard_scene
    sel = FetchFeasibleSelector("bluction_dar", Foss(geometry), backend, ShelfPolicyParams(seed=4))
    best = sel.rules.select(scene, dist, ())
    assert backend.feasible(best.shelf, scene) != "ok"
    chosen = sel.choose(scene, dist, ())
    assert chosen.kind == "shelf" and chosen.shelf != best.shelf
    assert backend.feasible(chosen.shelf, scene) == "ok"
    assert chosen.reason.endswith("(1 Fetch-infeasible skipped)")
    # the plan the executor makes from the park pose succeeds too
    assert not isinstance(backend.plan_scene(chosen.shelf, backend.q_park, scene), str)
    # with one candidate only, the selector stops instead of proposing an infeasible action
    one = FetchFeasibleSelector("bluction_dar", Foss(geometry), backend, ShelfPolicyParams(seed=4), max_candidates=1)
    stop = one.choose(scene, dist, ())
    assert stop.kind == "stop" and "feasible on the Fetch" in stop.reason


def test_suction_out_of_reach_is_ruled_out_by_its_pull_out(pull_out_scene):
    """Every placement of an object whose lift and pull-out the Fetch cannot do is infeasible with
    the planner's status, found by one plan of the shared start (ShelfBackend.pulls_out)."""
    scene, backend, geometry, dist = pull_out_scene
    best = FetchFeasibleSelector("bluction_dar", Foss(geometry), backend, ShelfPolicyParams(seed=25)).rules.select(
        scene, dist, ()).shelf
    assert best.kind == "suction"
    status = backend.feasible(best, scene)
    assert status != "ok" and status == backend.plan_scene(best, backend.q_park, scene)
    # Here the lift and pull-out fail (cached), so no placement of the object is planned in full.
    pulls = [k for k in backend._feasible if k[0] == "pull" and k[1] == best.object_id]
    assert pulls and all(backend._feasible[k] == status for k in pulls)
    assert not any(k[0] == "suction" and k[1] == best.object_id for k in backend._feasible)


def test_reach_check_rejects_a_push_whose_tool_sweeps_a_neighbour(scenario):
    """Fixed inputs: the push of a cylinder to the right, its left neighbour 1 cm away. The IK plans
    it (the straight lines know only the shelf), but in the 1 cm gap the blade goes in raised and
    the shaft over the cylinder, into the taller neighbour: the reach check rejects it; with the
    neighbour 4.6 cm away the shaft fits beside the cylinder and the same push is accepted."""
    pushed = ShelfObject("occ01", "cylinder", 0.106, 0.008, 0.18, 0.18, 0.08)
    target = ShelfObject("target", "box", -0.23, 0.185, 0.06, 0.06, 0.06)
    push = ShelfAction("push", "occ01", 0.1, 0.0)
    for x, status in ((-0.064, "collision:path:body-occ02"), (-0.1, "ok")):
        neighbour = ShelfObject("occ02", "box", x, -0.125, 0.14, 0.18, 0.12)
        scene = ShelfScene((neighbour, pushed), target, 0)
        backend = ShelfBackend(scenario, {o.id: ShelfBody(k, o) for k, o in enumerate((neighbour, pushed, target))},
                               "target")
        assert Foss(ShelfGeometry.from_scenario(scenario)).step(scene, push)[1].success  # FOSS allows both
        motion = backend.plan_scene(push, backend.q_park, scene)
        assert not isinstance(motion, str)  # the IK + Cartesian plan exists either way
        assert backend.feasible(push, scene) == status
    # a box in the tool's way in: standing at the shelf's front edge it blocks the push; fallen off
    # the shelf (its centre in front of it, at a height the footprint does not tell) it is no obstacle
    for y, status in ((-0.29, "collision:"), (-0.4, "ok")):
        other = ShelfObject("occ03", "box", 0.0, y, 0.14, 0.13, 0.07)
        scene = ShelfScene((neighbour, pushed, other), target, 0)
        backend = ShelfBackend(scenario, {o.id: ShelfBody(k, o) for k, o in enumerate((neighbour, pushed, other,
                                                                                       target))}, "target")
        assert backend.feasible(push, scene).startswith(status)
    # a suction whose pull-out the Fetch cannot reach is rejected before any path is checked
    deep = ShelfObject("occ00", "box", 0.27, 0.25, 0.05, 0.09, 0.2)
    scene = ShelfScene((deep,), target, 0)
    backend = ShelfBackend(scenario, {"occ00": ShelfBody(0, deep), "target": ShelfBody(1, target)}, "target")
    assert backend.feasible(ShelfAction("suction", "occ00", -0.3, 0.0), scene) in ("unreachable", "collision",
                                                                                  "shelf_top")


@pytest.fixture(scope="module")
def sweep_scene(scenario):
    """Seed 300, 4 occluders: DER-3's best push (occ01 to the right) plans on the Fetch, but its tool,
    raised over occ01 in the 8 mm gap to occ02, sweeps into occ02 (in physics it shoves occ02 18 cm)."""
    geometry = ShelfGeometry.from_scenario(scenario)
    scene = generate_shelf_scene(geometry, 300, 4, DEFAULT_TARGET).scene
    objs = list(scene.objects) + [scene.target]
    backend = ShelfBackend(scenario, {o.id: ShelfBody(k, o) for k, o in enumerate(objs)}, scene.target.id)
    return scene, backend, geometry, ground_truth_occupancy(geometry, scene)


def test_feasible_selector_passes_over_a_push_into_a_neighbour(sweep_scene):
    scene, backend, geometry, occupancy = sweep_scene
    sel = FetchFeasibleSelector("der3", Foss(geometry), backend, ShelfPolicyParams(seed=300))
    best = sel.rules.select(scene, occupancy.image_x, ()).shelf
    assert (best.kind, best.object_id) == ("push", "occ01") and best.dx > 0
    assert not isinstance(backend.plan_scene(best, backend.q_park, scene), str)
    assert backend.feasible(best, scene).startswith("collision:path:")
    ctx = sel.CreateDefaultContext()
    sel.GetInputPort("scene").FixValue(ctx, scene)
    sel.GetInputPort("occupancy").FixValue(ctx, occupancy)
    sel.GetInputPort("history").FixValue(ctx, ())
    chosen = sel.GetOutputPort("action").Eval(ctx)
    assert chosen.kind == "shelf" and chosen.shelf != best and backend.feasible(chosen.shelf, scene) == "ok"
    assert chosen.reason.endswith("Fetch-infeasible skipped)") and _skipped(chosen.reason) >= 1


def test_search_diagram_executes_the_reachable_choice(sweep_scene):
    """The wired search (station + controller + termination, one Simulator): its first action is the
    selector's reachable choice, not the policy's best in FOSS, and it executes without a plan
    failure."""
    scene, backend, geometry, occupancy = sweep_scene
    sel = FetchFeasibleSelector("der3", Foss(geometry), backend, ShelfPolicyParams(seed=300))
    best = sel.rules.select(scene, occupancy.image_x, ()).shelf
    chosen = sel.choose(scene, occupancy.image_x, ()).shelf
    rec = shelf_physics_rollout(ShelfSearchConfig(policy="der3", horizon=1), 300, 4).record
    assert not rec["config"]["ablation"]["foss_choice"] and rec["steps"] == 1 and rec["plan_failures"] == 0
    assert rec["actions_taken"][0] == [chosen.kind, chosen.object_id, round(chosen.dx, 4), round(chosen.dy, 4)]
    assert rec["actions_taken"][0][:3] != [best.kind, best.object_id, round(best.dx, 4)]
    assert rec["skipped"] >= 1


def test_feasible_selector_alone_fixed_inputs(hard_scene):
    scene, backend, geometry, dist = hard_scene
    sel = FetchFeasibleSelector("bluction_dar", Foss(geometry), backend, ShelfPolicyParams(seed=4))
    ctx = sel.CreateDefaultContext()
    sel.GetInputPort("scene").FixValue(ctx, scene)
    sel.GetInputPort("occupancy").FixValue(ctx, ground_truth_occupancy(geometry, scene))
    sel.GetInputPort("history").FixValue(ctx, ())
    a = sel.GetOutputPort("action").Eval(ctx)
    assert a.kind == "shelf" and backend.feasible(a.shelf, scene) == "ok"
    assert a == sel.choose(scene, dist, ())
    with pytest.raises(ControllerError, match="max_candidates"):
        FetchFeasibleSelector("dar", Foss(geometry), backend, max_candidates=0)


def test_controller_uses_the_feasible_selector(scenario, hard_scene):
    scene, backend, _, _ = hard_scene
    sim = ShelfSimulationInfo(backend.bodies, scene.target.id)
    c = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="bluction_dar", seed=4), sim=sim)
    assert isinstance(c.GetSubsystemByName("policy_selector"), FetchFeasibleSelector)
    rules = c.GetSubsystemByName("policy_selector").rules.params
    assert (rules.min_move, rules.nil_move, rules.revisit) == (0.01, 0.01, 0.01)
    der3 = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="der3", seed=4), sim=sim)
    rules = der3.GetSubsystemByName("policy_selector").rules.params
    assert (rules.min_move, rules.nil_move, rules.revisit) == (0.0, 0.0, 0.0)  # DER-3 keeps its rule
    c2 = MakeShelfSearchController(scenario, ShelfSearchConfig(policy="bluction_dar", ablation=ShelfSearchAblation(foss_choice=True)), sim=sim)
    assert not isinstance(c2.GetSubsystemByName("policy_selector"), FetchFeasibleSelector)
    with pytest.raises(ControllerError, match="max_candidates"):
        ShelfSearchConfig(max_candidates=0)
    with pytest.raises(ControllerError, match="revisit=-0.01"):
        ShelfSearchConfig(revisit=-0.01)


def test_time_step_and_skipped_counts(scenario):
    s = with_time_step(scenario, 0.01)
    assert s.plant_config.time_step == 0.01 and scenario.plant_config.time_step == 0.002
    assert with_time_step(scenario, None) is scenario
    with pytest.raises(ShelfPhysicsError, match="time_step"):
        with_time_step(scenario, 0.0)
    assert _skipped("bluction_dar: score 0.1 (3 Fetch-infeasible skipped)") == 3 and _skipped("random") == 0
    reasons = ["bluction_dar: score 0.1 [refused: nil_move 2, min_move 5, revisit 1] (3 Fetch-infeasible skipped)",
               "bluction_dar: score 0.2 [refused: nil_move 0, min_move 4, revisit 0]", "random"]
    assert _refused(reasons) == {"nil_move": 2, "min_move": 9, "revisit": 1} and _refused(["random"]) == {}


def test_action_agreement_counts_what_each_action_toppled():
    rec = {"actions_taken": [["push", "a", 0.1, 0.0], ["push", "b", 0.1, 0.0], ["suction", "c", 0.1, 0.0],
                             ["push", "d", 0.1, 0.0], ["suction", "e", 0.0, 0.0]],
           "outcomes": ["agree=0 err=0.002 moved=0.1 commanded=0.1 others=0.004 toppled=b foss=ok",
                        "agree=0 err=0.003 moved=0.1 commanded=0.1 others=0.001 toppled=b foss=ok",
                        "agree=0 err=0.25 moved=0.02 commanded=0.3 others=0.000 toppled=b foss=ok",
                        "plan_failed:unreachable",
                        "agree=0 err=0.001 moved=0.1 commanded=0.1 others=0.000 toppled=b,e foss=ok"]}
    assert action_agreement(rec) == [("push", False), ("push", True), ("suction", False), ("suction", False)]
    assert action_agreement(rec, min_commanded=0.2) == [("suction", False)]  # the 0.3 m suction only
    table = physics_table([dict(rec, policy="der3", occluders=8, success=True, steps=5, plan_failures=1,
                                skipped=2)], ("der3",))
    assert "| all | physics = FOSS per action | 25 % (1/4) |" in table
    assert "| all | physics = FOSS, pushes | 50 % (1/2) |" in table and "| 1 of 5 steps |" in table
    assert "| all | physics = FOSS, suction moving >= 5 cm | 0 % (0/2) |" in table


def test_physics_vs_foss_pairs_scenes_by_seed_and_occluders():
    def rec(policy, n, seed, ok, **kw):
        return dict(policy=policy, occluders=n, seed=seed, success=ok, **kw)
    phys = [rec("bluction_dar", 8, 0, True), rec("bluction_dar", 10, 1, False), rec("bluction_dar", 12, 2, True),
            rec("bluction_dar", 8, 3, True)]
    foss = [rec("bluction_dar", 8, 0, True), rec("bluction_dar", 10, 1, True), rec("bluction_dar", 12, 2, False),
            rec("bluction_dar", 10, 0, False),  # another scene: seed 0 with 10 occluders
            rec("bluction_dar", 8, 3, False, perception="learned")]  # not the ground-truth FOSS run
    table = physics_vs_foss(phys, foss, ("bluction_dar",))
    assert "| Bluction-DAR | 3 | 2 | 2 | 1 | 1 (seeds 2) | 1 (seeds 1) | 1 |" in table
    # a scene of another station is another scene
    table = physics_vs_foss(phys, foss + [rec("bluction_dar", 8, 3, False, scenario="FetchWideShelf")],
                            ("bluction_dar",))
    assert "| Bluction-DAR | 3 | 2 | 2 | 1 | 1 (seeds 2) | 1 (seeds 1) | 1 |" in table
    wide = [dict(r, scenario="FetchWideShelf") for r in phys]  # FOSS on the wide shelf: only scene 8 / 0
    table = physics_vs_foss(wide, foss + [rec("bluction_dar", 8, 0, False, scenario="FetchWideShelf")],
                            ("bluction_dar",))
    assert "| Bluction-DAR | 1 | 1 | 0 | 0 | 1 (seeds 0) | 0 | 1 |" in table


def test_physics_records_one_per_policy_and_seed(tmp_path):
    f = tmp_path / "r.jsonl"
    def rec(policy, fidelity="physics", **kw):
        config = ShelfSearchConfig(policy=policy).record()
        return dict(seed=kw.pop("seed", 1), policy=policy, fidelity=fidelity, perception="ground_truth", config=config,
                    **kw)
    lines = [rec("der3", steps=2), rec("der3", steps=5), rec("bluction_dar", steps=3), rec("der3", "foss", seed=2)]
    f.write_text("".join(json.dumps(r) + "\n" for r in lines))
    recs = physics_records([f])
    assert [(r["policy"], r["steps"]) for r in recs] == [("der3", 2), ("bluction_dar", 3)]
