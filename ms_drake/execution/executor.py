"""ActionExecutor: executes the PolicySelector's Actions on a station, one at a time.

Ports (declared first in __init__):
  inputs
    action         Action (PolicySelector). Read only when the executor is idle.
    body_poses     the station's body_poses (list of RigidTransform): outcome checks (lifted?
                   left the bin?). Optional: unconnected = outcomes from the backend alone.
    ready          1-vector: no new action is latched while it is < 0.5 (e.g. before the first
                   camera images arrive from hardware; perception.ready.ImagesReady). Optional:
                   unconnected = always ready.
    carrying       1-vector: no new action is latched while it is >= 0.5 (an object is still being
                   carried out of the camera's view: execution.ObjectCarrier in the primitive
                   mode). Optional: unconnected = never carrying.
  outputs
    <command port> one vector output per station command input the backend drives (e.g.
                   `floating.position` (6), `floating_jaw.position` (1), `floating_jaw.force_limit`
                   (1); YuMi: both arms, the right jaw and the left suction cup). Connect each to
                   the station input of the same name (`connect_executor`).
    history        tuple[ActionOutcome], every finished action in order (feed PolicySelector.history).
    outcome        ActionOutcome of the last finished action (kind "stop" with message "none" before).
    removed        tuple[str]: ids of objects that left the bin (lifted out, or fell over a wall).
                   In full fidelity the robot itself drops a lifted object into a drop-off tray; in
                   the primitive mode execution.ObjectCarrier carries it there.
    status         ExecutorStatus (busy, done, steps, stop reason).

The end of the search ends the simulation: the update at which the executor becomes done returns
EventStatus.ReachedTermination (so `Simulator.AdvanceTo(t_max)` returns early, its status naming
the stop reason; a later AdvanceTo simulates on), and non-finite body poses raise SimulationBlewUp
(a RuntimeError) from AdvanceTo. `terminate=False` keeps the simulation running.

The executor latches a new Action only when idle, from a periodic unrestricted update (as Drake's
clutter-clearing planner does), so perception and planning run once per action, on demand. One
action: `backend.plan(action, hold, step)` returns a Motion (command values over time, a check
time, a duration); at the check time `backend.outcome(...)` decides what happened (an ActionOutcome and every object that left the bin); at the end of
the motion the executor is idle again and holds the motion's last commands. An Action of kind
"stop" ends the search (status.done). A plan that fails (unreachable grasp) is an unsuccessful
outcome with the planner's status as message; the selector's horizon bounds such repetitions.
Randomness: the backends draw from (seed, step), so a rollout is reproducible from its seed.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import BasicVector, EventStatus, LeafSystem

from ms_drake.errors import MsDrakeError
from ms_drake.types import Action, ActionOutcome


class ExecutionError(MsDrakeError, ValueError):
    """An executor was configured with an unknown fidelity, or wired without an input it needs."""


class SimulationBlewUp(MsDrakeError, RuntimeError):
    """The simulated scene's state became non-finite (raised from the executor's update, so
    Simulator.AdvanceTo raises it)."""


@dataclass(frozen=True)
class ExecutorStatus:
    busy: bool = False
    done: bool = False
    steps: int = 0
    stop_reason: str = ""


@dataclass
class Motion:
    """Command values over time for one action. commands: {port: callable(t) -> array}; ports not
    named hold their values. check_time: when the outcome is decided; duration: when it ends."""

    commands: dict
    check_time: float
    duration: float
    info: dict = field(default_factory=dict)
    # From this time on the motion may end early, as soon as the scene is at rest (see
    # ActionExecutor); None: it runs its full duration.
    settle_from: float | None = None

    def __deepcopy__(self, memo):  # immutable once planned; Drake copies abstract state values
        return self

    def values(self, t: float, hold: dict) -> dict:
        out = dict(hold)
        for k, f in self.commands.items():
            out[k] = np.atleast_1d(np.asarray(f(min(max(t, 0.0), self.duration)), float))
        return out


@dataclass
class _State:
    phase: str = "idle"  # idle | executing | done
    action: Action | None = None
    motion: Motion | None = None
    t0: float = 0.0
    checked: bool = False
    hold: dict = field(default_factory=dict)
    history: tuple = ()
    removed: tuple = ()
    stop_reason: str = ""
    last_poses: dict | None = None  # watched body index -> pose (12,) at the previous update
    still_since: float | None = None  # time from which every body has been at rest
    at_rest: bool = False  # the last action ended with the watched bodies at rest

    def __deepcopy__(self, memo):
        # Drake copies abstract state values twice per update. The update replaces fields and
        # never mutates what they hold (frozen Actions and outcomes, fresh dicts and tuples), so
        # a shallow copy isolates the two states; a deep copy grew with the history (~1 ms each).
        return copy.copy(self)


NO_OUTCOME = ActionOutcome(Action("stop", reason="none"), False, message="none")


class ActionExecutor(LeafSystem):
    """backend: PrimitiveBackend (floating gripper) or FullBackend (YuMi), see ms_drake.execution.
    period: the idle-check / outcome-check rate [s].

    Settle detection (our choice; the reference lets its simulator settle a fixed time): after
    `Motion.settle_from` the action ends (its outcome checked, if not yet) at the first update at
    which every body has moved by less than `still_distance` [m] and `still_angle` [rad] between
    consecutive updates for `still_time` s; otherwise at its full duration (the backend's
    `settle` bound). Needs the body_poses input; without it motions run their full duration.
    An action whose motion commands nothing (the primitive grasp) and removes nothing ends at
    its check when the action before it ended at rest: the scene is as it was.
    Only the heap is watched: the backend's `objects` not yet removed (a backend without
    `objects`, e.g. the shelf's, has every body watched). The robot's own bodies are
    not (a closed jaw's fingers chatter against each other by ~16 mm per update at 10 ms steps,
    which kept every settle running to its bound).
    The defaults (2 mm and 3 degrees per 50 ms) call "at rest" a heap whose rigid objects chatter
    in place on their point contacts (up to ~1 rad/s of angular jitter at 10 ms steps), which a
    tighter bound would never see end."""

    def __init__(self, backend, period: float = 0.05, still_distance: float = 2e-3,
                 still_angle: float = np.radians(3.0), still_time: float = 0.1, terminate: bool = True):
        super().__init__()
        self.backend = backend
        self.period = float(period)
        self.terminate = bool(terminate)
        self.still_distance, self.still_angle, self.still_time = float(still_distance), float(still_angle), float(still_time)
        # Ports first.
        self.action_port = self.DeclareAbstractInputPort("action", AbstractValue.Make(Action("stop")))
        self.poses_port = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self.ready_port = self.DeclareVectorInputPort("ready", 1)
        self.carrying_port = self.DeclareVectorInputPort("carrying", 1)
        init = _State(hold={k: np.atleast_1d(np.asarray(v, float)) for k, v in backend.initial_commands().items()})
        self._state_index = self.DeclareAbstractState(AbstractValue.Make(init))
        state_ticket = {self.abstract_state_ticket(self._state_index), self.time_ticket()}
        self.command_ports = {}
        for name, value in init.hold.items():
            self.command_ports[name] = self.DeclareVectorOutputPort(
                name, BasicVector(len(value)), lambda c, o, n=name: self._calc_command(c, o, n),
                prerequisites_of_calc=state_ticket)
        state_only = {self.abstract_state_ticket(self._state_index)}
        self.history_port = self.DeclareAbstractOutputPort(
            "history", lambda: AbstractValue.Make(()), lambda c, o: o.set_value(self._state(c).history),
            prerequisites_of_calc=state_only)
        self.outcome_port = self.DeclareAbstractOutputPort(
            "outcome", lambda: AbstractValue.Make(NO_OUTCOME), self._calc_outcome, prerequisites_of_calc=state_only)
        self.removed_port = self.DeclareAbstractOutputPort(
            "removed", lambda: AbstractValue.Make(()), lambda c, o: o.set_value(self._state(c).removed),
            prerequisites_of_calc=state_only)
        self.status_port = self.DeclareAbstractOutputPort(
            "status", lambda: AbstractValue.Make(ExecutorStatus()), self._calc_status, prerequisites_of_calc=state_only)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.period, 0.0, self._update)

    # ------------------------------------------------------------------ outputs
    def _state(self, context) -> _State:
        return context.get_abstract_state(self._state_index).get_value()

    def _calc_command(self, context, output, name):
        s = self._state(context)
        if s.phase == "executing":
            v = s.motion.values(context.get_time() - s.t0, s.hold)[name]
        else:
            v = s.hold[name]
        output.SetFromVector(v)

    def _calc_outcome(self, context, output):
        h = self._state(context).history
        output.set_value(h[-1] if h else NO_OUTCOME)

    def _calc_status(self, context, output):
        s = self._state(context)
        output.set_value(ExecutorStatus(s.phase == "executing", s.phase == "done", len(s.history), s.stop_reason))

    # ------------------------------------------------------------------ update
    def _settled(self, s: _State, poses, t: float) -> bool:
        """Track rest (updates s.last_poses / s.still_since); True when the motion may end now."""
        if poses is None or s.motion is None or s.motion.settle_from is None:
            return False
        objects = getattr(self.backend, "objects", None)  # {id: body index}; without it: every body
        watched = ([b for oid, b in objects.items() if oid not in s.removed and b < len(poses)]
                   if objects is not None else range(len(poses)))
        now = {b: np.concatenate([poses[b].translation(), poses[b].rotation().matrix().ravel()]) for b in watched}
        prev, s.last_poses = s.last_poses, now
        if t - s.t0 < s.motion.settle_from - 1e-9 or prev is None or not set(now) <= set(prev):
            s.still_since = None
            return False
        # The bodies watched at both updates (an object removed in between drops out).
        P = np.array([now[b] for b in now]).reshape(-1, 12)
        Q = np.array([prev[b] for b in now]).reshape(-1, 12)
        # Rotation change bound: |R_a - R_b|_F = 2 sqrt(2) sin(theta / 2) ~ sqrt(2) theta.
        moved = len(P) > 0 and (
            np.linalg.norm(P[:, :3] - Q[:, :3], axis=1).max() > self.still_distance
            or np.linalg.norm(P[:, 3:] - Q[:, 3:], axis=1).max() > np.sqrt(2.0) * self.still_angle)
        if moved:
            s.still_since = None
            return False
        if s.still_since is None:
            s.still_since = t - self.period  # at rest since the previous update
        return t - s.still_since >= self.still_time - 1e-9

    def _update(self, context, state):
        s = copy.copy(self._state(context))
        t = context.get_time()
        if s.phase == "done":
            return None
        poses = self.poses_port.Eval(context) if self.poses_port.HasValue(context) else None
        if poses is not None and not all(np.all(np.isfinite(X.GetAsMatrix34())) for X in poses):
            # (raised, not EventStatus.Failed: pydrake 1.51 crashes on a Failed status from Python)
            raise SimulationBlewUp(f"the simulation blew up at t = {t:.3f} s: non-finite body poses")
        if s.phase == "executing":
            dt = t - s.t0
            settled = self._settled(s, poses, t)
            unchanged = False
            if not s.checked and (dt >= s.motion.check_time - 1e-9 or settled):
                out, gone = self.backend.outcome(s.action, s.motion, poses, len(s.history), s.removed)
                s.history = s.history + (out,)
                new = [r for r in dict.fromkeys([out.removed_object, *gone]) if r and r not in s.removed]
                s.removed = s.removed + tuple(new)
                s.checked = True
                # A motion that commands nothing (a primitive grasp) and removed nothing left the
                # scene as it was; if that was at rest, there is nothing to settle.
                unchanged = not s.motion.commands and not new and s.at_rest and s.motion.settle_from is not None
            # The search is over once the target is out (its grasp succeeded): the heap's settle
            # after it changes nothing, so the action ends at its check.
            extracted = s.checked and self._extracted(s)
            if s.checked and (dt >= s.motion.duration - 1e-9 or settled or extracted or unchanged):
                s.hold = s.motion.values(s.motion.duration, s.hold)
                s.phase, s.motion, s.action = "idle", None, None
                s.last_poses, s.still_since, s.at_rest = None, None, settled or unchanged
                # Idle for one period before the next action: observers (the rollout driver, the
                # demo) see the settled scene the next action is chosen from.
                state.get_mutable_abstract_state(self._state_index).set_value(s)
                return
        if s.phase == "idle":
            if self.ready_port.HasValue(context) and self.ready_port.Eval(context)[0] < 0.5:
                return  # the observation is not there yet: stay idle
            if self._carrying(context) and not self._extracted(s):
                return  # a removed object is still on its way out of the camera's view
            if not self.action_port.HasValue(context):
                raise ExecutionError("ActionExecutor: connect the action input (PolicySelector.action)")
            action = self.action_port.Eval(context)
            if action.kind == "stop":
                s.phase, s.stop_reason = "done", action.reason or "stop"
            else:
                motion = self.backend.plan(action, s.hold, len(s.history), poses)
                if isinstance(motion, str):  # planning failed: an unsuccessful outcome, still idle
                    s.history = s.history + (ActionOutcome(action, False, message=f"plan_failed:{motion}"),)
                else:
                    s.phase, s.action, s.motion, s.t0, s.checked = "executing", action, motion, t, False
        state.get_mutable_abstract_state(self._state_index).set_value(s)
        return self._ended(s)

    def _extracted(self, s: _State) -> bool:
        """The last action lifted the target out: the search is over, whatever still moves."""
        if not s.history:
            return False
        o = s.history[-1]
        return (o.success and o.action.kind == "grasp" and bool(o.removed_object)
                and o.removed_object == getattr(self.backend, "target_id", ""))

    def _carrying(self, context) -> bool:
        return self.carrying_port.HasValue(context) and self.carrying_port.Eval(context)[0] >= 0.5

    def _ended(self, s: _State):
        """ReachedTermination at the update that ends the search (when `terminate`); simulating on
        afterwards (e.g. to watch the last object carried away) is not stopped again."""
        if s.phase == "done" and self.terminate:
            return EventStatus.ReachedTermination(self, f"search ended: {s.stop_reason}")
        return None

    def ready_to_act(self, context) -> bool:
        """Whether the update at this context's time latches the next action (idle, images ready,
        nothing being carried, and the time one of the executor's update times): an observer that
        evaluates the controller's outputs then sees the very scene the action is chosen from."""
        s = self._state(context)
        k = context.get_time() / self.period
        return (s.phase == "idle" and abs(k - round(k)) < 1e-6
                and not (self.ready_port.HasValue(context) and self.ready_port.Eval(context)[0] < 0.5)
                and not (self._carrying(context) and not self._extracted(s)))


