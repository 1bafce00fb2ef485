"""The end of a search inside the Diagram: systems whose periodic check stops Drake's Simulator.

A search's end is part of its Diagram, so `Simulator(diagram).AdvanceTo(T)` runs exactly the
search a benchmark runs and returns when it is over:

- `Termination`: the value of a termination system's ``termination`` output: whether the search
  is over (`stop`), why (`reason`, a short word such as "target_visible", "horizon",
  "no_action", "done"), whether that is a success, and a free-text `message`.
- `TerminationSystem(period, offset=0.0, poses_model=None)`: the base LeafSystem. A subclass
  declares its own input ports and state and implements `judge(context) -> Termination`. The base
  declares the ``termination`` output (judge's value) and a periodic publish event at
  (period, offset) that returns `EventStatus.ReachedTermination(self, reason)` when the output says
  stop, so `AdvanceTo` returns early with `SimulatorStatus.reason() ==
  kReachedTerminationCondition`. With `poses_model` (a list of RigidTransform, the station's
  ``body_poses``) the base also declares a ``body_poses`` input: a non-finite pose (a blown-up
  simulation) fails the event, and `AdvanceTo` raises RuntimeError("... non-finite plant state
  ..."). The failure is returned as `EventStatus.Failed(None, message)` with the system's name in
  the message: in pydrake 1.51 a Python event returning `EventStatus.Failed(self, ...)` crashes the
  interpreter when the Simulator throws.
  The publish event runs at the end of the simulator step that lands on a check time, so it
  judges the state an observer sees after `AdvanceTo(t)`; the system's own unrestricted updates at
  that time (declared by subclasses) see the same state at the start of the next step.
- `StopWhenDone(period, rest=0.0, status_model=None)`: stops `rest` seconds after its ``status``
  input (any value with a boolean `done`, e.g. the ActionExecutor's ExecutorStatus) first reads
  done at a check time (reason "done").
- `is_check_time(t, period, offset=0.0)`: whether simulated time t is one of the check times
  (exactly offset + k * period, as Drake computes periodic event times), for a Simulator monitor
  that reads the diagram at the checks.
- `finite_poses(poses)`: index of the first non-finite pose, or None.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import EventStatus, LeafSystem

from ms_drake.execution.executor import ExecutionError, ExecutorStatus


@dataclass(frozen=True)
class Termination:
    """stop: the search is over; reason: why (a short word; "" while it runs); success: whether the
    search reached its goal; message: details (e.g. the controller's stop reason)."""

    stop: bool = False
    reason: str = ""
    success: bool = False
    message: str = ""


RUNNING = Termination()


def is_check_time(t: float, period: float, offset: float = 0.0) -> bool:
    """Whether t is exactly a periodic event time offset + k * period (k >= 0)."""
    if t < offset:
        return False
    k = round((t - offset) / period)
    return any(offset + j * period == t for j in (k - 1, k, k + 1) if j >= 0)


def finite_poses(poses) -> int | None:
    """Index of the first pose in `poses` (RigidTransforms or 4x4 arrays) with a non-finite entry;
    None when all are finite."""
    for k, X in enumerate(poses):
        m = X.GetAsMatrix34() if isinstance(X, RigidTransform) else np.asarray(X, float)
        if not np.isfinite(m).all():
            return k
    return None


class TerminationSystem(LeafSystem):
    """Base of the systems that end a search (module docstring). Subclasses call
    ``super().__init__(period, offset, poses_model)`` first, then declare their ports and state,
    and implement `judge`."""

    def __init__(self, period: float, offset: float = 0.0, poses_model=None):
        super().__init__()
        if not (period > 0 and offset >= 0):
            raise ExecutionError(f"{type(self).__name__}: period must be > 0 s and offset >= 0 s, got period="
                                 f"{period!r}, offset={offset!r}")
        self.period, self.offset = float(period), float(offset)
        self.poses_port = (self.DeclareAbstractInputPort("body_poses", AbstractValue.Make(list(poses_model)))
                           if poses_model is not None else None)
        self.termination_port = self.DeclareAbstractOutputPort(
            "termination", lambda: AbstractValue.Make(RUNNING), lambda c, o: o.set_value(self.judge(c)))
        self.DeclarePeriodicPublishEvent(self.period, self.offset, self._check)

    def judge(self, context) -> Termination:
        """The search's state at `context`: RUNNING, or a Termination with stop=True."""
        raise NotImplementedError(f"{type(self).__name__} must implement judge(context)")

    def is_check_time(self, t: float) -> bool:
        return is_check_time(t, self.period, self.offset)

    def _check(self, context):
        if self.poses_port is not None and self.poses_port.HasValue(context):
            bad = finite_poses(self.poses_port.Eval(context))
            if bad is not None:
                return EventStatus.Failed(None, f"{self.get_name()} ({type(self).__name__}): non-finite plant state "
                                                f"(body_poses[{bad}] at t = {context.get_time():.3f} s)")
        term = self.termination_port.Eval(context)
        if term.stop:
            return EventStatus.ReachedTermination(self, term.reason or "stop")
        return EventStatus.Succeeded()


class StopWhenDone(TerminationSystem):
    """Stops `rest` s after its ``status`` input's `done` first reads True at a check time (the
    scene comes to rest after the controller's last motion); reason "done", success True (the
    controller finished; whether it did its task is the record's to say).

    Ports: input ``status`` (a value with a boolean `done`; model `status_model`, default
    ExecutorStatus()), optionally ``body_poses`` (poses_model: the blow-up check); output
    ``termination``. State: the time done was first seen (NaN before)."""

    def __init__(self, period: float, rest: float = 0.0, status_model=None, poses_model=None):
        super().__init__(period, 0.0, poses_model)
        if not rest >= 0:
            raise ExecutionError(f"StopWhenDone: rest must be >= 0 s, got {rest!r}")
        self.rest = float(rest)
        self.status_port = self.DeclareAbstractInputPort(
            "status", AbstractValue.Make(status_model if status_model is not None else ExecutorStatus()))
        self._since = self.DeclareAbstractState(AbstractValue.Make(math.nan))
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self._update)

    def _done(self, context) -> bool:
        if not self.status_port.HasValue(context):
            raise ExecutionError(f"{self.get_name()} (StopWhenDone): connect the status input (the controller's "
                                 "status output)")
        return bool(self.status_port.Eval(context).done)

    def done_since(self, context) -> float:
        """The time done was first seen (the current time if it is seen now; NaN: not yet)."""
        since = context.get_abstract_state(self._since).get_value()
        if math.isnan(since) and self._done(context):
            return context.get_time()
        return since

    def judge(self, context) -> Termination:
        since = self.done_since(context)
        if not math.isnan(since) and context.get_time() >= since + self.rest - 1e-9:
            return Termination(True, "done", True, f"done at t = {since:.2f} s, then {self.rest:g} s of rest")
        return RUNNING

    def _update(self, context, state):
        if math.isnan(context.get_abstract_state(self._since).get_value()) and self._done(context):
            state.get_mutable_abstract_state(self._since).set_value(context.get_time())


__all__ = ["RUNNING", "StopWhenDone", "Termination", "TerminationSystem", "finite_poses", "is_check_time"]
