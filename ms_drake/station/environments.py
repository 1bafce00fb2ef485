"""Static environments (bin, shelf, table) as SDF text generated from their dimensions.

Conventions (environment frame E, placed at `EnvironmentConfig.position` in the world):
- bin: floor top surface at z = 0, inner box [-x/2, x/2] x [-y/2, y/2] x [0, z]; walls of
  `wall_thickness` (>= 3 cm by default so that nothing tunnels at the drop speeds of a heap).
  The bin stands on a 1.6 x 1.2 m support table whose top is at the bin floor's underside, so
  objects that leave the bin land next to it (and are removed by the heap generator).
- shelf: inner [-x/2, x/2] x [-y/2, y/2] x [0, z] with the open front facing -y (towards the
  robot and camera); back wall, two side walls, top and floor; it stands on a cabinet down to
  z = -0.7 (the room floor, which is also modelled).
- table: top surface at z = 0 with the given top thickness, plus a room floor at z = -0.75.

Every geometry is a rigid-hydroelastic box (point contact is the fallback between two rigid
geometries), with the environment's friction.
"""

from __future__ import annotations

import numpy as np

from ms_drake.objects.sdf import Shape, _geometry_xml, _pose_xml

BIN_RGBA = (0.12, 0.12, 0.13, 1.0)  # the reference's black bin
SUPPORT_RGBA = (0.55, 0.50, 0.45, 1.0)
SHELF_RGBA = (0.76, 0.62, 0.45, 1.0)
TABLE_RGBA = (0.80, 0.80, 0.78, 1.0)
FLOOR_RGBA = (0.45, 0.45, 0.47, 1.0)


def _boxes(type_: str, size, t: float) -> list[tuple[str, Shape, tuple]]:
    x, y, z = (float(v) for v in size)
    if type_ == "bin":
        return [
            ("floor", Shape("box", (x + 2 * t, y + 2 * t, t), pose=(0, 0, -t / 2, 0, 0, 0)), BIN_RGBA),
            ("wall_px", Shape("box", (t, y + 2 * t, z), pose=(x / 2 + t / 2, 0, z / 2, 0, 0, 0)), BIN_RGBA),
            ("wall_nx", Shape("box", (t, y + 2 * t, z), pose=(-x / 2 - t / 2, 0, z / 2, 0, 0, 0)), BIN_RGBA),
            ("wall_py", Shape("box", (x, t, z), pose=(0, y / 2 + t / 2, z / 2, 0, 0, 0)), BIN_RGBA),
            ("wall_ny", Shape("box", (x, t, z), pose=(0, -y / 2 - t / 2, z / 2, 0, 0, 0)), BIN_RGBA),
            ("support", Shape("box", (1.6, 1.2, 0.05), pose=(0, 0, -t - 0.025, 0, 0, 0)), SUPPORT_RGBA),
        ]
    if type_ == "shelf":
        return [
            ("floor", Shape("box", (x + 2 * t, y + t, t), pose=(0, t / 2, -t / 2, 0, 0, 0)), SHELF_RGBA),
            ("top", Shape("box", (x + 2 * t, y + t, t), pose=(0, t / 2, z + t / 2, 0, 0, 0)), SHELF_RGBA),
            ("back", Shape("box", (x, t, z), pose=(0, y / 2 + t / 2, z / 2, 0, 0, 0)), SHELF_RGBA),
            ("side_px", Shape("box", (t, y + t, z), pose=(x / 2 + t / 2, t / 2, z / 2, 0, 0, 0)), SHELF_RGBA),
            ("side_nx", Shape("box", (t, y + t, z), pose=(-x / 2 - t / 2, t / 2, z / 2, 0, 0, 0)), SHELF_RGBA),
            ("cabinet", Shape("box", (x + 2 * t, y + t, 0.7 - t), pose=(0, t / 2, -t - (0.7 - t) / 2, 0, 0, 0)),
             SHELF_RGBA),
            ("room_floor", Shape("box", (4.0, 4.0, 0.05), pose=(0, 0, -0.725, 0, 0, 0)), FLOOR_RGBA),
        ]
    if type_ == "table":
        return [
            ("top", Shape("box", (x, y, z), pose=(0, 0, -z / 2, 0, 0, 0)), TABLE_RGBA),
            ("room_floor", Shape("box", (4.0, 4.0, 0.05), pose=(0, 0, -0.775, 0, 0, 0)), FLOOR_RGBA),
        ]
    raise ValueError(f"unknown environment type {type_!r}; use bin, shelf or table")


def environment_sdf(type_: str, size, wall_thickness: float = 0.03, friction: float = 0.5,
                    model_name: str = "environment") -> str:
    """SDF text of the environment `type_` with inner `size` (see module docstring)."""
    parts = []
    for name, shape, rgba in _boxes(type_, size, wall_thickness):
        geom = _geometry_xml(shape)
        parts.append(
            f'<visual name="{name}_visual">{_pose_xml(shape.pose)}<geometry>{geom}</geometry>'
            f"<material><diffuse>{' '.join(f'{c:.3g}' for c in rgba)}</diffuse></material></visual>"
            f'<collision name="{name}">{_pose_xml(shape.pose)}<geometry>{geom}</geometry>'
            f"<drake:proximity_properties><drake:rigid_hydroelastic/>"
            f"<drake:mu_dynamic>{friction:.4g}</drake:mu_dynamic><drake:mu_static>{friction:.4g}</drake:mu_static>"
            f"</drake:proximity_properties></collision>"
        )
    return (
        '<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
        f'<model name="{model_name}"><link name="{type_}">{"".join(parts)}</link></model></sdf>\n'
    )


def workspace_bounds(type_: str, size) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners of the region objects must stay in, in the environment frame."""
    x, y, z = (float(v) for v in size)
    if type_ in ("bin", "shelf"):
        return np.array([-x / 2, -y / 2, -0.01]), np.array([x / 2, y / 2, max(z, 0.3) + 0.5])
    return np.array([-x / 2, -y / 2, -0.01]), np.array([x / 2, y / 2, 1.0])
