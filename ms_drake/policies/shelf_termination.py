"""The end of a shelf search, inside its Diagram (simulation only: it reads the station's cheat
ports, as ShelfSceneObserver does).

`ShelfSearchTermination(camera, target, horizon, period, threshold=VISIBILITY)`, a
ms_drake.execution.termination.TerminationSystem, judges the search at every *idle step*: a check
time (every `period` s, the executor's period) at which the controller's executor is idle
(between actions, the robot parked) with a history it has not judged yet. There it measures the
target's visible fraction in the camera's label image (`target_visible_fraction`) and stops the
Simulator when

- the target is visible enough (>= threshold): reason "target_visible", a success;
- the history has reached the horizon: reason "horizon";

and, at any check time, when the executor is done (the policy has no action): reason
"no_action", the executor's stop reason as message. A non-finite body pose fails the simulation
(AdvanceTo raises).

Ports:
  inputs   status       ExecutorStatus (the controller's ``status`` output)
           label_image  ImageLabel16I: the camera's ``<cam>.label_image`` (labels = body indices)
           body_poses   the station's body_poses (the target's pose; the blow-up check)
  outputs  termination  Termination (ms_drake.execution.termination)
           visibility   1-vector: the target's visible fraction at the last idle step judged (now,
                        if this is one; 0 before the first)
           check        ShelfCheck(judging, steps, visible): whether now is an idle step to judge,
                        the history's length and the visibility (for a Simulator monitor that
                        records the idle steps)
State: the last idle step judged (history length, visibility), set by a periodic unrestricted
update at the check times.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import BasicVector
from pydrake.systems.sensors import ImageLabel16I

from ms_drake.execution.executor import ExecutorStatus
from ms_drake.execution.shelf_backend import ShelfBody
from ms_drake.execution.termination import RUNNING, Termination, TerminationSystem
from ms_drake.geometry import PinholeCamera
from ms_drake.policies.bin_search import ControllerError

#: The target's visible fraction at which a shelf search succeeds (FOSS's threshold).
VISIBILITY = 0.8


def target_visible_fraction(label: np.ndarray, X_WT: RigidTransform, size, label_value: int,
                            camera: PinholeCamera) -> float:
    """Pixels of `label` (H x W) equal to `label_value` inside the target's silhouette / pixels of
    the silhouette: its eight corners (a box of `size` (w, d, h) [m] at pose X_WT) projected by
    `camera` and their convex hull filled. 0 when the silhouette is empty."""
    half = 0.5 * np.asarray(size, float)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    pts = (X_WT.rotation().matrix() @ corners.T).T + X_WT.translation()
    uv, _ = camera.project(pts)
    sil = np.zeros(label.shape, np.uint8)
    cv2.fillConvexPoly(sil, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
    total = int(sil.sum())
    seen = int(np.count_nonzero((label == label_value) & (sil > 0)))
    return seen / total if total else 0.0


@dataclass(frozen=True)
class ShelfCheck:
    """judging: now is an idle step not judged before; steps: the executor's history length;
    visible: the target's visible fraction (measured now when judging, else the last one judged)."""

    judging: bool = False
    steps: int = 0
    visible: float = 0.0


@dataclass(frozen=True)
class _Judged:
    steps: int = -1
    visible: float = 0.0


