"""ShelfSearchTermination (ms_drake.policies.shelf_termination): the visible fraction of a
target, the system alone with fixed inputs (status, label image, body poses), wired in a diagram
(the Simulator stops on the target seen, at the horizon, on no action; an idle step is judged
once), and bad inputs. The whole search wired to the FetchShelf station: test_shelf_search_diagram."""

import numpy as np
import pytest
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator, SimulatorStatus
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantValueSource
from pydrake.systems.sensors import ImageLabel16I

from ms_drake.execution import ExecutorStatus
from ms_drake.execution.shelf_backend import ShelfBody
from ms_drake.execution.termination import RUNNING
from ms_drake.geometry import PinholeCamera
from ms_drake.policies.bin_search import ControllerError
from ms_drake.policies.shelf_termination import (
    VISIBILITY,
    ShelfCheck,
    ShelfSearchTermination,
    target_visible_fraction,
)
from ms_drake.scenario import load_scenario
from ms_drake.types import ShelfObject

TARGET = ShelfObject("target", "box", 0.0, 0.02, 0.06, 0.06, 0.06)
BODY = 7  # the target's body index = its label


@pytest.fixture(scope="module")
def setup():
    scenario = load_scenario(None, "FetchShelf")
    camera = PinholeCamera.from_config(scenario.cameras["front"])
    origin = np.asarray(scenario.environment.position, float)
    X = RigidTransform(origin + [TARGET.x, TARGET.y, TARGET.height / 2])
    poses = [RigidTransform() for _ in range(BODY)] + [X]
    return camera, poses


def _label(camera, value=0, left_of=None):
    img = ImageLabel16I(camera.width, camera.height)
    data = np.zeros((camera.height, camera.width, 1), np.int16)
    data[:, : (camera.width if left_of is None else left_of)] = value
    img.mutable_data[:] = data
    return img


def _silhouette_columns(camera, poses):
    half = 0.5 * np.array([TARGET.width, TARGET.depth, TARGET.height])
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    uv, _ = camera.project(corners + poses[BODY].translation())
    return uv[:, 0].min(), uv[:, 0].max()


def test_target_visible_fraction(setup):
    camera, poses = setup
    size = (TARGET.width, TARGET.depth, TARGET.height)
    full = np.asarray(_label(camera, BODY).data)[:, :, 0]
    assert target_visible_fraction(full, poses[BODY], size, BODY, camera) == 1.0
    assert target_visible_fraction(full, poses[BODY], size, BODY + 1, camera) == 0.0  # another body's label
    u0, u1 = _silhouette_columns(camera, poses)
    assert 0 <= u0 < u1 < camera.width  # the target is in view
    half = np.asarray(_label(camera, BODY, left_of=int((u0 + u1) / 2)).data)[:, :, 0]
    assert 0.3 < target_visible_fraction(half, poses[BODY], size, BODY, camera) < 0.7


def _alone(setup, status, label_value, horizon=4):
    camera, poses = setup
    end = ShelfSearchTermination(camera, ShelfBody(BODY, TARGET), horizon=horizon, period=0.05)
    ctx = end.CreateDefaultContext()
    end.status_port.FixValue(ctx, status)
    end.label_port.FixValue(ctx, _label(camera, label_value))
    end.poses_port.FixValue(ctx, poses)
    return end, ctx


def test_alone_fixed_inputs(setup):
    # idle with a history not judged yet: judged now
    end, ctx = _alone(setup, ExecutorStatus(steps=1), BODY)
    assert end.check_port.Eval(ctx) == ShelfCheck(True, 1, 1.0)
    assert end.GetOutputPort("visibility").Eval(ctx)[0] == 1.0
    term = end.termination_port.Eval(ctx)
    assert term.stop and term.reason == "target_visible" and term.success
    # hidden target, history below the horizon: the search goes on
    end, ctx = _alone(setup, ExecutorStatus(steps=1), 0)
    assert end.check_port.Eval(ctx).judging and end.termination_port.Eval(ctx) == RUNNING
    # ... at the horizon it stops
    end, ctx = _alone(setup, ExecutorStatus(steps=4), 0)
    term = end.termination_port.Eval(ctx)
    assert term.stop and term.reason == "horizon" and not term.success
    # busy (an action running): not judged, whatever the image
    end, ctx = _alone(setup, ExecutorStatus(busy=True, steps=4), BODY)
    assert not end.check_port.Eval(ctx).judging and end.termination_port.Eval(ctx) == RUNNING
    # the executor done: no action
    end, ctx = _alone(setup, ExecutorStatus(done=True, steps=2, stop_reason="der3: no candidate"), BODY)
    term = end.termination_port.Eval(ctx)
    assert term.stop and term.reason == "no_action" and term.message == "der3: no candidate" and not term.success
    assert VISIBILITY == 0.8


