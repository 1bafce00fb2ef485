"""Gripper models (SDF generated from dataclasses) and the floating-gripper base.

Frame convention shared by every gripper (choice recorded here; the reference is silent):
  * the gripper model's root body is `body`; its frame origin is the mounting face that welds to
    the robot flange;
  * +z of `body` is the approach direction (out of the flange, towards the object);
  * the parallel jaw closes along x;
  * frame `tcp` is the tool centre point: between the pads (jaw) or at the cup lip centre
    (suction), z along the approach. The bluction tool has `tcp` at the cup lip and `blade_tcp`
    at the blade's centre.

Parallel jaw: two prismatic joints `left_finger_sliding_joint` (q in [-w_max/2, 0]) and
`right_finger_sliding_joint` (q in [0, w_max/2]), both along +x of `body`, so that the opening
between the pad faces is exactly q_right - q_left. This is the joint layout Drake's
`SchunkWsgPositionController` (and its WSG LCM messages) assume, so the station drives the jaw
with Drake's WSG driver: `<gripper>.position` = opening [m], `<gripper>.force_limit` [N].

Pads are compliant hydroelastic (extruded polygon; a box when the polygon is the default
rectangle), with modulus, relaxation time (SAP), Hunt & Crossley dissipation (TAMSI) and
friction configurable through `PadConfig`. Default values follow Drake's hydroelastic user guide
for soft rubber-like pads (modulus 1e5-1e6 Pa; SAP dissipates through the relaxation time) and
were tuned by tests/test_grippers.py: 0.05-0.5 kg boxes lift stably at a 20-40 N grip force.

The bluction tool (Ch. 9.3, lines 1606-1610 of the reference): 0.40 m shaft of 0.03 m diameter
along +z, a 0.065 m (along the shaft) x 0.075 m (radial) blade near the tip on a revolute joint
`blade_joint` about the shaft axis (q = 0: blade hangs along -y of `body` ("down" when the tool
is horizontal with body y up); q = pi: blade up, out of the way for suction), and a 0.03 m
suction cup at the tip.

Floating gripper: any gripper welded to `floating_yaw_link` of a `floating_base` model with 6
PD-actuated joints floating_x, floating_y, floating_z (prismatic, world axes) and floating_roll,
floating_pitch, floating_yaw (revolute x, y, z in that chain order, so R_WG = Rx Ry Rz;
`robots.floating_gripper_positions(X_WG)` converts a pose). Its actuators carry
`drake:controller_gains`, so a discrete (SAP) plant drives them by its desired-state input.
"""

from __future__ import annotations

import hashlib
import math
import tempfile
from pathlib import Path

import numpy as np
from shapely.geometry import MultiPoint

from ms_drake.errors import ScenarioError
from ms_drake.robots import (
    BluctionConfig,
    PadConfig,
    ParallelJawConfig,
    SuctionCupConfig,
)

GRIPPERS_PKG = "package://ms_drake_models/grippers"


def _pose(x=0.0, y=0.0, z=0.0, r=0.0, p=0.0, yw=0.0) -> str:
    return f"<pose>{x:.6g} {y:.6g} {z:.6g} {r:.6g} {p:.6g} {yw:.6g}</pose>"


def _box_inertia(m, x, y, z):
    return (m / 12 * (y * y + z * z), m / 12 * (x * x + z * z), m / 12 * (x * x + y * y))


def _cyl_inertia(m, r, h):  # axis z
    return (m / 12 * (3 * r * r + h * h), m / 12 * (3 * r * r + h * h), m / 2 * r * r)


def _inertial(m, ixx, iyy, izz, pose="<pose>0 0 0 0 0 0</pose>") -> str:
    return (f"<inertial>{pose}<mass>{m:.6g}</mass><inertia><ixx>{ixx:.6g}</ixx><ixy>0</ixy><ixz>0</ixz>"
            f"<iyy>{iyy:.6g}</iyy><iyz>0</iyz><izz>{izz:.6g}</izz></inertia></inertial>")


def _visual(name, geom, pose, rgba) -> str:
    return (f'<visual name="{name}">{pose}<geometry>{geom}</geometry>'
            f"<material><diffuse>{' '.join(f'{c:.3g}' for c in rgba)}</diffuse></material></visual>")


def _collision(name, geom, pose, props="") -> str:
    return f'<collision name="{name}">{pose}<geometry>{geom}</geometry>{props}</collision>'


