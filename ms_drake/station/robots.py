"""Adding robots and grippers to a MultibodyPlant: the functions MakeStation calls.

    add_robot(plant, parser, "panda")                       -> ModelInstanceIndex (root welded)
    add_gripper(plant, parser, "parallel_jaw", frame)       -> ModelInstanceIndex (welded to frame)
    add_floating_gripper(plant, parser, "suction_cup")      -> (base instance, gripper instance)
    robot_spec("yumi").arms["yumi_right"].joints            -> joint names in command order
Stations (MakeStation calls these):
    add_robot_from_scenario(builder, plant, scene_graph, scenario, parser) -> RobotHandle (before Finalize)
    apply_drivers(builder, plant, scene_graph, scenario, handle)            (after Finalize; drivers.py)
    resolve_robot_config(scenario.robot) -> [(arm, gripper, port)], {port prefix: driver}
    station_robot_spec("floating"), station_arm_spec("yumi_left"), arm_joint_limits("fetch")
Every arm starts at ArmSpec.home (set_home); the floating gripper 0.45 m above its base origin,
pointing down.

Weld conventions (the flange frame of each arm and the transform X_FG from the flange frame F to
the gripper's `body` frame G, whose +z is the approach direction, see grippers.py):
  * Panda: F = panda_link8 (the franka_ros flange, z out of the flange); X_FG = RotZ(+pi/4), so the
    jaw closes along the same line as the Franka hand's fingers. Default gripper: parallel_jaw.
  * YuMi: F = yumi_link_7_r / yumi_link_7_l; X_FG = RotZ(pi), 7 mm along z (the gripper base
    offset of ROS yumi_description). Defaults: parallel_jaw on the right arm, suction_cup on the
    left arm (the reference's YuMi carries one of each; which arm is not stated).
  * Fetch: F = wrist_flange (outer face of wrist_roll_link, x out of the wrist; the converter adds
    it; gripper_link, the removed Fetch gripper's centre, is 0.147 m further out);
    X_FG = RotY(pi/2) so the tool's +z points along the wrist's x. Default gripper: bluction.
Roots: Panda panda_link0 and YuMi yumi_body are welded to the world at X_WR; the Fetch's
`base_origin` is welded to the world at X_WR and the planar joints base_x, base_y, base_yaw move
`base_link` above it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ms_drake.errors import ScenarioError
from ms_drake.paths import models_dir
from ms_drake.station.grippers import gripper_spec


@dataclass(frozen=True)
class ArmSpec:
    """One arm: its joints in command order, flange frame, weld transform and default gripper."""

    joints: tuple[str, ...]
    flange: str
    X_FG_rpy_xyz: tuple[tuple[float, float, float], tuple[float, float, float]]
    default_gripper: str
    velocity_limits: tuple[float, ...]
    acceleration_limits: tuple[float, ...]
    jerk_limits: tuple[float, ...]
    home: tuple[float, ...] = ()  # default joint positions in a station (() -> zeros within limits)

    def X_FG(self):
        from pydrake.math import RigidTransform, RollPitchYaw

        rpy, xyz = self.X_FG_rpy_xyz
        return RigidTransform(RollPitchYaw(*rpy), np.array(xyz))


@dataclass(frozen=True)
class RobotSpec:
    name: str
    file: str  # relative to models/
    root: str  # body / frame welded to the world
    arms: dict[str, ArmSpec] = field(default_factory=dict)
    other_joints: tuple[str, ...] = ()  # e.g. the Fetch base and head


def _yumi_arm(side: str, gripper: str, home: tuple) -> ArmSpec:
    joints = tuple(f"yumi_joint_{n}_{side}" for n in (1, 2, 7, 3, 4, 5, 6))
    return ArmSpec(
        joints=joints, flange=f"yumi_link_7_{side}", X_FG_rpy_xyz=((0, 0, np.pi), (0, 0, 0.007)),
        default_gripper=gripper,
        velocity_limits=(3.1416, 3.1416, 3.1416, 3.1416, 6.9813, 6.9813, 6.9813),
        # Not published by ABB; conservative values chosen for smooth motion (about 1/2 s to full speed).
        acceleration_limits=(6.0, 6.0, 6.0, 6.0, 12.0, 12.0, 12.0),
        jerk_limits=(60.0, 60.0, 60.0, 60.0, 120.0, 120.0, 120.0),
        home=home,
    )


# Limits for trajectory timing (ruckig). Panda: Franka's published limits (franka docs "Robot and
# interface specifications"): velocity from franka_ros; acceleration [15, 7.5, 10, 12.5, 15, 20, 20];
# jerk [7500, 3750, 5000, 6250, 7500, 10000, 10000] scaled by 1/10 for smoother plans.
ROBOTS: dict[str, RobotSpec] = {
    "panda": RobotSpec(
        "panda", "robots/panda/panda.sdf", "panda_link0",
        arms={"panda": ArmSpec(
            joints=tuple(f"panda_joint{i}" for i in range(1, 8)), flange="panda_link8",
            X_FG_rpy_xyz=((0, 0, np.pi / 4), (0, 0, 0)), default_gripper="parallel_jaw",
            velocity_limits=(2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61),
            acceleration_limits=(15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0),
            jerk_limits=(750.0, 375.0, 500.0, 625.0, 750.0, 1000.0, 1000.0),
            home=(0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785))},  # Franka's "ready" pose
    ),
    "yumi": RobotSpec(
        "yumi", "robots/yumi/yumi.sdf", "yumi_body",
        # Homes: tools pointing down 30 cm above the near half of a bin 0.55 m in front (by IK).
        arms={"yumi_right": _yumi_arm("r", "parallel_jaw", (-1.109, -0.708, 0.322, 1.067, 0.532, 0.116, 0.851)),
              "yumi_left": _yumi_arm("l", "suction_cup", (0.558, -0.759, -0.017, 1.074, 0.99, 0.378, 0.816))},
    ),
    "fetch": RobotSpec(
        "fetch", "robots/fetch/fetch.sdf", "base_origin",
        arms={"fetch": ArmSpec(
            joints=("torso_lift_joint", "shoulder_pan_joint", "shoulder_lift_joint", "upperarm_roll_joint",
                    "elbow_flex_joint", "forearm_roll_joint", "wrist_flex_joint", "wrist_roll_joint"),
            flange="wrist_flange", X_FG_rpy_xyz=((0, np.pi / 2, 0), (0, 0, 0)), default_gripper="bluction",
            velocity_limits=(0.1, 1.256, 1.454, 1.571, 1.521, 1.571, 2.268, 2.268),
            # fetch_description gives no acceleration limits; conservative choices (MoveIt config
            # of the Fetch uses 1.5 rad/s^2 for the arm).
            acceleration_limits=(0.5, 1.5, 1.5, 1.5, 1.5, 1.5, 2.5, 2.5),
            jerk_limits=(5.0, 15.0, 15.0, 15.0, 15.0, 15.0, 25.0, 25.0),
            # Home: torso down, tool level and pointing forward, blade down, tip 0.9 m ahead of
            # the base and 1.04 m above its floor (at the front of the FetchShelf shelf, by IK).
            home=(0.039, 0.498, -0.06, 0.607, -2.227, -0.468, 1.938, 0.707))},
        other_joints=("base_x", "base_y", "base_yaw", "head_pan_joint", "head_tilt_joint"),
    ),
}


def robot_spec(name: str) -> RobotSpec:
    if name not in ROBOTS:
        raise ScenarioError(f"unknown robot {name!r}; valid robots: {', '.join(sorted(ROBOTS))} "
                            "(or a floating gripper via add_floating_gripper)")
    return ROBOTS[name]


def _add_file(parser, path):
    """Parse one model file with auto-renaming on (several grippers of one kind may coexist),
    restoring the parser's previous auto-renaming setting."""
    from ms_drake.errors import ModelNotFoundError

    if not path.is_file():
        raise ModelNotFoundError(f"model file {path} is missing; regenerate it (robots: python -m "
                                 "ms_drake.station.convert_robots; grippers: python -m ms_drake.station.grippers)")
    old = parser.GetAutoRenaming()
    parser.SetAutoRenaming(True)
    try:
        (instance,) = parser.AddModels(str(path))
    finally:
        parser.SetAutoRenaming(old)
    return instance


