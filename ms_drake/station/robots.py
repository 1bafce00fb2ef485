"""Adding robots and grippers to a MultibodyPlant: the functions MakeStation calls.

    add_robot(plant, parser, "panda")                       -> ModelInstanceIndex (root welded)
    add_gripper(plant, parser, "parallel_jaw", frame)       -> ModelInstanceIndex (welded to frame)
    add_floating_gripper(plant, parser, "suction_cup")      -> (base instance, gripper instance)
    robot_spec("yumi").arms["yumi_right"].joints            -> joint names in command order
Stations (MakeStation calls these):
    add_robot_from_scenario(builder, plant, scene_graph, scenario, parser) -> RobotHandle (before Finalize)
    drivers.apply_robot_drivers(builder, plant, scene_graph, handle)        (after Finalize)
    resolve_robot_config(scenario.robot) -> [(arm, gripper, port)], {port prefix: driver}
    station_robot_spec("floating"), station_arm_spec("yumi_left"), arm_joint_limits("fetch")
Every arm starts at ArmSpec.home (set_home), the Fetch at a shelf at SHELF_PARK; the floating gripper 0.45 m above its base origin,
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
from pydrake.geometry import CollisionFilterDeclaration
from pydrake.math import RigidTransform, RollPitchYaw
from scipy.spatial.transform import Rotation

from ms_drake.errors import ModelNotFoundError, ScenarioError
from ms_drake.geometry import as_rigid_transform, transform_from_rpy_xyz
from ms_drake.paths import models_dir
from ms_drake.robots import (
    GRIPPERS,
    RobotSpec,
    gripper_spec,
    robot_spec,
    station_robot_spec,
)
from ms_drake.scenario import resolve_robot_config


def _add_file(parser, path):
    """Parse one model file with auto-renaming on (several grippers of one kind may coexist),
    restoring the parser's previous auto-renaming setting."""
    if not path.is_file():
        raise ModelNotFoundError(f"model file {path} is missing; regenerate it (robots: python -m "
                                 "tools.convert_robots; grippers: python -m tools.write_models)")
    old = parser.GetAutoRenaming()
    parser.SetAutoRenaming(True)
    text = path.read_text()
    try:
        if path.suffix == ".sdf" and "<uri>" not in text and "<include" not in text:
            # Self-contained SDF (the grippers, the floating base): parsed from its text. Drake's
            # vendored sdformat rebuilds its whole schema for every file it reads (~20 ms per
            # file, measured), and once per process for strings (~0.5 ms per model after that).
            (instance,) = parser.AddModelsFromString(text, "sdf")
        else:  # relative mesh URIs and includes resolve against the file's folder
            (instance,) = parser.AddModels(str(path))
    finally:
        parser.SetAutoRenaming(old)
    return instance


def add_robot(plant, parser, robot_name: str, X_WR=None, model_name: str | None = None):
    """Add robot `robot_name`, weld its root to the world at X_WR (RigidTransform or 4x4 array;
    default identity); returns its ModelInstanceIndex."""
    X_WR = RigidTransform() if X_WR is None else as_rigid_transform(X_WR, "X_WR")
    spec = robot_spec(robot_name)
    instance = _add_file(parser, models_dir() / spec.file)
    if model_name is not None:
        plant.RenameModelInstance(instance, model_name)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(spec.root, instance), X_WR)
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
    """Add gripper `gripper_name` and weld its `body` to `weld_to_frame` at X_FG (RigidTransform or
    4x4 array; default identity)."""
    X_FG = RigidTransform() if X_FG is None else as_rigid_transform(X_FG, "X_FG")
    spec = gripper_spec(gripper_name)
    instance = _add_file(parser, models_dir() / spec.file)
    if model_name is not None:
        plant.RenameModelInstance(instance, model_name)
    plant.WeldFrames(weld_to_frame, plant.GetFrameByName("body", instance), X_FG)
    return instance


def add_arm_gripper(plant, parser, robot_instance, robot_name: str, arm: str, gripper_name: str | None = None,
                    model_name: str | None = None):
    """Weld the arm's (default) gripper to its flange with the documented X_FG."""
    spec = robot_spec(robot_name)
    if arm not in spec.arms:
        raise ScenarioError(f"robot {robot_name!r} has no arm {arm!r}; arms: {', '.join(spec.arms)}")
    a = spec.arms[arm]
    flange = plant.GetFrameByName(a.flange, robot_instance)
    gripper = add_gripper(plant, parser, gripper_name or a.default_gripper, flange, transform_from_rpy_xyz(*a.X_FG_rpy_xyz), model_name)
    exclude_gripper_wrist_collisions(plant, parser, gripper, flange.body())
    return gripper


