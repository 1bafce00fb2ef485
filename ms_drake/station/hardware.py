"""The hardware twin: the station's ports backed by LCM instead of a simulated plant.

`MakeHardwareStation(scenario, lcm=...)` builds a Diagram with exactly the port names of the
simulated station (drivers.py) whose inputs become LCM commands and whose outputs come from
LCM status messages. `MakeEmulatedRobot(scenario, lcm=...)` (ms_drake/station/emulator.py) is the far side for tests
and dry runs: a simulated station that receives those commands and publishes that status.
`lcm` is any DrakeLcmInterface (tests: DrakeLcm("memq://...")); None -> DrakeLcm(scenario.lcm_url).

Channels and messages (documented here; <P> is the port prefix in upper case):
  Panda         PANDA_COMMAND lcmt_panda_command (position mode) / PANDA_STATUS lcmt_panda_status,
                through Drake's PandaCommandSender / PandaStatusReceiver (far side:
                PandaCommandReceiver / PandaStatusSender).
  YuMi, Fetch   <ARM>_COMMAND / <ARM>_STATUS (YUMI_RIGHT_, YUMI_LEFT_, FETCH_), both
                lcmt_robot_state: joint_name in ArmSpec order, joint_position (command: desired,
                status: measured). Velocities are estimated from successive status messages.
  parallel jaw  <P>_COMMAND lcmt_schunk_wsg_command / <P>_STATUS lcmt_schunk_wsg_status (e.g.
                YUMI_RIGHT_JAW_COMMAND), Drake's SchunkWsg{Command,Status}{Sender,Receiver}.
  suction       <P>_COMMAND / <P>_STATUS lcmt_drake_signal; command coords ["suction"] (+ "blade"
                for the bluction, the blade angle [rad]); status coords ["holding", "body_index",
                "gap"] (+ "blade", "blade_rate"). body_index is -1 on a real robot.
  cameras       DRAKE_RGBD_CAMERA_IMAGES_<camera name> lcmt_image_array (Drake's
                LcmImageArrayToImages; far side ImageToLcmImageArrayT), as Drake's ApplyCameraConfig;
                colour RGBA 8 bit, depth float32 metres, zlib-compressed: Drake 1.51's
                LcmImageArrayToImages copies an uncompressed depth image short (a byte per pixel),
                so a camera driver on this bus must compress its depth images.

Safety (CommandGuard in drivers.py, one per arm and gripper): commands are clipped to the joint
position and velocity limits (`<P>.command_clipped` reports it); nothing is published on a
command channel before the first status message of that device arrives; when the newest status
is older than the driver's `status_timeout` the command holds (arms: the last measured
position; grippers: the last command, so a held object is not dropped) and `<P>.fault` is 1.
Status is watched by message arrival, not by its timestamp, so robot and station clocks need
not agree. Sim-only ports (body_poses, query_object, contact_results, state, label images)
do not exist on hardware; Meshcat is not drawn from hardware status.
"""

from __future__ import annotations

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
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcm
from pydrake.manipulation import (
    PandaCommandSender,
    PandaControlMode,
    PandaStatusReceiver,
    SchunkWsgCommandSender,
    SchunkWsgStatusReceiver,
)
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.lcm import (
    LcmInterfaceSystem,
    LcmSubscriberSystem,
    PySerializer,
    _Serializer_,
)
from pydrake.systems.primitives import (
    Demultiplexer,
    Multiplexer,
)
from pydrake.systems.sensors import (
    LcmImageArrayToImages,
)

from ms_drake.errors import ScenarioError
from ms_drake.paths import make_parser
from ms_drake.station.drivers import (
    CONTROL_PERIOD,
    CommandField,
    CommandGuard,
    complete_arm_handles,
    jaw_guard_fields,
    jaw_limits,
    suction_guard_fields,
)
from ms_drake.station.robots import add_robot_from_scenario

SUCTION_STATUS = ("holding", "body_index", "gap")
BLADE_STATUS = ("blade", "blade_rate")


def command_channel(prefix: str) -> str:
    return f"{prefix.upper()}_COMMAND"


def status_channel(prefix: str) -> str:
    return f"{prefix.upper()}_STATUS"


def camera_channel(camera_name: str) -> str:
    return f"DRAKE_RGBD_CAMERA_IMAGES_{camera_name}"


def cpp_serializer(lcm_type):
    return _Serializer_[lcm_type]()


