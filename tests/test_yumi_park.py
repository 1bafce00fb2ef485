"""YuMiBin's park (ArmSpec.home) keeps the robot out of the overhead camera's view of the bin: at
park, every pixel the robot changes in the rendered depth image lies beyond the bin's outer wall
(only the body's foot, at the image's edge), and none of them is an arm's."""

import numpy as np

from ms_drake.scenario import load_scenario
from ms_drake.station import MakeStation


def _render(robot: bool):
    s = load_scenario(None, "YuMiBin")
    s.objects.count = 0
    if not robot:
        s.robot.name, s.robot.grippers = "", []
    station = MakeStation(s, label_images="render")
    ctx = station.CreateDefaultContext()  # arms at ArmSpec.home
    depth = np.array(station.GetOutputPort("overhead.depth_image").Eval(ctx).data, float)[..., 0]
    label = np.array(station.GetOutputPort("overhead.label_image").Eval(ctx).data)[..., 0]
    return s, depth, label


def test_parked_yumi_is_out_of_the_bin_in_the_overhead_image():
    s, depth, label = _render(robot=True)
    _, depth0, label0 = _render(robot=False)
    robot = np.abs(np.nan_to_num(depth, posinf=9.0) - np.nan_to_num(depth0, posinf=9.0)) > 1e-4
    cam = s.cameras["overhead"]
    v, u = np.nonzero(robot)
    x = (u - (cam.width - 1) / 2) / cam.focal.x * depth[robot]  # the image's x is the world's x
    outer_wall = -0.5 * s.environment.size[0] - s.environment.wall_thickness  # the bin is centred at x = 0
    assert robot.sum() < 0.02 * robot.size
    assert np.all(x < outer_wall)  # beyond the bin's near outer wall
    assert len(np.unique(label[robot])) == 1  # one body (the YuMi's torso foot), no arm link
    assert set(np.unique(label0)) <= set(np.unique(label))
