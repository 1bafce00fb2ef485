"""Hardware twin: the LCM translators alone, then the hardware station driven by the same
controller against an emulated robot on the far side of an in-process memq:// bus (Drake's
Panda and WSG messages, lcmt_robot_state arms, lcmt_drake_signal suction/blade, lcmt_image_array
cameras), with gating before the first status, clipping, and a lost-status fault."""

import numpy as np
import pytest
from drake import lcmt_drake_signal, lcmt_robot_state
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.lcm import PySerializer

from ms_drake.errors import ScenarioError
from ms_drake.scenario import ArmDriver
from ms_drake.robots import ROBOTS
from ms_drake.station.drivers import station_arms, station_grippers
from ms_drake.station.emulator import MakeEmulatedRobot
from ms_drake.station.hardware import GatedLcmPublisher, MakeHardwareStation, RobotStateReceiver, RobotStateSender, SignalReceiver, SignalSender, command_channel, status_channel
from test_drivers import add_joint_move_controller, bare, gripper_commands


class Counter:
    """Counts (and keeps the last payload of) messages on a channel."""

    def __init__(self, lcm, channel):
        self.count, self.last = 0, None
        lcm.Subscribe(channel, self._on)

    def _on(self, data):
        self.count += 1
        self.last = data


# ----------------------------------------------------------------------------- translators alone
def test_robot_state_sender_names_joints_and_stamps_time():
    sender = RobotStateSender(["a", "b"])
    ctx = sender.CreateDefaultContext()
    ctx.SetTime(1.25)
    sender.GetInputPort("position").FixValue(ctx, [0.1, -0.2])
    msg = sender.GetOutputPort("message").Eval(ctx)
    assert msg.utime == 1_250_000 and msg.num_joints == 2 and list(msg.joint_name) == ["a", "b"]
    np.testing.assert_allclose(msg.joint_position, [0.1, -0.2], atol=1e-7)


def _state(names, q, utime):
    m = lcmt_robot_state()
    m.utime, m.num_joints, m.joint_name, m.joint_position = utime, len(names), list(names), list(q)
    return m


def test_robot_state_receiver_latches_and_estimates_velocity():
    rx = RobotStateReceiver(["a", "b"], period=0.01)
    ctx = rx.CreateDefaultContext()
    sim = Simulator(rx, ctx)
    rx.GetInputPort("message").FixValue(ctx, lcmt_robot_state())  # empty: nothing received
    sim.AdvanceTo(0.02)
    assert rx.GetOutputPort("received").Eval(ctx)[0] == 0
    rx.GetInputPort("message").FixValue(ctx, _state("ab", [1.0, 2.0], 1_000_000))
    sim.AdvanceTo(0.04)
    rx.GetInputPort("message").FixValue(ctx, _state("ab", [1.01, 1.98], 1_010_000))
    sim.AdvanceTo(0.06)
    np.testing.assert_allclose(rx.GetOutputPort("position").Eval(ctx), [1.01, 1.98], atol=1e-6)
    np.testing.assert_allclose(rx.GetOutputPort("state").Eval(ctx)[2:], [1.0, -2.0], atol=1e-3)
    assert rx.GetOutputPort("received").Eval(ctx)[0] == 2
    rx.GetInputPort("message").FixValue(ctx, _state("ax", [0.0, 0.0], 1_020_000))
    with pytest.raises((ScenarioError, RuntimeError), match="carries joints"):
        sim.AdvanceTo(0.08)


def test_robot_state_receiver_holds_before_the_first_command():
    rx = RobotStateReceiver(["a"], period=0.01, hold_input=True)
    ctx = rx.CreateDefaultContext()
    rx.GetInputPort("message").FixValue(ctx, lcmt_robot_state())
    rx.GetInputPort("position_hold").FixValue(ctx, [0.7])
    sim = Simulator(rx, ctx)
    sim.AdvanceTo(0.05)
    assert rx.GetOutputPort("position").Eval(ctx)[0] == pytest.approx(0.7)
    rx.GetInputPort("message").FixValue(ctx, _state("a", [0.2], 0))  # a command stamped t = 0 counts
    sim.AdvanceTo(0.07)
    assert rx.GetOutputPort("position").Eval(ctx)[0] == pytest.approx(0.2)


