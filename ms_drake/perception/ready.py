"""ImagesReady: whether a camera's images have arrived, so a controller does not act on nothing.

Ports (declared first):
  inputs  rgb_image (ImageRgba8U), depth_image (ImageDepth32F)
  output  ready: 1-vector, 1.0 once both images have the camera's size, else 0.0

A simulated station renders from time 0; a hardware station outputs empty (0 x 0) images until
the first camera message arrives over LCM. The ActionExecutor's `ready` input keeps the
controller idle until then.
"""

from __future__ import annotations

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U


class ImagesReady(LeafSystem):
    def __init__(self, width: int, height: int):
        super().__init__()
        self.rgb_port = self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(ImageRgba8U(width, height)))
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(width, height)))
        self.DeclareVectorOutputPort("ready", BasicVector(1), self._calc)
        self.size = (int(width), int(height))

    def _calc(self, context, output):
        ok = all(p.HasValue(context) and (p.Eval(context).width(), p.Eval(context).height()) == self.size
                 for p in (self.rgb_port, self.depth_port))
        output.SetAtIndex(0, 1.0 if ok else 0.0)
