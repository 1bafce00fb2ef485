"""`TargetInstance`: the target's pixels as an instance mask of their own.

A depth segmenter rarely gives a thin or mostly hidden target a mask of its own: the
TargetDetector then finds it inside a mask that is mostly another object, or in no mask (a
TargetEstimate with ``instance_index`` -1), and no grasp can be planned on it. This system cuts
the target's pixels out of every mask and appends them as one more mask, which the estimate then
names (its ``instance_index``), so the grasp planner plans on the target and the policy grasps it
first. A mask left with fewer than `min_pixels` pixels drops out. Estimates with an instance,
targets not seen, and targets of fewer than `min_pixels` pixels pass through unchanged.

Ports (declared first): inputs ``masks`` (InstanceMasks) and ``target`` (TargetEstimate);
outputs ``masks`` and ``target``. The controller puts it after the detector when the masks come
from a segmenter (ground-truth masks give the target its own mask already).
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ms_drake.types import InstanceMasks, TargetEstimate


def target_instance(masks: InstanceMasks, target: TargetEstimate,
                    min_pixels: int = 20) -> tuple[InstanceMasks, TargetEstimate]:
    """(masks, target) with the target's pixels as a mask of their own (see the module doc)."""
    t = np.asarray(target.mask, bool)
    if not target.visible or 0 <= target.instance_index < len(masks) or int(t.sum()) < min_pixels:
        return masks, target
    if t.shape != masks.masks.shape[1:]:
        raise ValueError(f"TargetInstance: target mask {t.shape} and masks {masks.masks.shape[1:]} differ in size")
    rest = masks.masks & ~t[None]
    keep = rest.reshape(len(masks), -1).sum(axis=1) >= min_pixels
    ids = tuple(i for i, k in zip(masks.ids, keep) if k)
    new_id = next(f"seg_{n}" for n in range(len(masks.ids) + 1) if f"seg_{n}" not in masks.ids)
    out = InstanceMasks(np.concatenate([rest[keep], t[None]]), ids + (new_id,),
                        np.append(np.asarray(masks.scores, float)[keep], float(target.confidence)))
    return out, TargetEstimate(True, t.copy(), target.confidence, len(out) - 1)


class TargetInstance(LeafSystem):
    """See the module doc. width, height: the camera's image size."""

    def __init__(self, width: int = 640, height: int = 480, min_pixels: int = 20):
        super().__init__()
        self.masks_in = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(height, width)))
        self.target_in = self.DeclareAbstractInputPort(
            "target", AbstractValue.Make(TargetEstimate(False, np.zeros((height, width), bool))))
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make(InstanceMasks.empty(height, width)),
                                       lambda c, o: o.set_value(self._eval(c)[0]),
                                       prerequisites_of_calc={self.all_input_ports_ticket()})
        self.DeclareAbstractOutputPort(
            "target", lambda: AbstractValue.Make(TargetEstimate(False, np.zeros((height, width), bool))),
            lambda c, o: o.set_value(self._eval(c)[1]), prerequisites_of_calc={self.all_input_ports_ticket()})
        self.min_pixels = int(min_pixels)

    def _eval(self, context):
        return target_instance(self.masks_in.Eval(context), self.target_in.Eval(context), self.min_pixels)