# --------------------------------------------------------------------------------- systems
class GatedLcmPublisher(LeafSystem):
    """Publishes its `message` input on `channel` every `period` while `enabled` > 0.5.

    Input ports:
      message  abstract, the serializer's type (C++ lcmt via _Serializer_, or PySerializer)
      enabled  (1) optional; unconnected means always enabled
    """

    def __init__(self, channel: str, serializer, lcm, period: float):
        super().__init__()
        self._message = self.DeclareAbstractInputPort("message", serializer.CreateDefaultValue())
        self._enabled = self.DeclareVectorInputPort("enabled", 1)
        self._channel, self._serializer, self._lcm = channel, serializer, lcm
        self.DeclarePeriodicPublishEvent(period, 0.0, self._publish)
        self.published = 0  # number of messages sent (for tests and logs)

    def _publish(self, context):
        if self._enabled.HasValue(context) and self._enabled.Eval(context)[0] <= 0.5:
            return
        data = self._serializer.Serialize(self._message.EvalAbstract(context))
        self._lcm.Publish(self._channel, data, context.get_time())
        self.published += 1


class RobotStateSender(LeafSystem):
    """Input port: position (n). Output port: message (lcmt_robot_state with the joint names,
    utime = context time)."""

    def __init__(self, joint_names):
        super().__init__()

        self._names = list(joint_names)
        self._in = self.DeclareVectorInputPort("position", len(self._names))
        self.DeclareAbstractOutputPort("message", lambda: AbstractValue.Make(lcmt_robot_state()), self._calc)
        self._type = lcmt_robot_state

    def _calc(self, context, output):
        msg = self._type()
        msg.utime = int(round(context.get_time() * 1e6))
        msg.num_joints = len(self._names)
        msg.joint_name = list(self._names)
        msg.joint_position = [float(v) for v in self._in.Eval(context)]
        output.set_value(msg)


class RobotStateReceiver(LeafSystem):
    """Latches lcmt_robot_state messages every `period`.

    Input ports:
      message        abstract lcmt_robot_state (an LcmSubscriberSystem with the Python serializer)
      position_hold  (n) only when hold_input=True: the output before the first message (the
                     value at initialization is latched; e.g. the measured position on the robot side)
    Output ports:
      position  (n) the newest message's positions (before any: zeros, or the latched hold)
      state     (2n) [position, velocity]; velocity from the last two messages' positions and utimes
      received  (1) number of messages latched so far
    A message whose joint names differ from `joint_names` raises ScenarioError (the robot on the
    bus is not the scenario's robot).
    """

    def __init__(self, joint_names, period: float = CONTROL_PERIOD, hold_input: bool = False, channel: str = ""):
        super().__init__()

        n = len(joint_names)
        self._msg = self.DeclareAbstractInputPort("message", AbstractValue.Make(lcmt_robot_state()))
        self._hold = self.DeclareVectorInputPort("position_hold", n) if hold_input else None
        # state: q (n), v (n), last utime, count
        self._x = self.DeclareDiscreteState(2 * n + 2)
        self._n, self._names, self._channel = n, list(joint_names), channel
        self.DeclareVectorOutputPort("position", n, lambda c, o: o.SetFromVector(c.get_discrete_state(self._x).value()[:n]),
                                     prerequisites_of_calc={self.discrete_state_ticket(self._x)})
        self.DeclareVectorOutputPort("state", 2 * n,
                                     lambda c, o: o.SetFromVector(c.get_discrete_state(self._x).value()[:2 * n]),
                                     prerequisites_of_calc={self.discrete_state_ticket(self._x)})
        self.DeclareVectorOutputPort("received", 1, lambda c, o: o.SetAtIndex(0, c.get_discrete_state(self._x).value()[-1]),
                                     prerequisites_of_calc={self.discrete_state_ticket(self._x)})
        if hold_input:
            self.DeclareInitializationDiscreteUpdateEvent(self._init)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _init(self, context, discrete_state):
        x = np.array(context.get_discrete_state(self._x).value())
        x[:self._n] = self._hold.Eval(context)
        x[-2] = -1.0
        discrete_state.set_value(self._x, x)

    def _update(self, context, discrete_state):
        x = np.array(context.get_discrete_state(self._x).value())
        msg = self._msg.Eval(context)
        n = self._n
        if msg.num_joints == 0 or (x[-1] > 0 and msg.utime == x[-2]):  # nothing new
            discrete_state.set_value(self._x, x)
            return
        if list(msg.joint_name) != self._names:
            raise ScenarioError(f"LCM channel {self._channel or '(robot state)'} carries joints {list(msg.joint_name)} "
                                f"but the scenario's arm has {self._names}; check the robot's driver configuration")
        q = np.asarray(msg.joint_position, float)
        if x[-1] > 0 and msg.utime > x[-2]:
            x[n:2 * n] = (q - x[:n]) / ((msg.utime - x[-2]) * 1e-6)
        else:
            x[n:2 * n] = 0.0
        x[:n] = q
        x[-2] = msg.utime
        x[-1] += 1
        discrete_state.set_value(self._x, x)


