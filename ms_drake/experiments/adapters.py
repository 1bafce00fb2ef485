"""Small adapter systems of the bin-search controller diagram.

TargetAmodalMask (simulation only, the oracle's view of the true state):
  input ``masks`` (InstanceMasks of every object's amodal mask, perception.masks.AmodalMasks);
  output ``target_amodal`` ((H, W) bool numpy array: the target's amodal mask, all False when the
  target is not among the masks, e.g. after it was removed).
MergeGrasps: inputs ``grasps_0`` .. ``grasps_{k-1}`` (tuple[Grasp] from k GraspPlanners, e.g. a
  parallel-jaw and a suction model); output ``grasps``: their concatenation in input order (the
  selector keeps the best per mask). Unconnected inputs count as empty.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ms_drake.types import InstanceMasks


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
