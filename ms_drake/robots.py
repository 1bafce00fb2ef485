"""Robot, arm and gripper tables: Drake-free data that scenarios, stations and planners read.

    robot_spec("yumi").arms["yumi_right"].joints   -> joint names in command order
    station_robot_spec("floating"), station_arm_spec("yumi_left"), arm_joint_limits("fetch")
    gripper_spec("parallel_jaw"), gripper_port_name("yumi_right", "parallel_jaw") -> "yumi_right_jaw"
    PadConfig, ParallelJawConfig, SuctionCupConfig, BluctionConfig: gripper geometry and contact
    parameters (the station writes its gripper models from them; the grasp physics uses the same pads)

Weld conventions (the flange frame F of each arm and X_FG, flange to the gripper's `body` frame G
whose +z is the approach direction) are documented in ms_drake/station/robots.py, which builds
the plant from these tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ms_drake.errors import ScenarioError
from ms_drake.types import JointLimits


@dataclass(frozen=True)
class PadConfig:
    """A compliant jaw pad: a polygon in the pad plane extruded along the closing axis.

    polygon: convex outline (u, v) [m], u along the gripper y axis, v along the approach z,
        centred on the pad centre. None -> rectangle `width` x `length` (written as a box).
    thickness: extrusion along x [m] (the compliant layer).
    hydroelastic_modulus [Pa]: 1e5-1e6 for rubber-like pads.
    relaxation_time [s]: dissipation under SAP. hunt_crossley_dissipation [s/m]: under TAMSI.
    mu_static, mu_dynamic: Coulomb friction of the pad.
    resolution_hint [m]: tetrahedral mesh size for non-box pads.
    """

    polygon: tuple[tuple[float, float], ...] | None = None
    width: float = 0.02
    length: float = 0.03
    thickness: float = 0.006
    hydroelastic_modulus: float = 3e5
    relaxation_time: float = 0.1
    hunt_crossley_dissipation: float = 5.0
    mu_static: float = 1.0
    mu_dynamic: float = 0.9
    resolution_hint: float = 0.004

    def __post_init__(self):
        for name in ("width", "length", "thickness", "hydroelastic_modulus", "resolution_hint"):
            if getattr(self, name) <= 0:
                raise ScenarioError(f"PadConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.mu_dynamic > self.mu_static or self.mu_dynamic < 0:
            raise ScenarioError("PadConfig: need 0 <= mu_dynamic <= mu_static "
                                f"(got mu_static={self.mu_static}, mu_dynamic={self.mu_dynamic})")
        if self.polygon is not None and len(self.polygon) < 3:
            raise ScenarioError("PadConfig.polygon needs at least 3 (u, v) points")



# f_C [N]: the parallel jaw's closing force the jaw grasp models assume by default
# (grasping.evaluator); the full-fidelity stations grip with it (FullBackend.grip_force), so a
# grasp is executed with the force it was scored at.
CLOSING_FORCE = 10.0


@dataclass(frozen=True)
class ParallelJawConfig:
    """Parallel-jaw gripper geometry; defaults are close to the YuMi smart gripper's size."""

    pads: PadConfig = field(default_factory=PadConfig)
    max_opening: float = 0.10  # [m] between pad faces
    max_force: float = 40.0  # [N] per finger (actuator effort limit)
    palm_size: tuple[float, float, float] = (0.13, 0.05, 0.05)  # x, y, z
    finger_length: float = 0.06  # along z, below the palm
    finger_thickness: float = 0.012  # along x
    finger_depth: float = 0.02  # along y
    palm_mass: float = 0.25
    finger_mass: float = 0.03

    def __post_init__(self):
        if self.max_opening <= 0 or self.max_force <= 0:
            raise ScenarioError("ParallelJawConfig: max_opening and max_force must be > 0")
        if self.pads.length > self.finger_length:
            raise ScenarioError("ParallelJawConfig: pad length exceeds finger_length")