def connect_executor(builder, executor: ActionExecutor, station, selector=None):
    """Wire the executor's command outputs to the station inputs of the same names, body_poses
    to the executor, and (optionally) the selector's action / the executor's history."""
    for name, port in executor.command_ports.items():
        builder.Connect(port, station.GetInputPort(name))
    builder.Connect(station.GetOutputPort("body_poses"), executor.poses_port)
    if selector is not None:
        builder.Connect(selector.GetOutputPort("action"), executor.action_port)
        builder.Connect(executor.history_port, selector.GetInputPort("history"))


def remove_objects(plant, plant_context, body_indices) -> None:
    """Move bodies far out of the scene (1 m apart, 5 m below the floor), at rest and locked, so
    they neither fall forever nor touch anything. A scene-setup tool for experiments that start
    from a recorded state (a replayed attempt, the push study's states); a search never calls it:
    its diagram carries lifted objects to the drop-off trays."""
    for j, b in enumerate(body_indices):
        body = plant.get_body(BodyIndex(int(b)))
        X = RigidTransform([20.0 + 1.0 * int(b), 0.0, -5.0])
        plant.SetFreeBodyPose(plant_context, body, X)
        plant.SetFreeBodySpatialVelocity(plant_context, body, _zero_velocity())
        body.Lock(plant_context)


def _zero_velocity():
    return SpatialVelocity(np.zeros(3), np.zeros(3))


__all__ = [
    "NO_OUTCOME",
    "ActionExecutor",
    "SimulationBlewUp",
    "ExecutionError",
    "ExecutorStatus",
    "Motion",
    "connect_executor",
    "remove_objects",
]
