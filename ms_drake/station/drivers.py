"""Robot drivers of the simulated station: scenario entries -> controllers behind named ports.

Drake's `model_drivers` pattern: each scenario entry `robot.drivers[<prefix>]` is a dataclass
(ms_drake.scenario.ArmDriver, JawDriver, SuctionDriver) and one apply function per kind wires it
(`apply_arm_drivers`, `apply_jaw_driver`, `apply_suction_driver`). Missing entries use the
dataclass defaults. The port names are the same in simulation and on hardware (hardware.py):

  arm (e.g. `panda`, `yumi_right`, `yumi_left`, `fetch`, `floating`):
    <arm>.position (in, n)           commanded joint positions, in ArmSpec.joints order
    <arm>.position_measured (out, n) <arm>.state_estimated (out, 2n: [q, v])
    <arm>.fault (out, 1)             1 while the command is held (hardware: status lost)
    <arm>.command_clipped (out, 1)   1 when the last command was clipped to the joint limits
  parallel jaw (`<arm>_jaw`, e.g. `yumi_right_jaw`, `panda_jaw`, `floating_jaw`):
    <g>.position (in, 1) opening [m]; <g>.force_limit (in, 1) [N]
    <g>.state_measured (out, 2) [opening, opening rate]; <g>.force_measured (out, 1)
  suction cup (`<arm>_suction`, e.g. `yumi_left_suction`, `floating_suction`):
    <g>.suction (in, 1) vacuum on when > 0.5; <g>.suction_state (out, 3) [holding, body, gap]
  bluction (`<arm>_bluction`, e.g. `fetch_bluction`): the suction ports plus
    <g>.position (in, 1) blade angle [rad] (0: blade down for pushing, pi: up for suction);
    <g>.state_measured (out, 2) [blade angle, rate]
  every gripper also has <g>.fault and <g>.command_clipped.
Unconnected command inputs are allowed: an arm (and the blade) then holds the position it had
when the simulation started, a jaw stays open at the default force limit, suction stays off.

Choices (the reference is silent):
  * Arms use joint stiffness: the plant's own implicit PD controllers (JointActuator controller
    gains, solved inside the discrete SAP/lagged contact solver, stable at any gain) plus a
    gravity-compensation feed-forward from InverseDynamics on a control plant (the robot with
    each gripper lumped into one rigid body at its flange). Default stiffness: the joint's effort
    limit reached at STIFFNESS_ANGLE = 0.05 rad (0.01 m for prismatic joints; softer arms lagged a
    blade push by a centimetre); damping 2 * ratio * sqrt(kp * M_ii)
    with M the joint-space inertia at the home configuration. Needs a discrete plant whose
    contact approximation is sap / lagged / similar (not tamsi).
  * Joints of the robot outside every arm (Fetch base x/y/yaw, head pan/tilt) hold their
    default positions with the same PD.
  * Every command passes a CommandGuard at CONTROL_PERIOD (200 Hz, a usual arm-interface rate;
    in simulation rounded to a multiple of the plant step, 250 Hz at 2 ms): clipped to position
    limits and to velocity limits (a rate limit on successive commands); its finite difference
    is the desired velocity of the PD. The same guard watches the status on hardware.
  * The floating gripper keeps the PD gains of its model (drake:controller_gains) unless the
    scenario gives `kp`.
  * Jaw: Drake's SchunkWsgPositionController (the SchunkWsgDriver pattern) on the two finger
    joints, which follow the WSG layout (see grippers.py); the force limit is clipped to the
    finger actuator's effort limit.
  * Suction: ms_drake.station.suction.SuctionCup forces on the plant's applied-force input
    (several cups are combined with ExternallyAppliedSpatialForceMultiplexer).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydrake.manipulation import (
    MakeMultibodyStateToWsgStateSystem,
    SchunkWsgPositionController,
)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import (
    ExternallyAppliedSpatialForceMultiplexer,
    MultibodyPlant,
)
from pydrake.multibody.tree import PdControllerGains
from pydrake.systems.controllers import InverseDynamics
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.primitives import (
    AffineSystem,
    ConstantVectorSource,
    MatrixGain,
    Multiplexer,
    SharedPointerSystem,
)

from ms_drake.errors import ScenarioError
from ms_drake.geometry import transform_from_rpy_xyz
from ms_drake.paths import make_parser
from ms_drake.robots import gripper_spec
from ms_drake.station import robots
from ms_drake.station.robots import GripperHandle, RobotHandle
from ms_drake.station.suction import SuctionCup

CONTROL_PERIOD = 0.005  # [s] command rate of every guard (200 Hz)
STIFFNESS_ANGLE = 0.05  # [rad] error at which the default stiffness reaches the effort limit


# --------------------------------------------------------------------------------- guard
@dataclass(frozen=True)
class CommandField:
    """One command vector of a CommandGuard.

    lower/upper: limits (clipped); max_rate: per-second limit on the change between successive
    commands (None: none); default: the command while the input is unconnected (None: hold the
    measured value latched when the guard became active); hold: what a fault holds, "measured"
    (the measured value at the fault's onset) or "command" (the last command sent).
    """

    name: str
    lower: tuple
    upper: tuple
    max_rate: tuple | None = None
    default: tuple | None = None
    hold: str = "measured"

    @property
    def size(self) -> int:
        return len(self.lower)

    @property
    def needs_measured(self) -> bool:
        return self.default is None or self.hold == "measured" or self.max_rate is not None


class CommandGuard(LeafSystem):
    """Clips commands to limits, gates them on robot status and holds them when status is lost.

    Input ports (per field f):
      f.name            (n_f) command; optional (see CommandField.default)
      f.name_measured   (n_f) measured value; only for fields that need it
    Output ports:
      f.name            (n_f) the guarded command (zero-order hold at `period`)
      f.name_velocity   (n_f) its finite difference (the desired velocity)
      enabled           (1) 1 once a status has arrived and the guard has latched it (commands may be sent)
      fault             (1) 1 while status is older than `status_timeout` (commands held)
      clipped           (1) 1 if the last update clipped a command (position or rate limit)

    status: None (simulation: status is always fresh) or (lcm, channel): the guard subscribes
    to `channel` and counts messages; a new message refreshes the status. Before the first one
    nothing is enabled; after `status_timeout` without one the fields hold (CommandField.hold)
    and `fault` is 1; it clears when messages arrive again, and the commands then move from the
    held value at most at max_rate (no jump).
    """

    _META = 6  # have_status, initialized, messages_seen, arrival_time, fault, clipped

    def __init__(self, fields, period: float = CONTROL_PERIOD, status=None, status_timeout: float = math.inf):
        super().__init__()
        self._fields = list(fields)
        self._cmd, self._meas = [], []
        for f in self._fields:  # ports first
            if f.hold not in ("measured", "command"):
                raise ValueError(f"CommandField {f.name}: hold must be 'measured' or 'command'")
            self._cmd.append(self.DeclareVectorInputPort(f.name, f.size))
            self._meas.append(self.DeclareVectorInputPort(f"{f.name}_measured", f.size) if f.needs_measured else None)
        offsets, o = [], 0
        for f in self._fields:
            offsets.append(o)
            o += 3 * f.size  # last, previous, hold
        self._offsets = offsets
        self._meta = o
        x0 = np.zeros(o + self._META)
        for f, off in zip(self._fields, offsets):  # before initialization: the defaults
            if f.default is not None:
                x0[off:off + 3 * f.size] = np.tile(np.asarray(f.default, float), 3)
        self._state = self.DeclareDiscreteState(x0)
        for k, f in enumerate(self._fields):
            self.DeclareVectorOutputPort(f.name, f.size, lambda c, out, k=k: self._out(c, out, k, 0),
                                         prerequisites_of_calc={self.discrete_state_ticket(self._state)})
            self.DeclareVectorOutputPort(f"{f.name}_velocity", f.size, lambda c, out, k=k: self._out_velocity(c, out, k),
                                         prerequisites_of_calc={self.discrete_state_ticket(self._state)})
        for i, name in ((1, "enabled"), (4, "fault"), (5, "clipped")):
            self.DeclareVectorOutputPort(name, 1, lambda c, out, i=i: out.SetAtIndex(
                0, c.get_discrete_state(self._state).GetAtIndex(self._meta + i)),
                prerequisites_of_calc={self.discrete_state_ticket(self._state)})

        if period <= 0:
            raise ValueError("CommandGuard: period must be > 0")
        self._period = period
        self._timeout = status_timeout
        self._lower = [np.asarray(f.lower, float) for f in self._fields]
        self._upper = [np.asarray(f.upper, float) for f in self._fields]
        self._rate = [None if f.max_rate is None else np.asarray(f.max_rate, float) * period for f in self._fields]
        self._default = [None if f.default is None else np.asarray(f.default, float) for f in self._fields]
        self._slices = [tuple(self._slice(k, part) for part in range(3)) for k in range(len(self._fields))]
        self._messages = 0
        self._status = status
        if status is not None:
            lcm, channel = status
            lcm.Subscribe(channel, self._on_message)
        self.DeclareInitializationDiscreteUpdateEvent(self._update)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)

    def _on_message(self, _data):
        self._messages += 1

    def field_names(self):
        return [f.name for f in self._fields]

    def _slice(self, k, part):
        o = self._offsets[k] + part * self._fields[k].size
        return slice(o, o + self._fields[k].size)

    def _out(self, context, output: BasicVector, k, part):
        output.SetFromVector(context.get_discrete_state(self._state).value()[self._slices[k][part]])

    def _out_velocity(self, context, output, k):
        x = context.get_discrete_state(self._state).value()
        last, prev, _ = self._slices[k]
        output.SetFromVector((x[last] - x[prev]) * (1.0 / self._period))

    def _update(self, context, discrete_state):
        x = np.array(context.get_discrete_state(self._state).value())
        t = context.get_time()
        m = self._meta
        have, initialized, seen, arrival, fault = x[m:m + 5]
        if self._status is None:
            have, arrival = 1.0, t
        elif self._messages != seen:
            first = not have
            seen, arrival, have = float(self._messages), t, 1.0
            if first:  # receivers latch the first status at this same tick: initialize at the next
                x[m:m + 4] = (have, 0.0, seen, arrival)
                discrete_state.set_value(self._state, x)
                return
        if not have:
            discrete_state.set_value(self._state, x)
            return
        stale = (t - arrival) > self._timeout
        clipped = 0.0
        for k, f in enumerate(self._fields):
            last, prev, hold = self._slices[k]
            lo, hi, rate = self._lower[k], self._upper[k], self._rate[k]
            meas = self._meas[k].Eval(context) if self._meas[k] is not None else None
            if not initialized:
                start = meas if meas is not None else np.asarray(f.default, float)
                x[last] = x[prev] = x[hold] = np.minimum(np.maximum(start, lo), hi)
            if stale:
                if not fault:  # onset: latch what to hold
                    x[hold] = meas if f.hold == "measured" else x[last]
                target, is_command = x[hold], False
            elif self._cmd[k].HasValue(context):
                target, is_command = self._cmd[k].Eval(context), True
            elif f.default is not None:
                target, is_command = self._default[k], False
            else:
                target, is_command = x[hold], False
            safe = np.minimum(np.maximum(target, lo), hi)
            if rate is not None:
                safe = np.minimum(np.maximum(safe, x[last] - rate), x[last] + rate)
            if is_command and np.any(np.abs(safe - target) > 1e-9):
                clipped = 1.0
            x[prev] = x[last]
            x[last] = safe
        x[m:m + 6] = (have, 1.0, seen, arrival, 1.0 if stale else 0.0, clipped)
        discrete_state.set_value(self._state, x)


# --------------------------------------------------------------------------------- helpers
def _joint_layout(plant, instance, joints):
    """Global position / velocity indices of `joints` of `instance`."""
    js = [plant.GetJointByName(n, instance) for n in joints]
    return np.array([j.position_start() for j in js]), np.array([j.velocity_start() for j in js])


def _selector(plant, idx_q, idx_v, state: bool):
    """A MatrixGain picking [q(idx)] or [q(idx), v(idx)] from the full plant state."""
    nq, nv = plant.num_positions(), plant.num_velocities()
    rows = list(idx_q) + ([nq + i for i in idx_v] if state else [])
    S = np.zeros((len(rows), nq + nv))
    S[np.arange(len(rows)), rows] = 1.0
    return MatrixGain(S)


def complete_arm_handles(plant, handle: RobotHandle):
    """Fill limits (from the finalized plant) and default gains of every arm."""
    ctx = plant.CreateDefaultContext()
    M = plant.CalcMassMatrix(ctx)
    for arm in handle.arms:
        js = [plant.GetJointByName(n, arm.robot_instance) for n in arm.joints]
        arm.lower = np.array([j.position_lower_limits()[0] for j in js])
        arm.upper = np.array([j.position_upper_limits()[0] for j in js])
        arm.velocity = np.array([j.velocity_upper_limits()[0] for j in js])
        actuators = {plant.get_joint_actuator(a).joint().name(): plant.get_joint_actuator(a)
                     for a in plant.GetJointActuatorIndices(arm.robot_instance)}
        kp = np.asarray(arm.driver.kp, float) if arm.driver.kp else np.array(
            [default_stiffness(j, actuators[j.name()]) for j in js])
        arm.kp = kp
        diag = np.array([M[j.velocity_start(), j.velocity_start()] for j in js])
        arm.kd = 2.0 * arm.driver.damping_ratio * np.sqrt(kp * np.maximum(diag, 1e-6))


def default_stiffness(joint, actuator) -> float:
    """The effort limit reached at 0.1 rad (revolute) or 0.01 m (prismatic) of error."""
    effort = actuator.effort_limit()
    if not np.isfinite(effort):
        effort = 100.0
    prismatic = joint.type_name() == "prismatic"
    return effort / (0.01 if prismatic else STIFFNESS_ANGLE)


def make_control_plant(plant, handle: RobotHandle):
    """The robot alone with each gripper lumped into one rigid body welded at its mount (for
    gravity compensation). Same joints and actuator order as the robot's model instance."""

    control = MultibodyPlant(0.0)
    parser = make_parser(control)
    if handle.robot == "floating":
        base = robots._add_file(parser, robots.models_dir() / "grippers" / "floating_base.sdf")
        control.WeldFrames(control.world_frame(), control.GetFrameByName("floating_origin_link", base), handle.X_WR)
        instance = base
    else:
        instance = robots.add_robot(control, parser, handle.robot, handle.X_WR)
    ctx = plant.CreateDefaultContext()
    for g in handle.grippers:
        body_frame = plant.GetFrameByName("body", g.instance)
        M_GGo_G = plant.CalcSpatialInertia(ctx, body_frame, plant.GetBodyIndices(g.instance))
        if handle.robot == "floating":
            mount, X_FG = control.GetFrameByName("floating_yaw_link", instance), None
        else:
            a = robots.robot_spec(handle.robot).arms[g.arm]
            mount, X_FG = control.GetFrameByName(a.flange, instance), transform_from_rpy_xyz(*a.X_FG_rpy_xyz)
        lumped = control.AddRigidBody(f"{g.port}_lumped", instance, M_GGo_G)

        control.WeldFrames(mount, lumped.body_frame(), X_FG if X_FG is not None else RigidTransform())
    control.Finalize()
    return control, instance


# --------------------------------------------------------------------------------- apply
def sim_period(plant) -> float:
    """The guards' period in simulation: CONTROL_PERIOD rounded to a multiple of the plant's
    time step (fewer simulator steps than two unrelated rates)."""
    dt = plant.time_step()
    return dt * max(1, round(CONTROL_PERIOD / dt)) if dt > 0 else CONTROL_PERIOD


def apply_robot_drivers(builder, plant, scene_graph, handle: RobotHandle):
    """Wire every arm and gripper driver of `handle` (after plant.Finalize()) and export the
    robot's ports. The drivers use the plant's PD-controlled actuators, so the plant must be
    discrete with a SAP-family contact approximation (ScenarioError otherwise)."""
    if plant.time_step() <= 0:
        raise ScenarioError("plant_config.time_step: the robot drivers use the plant's PD controllers, which "
                            "need a discrete plant; set time_step > 0 (e.g. 0.002)")
    if plant.get_discrete_contact_approximation().name == "kTamsi":
        raise ScenarioError("plant_config.discrete_contact_approximation: the robot drivers need sap, similar or "
                            "lagged (PD-controlled actuators); tamsi does not support them")
    complete_arm_handles(plant, handle)
    apply_arm_drivers(builder, plant, handle)
    cups = []
    for g in handle.grippers:
        if g.kind == "parallel_jaw":
            apply_jaw_driver(builder, plant, g)
        else:
            cups.append(apply_suction_driver(builder, plant, scene_graph, g))
    if cups:
        _connect_spatial_forces(builder, plant, cups)


def _export(builder, port, name):
    builder.ExportOutput(port, name)


def apply_arm_drivers(builder, plant, handle: RobotHandle):
    """Joint stiffness (plant PD) + gravity compensation for the arms of the robot instance."""
    inst = handle.instance
    actuators = [plant.get_joint_actuator(a) for a in plant.GetJointActuatorIndices(inst)]
    nu = len(actuators)
    # which command feeds each actuator: (arm k, joint j) or a hold value
    slot = {}
    sizes = []
    for k, arm in enumerate(handle.arms):
        for j, n in enumerate(arm.joints):
            slot[n] = (k, j)
        sizes += [len(arm.joints), len(arm.joints)]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    D = np.zeros((2 * nu, int(offsets[-1])))
    y0 = np.zeros(2 * nu)
    default_q = plant.GetDefaultPositions()
    ctx = plant.CreateDefaultContext()
    M = plant.CalcMassMatrix(ctx)
    for a, act in enumerate(actuators):
        joint = act.joint()
        if joint.name() in slot:
            k, j = slot[joint.name()]
            arm = handle.arms[k]
            D[a, offsets[2 * k] + j] = 1.0
            D[nu + a, offsets[2 * k + 1] + j] = 1.0
            kp, kd = arm.kp[j], arm.kd[j]
        else:  # held joint (Fetch base, head)
            y0[a] = default_q[joint.position_start()]
            kp = default_stiffness(joint, act)
            kd = 2.0 * np.sqrt(kp * max(M[joint.velocity_start(), joint.velocity_start()], 1e-6))
        if handle.robot != "floating" or handle.arms[0].driver.kp:
            act.set_controller_gains(PdControllerGains(p=float(kp), d=float(kd)))

    mux = builder.AddSystem(Multiplexer(sizes))
    mux.set_name(f"{handle.robot}_command_mux")
    desired = builder.AddSystem(AffineSystem(D=D, y0=y0))
    desired.set_name(f"{handle.robot}_desired_state")
    builder.Connect(mux.get_output_port(), desired.get_input_port())
    builder.Connect(desired.get_output_port(), plant.get_desired_state_input_port(inst))

    for k, arm in enumerate(handle.arms):
        iq, iv = _joint_layout(plant, arm.robot_instance, arm.joints)
        meas = builder.AddSystem(_selector(plant, iq, iv, state=False))
        meas.set_name(f"{arm.name}_position_measured")
        est = builder.AddSystem(_selector(plant, iq, iv, state=True))
        est.set_name(f"{arm.name}_state_estimated")
        builder.Connect(plant.get_state_output_port(), meas.get_input_port())
        builder.Connect(plant.get_state_output_port(), est.get_input_port())
        guard = builder.AddSystem(CommandGuard([CommandField(
            "position", tuple(arm.lower), tuple(arm.upper), max_rate=tuple(arm.velocity))], sim_period(plant)))
        guard.set_name(f"{arm.name}_guard")
        builder.Connect(meas.get_output_port(), guard.GetInputPort("position_measured"))
        builder.Connect(guard.GetOutputPort("position"), mux.get_input_port(2 * k))
        builder.Connect(guard.GetOutputPort("position_velocity"), mux.get_input_port(2 * k + 1))
        builder.ExportInput(guard.GetInputPort("position"), f"{arm.name}.position")
        _export(builder, meas.get_output_port(), f"{arm.name}.position_measured")
        _export(builder, est.get_output_port(), f"{arm.name}.state_estimated")
        _export(builder, guard.GetOutputPort("fault"), f"{arm.name}.fault")
        _export(builder, guard.GetOutputPort("clipped"), f"{arm.name}.command_clipped")

    if any(arm.driver.gravity_compensation for arm in handle.arms):
        control, _ = make_control_plant(plant, handle)
        SharedPointerSystem.AddToBuilder(builder, control)  # the diagram owns the control plant
        gc = builder.AddSystem(InverseDynamics(control, InverseDynamics.InverseDynamicsMode.kGravityCompensation))
        gc.set_name(f"{handle.robot}_gravity_compensation")
        B = control.MakeActuationMatrix()  # nv x nu, actuator order = the instance's
        mask = np.ones(nu)
        for arm in handle.arms:
            if not arm.driver.gravity_compensation:
                for n in arm.joints:
                    mask[[a for a, act in enumerate(actuators) if act.joint().name() == n]] = 0.0
        to_u = builder.AddSystem(MatrixGain(np.diag(mask) @ B.T))
        to_u.set_name(f"{handle.robot}_gravity_to_actuation")
        builder.Connect(plant.get_state_output_port(inst), gc.get_input_port_estimated_state())
        builder.Connect(gc.get_output_port_generalized_force(), to_u.get_input_port())
        builder.Connect(to_u.get_output_port(), plant.get_actuation_input_port(inst))
    else:
        zero = builder.AddSystem(ConstantVectorSource(np.zeros(nu)))
        builder.Connect(zero.get_output_port(), plant.get_actuation_input_port(inst))


def jaw_limits(plant, instance):
    """(max opening [m], max force [N]) of a parallel jaw model instance."""
    left = plant.GetJointByName("left_finger_sliding_joint", instance)
    right = plant.GetJointByName("right_finger_sliding_joint", instance)
    opening = right.position_upper_limits()[0] - left.position_lower_limits()[0]
    efforts = [plant.get_joint_actuator(a).effort_limit() for a in plant.GetJointActuatorIndices(instance)]
    return float(opening), float(min(efforts))


def jaw_guard_fields(max_opening, max_force, default_force):
    return [CommandField("position", (0.0,), (max_opening,), default=(max_opening,), hold="command"),
            CommandField("force_limit", (0.0,), (max_force,), default=(min(default_force, max_force),),
                         hold="command")]


def apply_jaw_driver(builder, plant, g: GripperHandle):
    """Drake's WSG position controller with a force limit on the two finger joints."""
    d = g.driver
    max_opening, max_force = jaw_limits(plant, g.instance)
    guard = builder.AddSystem(CommandGuard(jaw_guard_fields(max_opening, max_force, d.default_force_limit),
                                           sim_period(plant)))
    guard.set_name(f"{g.port}_guard")
    wsg = builder.AddSystem(SchunkWsgPositionController(kp_command=d.kp_command, kd_command=d.kd_command,
                                                        default_force_limit=d.default_force_limit))
    wsg.set_name(f"{g.port}_controller")
    builder.Connect(guard.GetOutputPort("position"), wsg.get_desired_position_input_port())
    builder.Connect(guard.GetOutputPort("force_limit"), wsg.get_force_limit_input_port())
    builder.Connect(plant.get_state_output_port(g.instance), wsg.get_state_input_port())
    builder.Connect(wsg.get_generalized_force_output_port(), plant.get_actuation_input_port(g.instance))
    to_wsg = builder.AddSystem(MakeMultibodyStateToWsgStateSystem())
    to_wsg.set_name(f"{g.port}_state")
    builder.Connect(plant.get_state_output_port(g.instance), to_wsg.get_input_port())
    builder.ExportInput(guard.GetInputPort("position"), f"{g.port}.position")
    builder.ExportInput(guard.GetInputPort("force_limit"), f"{g.port}.force_limit")
    _export(builder, to_wsg.get_output_port(), f"{g.port}.state_measured")
    _export(builder, wsg.get_grip_force_output_port(), f"{g.port}.force_measured")
    _export(builder, guard.GetOutputPort("fault"), f"{g.port}.fault")
    _export(builder, guard.GetOutputPort("clipped"), f"{g.port}.command_clipped")


BLADE_MAX_RATE = 3.0  # [rad/s], the blade joint's velocity limit in the bluction model


def suction_guard_fields(kind, blade_lower=0.0, blade_upper=math.pi, blade_rate=BLADE_MAX_RATE):
    fields = [CommandField("suction", (0.0,), (1.0,), default=(0.0,), hold="command")]
    if kind == "bluction":
        fields.append(CommandField("position", (blade_lower,), (blade_upper,), max_rate=(blade_rate,)))
    return fields


def apply_suction_driver(builder, plant, scene_graph, g: GripperHandle):
    """SuctionCup at the gripper's tcp; for the bluction also the blade's joint PD."""

    d = g.driver
    spec = gripper_spec(g.name)
    blade = plant.GetJointByName("blade_joint", g.instance) if g.kind == "bluction" else None
    fields = suction_guard_fields(g.kind, *( (blade.position_lower_limits()[0], blade.position_upper_limits()[0],
                                             blade.velocity_upper_limits()[0]) if blade is not None else ()))
    guard = builder.AddSystem(CommandGuard(fields, sim_period(plant)))
    guard.set_name(f"{g.port}_guard")
    frame = plant.GetFrameByName(spec.tcp_frame, g.instance)
    cup = builder.AddSystem(SuctionCup(plant, frame.body(), frame.GetFixedPoseInBodyFrame(), spec.suction_radius,
                                       max_gap=d.max_gap, max_force=d.max_force, seal_tolerance=d.seal_tolerance,
                                       max_tilt_deg=d.max_tilt_deg))
    cup.set_name(f"{g.port}_cup")
    builder.Connect(plant.get_body_poses_output_port(), cup.body_poses_input())
    builder.Connect(scene_graph.get_query_output_port(), cup.query_object_input())
    builder.Connect(guard.GetOutputPort("suction"), cup.suction_input())
    builder.ExportInput(guard.GetInputPort("suction"), f"{g.port}.suction")
    _export(builder, cup.GetOutputPort("suction_state"), f"{g.port}.suction_state")
    _export(builder, guard.GetOutputPort("fault"), f"{g.port}.fault")
    _export(builder, guard.GetOutputPort("clipped"), f"{g.port}.command_clipped")
    if blade is not None:
        act = plant.get_joint_actuator(plant.GetJointActuatorIndices(g.instance)[0])
        ctx = plant.CreateDefaultContext()
        M = plant.CalcMassMatrix(ctx)
        inertia = max(M[blade.velocity_start(), blade.velocity_start()], 1e-6)
        act.set_controller_gains(PdControllerGains(p=d.blade_kp, d=2.0 * np.sqrt(d.blade_kp * inertia)))

        angle = builder.AddSystem(MatrixGain(np.array([[1.0, 0.0]])))
        builder.Connect(plant.get_state_output_port(g.instance), angle.get_input_port())
        builder.Connect(angle.get_output_port(), guard.GetInputPort("position_measured"))
        mux = builder.AddSystem(Multiplexer([1, 1]))
        builder.Connect(guard.GetOutputPort("position"), mux.get_input_port(0))
        builder.Connect(guard.GetOutputPort("position_velocity"), mux.get_input_port(1))
        builder.Connect(mux.get_output_port(), plant.get_desired_state_input_port(g.instance))
        builder.ExportInput(guard.GetInputPort("position"), f"{g.port}.position")
        _export(builder, plant.get_state_output_port(g.instance), f"{g.port}.state_measured")
    return cup


def _connect_spatial_forces(builder, plant, cups):
    if len(cups) == 1:
        builder.Connect(cups[0].GetOutputPort("spatial_forces"), plant.get_applied_spatial_force_input_port())
        return

    mux = builder.AddSystem(ExternallyAppliedSpatialForceMultiplexer(len(cups)))
    for i, cup in enumerate(cups):
        builder.Connect(cup.GetOutputPort("spatial_forces"), mux.get_input_port(i))
    builder.Connect(mux.get_output_port(), plant.get_applied_spatial_force_input_port())


# --------------------------------------------------------------------------------- discovery
def station_arms(station) -> list[str]:
    """Arm names of a station (sim or hardware), from its ports: every `<p>.position` input
    with a `<p>.position_measured` output."""
    names = [station.get_input_port(i).get_name() for i in range(station.num_input_ports())]
    return [n[:-len(".position")] for n in names
            if n.endswith(".position") and station.HasOutputPort(n[:-len(".position")] + ".position_measured")]


def station_grippers(station) -> dict[str, str]:
    """{gripper port prefix: kind} of a station, kind parallel_jaw | suction | bluction."""
    out = {}
    for i in range(station.num_input_ports()):
        name = station.get_input_port(i).get_name()
        prefix = name.rsplit(".", 1)[0]
        if name.endswith(".force_limit"):
            out[prefix] = "parallel_jaw"
        elif name.endswith(".suction"):
            out[prefix] = "bluction" if station.HasInputPort(prefix + ".position") else "suction"
    return out