class SignalSender(LeafSystem):
    """Input port: value (len(coords)). Output port: message (lcmt_drake_signal with coords)."""

    def __init__(self, coords):
        super().__init__()

        self._coords, self._type = list(coords), lcmt_drake_signal
        self._in = self.DeclareVectorInputPort("value", len(self._coords))
        self.DeclareAbstractOutputPort("message", lambda: AbstractValue.Make(lcmt_drake_signal()), self._calc)

    def _calc(self, context, output):
        msg = self._type()
        msg.timestamp = int(round(context.get_time() * 1e6))
        msg.dim = len(self._coords)
        msg.coord = list(self._coords)
        msg.val = [float(v) for v in self._in.Eval(context)]
        output.set_value(msg)


class SignalReceiver(LeafSystem):
    """Input port: message (lcmt_drake_signal). Output port: value (len(coords)): the message's
    values when its coords match, else `default` (e.g. before the first message)."""

    def __init__(self, coords, default):
        super().__init__()

        self._coords = list(coords)
        self._default = np.asarray(default, float)
        self._msg = self.DeclareAbstractInputPort("message", AbstractValue.Make(lcmt_drake_signal()))
        self.DeclareVectorOutputPort("value", len(self._coords), self._calc)

    def _calc(self, context, output):
        msg = self._msg.Eval(context)
        if msg.dim == len(self._coords) and list(msg.coord) == self._coords:
            output.SetFromVector(np.asarray(msg.val, float))
        else:
            output.SetFromVector(self._default)


# --------------------------------------------------------------------------------- layout
def robot_layout(scenario):
    """The scenario's robot parsed into a bare plant (no simulation): (plant, RobotHandle) with
    arm limits filled in; used to size the hardware ports."""

    if not scenario.robot.name:
        raise ScenarioError("robot.name: the hardware station needs a robot; set robot.name")
    plant = MultibodyPlant(0.0)
    handle = add_robot_from_scenario(None, plant, None, scenario, make_parser(plant))
    plant.Finalize()
    complete_arm_handles(plant, handle)
    return plant, handle


def lcm_for(scenario, lcm):
    if lcm is not None:
        return lcm

    return DrakeLcm(scenario.lcm_url)


# --------------------------------------------------------------------------------- station side
def MakeHardwareStation(scenario, meshcat=None, lcm=None, name: str = "hardware_station"):
    """The station of `scenario` talking LCM (see the module docstring for channels/safety).

    meshcat is accepted for MakeStation's signature and not drawn into (no plant state here).
    One Simulator per hardware station: the status watchdogs count messages per system."""
    lcm = lcm_for(scenario, lcm)
    plant, handle = robot_layout(scenario)
    builder = DiagramBuilder()
    builder.AddSystem(LcmInterfaceSystem(lcm)).set_name("lcm")
    for arm in handle.arms:
        _hardware_arm(builder, lcm, handle.robot, arm)
    for g in handle.grippers:
        if g.kind == "parallel_jaw":
            _hardware_jaw(builder, lcm, plant, g)
        else:
            _hardware_suction(builder, lcm, plant, g)
    for cam_name, cam in scenario.cameras.items():
        sub = builder.AddSystem(LcmSubscriberSystem.Make(camera_channel(cam.name), lcmt_image_array, lcm,
                                                         use_cpp_serializer=True))
        sub.set_name(f"{cam_name}_subscriber")
        images = builder.AddSystem(LcmImageArrayToImages())
        images.set_name(f"{cam_name}_images")
        builder.Connect(sub.get_output_port(), images.image_array_t_input_port())
        if cam.rgb:
            builder.ExportOutput(images.color_image_output_port(), f"{cam_name}.rgb_image")
        if cam.depth:
            builder.ExportOutput(images.depth_image_output_port(), f"{cam_name}.depth_image")
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


