"""Small adapter systems of the bin-search controller diagram.

TargetAmodalMask (simulation only, the oracle's view of the true state):
  input ``masks`` (InstanceMasks of every object's amodal mask, perception.masks.AmodalMasks);
  output ``target_amodal`` ((H, W) bool numpy array: the target's amodal mask, all False when the
  target is not among the masks, e.g. after it was removed).
MergeGrasps: inputs ``grasps_0`` .. ``grasps_{k-1}`` (tuple[Grasp] from k GraspPlanners, e.g. a
  parallel-jaw and a suction model); output ``grasps``: their concatenation in input order (the
  selector keeps the best per mask). Unconnected inputs count as empty.
LazyGraspPlanner: the grasp planning of a rollout, on demand per object (see its docstring):
  inputs ``depth_image``, ``masks``, ``objects`` (as ms_drake.grasping.planner.GraspPlanner);
  output ``grasps``: a LazyGrasps mapping object id -> best Grasp over the wrapped planners,
  planned only for the ids the selector asks for.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.types import Grasp, InstanceMasks


class TargetAmodalMask(LeafSystem):
    def __init__(self, target_id: str):
        super().__init__()
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(1, 1)))
        self.DeclareAbstractOutputPort("target_amodal", lambda: AbstractValue.Make(np.zeros((1, 1), bool)), self._calc)
        self.target_id = target_id

    def _calc(self, context, output):
        m = self.masks_port.Eval(context)
        if self.target_id in m.ids:
            output.set_value(np.asarray(m.masks[m.ids.index(self.target_id)], bool))
        else:
            output.set_value(np.zeros(m.masks.shape[1:], bool))


class MergeGrasps(LeafSystem):
    def __init__(self, num_inputs: int):
        super().__init__()
        self.inputs = [self.DeclareAbstractInputPort(f"grasps_{k}", AbstractValue.Make(())) for k in range(num_inputs)]
        self.DeclareAbstractOutputPort("grasps", lambda: AbstractValue.Make(()), self._calc)

    def _calc(self, context, output):
        out = []
        for p in self.inputs:
            if p.HasValue(context):
                out.extend(p.Eval(context))
        output.set_value(tuple(out))


# ---------------------------------------------------------------------------------------------
# Lazy grasp planning


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
        nearest depth; intrinsics shifted accordingly) with the sampling seed `object_seed(seed, id)`; the
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
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(width, height)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
        self.objects_port = self.DeclareAbstractInputPort("objects", AbstractValue.Make(()))
        self.grasps_port = self.DeclareAbstractOutputPort(
            "grasps", lambda: AbstractValue.Make(LazyGrasps(lambda oid: (), ())), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.planners = list(planners)
        for p in self.planners:  # the planner attributes this wrapper sets per call
            if not (hasattr(p, "K") and hasattr(p, "seed") and hasattr(p, "plan")):
                raise TypeError("LazyGraspPlanner wraps ms_drake.grasping.planner.GraspPlanner instances")
        self._K = [np.array(p.K, float) for p in self.planners]
        self.seed, self.margin, self.crop_margin = int(seed), int(margin), float(crop_margin)
        self.planned = 0  # objects planned afresh (all steps)

    def plan_object(self, depth: np.ndarray, masks: InstanceMasks, geoms: dict, oid: str) -> tuple[Grasp, ...]:
        """Every planner's best grasp for mask `oid` (the computation behind one lookup)."""
        k = masks.ids.index(oid)
        mask = masks.masks[k]
        geom = geoms.get(oid)
        rows, cols = np.nonzero(mask)
        if len(rows) == 0:
            return ()
        H, W = mask.shape
        out = []
        seed = object_seed(self.seed, oid)
        for p, K in zip(self.planners, self._K):
            if geom is not None:
                pad = self.margin
                if getattr(p, "model", "") != "suction":  # the jaw sampler looks around the mask
                    z = depth[rows, cols]
                    z = z[np.isfinite(z) & (z > 0)]
                    pad += int(np.ceil(self.crop_margin * max(K[0, 0], K[1, 1]) / z.min())) if len(z) else max(H, W)
                y0, y1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, H)
                x0, x1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, W)
                crop_depth = np.ascontiguousarray(depth[y0:y1, x0:x1])
                one = InstanceMasks(np.ascontiguousarray(mask[y0:y1, x0:x1])[None], (oid,), np.ones(1))
                shift = np.array([x0, y0], float)
            else:
                crop_depth, one, shift = depth, InstanceMasks(mask[None], (oid,), np.ones(1)), np.zeros(2)
            Kc = K.copy()
            Kc[:2, 2] -= shift
            p.K, p.seed = Kc, seed
            try:
                out.extend(p.plan(crop_depth, one, (geom,) if geom is not None else ()))
            finally:
                p.K = K
        self.planned += 1
        return tuple(out)

    def _calc(self, context, output):
        depth = np.asarray(self.depth_port.Eval(context).data, float)[..., 0]
        masks = self.masks_port.Eval(context)
        geoms = {o.id: o for o in (self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ())}
        output.set_value(LazyGrasps(lambda oid: self.plan_object(depth, masks, geoms, oid), masks.ids))
