"""TrajectoryStreamer: plays a joint trajectory as commanded positions over time.

Feed `position` to `<arm>.position` of the station. The trajectory comes either from the
`trajectory` input port (an abstract `TimedTrajectory`, e.g. from the action executor) when it is
connected, or from the constructor. Before the start time the first point is held, after the end
the last one; with no trajectory at all `q_hold` is output. Anything with `value(t)`,
`velocity(t)` and `duration` works as the trajectory (JointTrajectory, or a Drake trajectory
through `DrakeTrajectoryAdapter`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem


@dataclass(frozen=True, eq=False)
class TimedTrajectory:
    trajectory: object  # value(t), velocity(t), duration
    start_time: float = 0.0

    def end_time(self) -> float:
        return self.start_time + self.trajectory.duration


class DrakeTrajectoryAdapter:
    """Wrap a pydrake Trajectory (e.g. PiecewisePolynomial) as value/velocity/duration."""

    def __init__(self, traj):
        self._t = traj
        self._d = traj.MakeDerivative()
        self.duration = traj.end_time() - traj.start_time()

    def __deepcopy__(self, memo):  # immutable; Drake's AbstractValue copies port values
        return self

    def value(self, t):
        return self._t.value(self._t.start_time() + np.clip(t, 0, self.duration)).ravel()

    def velocity(self, t):
        if t <= 0 or t >= self.duration:
            return np.zeros(self._t.rows())
        return self._d.value(self._t.start_time() + t).ravel()


class TrajectoryStreamer(LeafSystem):
    """Input ports:
      trajectory  abstract TimedTrajectory (optional; overrides the constructor's trajectory)
    Output ports:
      position    (n) commanded joint positions
      velocity    (n) commanded joint velocities
      done        (1) 1.0 once the current time is past the trajectory's end (or no trajectory)
    """

    def __init__(self, num_joints: int, q_hold=None, trajectory: TimedTrajectory | None = None):
        super().__init__()
        self._in = self.DeclareAbstractInputPort("trajectory", AbstractValue.Make(TimedTrajectory(None)))
        self.DeclareVectorOutputPort("position", num_joints, self._calc_position)
        self.DeclareVectorOutputPort("velocity", num_joints, self._calc_velocity)
        self.DeclareVectorOutputPort("done", 1, self._calc_done)
        self._n = num_joints
        self._q_hold = np.zeros(num_joints) if q_hold is None else np.asarray(q_hold, float)
        if len(self._q_hold) != num_joints:
            raise ValueError(f"TrajectoryStreamer: q_hold has {len(self._q_hold)} entries, expected {num_joints}")
        self._fixed = trajectory

    def _current(self, context) -> TimedTrajectory | None:
        if self._in.HasValue(context):
            tt = self._in.Eval(context)
            if tt is not None and tt.trajectory is not None:
                return tt
        return self._fixed

    def _calc_position(self, context, output):
        tt = self._current(context)
        if tt is None:
            output.SetFromVector(self._q_hold)
            return
        output.SetFromVector(np.asarray(tt.trajectory.value(context.get_time() - tt.start_time), float))

    def _calc_velocity(self, context, output):
        tt = self._current(context)
        if tt is None:
            output.SetFromVector(np.zeros(self._n))
            return
        output.SetFromVector(np.asarray(tt.trajectory.velocity(context.get_time() - tt.start_time), float))

    def _calc_done(self, context, output):
        tt = self._current(context)
        output.SetFromVector([1.0 if tt is None or context.get_time() >= tt.end_time() else 0.0])
