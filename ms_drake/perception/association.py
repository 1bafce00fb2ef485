"""`MaskAssociation` (simulation only): names the masks of a depth segmenter after the simulated
objects behind them, so that a simulated executor can tell which object a grasp on a mask lifted.

A segmenter's masks are named ``seg_k``; the primitive executor decides a grasp's outcome and
removes the grasped object by its id, and the search ends when the target's id is removed. This
system reads the station's label image and gives each mask the id of the object covering the
largest part of it, if that object covers at least `min_fraction` of the mask's pixels; when
several masks qualify for one object (a segmenter that cut it in pieces), the mask with the most
of its pixels takes the id and each other piece is named ``<id>@<k>`` (ids stay unique;
`types.object_of` gives the object back), so a grasp on any piece lifts that object. A mask no
object covers half of (mostly bin) keeps ``seg_k``: a grasp on it lifts nothing. The masks'
pixels, order and scores are the segmenter's: what the policy sees is unchanged, only the names
are ground truth. Through the names the grasp planner also finds the object's exact mesh (as it
does with ground-truth masks in simulation) -- for a mask that mixes two objects, the mesh of the
one covering most of it.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageLabel16I

from ms_drake.errors import PerceptionError
from ms_drake.types import FRAGMENT_MARK, InstanceMasks


def associate(masks: InstanceMasks, labels: np.ndarray, label_to_id: dict[int, str],
              min_fraction: float = 0.5) -> InstanceMasks:
    """The masks renamed after the objects behind them (see the module doc)."""
    labels = np.asarray(labels)
    if labels.ndim == 3:
        labels = labels[:, :, 0]
    if len(masks) == 0:
        return masks
    if labels.shape != masks.masks.shape[1:]:
        raise PerceptionError(f"MaskAssociation: label image {labels.shape} and masks {masks.masks.shape[1:]} differ "
                              "in size; give the label image of the camera the masks come from")
    best: dict[str, tuple[int, int]] = {}
    behind: dict[int, str] = {}  # mask -> the object covering at least min_fraction of it
    for k in range(len(masks)):
        vals, counts = np.unique(labels[masks.masks[k]], return_counts=True)
        named = [(int(c), label_to_id[int(v)]) for v, c in zip(vals, counts) if int(v) in label_to_id]
        if not named:
            continue
        c, oid = max(named)
        if c >= min_fraction * counts.sum():
            behind[k] = oid
            if c > best.get(oid, (-1, -1))[0]:
                best[oid] = (c, k)
    ids = list(masks.ids)
    taken = {k: oid for oid, (_, k) in best.items()}
    for k, oid in behind.items():
        ids[k] = oid if taken.get(k) == oid else f"{oid}{FRAGMENT_MARK}{k}"
    used = set(ids[k] for k in behind)
    for k in range(len(ids)):  # a segmenter id equal to an object's name would collide: rename it
        if k not in behind and (ids[k] in used or FRAGMENT_MARK in ids[k]):
            ids[k] = f"seg_{k}"
    return InstanceMasks(masks.masks, tuple(ids), masks.scores)


class MaskAssociation(LeafSystem):
    """Inputs ``masks`` (InstanceMasks) and ``label_image`` (ImageLabel16I); output ``masks``
    renamed (see the module doc). label_to_id: render label -> object id (masks.object_labels)."""

    def __init__(self, label_to_id: dict[int, str], width: int = 640, height: int = 480, min_fraction: float = 0.5):
        super().__init__()
        if not 0.0 < min_fraction <= 1.0:
            raise PerceptionError(f"MaskAssociation min_fraction={min_fraction} must lie in (0, 1]")
        self.masks_in = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
        self.labels_in = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(ImageLabel16I(width, height)))
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make(InstanceMasks.empty(height, width)),
                                       self._calc, prerequisites_of_calc={self.all_input_ports_ticket()})
        self.label_to_id, self.min_fraction = dict(label_to_id), float(min_fraction)

    def _calc(self, context, output):
        masks = self.masks_in.Eval(context)
        labels = np.array(self.labels_in.Eval(context).data)
        output.set_value(associate(masks, labels, self.label_to_id, self.min_fraction))