def _hardware_arm(builder, lcm, robot, arm):
    cmd, st = command_channel(arm.name), status_channel(arm.name)
    guard = builder.AddSystem(CommandGuard(
        [CommandField("position", tuple(arm.lower), tuple(arm.upper), max_rate=tuple(arm.velocity))],
        CONTROL_PERIOD, status=(lcm, st), status_timeout=arm.driver.status_timeout))
    guard.set_name(f"{arm.name}_guard")
    n = len(arm.joints)
    if robot == "panda":
        sub = builder.AddSystem(LcmSubscriberSystem.Make(st, lcmt_panda_status, lcm, use_cpp_serializer=True))
        rx = builder.AddSystem(PandaStatusReceiver(n))
        builder.Connect(sub.get_output_port(), rx.get_input_port())
        mux = builder.AddSystem(Multiplexer([n, n]))
        builder.Connect(rx.get_position_measured_output_port(), mux.get_input_port(0))
        builder.Connect(rx.get_velocity_measured_output_port(), mux.get_input_port(1))
        position, state = rx.get_position_measured_output_port(), mux.get_output_port()
        sender = builder.AddSystem(PandaCommandSender(n, PandaControlMode.kPosition))
        builder.Connect(guard.GetOutputPort("position"), sender.get_input_port(0))
        pub = builder.AddSystem(GatedLcmPublisher(cmd, cpp_serializer(lcmt_panda_command), lcm, CONTROL_PERIOD))
    else:
        sub = builder.AddSystem(LcmSubscriberSystem.Make(st, lcmt_robot_state, lcm))
        rx = builder.AddSystem(RobotStateReceiver(arm.joints, CONTROL_PERIOD, channel=st))
        builder.Connect(sub.get_output_port(), rx.GetInputPort("message"))
        position, state = rx.GetOutputPort("position"), rx.GetOutputPort("state")
        sender = builder.AddSystem(RobotStateSender(arm.joints))
        builder.Connect(guard.GetOutputPort("position"), sender.GetInputPort("position"))
        pub = builder.AddSystem(GatedLcmPublisher(cmd, PySerializer(lcmt_robot_state), lcm, CONTROL_PERIOD))
    sub.set_name(f"{arm.name}_status_subscriber")
    rx.set_name(f"{arm.name}_status_receiver")
    sender.set_name(f"{arm.name}_command_sender")
    pub.set_name(f"{arm.name}_command_publisher")
    builder.Connect(sender.get_output_port(0), pub.GetInputPort("message"))
    builder.Connect(guard.GetOutputPort("enabled"), pub.GetInputPort("enabled"))
    builder.Connect(position, guard.GetInputPort("position_measured"))
    builder.ExportInput(guard.GetInputPort("position"), f"{arm.name}.position")
    builder.ExportOutput(position, f"{arm.name}.position_measured")
    builder.ExportOutput(state, f"{arm.name}.state_estimated")
    builder.ExportOutput(guard.GetOutputPort("fault"), f"{arm.name}.fault")
    builder.ExportOutput(guard.GetOutputPort("clipped"), f"{arm.name}.command_clipped")


def _hardware_jaw(builder, lcm, plant, g):

    max_opening, max_force = jaw_limits(plant, g.instance)
    cmd, st = command_channel(g.port), status_channel(g.port)
    guard = builder.AddSystem(CommandGuard(jaw_guard_fields(max_opening, max_force, g.driver.default_force_limit),
                                           CONTROL_PERIOD, status=(lcm, st), status_timeout=g.driver.status_timeout))
    guard.set_name(f"{g.port}_guard")
    sender = builder.AddSystem(SchunkWsgCommandSender(default_force_limit=g.driver.default_force_limit))
    sender.set_name(f"{g.port}_command_sender")
    builder.Connect(guard.GetOutputPort("position"), sender.GetInputPort("position"))
    builder.Connect(guard.GetOutputPort("force_limit"), sender.GetInputPort("force_limit"))
    pub = builder.AddSystem(GatedLcmPublisher(cmd, cpp_serializer(lcmt_schunk_wsg_command), lcm, CONTROL_PERIOD))
    pub.set_name(f"{g.port}_command_publisher")
    builder.Connect(sender.get_output_port(0), pub.GetInputPort("message"))
    builder.Connect(guard.GetOutputPort("enabled"), pub.GetInputPort("enabled"))
    sub = builder.AddSystem(LcmSubscriberSystem.Make(st, lcmt_schunk_wsg_status, lcm, use_cpp_serializer=True))
    sub.set_name(f"{g.port}_status_subscriber")
    rx = builder.AddSystem(SchunkWsgStatusReceiver())
    rx.set_name(f"{g.port}_status_receiver")
    builder.Connect(sub.get_output_port(), rx.get_input_port(0))
    builder.ExportInput(guard.GetInputPort("position"), f"{g.port}.position")
    builder.ExportInput(guard.GetInputPort("force_limit"), f"{g.port}.force_limit")
    builder.ExportOutput(rx.GetOutputPort("state"), f"{g.port}.state_measured")
    builder.ExportOutput(rx.GetOutputPort("force"), f"{g.port}.force_measured")
    builder.ExportOutput(guard.GetOutputPort("fault"), f"{g.port}.fault")
    builder.ExportOutput(guard.GetOutputPort("clipped"), f"{g.port}.command_clipped")


