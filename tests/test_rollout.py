"""Bin-search rollouts: on-demand, per-object, cropped grasp planning (LazyGraspPlanner) gives the
planners' own answers; a rollout is reproducible from its seed."""

import numpy as np
import pytest

from ms_drake.grasping.planner import LazyGraspPlanner, LazyGrasps, object_seed
from ms_drake.policies import select_action
from ms_drake.types import InstanceMasks


@pytest.fixture(scope="module")
def heap4():
    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap

    return generate_heap(load_scenario(None, "BinHeap15"), 4, seed=3, params=SEARCH_HEAPS)


@pytest.fixture(scope="module")
def scene(heap4):
    """A search system on heap4 and its first observation: depth, masks, object geometry."""
    from pydrake.systems.analysis import Simulator

    from ms_drake.experiments.rollout import build_search
    from ms_drake.policies.bin_search import load_bin_search_config, set_initial_conditions
    from ms_drake.scenario import load_scenario

    params = load_bin_search_config("ch7", policy="largest", seed=5, grasp_planner="image")
    system = build_search(load_scenario(None, "FloatingGripperBin"), heap4, params)
    sim = Simulator(system.diagram)
    ctx = sim.get_mutable_context()
    set_initial_conditions(system.diagram, ctx, heap4)
    gp = system.controller.GetSubsystemByName("grasp_planner")
    gctx = gp.GetMyContextFromRoot(ctx)
    depth = np.asarray(gp.depth_port.Eval(gctx).data, float)[..., 0]
    masks = gp.masks_port.Eval(gctx)
    geoms = {o.id: o for o in gp.objects_port.Eval(gctx)}
    return system, ctx, depth, masks, geoms


def test_cropped_per_object_plan_equals_the_whole_image(scene):
    system, _, depth, masks, geoms = scene
    gp = system.controller.GetSubsystemByName("grasp_planner")
    fresh = LazyGraspPlanner(gp.planners, depth.shape[1], depth.shape[0], seed=5)
    assert len(masks) == 4
    models = set()
    for k, oid in enumerate(masks.ids):
        cropped = fresh.plan_object(depth, masks, geoms, oid)
        whole = []
        for p in gp.planners:  # the wrapped planner itself, on the whole image, the same seed
            whole.extend(p.plan(depth, InstanceMasks(masks.masks[k:k + 1], (oid,), np.ones(1)), (geoms[oid],),
                                seed=object_seed(5, oid)))
        assert cropped == tuple(whole)
        models |= {g.model for g in whole}
    assert models == {"soft_point", "suction"}


def test_lazy_grasps_plan_only_what_the_selector_reaches(scene):
    system, _, depth, masks, geoms = scene
    gp = system.controller.GetSubsystemByName("grasp_planner")
    lazy_planner = LazyGraspPlanner(gp.planners, depth.shape[1], depth.shape[0], seed=5)
    lazy = LazyGrasps(lambda oid: lazy_planner.plan_object(depth, masks, geoms, oid), masks.ids)
    eager = tuple(g for oid in masks.ids for g in lazy_planner.plan_object(depth, masks, geoms, oid))
    box, _, _, cylinder = masks.ids  # heap4: box_324, the target cylinder_034, packaged_071, cylinder_094
    for policy, choice in (("largest", box), ("random", cylinder), ("preempted_random", cylinder)):
        lazy = LazyGrasps(lambda oid: lazy_planner.plan_object(depth, masks, geoms, oid), masks.ids)
        a = select_action(policy, masks, grasps=lazy)
        b = select_action(policy, masks, grasps=eager)
        assert a == b
        # the first object it looked up had a grasp above the threshold: only that one was planned
        assert a.kind == "grasp" and a.grasp.object_id == choice and lazy.planned == (choice,), policy
    # Iterating plans everything and yields the best grasp per object.
    full = dict(lazy)
    for oid, g in full.items():
        assert g.quality == max(x.quality for x in eager if x.object_id == oid)


