"""Drivers: CommandGuard alone (clip, rate limit, defaults, hold, status watchdog) and in a
station; driver entries in scenario files; one controller moving every robot of every scenario."""

import dataclasses
import textwrap

import numpy as np
import pytest
from pydrake.lcm import DrakeLcm
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from ms_drake.errors import ScenarioError
from ms_drake.planning import TimedTrajectory, TrajectoryStreamer, plan_joint_motion
from ms_drake.scenario import ArmDriver, JawDriver, SuctionDriver, load_scenario
from ms_drake.station import MakeStation, get_plant
from ms_drake.station.drivers import CommandField, CommandGuard, station_arms, station_grippers
from ms_drake.robots import arm_joint_limits, station_robot_spec
from ms_drake.scenario import resolve_robot_config

SCENARIOS = ["YuMiBin", "PandaTable", "FetchShelf", "FloatingGripperBin"]
GRIPPERS = {  # {gripper port prefix: kind} of each scenario's station
    "YuMiBin": {"yumi_right_jaw": "parallel_jaw", "yumi_left_suction": "suction"},
    "PandaTable": {"panda_jaw": "parallel_jaw"},
    "FetchShelf": {"fetch_bluction": "bluction"},
    "FloatingGripperBin": {"floating_jaw": "parallel_jaw"},
}


def bare(name, **robot):
    """Scenario `name` without objects and cameras (robot fields overridden by `robot`)."""
    s = load_scenario(None, name)
    s = dataclasses.replace(s, cameras={}, objects=dataclasses.replace(s.objects, count=0, names=[]))
    if robot:
        s = dataclasses.replace(s, robot=dataclasses.replace(s.robot, **robot))
    return s


# ----------------------------------------------------------------------------- CommandGuard alone
def _guard_sim(guard, **inputs):
    ctx = guard.CreateDefaultContext()
    for name, value in inputs.items():
        guard.GetInputPort(name).FixValue(ctx, value)
    sim = Simulator(guard, ctx)
    return sim, ctx


def _out(guard, ctx, name):
    return guard.GetOutputPort(name).Eval(ctx)


def test_guard_clips_to_limits_and_rate_and_reports_it():
    guard = CommandGuard([CommandField("position", (-1.0, -1.0), (1.0, 1.0), max_rate=(2.0, 2.0))], period=0.01)
    sim, ctx = _guard_sim(guard, position=[5.0, 0.5], position_measured=[0.0, 0.5])
    sim.Initialize()
    np.testing.assert_allclose(_out(guard, ctx, "position"), [0.02, 0.5])  # one rate step from measured
    assert _out(guard, ctx, "clipped")[0] == 1 and _out(guard, ctx, "enabled")[0] == 1
    sim.AdvanceTo(0.1)
    np.testing.assert_allclose(_out(guard, ctx, "position"), [0.22, 0.5], atol=1e-12)
    np.testing.assert_allclose(_out(guard, ctx, "position_velocity"), [2.0, 0.0], atol=1e-9)
    sim.AdvanceTo(1.0)
    np.testing.assert_allclose(_out(guard, ctx, "position"), [1.0, 0.5])  # never beyond the upper limit
    assert _out(guard, ctx, "clipped")[0] == 1  # the command is still out of range
    guard.GetInputPort("position").FixValue(ctx, [0.9, -0.5])
    sim.AdvanceTo(1.6)
    np.testing.assert_allclose(_out(guard, ctx, "position"), [0.9, -0.5])
    assert _out(guard, ctx, "clipped")[0] == 0 and _out(guard, ctx, "fault")[0] == 0


