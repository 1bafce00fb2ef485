"""Development-time converter: robot models from PyPI packages -> Drake SDF in models/robots/.

Run in a venv that has the SOURCE packages (never needed at run time):

    python -m tools.convert_robots --robot panda|yumi|fetch|all

Sources (pip install them into the converter venv, e.g. /work/venvs/robots):
  panda  example-robot-data 6.0.0  panda_description (franka_ros), Apache-2.0. URDF with franka_ros
         inertias and limits; visual meshes are .dae, collision meshes .stl.
  yumi   robosuite-models 1.0.0    assets/robots/yumi (MJCF), MIT. Full and coarse STL meshes;
         placeholder inertias (2 kg, 0.1 kg m^2 everywhere) -> recomputed from the meshes.
  fetch  gymnasium-robotics 1.4.2  envs/assets/fetch (MJCF), MIT. STL meshes, fetch_description
         inertias; zero-mass camera bodies become frames.
Converter needs: numpy, scipy, trimesh, fast-simplification (decimation), pycollada (.dae), mujoco
(reference kinematics of the MJCF sources) and drake (reference kinematics of the Panda URDF).
The venv used for the committed files (only the model assets of the three source packages are
read, so they are installed without their dependencies):

    python3.11 -m venv /work/venvs/robots
    /work/venvs/robots/bin/pip install --no-deps example-robot-data==6.0.0 robosuite-models==1.0.0 \
        gymnasium-robotics==1.4.2
    /work/venvs/robots/bin/pip install numpy==2.4.6 scipy==1.17.1 trimesh==5.2.0 manifold3d==3.5.4 \
        fast-simplification==0.2.0 pycollada==0.9.3 mujoco==4.0.0 drake==1.51.1
    cd <checkout> && /work/venvs/robots/bin/python -m tools.convert_robots --robot all
The output is deterministic (re-running reproduces the committed files byte for byte).

What the converter does, robot by robot:
  * reads the source kinematic tree (its own small URDF / MJCF readers, see `read_urdf`,
    `read_mjcf`) into `Link` records with poses at the zero configuration;
  * visual meshes -> one decimated .obj per link (at most `VISUAL_FACES[robot]` triangles), geometry
    baked into the link frame so the SDF needs no geometry poses;
  * collision -> one convex hull .obj per link, declared with `<drake:declare_convex/>`;
  * inertia: kept where the source has real values; where it has placeholders (YuMi) it is
    recomputed from the convex hull of the collision mesh at `YUMI_DENSITY` (uniform density);
  * joint position limits kept from the source, velocity / effort limits from the source or,
    where the MJCF has none, from the manufacturer tables below (`VELOCITY_LIMITS`);
  * massless fixed children (flanges, camera optical frames, hands) -> SDF `<frame>`s;
  * writes <robot>.sdf, NOTICE (licence + provenance) and tests/data/fk_<robot>.json: poses of
    every link/frame relative to the root link for a few configurations, computed from the SOURCE
    model with an independent tool (MuJoCo for MJCF, Drake's URDF parser for the Panda URDF).

Conventions of the outputs:
  * root link: panda_link0 (Panda), yumi_body (YuMi), base_link (Fetch); every model is free
    (the station welds the root or, for the Fetch, the planar-base root `base_origin`).
  * Fetch: the source base has three slide joints; we give it a planar base (base_x, base_y,
    base_yaw joints through two massless links) above `base_link`.
  * Fetch head_tilt_joint: MuJoCo's `ref=0.06` is folded in (our angle = qpos - ref).
  * YuMi joint names are those of ROS yumi_description; along each arm the chain order is
    joints 1, 2, 7, 3, 4, 5, 6.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import sys
import sysconfig
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "models" / "robots"
TESTDATA = REPO / "tests" / "data"
PKG = "package://ms_drake_models/robots"

VISUAL_FACES = {"panda": 3000, "yumi": 6000, "fetch": 3000}  # decimation target per link (triangles)
HULL_MAX_VERTICES = 120  # collision hull: computed on a mesh decimated to about this many
YUMI_DENSITY = 1000.0  # kg/m^3 on the convex hull of the coarse link mesh (hollow cast links)
SEED = 20260701

# Velocity [rad/s or m/s] and effort [N m or N] limits where the source (MJCF) has none.
# YuMi: ABB IRB 14000 product specification axis speeds (180 deg/s axes 1,2,7,3; 400 deg/s 4,5,6),
# as in ROS yumi_description. Fetch: fetch_description URDF.
VELOCITY_LIMITS = {
    "yumi": {"1": (3.1416, 42.0), "2": (3.1416, 42.0), "7": (3.1416, 42.0), "3": (3.1416, 24.0),
             "4": (6.9813, 24.0), "5": (6.9813, 7.0), "6": (6.9813, 7.0)},
    "fetch": {
        "torso_lift_joint": (0.1, 450.0), "head_pan_joint": (1.57, 0.32),
        "head_tilt_joint": (1.57, 0.68), "shoulder_pan_joint": (1.256, 33.82),
        "shoulder_lift_joint": (1.454, 131.76), "upperarm_roll_joint": (1.571, 76.94),
        "elbow_flex_joint": (1.521, 66.18), "forearm_roll_joint": (1.571, 29.35),
        "wrist_flex_joint": (2.268, 25.7), "wrist_roll_joint": (2.268, 7.36),
    },
}


# ----------------------------------------------------------------------------- records
@dataclass
class Joint:
    name: str
    type: str  # revolute | prismatic | continuous | fixed
    axis: np.ndarray  # in the child link frame
    lower: float = -np.inf
    upper: float = np.inf
    velocity: float = np.inf
    effort: float = np.inf


@dataclass
class Link:
    name: str
    parent: str | None
    X_PL: np.ndarray  # 4x4 pose of this link frame in the parent link frame at q = 0
    joint: Joint | None = None
    visuals: list = field(default_factory=list)  # (path, 4x4 X_LG, scale)
    collisions: list = field(default_factory=list)  # (path, 4x4 X_LG, scale)
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # about com, link frame
    rgba: tuple = (0.8, 0.8, 0.8, 1.0)


def _tf(R=None, p=None):
    X = np.eye(4)
    if R is not None:
        X[:3, :3] = R
    if p is not None:
        X[:3, 3] = p
    return X


def _rpy(r, p, y):
    return Rotation.from_euler("xyz", [r, p, y]).as_matrix()  # extrinsic x-y-z = URDF/SDF rpy


def _quat_wxyz(q):
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q)
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _floats(s, default):
    return np.array([float(v) for v in s.split()]) if s is not None else np.array(default, float)


# ----------------------------------------------------------------------------- readers
def read_urdf(path: Path, resolve_uri) -> dict[str, Link]:
    """URDF -> links. Link frame = joint frame (URDF convention)."""
    root = ET.parse(path).getroot()
    links: dict[str, Link] = {}
    for el in root.findall("link"):
        link = Link(el.get("name"), None, np.eye(4))
        for tag, dest in (("visual", link.visuals), ("collision", link.collisions)):
            for g in el.findall(tag):
                mesh = g.find("geometry/mesh")
                if mesh is None:
                    continue  # primitive geometry (only on the dropped Panda fingers)
                o = g.find("origin")
                X = _tf(_rpy(*_floats(o.get("rpy") if o is not None else None, [0, 0, 0])),
                        _floats(o.get("xyz") if o is not None else None, [0, 0, 0]))
                scale = _floats(mesh.get("scale"), [1, 1, 1])
                dest.append((resolve_uri(mesh.get("filename")), X, scale))
        inertial = el.find("inertial")
        if inertial is not None:
            o = inertial.find("origin")
            R = _rpy(*_floats(o.get("rpy") if o is not None else None, [0, 0, 0]))
            link.com = _floats(o.get("xyz") if o is not None else None, [0, 0, 0])
            link.mass = float(inertial.find("mass").get("value"))
            i = {k: float(v) for k, v in inertial.find("inertia").attrib.items()}
            I = np.array([[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]],
                          [i["ixz"], i["iyz"], i["izz"]]])
            link.inertia = R @ I @ R.T
        links[link.name] = link
    for el in root.findall("joint"):
        child = links[el.find("child").get("link")]
        child.parent = el.find("parent").get("link")
        o = el.find("origin")
        child.X_PL = _tf(_rpy(*_floats(o.get("rpy") if o is not None else None, [0, 0, 0])),
                         _floats(o.get("xyz") if o is not None else None, [0, 0, 0]))
        jt = el.get("type")
        ax = el.find("axis")
        j = Joint(el.get("name"), jt, _floats(ax.get("xyz") if ax is not None else None, [1, 0, 0]))
        lim = el.find("limit")
        if lim is not None and jt in ("revolute", "prismatic"):
            j.lower, j.upper = float(lim.get("lower")), float(lim.get("upper"))
        if lim is not None:
            j.velocity = float(lim.get("velocity", "inf"))
            j.effort = float(lim.get("effort", "inf"))
        child.joint = j
    return links


def read_mjcf(path: Path, meshdir: Path, prefix: str = "", extra_assets: Path | None = None) -> dict:
    """MJCF bodies -> links (bodies with pos/quat/euler, hinge/slide joints at the body origin).

    Returns {name: Link}; joints carry MuJoCo's `ref` in `Joint.effort`-free attribute `ref`.
    Only the subset of MJCF used by the two sources is supported (asserted).
    """
    meshes = {}
    for src in [p for p in (extra_assets, path) if p is not None]:
        for m in ET.parse(src).getroot().iter("mesh"):
            if m.get("file"):
                meshes[m.get("name")] = (meshdir / m.get("file"), _floats(m.get("scale"), [1, 1, 1]))
    root = ET.parse(path).getroot()
    wb = root.find("worldbody") if root.find("worldbody") is not None else root
    links: dict[str, Link] = {}

    def strip(n):
        return n[len(prefix):] if prefix and n.startswith(prefix) else n

    def frame_of(el):
        R = np.eye(3)
        if el.get("quat") is not None:
            R = _quat_wxyz(_floats(el.get("quat"), None))
        elif el.get("euler") is not None:
            R = Rotation.from_euler("XYZ", _floats(el.get("euler"), None)).as_matrix()
        return _tf(R, _floats(el.get("pos"), [0, 0, 0]))

    def walk(el, parent):
        name = strip(el.get("name"))
        link = Link(name, parent, frame_of(el))
        joints = el.findall("joint")
        link.mj_joints = []
        for j in joints:
            assert np.allclose(_floats(j.get("pos"), [0, 0, 0]), 0), "joint pos must be 0"
            jt = {"hinge": "revolute", "slide": "prismatic", None: "revolute"}[j.get("type")]
            joint = Joint(strip(j.get("name")), jt, _floats(j.get("axis"), [0, 0, 1]))
            joint.ref = float(j.get("ref", 0.0))
            rng = j.get("range")
            if rng is not None and j.get("limited", "true") != "false":
                lo, hi = _floats(rng, None)
                joint.lower, joint.upper = lo - joint.ref, hi - joint.ref
            elif jt == "revolute":
                joint.type = "continuous"
            link.mj_joints.append(joint)
        if len(joints) == 1:
            link.joint = link.mj_joints[0]
        inertial = el.find("inertial")
        if inertial is not None:
            R = np.eye(3)
            if inertial.get("quat") is not None:
                R = _quat_wxyz(_floats(inertial.get("quat"), None))
            link.mass = float(inertial.get("mass"))
            link.com = _floats(inertial.get("pos"), [0, 0, 0])
            link.inertia = R @ np.diag(_floats(inertial.get("diaginertia"), None)) @ R.T
        for g in el.findall("geom"):
            if g.get("mesh") is None:
                continue
            mfile, scale = meshes[g.get("mesh")]
            X = frame_of(g)
            group = g.get("group")
            if group == "1" or g.get("contype") == "0":
                link.visuals.append((mfile, X, scale))
            elif group == "0":
                link.collisions.append((mfile, X, scale))
            else:  # one mesh for both (Fetch)
                link.visuals.append((mfile, X, scale))
                link.collisions.append((mfile, X, scale))
        links[name] = link
        for child in el.findall("body"):
            walk(child, name)

    for b in wb.findall("body"):
        walk(b, None)
    return links


# ----------------------------------------------------------------------------- meshes
def _load_mesh(path: Path, X: np.ndarray, scale):
    m = trimesh.load(str(path), force="mesh", process=True)
    m = trimesh.Trimesh(m.vertices * np.asarray(scale), m.faces, process=True)
    m.apply_transform(X)
    return m


def _cluster(m, h: float):
    """Vertex-clustering decimation: merge the vertices in each h-sized grid cell."""
    keys = np.floor(m.vertices / h).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = inv.max() + 1
    v = np.zeros((n, 3))
    np.add.at(v, inv, m.vertices)
    v /= np.bincount(inv, minlength=n)[:, None]
    f = inv[m.faces]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return trimesh.Trimesh(v, f[np.sort(keep)], process=True)


def _decimate(m, faces: int):
    """Quadric decimation (fast-simplification); meshes that are triangle soups (many small
    components, which quadric collapse cannot reduce) finish with vertex clustering, the grid
    size found by bisection so that the result has at most `faces` triangles."""
    if len(m.faces) <= faces:
        return m
    import fast_simplification

    v, f = fast_simplification.simplify(m.vertices.astype(np.float64), m.faces, target_count=faces)
    out = trimesh.Trimesh(v, f, process=True)
    if len(out.faces) <= 1.2 * faces:
        return out
    lo, hi = 1e-5, float(out.scale)
    for _ in range(30):
        mid = np.sqrt(lo * hi)
        if len(_cluster(out, mid).faces) > faces:
            lo = mid
        else:
            hi = mid
    return _cluster(out, hi)


_WRITTEN: dict[str, Path] = {}  # obj text -> first file with that text (identical meshes shared)


def _write_obj(m, path: Path, normals: bool = False) -> str:
    """Write `m` as .obj unless an identical mesh was already written; returns the file name.
    Visual meshes carry vertex normals (Drake's VTK renderer refuses OBJ files without)."""
    lines = ["# ms_drake convert_robots.py"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in m.vertices]
    if normals:
        lines += [f"vn {x:.4f} {y:.4f} {z:.4f}" for x, y, z in m.vertex_normals]
        lines += [f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}" for a, b, c in m.faces]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    text = "\n".join(lines) + "\n"
    if text in _WRITTEN and _WRITTEN[text].parent == path.parent:
        return _WRITTEN[text].name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    _WRITTEN[text] = path
    return path.name


def _mesh_union(items):
    ms = [_load_mesh(p, X, s) for p, X, s in items]
    return trimesh.util.concatenate(ms) if ms else None


def _hull(m):
    hull = m.convex_hull
    if len(hull.vertices) > HULL_MAX_VERTICES:
        hull = _decimate(hull, 2 * HULL_MAX_VERTICES).convex_hull
    return hull


# ----------------------------------------------------------------------------- writer
def _pose(X) -> str:
    rpy = Rotation.from_matrix(X[:3, :3]).as_euler("xyz")
    return "<pose>" + " ".join(f"{v:.9g}" for v in (*X[:3, 3], *rpy)) + "</pose>"


def _fmt(v) -> str:
    return f"{v:.9g}"


def write_model(robot: str, links: dict[str, Link], frames: dict[str, tuple[str, np.ndarray]],
                out_dir: Path, filter_groups: dict[str, list[str]], inertia_from_mesh: set[str],
                density: float) -> dict:
    """Write meshes + <robot>.sdf. Returns a summary (masses) for the NOTICE."""
    shutil.rmtree(out_dir / "meshes", ignore_errors=True)
    # World (model-frame) pose of every link at q = 0.
    X_M = {}

    def pose_of(name):
        if name not in X_M:
            link = links[name]
            X_M[name] = link.X_PL if link.parent is None else pose_of(link.parent) @ link.X_PL
        return X_M[name]

    for n in links:
        pose_of(n)
    body = []
    summary = {}
    for name, link in links.items():
        vis = _mesh_union(link.visuals)
        col_src = _mesh_union(link.collisions) if link.collisions else vis
        xml = [f'  <link name="{name}">', "    " + _pose(X_M[name])]
        hull = None
        if col_src is not None:
            hull = _hull(col_src)
            col_file = _write_obj(hull, out_dir / "meshes" / "collision" / f"{name}.obj")
        if name in inertia_from_mesh and hull is not None:
            link.mass = float(hull.volume * density)
            link.com = np.asarray(hull.center_mass)
            link.inertia = np.asarray(hull.moment_inertia) * density  # trimesh: unit density
        if link.mass > 0:
            I = link.inertia
            xml += ["    <inertial>", f"      <pose>{' '.join(_fmt(v) for v in link.com)} 0 0 0</pose>",
                    f"      <mass>{_fmt(link.mass)}</mass>", "      <inertia>",
                    f"        <ixx>{_fmt(I[0, 0])}</ixx><ixy>{_fmt(I[0, 1])}</ixy><ixz>{_fmt(I[0, 2])}</ixz>",
                    f"        <iyy>{_fmt(I[1, 1])}</iyy><iyz>{_fmt(I[1, 2])}</iyz><izz>{_fmt(I[2, 2])}</izz>",
                    "      </inertia>", "    </inertial>"]
        summary[name] = link.mass
        if vis is not None:
            vis = _decimate(vis, VISUAL_FACES[robot])
            vis_file = _write_obj(vis, out_dir / "meshes" / "visual" / f"{name}.obj", normals=True)
            rgba = " ".join(_fmt(c) for c in link.rgba)
            xml += ['    <visual name="visual">', "      <geometry><mesh><uri>"
                    f"{PKG}/{robot}/meshes/visual/{vis_file}</uri></mesh></geometry>",
                    f"      <material><diffuse>{rgba}</diffuse></material>", "    </visual>"]
        if hull is not None:
            xml += ['    <collision name="collision">', "      <geometry><mesh><uri>"
                    f"{PKG}/{robot}/meshes/collision/{col_file}</uri><drake:declare_convex/></mesh>"
                    "</geometry>", "    </collision>"]
        xml.append("  </link>")
        body += xml
    for name, link in links.items():
        if link.parent is None:
            continue
        j = link.joint or Joint(f"{link.parent}_to_{name}", "fixed", np.array([1.0, 0, 0]))
        jtype = "revolute" if j.type == "continuous" else j.type
        xml = [f'  <joint name="{j.name}" type="{jtype}">', f"    <parent>{link.parent}</parent>",
               f"    <child>{name}</child>"]
        if jtype != "fixed":
            ax = j.axis / np.linalg.norm(j.axis)
            xml += ["    <axis>", f"      <xyz>{' '.join(_fmt(v) for v in ax)}</xyz>", "      <limit>"]
            if j.type != "continuous":
                xml += [f"        <lower>{_fmt(j.lower)}</lower>", f"        <upper>{_fmt(j.upper)}</upper>"]
            if np.isfinite(j.effort):
                xml.append(f"        <effort>{_fmt(j.effort)}</effort>")
            if np.isfinite(j.velocity):
                xml.append(f"        <velocity>{_fmt(j.velocity)}</velocity>")
            xml += ["      </limit>", "    </axis>"]
        xml.append("  </joint>")
        body += xml
    for fname, (attached, X) in frames.items():
        body += [f'  <frame name="{fname}" attached_to="{attached}">',
                 f'    <pose relative_to="{attached}">' + _pose(X)[6:], "  </frame>"]
    for gname, members in filter_groups.items():
        body += [f'  <drake:collision_filter_group name="{gname}">']
        body += [f"    <drake:member>{m}</drake:member>" for m in members]
        body += [f"    <drake:ignored_collision_filter_group>{gname}</drake:ignored_collision_filter_group>",
                 "  </drake:collision_filter_group>"]
    sdf = ['<?xml version="1.0"?>', "<!-- Generated by tools/convert_robots.py; do not edit. -->",
           '<sdf version="1.9" xmlns:drake="http://drake.mit.edu">', f'<model name="{robot}">'] + body
    sdf += ["</model>", "</sdf>"]
    (out_dir / f"{robot}.sdf").write_text("\n".join(sdf) + "\n")
    return summary


# ----------------------------------------------------------------------------- sources
def _site() -> Path:
    return Path(sysconfig.get_paths()["purelib"])


def _pkg_dir(mod: str) -> Path:
    spec = importlib.util.find_spec(mod)
    if spec is None:
        sys.exit(f"convert_robots: Python package {mod!r} is not installed in this venv; "
                 f"pip install it (see the module docstring).")
    return Path(spec.submodule_search_locations[0])


def _fold_fixed_massless(links: dict[str, Link], keep: set[str]) -> dict[str, tuple[str, np.ndarray]]:
    """Turn leaf-ish massless links without geometry into frames on their parent. Returns frames."""
    frames = {}
    changed = True
    while changed:
        changed = False
        for name, link in list(links.items()):
            if name in keep or link.parent is None:
                continue
            movable = link.joint is not None and link.joint.type != "fixed"
            has_children = any(l.parent == name for l in links.values())
            if not movable and link.mass <= 0 and not link.visuals and not link.collisions and not has_children:
                frames[name] = (link.parent, link.X_PL)
                del links[name]
                changed = True
    # frames attached to removed frames: re-express on the surviving link
    for fname, (att, X) in list(frames.items()):
        while att in frames:
            att, X = frames[att][0], frames[att][1] @ X
        frames[fname] = (att, X)
    return frames


def convert_panda():
    base = _site() / "cmeel.prefix" / "share" / "example-robot-data" / "robots" / "panda_description"
    if not base.is_dir():
        sys.exit("convert_robots: example-robot-data is not installed; pip install example-robot-data==6.0.0")

    def resolve(uri):
        return base / uri.split("panda_description/")[1]

    links = read_urdf(base / "urdf" / "panda.urdf", resolve)
    # Drop the Franka hand: we weld our own compliant parallel jaw to panda_link8.
    for n in ("panda_hand", "panda_hand_tcp", "panda_leftfinger", "panda_rightfinger"):
        links.pop(n)
    for n, link in links.items():
        link.rgba = (0.95, 0.95, 0.95, 1.0) if n not in ("panda_link0", "panda_link7") else (0.25, 0.25, 0.27, 1.0)
        if link.mass == 0:
            link.mass = 0.0
    frames = _fold_fixed_massless(links, keep=set())
    out = MODELS / "panda"
    summary = write_model("panda", links, frames, out, {"base": ["panda_link0", "panda_link1"], "wrist": ["panda_link5", "panda_link6", "panda_link7"]}, set(), 0)
    notice = f"""Franka Emika Panda arm (7 DoF, without the Franka hand)
Converted by tools/convert_robots.py (python -m tools.convert_robots --robot panda).

Source: PyPI package example-robot-data 6.0.0, robots/panda_description (urdf/panda.urdf),
generated from franka_ros/franka_description (https://github.com/frankaemika/franka_ros).
Licence: Apache License 2.0 (Copyright Franka Emika GmbH). A copy of the licence is at
https://www.apache.org/licenses/LICENSE-2.0 ; it applies to the meshes and kinematic/inertial
data in this folder, which are a derivative work (format conversion).

Changes: the hand and fingers were removed (ms_drake welds its own grippers to frame
panda_link8, the flange); .dae visual meshes converted to .obj and decimated to <= {VISUAL_FACES["panda"]}
triangles; collision geometry is the convex hull of each franka_ros collision .stl
(drake:declare_convex). Inertias, joint position, velocity and effort limits are franka_ros values.
Link masses [kg]: {json.dumps({k: round(v, 4) for k, v in summary.items()})}
"""
    (out / "NOTICE").write_text(notice)

    # Reference FK from the SOURCE URDF with Drake's URDF parser (geometry stripped).
    tree = ET.parse(base / "urdf" / "panda.urdf")
    for link in tree.getroot().findall("link"):
        for tag in ("visual", "collision"):
            for g in link.findall(tag):
                link.remove(g)
    text = ET.tostring(tree.getroot(), encoding="unicode")

    plant = MultibodyPlant(0.0)
    Parser(plant).AddModelsFromString(text, "urdf")
    plant.Finalize()
    names = [f"panda_joint{i}" for i in range(1, 8)]
    lims = [(plant.GetJointByName(n).position_lower_limits()[0], plant.GetJointByName(n).position_upper_limits()[0])
            for n in names]
    bodies = [f"panda_link{i}" for i in range(8 + 1)]
    configs = _sample_configs(names, lims)

    def fk(q):
        ctx = plant.CreateDefaultContext()
        for n, v in q.items():
            plant.GetJointByName(n).set_angle(ctx, v)
        X_W0 = plant.GetFrameByName("panda_link0").CalcPoseInWorld(ctx)
        return {b: (X_W0.inverse() @ plant.GetFrameByName(b).CalcPoseInWorld(ctx)).GetAsMatrix4().tolist()
                for b in bodies}

    _write_fk("panda", "panda_link0", configs, fk, "example-robot-data 6.0.0 panda.urdf via Drake's URDF parser")


def _sample_configs(names, lims, n_random=3):
    rng = np.random.default_rng(SEED)
    configs = [{n: 0.0 for n in names}]
    for _ in range(n_random):
        q = {}
        for n, (lo, hi) in zip(names, lims):
            lo, hi = (max(lo, -np.pi), min(hi, np.pi))
            q[n] = float(rng.uniform(lo, hi))
        configs.append(q)
    # keep zero config only if within limits; clip anyway for the joints with limits
    for q in configs:
        for n, (lo, hi) in zip(names, lims):
            q[n] = float(np.clip(q[n], lo, hi))
    return configs


def _write_fk(robot, root, configs, fk, source):
    TESTDATA.mkdir(parents=True, exist_ok=True)
    data = {"robot": robot, "root": root, "source": source, "tolerance_m": 1e-3,
            "configs": [{"q": q, "X_root_frame": fk(q)} for q in configs]}
    (TESTDATA / f"fk_{robot}.json").write_text(json.dumps(data, indent=1))


def _mujoco_fk(xml_text: str, assets_dir: Path, root: str, prefix: str, joint_names, ref, bodies, configs):
    import mujoco

    model = mujoco.MjModel.from_xml_string(xml_text)
    data = mujoco.MjData(model)
    out = []

    def fk(q):
        data.qpos[:] = model.qpos0
        for n, v in q.items():
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, prefix + n)
            data.qpos[model.jnt_qposadr[jid]] = v + ref.get(n, 0.0)
        mujoco.mj_kinematics(model, data)

        def X(b):
            bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + b)
            T = np.eye(4)
            T[:3, :3] = data.xmat[bid].reshape(3, 3)
            T[:3, 3] = data.xpos[bid]
            return T

        X_root_inv = np.linalg.inv(X(root))
        return {b: (X_root_inv @ X(b)).tolist() for b in bodies}

    return fk


