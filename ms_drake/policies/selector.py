"""PolicySelector: one LeafSystem in front of every bin selector (ms_drake.policies.bin_selectors).

Ports (declared first in __init__):
  inputs
    masks          InstanceMasks (Segmenter)
    target         TargetEstimate (TargetDetector; optional: unconnected = target not visible)
    occupancy      OccupancyMap (OccupancyEstimator; required by xray)
    grasps         tuple[Grasp] (GraspPlanner(s); optional). Several planners (jaw, suction) can be
                   merged into one tuple upstream; the selector takes the best per mask. Or a
                   Mapping object id -> best Grasp (grasping.planner.LazyGraspPlanner's
                   LazyGrasps), looked up only for the masks the selector reaches.
    pushes         tuple[Push] (PushPlanner; optional)
    history        tuple[ActionOutcome] (the executor's record; optional: unconnected = first step)
    target_amodal  the target's true amodal mask (oracle only; optional): an (H, W) bool array, or
                   InstanceMasks such as ms_drake.perception.masks.AmodalMasks' output, of which
                   the mask with id `target_id` is used
  output
    action         Action (kind grasp | push | stop)
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ms_drake.policies.bin_selectors import (
    OCCUPANCY_POLICIES,
    PolicyError,
    SelectorParams,
    check_policy,
    select_action,
)
from ms_drake.types import Action, InstanceMasks, OccupancyMap, TargetEstimate


class PolicySelector(LeafSystem):
    """policy: one of ms_drake.policies.POLICIES; params: SelectorParams (thresholds, horizon,
    seed); target_id: the target's true id (simulation: its model-instance name) for the
    termination rules and the oracle ("" when unknown)."""

    def __init__(self, policy: str, params: SelectorParams | None = None, target_id: str = "",
                 width: int = 640, height: int = 480):
        super().__init__()
        check_policy(policy)
        empty = InstanceMasks.empty(height, width)
        # Ports first.
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(empty))
        self.target_port = self.DeclareAbstractInputPort(
            "target", AbstractValue.Make(TargetEstimate(False, np.zeros((height, width), bool))))
        self.occupancy_port = self.DeclareAbstractInputPort(
            "occupancy", AbstractValue.Make(OccupancyMap(np.zeros((height, width)))))
        self.grasps_port = self.DeclareAbstractInputPort("grasps", AbstractValue.Make(()))
        self.pushes_port = self.DeclareAbstractInputPort("pushes", AbstractValue.Make(()))
        self.history_port = self.DeclareAbstractInputPort("history", AbstractValue.Make(()))
        self.amodal_port = self.DeclareAbstractInputPort("target_amodal", AbstractValue.Make(np.zeros((1, 1), bool)))
        self.action_port = self.DeclareAbstractOutputPort(
            "action", lambda: AbstractValue.Make(Action("stop")), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.policy = policy
        self.params = params or SelectorParams()
        self.target_id = target_id

    def _opt(self, port, context, default):
        return port.Eval(context) if port.HasValue(context) else default

    def _calc(self, context, output):
        if not self.masks_port.HasValue(context):
            raise PolicyError("PolicySelector: the masks input is not connected")
        if self.policy in OCCUPANCY_POLICIES and not self.occupancy_port.HasValue(context):
            raise PolicyError(f"PolicySelector({self.policy!r}): connect the occupancy input (OccupancyEstimator)")
        output.set_value(select_action(
            self.policy, self.masks_port.Eval(context),
            target=self._opt(self.target_port, context, None),
            grasps=self._grasps(context),
            pushes=tuple(self._opt(self.pushes_port, context, ())),
            history=tuple(self._opt(self.history_port, context, ())),
            occupancy=self._opt(self.occupancy_port, context, None),
            params=self.params, target_id=self.target_id,
            target_amodal=self._amodal(context)))

    def _grasps(self, context):
        g = self._opt(self.grasps_port, context, ())
        return g if isinstance(g, Mapping) else tuple(g)

    def _amodal(self, context):
        value = self._opt(self.amodal_port, context, None)
        if isinstance(value, InstanceMasks):
            if self.target_id not in value.ids:
                return None
            return value.masks[value.ids.index(self.target_id)]
        return value
