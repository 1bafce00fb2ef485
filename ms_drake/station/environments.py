"""Static environments (bin, shelf, table) as SDF text generated from their dimensions.

Conventions (environment frame E, placed at `EnvironmentConfig.position` in the world):
- bin: floor top surface at z = 0, inner box [-x/2, x/2] x [-y/2, y/2] x [0, z]; walls of
  `wall_thickness` (>= 3 cm by default so that nothing tunnels at the drop speeds of a heap).
  The bin stands on a 1.6 x 1.2 m support table whose top is at the bin floor's underside, so
  objects that leave the bin land next to it (and are removed by the heap generator). Two
  drop-off trays stand on the support beside the bin's +y and -y walls (`dropoff_points`), out
  of the overhead camera's view: a lifted object is carried to the nearer one and released there
  (by the robot in full fidelity, by execution.ObjectCarrier in the primitive mode). The stations
  also model the room floor 0.7 m below the support's top (hidden from the overhead camera by
  the support): an object knocked off the support lands there instead of falling for ever (a body
  falling for tens of seconds spins up until the plant's step diverges).
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


TRAY_RGBA = (0.20, 0.35, 0.55, 1.0)
# Drop-off trays (inner x, y, wall height) [m], their walls' thickness, and the gap between the
# bin's outer wall and a tray's inner wall: with the default bin the trays' inner edges are 0.35 m
# from the bin's centre line, outside the overhead camera's view (+-0.29 m at the support's top),
# and within reach of the YuMi's and the Panda's arms on the side of the bin near the robot.
TRAY_INNER = (0.26, 0.18, 0.06)
TRAY_WALL = 0.01
TRAY_GAP = 0.12
TRAY_X = -0.15  # tray centre along the bin's x (the robots stand at -x)


def _tray_centers(size, t: float) -> list[tuple[float, float, float]]:
    """Centres of the drop-off trays' floor tops in the environment frame (+y tray first)."""
    y = float(size[1])
    cy = y / 2 + t + TRAY_GAP + TRAY_WALL + TRAY_INNER[1] / 2
    return [(TRAY_X, s * cy, -t + TRAY_WALL) for s in (1.0, -1.0)]


def _tray_boxes(size, t: float) -> list[tuple[str, Shape, tuple]]:
    ix, iy, iz = TRAY_INNER
    w = TRAY_WALL
    out = []
    for name, (cx, cy, cz) in zip(("tray_py", "tray_ny"), _tray_centers(size, t)):
        out += [
            (f"{name}_floor", Shape("box", (ix + 2 * w, iy + 2 * w, w), pose=(cx, cy, cz - w / 2, 0, 0, 0)), TRAY_RGBA),
            (f"{name}_px", Shape("box", (w, iy + 2 * w, iz), pose=(cx + ix / 2 + w / 2, cy, cz + iz / 2, 0, 0, 0)),
             TRAY_RGBA),
            (f"{name}_nx", Shape("box", (w, iy + 2 * w, iz), pose=(cx - ix / 2 - w / 2, cy, cz + iz / 2, 0, 0, 0)),
             TRAY_RGBA),
            (f"{name}_py", Shape("box", (ix, w, iz), pose=(cx, cy + iy / 2 + w / 2, cz + iz / 2, 0, 0, 0)), TRAY_RGBA),
            (f"{name}_ny", Shape("box", (ix, w, iz), pose=(cx, cy - iy / 2 - w / 2, cz + iz / 2, 0, 0, 0)), TRAY_RGBA),
        ]
    return out


def dropoff_points(env) -> list[np.ndarray]:
    """World points at the centre of each drop-off tray's floor (bin environments; [] else).
    env: the scenario's EnvironmentConfig."""
    if env.type != "bin":
        return []
    origin = np.asarray(env.position, float)
    return [origin + np.asarray(c) for c in _tray_centers(env.resolved_size(), float(env.wall_thickness))]


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
                    model_name: str = "environment", dropoffs: bool = True) -> str:
    """SDF text of the environment `type_` with inner `size` (see module docstring); a bin's
    drop-off trays and room floor only with `dropoffs` (the stations have them; the heap
    generators' drop worlds do not, so a heap does not depend on them)."""
    parts = []
    boxes = _boxes(type_, size, wall_thickness)
    if dropoffs and type_ == "bin":
        t = wall_thickness
        boxes = boxes + _tray_boxes(size, t) + [
            ("room_floor", Shape("box", (4.0, 4.0, 0.05), pose=(0, 0, -t - 0.725, 0, 0, 0)), FLOOR_RGBA)]
    for name, shape, rgba in boxes:
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
