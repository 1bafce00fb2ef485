"""Adding robots and grippers to a MultibodyPlant: the functions MakeStation calls.

    add_robot(plant, parser, "panda")                       -> ModelInstanceIndex (root welded)
    add_gripper(plant, parser, "parallel_jaw", frame)       -> ModelInstanceIndex (welded to frame)
    add_floating_gripper(plant, parser, "suction_cup")      -> (base instance, gripper instance)
    robot_spec("yumi").arms["yumi_right"].joints            -> joint names in command order

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


def _yumi_arm(side: str, gripper: str) -> ArmSpec:
    joints = tuple(f"yumi_joint_{n}_{side}" for n in (1, 2, 7, 3, 4, 5, 6))
    return ArmSpec(
        joints=joints, flange=f"yumi_link_7_{side}", X_FG_rpy_xyz=((0, 0, np.pi), (0, 0, 0.007)),
        default_gripper=gripper,
        velocity_limits=(3.1416, 3.1416, 3.1416, 3.1416, 6.9813, 6.9813, 6.9813),
        # Not published by ABB; conservative values chosen for smooth motion (about 1/2 s to full speed).
        acceleration_limits=(6.0, 6.0, 6.0, 6.0, 12.0, 12.0, 12.0),
        jerk_limits=(60.0, 60.0, 60.0, 60.0, 120.0, 120.0, 120.0),
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
            jerk_limits=(750.0, 375.0, 500.0, 625.0, 750.0, 1000.0, 1000.0))},
    ),
    "yumi": RobotSpec(
        "yumi", "robots/yumi/yumi.sdf", "yumi_body",
        arms={"yumi_right": _yumi_arm("r", "parallel_jaw"), "yumi_left": _yumi_arm("l", "suction_cup")},
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
            jerk_limits=(5.0, 15.0, 15.0, 15.0, 15.0, 15.0, 25.0, 25.0))},
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
    return instance


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
