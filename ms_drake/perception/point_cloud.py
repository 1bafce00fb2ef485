"""Depth image -> point cloud, with Drake's DepthImageToPointCloud.

`add_point_cloud(builder, station, camera_name, camera_config)` adds Drake's system fed by the
station's ``<cam>.depth_image`` (and ``<cam>.rgb_image`` for colour), with the camera's pose
as a constant input so the cloud is in the world frame; returns the system, whose output
port ``point_cloud`` gives a pydrake PointCloud (invalid depths are NaN points).
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.perception import BaseField, DepthImageToPointCloud
from pydrake.systems.primitives import ConstantValueSource

from ms_drake.geometry import PinholeCamera


def add_point_cloud(builder, station, camera_name: str, camera_config, color: bool = True):
    color_cam, depth_cam = camera_config.MakeCameras()
    X_WC = PinholeCamera.from_config(camera_config).X_WC
    fields = BaseField.kXYZs | (BaseField.kRGBs if color and camera_config.rgb else 0)
    system = builder.AddSystem(DepthImageToPointCloud(depth_cam.core().intrinsics(), fields=fields))
    system.set_name(f"{camera_name}.point_cloud")
    builder.Connect(station.GetOutputPort(f"{camera_name}.depth_image"), system.depth_image_input_port())
    if color and camera_config.rgb:
        builder.Connect(station.GetOutputPort(f"{camera_name}.rgb_image"), system.color_image_input_port())
    pose = builder.AddSystem(ConstantValueSource(AbstractValue.Make(X_WC)))
    pose.set_name(f"{camera_name}.X_WC")
    builder.Connect(pose.get_output_port(), system.camera_pose_input_port())
    return system


def finite_points(cloud) -> np.ndarray:
    """(N, 3) finite xyz points of a pydrake PointCloud."""
    xyz = cloud.xyzs().T
    return xyz[np.all(np.isfinite(xyz), axis=1)]