def test_signal_sender_and_receiver_round_trip():
    sender = SignalSender(["suction", "blade"])
    sctx = sender.CreateDefaultContext()
    sender.GetInputPort("value").FixValue(sctx, [1.0, 3.0])
    msg = sender.GetOutputPort("message").Eval(sctx)
    rx = SignalReceiver(["suction", "blade"], default=[0.0, 0.5])
    rctx = rx.CreateDefaultContext()
    rx.GetInputPort("message").FixValue(rctx, lcmt_drake_signal())
    np.testing.assert_allclose(rx.GetOutputPort("value").Eval(rctx), [0.0, 0.5])  # no message yet
    rx.GetInputPort("message").FixValue(rctx, lcmt_drake_signal.decode(msg.encode()))
    np.testing.assert_allclose(rx.GetOutputPort("value").Eval(rctx), [1.0, 3.0])
    wrong = SignalReceiver(["suction"], default=[0.0])
    wctx = wrong.CreateDefaultContext()
    wrong.GetInputPort("message").FixValue(wctx, msg)
    assert wrong.GetOutputPort("value").Eval(wctx)[0] == 0.0  # other coords: ignored


def test_gated_publisher_publishes_only_when_enabled():
    lcm = DrakeLcm("memq://test_gated_publisher")
    counter = Counter(lcm, "CH")
    pub = GatedLcmPublisher("CH", PySerializer(lcmt_robot_state), lcm, period=0.01)
    ctx = pub.CreateDefaultContext()
    pub.GetInputPort("message").FixValue(ctx, AbstractValue.Make(_state("a", [0.5], 7)))
    pub.GetInputPort("enabled").FixValue(ctx, [0.0])
    sim = Simulator(pub, ctx)
    sim.AdvanceTo(0.1)
    lcm.HandleSubscriptions(0)
    assert counter.count == 0
    pub.GetInputPort("enabled").FixValue(ctx, [1.0])
    sim.AdvanceTo(0.2)
    lcm.HandleSubscriptions(0)
    assert counter.count == 10 and lcmt_robot_state.decode(counter.last).joint_position[0] == pytest.approx(0.5)


def test_gated_publisher_in_a_diagram_with_a_translator():
    lcm = DrakeLcm("memq://test_gated_publisher_diagram")
    counter = Counter(lcm, "SIG")
    builder = DiagramBuilder()
    from pydrake.systems.primitives import ConstantVectorSource

    src = builder.AddSystem(ConstantVectorSource([1.0]))
    sender = builder.AddSystem(SignalSender(["suction"]))
    pub = builder.AddSystem(GatedLcmPublisher("SIG", PySerializer(lcmt_drake_signal), lcm, 0.05))
    builder.Connect(src.get_output_port(), sender.GetInputPort("value"))
    builder.Connect(sender.GetOutputPort("message"), pub.GetInputPort("message"))
    sim = Simulator(builder.Build())
    sim.AdvanceTo(0.22)
    lcm.HandleSubscriptions(0)
    assert counter.count == 5 and list(lcmt_drake_signal.decode(counter.last).val) == [1.0]


# ----------------------------------------------------------------------------- hardware station
@pytest.mark.parametrize("name", ["PandaTable", "YuMiBin", "FetchShelf", "FloatingGripperBin"])
def test_hardware_station_has_the_simulated_station_ports(name):
    from ms_drake.station import MakeStation

    scenario = bare(name)
    hw = MakeHardwareStation(scenario, lcm=DrakeLcm(f"memq://ports_{name}"))
    sim = MakeStation(scenario)
    names = lambda s, kind: {getattr(s, f"get_{kind}_port")(i).get_name()  # noqa: E731
                             for i in range(getattr(s, f"num_{kind}_ports")())}
    # simulation-only ports: the plant's state and forces, the scene graph's queries
    assert names(hw, "input") == names(sim, "input") - {"applied_spatial_force"}
    assert names(hw, "output") == names(sim, "output") - {"body_poses", "body_spatial_velocities", "query_object",
                                                          "contact_results", "state"}


def test_nothing_is_commanded_before_the_first_status():
    scenario = bare("PandaTable")
    lcm = DrakeLcm("memq://test_no_status")
    commands = Counter(lcm, "PANDA_COMMAND")
    jaw = Counter(lcm, "PANDA_JAW_COMMAND")
    hw = MakeHardwareStation(scenario, lcm=lcm)
    sim = Simulator(hw)
    ctx = sim.get_mutable_context()
    hw.GetInputPort("panda.position").FixValue(ctx, np.zeros(7))
    sim.AdvanceTo(0.3)
    lcm.HandleSubscriptions(0)
    assert commands.count == 0 and jaw.count == 0
    assert hw.GetOutputPort("panda.fault").Eval(ctx)[0] == 0  # not a fault: never connected


