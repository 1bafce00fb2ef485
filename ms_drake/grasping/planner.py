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
mesh, pose and mass are used (simulation; a piece ``<id>@<k>`` of a cut object uses the object's
(`types.object_of`)); otherwise (hardware) the object is approximated by
the convex hull of its visible points extruded down to the lowest point seen in the image (the
bin floor), with `default_mass` -- a choice of ours; the reference plans on known meshes in
simulation and with a learned GQ-CNN on hardware.

jaw_contact (jaw models): "center" (default) -- the jaws' centre goes min_grasp_depth under the
object's top and the contacts are on the line through it; "pad" -- the pads' lower edge must be
that deep instead, and the point models seek the contacts down the pads' lower half
(`sample_antipodal_grasps_depth(pad_contact=True)`, `GraspEvaluator(pad_span=PAD_BELOW)`): thin
objects lying flat get jaw grasps. Our choice, opt-in; the area models' pads are their polygon.

Randomness: candidate sampling for mask k uses seed (seed, k); robust trials use the same seed.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
import numpy as np
import trimesh
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import CameraInfo, ImageDepth32F
from scipy.spatial import QhullError

from ms_drake.geometry import as_matrix4, preprocess_depth, transform_points
from ms_drake.grasping.evaluator import MODELS, GraspEvaluator
from ms_drake.grasping.grasp import GraspError
from ms_drake.grasping.samplers import (
    depth_to_points,
    sample_antipodal_grasps_depth,
    sample_suction_grasps_depth,
)
from ms_drake.grasping.suction import SuctionEvaluator
from ms_drake.types import Grasp, InstanceMasks, ObjectGeometry, object_of


JAW_CONTACTS = ("center", "pad")  # GraspPlanner.jaw_contact
PAD_BELOW = 0.015  # how far the station jaw's pads reach under the tool point (samplers' pad_below)


def intrinsics(camera_info: CameraInfo) -> np.ndarray:
    return np.asarray(camera_info.intrinsic_matrix(), float)