class _Status(LeafSystem):
    """ExecutorStatus over time: idle with `steps` = the number of `idle_from` times passed, busy
    in between (between idle_from[k] - busy and idle_from[k])."""

    def __init__(self, idle_from, busy=0.2):
        super().__init__()
        self.idle_from, self.busy = list(idle_from), busy
        self.DeclareAbstractOutputPort("status", lambda: AbstractValue.Make(ExecutorStatus()), self._calc)

    def _calc(self, context, output):
        t = context.get_time()
        steps = sum(t >= s - 1e-12 for s in self.idle_from)
        busy = any(s - self.busy <= t < s - 1e-12 for s in self.idle_from)
        output.set_value(ExecutorStatus(busy=busy, steps=steps))


class _Label(LeafSystem):
    """The target's label everywhere from time `t_seen` on (nothing before)."""

    def __init__(self, camera, t_seen):
        super().__init__()
        self.images = (_label(camera, 0), _label(camera, BODY))
        self.t_seen = t_seen
        self.DeclareAbstractOutputPort("label_image", lambda: AbstractValue.Make(self.images[0]),
                                       lambda c, o: o.set_value(self.images[int(c.get_time() >= self.t_seen)]))


def _wired(setup, status_system, t_seen, horizon):
    camera, poses = setup
    builder = DiagramBuilder()
    status = builder.AddSystem(status_system)
    label = builder.AddSystem(_Label(camera, t_seen))
    poses_src = builder.AddSystem(ConstantValueSource(AbstractValue.Make(poses)))
    end = builder.AddNamedSystem("termination", ShelfSearchTermination(camera, ShelfBody(BODY, TARGET), horizon,
                                                                       period=0.05))
    builder.Connect(status.get_output_port(), end.status_port)
    builder.Connect(label.get_output_port(), end.label_port)
    builder.Connect(poses_src.get_output_port(), end.poses_port)
    diagram = builder.Build()
    sim = Simulator(diagram)
    status = sim.AdvanceTo(5.0)
    ctx = end.GetMyContextFromRoot(sim.get_context())
    return status, sim.get_context().get_time(), end.termination_port.Eval(ctx), end


def test_wired_stops_when_the_target_is_seen_at_an_idle_step(setup):
    # actions end (idle) at 0.5 and 1.0 s; the target shows from 0.7 s: seen at the idle step of 1.0 s
    status, t, term, end = _wired(setup, _Status([0.5, 1.0]), t_seen=0.7, horizon=4)
    assert status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
    assert "target_visible" in status.FormatMessage()
    assert abs(t - 1.0) < 1e-9 and term.reason == "target_visible" and term.success


def test_wired_stops_at_the_horizon(setup):
    status, t, term, _ = _wired(setup, _Status([0.5, 1.0]), t_seen=np.inf, horizon=2)
    assert status.reason() == SimulatorStatus.ReturnReason.kReachedTerminationCondition
    assert abs(t - 1.0) < 1e-9 and term.reason == "horizon" and not term.success


def test_wired_judges_each_idle_step_once(setup):
    # idle from 0.5 s on with one action done; the target shows at 0.7 s, but that idle step was
    # judged at 0.5 s (hidden): nothing stops the run before its end
    status, t, term, _ = _wired(setup, _Status([0.5]), t_seen=0.7, horizon=4)
    assert status.reason() == SimulatorStatus.ReturnReason.kReachedBoundaryTime and t == 5.0
    assert term == RUNNING


def test_bad_inputs(setup):
    camera, poses = setup
    with pytest.raises(ControllerError, match="ShelfBody"):
        ShelfSearchTermination(camera, TARGET, 4, 0.05)
    with pytest.raises(ControllerError, match="horizon"):
        ShelfSearchTermination(camera, ShelfBody(BODY, TARGET), 0, 0.05)
    with pytest.raises(ControllerError, match="threshold"):
        ShelfSearchTermination(camera, ShelfBody(BODY, TARGET), 4, 0.05, threshold=1.5)
    end = ShelfSearchTermination(camera, ShelfBody(BODY, TARGET), 4, 0.05)
    ctx = end.CreateDefaultContext()
    with pytest.raises(ControllerError, match="connect the status input"):
        end.termination_port.Eval(ctx)
    end.status_port.FixValue(ctx, ExecutorStatus())
    with pytest.raises(ControllerError, match="label_image"):
        end.termination_port.Eval(ctx)
