"""Object masks from simulation: modal (visible) masks from the label image and amodal (whole
object, ignoring occlusion) masks by projecting the object's mesh through the camera.

- `label_image_to_masks`, `object_labels`: label image -> InstanceMasks of the plant's objects
  (Drake's default render label of a plant body is its BodyIndex); the ground-truth backend of
  ms_drake.perception.segmentation.Segmenter uses them.
- `AmodalMasks` (LeafSystem): body poses -> InstanceMasks of every object's full silhouette.
  The silhouette is the union of the object's mesh triangles projected with the pinhole
  model (cv2.fillPoly); it equals rendering the object alone (tests check IoU > 0.97) at a
  fraction of the cost of one render per object.
- `TargetAmodalMask` (LeafSystem): the target's amodal mask among them (the oracle's view).
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem

from ms_drake.geometry import PinholeCamera, as_rigid_transform, silhouette
from ms_drake.objects import get_object
from ms_drake.station.station import station_objects
from ms_drake.types import InstanceMasks


def label_image_to_masks(labels: np.ndarray, label_to_id: dict[int, str] | None = None, min_pixels: int = 1,
                         max_pixels: float = np.inf) -> InstanceMasks:
    """InstanceMasks of a label image, one per label with min_pixels <= area <= max_pixels.

    label_to_id given (ground truth): the labels it names, in label order, with its ids.
    None (a segmenter's clusters): every label >= 0, largest first, named seg_0, seg_1, ..."""
    labels = np.asarray(labels)
    if label_to_id is None:
        present, counts = np.unique(labels[labels >= 0], return_counts=True)
    else:
        present, counts = np.unique(labels, return_counts=True)
    keep = [(int(lbl), int(n)) for lbl, n in zip(present, counts)
            if (label_to_id is None or int(lbl) in label_to_id) and min_pixels <= n <= max_pixels]
    if label_to_id is None:
        keep.sort(key=lambda t: -t[1])  # stable: equal areas stay in label order
    if not keep:
        return InstanceMasks.empty(*labels.shape)
    masks = np.stack([labels == lbl for lbl, _ in keep])
    ids = tuple(f"seg_{k}" for k in range(len(keep))) if label_to_id is None else \
        tuple(label_to_id[lbl] for lbl, _ in keep)
    return InstanceMasks(masks, ids, np.ones(len(keep)))


def object_labels(plant) -> dict[int, str]:
    """Render label -> object model-instance name for the objects of a station plant."""
    return {int(o.body_index): o.model_name for o in station_objects(plant)}


class AmodalMasks(LeafSystem):
    """Amodal masks of the objects: each object's mesh projected at its pose.

    Input ``body_poses`` (list of RigidTransform indexed by BodyIndex, the plant's port);
    output ``masks`` (InstanceMasks, one per object in `objects`, possibly empty masks).
    objects: (id, body_index, trimesh.Trimesh in the body frame) triples.
    """

    def __init__(self, camera: PinholeCamera, objects: list[tuple[str, int, object]]):
        super().__init__()
        self._poses = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make(InstanceMasks.empty(1, 1)),
                                       self._calc)
        self._camera = camera
        self._objects = [(i, int(b), np.asarray(m.vertices), np.asarray(m.faces)) for i, b, m in objects]

    def masks_for(self, poses) -> InstanceMasks:
        """Silhouettes of the objects at `poses` (the plant's body_poses: indexed by body index;
        RigidTransforms or 4x4 arrays)."""
        cam = self._camera
        if not self._objects:
            return InstanceMasks.empty(cam.height, cam.width)
        out = []
        for _, b, v, f in self._objects:
            X = as_rigid_transform(poses[b], f"poses[{b}]")
            out.append(silhouette(cam, (X.rotation().matrix() @ v.T).T + X.translation(), f))
        return InstanceMasks(np.stack(out), tuple(i for i, *_ in self._objects), np.ones(len(out)))

    def _calc(self, context, output):
        output.set_value(self.masks_for(self._poses.Eval(context)))


def make_amodal_masks(plant, camera: PinholeCamera) -> AmodalMasks:
    """An AmodalMasks system for all objects of a station plant."""
    objs = [(o.model_name, int(o.body_index), get_object(o.full_name).trimesh()) for o in station_objects(plant)]
    return AmodalMasks(camera, objs)


class TargetAmodalMask(LeafSystem):
    """Simulation only (the oracle's view of the true state): input ``masks`` (InstanceMasks of
    every object's amodal mask, AmodalMasks), output ``target_amodal`` ((H, W) bool: the target's
    amodal mask, all False when the target is not among the masks, e.g. after it was removed)."""

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
