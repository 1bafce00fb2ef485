"""Jaw grasps on a real bin heap: the GraspPlanner's inputs rendered from a heap, and a per-object
account of what the planner found (quality, the candidates' outcome reasons).

    from ms_drake.scenario import load_scenario
    from ms_drake.scenes.heaps import generate_heap
    s = load_scenario(None, "BinHeap15")
    inputs = heap_grasp_inputs(s, generate_heap(s, 6, seed=3))
    rows = heap_grasp_report(inputs, GraspPlanner(inputs.camera_info, inputs.X_WC, model="soft_point"))

tests/test_grasp_heap.py runs this on a small heap; over many heaps it gives the fraction of heap
objects with a jaw grasp above t = 0.15 (measured 2026-11-22, commits 148b8af and 426230b).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import coal
import numpy as np
from scipy.spatial.transform import Rotation

from ms_drake.geometry import PinholeCamera, as_matrix4, silhouette
from ms_drake.objects import get_object
from ms_drake.perception.masks import label_image_to_masks, object_labels
from ms_drake.robots import ParallelJawConfig
from ms_drake.scenes.heaps import scenario_with_heap, set_heap_poses
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.station.environments import _boxes
from ms_drake.types import InstanceMasks, ObjectGeometry


@dataclass
class HeapGraspInputs:
    depth: np.ndarray  # (H, W) metres, inf = no return
    masks: InstanceMasks  # visible masks, ids = model instance names
    objects: tuple  # tuple[ObjectGeometry] at the heap's poses
    camera_info: object  # CameraInfo of the overhead camera
    X_WC: np.ndarray  # 4x4 camera pose
    names: dict  # id -> full object name ("procedural/box_003")
    visible_ratio: dict  # id -> visible / amodal pixel ratio


def heap_grasp_inputs(scenario, heap, camera: str = "overhead", min_pixels: int = 20) -> HeapGraspInputs:
    """Build the station holding `heap`, render `camera` and collect what a GraspPlanner reads."""
    s = scenario_with_heap(scenario, heap)
    station = MakeStation(s, target_index=heap.target_index)
    context = station.CreateDefaultContext()
    set_heap_poses(station, context, heap)
    plant = get_plant(station)
    pc = plant.GetMyContextFromRoot(context)
    depth = np.array(station.GetOutputPort(f"{camera}.depth_image").Eval(context).data)[:, :, 0].astype(float)
    labels = np.array(station.GetOutputPort(f"{camera}.label_image").Eval(context).data)[:, :, 0]
    masks = label_image_to_masks(labels, object_labels(plant), min_pixels=min_pixels)
    cfg = s.cameras[camera]
    cam = PinholeCamera.from_config(cfg)
    color, _ = cfg.MakeCameras()
    objects, names, ratio = [], {}, {}
    for o in station_objects(plant):
        spec = get_object(o.full_name)
        mesh = spec.trimesh()
        X = plant.EvalBodyPoseInWorld(pc, plant.get_body(o.body_index))
        objects.append(ObjectGeometry(o.model_name, np.asarray(mesh.vertices, float), np.asarray(mesh.faces),
                                      X.GetAsMatrix4(), spec.mass))
        names[o.model_name] = o.full_name
        amodal = silhouette(cam, np.asarray(mesh.vertices) @ X.rotation().matrix().T + X.translation(),
                            np.asarray(mesh.faces)).sum()
        modal = int((labels == int(o.body_index)).sum())
        ratio[o.model_name] = min(1.0, modal / amodal) if amodal > 0 else 0.0
    return HeapGraspInputs(depth, masks, tuple(objects), color.core().intrinsics(), cam.X_WC.GetAsMatrix4(),
                           names, ratio)


def graspable_size(vertices: np.ndarray, X_WO: np.ndarray, max_width: float, jaw_margin: float = 0.01) -> bool:
    """True when a top-down jaw could span the object: the narrower of the two principal extents
    of its world-frame footprint (vertices projected on the horizontal plane) is below
    max_width - 2 jaw_margin (the depth sampler's limit). X_WO: RigidTransform or 4x4 array."""
    X = as_matrix4(X_WO, "X_WO")
    xy = (np.asarray(vertices, float) @ X[:3, :3].T)[:, :2]
    xy = xy - xy.mean(axis=0)
    _, _, Vt = np.linalg.svd(xy, full_matrices=False)
    return bool(np.min(np.ptp(xy @ Vt.T, axis=0)) < max_width - 2 * jaw_margin)


def heap_grasp_report(inputs: HeapGraspInputs, planner, diagnose: bool = True, scenario=None) -> list[dict]:
    """One row per visible object: id, name, visible ratio, pixels, graspable-sized, the planner's
    best quality (0.0 when it returned no grasp), with `scenario` the owners the opened jaw at
    that grasp collides with (`collides`: other objects and "bin"; the grasped object itself is
    listed too), and with `diagnose` the outcome counts of the nominal (non-robust) evaluation
    of each candidate."""
    shapes = scene_shapes(scenario, inputs) if scenario is not None else None
    grasps = {g.object_id: g for g in planner.plan(inputs.depth, inputs.masks, inputs.objects, inputs.X_WC)}
    geoms = {o.id: o for o in inputs.objects}
    rows = []
    for k, oid in enumerate(inputs.masks.ids):
        g = grasps.get(oid)
        geom = geoms[oid]
        row = {"id": oid, "name": inputs.names.get(oid, oid), "visible": round(inputs.visible_ratio.get(oid, 1.0), 3),
               "pixels": int(inputs.masks.masks[k].sum()),
               "graspable_size": graspable_size(geom.vertices, geom.X_WO, planner.max_width),
               "quality": float(g.quality) if g is not None else 0.0, "grasp": g}
        if shapes is not None:
            row["collides"] = sorted(grasp_collisions(g, shapes, 0.001)) if g is not None else []
        if diagnose:
            cands = planner.jaw_candidates(inputs.depth, inputs.masks.masks[k], inputs.X_WC,
                                           planner.seed * 100003 + k)
            mesh = planner._mesh(geom)
            reasons = Counter(planner.evaluator.evaluate(mesh, geom.X_WO, c, geom.mass).reason for c in cands)
            row["candidates"] = len(cands)
            row["reasons"] = dict(reasons)
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- exact collision check
def _coal_shape(shape):
    if shape.kind == "box":
        return coal.Box(*(float(v) for v in shape.size))
    if shape.kind == "cylinder":
        return coal.Cylinder(float(shape.size[0]), float(shape.size[1]))
    if shape.kind == "sphere":
        return coal.Sphere(float(shape.size[0]))
    raise ValueError(f"no coal shape for {shape.kind}")


def _shape_pose(X_WB: np.ndarray, pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose[3:]).as_matrix()
    T[:3, 3] = pose[:3]
    return X_WB @ T


def scene_shapes(scenario, inputs: HeapGraspInputs) -> list[tuple[str, object, np.ndarray]]:
    """(owner, coal shape, 4x4 world pose) of every object's collision primitives and of the bin
    (its floor and walls). Owner: the object id, or "bin"."""
    out = []
    for o in inputs.objects:
        for sh in get_object(inputs.names[o.id]).collisions:
            out.append((o.id, _coal_shape(sh), _shape_pose(np.asarray(o.X_WO, float), sh.pose)))
    env = scenario.environment
    X_env = np.eye(4)
    X_env[:3, 3] = np.asarray(env.position, float)
    for name, sh, _ in _boxes(env.type, env.resolved_size(), env.wall_thickness):
        out.append(("bin", _coal_shape(sh), _shape_pose(X_env, sh.pose)))
    return out


def gripper_boxes(grasp, config=None) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, size (3,), 4x4 world pose) of the station's parallel jaw (palm, two fingers with
    their pads) opened to grasp.width with its tool point at the grasp centre."""
    c = config or ParallelJawConfig()
    p = c.pads
    ax = np.asarray(grasp.axis, float)
    ap = np.asarray(grasp.approach, float)
    R = np.column_stack([ax, np.cross(ap, ax), ap])  # x = axis, y = across, z = approach
    pz, flen = c.palm_size[2], c.finger_length
    tcp_z = pz + flen - p.length / 2  # tool point in the body frame (z along the approach)
    out = []

    def add(name, size, center_body):
        X = np.eye(4)
        X[:3, :3] = R
        X[:3, 3] = np.asarray(grasp.center, float) + R @ (np.asarray(center_body) - [0, 0, tcp_z])
        out.append((name, np.asarray(size, float), X))

    add("palm", c.palm_size, (0, 0, pz / 2))
    w = float(grasp.width) / 2
    thick = p.thickness + c.finger_thickness
    for sign in (-1.0, 1.0):
        add("finger", (thick, c.finger_depth, flen), (sign * (w + thick / 2), 0, pz + flen / 2))
    return out


def grasp_collisions(grasp, shapes, margin: float = 0.0) -> set[str]:
    """Owners (object ids, "bin") whose collision shapes the opened jaw at `grasp` intersects
    (penetration deeper than `margin`, metres)."""
    req = coal.CollisionRequest()
    hit = set()
    for _, size, X in gripper_boxes(grasp):
        box = coal.Box(*(size - 2 * margin).clip(1e-6))
        T1 = coal.Transform3s(X[:3, :3], X[:3, 3])
        for owner, shape, Xs in shapes:
            if owner in hit:
                continue
            res = coal.CollisionResult()
            if coal.collide(box, T1, shape, coal.Transform3s(Xs[:3, :3], Xs[:3, 3]), req, res):
                hit.add(owner)
    return hit