def suction_coords(kind):
    command = ("suction", "blade") if kind == "bluction" else ("suction",)
    status = SUCTION_STATUS + (BLADE_STATUS if kind == "bluction" else ())
    return command, status


def _blade_limits(plant, g):
    if g.kind != "bluction":
        return ()
    j = plant.GetJointByName("blade_joint", g.instance)
    return j.position_lower_limits()[0], j.position_upper_limits()[0], j.velocity_upper_limits()[0]


def _hardware_suction(builder, lcm, plant, g):
    cmd, st = command_channel(g.port), status_channel(g.port)
    command_coords, status_coords = suction_coords(g.kind)
    fields = suction_guard_fields(g.kind, *_blade_limits(plant, g))
    guard = builder.AddSystem(CommandGuard(fields, CONTROL_PERIOD, status=(lcm, st),
                                           status_timeout=g.driver.status_timeout))
    guard.set_name(f"{g.port}_guard")
    sender = builder.AddSystem(SignalSender(command_coords))
    sender.set_name(f"{g.port}_command_sender")
    mux = builder.AddSystem(Multiplexer([1] * len(command_coords)))
    builder.Connect(guard.GetOutputPort("suction"), mux.get_input_port(0))
    if g.kind == "bluction":
        builder.Connect(guard.GetOutputPort("position"), mux.get_input_port(1))
    builder.Connect(mux.get_output_port(), sender.GetInputPort("value"))
    pub = builder.AddSystem(GatedLcmPublisher(cmd, PySerializer(lcmt_drake_signal), lcm, CONTROL_PERIOD))
    pub.set_name(f"{g.port}_command_publisher")
    builder.Connect(sender.GetOutputPort("message"), pub.GetInputPort("message"))
    builder.Connect(guard.GetOutputPort("enabled"), pub.GetInputPort("enabled"))
    sub = builder.AddSystem(LcmSubscriberSystem.Make(st, lcmt_drake_signal, lcm))
    sub.set_name(f"{g.port}_status_subscriber")
    default = [0.0, -1.0, math.nan] + ([0.0, 0.0] if g.kind == "bluction" else [])
    rx = builder.AddSystem(SignalReceiver(status_coords, default))
    rx.set_name(f"{g.port}_status_receiver")
    builder.Connect(sub.get_output_port(), rx.GetInputPort("message"))
    builder.ExportInput(guard.GetInputPort("suction"), f"{g.port}.suction")
    if g.kind == "bluction":
        demux = builder.AddSystem(Demultiplexer([3, 2]))
        builder.Connect(rx.GetOutputPort("value"), demux.get_input_port())
        angle = builder.AddSystem(Demultiplexer([1, 1]))
        builder.Connect(demux.get_output_port(1), angle.get_input_port())
        builder.Connect(angle.get_output_port(0), guard.GetInputPort("position_measured"))
        builder.ExportOutput(demux.get_output_port(0), f"{g.port}.suction_state")
        builder.ExportInput(guard.GetInputPort("position"), f"{g.port}.position")
        builder.ExportOutput(demux.get_output_port(1), f"{g.port}.state_measured")
    else:
        builder.ExportOutput(rx.GetOutputPort("value"), f"{g.port}.suction_state")
    builder.ExportOutput(guard.GetOutputPort("fault"), f"{g.port}.fault")
    builder.ExportOutput(guard.GetOutputPort("clipped"), f"{g.port}.command_clipped")