def _compliant(modulus, relaxation, mu_s, mu_d, hint=None, hc=None) -> str:
    hint_xml = f"<drake:mesh_resolution_hint>{hint:.6g}</drake:mesh_resolution_hint>" if hint else ""
    hc_xml = f"<drake:hunt_crossley_dissipation>{hc:.6g}</drake:hunt_crossley_dissipation>" if hc else ""
    return ("<drake:proximity_properties><drake:compliant_hydroelastic/>"
            f"<drake:hydroelastic_modulus>{modulus:.6g}</drake:hydroelastic_modulus>{hint_xml}"
            f"<drake:relaxation_time>{relaxation:.6g}</drake:relaxation_time>{hc_xml}"
            f"<drake:mu_static>{mu_s:.6g}</drake:mu_static><drake:mu_dynamic>{mu_d:.6g}</drake:mu_dynamic>"
            "</drake:proximity_properties>")


def _rigid_friction(mu) -> str:
    return (f"<drake:proximity_properties><drake:mu_static>{mu:.6g}</drake:mu_static>"
            f"<drake:mu_dynamic>{mu:.6g}</drake:mu_dynamic></drake:proximity_properties>")


def _box(x, y, z) -> str:
    return f"<box><size>{x:.6g} {y:.6g} {z:.6g}</size></box>"


def _cyl(r, h) -> str:
    return f"<cylinder><radius>{r:.6g}</radius><length>{h:.6g}</length></cylinder>"


def _sdf(model: str, body: str) -> str:
    return ('<?xml version="1.0"?>\n<sdf version="1.9" xmlns:drake="http://drake.mit.edu">\n'
            f'<model name="{model}">\n{body}\n</model>\n</sdf>\n')


def pad_prism_obj(pads: PadConfig) -> str:
    """OBJ text of a pad polygon (u along y, v along z) extruded by `thickness` along x,
    centred on the origin. Used for non-rectangular pads (declared convex)."""
    poly = np.asarray(pads.polygon, float)

    hull = MultiPoint([tuple(p) for p in poly]).convex_hull
    pts = np.asarray(hull.exterior.coords)[:-1]
    if len(pts) != len(poly):
        raise ScenarioError("PadConfig.polygon must be convex (its convex hull drops points)")
    n = len(pts)
    t = pads.thickness / 2
    a, b = pts[1] - pts[0], pts[2] - pts[1]
    if a[0] * b[1] - a[1] * b[0] < 0:  # make the outline counter-clockwise in (u, v)
        pts = pts[::-1]
    V = [(x, u, v) for x in (-t, t) for u, v in pts]
    faces = []  # outward-facing triangles (vertex indices) with their normals
    for i in range(n):  # sides
        j = (i + 1) % n
        du, dv = pts[j] - pts[i]
        normal = (0.0, dv, -du)
        faces += [((i, j, n + j), normal), ((i, n + j, n + i), normal)]
    for i in range(1, n - 1):  # caps at x = -t (normal -x) and x = +t (normal +x)
        faces += [((0, i + 1, i), (-1.0, 0.0, 0.0)), ((n, n + i, n + i + 1), (1.0, 0.0, 0.0))]
    lines = ["# ms_drake pad prism"]
    lines += [f"v {x:.6g} {u:.6g} {v:.6g}" for x, u, v in V]
    for k, (_, nrm) in enumerate(faces):
        nrm = np.asarray(nrm) / np.linalg.norm(nrm)
        lines.append(f"vn {nrm[0]:.6g} {nrm[1]:.6g} {nrm[2]:.6g}")
    for k, (f, _) in enumerate(faces):
        lines.append("f " + " ".join(f"{a + 1}//{k + 1}" for a in f))
    return "\n".join(lines) + "\n"


def _pad_geometry(pads: PadConfig, mesh_dir: Path | None, uri_prefix: str | None) -> str:
    if pads.polygon is None:
        return _box(pads.thickness, pads.width, pads.length)
    text = pad_prism_obj(pads)
    name = "pad_" + hashlib.sha1(text.encode()).hexdigest()[:12] + ".obj"
    target = mesh_dir if mesh_dir is not None else Path(tempfile.gettempdir()) / "ms_drake_pads"
    target.mkdir(parents=True, exist_ok=True)
    (target / name).write_text(text)
    uri = f"{uri_prefix}/{name}" if uri_prefix else f"file://{(target / name).resolve()}"
    return f"<mesh><uri>{uri}</uri><drake:declare_convex/></mesh>"