def convert_yumi():
    src = _pkg_dir("robosuite_models") / "assets" / "robots" / "yumi"
    links = read_mjcf(src / "robot.xml", src)
    # base / right_arm / left_arm are empty frames at the origin; hands are massless frames.
    for n in ("right_arm", "left_arm"):
        for l in links.values():
            if l.parent == n:
                l.parent = "yumi_body"
                l.X_PL = links[n].X_PL @ l.X_PL
        links.pop(n)
    links["yumi_body"].parent = None
    links["yumi_body"].X_PL = links["base"].X_PL @ links["yumi_body"].X_PL
    links.pop("base")
    for l in links.values():
        if l.name.startswith("yumi_link"):
            num = l.joint.name.split("_")[2]
            l.joint.velocity, l.joint.effort = VELOCITY_LIMITS["yumi"][num]
            l.rgba = (0.85, 0.85, 0.85, 1.0) if num in ("1", "3", "5", "6") else (0.6, 0.6, 0.62, 1.0)
    links["yumi_body"].rgba = (0.85, 0.85, 0.85, 1.0)
    for h in ("right_hand", "left_hand"):
        links[h].mass = 0.0
    frames = _fold_fixed_massless(links, keep=set())
    out = MODELS / "yumi"
    groups = {"body": ["yumi_body", "yumi_link_1_r", "yumi_link_1_l", "yumi_link_2_r", "yumi_link_2_l"],
              "wrist_r": ["yumi_link_5_r", "yumi_link_6_r", "yumi_link_7_r"],
              "wrist_l": ["yumi_link_5_l", "yumi_link_6_l", "yumi_link_7_l"]}
    summary = write_model("yumi", links, frames, out, groups,
                          inertia_from_mesh=set(links), density=YUMI_DENSITY)
    notice = f"""ABB YuMi (IRB 14000), two 7-DoF arms, without grippers
Converted by tools/convert_robots.py (python -m tools.convert_robots --robot yumi).

Source: PyPI package robosuite-models 1.0.0, robosuite_models/assets/robots/yumi (robot.xml, MJCF;
meshes/*.stl full, meshes/coarse/*.stl coarse), https://github.com/ARISE-Initiative/robosuite_models.
Licence: MIT (robosuite-models). The YuMi geometry derives from ROS yumi_description
(OrebroUniversity/yumi, BSD-2-Clause). This folder is a derivative work (format conversion).

Changes: full .stl visual meshes decimated to <= {VISUAL_FACES["yumi"]} triangles and written as .obj;
collision = convex hull of each coarse .stl (drake:declare_convex). The source inertias are
placeholders (2 kg, 0.1 kg m^2 on every link), so every inertia was recomputed from the convex hull
of the coarse mesh at a uniform density of {YUMI_DENSITY:g} kg/m^3 (hollow cast links; the arm then
weighs ~7 kg, the real one ~9.5 kg with motors; the body is welded so its mass is irrelevant).
Joint ranges from the MJCF; velocity / effort limits (not in the MJCF) from ABB's product
specification as in yumi_description: {json.dumps(VELOCITY_LIMITS['yumi'])} (by joint number).
Joint order along each arm (chain order): 1, 2, 7, 3, 4, 5, 6 (yumi_description naming).
Grippers weld to yumi_link_7_r / yumi_link_7_l (frames right_hand / left_hand coincide with them).
Link masses [kg]: {json.dumps({k: round(v, 4) for k, v in summary.items()})}
"""
    (out / "NOTICE").write_text(notice)
    names, lims, ref = [], [], {}
    for side in ("r", "l"):
        for num in ("1", "2", "7", "3", "4", "5", "6"):
            n = f"yumi_joint_{num}_{side}"
            j = next(l.joint for l in links.values() if l.joint is not None and l.joint.name == n)
            names.append(n)
            lims.append((j.lower, j.upper))
    bodies = [n for n in links if n != "yumi_body"] + list(frames)
    fk = _mujoco_fk((src / "robot.xml").read_text().replace('file="meshes/', f'file="{src}/meshes/'),
                    src, "yumi_body", "", names, ref, bodies, None)
    _write_fk("yumi", "yumi_body", _sample_configs(names, lims), fk,
              "robosuite-models 1.0.0 yumi/robot.xml via MuJoCo mj_kinematics")