def add_robot(plant, parser, robot_name: str, X_WR=None, model_name: str | None = None):
    """Add robot `robot_name`, weld its root to the world at X_WR; returns its ModelInstanceIndex."""
    from pydrake.math import RigidTransform

    spec = robot_spec(robot_name)
    instance = _add_file(parser, models_dir() / spec.file)
    if model_name is not None:
        plant.RenameModelInstance(instance, model_name)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(spec.root, instance),
                     X_WR if X_WR is not None else RigidTransform())
    exclude_close_link_collisions(plant, parser, instance)
    return instance


def exclude_close_link_collisions(plant, parser, instance, levels: int = 3):
    """Filter collisions between each link of `instance` and its `levels` nearest ancestors.

    The links' collision geometry are convex hulls, which overlap near joints (e.g. YuMi link 2
    and link 4 at 5 mm in ordinary poses) where the real links cannot touch; without the filter
    the simulated arm would fight phantom self-contacts. Links further apart along the chain
    (the two YuMi arms, the Fetch arm and its base) still collide."""
    sg = parser.scene_graph()
    if sg is None or not plant.geometry_source_is_registered():
        return
    from pydrake.geometry import CollisionFilterDeclaration

    parent = {}
    for j in plant.GetJointIndices(instance):
        joint = plant.get_joint(j)
        parent[int(joint.child_body().index())] = joint.parent_body()
    world = int(plant.world_body().index())
    manager = sg.collision_filter_manager()
    for b in plant.GetBodyIndices(instance):
        chain, body = [plant.get_body(b)], plant.get_body(b)
        for _ in range(levels):
            up = parent.get(int(body.index()))
            if up is None or int(up.index()) == world:
                break
            chain.append(up)
            body = up
        if len(chain) > 1:
            manager.Apply(CollisionFilterDeclaration().ExcludeWithin(plant.CollectRegisteredGeometries(chain)))


