"""The rearrangement controller (ms_drake.policies.rearrange), its arm model
(ms_drake.planning.arm_model) and the experiment around it (ms_drake.experiments.rearrange)."""

import dataclasses
import json

from ms_drake.config_files import config_dict

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.systems.framework import DiagramBuilder

from ms_drake.experiments.rearrange import (
    bench_params,
    rearrange_records,
    DEMO_ZONE,
    SCENARIO,
    barrier_scene,
    build_rearrange,
    rearrange_table,
    run_rearrange,
    run_rearrange_bench,
    table_scene,
)
from ms_drake.geometry import PinholeCamera
from ms_drake.planning.arm_model import ArmModel, ArmModelError
from ms_drake.planning.mppi import MppiParams, mppi_step
from ms_drake.planning.sequences import arm_ik
from ms_drake.policies.rearrange import (
    ControllerError,
    MakeRearrangementController,
    RearrangementPlanner,
    RearrangeParams,
    RearrangeSimInfo,
    cloud_from_depth,
    connect_controller,
    pad,
    sample_placements,
    segment_scene,
    sim_info,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, station_objects


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(None, SCENARIO)


@pytest.fixture(scope="module")
def ik(scenario):
    ik, _, q_home, keep = arm_ik(scenario, "panda")
    return ik, q_home, keep


@pytest.fixture(scope="module")
def barrier(scenario):
    """The barrier scene's station, its plant, and the front camera's depth and label images."""
    heap = barrier_scene()
    scn = scenario_with_heap(scenario, heap)
    station = MakeStation(scn)
    ctx = station.CreateDefaultContext()
    set_heap_poses(station, ctx, heap)
    plant = get_plant(station)
    depth = station.GetOutputPort("front.depth_image").Eval(ctx)
    label = station.GetOutputPort("front.label_image").Eval(ctx)
    return scn, plant, depth, label


def test_arm_model_kinematics_points_and_self_collision(ik):
    ik, q_home, _ = ik
    model = ArmModel(ik, points_per_body=64)
    assert {"panda_link3", "panda_link7", "body", "left_finger"} <= set(model.points)
    assert all(p.shape == (64, 3) for p in model.points.values())
    rng = np.random.default_rng(1)
    qs = q_home + rng.normal(0, 0.6, (4, 7))
    poses = model.link_poses(qs)
    plant, ctx = ik.plant, ik.context
    for i, q in enumerate(qs):
        q_all = model.q_fixed.copy()
        q_all[model.idx] = q
        plant.SetPositions(ctx, q_all)
        for name in model.body_names:
            X = plant.EvalBodyPoseInWorld(ctx, plant.GetBodyByName(name)).GetAsMatrix4()
            assert np.abs(X - poses[name][i]).max() < 1e-9
    plant.SetPositions(ctx, model.q_fixed)
    # the tool pose at a configuration: the tool frame of the plant there
    X_tool = model.tool_pose(qs[0])
    q_all = model.q_fixed.copy()
    q_all[model.idx] = qs[0]
    plant.SetPositions(ctx, q_all)
    assert np.allclose(X_tool, ik.frame.CalcPoseInWorld(ctx).GetAsMatrix4())
    plant.SetPositions(ctx, model.q_fixed)
    down = q_home.copy()
    down[1], down[3] = 1.6, -0.4  # the arm folded forward into the table
    assert list(model.self_collides(np.stack([q_home, down]))) == [False, True]
    with pytest.raises(ArmModelError, match="7 joints"):
        model.link_poses(np.zeros((2, 6)))


def test_mppi_lazy_check_chooses_the_same_waypoint():
    lower, upper = -np.ones(2) * 3, np.ones(2) * 3
    wall = lambda qs: (np.abs(qs[:, 0] - 0.5) < 0.1) & (qs[:, 1] < 0.4)
    q, goal = np.zeros(2), np.array([1.0, 0.0])
    params = MppiParams(trajectories=64, horizon=12, sigma=0.8)
    full, info_full = mppi_step(q, goal, wall, lower, upper, params, np.random.default_rng(3))
    lazy, info_lazy = mppi_step(q, goal, None, lower, upper, params, np.random.default_rng(3), lazy=wall)
    assert full is not None and np.allclose(full, lazy)
    assert info_lazy["lazy_checks"] < info_full["checks"]
    path = info_lazy["path"]
    assert np.allclose(path[-1], lazy) and not wall(path).any()


def test_params_and_sim_info_errors():
    with pytest.raises(ControllerError, match="method 'fcl' unknown"):
        RearrangeParams(method="fcl")
    with pytest.raises(ControllerError, match="zone"):
        RearrangeParams(zone=(0.2, 0.1, 0.0, 0.1))
    with pytest.raises(ControllerError, match="trajectories must be >= 1"):
        RearrangeParams(trajectories=0)
    with pytest.raises(ControllerError, match="not objects of the station"):
        RearrangeSimInfo({3: "a"}, (1,), ("b",))


def test_placements_lowest_first_in_the_zone_and_padding():
    rng = np.random.default_rng(0)
    # a 10 cm tall block over the zone's left half
    xs, ys = np.meshgrid(np.linspace(0.0, 0.1, 20), np.linspace(0.0, 0.2, 20))
    block = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.10)])
    held = np.array([[0.02, 0.02, 0], [-0.02, 0.02, 0], [0.02, -0.02, 0], [-0.02, -0.02, 0.03]])
    c = sample_placements((0.0, 0.2, 0.0, 0.2), block, held, 50, rng)
    assert c.shape == (50, 3) and np.all(np.diff(c[:, 2]) >= 0)
    assert np.all((c[:, 0] >= 0) & (c[:, 0] <= 0.2) & (c[:, 1] >= 0) & (c[:, 1] <= 0.2))
    assert c[0, 2] == 0.0 and c[-1, 2] == pytest.approx(0.10)
    assert c[0, 0] > 0.1  # the lowest placements are off the block
    grown = pad(held, 0.01)
    r0 = np.linalg.norm(held - held.mean(axis=0), axis=1)
    r1 = np.linalg.norm(grown - held.mean(axis=0), axis=1)
    assert np.allclose(r1 - r0, 0.01)