class ShelfSearchTermination(TerminationSystem):
    """Stops a simulated shelf search (module docstring). camera: the PinholeCamera of the label
    image; target: the target's ShelfBody (plant body index = its label, and its size); horizon:
    the action budget H; period: the check period [s] (the controller's, ShelfSearchConfig.period);
    threshold: the visible fraction that reveals the target."""

    def __init__(self, camera: PinholeCamera, target: ShelfBody, horizon: int, period: float,
                 threshold: float = VISIBILITY):
        super().__init__(period, 0.0, poses_model=[RigidTransform()])
        if not isinstance(target, ShelfBody):
            raise ControllerError(f"ShelfSearchTermination: target must be the target's ShelfBody (body index and "
                                  f"ShelfObject), got {type(target).__name__}")
        if int(horizon) < 1:
            raise ControllerError(f"ShelfSearchTermination: horizon must be >= 1 action, got {horizon!r}")
        if not 0.0 < threshold <= 1.0:
            raise ControllerError(f"ShelfSearchTermination: threshold is a visible fraction in (0, 1], got "
                                  f"{threshold!r}")
        self.camera, self.target, self.horizon, self.threshold = camera, target, int(horizon), float(threshold)
        self.status_port = self.DeclareAbstractInputPort("status", AbstractValue.Make(ExecutorStatus()))
        self.label_port = self.DeclareAbstractInputPort(
            "label_image", AbstractValue.Make(ImageLabel16I(camera.width, camera.height)))
        self._judged = self.DeclareAbstractState(AbstractValue.Make(_Judged()))
        self.check_port = self.DeclareAbstractOutputPort(
            "check", lambda: AbstractValue.Make(ShelfCheck()), lambda c, o: o.set_value(self._check_now(c)))
        self.DeclareVectorOutputPort("visibility", BasicVector(1),
                                     lambda c, o: o.SetAtIndex(0, self.check_port.Eval(c).visible))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self._update)

    def _status(self, context) -> ExecutorStatus:
        if not self.status_port.HasValue(context):
            raise ControllerError(f"{self.get_name()} (ShelfSearchTermination): connect the status input (the "
                                  "shelf controller's status output)")
        return self.status_port.Eval(context)

    def visible_fraction(self, context) -> float:
        """The target's visible fraction in the label image now."""
        for port, what in ((self.label_port, "the camera's label_image"), (self.poses_port, "the station's body_poses")):
            if not port.HasValue(context):
                raise ControllerError(f"{self.get_name()} (ShelfSearchTermination): connect {port.get_name()} ({what}; "
                                      "simulation only)")
        label = np.asarray(self.label_port.Eval(context).data)[:, :, 0]
        X = self.poses_port.Eval(context)[self.target.body_index]
        t = self.target.shape
        return target_visible_fraction(label, X, (t.width, t.depth, t.height), self.target.body_index, self.camera)

    def _check_now(self, context) -> ShelfCheck:
        status = self._status(context)
        last = context.get_abstract_state(self._judged).get_value()
        if not status.busy and not status.done and status.steps != last.steps:
            return ShelfCheck(True, status.steps, self.visible_fraction(context))
        return ShelfCheck(False, status.steps, last.visible)

    def judge(self, context) -> Termination:
        status = self._status(context)
        if status.done:
            return Termination(True, "no_action", False, status.stop_reason)
        check = self.check_port.Eval(context)
        if check.judging:
            if check.visible >= self.threshold:
                return Termination(True, "target_visible", True, f"visible {check.visible:.3f} after {check.steps} "
                                                                 "actions")
            if check.steps >= self.horizon:
                return Termination(True, "horizon", False, f"{check.steps} actions, visible {check.visible:.3f}")
        return RUNNING

    def _update(self, context, state):
        check = self.check_port.Eval(context)
        if check.judging:
            state.get_mutable_abstract_state(self._judged).set_value(_Judged(check.steps, check.visible))


def connect_termination(builder, termination: ShelfSearchTermination, station, controller, camera: str = "front"):
    """Wire a ShelfSearchTermination: the controller's status, the station's `<camera>.label_image`
    and body_poses (the simulated station's cheat ports)."""
    builder.Connect(controller.GetOutputPort("status"), termination.status_port)
    builder.Connect(station.GetOutputPort(f"{camera}.label_image"), termination.label_port)
    builder.Connect(station.GetOutputPort("body_poses"), termination.poses_port)


__all__ = ["VISIBILITY", "ShelfCheck", "ShelfSearchTermination", "connect_termination", "target_visible_fraction"]
