"""SDF text for one rigid object, shared by every object set.

Objects are free bodies with rigid-hydroelastic collision geometry (primitives or convex
pieces) and one visual. Mesh URIs are `package://ms_drake_models/...` so the SDF parses from
a string anywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np
from scipy.spatial.transform import Rotation

#: Hydroelastic modulus of objects (Pa): stiff (hard plastic / wood-like contact patches of a
#: few mm at object weights) yet much softer than rigid, so the contact solver stays well
#: conditioned at millisecond time steps.
OBJECT_MODULUS = 5.0e6


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


def _resolution_xml(shape: Shape, edges: int = 12) -> str:
    """Hydroelastic cylinders and spheres are tessellated: ~`edges` edges around."""
    if shape.kind in ("cylinder", "sphere"):
        hint = max(0.002, 2 * 3.14159 * shape.size[0] / edges)
        return f"<drake:mesh_resolution_hint>{hint:.4g}</drake:mesh_resolution_hint>"
    return ""


def hydroelastic_xml(shape: Shape, compliance: str, modulus: float, edges: int = 12) -> str:
    """Proximity properties: 'rigid' or 'compliant' (with `modulus` in Pa) hydroelastic;
    round shapes tessellated with ~`edges` edges around."""
    if compliance == "rigid":
        return f"<drake:rigid_hydroelastic/>{_resolution_xml(shape, edges)}"
    if compliance == "compliant":
        # The hydroelastic pressure field of a primitive grows from 0 at the surface to E at
        # its medial axis, so a thin shape (a 4 mm cardboard backing) is far stiffer than a
        # chunky one at the same E. Scale E by the smallest half-size relative to 2.5 cm so
        # the contact stiffness E * area / half-size stays comparable across shapes.
        dims = {"box": lambda sz: min(sz) / 2, "cylinder": lambda sz: min(sz[0], sz[1] / 2),
                "sphere": lambda sz: sz[0]}.get(shape.kind)
        if dims is not None:
            modulus = modulus * min(1.0, max(0.05, dims(shape.size) / 0.025))
        return (f"<drake:compliant_hydroelastic/><drake:hydroelastic_modulus>{modulus:.4g}"
                f"</drake:hydroelastic_modulus>{_resolution_xml(shape, edges)}")
    raise ValueError(f"compliance {compliance!r}: use rigid or compliant")


def contact_points(shape: Shape, max_radius: float = 0.005) -> list[tuple[tuple[float, float, float], float]]:
    """(centre, radius) of small spheres (shape frame) tucked into the corners / rims of a
    primitive, flush with its faces.

    Two rigid geometries in point contact touch at one point, so a box resting on a face
    rocks forever; spheres in the corners give it a stable multi-point support (the classic
    remedy). Cylinders get 8 spheres on each rim. Radii are at most `max_radius` and 45 % of
    the thinnest half-size, so a sphere never pokes out of the shape.
    """
    if shape.kind == "box":
        h = np.asarray(shape.size, float) / 2
        r = min(max_radius, 0.45 * h.min())
        c = h - r
        return [((sx * c[0], sy * c[1], sz * c[2]), r) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    if shape.kind == "cylinder":
        rad, height = shape.size
        r = min(max_radius, 0.45 * min(rad, height / 2))
        return [(((rad - r) * math.cos(a), (rad - r) * math.sin(a), sz * (height / 2 - r)), r)
                for a in np.linspace(0, 2 * math.pi, 8, endpoint=False) for sz in (-1, 1)]
    return []


def _compose(pose, p):
    """A point p of a shape posed at `pose` (x y z r p y), in the object frame."""
    return tuple(np.asarray(pose[:3]) + Rotation.from_euler("xyz", pose[3:]).apply(p))


def object_sdf(
    model_name: str,
    inertia: Inertia,
    visuals: list[tuple[Shape, tuple[float, float, float, float]]],
    collisions: list[Shape],
    friction: float = 0.5,
    compliance: str = "rigid",
    modulus: float = OBJECT_MODULUS,
    extra_points: list | None = None,
    point_radius: float = 0.001,
    contact_spheres: bool = True,
    resolution_edges: int = 12,
) -> str:
    """SDF 1.9 text of a one-link model named `model_name` with link `body`.

    visuals: (shape, rgba) pairs. collisions: rigid-hydroelastic shapes (point contact is the
    fallback between two rigid geometries, e.g. object-object and object-bin), plus small
    contact spheres on corners and rims (`contact_points`) so that point contact supports a
    resting object at several points. compliance="compliant" makes the object itself
    compliant-hydroelastic instead (slower: use it where object-object pressure matters).
    resolution_edges: hydroelastic cylinders and spheres get ~this many edges around (12 by
    default; the heap generator's drop world uses fewer, see ms_drake.scenes.heaps).
    """
    i = inertia
    vis = "".join(
        f'<visual name="visual_{k}">{_pose_xml(s.pose)}<geometry>{_geometry_xml(s)}</geometry>'
        f"<material><diffuse>{' '.join(f'{c:.4g}' for c in rgba)}</diffuse></material></visual>"
        for k, (s, rgba) in enumerate(visuals)
    )
    col = "".join(
        f'<collision name="collision_{k}">{_pose_xml(s.pose)}<geometry>{_geometry_xml(s)}</geometry>'
        f"<drake:proximity_properties>{hydroelastic_xml(s, compliance, modulus, resolution_edges)}"
        f"<drake:mu_dynamic>{friction:.4g}</drake:mu_dynamic><drake:mu_static>{friction:.4g}</drake:mu_static>"
        f"</drake:proximity_properties></collision>"
        for k, s in enumerate(collisions)
    )
    # Contact spheres tucked into corners and rims (flush with the faces).
    points = []
    if contact_spheres:
        points = [(_compose(s.pose, p), r) for s in collisions for p, r in contact_points(s)]
        points += [(p, point_radius) for p in (extra_points or [])]
    for k, (p, r) in enumerate(points):
        sph = Shape("sphere", (r,))
        pose = (*p, 0, 0, 0)
        col += (f'<collision name="point_{k}">{_pose_xml(pose)}<geometry>{_geometry_xml(sph)}</geometry>'
                f"<drake:proximity_properties><drake:mu_dynamic>{friction:.4g}</drake:mu_dynamic>"
                f"<drake:mu_static>{friction:.4g}</drake:mu_static></drake:proximity_properties></collision>")
    return (
        '<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
        f'<model name="{escape(model_name)}"><link name="body">'
        f"<inertial><pose>{i.com[0]:.6g} {i.com[1]:.6g} {i.com[2]:.6g} 0 0 0</pose><mass>{i.mass:.6g}</mass>"
        f"<inertia><ixx>{i.ixx:.6g}</ixx><iyy>{i.iyy:.6g}</iyy><izz>{i.izz:.6g}</izz>"
        f"<ixy>{i.ixy:.6g}</ixy><ixz>{i.ixz:.6g}</ixz><iyz>{i.iyz:.6g}</iyz></inertia></inertial>"
        f"{vis}{col}</link></model></sdf>\n"
    )
