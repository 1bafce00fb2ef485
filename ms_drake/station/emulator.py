"""The far side of the hardware twin, for tests and dry runs: `MakeEmulatedRobot(scenario,
lcm=...)` is the simulated station of `scenario` that takes its commands from LCM and publishes
its status and camera images there, on the channels and messages of ms_drake/station/hardware.py.
"""


from __future__ import annotations

import dataclasses
import math

import numpy as np
from drake import (
    lcmt_drake_signal,
    lcmt_image_array,
    lcmt_panda_command,
    lcmt_panda_status,
    lcmt_robot_state,
    lcmt_schunk_wsg_command,
    lcmt_schunk_wsg_status,
)
from pydrake.manipulation import (
    PandaCommandReceiver,
    PandaControlMode,
    PandaStatusSender,
    SchunkWsgCommandReceiver,
    SchunkWsgStatusSender,
)
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.lcm import (
    LcmInterfaceSystem,
    LcmSubscriberSystem,
    PySerializer,
)
from pydrake.systems.primitives import (
    ConstantVectorSource,
    Demultiplexer,
    Multiplexer,
    TrajectorySource,
)
from pydrake.systems.sensors import (
    ImageToLcmImageArrayT,
    PixelType,
)
from pydrake.trajectories import PiecewisePolynomial

from ms_drake.station.drivers import (
    CONTROL_PERIOD,
    jaw_limits,
)
from ms_drake.station.hardware import (
    GatedLcmPublisher,
    RobotStateReceiver,
    RobotStateSender,
    SignalReceiver,
    SignalSender,
    cpp_serializer,
    lcm_for,
    suction_coords,
    camera_channel,
    command_channel,
    robot_layout,
    status_channel,
)
from ms_drake.station.station import MakeStation


def MakeEmulatedRobot(scenario, lcm=None, meshcat=None, status_period: float = CONTROL_PERIOD,
                      status_until: float = math.inf, name: str = "emulated_robot"):
    """The far side of the hardware twin: the simulated station of `scenario` that takes its
    commands from LCM and publishes its status (and camera images) on LCM.

    status_until: the robot stops publishing status at that time (to test lost-status faults).
    Exports every output port of the simulated station under the same name (so tests can read
    body_poses, state, ...). Before any command arrives each device holds its position.
    """

    lcm = lcm_for(scenario, lcm)
    sim_scenario = dataclasses.replace(scenario, hardware=False)
    plant, handle = robot_layout(scenario)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(sim_scenario, meshcat=meshcat, name="simulated_station"))
    builder.AddSystem(LcmInterfaceSystem(lcm)).set_name("lcm")
    enabled = None
    if math.isfinite(status_until):  # 1 until status_until, then 0

        t_end = max(status_until, 1e-9)
        until = builder.AddSystem(TrajectorySource(PiecewisePolynomial.ZeroOrderHold(
            [0.0, t_end, t_end + 1e6], np.array([[1.0, 0.0, 0.0]]))))
        until.set_name("status_until")
        enabled = until.get_output_port()
    for arm in handle.arms:
        _emulated_arm(builder, lcm, station, handle.robot, arm, status_period, enabled)
    for g in handle.grippers:
        if g.kind == "parallel_jaw":
            _emulated_jaw(builder, lcm, station, plant, g, status_period, enabled)
        else:
            _emulated_suction(builder, lcm, station, plant, g, status_period, enabled)
    for cam_name, cam in scenario.cameras.items():
        _emulated_camera(builder, lcm, station, cam_name, cam)
    for i in range(station.num_output_ports()):
        builder.ExportOutput(station.get_output_port(i), station.get_output_port(i).get_name())
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


def _publisher(builder, channel, serializer, lcm, period, enabled, source_port, name):
    pub = builder.AddSystem(GatedLcmPublisher(channel, serializer, lcm, period))
    pub.set_name(name)
    builder.Connect(source_port, pub.GetInputPort("message"))
    if enabled is not None:
        builder.Connect(enabled, pub.GetInputPort("enabled"))
    return pub


def _emulated_arm(builder, lcm, station, robot, arm, period, enabled):
    n = len(arm.joints)
    cmd, st = command_channel(arm.name), status_channel(arm.name)
    measured = station.GetOutputPort(f"{arm.name}.position_measured")
    if robot == "panda":
        sub = builder.AddSystem(LcmSubscriberSystem.Make(cmd, lcmt_panda_command, lcm, use_cpp_serializer=True))
        rx = builder.AddSystem(PandaCommandReceiver(n, PandaControlMode.kPosition))
        builder.Connect(sub.get_output_port(), rx.get_message_input_port())
        builder.Connect(measured, rx.get_position_measured_input_port())
        builder.Connect(rx.get_commanded_position_output_port(), station.GetInputPort(f"{arm.name}.position"))
        status = builder.AddSystem(PandaStatusSender(n))
        split = builder.AddSystem(Demultiplexer([n, n]))
        builder.Connect(station.GetOutputPort(f"{arm.name}.state_estimated"), split.get_input_port())
        builder.Connect(measured, status.get_position_measured_input_port())
        builder.Connect(split.get_output_port(1), status.get_velocity_measured_input_port())
        builder.Connect(rx.get_commanded_position_output_port(), status.get_position_commanded_input_port())
        zero = builder.AddSystem(ConstantVectorSource(np.zeros(n)))
        builder.Connect(zero.get_output_port(), status.get_torque_commanded_input_port())
        _publisher(builder, st, cpp_serializer(lcmt_panda_status), lcm, period, enabled, status.get_output_port(0),
                   f"{arm.name}_status_publisher")
    else:
        sub = builder.AddSystem(LcmSubscriberSystem.Make(cmd, lcmt_robot_state, lcm))
        rx = builder.AddSystem(RobotStateReceiver(arm.joints, period, hold_input=True, channel=cmd))
        builder.Connect(sub.get_output_port(), rx.GetInputPort("message"))
        builder.Connect(measured, rx.GetInputPort("position_hold"))
        builder.Connect(rx.GetOutputPort("position"), station.GetInputPort(f"{arm.name}.position"))
        status = builder.AddSystem(RobotStateSender(arm.joints))
        builder.Connect(measured, status.GetInputPort("position"))
        _publisher(builder, st, PySerializer(lcmt_robot_state), lcm, period, enabled, status.GetOutputPort("message"),
                   f"{arm.name}_status_publisher")
    sub.set_name(f"{arm.name}_command_subscriber")
    rx.set_name(f"{arm.name}_command_receiver")
    status.set_name(f"{arm.name}_status_sender")