def add_gripper(plant, parser, gripper_name: str, weld_to_frame, X_FG=None, model_name: str | None = None):
    """Add gripper `gripper_name` and weld its `body` to `weld_to_frame` at X_FG."""
    from pydrake.math import RigidTransform

    spec = gripper_spec(gripper_name)
    instance = _add_file(parser, models_dir() / spec.file)
    if model_name is not None:
        plant.RenameModelInstance(instance, model_name)
    plant.WeldFrames(weld_to_frame, plant.GetFrameByName("body", instance),
                     X_FG if X_FG is not None else RigidTransform())
    return instance


def add_arm_gripper(plant, parser, robot_instance, robot_name: str, arm: str, gripper_name: str | None = None,
                    model_name: str | None = None):
    """Weld the arm's (default) gripper to its flange with the documented X_FG."""
    spec = robot_spec(robot_name)
    if arm not in spec.arms:
        raise ScenarioError(f"robot {robot_name!r} has no arm {arm!r}; arms: {', '.join(spec.arms)}")
    a = spec.arms[arm]
    flange = plant.GetFrameByName(a.flange, robot_instance)
    gripper = add_gripper(plant, parser, gripper_name or a.default_gripper, flange, a.X_FG(), model_name)
    exclude_gripper_wrist_collisions(plant, parser, gripper, flange.body())
    return gripper


def exclude_gripper_wrist_collisions(plant, parser, gripper_instance, flange_body, levels: int = 3):
    """Filter collisions between the gripper's bodies and the last `levels` links of the arm (the
    flange body and its parents): their convex hulls overlap by construction at the mount."""
    sg = parser.scene_graph()
    if sg is None or not plant.geometry_source_is_registered():
        return
    from pydrake.geometry import CollisionFilterDeclaration

    wrist, body = [], flange_body
    for _ in range(levels):
        wrist.append(body)
        joint = next((plant.get_joint(j) for j in plant.GetJointIndices(body.model_instance())
                      if plant.get_joint(j).child_body().index() == body.index()), None)
        if joint is None or joint.parent_body().index() == plant.world_body().index():
            break
        body = joint.parent_body()
    tool = [plant.get_body(b) for b in plant.GetBodyIndices(gripper_instance)]
    sg.collision_filter_manager().Apply(CollisionFilterDeclaration().ExcludeBetween(
        plant.CollectRegisteredGeometries(wrist), plant.CollectRegisteredGeometries(tool)))


def add_floating_gripper(plant, parser, gripper_name: str, X_WB=None, model_name: str | None = None):
    """A gripper on 6 PD-actuated joints (x, y, z, roll, pitch, yaw) welded to the world at X_WB.

    Returns (base_instance, gripper_instance). Drive the base through
    plant.get_desired_state_input_port(base_instance) ([q(6), v(6)]) on a discrete SAP plant.
    """
    from pydrake.math import RigidTransform

    base = _add_file(parser, models_dir() / "grippers" / "floating_base.sdf")
    if model_name is not None:
        plant.RenameModelInstance(base, f"{model_name}_base")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("floating_origin_link", base),
                     X_WB if X_WB is not None else RigidTransform())
    gripper = add_gripper(plant, parser, gripper_name, plant.GetFrameByName("floating_yaw_link", base),
                          model_name=model_name)
    return base, gripper


FLOATING_JOINTS = ("floating_x", "floating_y", "floating_z", "floating_roll", "floating_pitch", "floating_yaw")