class GraspPlanner(LeafSystem):
    """Best grasp per object (see the module docstring for ports and choices).

    model: point | soft_point | elliptical | reach | mfe | 6dfc | suction.
    evaluator_params: keyword arguments of GraspEvaluator (or SuctionEvaluator for suction),
    e.g. {"friction": 0.6, "closing_force": 20.0}. cup_clearance (suction): a candidate whose cup
    would land on a seen neighbour more than this above the contact point is dropped
    (`sample_suction_grasps_depth`; None: no check). jaw_contact: JAW_CONTACTS (module docstring)."""

    def __init__(self, camera_info: CameraInfo, X_WC=None, model: str = "soft_point", num_samples: int = 30,
                 robust_samples: int = 0, seed: int = 0, evaluator_params: dict | None = None,
                 max_width: float = 0.1, default_mass: float = 0.2, candidate_pool: int = 3,
                 jaw_margin: float = 0.01, cup_clearance: float | None = 0.005, jaw_contact: str = "center"):
        super().__init__()
        if model not in MODELS and model != "suction":
            raise GraspError(f"GraspPlanner model {model!r} unknown; choose one of {', '.join(MODELS)}, suction")
        if jaw_contact not in JAW_CONTACTS:
            raise GraspError(f"GraspPlanner jaw_contact {jaw_contact!r} unknown; choose one of {', '.join(JAW_CONTACTS)}")
        h, w = camera_info.height(), camera_info.width()
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(h, w)))
        self.objects_port = self.DeclareAbstractInputPort("objects", AbstractValue.Make(()))
        self.camera_pose_port = self.DeclareAbstractInputPort("camera_pose", AbstractValue.Make(RigidTransform()))
        self.grasps_port = self.DeclareAbstractOutputPort(
            "grasps", lambda: AbstractValue.Make(()), self._calc_grasps,
            prerequisites_of_calc={self.all_input_ports_ticket()})

        params = dict(evaluator_params or {})
        self.jaw_contact = jaw_contact
        if jaw_contact == "pad" and model != "suction":
            params.setdefault("pad_span", PAD_BELOW)
        self.model = model
        self.evaluator = SuctionEvaluator(**params) if model == "suction" else GraspEvaluator(model, **params)
        self.K = intrinsics(camera_info)
        self.X_WC = np.eye(4) if X_WC is None else as_matrix4(X_WC, "X_WC")
        self.num_samples, self.robust_samples, self.seed = int(num_samples), int(robust_samples), int(seed)
        self.max_width, self.default_mass = float(max_width), float(default_mass)
        if int(candidate_pool) < 1:
            raise GraspError(f"GraspPlanner candidate_pool must be >= 1, got {candidate_pool!r}")
        self.candidate_pool = int(candidate_pool)
        if not (0 <= jaw_margin < 0.5 * max_width):
            raise GraspError(f"GraspPlanner jaw_margin must be in [0, max_width / 2), got {jaw_margin!r}")
        self.jaw_margin = float(jaw_margin)
        self.cup_clearance = None if cup_clearance is None else float(cup_clearance)
        self.friction = params.get("friction", 0.5)
        self._mesh_cache: dict = {}

    # ------------------------------------------------------------------ helpers
    def _mesh(self, geom: ObjectGeometry):
        """The object's trimesh, from a cache keyed by the mesh's content (id, shapes, CRC of the
        vertex and face bytes): equal meshes share an entry, a changed mesh never hits a stale one."""
        v, f = np.ascontiguousarray(geom.vertices), np.ascontiguousarray(geom.faces)
        key = (geom.id, v.shape, f.shape, zlib.crc32(v.tobytes()), zlib.crc32(f.tobytes()))
        m = self._mesh_cache.get(key)
        if m is None:
            if len(self._mesh_cache) > 256:
                self._mesh_cache.clear()
            m = self._mesh_cache[key] = trimesh.Trimesh(np.asarray(geom.vertices, float),
                                                        np.asarray(geom.faces, np.int64), process=True)
        return m

    def _hull(self, P_W: np.ndarray, mask: np.ndarray, floor_z: float):
        pts = P_W[mask & np.all(np.isfinite(P_W), axis=-1)]
        if len(pts) < 4:
            return None
        low = pts.copy()
        low[:, 2] = min(floor_z, pts[:, 2].min() - 1e-3)
        try:
            return trimesh.convex.convex_hull(np.vstack([pts, low]))
        except QhullError:  # qhull refuses degenerate (flat) point sets
            return None

    def jaw_candidates(self, depth: np.ndarray, mask: np.ndarray, X_WC, seed: int, K=None):
        """The jaw candidates scored for one mask (see the module docstring); K: the intrinsics of
        `depth` (default: the constructor's camera; a crop passes its shifted intrinsics)."""
        K = self.K if K is None else np.asarray(K, float)
        return sample_antipodal_grasps_depth(depth, K, as_matrix4(X_WC, "X_WC"), mask,
                                             self.num_samples * self.candidate_pool, friction=self.friction,
                                             max_width=self.max_width, seed=seed, prefer_center=True,
                                             jaw_margin=self.jaw_margin, pad_below=PAD_BELOW,
                                             pad_contact=self.jaw_contact == "pad")

    def plan(self, depth: np.ndarray, masks: InstanceMasks, objects=(), X_WC=None, K=None,
             seed: int | None = None) -> tuple[Grasp, ...]:
        """The computation behind the output port, callable without a Diagram. K: intrinsics of
        `depth` (default: the camera's; a crop of the image passes its shifted K); seed: the
        sampling seed (default: the constructor's)."""
        X_WC = self.X_WC if X_WC is None else as_matrix4(X_WC, "X_WC")
        K = self.K if K is None else np.asarray(K, float)
        base_seed = self.seed if seed is None else int(seed)
        depth = np.asarray(depth, float).reshape(masks.masks.shape[1:]) if len(masks) else np.asarray(depth, float)
        geoms = {o.id: o for o in objects}
        P_W = None
        out = []
        for k in range(len(masks)):
            mask = masks.masks[k]
            oid = masks.ids[k]
            seed = base_seed * 100003 + k
            if self.model == "suction":
                cands = sample_suction_grasps_depth(
                    depth, K, X_WC, mask, self.num_samples, seed=seed,
                    cup_radius=None if self.cup_clearance is None else self.evaluator.cup_radius,
                    clearance=self.cup_clearance or 0.0)
            else:
                cands = self.jaw_candidates(depth, mask, X_WC, seed, K)
            if not cands:
                continue
            geom = geoms.get(object_of(oid))
            if geom is not None:
                X_WO = as_matrix4(geom.X_WO, f"objects[{oid!r}].X_WO")
                mesh, mass, com = self._mesh(geom), geom.mass, geom.com
            else:
                if P_W is None:
                    P_C = depth_to_points(depth, K)
                    P_W = transform_points(X_WC, P_C)
                    zs = P_W[..., 2][np.isfinite(P_W[..., 2])]
                    floor_z = float(zs.min()) if len(zs) else 0.0
                mesh = self._hull(P_W, mask, floor_z)
                X_WO, mass, com = np.eye(4), self.default_mass, None
                if mesh is None:
                    continue
            best, best_q, lifts = self._best(cands, mesh, X_WO, mass, seed, com)
            out.append(best.to_grasp(best_q, self.model, oid, lifts))
        return tuple(out)

    def _best(self, cands, mesh, X_WO, mass, seed, com):
        """(grasp, quality, lifts) of the best candidate (search order in the module docstring);
        lifts: whether the nominal (unperturbed) model lifts the object with it."""
        ev, n = self.evaluator, self.robust_samples
        if self.model == "suction":
            best, best_q = None, -1.0
            for g in cands:
                q = ev.quality(mesh, X_WO, g, mass, n, seed, com)
                if q > best_q:
                    best, best_q = g, q
            lifts = best_q > 0.0 if n == 0 else ev.quality(mesh, X_WO, best, mass, 0, seed, com) > 0.0
            return best, best_q, bool(lifts)
        # nominal check of every candidate; robust evaluation of the most promising ones
        nominal = []
        for k, g in enumerate(cands):
            r = ev.evaluate(mesh, X_WO, g, mass, 0, seed, com)
            if r.reason in ("resisted", "slips"):  # contacts found (the others: no contact pair)
                nominal.append((0.0 if r.quality > 0 else r.residual, k))
        if not nominal:
            return cands[0], 0.0, False
        best, best_q, lifts = None, -1.0, False
        for res, k in sorted(nominal)[: self.num_samples]:
            q = ev.quality(mesh, X_WO, cands[k], mass, n, seed, com) if n > 0 else (1.0 if res == 0.0 else 0.0)
            if q > best_q:
                best, best_q, lifts = cands[k], q, res == 0.0
            if best_q >= 1.0:
                break
        return best, best_q, lifts

    def _calc_grasps(self, context, output):
        depth = self.depth_port.Eval(context)
        masks = self.masks_port.Eval(context)
        objects = self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ()
        X_WC = self.camera_pose_port.Eval(context) if self.camera_pose_port.HasValue(context) else None
        output.set_value(self.plan(np.asarray(preprocess_depth(depth), float), masks, objects, X_WC))


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