def _twin(scenario, bus, status_until=np.inf, controller=None):
    lcm = DrakeLcm(f"memq://{bus}")
    builder = DiagramBuilder()
    hw = builder.AddSystem(MakeHardwareStation(scenario, lcm=lcm))
    robot = builder.AddSystem(MakeEmulatedRobot(scenario, lcm=lcm, status_until=status_until))
    q_home = {arm: robot.GetOutputPort(f"{arm}.position_measured").Eval(robot.CreateDefaultContext()).copy()
              for arm in station_arms(hw)}
    if controller is not None:
        controller(builder, hw, q_home)
    diagram = builder.Build()
    return Simulator(diagram), hw, robot, q_home, lcm


@pytest.mark.parametrize("name, grippers", [("PandaTable", {"panda_jaw": "parallel_jaw"}),
                                            ("FetchShelf", {"fetch_bluction": "bluction"})])
def test_the_same_controller_drives_the_hardware_twin(name, grippers):
    scenario = bare(name)
    delta = 0.06
    sim, hw, robot, q_home, _ = _twin(scenario, f"twin_{name}", controller=lambda b, s, q: add_joint_move_controller(
        b, s, q, delta, gripper_commands(s)))
    sim.AdvanceTo(1.4)
    hc, rc = hw.GetMyContextFromRoot(sim.get_context()), robot.GetMyContextFromRoot(sim.get_context())
    for arm, q0 in q_home.items():
        q_robot = robot.GetOutputPort(f"{arm}.position_measured").Eval(rc)
        np.testing.assert_allclose(q_robot, q0 + delta, atol=5e-3)  # the far side moved
        np.testing.assert_allclose(hw.GetOutputPort(f"{arm}.position_measured").Eval(hc), q_robot, atol=2e-3)
        assert hw.GetOutputPort(f"{arm}.fault").Eval(hc)[0] == 0
    assert station_grippers(hw) == grippers
    for port, kind in grippers.items():
        if kind == "parallel_jaw":  # closed over WSG messages; status back within a mm
            width = robot.GetOutputPort(f"{port}.state_measured").Eval(rc)[0]
            assert width < 0.003
            assert hw.GetOutputPort(f"{port}.state_measured").Eval(hc)[0] == pytest.approx(width, abs=1e-3)
        else:  # bluction: blade at pi/2, vacuum on with nothing held
            blade = robot.GetOutputPort(f"{port}.state_measured").Eval(rc)[0]
            assert blade == pytest.approx(np.pi / 2, abs=0.02)
            assert hw.GetOutputPort(f"{port}.state_measured").Eval(hc)[0] == pytest.approx(blade, abs=0.01)
            np.testing.assert_array_equal(hw.GetOutputPort(f"{port}.suction_state").Eval(hc)[:2], [0, -1])


def test_lost_status_raises_a_fault_and_holds_the_arm():
    scenario = bare("YuMiBin")
    scenario.robot.drivers = {"yumi_right": ArmDriver(status_timeout=0.05)}
    speed = 0.4  # rad/s on every joint of the right arm, for 2 s: the controller keeps commanding motion

    def controller(builder, station, q_home):
        from pydrake.systems.primitives import TrajectorySource
        from pydrake.trajectories import PiecewisePolynomial

        q0 = q_home["yumi_right"]
        src = builder.AddSystem(TrajectorySource(PiecewisePolynomial.FirstOrderHold(
            [0.0, 2.0], np.stack([q0, q0 + 2.0 * speed], 1))))
        builder.Connect(src.get_output_port(), station.GetInputPort("yumi_right.position"))

    sim, hw, robot, q_home, lcm = _twin(scenario, "twin_lost", status_until=0.3, controller=controller)
    commands = Counter(lcm, command_channel("yumi_right"))
    hc, rc = hw.GetMyContextFromRoot(sim.get_context()), robot.GetMyContextFromRoot(sim.get_context())
    sim.AdvanceTo(0.3)
    assert hw.GetOutputPort("yumi_right.fault").Eval(hc)[0] == 0
    sim.AdvanceTo(0.4)  # > status_until + timeout
    assert hw.GetOutputPort("yumi_right.fault").Eval(hc)[0] == 1
    assert hw.GetOutputPort("yumi_right_jaw.fault").Eval(hc)[0] == 0  # the jaw's own timeout is 0.25 s
    held = robot.GetOutputPort("yumi_right.position_measured").Eval(rc).copy()
    sim.AdvanceTo(0.8)
    assert hw.GetOutputPort("yumi_right_jaw.fault").Eval(hc)[0] == 1  # every device lost its status
    assert hw.GetOutputPort("yumi_left_suction.fault").Eval(hc)[0] == 1
    moved = robot.GetOutputPort("yumi_right.position_measured").Eval(rc) - held
    assert np.abs(moved).max() < 0.02  # held while the controller asked for 0.16 rad more
    last = lcmt_robot_state.decode(commands.last)
    assert commands.count > 0 and list(last.joint_name) == list(ROBOTS["yumi"].arms["yumi_right"].joints)
    np.testing.assert_allclose(last.joint_position, held, atol=0.03)  # the hold is what is sent