def floating_gripper_positions(X_WG) -> np.ndarray:
    """Joint positions [x, y, z, roll, pitch, yaw] of the floating base that put the gripper's
    `body` frame at X_WG. The revolute chain is roll about x, then pitch about the rolled y, then
    yaw about the resulting z, so R_WG = Rx(roll) Ry(pitch) Rz(yaw) (intrinsic x-y-z Euler angles,
    not Drake's extrinsic RollPitchYaw)."""
    from scipy.spatial.transform import Rotation

    R = X_WG.rotation().matrix()
    rpy = Rotation.from_matrix(R).as_euler("XYZ")
    return np.concatenate([X_WG.translation(), rpy])


# ----------------------------------------------------------------------------- stations
# The floating gripper as a one-arm "robot" for stations: arm `floating` = the 6 base joints.
# Its limits for trajectory timing are choices (a fast but not violent gripper).
FLOATING_ARM = ArmSpec(
    joints=FLOATING_JOINTS, flange="floating_yaw_link", X_FG_rpy_xyz=((0, 0, 0), (0, 0, 0)),
    default_gripper="parallel_jaw",
    velocity_limits=(1.0, 1.0, 1.0, 3.0, 3.0, 3.0), acceleration_limits=(3.0, 3.0, 3.0, 8.0, 8.0, 8.0),
    jerk_limits=(30.0, 30.0, 30.0, 80.0, 80.0, 80.0),
    home=(0.0, 0.0, 0.45, np.pi, 0.0, 0.0))  # 0.45 m above the base origin, pointing down
FLOATING = RobotSpec("floating", "grippers/floating_base.sdf", "floating_origin_link", arms={"floating": FLOATING_ARM})
STATION_ROBOTS = ("fetch", "floating", "panda", "yumi")


def station_robot_spec(name: str) -> RobotSpec:
    """robot_spec for stations, including the `floating` gripper."""
    if name == "floating":
        return FLOATING
    if name not in ROBOTS:
        raise ScenarioError(f"robot.name: unknown robot {name!r}; valid robots: {', '.join(STATION_ROBOTS)}")
    return ROBOTS[name]


def station_arm_spec(arm: str) -> ArmSpec:
    """The ArmSpec of a station arm by its port name (panda, yumi_right, yumi_left, fetch, floating)."""
    for name in STATION_ROBOTS:
        spec = station_robot_spec(name)
        if arm in spec.arms:
            return spec.arms[arm]
    raise ScenarioError(f"unknown arm {arm!r}; arms: "
                        f"{', '.join(a for n in STATION_ROBOTS for a in station_robot_spec(n).arms)}")


def arm_joint_limits(arm: str, scale: float = 1.0):
    """planning.JointLimits (velocity, acceleration, jerk) of a station arm, velocity and
    acceleration scaled by `scale`."""
    from ms_drake.planning import JointLimits

    a = station_arm_spec(arm)
    return JointLimits(np.array(a.velocity_limits) * scale, np.array(a.acceleration_limits) * scale,
                       np.array(a.jerk_limits) * scale)


def resolve_robot_config(robot_config):
    """Check a scenario's RobotConfig; returns [(arm, gripper name, gripper port)] and the
    driver of every port prefix ({prefix: driver dataclass}, defaults filled in).

    Errors (ScenarioError) name the key, the bad value and the valid names."""
    from ms_drake.scenario import ArmDriver, JawDriver, SuctionDriver
    from ms_drake.station.drivers import gripper_port_name
    from ms_drake.station.grippers import GRIPPERS

    spec = station_robot_spec(robot_config.name)
    arms = list(spec.arms)
    names = list(robot_config.grippers)
    if len(names) > len(arms):
        raise ScenarioError(f"robot.grippers: {names} lists {len(names)} grippers but {robot_config.name!r} has "
                            f"{len(arms)} arm(s) ({', '.join(arms)}); give one gripper per arm, in that order")
    chosen = []
    for i, arm in enumerate(arms):
        g = names[i] if i < len(names) else spec.arms[arm].default_gripper
        if g not in GRIPPERS:
            raise ScenarioError(f"robot.grippers[{i}]: unknown gripper {g!r}; valid grippers: "
                                f"{', '.join(sorted(GRIPPERS))}")
        chosen.append((arm, g, gripper_port_name(arm, GRIPPERS[g].kind)))
    wanted = {arm: ArmDriver for arm in arms}
    wanted.update({port: JawDriver if GRIPPERS[g].kind == "parallel_jaw" else SuctionDriver
                   for _, g, port in chosen})
    drivers = {}
    for key, d in robot_config.drivers.items():
        if key not in wanted:
            raise ScenarioError(f"robot.drivers: no arm or gripper named {key!r} on {robot_config.name!r}; "
                                f"valid driver names: {', '.join(wanted)}")
        if not isinstance(d, wanted[key]):
            raise ScenarioError(f"robot.drivers.{key}: a {type(d).__name__} cannot drive {key!r}; "
                                f"use !{wanted[key].__name__}")
        drivers[key] = d
    for key, cls in wanted.items():
        drivers.setdefault(key, cls())
    for arm in arms:
        kp = drivers[arm].kp
        n = len(spec.arms[arm].joints)
        if kp and (len(kp) != n or min(kp) <= 0):
            raise ScenarioError(f"robot.drivers.{arm}.kp: give {n} positive stiffnesses (one per joint of "
                                f"{', '.join(spec.arms[arm].joints)}) or [] for the defaults; got {list(kp)}")
        if drivers[arm].damping_ratio < 0:
            raise ScenarioError(f"robot.drivers.{arm}.damping_ratio: must be >= 0, got {drivers[arm].damping_ratio}")
    return chosen, drivers