@dataclass(frozen=True)
class PickApproach:
    """How a station's gripper comes down to a grasp, shared by the grasp planners' free check and
    the stations' pick plans (ms_drake.planning.sequences.plan_pick): straight down from above the
    heap to the pre-grasp, `distance` back along the tool axis from the grasp, then straight along
    the axis to it. On the way down the tool keeps `descent_clearance` from everything; on the
    approach it may not touch anything before contact."""

    distance: float = 0.10  # [m] the straight approach along the tool axis
    descent_clearance: float = 0.005  # [m]
    steps: int = 4  # tool poses checked along the approach, besides the grasp's own


PICK_APPROACH = PickApproach()


@dataclass(frozen=True)
class SuctionCupConfig:
    """Suction tool: a stem (cylinder) ending in a cup of radius `cup_radius`."""

    cup_radius: float = 0.015
    cup_height: float = 0.012
    stem_radius: float = 0.01
    stem_length: float = 0.10
    mass: float = 0.15
    cup_modulus: float = 2e5  # compliant cup lip
    relaxation_time: float = 0.1
    mu: float = 1.0


@dataclass(frozen=True)
class BluctionConfig:
    """Bluction tool of the Fetch (reference Ch. 9.3)."""

    shaft_length: float = 0.40
    shaft_diameter: float = 0.03
    blade_width: float = 0.065  # along the shaft
    blade_height: float = 0.075  # radial, away from the shaft
    blade_thickness: float = 0.004
    cup_diameter: float = 0.03
    cup_height: float = 0.012
    blade_offset: float = 0.06  # blade centre, measured back from the shaft tip
    mass_shaft: float = 0.2
    mass_blade: float = 0.05
    cup_modulus: float = 2e5
    relaxation_time: float = 0.1
    mu: float = 0.8


# ----------------------------------------------------------------------------- helpers


@dataclass(frozen=True)
class GripperSpec:
    """What the station needs to know about a gripper model."""

    name: str
    file: str  # relative to models/
    kind: str  # parallel_jaw | suction | bluction
    tcp_frame: str = "tcp"
    finger_joints: tuple[str, ...] = ()
    suction_radius: float = 0.0
    extra_joints: tuple[str, ...] = ()


GRIPPERS: dict[str, GripperSpec] = {
    "parallel_jaw": GripperSpec("parallel_jaw", "grippers/parallel_jaw.sdf", "parallel_jaw",
                                finger_joints=("left_finger_sliding_joint", "right_finger_sliding_joint")),
    "suction_cup": GripperSpec("suction_cup", "grippers/suction_cup.sdf", "suction",
                               suction_radius=SuctionCupConfig().cup_radius),
    "bluction": GripperSpec("bluction", "grippers/bluction.sdf", "bluction",
                            suction_radius=BluctionConfig().cup_diameter / 2, extra_joints=("blade_joint",)),
}


def gripper_spec(name: str) -> GripperSpec:
    if name not in GRIPPERS:
        raise ScenarioError(f"unknown gripper {name!r}; valid grippers: {', '.join(sorted(GRIPPERS))}")
    return GRIPPERS[name]


GRIPPER_SHORT_NAMES = {"parallel_jaw": "jaw", "suction": "suction", "bluction": "bluction"}


def gripper_port_name(arm: str, gripper_kind: str) -> str:
    """Port prefix of the gripper on `arm`: <arm>_jaw | <arm>_suction | <arm>_bluction."""
    return f"{arm}_{GRIPPER_SHORT_NAMES[gripper_kind]}"


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
        # Homes (the park at a bin station, by IK): tools pointing down,
        # tcps 0.25 m in front of the base, 0.30 m to either side, 0.30 m up -- out of the
        # overhead camera's view of a bin whose centre is 0.45 m in front (YuMiBin); every
        # joint at least 0.3 rad from its limits.
        arms={"yumi_right": _yumi_arm("r", "parallel_jaw", (-0.541, -0.79, -0.897, 1.041, -0.024, 0.114, 0.521)),
              "yumi_left": _yumi_arm("l", "suction_cup", (0.307, -1.184, 0.906, 1.081, 1.257, 0.486, 1.46))},
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


FLOATING_JOINTS = ("floating_x", "floating_y", "floating_z", "floating_roll", "floating_pitch", "floating_yaw")


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
    a = station_arm_spec(arm)
    return JointLimits(np.array(a.velocity_limits) * scale, np.array(a.acceleration_limits) * scale,
                       np.array(a.jerk_limits) * scale)