def test_guard_defaults_and_holds_when_unconnected():
    guard = CommandGuard([CommandField("position", (-2.0,), (2.0,)),
                          CommandField("force_limit", (0.0,), (40.0,), default=(25.0,), hold="command")], period=0.01)
    ctx = guard.CreateDefaultContext()
    assert _out(guard, ctx, "force_limit")[0] == 25.0  # before initialization: the default
    assert not guard.HasInputPort("force_limit_measured")
    guard.GetInputPort("position_measured").FixValue(ctx, [0.3])
    sim = Simulator(guard, ctx)
    sim.Initialize()
    guard.GetInputPort("position_measured").FixValue(ctx, [1.5])  # the measurement moves on ...
    sim.AdvanceTo(0.2)
    assert _out(guard, ctx, "position")[0] == pytest.approx(0.3)  # ... the unconnected command holds
    assert _out(guard, ctx, "force_limit")[0] == 25.0
    guard.GetInputPort("force_limit").FixValue(ctx, [90.0])
    sim.AdvanceTo(0.3)
    assert _out(guard, ctx, "force_limit")[0] == 40.0 and _out(guard, ctx, "clipped")[0] == 1


def test_guard_waits_for_status_and_holds_measured_when_it_is_lost():
    lcm = DrakeLcm("memq://test_guard_status")
    guard = CommandGuard([CommandField("position", (-3.0,), (3.0,), max_rate=(10.0,))], period=0.01,
                         status=(lcm, "ARM_STATUS"), status_timeout=0.05)
    sim, ctx = _guard_sim(guard, position=[1.0], position_measured=[0.2])
    sim.AdvanceTo(0.1)
    assert _out(guard, ctx, "enabled")[0] == 0  # no status yet: nothing may be sent

    def status(until):
        while sim.get_context().get_time() < until - 1e-9:
            lcm.Publish("ARM_STATUS", b"status")
            lcm.HandleSubscriptions(0)
            sim.AdvanceTo(sim.get_context().get_time() + 0.01)

    status(0.2)
    assert _out(guard, ctx, "enabled")[0] == 1 and _out(guard, ctx, "fault")[0] == 0
    assert _out(guard, ctx, "position")[0] == pytest.approx(1.0)  # from 0.2 at 0.1 rad per step
    guard.GetInputPort("position_measured").FixValue(ctx, [0.8])  # the robot lags behind
    sim.AdvanceTo(0.3)  # status lost for 0.1 s > timeout
    assert _out(guard, ctx, "fault")[0] == 1
    assert _out(guard, ctx, "position")[0] == pytest.approx(0.8)  # holds the measured position
    guard.GetInputPort("position_measured").FixValue(ctx, [0.5])
    sim.AdvanceTo(0.35)
    assert _out(guard, ctx, "position")[0] == pytest.approx(0.8)  # latched at the fault's onset
    status(0.36)  # status is back: fault clears, command resumes at the rate limit
    sim.AdvanceTo(0.38)
    assert _out(guard, ctx, "fault")[0] == 0
    assert 0.8 < _out(guard, ctx, "position")[0] <= 1.0


