"""IndexedGraspPlanner: the grasp planner of the bin search on pre-computed grasp sets (the
reference's simulations index Dex-Net 1.0 grasps per object, lines 1262-1264).

Ports (declared first; those of LazyGraspPlanner, so the selector is unchanged):
  inputs  depth_image (ImageDepth32F), masks (InstanceMasks), objects (tuple[ObjectGeometry])
  output  grasps: LazyGrasps (object id -> its best Grasp over the jaw and the suction cup)

Per object looked up (on demand, as LazyGraspPlanner): its grasp set (ms_drake.grasping.grasp_sets)
moved to the object's current pose; candidates out of reach dropped (approach tilted more than
`max_tilt` from world -z, grasp point outside the bin's inner box or below its floor);
the rest taken best quality first (ties: jaw grasps the less tilted; suction grasps the nearer the
object's centre of mass across the floor, the weight's lever arm about the cup, which decides the
stations' lifts more often the farther it is: docs/results/ch7_bin_search.md, then the less tilted), and the
first whose gripper is free
of the scene is the object's grasp of that kind. Free: the gripper's geometry -- the jaw's palm
and two fingers (with their pads) opened to the grasp's width (the contacts' distance and a
margin each side: the opening the station's jaw comes down with), or the suction cup and its shaft lifted `suction_clearance` off the surface -- does not
intersect (coal, shrunk by `margin`) any object's collision shapes (the grasped object's
included) or the bin, at the grasp and on the way a station's gripper comes to it (`approach`,
robots.PickApproach: back along the approach to the pre-grasp, and straight up from there,
descent_clearance clear, until above everything). At most `max_checks`
candidates per kind and object are checked (candidates are sorted; the cap bounds a buried
object's cost). Objects without a grasp set, or whose set has no free grasp at their pose, go to
`fallback` (a LazyGraspPlanner: the image-based planners) when given, else get no grasp.
With `reach` (a callable Grasp -> bool or Grasp, e.g. ms_drake.execution.reach.PickReach of a
robot) a free grasp must also be one the robot reaches (a Grasp returned is the grasp to use: the
same with the arm posture that reaches it); at most `max_reach_checks` free candidates per
kind and object are tried (each check is an IK plan, 20-250 ms); the fallback's grasps are
checked too. A reach with a true `checks_scene` attribute is called as reach(grasp, scene) with
the step's Scene (PickReach: the arm's links must stay clear of the objects along the approach).

Broad phase: each shape carries a bounding sphere; coal.collide runs only on gripper-part /
shape pairs whose spheres overlap.
"""

from __future__ import annotations

import functools
import zlib

import coal
import numpy as np
import trimesh
from pydrake.systems.framework import LeafSystem
from scipy.spatial.transform import Rotation

from ms_drake.geometry import Workspace, as_matrix4, coal_convex
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp, SuctionGrasp
from ms_drake.grasping.grasp_sets import GraspSet
from ms_drake.grasping.planner import LazyGraspPlanner, LazyGrasps, declare_lazy_grasp_ports
from ms_drake.objects import get_object
from ms_drake.paths import PACKAGE_NAME, models_dir
from ms_drake.robots import PICK_APPROACH, ParallelJawConfig, PickApproach, SuctionCupConfig
from ms_drake.station.environments import _boxes
from ms_drake.types import Grasp

# (coal shape, 4x4 pose in the owner's frame, bounding-sphere centre in that frame, radius)
Part = tuple


