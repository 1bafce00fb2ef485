"""Motion: IK (Drake InverseKinematics), ruckig timing, Cartesian lines, trajectory streaming."""

from ms_drake.planning.cartesian import (  # noqa: F401
    CartesianPlan,
    approach_pose,
    ik_pose,
    plan_cartesian_line,
)
from ms_drake.planning.ik import ArmIk, IkResult, make_ik_diagram  # noqa: F401
from ms_drake.planning.streamer import DrakeTrajectoryAdapter, TimedTrajectory, TrajectoryStreamer  # noqa: F401
from ms_drake.planning.trajectories import JointTrajectory, plan_joint_motion, plan_path_motion  # noqa: F401
from ms_drake.types import JointLimits  # noqa: F401