# ----------------------------------------------------------------------------- models
def parallel_jaw_sdf(config: ParallelJawConfig = ParallelJawConfig(), model_name: str = "parallel_jaw",
                     mesh_dir: Path | None = None, uri_prefix: str | None = None) -> str:
    """SDF text of the compliant-pad parallel jaw (see module docstring for frames/joints)."""
    c, p = config, config.pads
    px, py, pz = c.palm_size
    grey, dark, pad_rgba = (0.7, 0.7, 0.72, 1), (0.25, 0.25, 0.27, 1), (0.15, 0.3, 0.8, 1)
    # finger frames: origin on the pad face centre at q = 0 (pads touch at x = 0).
    pad_z = pz + c.finger_length - p.length / 2  # pad centre along z
    fz = pz + c.finger_length / 2  # finger box centre along z
    parts = [
        '<link name="body">',
        _inertial(c.palm_mass, *_box_inertia(c.palm_mass, px, py, pz), _pose(0, 0, pz / 2)),
        _visual("palm", _box(px, py, pz), _pose(0, 0, pz / 2), grey),
        _collision("palm", _box(px, py, pz), _pose(0, 0, pz / 2), _rigid_friction(0.5)),
        "</link>",
        '<frame name="tcp" attached_to="body">' + _pose(0, 0, pad_z) + "</frame>",
    ]
    pad_geom = _pad_geometry(p, mesh_dir, uri_prefix)
    pad_props = _compliant(p.hydroelastic_modulus, p.relaxation_time, p.mu_static, p.mu_dynamic,
                           p.resolution_hint, p.hunt_crossley_dissipation)
    for side, sign in (("left", -1.0), ("right", 1.0)):
        # finger body sits outside its pad: pad occupies [0, t] (outwards) from the pad face
        fx = sign * (p.thickness + c.finger_thickness / 2)
        parts += [
            f'<link name="{side}_finger">',
            _pose(0, 0, 0),
            _inertial(c.finger_mass, *_box_inertia(c.finger_mass, c.finger_thickness, c.finger_depth,
                                                   c.finger_length), _pose(fx, 0, fz)),
            _visual("finger", _box(c.finger_thickness, c.finger_depth, c.finger_length), _pose(fx, 0, fz), dark),
            _collision("finger", _box(c.finger_thickness, c.finger_depth, c.finger_length), _pose(fx, 0, fz),
                       _rigid_friction(0.5)),
            _visual("pad", pad_geom, _pose(sign * p.thickness / 2, 0, pad_z), pad_rgba),
            _collision("pad", pad_geom, _pose(sign * p.thickness / 2, 0, pad_z), pad_props),
            "</link>",
        ]
    half = c.max_opening / 2
    for side, lo, hi in (("left", -half, 0.0), ("right", 0.0, half)):
        parts += [
            f'<joint name="{side}_finger_sliding_joint" type="prismatic">',
            f"<parent>body</parent><child>{side}_finger</child>",
            f"<axis><xyz expressed_in=\"body\">1 0 0</xyz><limit><lower>{lo:.6g}</lower><upper>{hi:.6g}</upper>"
            f"<effort>{c.max_force:.6g}</effort><velocity>0.4</velocity></limit>"
            "<dynamics><damping>0.5</damping></dynamics></axis>",
            "</joint>",
        ]
    parts += ['<drake:collision_filter_group name="jaw">', "<drake:member>body</drake:member>",
              "<drake:member>left_finger</drake:member>", "<drake:member>right_finger</drake:member>",
              "<drake:ignored_collision_filter_group>jaw</drake:ignored_collision_filter_group>",
              "</drake:collision_filter_group>"]
    return _sdf(model_name, "\n".join(parts))


def suction_cup_sdf(config: SuctionCupConfig = SuctionCupConfig(), model_name: str = "suction_cup") -> str:
    """A suction tool: stem along +z ending in a compliant cup; `tcp` at the cup lip centre."""
    c = config
    lip = c.stem_length + c.cup_height
    ixx, iyy, izz = _cyl_inertia(c.mass, c.stem_radius, c.stem_length)
    parts = [
        '<link name="body">',
        _inertial(c.mass, ixx, iyy, izz, _pose(0, 0, c.stem_length / 2)),
        _visual("stem", _cyl(c.stem_radius, c.stem_length), _pose(0, 0, c.stem_length / 2), (0.7, 0.7, 0.72, 1)),
        _collision("stem", _cyl(c.stem_radius, c.stem_length), _pose(0, 0, c.stem_length / 2),
                   _rigid_friction(0.5)),
        _visual("cup", _cyl(c.cup_radius, c.cup_height), _pose(0, 0, c.stem_length + c.cup_height / 2),
                (0.1, 0.1, 0.1, 1)),
        _collision("cup", _cyl(c.cup_radius, c.cup_height), _pose(0, 0, c.stem_length + c.cup_height / 2),
                   _compliant(c.cup_modulus, c.relaxation_time, c.mu, c.mu, c.cup_radius / 3)),
        "</link>",
        '<frame name="tcp" attached_to="body">' + _pose(0, 0, lip) + "</frame>",
    ]
    return _sdf(model_name, "\n".join(parts))