def test_guard_in_a_diagram_rate_limits_a_constant_command():
    builder = DiagramBuilder()
    guard = builder.AddSystem(CommandGuard([CommandField("position", (0.0,), (1.0,), max_rate=(0.5,))], 0.01))
    cmd = builder.AddSystem(ConstantVectorSource([1.0]))
    meas = builder.AddSystem(ConstantVectorSource([0.0]))
    builder.Connect(cmd.get_output_port(), guard.GetInputPort("position"))
    builder.Connect(meas.get_output_port(), guard.GetInputPort("position_measured"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    sim.AdvanceTo(1.0)
    pos = guard.GetOutputPort("position").Eval(guard.GetMyContextFromRoot(sim.get_context()))
    assert pos[0] == pytest.approx(0.505, abs=1e-9)  # 101 updates (t = 0 .. 1) of 5 mm


# ----------------------------------------------------------------------------- scenario entries
def test_driver_entries_load_from_yaml_and_configure_the_station(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(textwrap.dedent("""
        Panda:
          plant_config: { time_step: 0.002, discrete_contact_approximation: lagged }
          environment: { type: table }
          robot:
            name: panda
            grippers: [parallel_jaw]
            base_position: [-0.6, 0, 0]
            drivers:
              panda: !ArmDriver { kp: [800, 800, 800, 800, 100, 100, 100], damping_ratio: 0.8 }
              panda_jaw: !JawDriver { default_force_limit: 20.0 }
        Bad:
          robot: { name: panda, drivers: { panda: !Nope {} } }
    """))
    s = load_scenario(f, "Panda")
    assert s.robot.drivers["panda"].kp[0] == 800 and s.robot.drivers["panda_jaw"].default_force_limit == 20.0
    station = MakeStation(s)
    ctx = station.CreateDefaultContext()
    # the jaw squeezes at the force limit the YAML entry set (20 N)
    assert np.allclose(station.GetOutputPort("panda_jaw.force_measured").Eval(ctx), 20.0)
    guard = station.GetSubsystemByName("panda_jaw_guard")
    assert guard.GetOutputPort("force_limit").Eval(guard.GetMyContextFromRoot(ctx))[0] == 20.0
    plant = get_plant(station)
    gains = plant.get_joint_actuator(plant.GetJointActuatorIndices(plant.GetModelInstanceByName("panda"))[0])
    assert gains.get_controller_gains().p == 800
    with pytest.raises(ScenarioError, match="Nope"):
        load_scenario(f, "Bad")


@pytest.mark.parametrize("robot,match", [
    (dict(name="yumi", grippers=["parallel_jaw", "vacuum"]), r"robot.grippers\[1\]: unknown gripper 'vacuum'; "
                                                             r"valid grippers: bluction, parallel_jaw, suction_cup"),
    (dict(name="panda", grippers=["parallel_jaw", "parallel_jaw"]), "has 1 arm"),
    (dict(name="panda", drivers={"panda_hand": ArmDriver()}), "valid driver names: panda, panda_jaw"),
    (dict(name="panda", drivers={"panda_jaw": SuctionDriver()}), "use !JawDriver"),
    (dict(name="fetch", drivers={"fetch": ArmDriver(kp=[1.0, 2.0])}), "give 8 positive stiffnesses"),
    (dict(name="ur5"), "valid robots: fetch, floating, panda, yumi"),
])
def test_bad_robot_configs_name_the_key_and_the_valid_values(robot, match):
    from ms_drake.scenario import RobotConfig

    with pytest.raises(ScenarioError, match=match):
        resolve_robot_config(RobotConfig(**robot))


def test_default_gripper_ports_and_drivers():
    chosen, drivers = resolve_robot_config(load_scenario(None, "YuMiBin").robot)
    assert [p for _, _, p in chosen] == ["yumi_right_jaw", "yumi_left_suction"]
    assert isinstance(drivers["yumi_right"], ArmDriver) and isinstance(drivers["yumi_right_jaw"], JawDriver)
    chosen, _ = resolve_robot_config(load_scenario(None, "FetchShelf").robot)
    assert chosen == [("fetch", "bluction", "fetch_bluction")]


def test_station_needs_a_discrete_sap_family_plant():
    s = bare("PandaTable")
    s.plant_config.time_step = 0.0
    with pytest.raises(ScenarioError, match="time_step"):
        MakeStation(s)
    s = bare("PandaTable")
    s.plant_config.discrete_contact_approximation = "tamsi"
    with pytest.raises(ScenarioError, match="tamsi"):
        MakeStation(s)


# ----------------------------------------------------------------------------- one controller, every robot
def add_joint_move_controller(builder, station, q_now: dict, delta: float, gripper_commands: dict):
    """The controller under test: for every arm of `station` (found by port names) a ruckig move
    from q_now[arm] by `delta` on every joint (kept inside the joint limits), streamed into
    `<arm>.position`; constant gripper commands {port: value}. Nothing robot-specific."""
    streamers = {}
    for arm in station_arms(station):
        q0 = np.asarray(q_now[arm])
        traj = plan_joint_motion([q0, q0 + delta], arm_joint_limits(arm))
        streamers[arm] = builder.AddSystem(TrajectoryStreamer(len(q0), trajectory=TimedTrajectory(traj, 0.05)))
        builder.Connect(streamers[arm].GetOutputPort("position"), station.GetInputPort(f"{arm}.position"))
    for port, value in gripper_commands.items():
        src = builder.AddSystem(ConstantVectorSource(np.atleast_1d(value)))
        builder.Connect(src.get_output_port(), station.GetInputPort(port))
    return streamers


def gripper_commands(station):
    cmds = {}
    for port, kind in station_grippers(station).items():
        if kind == "parallel_jaw":
            cmds[f"{port}.position"], cmds[f"{port}.force_limit"] = 0.0, 20.0  # close
        else:
            cmds[f"{port}.suction"] = 1.0
            if kind == "bluction":
                cmds[f"{port}.position"] = np.pi / 2  # blade half up
    return cmds


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_same_controller_moves_every_robot(name):
    scenario = bare(name)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario))
    ctx0 = station.CreateDefaultContext()
    arms = station_arms(station)
    assert arms == list(station_robot_spec(scenario.robot.name).arms)
    q_now = {arm: station.GetOutputPort(f"{arm}.position_measured").Eval(ctx0).copy() for arm in arms}
    delta = 0.06  # (0.05 hits ruckig 0.19.4's boundary-case bug at some limits: 'error in step 1')
    add_joint_move_controller(builder, station, q_now, delta, gripper_commands(station))
    diagram = builder.Build()
    sim = Simulator(diagram)
    sim.AdvanceTo(1.3)
    sc = station.GetMyContextFromRoot(sim.get_context())
    for arm in arms:
        q = station.GetOutputPort(f"{arm}.position_measured").Eval(sc)
        np.testing.assert_allclose(q, q_now[arm] + delta, atol=5e-3, err_msg=f"{name}: {arm} did not track")
        x = station.GetOutputPort(f"{arm}.state_estimated").Eval(sc)
        np.testing.assert_allclose(x[:len(q)], q)
        np.testing.assert_allclose(x[len(q):], 0, atol=0.02)
        assert station.GetOutputPort(f"{arm}.fault").Eval(sc)[0] == 0
    grippers = station_grippers(station)
    assert grippers == GRIPPERS[name]
    for port, kind in grippers.items():
        if kind == "parallel_jaw":
            assert station.GetOutputPort(f"{port}.state_measured").Eval(sc)[0] < 0.003  # closed on nothing
        elif kind == "suction":
            assert station.GetOutputPort(f"{port}.suction_state").Eval(sc)[0] == 0  # vacuum on, nothing held
        else:  # bluction: vacuum on with nothing held, blade turned to pi/2
            assert station.GetOutputPort(f"{port}.suction_state").Eval(sc)[0] == 0
            assert station.GetOutputPort(f"{port}.state_measured").Eval(sc)[0] == pytest.approx(np.pi / 2, abs=0.02)


def test_arm_holds_still_and_commands_beyond_limits_are_clipped():
    scenario = bare("PandaTable")
    station = MakeStation(scenario)
    sim = Simulator(station)
    ctx = sim.get_mutable_context()
    sim.Initialize()
    q0 = station.GetOutputPort("panda.position_measured").Eval(ctx).copy()
    sim.AdvanceTo(0.5)  # no command connected: gravity compensation + stiffness hold the home pose
    np.testing.assert_allclose(station.GetOutputPort("panda.position_measured").Eval(ctx), q0, atol=1e-4)
    plant = get_plant(station)
    upper = plant.GetPositionUpperLimits()[:7]
    station.GetInputPort("panda.position").FixValue(ctx, q0 + np.array([0, 0, 0, 5.0, 0, 0, 0]))  # joint 4 up to -0.07
    sim.AdvanceTo(2.0)
    assert station.GetOutputPort("panda.command_clipped").Eval(ctx)[0] == 1
    q = station.GetOutputPort("panda.position_measured").Eval(ctx)
    assert q[3] == pytest.approx(upper[3], abs=0.01) and q[3] <= upper[3] + 1e-3
