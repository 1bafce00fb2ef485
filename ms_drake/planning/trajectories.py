"""Time-optimal joint trajectories with ruckig, under per-robot velocity/acceleration/jerk limits.

* Limits are `ms_drake.types.JointLimits`; `ms_drake.robots.arm_joint_limits("panda")` reads the
  per-arm table (velocity / acceleration / jerk limits) of ms_drake/robots.py.
* `plan_joint_motion(waypoints, limits)`: rest-to-rest ruckig segments through the waypoints
  (the open-source ruckig has no intermediate waypoints; stopping at each is the safe choice for
  approach / grasp / lift phases that stop anyway).
* `plan_path_motion(qs, limits, ...)`: a densely sampled joint path (e.g. a Cartesian line from
  successive IK solves) timed by one 1-DoF ruckig profile on the path parameter s in [0, 1]; the
  path speed/acceleration/jerk limits are the tightest joint limits divided by max |dq/ds| (and
  the path's Cartesian limits), so every joint stays within its limits.
Both return a `JointTrajectory` (value(t), velocity(t), duration) that `TrajectoryStreamer` plays.
"""

from __future__ import annotations

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from ms_drake.errors import ScenarioError
from ms_drake.types import JointLimits


class JointTrajectory:
    """A sequence of ruckig segments, or a 1-DoF path profile composed with an interpolated path."""

    def __init__(self, segments=None, path_profile=None, path_s=None, path_q=None, q_start=None):
        self._segments = segments or []
        self._starts = np.cumsum([0.0] + [s.duration for s in self._segments])
        self._profile = path_profile
        self._s = path_s
        self._q = path_q
        if path_profile is not None:
            self._duration = path_profile.duration
            self._q0 = path_q[0]
        else:
            self._duration = float(self._starts[-1])
            self._q0 = np.asarray(q_start, float)

    @property
    def duration(self) -> float:
        return self._duration

    def __deepcopy__(self, memo):  # immutable; Drake's AbstractValue copies port values
        return self

    def __copy__(self):
        return self

    def rows(self) -> int:
        return len(self._q0)

    def _path(self, t):
        s, sd, _ = self._profile.at_time(float(np.clip(t, 0, self._duration)))
        s, sd = s[0], sd[0]
        i = int(np.clip(np.searchsorted(self._s, s) - 1, 0, len(self._s) - 2))
        w = (s - self._s[i]) / (self._s[i + 1] - self._s[i])
        dq_ds = (self._q[i + 1] - self._q[i]) / (self._s[i + 1] - self._s[i])
        return self._q[i] + w * (self._q[i + 1] - self._q[i]), dq_ds * sd

    def value(self, t: float) -> np.ndarray:
        if self._profile is not None:
            return self._path(t)[0]
        if not self._segments:
            return self._q0.copy()
        t = float(np.clip(t, 0.0, self._duration))
        i = int(np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, len(self._segments) - 1))
        return np.array(self._segments[i].at_time(t - self._starts[i])[0])

    def velocity(self, t: float) -> np.ndarray:
        if self._profile is not None:
            return self._path(t)[1]
        if not self._segments or t <= 0 or t >= self._duration:
            return np.zeros_like(self._q0)
        i = int(np.clip(np.searchsorted(self._starts, t, side="right") - 1, 0, len(self._segments) - 1))
        return np.array(self._segments[i].at_time(t - self._starts[i])[1])

    def final(self) -> np.ndarray:
        return self.value(self._duration)


def _segment(otg, q0, q1, limits):
    n = len(q0)
    inp = InputParameter(n)
    inp.current_position = list(q0)
    inp.current_velocity = [0.0] * n
    inp.current_acceleration = [0.0] * n
    inp.target_position = list(q1)
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = list(limits.velocity)
    inp.max_acceleration = list(limits.acceleration)
    inp.max_jerk = list(limits.jerk)
    traj = Trajectory(n)
    result = otg.calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise ScenarioError(f"ruckig could not time the segment {q0} -> {q1}: {result}")
    return traj


def plan_joint_motion(waypoints, limits: JointLimits) -> JointTrajectory:
    """Rest-to-rest time-optimal (jerk-limited) motion through `waypoints` (N x dof, N >= 1)."""
    W = np.atleast_2d(np.asarray(waypoints, float))
    if W.shape[1] != len(limits.velocity):
        raise ScenarioError(f"waypoints have {W.shape[1]} joints but the limits have {len(limits.velocity)}")
    otg = Ruckig(W.shape[1])
    segs = [_segment(otg, W[i], W[i + 1], limits) for i in range(len(W) - 1)
            if np.any(np.abs(W[i + 1] - W[i]) > 1e-12)]
    return JointTrajectory(segments=segs, q_start=W[0])


def plan_path_motion(qs, limits: JointLimits, path_length: float | None = None,
                     max_speed: float = 0.25, max_accel: float = 1.0, max_jerk: float = 10.0) -> JointTrajectory:
    """Time a dense joint path `qs` (N x dof) along its path parameter with one ruckig profile.

    path_length [m] with max_speed [m/s], max_accel, max_jerk: Cartesian limits of the tool along
    the path (for a straight line of that length); joint limits are enforced as described above.
    """
    Q = np.asarray(qs, float)
    if len(Q) < 2:
        return JointTrajectory(q_start=Q[0])
    seg = np.linalg.norm(np.diff(Q, axis=0), axis=1) + 1e-12
    s = np.concatenate([[0.0], np.cumsum(seg)])
    s /= s[-1]
    dq_ds = np.abs(np.diff(Q, axis=0) / np.diff(s)[:, None]).max(axis=0) + 1e-12  # per joint
    v = float(np.min(limits.velocity / dq_ds))
    a = float(np.min(limits.acceleration / dq_ds))
    j = float(np.min(limits.jerk / dq_ds))
    if path_length:
        v, a, j = min(v, max_speed / path_length), min(a, max_accel / path_length), min(j, max_jerk / path_length)
    otg = Ruckig(1)
    profile = _segment(otg, [0.0], [1.0], JointLimits(np.array([v]), np.array([a]), np.array([j])))
    return JointTrajectory(path_profile=profile, path_s=s, path_q=Q)
