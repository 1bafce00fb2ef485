"""PushPlanner: a free-space linear push per segmented object (ms_drake.pushing.free_space).

Ports (declared first in __init__):
  inputs
    depth_image   ImageDepth32F (metres), from the station's camera
    masks         InstanceMasks (visible masks; ids name the objects)
  output
    pushes        tuple[Push]: one per mask that has a valid push (quality 1), `object_id` = the
                  mask id, in mask order; masks without a valid push (quality 0) are left out.
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.pushing.free_space import PushError, PushParams, plan_pushes
from ms_drake.types import InstanceMasks


class PushPlanner(LeafSystem):
    """camera: PinholeCamera of the depth camera; workspace: Workspace.from_scenario(scenario)."""

    def __init__(self, camera: PinholeCamera, workspace: Workspace, params: PushParams | None = None):
        super().__init__()
        if camera is None or workspace is None:
            raise PushError("PushPlanner needs camera= (PinholeCamera.from_config) and workspace= "
                            "(Workspace.from_scenario)")
        w, h = camera.width, camera.height
        # Ports first.
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(h, w)))
        self.pushes_port = self.DeclareAbstractOutputPort(
            "pushes", lambda: AbstractValue.Make(()), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.camera, self.workspace = camera, workspace
        self.params = params or PushParams()

    def plan(self, depth, masks: InstanceMasks):
        """The computation behind the output port, callable without a Diagram."""
        return plan_pushes(depth, masks, self.camera, self.workspace, self.params)

    def _calc(self, context, output):
        if not self.depth_port.HasValue(context):
            raise PushError("PushPlanner: the depth_image input is not connected")
        depth = self.depth_port.Eval(context)
        masks = self.masks_port.Eval(context) if self.masks_port.HasValue(context) else InstanceMasks.empty(
            self.camera.height, self.camera.width)
        output.set_value(self.plan(depth, masks))