# ---------------------------------------------------------------------------------------------
# Lazy grasp planning: the grasp planner of the bin-search controller


def object_seed(seed: int, object_id: str) -> int:
    """The sampling seed of one object's grasps: a function of (rollout seed, object id) only, so
    an object's candidates do not depend on which other masks are present or in which order."""
    return (int(seed) * 1_000_003 + zlib.crc32(object_id.encode())) % (2 ** 31 - 1)


class LazyGrasps(Mapping):
    """Object id -> its best Grasp over the planners (ids without any grasp are absent), planned
    the first time an id is looked up. Iterating (or len) plans every mask. Immutable for Drake
    (copies share it): its answers depend only on the inputs it was made from."""

    def __init__(self, plan_one, ids: tuple[str, ...]):
        self._plan_one, self._ids, self._memo = plan_one, tuple(ids), {}

    def __deepcopy__(self, memo):
        return self

    def _best(self, oid: str) -> Grasp | None:
        if oid not in self._memo:
            best = None
            for g in self._plan_one(oid):
                if best is None or g.quality > best.quality:
                    best = g
            self._memo[oid] = best
        return self._memo[oid]

    def __getitem__(self, oid: str) -> Grasp:
        g = self._best(oid) if oid in self._ids else None
        if g is None:
            raise KeyError(oid)
        return g

    def __iter__(self):
        return (oid for oid in self._ids if self._best(oid) is not None)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    @property
    def planned(self) -> tuple[str, ...]:
        """The ids planned so far (for tests and the benchmark's accounting)."""
        return tuple(self._memo)


def declare_lazy_grasp_ports(system: LeafSystem, width: int, height: int, calc) -> tuple:
    """Declare on `system` the ports of a lazy grasp planner (LazyGraspPlanner, IndexedGraspPlanner):
    inputs depth_image, masks and objects; output grasps, a LazyGrasps that `calc(context, output)`
    makes whenever an input changes. Returns the (depth_image, masks, objects, grasps) ports."""
    depth = system.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(width, height)))
    masks = system.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
    objects = system.DeclareAbstractInputPort("objects", AbstractValue.Make(()))
    grasps = system.DeclareAbstractOutputPort("grasps", lambda: AbstractValue.Make(LazyGrasps(lambda oid: (), ())),
                                              calc, prerequisites_of_calc={system.all_input_ports_ticket()})
    return depth, masks, objects, grasps


