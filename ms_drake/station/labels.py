"""The station's label-image sensor computed from its depth image: one VTK render per depth +
label pair instead of two.

- `DepthLabeler`: the scene's primitives (boxes, cylinders, spheres) and per-pixel depth ->
  label image; one numba kernel (ms_drake/station/_label_kernel.py) claims every pixel for the
  primitive whose surface the depth point lies on.
- `DepthLabelImage` (LeafSystem): `<cam>.depth_image` + `query_object` -> `<cam>.label_image`;
  `make_depth_label_image(sensor, scene_graph)` builds it for an RgbdSensor. MakeStation uses it
  by default (`label_images="depth"`); its pixels equal VTK's own label image on 99.99 % of
  pixels (tests/test_depth_labels.py).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    Box,
    Capsule,
    Cylinder,
    Ellipsoid,
    HalfSpace,
    QueryObject,
    RenderLabel,
    Role,
    Sphere,
)
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I

from ms_drake.geometry import as_matrix4, as_rigid_transform
from ms_drake.station._label_kernel import label_rows, prepare

# --------------------------------------------------------------------------------------------
# Label image from the rendered depth image (one VTK render per depth + label pair, not two)
# --------------------------------------------------------------------------------------------

# RenderEngineVtk tessellates cylinders with 50 sides and spheres with 50 x 50 (Drake's
# SetCylinderOptions / SetSphereOptions): the drawn faces lie inside the true shape by at most
# the chord sagitta r * (1 - cos(pi / 50)) = 0.002 r.
_VTK_SAGITTA = 1.0 - np.cos(np.pi / 50)
# Numerical tolerance of a de-projected depth pixel (float32 depth, 24-bit depth encoding over
# <= 3 m is 0.2 um; measured on saved heaps: median 0.1 um from the true surface).
_DEPTH_TOL = 2e-5
# Kind codes of the kernel (_label_kernel: BOX, CYLINDER, SPHERE); larger codes force a render.
_KIND_CODES = {"box": 0, "cylinder": 1, "sphere": 2, "unsupported": 3, "not_rendered": 4}
_SPHERE = 2
_UNIT_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)


@dataclass(frozen=True)
class _LabelPrimitive:
    """One perception geometry as the labeller sees it (geometry frame G)."""

    geometry_id: object  # GeometryId
    label: int
    kind: str  # "box" | "cylinder" | "sphere" | "unsupported" | "not_rendered"
    size: np.ndarray  # (3,) half extents (box), (r, r, L/2) (cylinder), (r, r, r) (sphere)
    eps: float  # how far outside the true shape a drawn surface point may lie
    corners: np.ndarray  # (8, 3) corners of an inflated bounding box, in G

    @property
    def half(self) -> np.ndarray:
        """Half extents of the claim region."""
        return self.size + self.eps


class DepthLabeler:
    """The label image a renderer would draw, computed from its depth image instead.

    Every valid depth pixel is de-projected to its surface point; the pixel takes the label of
    the geometry whose surface that point lies on (within the renderer's tessellation error
    plus a numerical tolerance: 0.02 mm + 0.002 r for cylinders/spheres); pixels within reach
    of two geometries go to the one with the smaller |signed distance|. Pixels no geometry
    claims take `default_label` (the environment: by default the label whose geometries have
    the largest total bounding-box volume); pixels without depth (kTooFar) take kEmpty.
    Supported shapes: Box, Cylinder, Sphere (every ms_drake object and environment). One
    numba kernel (ms_drake.station._label_kernel.label_rows, compiled on the first call
    and cached in __pycache__) visits each pixel once and tests only the geometries whose
    screen rectangle holds it (one OpenCV pass (cv2.transform, cv2.inRange) per geometry plus
    a numpy pass over the crowded pixels, the reference in tests/test_depth_labels.py, is 2-4x
    slower).

    `label(...)` returns None when the answer could be inexact, and callers then render:
    a geometry of another shape (mesh, capsule, ...) or with label kDoNotRender in the view
    frustum of a non-default label, or a pixel closer than the depth range (kTooClose).

    threads: the image is cut into this many row bands labelled in parallel threads (the
    kernel releases the GIL); default 1: at 640x480 with 19 geometries one thread takes 0.98 ms
    wall, two 0.91 ms wall for 1.3x the CPU (idle 2-core machine), and two are slower when the
    other core is busy (the renderer's or another process's); measured 2026-11-22, commit 523f11c.

    Pixel convention, measured: RenderEngineVtk's pixel (u, v) sees the ray through
    ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy); with the integer-centre convention of
    drake::systems::sensors::CameraInfo (and of `PinholeCamera`) the de-projected points of
    8 saved heaps are 0.15 mm (median) / 0.85 mm (max) off the geometry, with +0.5 they are
    0.1 um / 0.085 mm (the cylinder sagitta). Drake knows of this half pixel
    (RobotLocomotion/drake PR #10190).

    Agreement with RenderEngineVtk's label image on 8 saved 15-object heaps at 640x480:
    99.993-100 % of the pixels (0-21 differing pixels per image, where objects touch).
    """

    def __init__(self, inspector, intrinsics, renderer_name: str, default_label: int | None = None,
                 threads: int | None = None):
        self.width, self.height = intrinsics.width(), intrinsics.height()
        self.fx, self.fy = intrinsics.focal_x(), intrinsics.focal_y()
        self.cx, self.cy = intrinsics.center_x(), intrinsics.center_y()
        self._rx = ((np.arange(self.width) + 0.5 - self.cx) / self.fx).astype(np.float32)  # x / z of column u
        self._ry = ((np.arange(self.height) + 0.5 - self.cy) / self.fy).astype(np.float32)  # y / z of row v
        prims, volume = [], {}
        for gid in inspector.GetAllGeometryIds(Role.kPerception):
            props = inspector.GetPerceptionProperties(gid)
            accepting = props.GetPropertyOrDefault("renderer", "accepting", set())
            if accepting and renderer_name not in accepting:
                continue  # this renderer never draws it
            if not props.HasProperty("label", "id"):
                raise ValueError(f"DepthLabeler: geometry {inspector.GetName(gid)!r} has no ('label', 'id') "
                                 "perception property; RenderEngineVtk would refuse it too")
            label = props.GetProperty("label", "id")
            shape = inspector.GetShape(gid)
            if label == RenderLabel.kDoNotRender:
                kind, half, eps = "not_rendered", None, 0.0
            elif isinstance(shape, Box):
                kind, half, eps = "box", np.array([shape.width(), shape.depth(), shape.height()]) / 2, _DEPTH_TOL
            elif isinstance(shape, Cylinder):
                r = shape.radius()
                kind, half, eps = "cylinder", np.array([r, r, shape.length() / 2]), _DEPTH_TOL + _VTK_SAGITTA * r
            elif isinstance(shape, Sphere):
                r = shape.radius()
                kind, half, eps = "sphere", np.full(3, r), _DEPTH_TOL + 2 * _VTK_SAGITTA * r
            else:
                kind, half, eps = "unsupported", None, 0.0
            if half is None:  # bounds of any shape: its axis-aligned bounding box in G
                half, centre = _shape_aabb(shape)
            else:
                centre = np.zeros(3)
            lab = int(label)
            if kind != "not_rendered":
                volume[lab] = volume.get(lab, 0.0) + float(np.prod(2 * half))
            prims.append(_LabelPrimitive(gid, lab, kind, half, eps, centre + _UNIT_CORNERS * (half + eps)))
        if default_label is None:
            default_label = max(volume, key=volume.get) if volume else int(RenderLabel.kEmpty)
        self.default_label = int(default_label)
        self._prims = [p for p in prims if p.label != self.default_label or p.kind == "not_rendered"]
        self._corners = np.array([p.corners for p in self._prims], np.float64).reshape(-1, 8, 3)
        self._ids = [p.geometry_id for p in self._prims]
        # The primitives packed for the kernel (ms_drake.station._label_kernel.label_rows).
        self._kind = np.array([_KIND_CODES[p.kind] for p in self._prims], np.int64)
        self._size = np.array([p.size for p in self._prims], np.float64).reshape(-1, 3)
        self._eps = np.array([p.eps for p in self._prims], np.float64)
        half = self._size + self._eps[:, None]
        self._half = half.astype(np.float32)  # the claim test is float32 (as OpenCV's was)
        self._r2 = (half[:, 0] ** 2).astype(np.float32)
        self._labels = np.array([p.label for p in self._prims], np.int16)
        self._empty = int(RenderLabel.kEmpty)
        self.threads = max(1, int(threads or 1))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    @property
    def geometry_ids(self) -> list:
        """Geometries whose poses `label` asks for (all but those of the default label)."""
        return [p.geometry_id for p in self._prims]

    def label(self, depth: np.ndarray, X_WC: RigidTransform, poses: dict, z_near: float = 0.0,
              z_far: float = np.inf) -> np.ndarray | None:
        """(H, W) int16 label image from a depth image (metres, Drake's kTooFar = inf and
        kTooClose = 0) taken from X_WC; `poses` maps the `geometry_ids` to X_WG (poses:
        RigidTransform or 4x4 array). None when the result could differ from a rendered label
        image (see the class doc)."""
        X_WC = as_rigid_transform(X_WC, "X_WC")
        if depth.shape != (self.height, self.width):
            raise ValueError(f"DepthLabeler: depth image is {depth.shape[1]}x{depth.shape[0]}, camera is "
                             f"{self.width}x{self.height}")

        depth = np.ascontiguousarray(depth, np.float32)
        if depth.flags.writeable:  # one compiled kernel: numba specialises on read-only (Drake's images)
            depth = depth.view()
            depth.flags.writeable = False
        # Drake's own poses (a QueryObject's) as they are: checking 20-odd of them for every image
        # would add ~10 % to the labeller; arrays are checked, and every pose must be finite.
        X_WG = np.array([X.GetAsMatrix4() if isinstance(X, RigidTransform) else as_matrix4(X, f"poses[{g}]")
                         for g, X in ((g, poses[g]) for g in self._ids)]).reshape(-1, 4, 4)
        if not np.isfinite(X_WG).all():
            raise ValueError("DepthLabeler.label: poses holds a non-finite pose (NaN or inf)")
        X_CW = np.ascontiguousarray(X_WC.inverse().GetAsMatrix4())
        M, rects = prepare(X_CW, X_WG, self._corners, self.fx, self.fy, self.cx, self.cy, self.height, self.width,
                           float(z_near), float(z_far))
        seen = np.flatnonzero((rects[:, 1] > rects[:, 0]) & (rects[:, 3] > rects[:, 2]))
        if seen.size and np.any(self._kind[seen] > _SPHERE):
            return None  # an unsupported or kDoNotRender geometry in view
        if seen.size:
            v0, u0 = int(rects[seen, 0].min()), int(rects[seen, 2].min())
            v1, u1 = int(rects[seen, 1].max()), int(rects[seen, 3].max())
        else:
            v0 = v1 = u0 = u1 = 0
        label = np.empty(depth.shape, np.int16)
        args = (v0, v1, u0, u1, seen, rects, M, self._kind, self._half, self._r2, self._size, self._eps,
                self._labels, self.default_label, self._empty)
        if self.threads == 1 or v1 - v0 < 16 * self.threads:
            too_close = label_rows(depth, self._rx, self._ry, label, 0, self.height, *args)
        else:  # row bands of the claimed rows in threads (the kernel releases the GIL); disjoint outputs
            edges = np.linspace(v0, v1, self.threads + 1).astype(int)
            edges[0], edges[-1] = 0, self.height
            jobs = [self._pool.submit(label_rows, depth, self._rx, self._ry, label, int(a), int(b), *args)
                    for a, b in zip(edges[:-1], edges[1:])]
            too_close = any([job.result() for job in jobs])
        return None if too_close else label  # kTooClose: the renderer's label shows what lies there


def _shape_aabb(shape) -> tuple[np.ndarray, np.ndarray]:
    """(half extents, centre) of a bounding box of any Drake shape in its own frame."""
    if isinstance(shape, Capsule):
        r = shape.radius()
        return np.array([r, r, shape.length() / 2 + r]), np.zeros(3)
    if isinstance(shape, Ellipsoid):
        return np.array([shape.a(), shape.b(), shape.c()]), np.zeros(3)
    if isinstance(shape, HalfSpace):
        return np.full(3, 1e4), np.array([0.0, 0.0, -1e4])
    if hasattr(shape, "GetConvexHull"):  # Mesh, Convex
        hull = shape.GetConvexHull()
        v = np.array([hull.vertex(i) for i in range(hull.num_vertices())])
        lo, hi = v.min(axis=0), v.max(axis=0)
        return (hi - lo) / 2, (hi + lo) / 2
    return np.full(3, 1e4), np.zeros(3)  # unknown shape: everywhere (always forces a render)


class DepthLabelImage(LeafSystem):
    """Label image from the depth image (`DepthLabeler`), rendering only when it must.

    Inputs ``depth_image`` (ImageDepth32F, from the RgbdSensor), ``query_object`` (SceneGraph's
    QueryObject, for the geometry and camera poses) and ``rendered_label_image`` (ImageLabel16I,
    the sensor's own label port: evaluated, i.e. rendered, only for the images `DepthLabeler`
    cannot do exactly; may stay unconnected if that never happens). Output ``label_image``
    (ImageLabel16I). The camera is the sensor's default one (parent frame, X_PB, intrinsics);
    geometries added to SceneGraph after construction are not seen.
    """

    def __init__(self, labeler: DepthLabeler, parent_frame, X_PC: RigidTransform, z_near: float, z_far: float):
        super().__init__()

        w, h = labeler.width, labeler.height
        # Ports first.
        self._depth = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self._query = self.DeclareAbstractInputPort("query_object", AbstractValue.Make(QueryObject()))
        self._rendered = self.DeclareAbstractInputPort("rendered_label_image", AbstractValue.Make(ImageLabel16I(w, h)))
        self.DeclareAbstractOutputPort("label_image", lambda: AbstractValue.Make(ImageLabel16I(w, h)), self._calc)
        self.labeler = labeler
        self._parent, self._X_PC = parent_frame, as_rigid_transform(X_PC, "X_PC")
        self._z_near, self._z_far = z_near, z_far
        self.renders = 0  # diagnostics: how many images fell back to the rendered label image

    def _calc(self, context, output):
        qo = self._query.Eval(context)
        depth = np.asarray(self._depth.Eval(context).data)[:, :, 0]
        X_WC = qo.GetPoseInWorld(self._parent) @ self._X_PC
        poses = {g: qo.GetPoseInWorld(g) for g in self.labeler.geometry_ids}
        label = self.labeler.label(depth, X_WC, poses, self._z_near, self._z_far)
        if label is None:
            if not self._rendered.HasValue(context):
                raise ValueError("DepthLabelImage: this image needs the rendered label image (a mesh or "
                                 "kDoNotRender geometry in view, or depth below z_near); connect the sensor's "
                                 "label_image port to 'rendered_label_image'")
            self.renders += 1
            output.set_value(self._rendered.Eval(context))
            return
        img = output.get_mutable_value()
        np.asarray(img.mutable_data)[:, :, 0] = label


def make_depth_label_image(sensor, scene_graph) -> DepthLabelImage:
    """A DepthLabelImage for an RgbdSensor (its default cameras and pose). The color (label) and
    depth cameras must share renderer, intrinsics, pose and clipping range, and the depth range
    must reach the far clipping plane (as ApplyCameraConfig makes them when clipping_near/far
    equal z_near/z_far); otherwise the two images see different things and this raises."""
    color, depth = sensor.default_color_render_camera(), sensor.default_depth_render_camera()
    cc, dc = color.core(), depth.core()
    ci, di = cc.intrinsics(), dc.intrinsics()
    same = (cc.renderer_name() == dc.renderer_name()
            and (ci.width(), ci.height()) == (di.width(), di.height())
            and np.allclose([ci.focal_x(), ci.focal_y(), ci.center_x(), ci.center_y()],
                            [di.focal_x(), di.focal_y(), di.center_x(), di.center_y()])
            and cc.sensor_pose_in_camera_body().IsExactlyEqualTo(dc.sensor_pose_in_camera_body())
            and (cc.clipping().near(), cc.clipping().far()) == (dc.clipping().near(), dc.clipping().far())
            and depth.depth_range().max_depth() >= cc.clipping().far())
    if not same:
        raise ValueError(f"sensor {sensor.get_name()!r}: a label image from depth needs the color and depth "
                         "cameras to share renderer, intrinsics, pose and clipping range, with z_far >= "
                         "clipping_far; fix the camera config or render the label image")
    labeler = DepthLabeler(scene_graph.model_inspector(), di, dc.renderer_name())
    X_PC = sensor.default_X_PB() @ dc.sensor_pose_in_camera_body()
    return DepthLabelImage(labeler, sensor.default_parent_frame_id(), X_PC,
                           cc.clipping().near(), cc.clipping().far())