def bluction_sdf(config: BluctionConfig = BluctionConfig(), model_name: str = "bluction") -> str:
    """The bluction tool: shaft + rotating blade + suction cup (see module docstring)."""
    c = config
    r = c.shaft_diameter / 2
    lip = c.shaft_length + c.cup_height
    ixx, iyy, izz = _cyl_inertia(c.mass_shaft, r, c.shaft_length)
    bz = c.shaft_length - c.blade_offset  # blade centre along the shaft
    by = -(r + c.blade_height / 2)  # hangs along -y at q = 0
    bi = _box_inertia(c.mass_blade, c.blade_thickness, c.blade_height, c.blade_width)
    parts = [
        '<link name="body">',
        _inertial(c.mass_shaft, ixx, iyy, izz, _pose(0, 0, c.shaft_length / 2)),
        _visual("shaft", _cyl(r, c.shaft_length), _pose(0, 0, c.shaft_length / 2), (0.75, 0.75, 0.78, 1)),
        _collision("shaft", _cyl(r, c.shaft_length), _pose(0, 0, c.shaft_length / 2), _rigid_friction(0.4)),
        _visual("cup", _cyl(c.cup_diameter / 2, c.cup_height), _pose(0, 0, c.shaft_length + c.cup_height / 2),
                (0.1, 0.1, 0.1, 1)),
        _collision("cup", _cyl(c.cup_diameter / 2, c.cup_height), _pose(0, 0, c.shaft_length + c.cup_height / 2),
                   _compliant(c.cup_modulus, c.relaxation_time, c.mu, c.mu, c.cup_diameter / 6)),
        "</link>",
        '<frame name="tcp" attached_to="body">' + _pose(0, 0, lip) + "</frame>",
        '<link name="blade">',
        _inertial(c.mass_blade, *bi, _pose(0, by, bz)),
        _visual("blade", _box(c.blade_thickness, c.blade_height, c.blade_width), _pose(0, by, bz), (0.2, 0.2, 0.22, 1)),
        _collision("blade", _box(c.blade_thickness, c.blade_height, c.blade_width), _pose(0, by, bz),
                   _rigid_friction(0.4)),
        "</link>",
        '<frame name="blade_tcp" attached_to="blade">' + _pose(0, by, bz) + "</frame>",
        '<joint name="blade_joint" type="revolute"><parent>body</parent><child>blade</child>',
        '<axis><xyz expressed_in="body">0 0 1</xyz><limit><lower>0</lower><upper>3.14159265</upper>'
        "<effort>5</effort><velocity>3</velocity></limit><dynamics><damping>0.05</damping></dynamics></axis>",
        "</joint>",
    ]
    return _sdf(model_name, "\n".join(parts))


def floating_base_sdf(model_name: str = "floating_base", kp_lin: float = 2e4, kd_lin: float = 600.0,
                      kp_rot: float = 400.0, kd_rot: float = 20.0, max_force: float = 400.0,
                      max_torque: float = 40.0, limit: float = 5.0) -> str:
    """Six PD-actuated joints x, y, z, roll, pitch, yaw; grippers weld to `floating_yaw_link`.

    The five intermediate links have a tiny mass (1 g) so the articulated inertia stays
    well-conditioned; the world-side end `floating_origin` is welded to the world by the caller.
    """
    names = ["origin", "x", "y", "z", "roll", "pitch", "yaw"]
    parts = []
    for n in names:
        m = 1e-3
        parts.append(f'<link name="floating_{n}_link">{_inertial(m, 1e-7, 1e-7, 1e-7)}</link>')
    axes = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1", "roll": "1 0 0", "pitch": "0 1 0", "yaw": "0 0 1"}
    for parent, child in zip(names[:-1], names[1:]):
        lin = child in ("x", "y", "z")
        jt = "prismatic" if lin else "revolute"
        lo, hi = (-limit, limit) if lin else (-4 * math.pi, 4 * math.pi)
        effort = max_force if lin else max_torque
        kp, kd = (kp_lin, kd_lin) if lin else (kp_rot, kd_rot)
        parts.append(
            f'<joint name="floating_{child}" type="{jt}"><parent>floating_{parent}_link</parent>'
            f"<child>floating_{child}_link</child><axis><xyz>{axes[child]}</xyz><limit><lower>{lo:.6g}</lower>"
            f"<upper>{hi:.6g}</upper><effort>{effort:.6g}</effort><velocity>{2.0 if lin else 6.0}</velocity>"
            f'</limit></axis><drake:controller_gains p="{kp:.6g}" d="{kd:.6g}"/></joint>')
    return _sdf(model_name, "\n".join(parts))