def test_commands_beyond_limits_are_clipped_before_they_are_sent():
    scenario = bare("PandaTable")
    bus = "twin_clip"

    def controller(builder, station, q_home):
        from pydrake.systems.primitives import ConstantVectorSource

        target = q_home["panda"] + np.array([0, 0, 0, 5.0, 0, 0, 0])  # joint 4 far above its limit
        src = builder.AddSystem(ConstantVectorSource(target))
        builder.Connect(src.get_output_port(), station.GetInputPort("panda.position"))

    sim, hw, robot, q_home, lcm = _twin(scenario, bus, controller=controller)
    status = Counter(lcm, status_channel("panda"))
    sim.AdvanceTo(1.5)
    hc, rc = hw.GetMyContextFromRoot(sim.get_context()), robot.GetMyContextFromRoot(sim.get_context())
    assert hw.GetOutputPort("panda.command_clipped").Eval(hc)[0] == 1
    q = robot.GetOutputPort("panda.position_measured").Eval(rc)
    upper = -0.0698  # panda_joint4's upper limit
    assert q[3] == pytest.approx(upper, abs=0.01) and q[3] <= upper + 1e-3
    assert status.count > 200  # the robot kept reporting (200 Hz)


def test_camera_images_arrive_through_lcmt_image_array():
    from pydrake.systems.lcm import LcmInterfaceSystem
    from pydrake.systems.primitives import ConstantValueSource
    from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

    from ms_drake.scenario import load_scenario
    from ms_drake.station.emulator import add_image_publisher

    scenario = load_scenario(None, "YuMiBin")
    cam = scenario.cameras["overhead"]
    lcm = DrakeLcm("memq://test_camera")
    builder = DiagramBuilder()
    hw = builder.AddSystem(MakeHardwareStation(scenario, lcm=lcm))
    rgb = ImageRgba8U(cam.width, cam.height)
    rgb.mutable_data[:, :, 0] = np.arange(cam.width, dtype=np.uint8)[None, :]  # a horizontal ramp
    rgb.mutable_data[:, :, 3] = 255
    depth = ImageDepth32F(cam.width, cam.height)
    depth.mutable_data[:, :, 0] = np.linspace(0.5, 1.5, cam.height, dtype=np.float32)[:, None]
    rgb_src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(rgb)))
    depth_src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(depth)))
    # the emulated robot's camera path, fed by fixed images instead of a renderer
    add_image_publisher(builder, lcm, cam, rgb_src.get_output_port(), depth_src.get_output_port())
    builder.AddSystem(LcmInterfaceSystem(lcm))
    sim = Simulator(builder.Build())
    sim.AdvanceTo(0.15)
    hc = hw.GetMyContextFromRoot(sim.get_context())
    got = hw.GetOutputPort("overhead.rgb_image").Eval(hc)
    assert (got.width(), got.height()) == (cam.width, cam.height)
    np.testing.assert_array_equal(got.data[5, :, 0], np.arange(cam.width, dtype=np.uint8))
    got_depth = hw.GetOutputPort("overhead.depth_image").Eval(hc)
    np.testing.assert_allclose(got_depth.data[:, 7, 0], depth.data[:, 7, 0])


def test_the_scenarios_hardware_key_selects_the_hardware_station():
    from ms_drake.scenario import load_scenario
    from ms_drake.station import MakeStation

    scenario = load_scenario(None, "PandaTable")
    scenario.hardware = True
    scenario.lcm_url = "memq://scenario_hardware_key"
    station = MakeStation(scenario)
    assert station.get_name() == "hardware_station" and not station.HasOutputPort("body_poses")
    assert station.HasInputPort("panda.position") and station.HasOutputPort("front.depth_image")
    assert MakeStation(scenario, hardware=False).HasOutputPort("body_poses")  # the argument overrides it