def _pose(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose[3:]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def _convex(points: np.ndarray):
    hull = trimesh.convex.convex_hull(np.asarray(points, float))
    v = np.asarray(hull.vertices, float)
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    return coal_convex(v, hull.faces), c, float(np.linalg.norm(v - c, axis=1).max())


def _primitive(kind: str, size) -> tuple:
    if kind == "box":
        return coal.Box(*(float(s) for s in size)), 0.5 * float(np.linalg.norm(size))
    if kind == "cylinder":
        return coal.Cylinder(float(size[0]), float(size[1])), float(np.hypot(size[0], 0.5 * size[1]))
    if kind == "sphere":
        return coal.Sphere(float(size[0])), float(size[0])
    raise GraspError(f"no collision shape for kind {kind!r}")


@functools.lru_cache(maxsize=2048)
def object_parts(full_name: str) -> tuple[Part, ...]:
    """The collision shapes of a registry object (object frame), as coal parts."""
    out = []
    for s in get_object(full_name).collisions:
        T = _pose(s.pose)
        if s.kind in ("convex", "mesh"):
            rel = s.uri.split(f"package://{PACKAGE_NAME}/", 1)[-1]
            pts = np.asarray(trimesh.load(models_dir() / rel, force="mesh", process=False).vertices, float)
            shape, c, r = _convex(pts)
            out.append((shape, T, (T[:3, :3] @ c + T[:3, 3]), r))
        else:
            shape, r = _primitive(s.kind, s.size)
            out.append((shape, T, T[:3, 3].copy(), r))
    return tuple(out)


def environment_parts(scenario) -> tuple[Part, ...]:
    """The bin's floor, walls and support as coal parts in the world frame."""
    env = scenario.environment
    X = np.eye(4)
    X[:3, 3] = np.asarray(env.position, float)
    out = []
    for _, sh, _ in _boxes(env.type, env.resolved_size(), env.wall_thickness):
        shape, r = _primitive(sh.kind, sh.size)
        T = X @ _pose(sh.pose)
        out.append((shape, T, T[:3, 3].copy(), r))
    return tuple(out)


class GripperGeometry:
    """The collision geometry of the jaw (palm, two fingers with their pads) and of the suction
    tool (cup, shaft), built once (coal shapes shrunk by `margin` on every side); `jaw(...)` and
    `suction(...)` give the parts (coal shape, 3x3 rotation, world centre, bounding radius) at a
    grasp."""

    def __init__(self, jaw: ParallelJawConfig, cup: SuctionCupConfig, margin: float, clearance: float):
        p = jaw.pads
        pz, flen = jaw.palm_size[2], jaw.finger_length
        tcp_z = pz + flen - p.length / 2  # tool point (pads' centre) in the gripper body, z along the approach
        self.thick = p.thickness + jaw.finger_thickness
        palm = (np.asarray(jaw.palm_size, float) - 2 * margin).clip(1e-6)
        finger = (np.array([self.thick, jaw.finger_depth, flen], float) - 2 * margin).clip(1e-6)
        self.palm, self.palm_r, self.palm_z = coal.Box(*palm), 0.5 * float(np.linalg.norm(palm)), pz / 2 - tcp_z
        self.finger, self.finger_r = coal.Box(*finger), 0.5 * float(np.linalg.norm(finger))
        self.finger_z = pz + flen / 2 - tcp_z
        self.cup_parts = []
        for radius, length, back in ((cup.cup_radius, cup.cup_height, 0.0),
                                     (cup.stem_radius, cup.stem_length, cup.cup_height)):
            r, h = max(radius - margin, 1e-6), max(length - 2 * margin, 1e-6)
            self.cup_parts.append((coal.Cylinder(r, h), float(np.hypot(r, 0.5 * h)), clearance + back + 0.5 * length))

    def jaw(self, center, axis, approach, width, across=None) -> list:
        """Palm and fingers opened to `width` with the tool point at `center` (x = axis, z = approach)."""
        ax, ap = np.asarray(axis, float), np.asarray(approach, float)
        across = np.cross(ap, ax) if across is None else across
        R = np.empty((3, 3))
        R[:, 0], R[:, 1], R[:, 2] = ax, across, ap
        c = np.asarray(center, float)
        fx = 0.5 * float(width) + 0.5 * self.thick
        fz = c + self.finger_z * ap
        return [(self.palm, R, c + self.palm_z * ap, self.palm_r),
                (self.finger, R, fz - fx * ax, self.finger_r), (self.finger, R, fz + fx * ax, self.finger_r)]

    def suction(self, point, approach) -> list:
        """Cup and shaft along the approach, the lip `clearance` off the surface point."""
        ap = np.asarray(approach, float)
        h = np.array([1.0, 0.0, 0.0]) if abs(ap[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(h, ap)
        x /= np.linalg.norm(x)
        R = np.empty((3, 3))
        R[:, 0], R[:, 1], R[:, 2] = x, np.cross(ap, x), ap  # z along the approach (the cylinders' axis)
        p = np.asarray(point, float)
        return [(shape, R, p - back * ap, r) for shape, r, back in self.cup_parts]


def jaw_parts(center, axis, approach, width, config: ParallelJawConfig, margin: float) -> list:
    """(coal box, 3x3 rotation, world centre, radius) of the jaw's palm and fingers opened to
    `width`, tool point (the pads' centre) at `center`; boxes shrunk by `margin` on every side."""
    return GripperGeometry(config, SuctionCupConfig(), margin, 0.0).jaw(center, axis, approach, width)


def suction_parts(point, approach, config: SuctionCupConfig, clearance: float, margin: float) -> list:
    """The suction cup and its shaft (cylinders along the approach) with the lip `clearance` off
    the surface point, shrunk by `margin`."""
    return GripperGeometry(ParallelJawConfig(), config, margin, clearance).suction(point, approach)


class Scene:
    """Every collision part of the objects at their current poses and of the environment, with
    their bounding spheres for the broad phase."""

    def __init__(self, parts: list):
        self.shapes = [p[0] for p in parts]
        self.transforms = [coal.Transform3s(p[1][:3, :3], p[1][:3, 3]) for p in parts]
        self.centers = np.array([p[2] for p in parts], float).reshape(-1, 3)
        self.radii = np.array([p[3] for p in parts], float)
        self.request = coal.CollisionRequest()

    def top_over(self, gripper: list, margin: float = 0.0) -> float:
        """The highest bounding-sphere top [m, world z] of the parts that a vertical line through
        the gripper's parts (coal shape, 3x3 rotation, centre, radius) could come within `margin`
        of (-inf when none): above it, a gripper rising straight up touches nothing."""
        top = -np.inf
        for _, _, c, r in gripper:
            d = self.centers[:, :2] - np.asarray(c, float)[:2]
            near = np.einsum("ij,ij->i", d, d) < (self.radii + r + margin) ** 2
            if near.any():
                top = max(top, float(np.max(self.centers[near, 2] + self.radii[near])))
        return top

    def hits(self, gripper: list, margin: float = 0.0) -> bool:
        """True when any gripper part (coal shape, 3x3 rotation, centre, radius) intersects any
        scene part, or (margin > 0) comes closer to one than `margin` [m]."""
        request = self.request
        if margin > 0:
            request = coal.CollisionRequest()
            request.security_margin = float(margin)
        for shape, R, c, r in gripper:
            d = self.centers - c
            near = np.nonzero(np.einsum("ij,ij->i", d, d) < (self.radii + r + margin) ** 2)[0]
            if len(near) == 0:
                continue
            Tg = coal.Transform3s(R, c)
            for j in near:
                res = coal.CollisionResult()
                if coal.collide(shape, Tg, self.shapes[j], self.transforms[j], request, res):
                    return True
        return False


def _world_parts(parts, X: np.ndarray) -> list:
    return [(s, X @ T, X[:3, :3] @ c + X[:3, 3], r) for s, T, c, r in parts]


class IndexedGraspPlanner(LeafSystem):
    """Best collision-free, reachable grasp per object from its grasp set (module docstring).

    names: object id -> registry full name ("procedural/box_003"), for the collision shapes;
    grasp_sets: object id -> GraspSet (ids without one go to `fallback`); environment: coal parts
    of the static scene (environment_parts(scenario)); workspace: the bin's inner box (reach);
    kinds: the grasp kinds the robot can execute ("parallel_jaw", "suction")."""

    def __init__(self, names: dict, grasp_sets: dict, environment, workspace: Workspace, width: int, height: int,
                 kinds=("parallel_jaw", "suction"), fallback: LazyGraspPlanner | None = None,
                 max_tilt: float = np.radians(45.0), min_quality: float = 0.05, max_checks: int = 48,
                 margin: float = 0.001, suction_clearance: float = 0.003,
                 jaw: ParallelJawConfig | None = None, cup: SuctionCupConfig | None = None, jaw_model: str = "",
                 reach=None, max_reach_checks: int = 8, approach: PickApproach | None = None):
        super().__init__()
        self.depth_port, self.masks_port, self.objects_port, self.grasps_port = declare_lazy_grasp_ports(
            self, width, height, self._calc)
        bad = [k for k in kinds if k not in ("parallel_jaw", "suction")]
        if bad or not kinds:
            raise GraspError(f"IndexedGraspPlanner kinds {tuple(kinds)!r}: use 'parallel_jaw' and / or 'suction'")
        if not (0 < max_tilt <= np.pi / 2):
            raise GraspError(f"IndexedGraspPlanner max_tilt must be in (0, pi/2] rad, got {max_tilt!r}")
        if int(max_checks) < 1:
            raise GraspError(f"IndexedGraspPlanner max_checks must be >= 1, got {max_checks!r}")
        for oid, gs in grasp_sets.items():
            if not isinstance(gs, GraspSet):
                raise GraspError(f"grasp_sets[{oid!r}] must be a GraspSet, got {type(gs).__name__}")
        self.names, self.sets = dict(names), dict(grasp_sets)
        self.environment = tuple(environment)
        self.workspace, self.kinds, self.fallback = workspace, tuple(kinds), fallback
        self.cos_tilt, self.min_quality, self.max_checks = float(np.cos(max_tilt)), float(min_quality), int(max_checks)
        self.margin, self.suction_clearance = float(margin), float(suction_clearance)
        self.jaw, self.cup = jaw or ParallelJawConfig(), cup or SuctionCupConfig()
        self.approach = approach or PICK_APPROACH
        self.gripper = GripperGeometry(self.jaw, self.cup, self.margin, self.suction_clearance)
        self.jaw_model = jaw_model or next((gs.model for gs in self.sets.values()), "soft_point")
        self._hull_cache: dict = {}
        if reach is not None and not callable(reach):
            raise GraspError(f"IndexedGraspPlanner reach must be a callable Grasp -> bool, got {type(reach).__name__}")
        if int(max_reach_checks) < 1:
            raise GraspError(f"IndexedGraspPlanner max_reach_checks must be >= 1, got {max_reach_checks!r}")
        self.reach, self.max_reach_checks = reach, int(max_reach_checks)

    # ------------------------------------------------------------------ scene
    def _parts_of(self, geom) -> tuple:
        name = self.names.get(geom.id)
        if name is not None:
            return object_parts(name)
        v = np.ascontiguousarray(geom.vertices, float)
        key = (geom.id, v.shape, zlib.crc32(v.tobytes()))
        if key not in self._hull_cache:  # an object not in the registry: its mesh's convex hull
            shape, c, r = _convex(v)
            self._hull_cache[key] = ((shape, np.eye(4), c, r),)
        return self._hull_cache[key]

    def scene(self, objects) -> Scene:
        parts = list(self.environment)
        for g in objects:
            parts.extend(_world_parts(self._parts_of(g), as_matrix4(g.X_WO, f"objects[{g.id!r}].X_WO")))
        return Scene(parts)

    def _reachable(self, p_W: np.ndarray) -> np.ndarray:
        return self.workspace.inside_xy(p_W) & (p_W[:, 2] > self.workspace.floor_z)

    # ------------------------------------------------------------------ planning
    def plan_object(self, oid: str, geoms: dict, scene: Scene) -> tuple[Grasp, ...]:
        """The best free jaw and suction grasps of object `oid` from its grasp set (world frame)."""
        gs, geom = self.sets.get(oid), geoms.get(oid)
        if gs is None or geom is None:
            return ()
        X = as_matrix4(geom.X_WO, f"objects[{oid!r}].X_WO")
        R, t = X[:3, :3], X[:3, 3]
        out = []
        if "parallel_jaw" in self.kinds and len(gs.jaw_center):
            c = gs.jaw_center @ R.T + t
            a = gs.jaw_axis @ R.T
            ap = gs.jaw_approaches() @ R.T  # (n, A, 3)
            q = gs.jaw_quality
            down = -ap[..., 2]
            ok = (down >= self.cos_tilt) & (q >= self.min_quality) & self._reachable(c)[:, None]
            i, k = np.nonzero(ok)
            order = np.lexsort((-down[i, k], -q[i, k]))[: self.max_checks]
            across = np.cross(ap[i[order], k[order]], a[i[order]])
            def jaw_at(j, y):  # the jaw opened to the grasp's width, moved by an offset
                return lambda o: self.gripper.jaw(c[i[j]] + o, a[i[j]], ap[i[j], k[j]], gs.jaw_width[i[j]], y)
            g = self._first_reached(scene, (
                ParallelJawGrasp(c[i[j]], a[i[j]], ap[i[j], k[j]], gs.jaw_width[i[j]]).to_grasp(
                    float(q[i[j], k[j]]), self.jaw_model, oid)
                for j, y in zip(order, across) if self._free(scene, jaw_at(j, y), ap[i[j], k[j]])))
            if g is not None:
                out.append(g)
        if "suction" in self.kinds and len(gs.suction_point):
            p = gs.suction_point @ R.T + t
            ap = -(gs.suction_normal @ R.T)
            q = gs.suction_quality
            down = -ap[:, 2]
            ok = (down >= self.cos_tilt) & (q >= self.min_quality) & self._reachable(p)
            idx = np.nonzero(ok)[0]
            com = R @ (np.asarray(geom.com, float) if geom.com is not None else geom.vertices.mean(axis=0)) + t
            arm = np.hypot(*(p[idx, :2] - com[:2]).T)  # the weight's lever arm about the cup, held upright
            order = idx[np.lexsort((-down[idx], arm, -q[idx]))][: self.max_checks]
            g = self._first_reached(scene, (
                SuctionGrasp(p[n], ap[n]).to_grasp(float(q[n]), "suction", oid) for n in order
                if self._free(scene, lambda o, n=n: self.gripper.suction(p[n] + o, ap[n]), ap[n])))
            if g is not None:
                out.append(g)
        return tuple(out)

    def _free(self, scene: Scene, parts_at, approach) -> bool:
        """Whether the gripper (parts_at(offset): its parts moved by `offset`, world [m]) is free of
        the scene at the grasp and on its way there (robots.PickApproach): at `steps` poses back
        along the approach to the pre-grasp, and, `descent_clearance` clear, on the straight line
        up from the pre-grasp in 2 cm steps until it is above everything under it."""
        if scene.hits(parts_at(np.zeros(3))):
            return False
        A, ap = self.approach, np.asarray(approach, float)
        if any(scene.hits(parts_at(-d * ap)) for d in np.linspace(A.distance, 0.0, A.steps + 1)[:-1]):
            return False
        pre = -A.distance * ap
        parts = parts_at(pre)
        top = scene.top_over(parts, A.descent_clearance)
        rise = 0.0
        while min(c[2] - r for _, _, c, r in parts) <= top:
            if scene.hits(parts, A.descent_clearance):
                return False
            rise += 0.02
            parts = parts_at(pre + np.array([0.0, 0.0, rise]))
        return True

    def _reaches(self, grasp, scene: Scene):
        """`reach` of the grasp (True without one): a bool, or the grasp to use instead (e.g. with
        the arm posture that reaches it); a reach with `checks_scene` (PickReach) is given the
        scene too, to keep the arm clear of it."""
        if self.reach is None:
            return True
        return self.reach(grasp, scene) if getattr(self.reach, "checks_scene", False) else self.reach(grasp)

    def _first_reached(self, scene: Scene, free_grasps):
        """The first of the collision-free grasps (best first) the robot reaches: without `reach`
        the first; with it, among at most `max_reach_checks` of them; None when there is none."""
        for checks, g in enumerate(free_grasps, start=1):
            reached = self._reaches(g, scene)
            if reached:
                return reached if isinstance(reached, Grasp) else g
            if checks >= self.max_reach_checks:
                return None
        return None

    def _calc(self, context, output):
        masks = self.masks_port.Eval(context)
        objects = self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ()
        geoms = {o.id: o for o in objects}
        state = {}

        def scene():  # built once per step, on the first lookup
            if "scene" not in state:
                state["scene"] = self.scene(objects)
            return state["scene"]

        def plan_one(oid):
            if oid in self.sets:
                grasps = self.plan_object(oid, geoms, scene())
                if grasps:
                    return grasps
            if self.fallback is None:
                return ()
            if "depth" not in state:  # no set, or no free grasp in it: the image planners
                state["depth"] = np.asarray(self.depth_port.Eval(context).data, float)[..., 0]
            grasps = self.fallback.plan_object(state["depth"], masks, geoms, oid)
            if self.reach is None:
                return grasps
            reached = (self._reaches(g, scene()) for g in grasps)
            return tuple(r if isinstance(r, Grasp) else g for g, r in zip(grasps, reached) if r)

        output.set_value(LazyGrasps(plan_one, masks.ids))