def exclude_gripper_wrist_collisions(plant, parser, gripper_instance, flange_body, levels: int = 3):
    """Filter collisions between the gripper's bodies and the last `levels` links of the arm (the
    flange body and its parents): their convex hulls overlap by construction at the mount."""
    sg = parser.scene_graph()
    if sg is None or not plant.geometry_source_is_registered():
        return

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
    X_WB: RigidTransform or 4x4 array (default identity).
    """
    X_WB = RigidTransform() if X_WB is None else as_rigid_transform(X_WB, "X_WB")
    base = _add_file(parser, models_dir() / "grippers" / "floating_base.sdf")
    if model_name is not None:
        plant.RenameModelInstance(base, f"{model_name}_base")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("floating_origin_link", base), X_WB)
    gripper = add_gripper(plant, parser, gripper_name, plant.GetFrameByName("floating_yaw_link", base),
                          model_name=model_name)
    return base, gripper





def floating_gripper_positions(X_WG) -> np.ndarray:
    """Joint positions [x, y, z, roll, pitch, yaw] of the floating base that put the gripper's
    `body` frame at X_WG. The revolute chain is roll about x, then pitch about the rolled y, then
    yaw about the resulting z, so R_WG = Rx(roll) Ry(pitch) Rz(yaw) (intrinsic x-y-z Euler angles,
    not Drake's extrinsic RollPitchYaw). X_WG: RigidTransform or 4x4 array."""
    X_WG = as_rigid_transform(X_WG, "X_WG")
    R = X_WG.rotation().matrix()
    rpy = Rotation.from_matrix(R).as_euler("XYZ")
    return np.concatenate([X_WG.translation(), rpy])


def base_transform(robot_config):
    """X_WR of the robot's root from base_position and base_yaw [deg]."""
    if len(robot_config.base_position) != 3:
        raise ScenarioError(f"robot.base_position: give [x, y, z] in metres, got {list(robot_config.base_position)}")
    return RigidTransform(RollPitchYaw(0, 0, np.deg2rad(robot_config.base_yaw)), list(robot_config.base_position))


@dataclass
class ArmHandle:
    """One arm of a station: its joints (command order) and their limits, PD gains, driver."""

    name: str
    robot_instance: object
    joints: tuple[str, ...]
    driver: object  # ms_drake.scenario.ArmDriver
    lower: np.ndarray = None
    upper: np.ndarray = None
    velocity: np.ndarray = None
    kp: np.ndarray = None
    kd: np.ndarray = None


@dataclass
class GripperHandle:
    """One gripper: its port prefix, registry name and kind, model instance, arm, driver."""

    port: str
    name: str
    kind: str
    instance: object
    arm: str
    driver: object


@dataclass
class RobotHandle:
    """What add_robot_from_scenario built (before Finalize); drivers.apply_robot_drivers completes it."""

    robot: str
    instance: object  # the robot's model instance (the floating base for `floating`)
    X_WR: object
    arms: list = field(default_factory=list)
    grippers: list = field(default_factory=list)
    hold_joints: tuple = ()  # joints of `instance` outside every arm, held at their defaults


def add_robot_from_scenario(builder, plant, scene_graph, scenario, parser):
    """Add the scenario's robot and grippers to `plant` (before Finalize) at their home
    configuration; returns the RobotHandle that drivers.apply_robot_drivers completes after Finalize.

    Model instance names: the robot keeps its file's model name (panda, yumi, fetch); grippers
    are named by their port prefix (e.g. yumi_right_jaw); the floating gripper's base is
    `<port>_base` (e.g. floating_jaw_base)."""
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
    if scenario.environment.type == "shelf" and rc.name in SHELF_PARK:
        for n, v in zip(spec.arms[rc.name].joints, SHELF_PARK[rc.name]):
            plant.GetJointByName(n, instance).set_default_positions([v])
    arm_joints = {n for a in arms for n in a.joints}
    hold = tuple(plant.get_joint(j).name() for j in plant.GetJointIndices(instance)
                 if plant.get_joint(j).num_velocities() == 1 and plant.get_joint(j).name() not in arm_joints)
    return RobotHandle(rc.name, instance, X_WR, arms, grippers, hold)


#: At a shelf, the Fetch starts parked out of the front camera's view: the bluction tool level and
#: pointing into the shelf, its tip 6 cm in front of the shelf's front plane and 6 cm below its
#: floor, the torso at 0.2 m, every link >= 2 cm from the robot's others (by IK; tests/test_shelf_fetch.py).
SHELF_PARK = {"fetch": (0.201, 1.453, 1.024, -0.459, 1.873, -1.733, 1.253, -0.204)}


def set_home(plant, instance, spec: RobotSpec):
    """Default positions of every arm: ArmSpec.home, or zeros clipped into the joint limits."""
    for arm in spec.arms.values():
        for k, n in enumerate(arm.joints):
            joint = plant.GetJointByName(n, instance)
            q = arm.home[k] if arm.home else 0.0
            lo, hi = joint.position_lower_limits()[0], joint.position_upper_limits()[0]
            joint.set_default_positions([float(np.clip(q, lo, hi))])


def set_arm_positions(plant, plant_context, robot_name: str, commands: dict) -> None:
    """Put every arm of `robot_name` whose `<arm>.position` is in `commands` at that position
    (e.g. a controller's initial commands, so a simulation starts where the controller expects
    its robot: parked out of the camera's view)."""
    q = plant.GetPositions(plant_context)
    for arm, a in station_robot_spec(robot_name).arms.items():
        if f"{arm}.position" in commands:
            for name, v in zip(a.joints, np.atleast_1d(commands[f"{arm}.position"])):
                q[plant.GetJointByName(name).position_start()] = v
    plant.SetPositions(plant_context, q)
