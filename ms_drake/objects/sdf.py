"""SDF text for one rigid object, shared by every object set.

Objects are free bodies with rigid-hydroelastic collision geometry (primitives or convex
pieces) and one visual. Mesh URIs are `package://ms_drake_models/...` so the SDF parses from
a string anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import escape


@dataclass(frozen=True)
class Inertia:
    """Mass properties about the centre of mass, expressed in the object frame."""

    mass: float
    com: tuple[float, float, float]
    ixx: float
    iyy: float
    izz: float
    ixy: float = 0.0
    ixz: float = 0.0
    iyz: float = 0.0


@dataclass(frozen=True)
class Shape:
    """One geometry of an object: kind box|cylinder|sphere|mesh|convex, with a pose offset.

    size: box (x, y, z); cylinder (radius, length); sphere (radius,); mesh/convex: ().
    uri: for mesh/convex, the package:// URI of the .obj file.
    pose: (x, y, z, roll, pitch, yaw) in the object frame.
    """

    kind: str
    size: tuple[float, ...] = ()
    uri: str = ""
    pose: tuple[float, float, float, float, float, float] = (0, 0, 0, 0, 0, 0)


def _geometry_xml(shape: Shape) -> str:
    if shape.kind == "box":
        x, y, z = shape.size
        return f"<box><size>{x:.6g} {y:.6g} {z:.6g}</size></box>"
    if shape.kind == "cylinder":
        r, length = shape.size
        return f"<cylinder><radius>{r:.6g}</radius><length>{length:.6g}</length></cylinder>"
    if shape.kind == "sphere":
        return f"<sphere><radius>{shape.size[0]:.6g}</radius></sphere>"
    if shape.kind == "mesh":
        return f"<mesh><uri>{escape(shape.uri)}</uri></mesh>"
    if shape.kind == "convex":
        return f"<mesh><uri>{escape(shape.uri)}</uri><drake:declare_convex/></mesh>"
    raise ValueError(f"unknown shape kind {shape.kind!r}; use box, cylinder, sphere, mesh or convex")


def _pose_xml(pose) -> str:
    return "<pose>" + " ".join(f"{v:.6g}" for v in pose) + "</pose>"


def object_sdf(
    model_name: str,
    inertia: Inertia,
    visuals: list[tuple[Shape, tuple[float, float, float, float]]],
    collisions: list[Shape],
    friction: float = 0.5,
) -> str:
    """SDF 1.9 text of a one-link model named `model_name` with link `body`.

    visuals: (shape, rgba) pairs. collisions: rigid-hydroelastic shapes (point contact is the
    fallback between two rigid geometries).
    """
    i = inertia
    vis = "".join(
        f'<visual name="visual_{k}">{_pose_xml(s.pose)}<geometry>{_geometry_xml(s)}</geometry>'
        f"<material><diffuse>{' '.join(f'{c:.4g}' for c in rgba)}</diffuse></material></visual>"
        for k, (s, rgba) in enumerate(visuals)
    )
    col = "".join(
        f'<collision name="collision_{k}">{_pose_xml(s.pose)}<geometry>{_geometry_xml(s)}</geometry>'
        f"<drake:proximity_properties><drake:rigid_hydroelastic/>"
        f"<drake:mu_dynamic>{friction:.4g}</drake:mu_dynamic><drake:mu_static>{friction:.4g}</drake:mu_static>"
        f"</drake:proximity_properties></collision>"
        for k, s in enumerate(collisions)
    )
    return (
        '<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
        f'<model name="{escape(model_name)}"><link name="body">'
        f"<inertial><pose>{i.com[0]:.6g} {i.com[1]:.6g} {i.com[2]:.6g} 0 0 0</pose><mass>{i.mass:.6g}</mass>"
        f"<inertia><ixx>{i.ixx:.6g}</ixx><iyy>{i.iyy:.6g}</iyy><izz>{i.izz:.6g}</izz>"
        f"<ixy>{i.ixy:.6g}</ixy><ixz>{i.ixz:.6g}</ixz><iyz>{i.iyz:.6g}</iyz></inertia></inertial>"
        f"{vis}{col}</link></model></sdf>\n"
    )