class LazyGraspPlanner(LeafSystem):
    """Grasp planning of the bin-search rollouts, on demand per object; wraps GraspPlanners.

    Ports (declared first):
      inputs  depth_image (ImageDepth32F), masks (InstanceMasks), objects (tuple[ObjectGeometry])
      output  grasps: LazyGrasps (a Mapping object id -> best Grasp; PolicySelector accepts it
              where it accepts a tuple of grasps)

    Two savings that leave the planners' answers exactly as they are, and one that was measured
    and left out (choices of ours; the reference plans every mask every step):
      * on demand: the selector walks its priority list and stops at the first grasp above its
        threshold, so only the masks it reaches are planned (every mask when nothing qualifies);
      * per object: each mask is planned alone on the crop of the depth image around it (the
        bounding box + `margin` pixels, for jaw models also + `crop_margin` metres at the mask's
        nearest depth, for suction too when it checks the cup's clearance (cup and stem: 11 cm); intrinsics shifted accordingly) with the sampling seed `object_seed(seed, id)`; the
        samplers read the mask and its neighbourhood only (the jaw sampler looks up to ~7 cm
        around it for the fingers and the palm), so the crop gives the same candidates as the
        whole image (tests/test_rollout.py checks it) -- a GraspPlanner on the whole image
        computes depth normals of all 307,200 pixels for every mask;
      * no cache across steps (measured, not assumed): keyed by the object's pose (1 mm / 1
        degree) and its unchanged visible mask, such a cache answered none of the 120 object
        plans of 6 rollouts of 15-object heaps (seeds 1000-1003, largest and random): between two steps
        every re-planned object had moved (0.4-7 mm: the heap settles after each removal) or
        its visible mask had changed (the removed neighbour uncovered it). And since the jaw
        sampler checks the fingers' clearance up to ~7 cm around the mask, an unchanged mask
        would not make the old grasps valid after a neighbour moved. Within one step the
        LazyGrasps memo plans an object at most once.
    Without `objects` geometry for an id (hardware) the id is planned on the whole image (the
    planner's convex-hull fallback looks at all pixels).
    """

    def __init__(self, planners, width: int, height: int, seed: int = 0, margin: int = 8,
                 crop_margin: float = 0.12):
        super().__init__()
        self.depth_port, self.masks_port, self.objects_port, self.grasps_port = declare_lazy_grasp_ports(
            self, width, height, self._calc)
        self.planners = list(planners)
        for p in self.planners:
            if not isinstance(p, GraspPlanner):
                raise TypeError(f"LazyGraspPlanner wraps GraspPlanner instances, got {type(p).__name__}")
        self.seed, self.margin, self.crop_margin = int(seed), int(margin), float(crop_margin)

    def plan_object(self, depth: np.ndarray, masks: InstanceMasks, geoms: dict, oid: str) -> tuple[Grasp, ...]:
        """Every planner's best grasp for mask `oid` (the computation behind one lookup)."""
        k = masks.ids.index(oid)
        mask = masks.masks[k]
        geom = geoms.get(object_of(oid))
        rows, cols = np.nonzero(mask)
        if len(rows) == 0:
            return ()
        H, W = mask.shape
        out = []
        seed = object_seed(self.seed, oid)
        for p in self.planners:
            K = p.K
            if geom is not None:
                pad = self.margin
                # the jaw sampler looks around the mask for the fingers, the suction sampler for the cup
                reach = (self.crop_margin if getattr(p, "model", "") != "suction" or p.cup_clearance is not None
                         else 0.0)
                if reach > 0:
                    z = depth[rows, cols]
                    z = z[np.isfinite(z) & (z > 0)]
                    pad += int(np.ceil(reach * max(K[0, 0], K[1, 1]) / z.min())) + 1 if len(z) else max(H, W)
                y0, y1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, H)
                x0, x1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, W)
                crop_depth = np.ascontiguousarray(depth[y0:y1, x0:x1])
                one = InstanceMasks(np.ascontiguousarray(mask[y0:y1, x0:x1])[None], (oid,), np.ones(1))
                shift = np.array([x0, y0], float)
            else:
                crop_depth, one, shift = depth, InstanceMasks(mask[None], (oid,), np.ones(1)), np.zeros(2)
            Kc = K.copy()
            Kc[:2, 2] -= shift
            out.extend(p.plan(crop_depth, one, (geom,) if geom is not None else (), K=Kc, seed=seed))
        return tuple(out)

    def _calc(self, context, output):
        depth = np.asarray(preprocess_depth(self.depth_port.Eval(context)), float)
        masks = self.masks_port.Eval(context)
        geoms = {o.id: o for o in (self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ())}
        output.set_value(LazyGrasps(lambda oid: self.plan_object(depth, masks, geoms, oid), masks.ids))