def convert_fetch():
    src = _pkg_dir("gymnasium_robotics") / "envs" / "assets"
    meshdir = src / "stls" / "fetch"
    links = read_mjcf(src / "fetch" / "robot.xml", meshdir, prefix="robot0:",
                      extra_assets=src / "fetch" / "shared.xml")
    links.pop("mocap")
    links.pop("external_camera_body_0")
    # Drop the Fetch two-finger gripper (the bluction tool replaces it) and tiny base add-ons.
    for n in ("r_gripper_finger_link", "l_gripper_finger_link", "estop_link", "laser_link"):
        links.pop(n)
    gripper = links.pop("gripper_link")
    for l in links.values():
        if l.parent == "gripper_link":
            l.parent = "wrist_roll_link"
            l.X_PL = gripper.X_PL @ l.X_PL
    ref = {}
    base = links["base_link"]
    base.X_PL = np.eye(4)  # the model origin is the base (the source offsets it in its scene)
    base.parent = "base_yaw_link"
    base.joint = Joint("base_yaw", "continuous", np.array([0.0, 0, 1]), velocity=1.0, effort=100.0)
    new = {
        "base_origin": Link("base_origin", None, np.eye(4)),
        "base_x_link": Link("base_x_link", "base_origin", np.eye(4),
                            Joint("base_x", "prismatic", np.array([1.0, 0, 0]), -10, 10, 1.0, 1000.0)),
        "base_yaw_link": Link("base_yaw_link", "base_x_link", np.eye(4),
                              Joint("base_y", "prismatic", np.array([0, 1.0, 0]), -10, 10, 1.0, 1000.0)),
    }
    links = {**new, **links}
    for l in links.values():
        if l.joint is not None and l.joint.name in VELOCITY_LIMITS["fetch"]:
            l.joint.velocity, l.joint.effort = VELOCITY_LIMITS["fetch"][l.joint.name]
            if l.joint.ref:
                ref[l.joint.name] = l.joint.ref
        if l.mass > 0 and np.all(np.linalg.eigvalsh(l.inertia) <= 0):
            l.mass = 0.0
        blue = l.name in ("shoulder_lift_link", "elbow_flex_link", "wrist_flex_link", "head_tilt_link",
                          "torso_fixed_link")
        l.rgba = (0.086, 0.506, 0.767, 1.0) if blue else (0.85, 0.85, 0.85, 1.0)
        if l.name in ("base_link", "head_pan_link"):
            l.rgba = (0.356, 0.361, 0.376, 1.0)
    # keep the gripper link's pose as a frame (the tool flange)
    frames_extra = {"gripper_link": ("wrist_roll_link", gripper.X_PL)}
    frames = _fold_fixed_massless(links, keep={"base_origin", "base_x_link", "base_yaw_link"})
    # Tool flange: the outer face of wrist_roll_link's mesh along its x axis (where the Fetch gripper
    # mounts); tools weld here instead of at gripper_link, which is the centre of the Fetch gripper.
    wrist = links["wrist_roll_link"]
    x_face = float(max(_mesh_union(wrist.collisions).vertices[:, 0]))
    frames_extra["wrist_flange"] = ("wrist_roll_link", _tf(p=[round(x_face, 4), 0.0, 0.0]))
    frames.update(frames_extra)
    out = MODELS / "fetch"
    groups = {"torso": ["base_link", "torso_fixed_link", "torso_lift_link", "shoulder_pan_link", "head_pan_link"]}
    summary = write_model("fetch", links, frames, out, groups, set(), 0)
    notice = f"""Fetch mobile manipulator (planar base, torso lift, head pan/tilt, 7-DoF arm), without its gripper
Converted by tools/convert_robots.py (python -m tools.convert_robots --robot fetch).

Source: PyPI package gymnasium-robotics 1.4.2, gymnasium_robotics/envs/assets/fetch/robot.xml and
shared.xml (MJCF) and assets/stls/fetch/*.stl, https://github.com/Farama-Foundation/Gymnasium-Robotics.
Licence: MIT (gymnasium-robotics, derived from OpenAI gym robotics); the meshes and inertias come
from fetch_description (Fetch Robotics, BSD-3-Clause). This folder is a derivative work.

Changes: the source's three slide joints are replaced by a planar base: joints base_x, base_y
(prismatic, through massless links base_x_link and base_yaw_link) and base_yaw (revolute) above
base_link; the model root is base_origin. The two-finger gripper was removed; frame gripper_link keeps
its pose on wrist_roll_link and the new frame wrist_flange marks the outer face of wrist_roll_link
along x (where tools such as the bluction weld); estop and laser bodies removed; zero-mass camera bodies became frames (head_camera_*). MuJoCo's ref=0.06 on
head_tilt_joint is folded in (our angle = MuJoCo qpos - 0.06, limits shifted alike).
Meshes: the source collision .stl decimated to <= {VISUAL_FACES["fetch"]} triangles for visuals; collision
= convex hull per link (drake:declare_convex). Inertias from the source (fetch_description).
Velocity / effort limits (absent from the MJCF) from fetch_description:
{json.dumps(VELOCITY_LIMITS['fetch'])}.
Link masses [kg]: {json.dumps({k: round(v, 4) for k, v in summary.items()})}
"""
    (out / "NOTICE").write_text(notice)
    names = ["torso_lift_joint", "head_pan_joint", "head_tilt_joint", "shoulder_pan_joint",
             "shoulder_lift_joint", "upperarm_roll_joint", "elbow_flex_joint", "forearm_roll_joint",
             "wrist_flex_joint", "wrist_roll_joint"]
    lims = []
    for n in names:
        j = next(l.joint for l in links.values() if l.joint is not None and l.joint.name == n)
        lims.append((j.lower, j.upper))
    bodies = [n for n in links if not n.startswith("base_")] + [f for f in frames if f not in frames_extra]
    wrapper = f"""<mujoco><compiler angle="radian" meshdir="{meshdir}" texturedir="{src / "textures"}"/>
      <include file="{src / 'fetch' / 'shared.xml'}"/>
      <worldbody><include file="{src / 'fetch' / 'robot.xml'}"/></worldbody></mujoco>"""
    # MuJoCo resolves the body list; the tool frame gripper_link is a body in the source.
    fk = _mujoco_fk(wrapper, meshdir, "base_link", "robot0:", names, ref, bodies + ["gripper_link"], None)
    _write_fk("fetch", "base_link", _sample_configs(names, lims), fk,
              "gymnasium-robotics 1.4.2 fetch/robot.xml via MuJoCo mj_kinematics")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", choices=["panda", "yumi", "fetch", "all"], required=True)
    args = ap.parse_args(argv)
    robots = ["panda", "yumi", "fetch"] if args.robot == "all" else [args.robot]
    for r in robots:
        {"panda": convert_panda, "yumi": convert_yumi, "fetch": convert_fetch}[r]()
        print(f"wrote {MODELS / r} and {TESTDATA / f'fk_{r}.json'}")


if __name__ == "__main__":
    main()
