"""GraspPlanner: the best grasp per segmented object, scored by a contact model.

Ports (declared first in __init__):
  inputs
    depth_image   ImageDepth32F (metres; 0 or inf = no return), from an RgbdSensor
    masks         InstanceMasks (visible masks; ids name the objects)
    objects       tuple[ObjectGeometry] (optional; simulation meshes, poses and masses)
    camera_pose   RigidTransform X_WC (optional; default: the constructor's X_WC)
  output
    grasps        tuple[Grasp]: one per mask that yielded a grasp, the best by quality, with
                  `quality`, `model` and `object_id` (the mask id) filled in; order of the masks.

Per mask: sample `num_samples` candidates from the depth image restricted to the mask
(top-down antipodal pairs for the jaw models, surface points for "suction"), score each with
the chosen model and keep the best. Jaw models (our choice of search order; the reference
scores a fixed sample): up to `candidate_pool` x num_samples top-down antipodal pairs whose
fingers clear the neighbours in the depth image are drawn and taken nearest-first to the mask's
footprint centroid (a grasp far from the centre of mass rarely holds); each is checked with the
nominal (non-robust) model, which costs a fraction of a robust evaluation; the num_samples with
the smallest nominal wrench residual (those that resist first, nearest-first among them) get the
robust evaluation, stopping at the first robust quality of 1.0. Candidates whose jaws find no
contact pair (miss, jaw collision) are never chosen; an object without any other gets its first
candidate with quality 0.0. When `objects` holds geometry with the mask's id the exact
mesh, pose and mass are used (simulation); otherwise (hardware) the object is approximated by
the convex hull of its visible points extruded down to the lowest point seen in the image (the
bin floor), with `default_mass` -- a choice of ours; the reference plans on known meshes in
simulation and with a learned GQ-CNN on hardware.

Randomness: candidate sampling for mask k uses seed (seed, k); robust trials use the same seed.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import CameraInfo, ImageDepth32F

from ms_drake.grasping.evaluator import MODELS, GraspEvaluator
from ms_drake.grasping.grasp import GraspError
from ms_drake.grasping.samplers import (depth_to_points, sample_antipodal_grasps_depth,
                                        sample_suction_grasps_depth)
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.types import Grasp, InstanceMasks, ObjectGeometry


def intrinsics(camera_info: CameraInfo) -> np.ndarray:
    return np.asarray(camera_info.intrinsic_matrix(), float)


def _as_matrix(X) -> np.ndarray:
    return X.GetAsMatrix4() if isinstance(X, RigidTransform) else np.asarray(X, float)


class GraspPlanner(LeafSystem):
    """Best grasp per object (see the module docstring for ports and choices).

    model: point | soft_point | elliptical | reach | mfe | 6dfc | suction.
    evaluator_params: keyword arguments of GraspEvaluator (or SuctionEvaluator for suction),
    e.g. {"friction": 0.6, "closing_force": 20.0}."""

    def __init__(self, camera_info: CameraInfo, X_WC=None, model: str = "soft_point", num_samples: int = 30,
                 robust_samples: int = 0, seed: int = 0, evaluator_params: dict | None = None,
                 max_width: float = 0.1, default_mass: float = 0.2, candidate_pool: int = 3,
                 jaw_margin: float = 0.01):
        super().__init__()
        if model not in MODELS and model != "suction":
            raise GraspError(f"GraspPlanner model {model!r} unknown; choose one of {', '.join(MODELS)}, suction")
        h, w = camera_info.height(), camera_info.width()
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(h, w)))
        self.objects_port = self.DeclareAbstractInputPort("objects", AbstractValue.Make(()))
        self.camera_pose_port = self.DeclareAbstractInputPort("camera_pose", AbstractValue.Make(RigidTransform()))
        self.grasps_port = self.DeclareAbstractOutputPort(
            "grasps", lambda: AbstractValue.Make(()), self._calc_grasps,
            prerequisites_of_calc={self.all_input_ports_ticket()})

        params = dict(evaluator_params or {})
        self.model = model
        self.evaluator = SuctionEvaluator(**params) if model == "suction" else GraspEvaluator(model, **params)
        self.K = intrinsics(camera_info)
        self.X_WC = np.eye(4) if X_WC is None else _as_matrix(X_WC)
        self.num_samples, self.robust_samples, self.seed = int(num_samples), int(robust_samples), int(seed)
        self.max_width, self.default_mass = float(max_width), float(default_mass)
        if int(candidate_pool) < 1:
            raise GraspError(f"GraspPlanner candidate_pool must be >= 1, got {candidate_pool!r}")
        self.candidate_pool = int(candidate_pool)
        if not (0 <= jaw_margin < 0.5 * max_width):
            raise GraspError(f"GraspPlanner jaw_margin must be in [0, max_width / 2), got {jaw_margin!r}")
        self.jaw_margin = float(jaw_margin)
        self.friction = params.get("friction", 0.5)
        self._mesh_cache: dict = {}

    # ------------------------------------------------------------------ helpers
    def _mesh(self, geom: ObjectGeometry):
        import trimesh

        key = (geom.id, geom.vertices.ctypes.data, geom.faces.ctypes.data, geom.vertices.shape, geom.faces.shape)
        m = self._mesh_cache.get(key)
        if m is None:
            if len(self._mesh_cache) > 256:
                self._mesh_cache.clear()
            m = self._mesh_cache[key] = trimesh.Trimesh(np.asarray(geom.vertices, float),
                                                        np.asarray(geom.faces, np.int64), process=True)
        return m

    def _hull(self, P_W: np.ndarray, mask: np.ndarray, floor_z: float):
        import trimesh

        pts = P_W[mask & np.all(np.isfinite(P_W), axis=-1)]
        if len(pts) < 4:
            return None
        low = pts.copy()
        low[:, 2] = min(floor_z, pts[:, 2].min() - 1e-3)
        try:
            return trimesh.convex.convex_hull(np.vstack([pts, low]))
        except Exception:  # noqa: BLE001 -- qhull refuses degenerate (flat) point sets
            return None

    def jaw_candidates(self, depth: np.ndarray, mask: np.ndarray, X_WC, seed: int):
        """The jaw candidates scored for one mask (see the module docstring)."""
        return sample_antipodal_grasps_depth(depth, self.K, _as_matrix(X_WC), mask,
                                             self.num_samples * self.candidate_pool, friction=self.friction,
                                             max_width=self.max_width, seed=seed, prefer_center=True,
                                             jaw_margin=self.jaw_margin)

    def plan(self, depth: np.ndarray, masks: InstanceMasks, objects=(), X_WC=None) -> tuple[Grasp, ...]:
        """The computation behind the output port, callable without a Diagram."""
        X_WC = self.X_WC if X_WC is None else _as_matrix(X_WC)
        depth = np.asarray(depth, float).reshape(masks.masks.shape[1:]) if len(masks) else np.asarray(depth, float)
        geoms = {o.id: o for o in objects}
        P_W = None
        out = []
        for k in range(len(masks)):
            mask = masks.masks[k]
            oid = masks.ids[k]
            seed = self.seed * 100003 + k
            if self.model == "suction":
                cands = sample_suction_grasps_depth(depth, self.K, X_WC, mask, self.num_samples, seed=seed)
            else:
                cands = self.jaw_candidates(depth, mask, X_WC, seed)
            if not cands:
                continue
            geom = geoms.get(oid)
            if geom is not None:
                mesh, X_WO, mass, com = self._mesh(geom), np.asarray(geom.X_WO, float), geom.mass, geom.com
            else:
                if P_W is None:
                    P_C = depth_to_points(depth, self.K)
                    P_W = P_C @ X_WC[:3, :3].T + X_WC[:3, 3]
                    zs = P_W[..., 2][np.isfinite(P_W[..., 2])]
                    floor_z = float(zs.min()) if len(zs) else 0.0
                mesh = self._hull(P_W, mask, floor_z)
                X_WO, mass, com = np.eye(4), self.default_mass, None
                if mesh is None:
                    continue
            best, best_q = self._best(cands, mesh, X_WO, mass, seed, com)
            out.append(best.to_grasp(best_q, self.model, oid))
        return tuple(out)

    def _best(self, cands, mesh, X_WO, mass, seed, com):
        """(grasp, quality) of the best candidate (search order in the module docstring)."""
        ev, n = self.evaluator, self.robust_samples
        if self.model == "suction":
            best, best_q = None, -1.0
            for g in cands:
                q = ev.quality(mesh, X_WO, g, mass, n, seed, com)
                if q > best_q:
                    best, best_q = g, q
            return best, best_q
        # nominal check of every candidate; robust evaluation of the most promising ones
        nominal = []
        for k, g in enumerate(cands):
            r = ev.evaluate(mesh, X_WO, g, mass, 0, seed, com)
            if r.reason in ("resisted", "slips"):  # contacts found (the others: no contact pair)
                nominal.append((0.0 if r.quality > 0 else r.residual, k))
        if not nominal:
            return cands[0], 0.0
        best, best_q = None, -1.0
        for res, k in sorted(nominal)[: self.num_samples]:
            q = ev.quality(mesh, X_WO, cands[k], mass, n, seed, com) if n > 0 else (1.0 if res == 0.0 else 0.0)
            if q > best_q:
                best, best_q = cands[k], q
            if best_q >= 1.0:
                break
        return best, best_q

    def _calc_grasps(self, context, output):
        depth = self.depth_port.Eval(context)
        masks = self.masks_port.Eval(context)
        objects = self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ()
        X_WC = self.camera_pose_port.Eval(context) if self.camera_pose_port.HasValue(context) else None
        output.set_value(self.plan(np.asarray(depth.data, float)[..., 0], masks, objects, X_WC))


class ObjectGeometrySource(LeafSystem):
    """Simulation cheat: ObjectGeometry of chosen plant bodies at their current poses.

    input  body_poses  (the plant's body_poses output: list of RigidTransform)
    output objects     tuple[ObjectGeometry]
    bodies: {id: (body, trimesh mesh in the body frame, mass, com or None)}."""

    def __init__(self, bodies: dict):
        super().__init__()
        self.poses_port = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self.DeclareAbstractOutputPort("objects", lambda: AbstractValue.Make(()), self._calc)
        self._bodies = [(oid, int(body.index()), np.asarray(mesh.vertices, float), np.asarray(mesh.faces),
                         float(mass), com) for oid, (body, mesh, mass, com) in bodies.items()]

    def _calc(self, context, output):
        poses = self.poses_port.Eval(context)
        output.set_value(tuple(ObjectGeometry(oid, v, f, poses[i].GetAsMatrix4(), m, com)
                               for oid, i, v, f, m, com in self._bodies))