def test_segment_scene_by_labels_and_by_clusters(scenario, barrier):
    scn, plant, depth, label = barrier
    camera = PinholeCamera.from_config(scn.cameras["front"])
    P = cloud_from_depth(np.asarray(depth.data)[:, :, 0], camera)
    objs = station_objects(plant)
    info = sim_info(plant, [objs[0].model_name])
    ids = segment_scene(P, np.asarray(label.data)[:, :, 0], info)
    target = P[ids == objs[0].model_name]
    assert len(target) > 200
    assert np.allclose(target.mean(axis=0)[:2], (-0.22, -0.20), atol=0.04)
    # without labels: every object a cluster; the target's cluster is where the target is
    ids2 = segment_scene(P, None, None)
    names = set(np.unique(ids2[ids2 != ""]))
    assert len(names) >= 5
    assert all(n.startswith("cluster_") for n in names)
    k = ids2[ids == objs[0].model_name]
    assert (k == k[0]).mean() > 0.9 and k[0].startswith("cluster_")


def test_planner_alone_with_fixed_inputs(scenario, barrier):
    scn, plant, depth, label = barrier
    objs = station_objects(plant)
    params = RearrangeParams(method="sdf", zone=DEMO_ZONE, trajectories=40, horizon=10)
    planner = RearrangementPlanner(scn, params, sim_info(plant, [objs[0].model_name]))
    ctx = planner.CreateDefaultContext()
    planner.GetInputPort("depth_image").FixValue(ctx, depth)
    planner.GetInputPort("label_image").FixValue(ctx, label)
    planner.GetInputPort("arm_state").FixValue(ctx, np.concatenate([planner.q_home, np.zeros(7)]))
    planner.GetInputPort("jaw_state").FixValue(ctx, [0.1, 0.0])
    assert np.allclose(planner.GetOutputPort("arm_position").Eval(ctx), planner.q_home)
    assert planner.GetOutputPort("jaw_position").Eval(ctx)[0] == pytest.approx(0.1)
    s0 = planner._fsm(ctx)
    s1 = planner.step(s0, 0.0, ctx)  # observe: target, grasp, pre-grasp goal
    assert s1.phase == "pregrasp" and s1.target == objs[0].model_name and s1.after == "grasp"
    X_pre = planner.model.tool_pose(s1.goal)
    assert np.allclose(X_pre[:2, 3], (-0.22, -0.20), atol=0.04) and X_pre[2, 3] > 0.08
    assert len(s1.target_points) > 100 and s1.checker is not None
    s2 = planner.step(s1, 0.0, ctx)  # one MPPI call and its motion
    assert s2.calls == 1 and s2.traj is not None and s2.busy_until > 0
    assert not planner.scene_collides(s1.checker, s2.traj.value(s2.traj.duration)[None], False)[0]
    # the jaw closed on nothing: the attempt fails and the arm goes home
    s3 = planner.step(dataclasses.replace(s2, phase="lift", q_cmd=s1.goal), 5.0, _jaw(planner, ctx, 0.0))
    assert s3.phase == "home" and s3.history[-1].status == "empty_jaw" and not s3.history[-1].grasped


def _jaw(planner, ctx, opening):
    planner.GetInputPort("jaw_state").FixValue(ctx, [opening, 0.0])
    return ctx


