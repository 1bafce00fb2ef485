"""The shipped bin stations' layouts (diagrams/scenarios.yaml YuMiBin, PandaBin): the robots
reach a fixed set of probe grasps over the bin (PickReach's pick plan from park, IK only), their
parked arms stay out of the overhead camera's view of the bin, and each arm reaches a drop-off
tray (FullBackend.drops)."""

import numpy as np
import pytest

from ms_drake.execution import FullBackend
from ms_drake.execution.reach import PickReach
from ms_drake.geometry import Workspace
from ms_drake.scenario import load_scenario
from ms_drake.station import MakeStation
from ms_drake.types import Grasp

# Probe grasps (centre 6 cm above the bin floor): straight down over the bin's middle and near
# half, and tilted 30 degrees towards the robot (approach along +x) over the far half.
TILT = np.radians(30.0)
PROBES = ([((x, y, 0.06), (0.0, 0.0, -1.0)) for x in (-0.15, 0.0) for y in (-0.1, 0.1)]
          + [((0.1, 0.0, 0.06), (np.sin(TILT), 0.0, -np.cos(TILT)))])
STATIONS = {"YuMiBin": ("parallel_jaw", "suction"), "PandaBin": ("parallel_jaw",)}


@pytest.mark.parametrize("name", sorted(STATIONS))
def test_station_reaches_probe_grasps(name):
    reach = PickReach(load_scenario(None, name))
    missed = []
    for kind in STATIONS[name]:
        for c, a in PROBES:
            g = Grasp(kind=kind, center=c, approach=a, axis=(0.0, 1.0, 0.0), width=0.04, quality=1.0,
                      object_id="probe")
            status = reach.status(g)
            if status != "ok":
                missed.append((kind, c, a, status))
    assert not missed, f"{name} misses probe grasps: {missed}"


@pytest.mark.parametrize("name", sorted(STATIONS))
def test_each_arm_reaches_a_dropoff(name):
    s = load_scenario(None, name)
    b = FullBackend(s, {}, Workspace.from_scenario(s))
    assert set(b.drops) == set(b.ik) and all(len(q) for q in b.drops.values()), b.drops


def _render(name: str, robot: bool):
    s = load_scenario(None, name)
    s.objects.count = 0
    if not robot:
        s.robot.name, s.robot.grippers = "", []
    station = MakeStation(s, label_images="render")
    ctx = station.CreateDefaultContext()  # arms at park (ArmSpec.home)
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data, float)[..., 0]
    label = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[..., 0]
    return s, depth, label


@pytest.mark.parametrize("name", sorted(STATIONS))
def test_parked_arms_are_out_of_the_overhead_view_of_the_bin(name):
    s, depth, label = _render(name, robot=True)
    _, depth0, _ = _render(name, robot=False)
    robot = np.abs(np.nan_to_num(depth, posinf=9.0) - np.nan_to_num(depth0, posinf=9.0)) > 1e-4
    cam = s.cameras["overhead"]
    v, u = np.nonzero(robot)
    x = (u - (cam.width - 1) / 2) / cam.focal.x * depth[robot]  # the image's x is the world's x
    outer_wall = -0.5 * s.environment.size[0] - s.environment.wall_thickness  # bin centred at x = 0
    assert robot.sum() < 0.02 * robot.size
    assert np.all(x < outer_wall)  # nothing of the robot over the bin
    assert len(np.unique(label[robot])) <= 1  # at most one body (the YuMi's torso foot), no arm link