def base_transform(robot_config):
    """X_WR of the robot's root from base_position and base_yaw [deg]."""
    from pydrake.math import RigidTransform, RollPitchYaw

    if len(robot_config.base_position) != 3:
        raise ScenarioError(f"robot.base_position: give [x, y, z] in metres, got {list(robot_config.base_position)}")
    return RigidTransform(RollPitchYaw(0, 0, np.deg2rad(robot_config.base_yaw)), list(robot_config.base_position))


def add_robot_from_scenario(builder, plant, scene_graph, scenario, parser):
    """Add the scenario's robot and grippers to `plant` (before Finalize) at their home
    configuration; returns the RobotHandle that apply_drivers completes after Finalize.

    Model instance names: the robot keeps its file's model name (panda, yumi, fetch); grippers
    are named by their port prefix (e.g. yumi_right_jaw); the floating gripper's base is
    `<port>_base` (e.g. floating_jaw_base)."""
    from ms_drake.station.drivers import ArmHandle, GripperHandle, RobotHandle
    from ms_drake.station.grippers import GRIPPERS

    rc = scenario.robot
    chosen, drivers = resolve_robot_config(rc)
    spec = station_robot_spec(rc.name)
    X_WR = base_transform(rc)
    if rc.name == "floating":
        (arm, g, port), = chosen
        instance, grip = add_floating_gripper(plant, parser, g, X_WR, model_name=port)
        grippers = [GripperHandle(port, g, GRIPPERS[g].kind, grip, arm, drivers[port])]
    else:
        instance = add_robot(plant, parser, rc.name, X_WR)
        grippers = [GripperHandle(port, g, GRIPPERS[g].kind,
                                  add_arm_gripper(plant, parser, instance, rc.name, arm, g, model_name=port),
                                  arm, drivers[port]) for arm, g, port in chosen]
    arms = [ArmHandle(a, instance, spec.arms[a].joints, drivers[a]) for a in spec.arms]
    set_home(plant, instance, spec)
    arm_joints = {n for a in arms for n in a.joints}
    hold = tuple(plant.get_joint(j).name() for j in plant.GetJointIndices(instance)
                 if plant.get_joint(j).num_velocities() == 1 and plant.get_joint(j).name() not in arm_joints)
    return RobotHandle(rc.name, instance, X_WR, arms, grippers, hold)


def set_home(plant, instance, spec: RobotSpec):
    """Default positions of every arm: ArmSpec.home, or zeros clipped into the joint limits."""
    for arm in spec.arms.values():
        for k, n in enumerate(arm.joints):
            joint = plant.GetJointByName(n, instance)
            q = arm.home[k] if arm.home else 0.0
            lo, hi = joint.position_lower_limits()[0], joint.position_upper_limits()[0]
            joint.set_default_positions([float(np.clip(q, lo, hi))])


def apply_drivers(builder, plant, scene_graph, scenario, handle, lcm=None):
    """Wire the drivers of `handle` (after Finalize) and export the robot's ports.

    The simulated station talks to nothing over LCM (`lcm` is accepted for MakeStation's
    signature and ignored); hardware.MakeEmulatedRobot puts a simulated station on a bus."""
    from ms_drake.station import drivers

    if plant.time_step() <= 0:
        raise ScenarioError("plant_config.time_step: the robot drivers use the plant's PD controllers, which "
                            "need a discrete plant; set time_step > 0 (e.g. 0.002)")
    if plant.get_discrete_contact_approximation().name == "kTamsi":
        raise ScenarioError("plant_config.discrete_contact_approximation: the robot drivers need sap, similar or "
                            "lagged (PD-controlled actuators); tamsi does not support them")
    drivers.apply_drivers(builder, plant, scene_graph, handle)