def test_controller_connects_to_the_hardware_station(scenario):
    builder = DiagramBuilder()
    hardware = builder.AddSystem(MakeStation(scenario, hardware=True, lcm=DrakeLcm("memq://rearrange_controller")))
    assert not hardware.HasOutputPort("front.label_image")
    controller = builder.AddSystem(MakeRearrangementController(scenario, RearrangeParams(method="sdf")))
    names = {controller.get_input_port(i).get_name() for i in range(controller.num_input_ports())}
    assert names == {"front.depth_image", "panda.state_estimated", "panda_jaw.state_measured"}
    connect_controller(builder, controller, hardware)
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    c = controller.GetMyContextFromRoot(ctx)
    assert controller.GetOutputPort("status").Eval(c).phase == "observe"
    assert np.allclose(controller.GetOutputPort("panda.position").Eval(c), controller.planner.q_home)
    with pytest.raises(ControllerError, match="PandaTable"):
        MakeRearrangementController(load_scenario(None, "FetchShelf"))


def test_wired_controller_moves_the_target_past_the_barrier(scenario):
    # ~6 s simulated; ~40 s on the shared 2 cores, so not marked slow
    params = RearrangeParams(method="coal_reconstruction", zone=DEMO_ZONE, trajectories=100, horizon=20)
    system = build_rearrange(scenario, barrier_scene(), params, order=[0])
    res = run_rearrange(system, params, max_sim=60.0)
    r = res.record
    assert r["failure"] == "" and r["grasps"] == 1, r
    (o,) = r["per_object"]
    assert o["placed"], o
    x0, x1, y0, y1 = DEMO_ZONE
    assert x0 - 0.02 <= o["end"][0] <= x1 + 0.02 and y0 - 0.02 <= o["end"][1] <= y1 + 0.02
    assert o["start"][1] < -0.1  # it started on the other side of the barrier (y = -0.06)


def test_table_scene_and_bench_records(scenario, tmp_path):
    heap = table_scene(scenario, 3, 6)
    assert len(heap.objects) == 6 and heap == table_scene(scenario, 3, 6)
    for o in heap.objects:
        x, y = o.q[4], o.q[5]
        assert -0.46 <= x <= 0.16 and -0.33 <= y <= 0.33
    f = tmp_path / "r.jsonl"
    rec = {"seed": 0, "method": "sdf", "objects": 10, "grasps_attempted": 12, "grasps": 8, "placements": 6,
           "minutes": 3.0, "plan_cpu_seconds": 20.0, "cpu_seconds": 90.0,
           "config": config_dict(bench_params("sdf", 0))}  # the whole controller config, as a run records it
    f.write_text(json.dumps(rec) + "\n")
    assert run_rearrange_bench("sdf", 1, 0, f, objects=10, log=lambda *a: None) == []  # already there
    # another controller config is another run: the table keeps them apart
    other = dict(rec, config=config_dict(bench_params("sdf", 0, trajectories=100)))
    assert "| table | sdf (T=100, H=40) | 1 |" in rearrange_table(rearrange_records([f]) + [other])
    table = rearrange_table([rec, dict(rec, seed=1)])
    assert "| table | sdf (T=300, H=40) | 2 | 20 | 16 / 24 | 12 | - | 6.0 |" in table
    with pytest.raises(ValueError, match="method 'fcl' unknown"):
        run_rearrange_bench("fcl", 1, 0, f)


def test_planner_without_labels_picks_an_object_cluster(scenario, barrier):
    """As on the hardware station (no label image): the target is a Euclidean cluster over the
    table, not the robot, the one nearest the robot outside the zone (here the barrier's first
    cylinder, too tall for a top-down grasp: the attempt ends with an IK status)."""
    scn, _, depth, _ = barrier
    params = RearrangeParams(method="sdf", zone=DEMO_ZONE, trajectories=40, horizon=10)
    planner = RearrangementPlanner(scn, params)
    ctx = planner.CreateDefaultContext()
    planner.GetInputPort("depth_image").FixValue(ctx, depth)
    planner.GetInputPort("arm_state").FixValue(ctx, np.concatenate([planner.q_home, np.zeros(7)]))
    planner.GetInputPort("jaw_state").FixValue(ctx, [0.1, 0.0])
    s = planner.step(planner._fsm(ctx), 0.0, ctx)
    assert s.target.startswith("cluster_") and len(s.target_points) > 500
    c = s.target_points.mean(axis=0)
    assert np.hypot(c[0] + 0.40, c[1] + 0.06) < 0.05  # the barrier's first cylinder (x = -0.40, y = -0.06)
    assert s.history[-1].target == s.target and s.tries[s.target] == 1
