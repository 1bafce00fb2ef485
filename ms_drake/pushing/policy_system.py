"""PushPolicySystem: one linear push by a Ch. 4 policy (ms_drake.pushing.policies).

Ports (declared first in __init__):
  inputs
    depth_image   ImageDepth32F (metres), from the station's camera
    masks         InstanceMasks (visible masks; ids name the objects)
    objects       tuple[ObjectGeometry] (optional: meshes and world poses, simulation ground truth)
  output
    pushes        tuple[Push]: the policy's push (one), or () when it finds no collision-free push.

source "state": the policy plans on `objects` (full state, coal checks); "image": on the depth
image and masks (image clearance check); "auto" (default): state when `objects` holds any
object, else the image. quasi_random draws from (seed, round(time in ms)).
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F

from ms_drake.geometry import PinholeCamera, Workspace
from ms_drake.pushing.free_space import PushError
from ms_drake.pushing.policies import (
    PolicyParams,
    check_push_policy,
    image_scene,
    plan_policy_push,
    state_scene,
)
from ms_drake.types import InstanceMasks

SOURCES = ("auto", "state", "image")


class PushPolicySystem(LeafSystem):
    """policy: one of ms_drake.pushing.policies.POLICIES; camera: PinholeCamera of the depth
    camera; workspace: Workspace.from_scenario(scenario)."""

    def __init__(self, policy: str, camera: PinholeCamera, workspace: Workspace, source: str = "auto",
                 params: PolicyParams | None = None, seed: int = 0):
        super().__init__()
        check_push_policy(policy)
        if source not in SOURCES:
            raise PushError(f"PushPolicySystem source {source!r} unknown; choose one of {', '.join(SOURCES)}")
        if camera is None or workspace is None:
            raise PushError("PushPolicySystem needs camera= (PinholeCamera.from_config) and workspace= "
                            "(Workspace.from_scenario)")
        w, h = camera.width, camera.height
        # Ports first.
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.masks_port = self.DeclareAbstractInputPort("masks", AbstractValue.Make(InstanceMasks.empty(h, w)))
        self.objects_port = self.DeclareAbstractInputPort("objects", AbstractValue.Make(()))
        self.pushes_port = self.DeclareAbstractOutputPort(
            "pushes", lambda: AbstractValue.Make(()), self._calc,
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.policy, self.source = policy, source
        self.camera, self.workspace = camera, workspace
        self.params = params or PolicyParams()
        self.seed = int(seed)

    def plan(self, depth=None, masks: InstanceMasks | None = None, objects=(), step: int = 0):
        """The computation behind the output port, callable without a Diagram: tuple[Push]."""
        use_state = self.source == "state" or (self.source == "auto" and len(objects) > 0)
        if use_state:
            if not objects:
                raise PushError("PushPolicySystem source='state' needs the objects input (tuple[ObjectGeometry])")
            scene = state_scene(objects, self.workspace)
        else:
            if depth is None:
                raise PushError("PushPolicySystem: the depth_image input is not connected (source 'image')")
            masks = masks if masks is not None else InstanceMasks.empty(self.camera.height, self.camera.width)
            scene = image_scene(depth, masks, self.camera, self.workspace, self.params)
        push = plan_policy_push(self.policy, scene, self.params, seed=[self.seed, int(step)])
        return () if push is None else (push,)

    def _calc(self, context, output):
        objects = self.objects_port.Eval(context) if self.objects_port.HasValue(context) else ()
        depth = self.depth_port.Eval(context) if self.depth_port.HasValue(context) else None
        masks = self.masks_port.Eval(context) if self.masks_port.HasValue(context) else None
        output.set_value(self.plan(depth, masks, tuple(objects), step=round(1000 * context.get_time())))
