"""The end of a search inside the Diagram (ms_drake.execution.termination): StopWhenDone alone
with fixed inputs, wired in a diagram (the Simulator stops `rest` s after done), the blow-up check
(AdvanceTo raises), the check-time helper and bad inputs."""

import math

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator, SimulatorStatus
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from ms_drake.execution import ExecutionError, ExecutorStatus
from ms_drake.execution.termination import RUNNING, StopWhenDone, Termination, finite_poses, is_check_time


def test_is_check_time_and_finite_poses():
    assert is_check_time(0.0, 0.05) and is_check_time(3 * 0.05, 0.05) and is_check_time(7 * 0.1, 0.1)
    assert not is_check_time(0.15, 0.05)  # 3 * 0.05 = 0.15000000000000002: the event time, not 0.15
    assert not is_check_time(0.01, 0.05) and not is_check_time(0.04, 0.1, offset=0.05)
    assert finite_poses([RigidTransform(), RigidTransform([1.0, 2.0, 3.0])]) is None
    assert finite_poses([RigidTransform(), RigidTransform([np.nan, 0.0, 0.0])]) == 1
    assert finite_poses([np.eye(4), np.full((4, 4), np.inf)]) == 1


def test_stop_when_done_alone_fixed_inputs():
    end = StopWhenDone(0.1, rest=0.5)
    ctx = end.CreateDefaultContext()
    end.status_port.FixValue(ctx, ExecutorStatus(busy=True))
    assert end.termination_port.Eval(ctx) == RUNNING
    assert math.isnan(end.done_since(ctx))
    ctx.SetTime(2.0)
    end.status_port.FixValue(ctx, ExecutorStatus(done=True, stop_reason="stop"))
    assert end.done_since(ctx) == 2.0 and not end.termination_port.Eval(ctx).stop  # rest first
    end0 = StopWhenDone(0.1)  # no rest: done stops at once
    ctx0 = end0.CreateDefaultContext()
    end0.status_port.FixValue(ctx0, ExecutorStatus(done=True))
    term = end0.termination_port.Eval(ctx0)
    assert term == Termination(True, "done", True, term.message) and term.message.startswith("done at")


class _DoneAt(LeafSystem):
    """ExecutorStatus source: done from time `t_done` on."""

    def __init__(self, t_done):
        super().__init__()
        self.t_done = t_done
        self.DeclareAbstractOutputPort("status", lambda: AbstractValue.Make(ExecutorStatus()),
                                       lambda c, o: o.set_value(ExecutorStatus(done=c.get_time() >= self.t_done)))


class _Poses(LeafSystem):
    """body_poses: one body, its translation NaN from time `t_bad` on."""

    def __init__(self, t_bad):
        super().__init__()
        self.t_bad = t_bad
        self.DeclareAbstractOutputPort(
            "body_poses", lambda: AbstractValue.Make([RigidTransform()]),
            lambda c, o: o.set_value([RigidTransform([np.nan if c.get_time() >= self.t_bad else 0.0, 0.0, 0.0])]))


def _wired(t_done, t_bad=np.inf, rest=0.5):
    builder = DiagramBuilder()
    src = builder.AddSystem(_DoneAt(t_done))
    poses = builder.AddSystem(_Poses(t_bad))
    end = builder.AddNamedSystem("end", StopWhenDone(0.1, rest, poses_model=[RigidTransform()]))
    builder.Connect(src.get_output_port(), end.status_port)
    builder.Connect(poses.get_output_port(), end.poses_port)
    return builder.Build(), end


def test_stop_when_done_wired_stops_the_simulator_after_the_rest():
    diagram, end = _wired(t_done=1.03)
    sim = Simulator(diagram)
    status = sim.AdvanceTo(10.0)
    assert status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
    assert "done" in status.FormatMessage()
    # done is first seen at the check at 1.1 s; 0.5 s of rest later the simulator stops
    assert abs(sim.get_context().get_time() - 1.6) < 1e-9
    term = end.termination_port.Eval(end.GetMyContextFromRoot(sim.get_context()))
    assert term.stop and term.reason == "done" and term.success


def test_stop_when_done_wired_runs_to_the_boundary_when_never_done():
    diagram, _ = _wired(t_done=np.inf)
    sim = Simulator(diagram)
    assert sim.AdvanceTo(2.0).reason() == SimulatorStatus.ReturnReason.kReachedBoundaryTime


def test_non_finite_poses_fail_the_simulation():
    diagram, _ = _wired(t_done=np.inf, t_bad=0.25)
    sim = Simulator(diagram)
    with pytest.raises(RuntimeError, match="non-finite plant state"):
        sim.AdvanceTo(2.0)
    assert abs(sim.get_context().get_time() - 0.3) < 1e-9  # the first check after the blow-up


def test_bad_inputs():
    with pytest.raises(ExecutionError, match="period"):
        StopWhenDone(0.0)
    with pytest.raises(ExecutionError, match="rest"):
        StopWhenDone(0.1, rest=-1.0)
    end = StopWhenDone(0.1)
    with pytest.raises(ExecutionError, match="connect the status input"):
        end.termination_port.Eval(end.CreateDefaultContext())
