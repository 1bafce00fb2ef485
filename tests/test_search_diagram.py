"""The bin search is the Diagram: ObjectCarrier alone and wired, the executor ending the simulation
(and failing it on a blow-up), removed objects in the drop-off trays, and sims/bin_search_diagram.py
agreeing with `ms-drake bench search` action by action."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import SpatialInertia, UnitInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from ms_drake.execution import ActionExecutor, CarrierError, ObjectCarrier, PrimitiveBackend
from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.policies.bin_search import (
    load_bin_search_config,
    ControllerError,
    MakeBinSearchController,
    SimulationInfo,
    connect_controller,
    search_scenario,
    set_initial_conditions,
)
from ms_drake.scenario import load_scenario
from ms_drake.scenes.heaps import SEARCH_HEAPS, generate_heap
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.environments import TRAY_INNER, dropoff_points
from ms_drake.types import Action

ROOT = Path(__file__).resolve().parents[1]
WS = Workspace((0.0, 0.0), (0.5, 0.4), 0.0, 0.12)


def _box_plant(mass=0.2):
    plant = MultibodyPlant(0.01)
    body = plant.AddRigidBody("box", SpatialInertia(mass, np.zeros(3), UnitInertia.SolidBox(0.05, 0.05, 0.05)))
    plant.Finalize()
    return plant, int(body.index())


def _fixed(carrier, removed, p=(0.0, 0.0, 0.05), v=(0.0, 0.0, 0.0), t=0.0):
    ctx = carrier.CreateDefaultContext()
    ctx.SetTime(t)
    carrier.GetInputPort("removed").FixValue(ctx, tuple(removed))
    carrier.GetInputPort("body_poses").FixValue(ctx, [RigidTransform(), RigidTransform(list(p))])
    carrier.GetInputPort("body_spatial_velocities").FixValue(
        ctx, [SpatialVelocity(), SpatialVelocity(np.zeros(3), np.asarray(v, float))])
    return ctx


def test_carrier_alone_lifts_a_removed_object_towards_the_nearer_tray():
    plant, b = _box_plant(0.2)
    trays = [np.array([0.0, 0.45, -0.02]), np.array([0.0, -0.45, -0.02])]
    carrier = ObjectCarrier(plant, {"a": b}, trays, travel_z=0.24)
    ctx = _fixed(carrier, ())
    assert carrier.GetOutputPort("applied_spatial_force").Eval(ctx) == []
    assert carrier.GetOutputPort("carrying").Eval(ctx)[0] == 0.0
    ctx = _fixed(carrier, ("a",))
    assert carrier.GetOutputPort("carrying").Eval(ctx)[0] == 1.0  # removed, not yet latched
    Simulator(carrier, ctx).AdvanceTo(0.0)  # the latching update at t = 0
    (F,) = carrier.GetOutputPort("applied_spatial_force").Eval(ctx)
    assert int(F.body_index) == b
    # at the start point, at rest: the force holds the object against gravity
    assert np.allclose(F.F_Bq_W.translational(), [0.0, 0.0, 0.2 * 9.81], atol=1e-6)
    # 0.1 s later the point it follows has risen: the force pulls up, beyond gravity
    ctx.SetTime(0.1)
    (F,) = carrier.GetOutputPort("applied_spatial_force").Eval(ctx)
    assert F.F_Bq_W.translational()[2] > 0.2 * 9.81 + 0.5
    # the path: up to the travel height, across to the nearer tray (+y for an object at y >= 0)
    path = carrier.path([0.0, 0.01, 0.05])
    assert np.allclose(path(path.duration)[0][:2], trays[0][:2])
    assert np.isclose(path.points[1][2], 0.24) and np.isclose(path.points[2][2], 0.24)
    assert np.allclose(carrier.path([0.0, -0.01, 0.05]).points[-1][:2], trays[1][:2])
    # released at the end: no force, not carrying
    ctx.SetTime(carrier.release_time([0.0, 0.0, 0.05]) + 0.01)
    assert carrier.GetOutputPort("applied_spatial_force").Eval(ctx) == []
    assert carrier.GetOutputPort("carrying").Eval(ctx)[0] == 0.0


def test_carrier_is_clear_once_the_object_leaves_the_cameras_view():
    plant, b = _box_plant()
    cfg = load_scenario(None, "FloatingGripperBin").cameras["overhead"]
    carrier = ObjectCarrier(plant, {"a": b}, [np.array([0.0, 0.45, -0.02])], travel_z=0.24,
                            camera=PinholeCamera.from_config(cfg), radii={"a": 0.03})
    ctx = _fixed(carrier, ("a",))
    Simulator(carrier, ctx).AdvanceTo(0.0)
    assert carrier.GetOutputPort("carrying").Eval(ctx)[0] == 1.0  # above the bin, in view
    ctx.SetTime(0.2)
    carrier.GetInputPort("body_poses").FixValue(ctx, [RigidTransform(), RigidTransform([0.0, 0.45, 0.24])])
    assert carrier.GetOutputPort("carrying").Eval(ctx)[0] == 0.0  # over the tray, out of view


def test_carrier_errors():
    plant, b = _box_plant()
    with pytest.raises(CarrierError, match="drop-off"):
        ObjectCarrier(plant, {"a": b}, [], travel_z=0.24)
    with pytest.raises(CarrierError, match="> 0"):
        ObjectCarrier(plant, {"a": b}, [np.zeros(3)], travel_z=0.24, speed=0.0)


def test_bin_environments_have_two_trays_out_of_the_cameras_view():
    s = load_scenario(None, "FloatingGripperBin")
    trays = dropoff_points(s.environment)
    assert len(trays) == 2 and trays[0][1] > 0 > trays[1][1]
    cam = PinholeCamera.from_config(s.cameras["overhead"])
    inner = np.array([[dx, dy, 0.0] for dx in (-0.5, 0.5) for dy in (-0.5, 0.5)]) * [*TRAY_INNER[:2], 0.0]
    for tray in trays:
        uv, _ = cam.project(tray + inner)
        outside = (uv[:, 0] < 0) | (uv[:, 0] > cam.width) | (uv[:, 1] < 0) | (uv[:, 1] > cam.height)
        assert outside.all()
    assert dropoff_points(load_scenario(None, "FetchShelf").environment) == []


def test_the_executor_ends_the_simulation_and_a_blow_up_fails_it():
    ex = ActionExecutor(PrimitiveBackend({"a": 1}, WS, tcp_offset=0.1, seed=0), period=0.05)
    ctx = ex.CreateDefaultContext()
    ex.action_port.FixValue(ctx, Action("stop", reason="no_action"))
    ex.poses_port.FixValue(ctx, [RigidTransform(), RigidTransform([0.0, 0.0, 0.02])])
    sim = Simulator(ex, ctx)
    status = sim.AdvanceTo(5.0)
    assert status.reason() == status.ReturnReason.kReachedTerminationCondition
    assert "no_action" in status.FormatMessage() and ctx.get_time() == 0.0
    assert sim.AdvanceTo(0.2).reason() == status.ReturnReason.kReachedBoundaryTime  # simulates on afterwards
    ex2 = ActionExecutor(PrimitiveBackend({"a": 1}, WS, tcp_offset=0.1, seed=0), period=0.05)
    ctx2 = ex2.CreateDefaultContext()
    ex2.action_port.FixValue(ctx2, Action("stop"))
    ex2.poses_port.FixValue(ctx2, [RigidTransform(), RigidTransform([np.nan, 0.0, 0.02])])
    sim2 = Simulator(ex2, ctx2)
    with pytest.raises(RuntimeError, match="non-finite"):
        sim2.AdvanceTo(1.0)


@pytest.fixture(scope="module")
def heap4():
    return generate_heap(load_scenario(None, "BinHeap15"), 4, 3, params=SEARCH_HEAPS)


def test_a_search_diagram_ends_itself_with_the_lifted_objects_in_the_trays(heap4):
    scenario = load_scenario(None, "FloatingGripperBin")
    builder = DiagramBuilder()
    config = load_bin_search_config("ch7", policy="largest", horizon=8, seed=1)
    station = builder.AddSystem(MakeStation(search_scenario(scenario, heap4, config), target_index=heap4.target_index))
    controller = builder.AddSystem(MakeBinSearchController(
        scenario, config,
        sim=SimulationInfo.from_station(station, heap4.target_index)))
    connect_controller(builder, controller, station)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    set_initial_conditions(diagram, simulator.get_mutable_context(), heap4)
    result = simulator.AdvanceTo(120.0)
    assert result.reason() == result.ReturnReason.kReachedTerminationCondition
    cc = controller.GetMyContextFromRoot(simulator.get_context())
    status = controller.GetOutputPort("status").Eval(cc)
    assert status.done and status.stop_reason == "success" and status.steps >= 1
    simulator.AdvanceTo(simulator.get_context().get_time() + 1.5)  # the target carried out too
    removed = controller.GetOutputPort("removed").Eval(cc)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(simulator.get_context())
    trays = dropoff_points(scenario.environment)
    ws = Workspace.from_scenario(scenario)
    for o in station_objects(plant):
        p = plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index)).translation()
        if o.model_name in removed:  # in a tray, on its floor
            assert any(np.all(np.abs(p[:2] - t[:2]) < 0.5 * np.asarray(TRAY_INNER[:2])) for t in trays), o.model_name
            assert p[2] < 0.15
        else:  # still in the bin
            assert ws.inside_xy(p) and p[2] < 0.2, o.model_name
    assert controller.target_id in removed


def test_set_initial_conditions_needs_one_station_and_one_controller(heap4):
    builder = DiagramBuilder()
    builder.AddSystem(MakeStation(search_scenario(load_scenario(None, "FloatingGripperBin"), heap4)))
    diagram = builder.Build()
    with pytest.raises(ControllerError, match="1 station"):
        set_initial_conditions(diagram, diagram.CreateDefaultContext(), heap4)


def _run(args):
    out = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


@pytest.mark.parametrize("policy,first,count,config", [
    ("largest", 0, 3, ["--config", "ch7", "--set", "heap.objects=10", "--set", "horizon=20"]),
    ("xray", 5000, 1, []),  # the defaults: Table 8.2's setting
])
def test_the_diagram_example_agrees_with_bench_search_action_by_action(tmp_path, policy, first, count, config):
    bench = tmp_path / "bench.jsonl"
    seeds = range(first, first + count)
    _run([str(Path(sys.executable).parent / "ms-drake"), "bench", "search", "--policy", policy,
          "--heaps", str(count), "--seed-start", str(first), *config, "--out", str(bench)])
    records = {r["seed"]: r for r in map(json.loads, bench.read_text().splitlines())}
    for seed in seeds:
        line = _run([sys.executable, "sims/bin_search_diagram.py", "--seed", str(seed), "--policy", policy, *config])
        got = json.loads(line.strip().splitlines()[-1])
        rec = records[seed]
        assert set(got) >= {"seed", "success", "actions", "action_kinds", "stop_reason"}
        assert (got["success"], got["actions"], got["action_kinds"], got["stop_reason"]) == \
            (rec["success"], rec["actions"], rec["action_kinds"], rec["stop_reason"]), seed
        assert got["grasp_objects"] == rec["grasp_objects"], seed


@pytest.mark.parametrize("args,message", [
    (["bench", "search", "--policy", "largest", "--scenario", "FetchShelf"], "a bin search needs a bin scenario"),
    (["bench", "search", "--policy", "largest", "--scenario", "PandaBin"], "use fidelity full for a robot"),
    (["bench", "search", "--policy", "largest", "--scenario", "Nope"], "no scenario named 'Nope'"),
    (["bench", "search", "--policy", "largest", "--fidelity", "full", "--scenario", "BinHeap15"], "has no robot"),
    (["demo", "--scenario", "PandaTable"], "a bin search needs a bin scenario"),
    (["demo", "shelf", "--scenario", "PandaBin"], "the shelf search needs a shelf scenario"),
    (["demo", "rearrange", "--scenario", "PandaBin"], "the rearrangement runs on a table with the Panda"),
    (["bench", "rearrange", "--method", "ik_line", "--scenario", "FetchShelf"], "runs on a table with the Panda"),
    (["bench", "fidelity", "--scenario", "FetchShelf"], "a bin search needs a bin scenario"),
    (["bench", "shelf-physics", "--policy", "der3", "--scenario", "YuMiBin"], "the shelf search needs a shelf"),
    (["bench", "shelf-segmentation", "--scenario", "YuMiBin"], "the shelf search needs a shelf"),
])
def test_unsuitable_scenarios_get_one_clear_error(tmp_path, args, message):
    out = subprocess.run([str(Path(sys.executable).parent / "ms-drake"), *args, "--out", str(tmp_path / "o.jsonl")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and message in out.stderr and "Traceback" not in out.stderr


def test_the_diagram_example_agrees_with_bench_search_on_a_robot_in_full_fidelity(tmp_path):
    """The Panda in physics: its grasps of non-target objects carry them to a drop-off tray."""
    bench = tmp_path / "panda.jsonl"
    config = ["--config", "ch7", "--set", "heap.objects=6", "--set", "horizon=12"]
    _run([str(Path(sys.executable).parent / "ms-drake"), "bench", "search", "--policy", "largest", "--fidelity", "full",
          "--scenario", "PandaBin", *config, "--heaps", "1", "--seed-start", "0", "--out", str(bench)])
    (rec,) = map(json.loads, bench.read_text().splitlines())
    assert rec["config"]["scenario"] == "PandaBin" and rec["fidelity"] == "full"
    got = json.loads(_run([sys.executable, "sims/bin_search_diagram.py", "--scenario", "PandaBin", "--fidelity", "full",
                           "--seed", "0", "--policy", "largest", *config]).strip().splitlines()[-1])
    assert (got["success"], got["actions"], got["action_kinds"], got["stop_reason"], got["grasp_objects"]) == \
        (rec["success"], rec["actions"], rec["action_kinds"], rec["stop_reason"], rec["grasp_objects"])
    assert rec["actions"] >= 2 and any(o not in ("", "target") for o in rec["grasp_objects"])  # a carried occluder


def test_bench_search_shows_progress_and_ctrl_c_says_how_to_resume(tmp_path):
    import signal
    import time

    out = tmp_path / "runs.jsonl"
    cmd = [str(Path(sys.executable).parent / "ms-drake"), "bench", "search", "--policy", "largest", "--config", "ch7",
           "--set", "heap.objects=6", "--heaps", "40", "--out", str(out)]
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_default_sigint)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 600 and not (out.exists() and out.read_text().count("\n") >= 1):
        time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 130, stderr[-1000:]
    done = out.read_text().count("\n")
    assert f"stopped after {done} of 40 rollouts; run the same command to resume" in stderr
    assert "rollouts:" in stderr and "Traceback" not in stderr  # the progress bar (tqdm writes to stderr)
    cmd[cmd.index("40")] = str(done + 1)  # the same run, one more heap: the notice comes first
    rerun = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0 and rerun.stdout.startswith(f"resuming: {done} of {done + 1} rollouts already in")


def _default_sigint():
    """In the child before exec: Ctrl-C's default action. A process that starts with SIGINT ignored
    keeps it ignored (Python installs its KeyboardInterrupt handler only over the default), and a
    test worker may have inherited or set that."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)
