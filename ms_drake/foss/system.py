"""FossSystem: the first-order shelf simulator as a Drake LeafSystem.

Ports (declared first in __init__):
  input   action             Action (kind "shelf" applies its ShelfAction; "stop" and anything else
                             change nothing); unconnected: nothing happens
  outputs scene              ShelfScene (occluders and target)
          visible_fraction   BasicVector(1): the fraction of the target's image area the camera sees
          history            tuple[ActionOutcome], one per applied shelf action, oldest first
State: the scene and the history (abstract state). A periodic unrestricted update every `period`
seconds (first at t = period) applies the action on the input, so action k is applied at t = k * period
(Drake's Simulator performs an update at t when it steps on from t: advance past k * period to see it).
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem

from ms_drake.foss.simulator import Foss, shelf_action
from ms_drake.types import Action, ShelfScene


class FossSystem(LeafSystem):
    def __init__(self, foss: Foss, scene: ShelfScene, period: float = 1.0):
        super().__init__()
        if scene.target is None:
            raise ValueError("FossSystem: the scene needs a target (ms_drake.scenes.shelf.generate_shelf_scene)")
        if not period > 0:
            raise ValueError(f"FossSystem(period={period}): must be > 0 s")
        # Ports first.
        self.action_port = self.DeclareAbstractInputPort("action", AbstractValue.Make(Action("stop")))
        self._scene = self.DeclareAbstractState(AbstractValue.Make(scene))
        self._history = self.DeclareAbstractState(AbstractValue.Make(()))
        self.DeclareAbstractOutputPort("scene", lambda: AbstractValue.Make(scene), self._calc_scene,
                                       prerequisites_of_calc={self.abstract_state_ticket(self._scene)})
        self.DeclareVectorOutputPort("visible_fraction", 1, self._calc_visible,
                                     prerequisites_of_calc={self.abstract_state_ticket(self._scene)})
        self.DeclareAbstractOutputPort("history", lambda: AbstractValue.Make(()), self._calc_history,
                                       prerequisites_of_calc={self.abstract_state_ticket(self._history)})
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, period, self._apply)
        self.foss = foss
        self.period = period

    def set_scene(self, context, scene: ShelfScene) -> None:
        """Start from `scene` (and an empty history)."""
        context.get_mutable_abstract_state(self._scene).set_value(scene)
        context.get_mutable_abstract_state(self._history).set_value(())

    def _calc_scene(self, context, output):
        output.set_value(context.get_abstract_state(self._scene).get_value())

    def _calc_visible(self, context, output: BasicVector):
        output.SetAtIndex(0, self.foss.visible_fraction(context.get_abstract_state(self._scene).get_value()))

    def _calc_history(self, context, output):
        output.set_value(context.get_abstract_state(self._history).get_value())

    def _apply(self, context, state):
        if not self.action_port.HasValue(context):
            return
        action = self.action_port.Eval(context)
        if shelf_action(action) is None:
            return
        scene = context.get_abstract_state(self._scene).get_value()
        new, outcome = self.foss.step(scene, action)
        history = context.get_abstract_state(self._history).get_value()
        state.get_mutable_abstract_state(self._scene).set_value(new)
        state.get_mutable_abstract_state(self._history).set_value(history + (outcome,))