def test_a_lookup_plans_an_object_once_per_step(scene):
    system, _, depth, masks, geoms = scene
    gp = system.controller.GetSubsystemByName("grasp_planner")
    planner = LazyGraspPlanner(gp.planners, depth.shape[1], depth.shape[0], seed=5)
    calls = []

    def plan_one(oid):
        calls.append(oid)
        return planner.plan_object(depth, masks, geoms, oid)

    lazy = LazyGrasps(plan_one, masks.ids)
    oid = masks.ids[0]
    first = lazy.get(oid)
    assert lazy.get(oid) is first and calls == [oid] and lazy.planned == (oid,)
    assert lazy.get("no such id") is None and calls == [oid]
    # A fresh step (a new LazyGrasps) plans again, and gets the same answer for the same input.
    again = LazyGrasps(plan_one, masks.ids).get(oid)
    assert again == first and calls == [oid, oid]


def test_lazy_grasp_planner_alone(scene):
    system, _, depth, masks, geoms = scene
    from pydrake.systems.sensors import ImageDepth32F

    gp = system.controller.GetSubsystemByName("grasp_planner")
    alone = LazyGraspPlanner(gp.planners, depth.shape[1], depth.shape[0], seed=5)
    ctx = alone.CreateDefaultContext()
    img = ImageDepth32F(depth.shape[1], depth.shape[0])
    img.mutable_data[:, :, 0] = depth
    alone.GetInputPort("depth_image").FixValue(ctx, img)
    alone.GetInputPort("masks").FixValue(ctx, masks)
    alone.GetInputPort("objects").FixValue(ctx, tuple(geoms.values()))
    out = alone.GetOutputPort("grasps").Eval(ctx)
    assert out.planned == ()  # nothing is planned before a lookup
    oid = masks.ids[0]
    g = out.get(oid)
    assert out.planned == (oid,) and (g.object_id, g.model, g.quality) == (oid, "suction", 0.25)
    # Without geometry the object is planned on the whole image from its depth points only.
    alone.GetInputPort("objects").FixValue(ctx, ())
    out = alone.GetOutputPort("grasps").Eval(ctx)
    best = {k: (v.object_id, v.model, v.quality) for k, v in dict(out).items()}
    box, target, packaged, cylinder = masks.ids
    assert best == {box: (box, "suction", 1.0), target: (target, "soft_point", 0.5),
                    packaged: (packaged, "suction", 0.25), cylinder: (cylinder, "soft_point", 0.25)}
    with pytest.raises(TypeError):
        LazyGraspPlanner([object()], 64, 48)


def test_rollout_is_reproducible_from_its_seed(heap4):
    from ms_drake.experiments.rollout import rollout
    from ms_drake.policies.bin_search import load_bin_search_config

    timing = ("seconds", "cpu_seconds")
    cfg = load_bin_search_config("ch7", ["heap.objects=4"], policy="largest", grasp_planner="image", horizon=8)
    a, b = ({k: v for k, v in rollout(cfg, 3, heap=heap4).record().items() if k not in timing} for _ in range(2))
    assert a == b
    # the target grasped at the first action
    assert {k: a[k] for k in ("success", "actions", "action_kinds", "stop_reason", "grasp_plans", "target")} == \
        dict(success=True, actions=1, action_kinds=["grasp"], stop_reason="success", grasp_plans=1,
             target="procedural/cylinder_034")
    assert a["objects"] == 4 and a["objects_present"] == len(heap4.objects)


def test_lazy_planner_wired_in_the_search_diagram(scene):
    system, ctx, _, masks, _ = scene
    action = system.output(ctx, "action")
    grasps = system.output(ctx, "grasps")
    assert isinstance(grasps, LazyGrasps)
    # the target's grasp (quality 0.5) reaches t_thresh: the target is planned first and grasped
    target = masks.ids[1]
    assert action.kind == "grasp" and (action.grasp.object_id, action.grasp.quality) == (target, 0.5)
    assert grasps.planned == (target,)


def test_the_scenarios_simulator_config_is_applied(heap4):
    from ms_drake.experiments.rollout import build_search, run_search
    from ms_drake.policies.bin_search import load_bin_search_config
    from ms_drake.scenario import load_scenario

    scenario = load_scenario(None, "FloatingGripperBin")
    scenario.simulator_config.integration_scheme = "no_such_integrator"
    params = load_bin_search_config("ch7", policy="largest", seed=5, horizon=1)
    system = build_search(scenario, heap4, params)
    with pytest.raises(Exception, match="no_such_integrator"):
        run_search(system, heap4, params)