def _emulated_jaw(builder, lcm, station, plant, g, period, enabled):

    max_opening, _ = jaw_limits(plant, g.instance)
    sub = builder.AddSystem(LcmSubscriberSystem.Make(command_channel(g.port), lcmt_schunk_wsg_command, lcm,
                                                     use_cpp_serializer=True))
    sub.set_name(f"{g.port}_command_subscriber")
    rx = builder.AddSystem(SchunkWsgCommandReceiver(initial_position=max_opening,
                                                    initial_force=g.driver.default_force_limit))
    rx.set_name(f"{g.port}_command_receiver")
    builder.Connect(sub.get_output_port(), rx.GetInputPort("command_message"))
    builder.Connect(rx.GetOutputPort("position"), station.GetInputPort(f"{g.port}.position"))
    builder.Connect(rx.GetOutputPort("force_limit"), station.GetInputPort(f"{g.port}.force_limit"))
    status = builder.AddSystem(SchunkWsgStatusSender())
    status.set_name(f"{g.port}_status_sender")
    builder.Connect(station.GetOutputPort(f"{g.port}.state_measured"), status.get_input_port(0))  # state
    builder.Connect(station.GetOutputPort(f"{g.port}.force_measured"), status.get_input_port(1))  # force
    _publisher(builder, status_channel(g.port), cpp_serializer(lcmt_schunk_wsg_status), lcm, period, enabled,
               status.get_output_port(0), f"{g.port}_status_publisher")


def _emulated_suction(builder, lcm, station, plant, g, period, enabled):
    command_coords, status_coords = suction_coords(g.kind)
    sub = builder.AddSystem(LcmSubscriberSystem.Make(command_channel(g.port), lcmt_drake_signal, lcm))
    sub.set_name(f"{g.port}_command_subscriber")
    blade0 = 0.0
    if g.kind == "bluction":
        blade0 = plant.GetJointByName("blade_joint", g.instance).get_default_angle()
    rx = builder.AddSystem(SignalReceiver(command_coords, [0.0] + ([blade0] if g.kind == "bluction" else [])))
    rx.set_name(f"{g.port}_command_receiver")
    builder.Connect(sub.get_output_port(), rx.GetInputPort("message"))
    split = builder.AddSystem(Demultiplexer([1] * len(command_coords)))
    builder.Connect(rx.GetOutputPort("value"), split.get_input_port())
    builder.Connect(split.get_output_port(0), station.GetInputPort(f"{g.port}.suction"))
    status = builder.AddSystem(SignalSender(status_coords))
    status.set_name(f"{g.port}_status_sender")
    if g.kind == "bluction":
        builder.Connect(split.get_output_port(1), station.GetInputPort(f"{g.port}.position"))
        mux = builder.AddSystem(Multiplexer([3, 2]))
        builder.Connect(station.GetOutputPort(f"{g.port}.suction_state"), mux.get_input_port(0))
        builder.Connect(station.GetOutputPort(f"{g.port}.state_measured"), mux.get_input_port(1))
        builder.Connect(mux.get_output_port(), status.GetInputPort("value"))
    else:
        builder.Connect(station.GetOutputPort(f"{g.port}.suction_state"), status.GetInputPort("value"))
    _publisher(builder, status_channel(g.port), PySerializer(lcmt_drake_signal), lcm, period, enabled,
               status.GetOutputPort("message"), f"{g.port}_status_publisher")


def _emulated_camera(builder, lcm, station, cam_name, cam):
    add_image_publisher(builder, lcm, cam,
                        station.GetOutputPort(f"{cam_name}.rgb_image") if cam.rgb else None,
                        station.GetOutputPort(f"{cam_name}.depth_image") if cam.depth else None)


def add_image_publisher(builder, lcm, cam, rgb_port=None, depth_port=None, enabled=None):
    """Publish the images on `rgb_port` (ImageRgba8U) / `depth_port` (ImageDepth32F) as one
    lcmt_image_array on DRAKE_RGBD_CAMERA_IMAGES_<cam.name> at cam.fps (the far side of the
    hardware station's cameras). Returns the publisher."""
    to_lcm = builder.AddSystem(ImageToLcmImageArrayT(do_compress=True))  # zlib: see the module docstring
    to_lcm.set_name(f"{cam.name}_to_lcm")
    if rgb_port is not None:
        builder.Connect(rgb_port, to_lcm.DeclareImageInputPort[PixelType.kRgba8U]("color"))
    if depth_port is not None:
        builder.Connect(depth_port, to_lcm.DeclareImageInputPort[PixelType.kDepth32F]("depth"))
    return _publisher(builder, camera_channel(cam.name), cpp_serializer(lcmt_image_array), lcm, 1.0 / cam.fps,
                      enabled, to_lcm.image_array_t_msg_output_port(), f"{cam.name}_image_publisher")
