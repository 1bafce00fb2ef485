"""Depth sensor models: what a real depth camera does to the perfect depth image Drake renders.

`DepthSensorModel` (a LeafSystem) sits between an RgbdSensor's ``depth_image_32F`` output and the
station's exported ``<cam>.depth_image`` port (same name and type, ImageDepth32F in metres). The
scenario file picks its parameters per camera (``depth_sensors: {overhead: {preset: phoxi}}``,
ms_drake.scenario.DepthSensorConfig); `apply_depth_sensor` is the same model on arrays.

The model, in the order it is applied to a depth image z (metres; Drake's "no return" values,
0 for too close and inf for too far, pass through unchanged):

1. Noise: z + sigma(z) * N(0, 1), sigma(z) = ``noise_a`` + ``noise_b`` * z^2 (the axial noise of
   triangulating sensors grows with the square of the distance).
2. Quantisation: either of disparity (``disparity_step`` px of a sensor with ``focal_baseline``
   = f * b px m, z = fb / d: the depth step grows as z^2 * step / fb), or of depth in
   ``depth_unit`` metres.
3. Missing pixels (set to 0, the value every consumer reads as "no return": perception keeps
   ``isfinite(d) & (d > 0)``), each class with its own probability:
   - edges: pixels within ``edge_width`` px of a neighbour nearer by more than ``edge_jump`` m,
     i.e. the far side of a depth discontinuity, where a structured-light projector or a
     lidar's beam does not reach (occlusion shadow, mixed pixels): ``edge_dropout``;
   - grazing surfaces: the angle between the surface normal (from the depth image's gradient, on
     continuous surfaces: every 4-neighbour within ``edge_jump``) and the viewing ray above
     ``grazing_deg``: dropout rising linearly to ``grazing_dropout`` at 90 degrees;
   - dark surfaces: pixels of the optional ``rgb_image`` input whose luminance (0..1) is below
     ``dark_threshold``: ``dark_dropout`` (low return signal). The thresholds sit below the
     rendered bin's dark grey (0.12): black objects lose returns, the bin's floor does not;
   - holes: a Poisson(``holes``) number of random elliptical blobs of mean radius
     ``hole_radius`` px per image (specular spots, interference);
   - single pixels: ``pixel_dropout``.
   The masks come from the clean image (the geometry), the noise is added last to what remains.

Presets (`PRESETS`; parameter values and their sources):

- ``phoxi``: the bin's overhead camera, a Photoneo PhoXi S (structured light, 1032 x 772).
  Photoneo specifies a temporal noise (sigma on a diffuse 80 % albedo plane) of ~0.05 mm inside
  the S's 384-520 mm range and ~0.1 mm for the M at 0.5-1.1 m (wiki.photoneo.com, "PhoXi 3D
  scanners family"); the reference cites "0.05 mm depth precision" (dissertation line 879) and
  found "very little white noise" (line 865). At our 0.8 m: sigma = 0.05 mm + 0.3 mm/m^2 * z^2 =
  0.24 mm. Few holes: the projector's occlusion shadow at depth steps > 1 cm (2 px), grazing surfaces
  past 70 degrees, very dark surfaces rarely.
- ``l515``: the shelf's and the table's cameras, an Intel RealSense L515 (MEMS lidar). Its
  datasheet (Rev. 003, 2021) gives a depth accuracy of ~5 mm to ~14 mm through 9 m, and a depth
  unit of 0.25 mm; its depth noise at 1 m on a diffuse target is 1-2 mm: sigma = 0.5 mm +
  1 mm/m^2 * z^2 (1.5 mm at 1 m). Mixed and invalidated pixels at depth edges, lost returns on
  dark (low-reflectivity at 860 nm) and grazing surfaces (Intel's L515 tuning guide: "poor
  reflective surfaces" reduce the signal).
- ``primesense``: the reference's low-resolution real test set, a Primesense Carmine (640 x 480,
  "1 mm depth precision", line 879), i.e. Kinect-v1-like structured light. Axial noise after
  Nguyen, Izadi and Lovell 2012 ("Modeling Kinect sensor noise for improved 3D reconstruction
  and tracking", 3DIMPVT: sigma = 1.2 mm + 1.9 mm/m^2 * (z - 0.4)^2, 1.5 mm at 0.8 m), fit as
  0.5 mm + 1.5 mm/m^2 * z^2; disparity quantised to 1/8 px with f * b = 580 px * 7.5 cm (Khoshelham
  and Elberink 2012, "Accuracy and resolution of Kinect depth data", Sensors 12: the depth
  resolution falls with z^2; Smisek et al. 2011 measured a step of 2.73 z^2 + 0.74 z - 0.58 mm,
  1.8 mm at 0.8 m as here); wide occlusion shadows (4 px), many holes.
- ``none``: the perfect depth (the station then adds no system at all).

On the segmentation benchmark's heap images (overhead camera, 0.75-0.85 m) the presets lose
4 % (phoxi), 11 % (l515) and 22 % (primesense) of the pixels, with 0.23, 1.1 and 1.5 mm of noise.
Simplification: the edge band has a fixed width, where a real projector's shadow widens with the
step's height (f * b * dz / z^2 px).

Randomness: every draw comes from `image_rng(seed, camera_name, time)`, a numpy Generator
seeded by the scenario's ``random_seed``, the camera's name and the image's time (microseconds),
so one (scenario, time) gives one image; there is no global RNG.
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass

import cv2
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from ms_drake.errors import ScenarioError
from ms_drake.scenario import DEPTH_SENSOR_PRESETS, DepthSensorConfig


@dataclass(frozen=True)
class DepthSensorParams:
    """The model's parameters (module doc); the defaults are the perfect sensor (`none`)."""

    noise_a: float = 0.0  # m: constant part of the noise sigma
    noise_b: float = 0.0  # 1/m: sigma grows by noise_b * z^2
    depth_unit: float = 0.0  # m: depth quantisation step (0: none)
    disparity_step: float = 0.0  # px: disparity quantisation step (0: none)
    focal_baseline: float = 0.0  # px m: focal length times baseline for the disparity
    edge_jump: float = 0.01  # m: a neighbour nearer by more than this makes a depth edge
    edge_width: int = 0  # px: width of the band on the far side of an edge
    edge_dropout: float = 0.0  # probability that a pixel of the edge band is lost
    grazing_deg: float = 90.0  # deg: incidence angle where grazing dropout starts
    grazing_dropout: float = 0.0  # probability at 90 degrees (linear from grazing_deg)
    dark_threshold: float = 0.0  # luminance (0..1) below which a surface is dark
    dark_dropout: float = 0.0  # probability that a dark pixel is lost
    holes: float = 0.0  # mean number of random blobs per image
    hole_radius: float = 0.0  # px: mean radius of a blob
    pixel_dropout: float = 0.0  # probability that any pixel is lost

    def is_identity(self) -> bool:
        return self == DepthSensorParams()


PRESETS: dict[str, DepthSensorParams] = {
    "none": DepthSensorParams(),
    "phoxi": DepthSensorParams(noise_a=0.00005, noise_b=0.0003, edge_jump=0.01, edge_width=2, edge_dropout=0.5,
                               grazing_deg=70.0, grazing_dropout=0.8, dark_threshold=0.03, dark_dropout=0.2,
                               holes=1.0, hole_radius=3.0, pixel_dropout=0.0005),
    "l515": DepthSensorParams(noise_a=0.0005, noise_b=0.001, depth_unit=0.00025, edge_jump=0.01, edge_width=2,
                              edge_dropout=0.8, grazing_deg=60.0, grazing_dropout=1.0, dark_threshold=0.08,
                              dark_dropout=0.7, holes=3.0, hole_radius=4.0, pixel_dropout=0.005),
    "primesense": DepthSensorParams(noise_a=0.0005, noise_b=0.0015, disparity_step=0.125, focal_baseline=43.5,
                                    edge_jump=0.01, edge_width=4, edge_dropout=0.9, grazing_deg=60.0,
                                    grazing_dropout=1.0, dark_threshold=0.06, dark_dropout=0.5, holes=8.0,
                                    hole_radius=6.0, pixel_dropout=0.01),
}
assert tuple(PRESETS) == DEPTH_SENSOR_PRESETS  # scenario.py validates against the names


def depth_sensor_params(config: DepthSensorConfig | str) -> DepthSensorParams:
    """The parameters of a scenario's DepthSensorConfig (its preset with its overrides) or of a
    preset name."""
    if isinstance(config, str):
        config = DepthSensorConfig(preset=config)
    if config.preset not in PRESETS:
        raise ScenarioError(f"depth sensor preset {config.preset!r} unknown; allowed: {', '.join(PRESETS)}")
    overrides = {f.name: getattr(config, f.name) for f in dataclasses.fields(DepthSensorParams)
                 if getattr(config, f.name, None) is not None}
    if "edge_width" in overrides:
        overrides["edge_width"] = int(overrides["edge_width"])
    return dataclasses.replace(PRESETS[config.preset], **overrides)


def image_rng(seed: int, camera_name: str, time: float) -> np.random.Generator:
    """The Generator of one image: (seed, camera name, time in microseconds)."""
    return np.random.default_rng([int(seed) % (1 << 63), zlib.crc32(camera_name.encode()),
                                  int(round(float(time) * 1e6)) % (1 << 63)])


def incidence_cos(z: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """|cos| of the angle between the surface normal (from the depth gradient) and the viewing ray
    at each pixel (NaN where z or a neighbour is not a return)."""
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    P = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=-1)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    nn = np.linalg.norm(n, axis=-1)
    pn = np.linalg.norm(P, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(np.einsum("ijk,ijk->ij", n, P)) / (nn * pn)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    c = np.asarray(rgb, np.float32)[..., :3] / 255.0
    return 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]


def dropout_probability(z: np.ndarray, p: DepthSensorParams, fx: float, fy: float, cx: float, cy: float,
                        rgb: np.ndarray | None = None) -> np.ndarray:
    """(H, W) probability that each pixel is lost, from the geometry (edges, grazing) and the
    colour (dark); the random blobs and single pixels are not in it."""
    valid = np.isfinite(z) & (z > 0)
    q = np.zeros(z.shape, np.float32)
    if p.edge_width > 0 and p.edge_dropout > 0:
        k = 2 * int(p.edge_width) + 1
        nearest = cv2.erode(np.where(valid, z, np.float32(np.inf)).astype(np.float32), np.ones((k, k), np.uint8),
                            borderType=cv2.BORDER_REPLICATE)
        edge = valid & (z - nearest > p.edge_jump)
        q = np.where(edge, np.float32(p.edge_dropout), q)
    if p.grazing_dropout > 0 and p.grazing_deg < 90.0:
        c = incidence_cos(np.where(valid, z, np.nan).astype(np.float32), fx, fy, cx, cy)
        ang = np.degrees(np.arccos(np.clip(np.nan_to_num(c, nan=1.0), 0.0, 1.0)))
        g = np.clip((ang - p.grazing_deg) / (90.0 - p.grazing_deg), 0.0, 1.0) * p.grazing_dropout
        # only on continuous surfaces: across a depth step the gradient's "normal" is not a surface's
        # (the step is the edge term's); continuous = every 4-neighbour within edge_jump
        zf = np.where(valid, z, np.float32(np.inf)).astype(np.float32)
        k = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
        lo = cv2.erode(zf, k, borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(np.where(valid, z, np.float32(0.0)).astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
        with np.errstate(invalid="ignore"):  # inf - inf off the valid pixels
            smooth = valid & (z - lo <= p.edge_jump) & (hi - z <= p.edge_jump)
        q = np.maximum(q, np.where(smooth, g, 0.0).astype(np.float32))
    if rgb is not None and p.dark_dropout > 0 and p.dark_threshold > 0:
        dark = _luminance(rgb) < p.dark_threshold
        q = np.where(dark, np.maximum(q, np.float32(p.dark_dropout)), q)
    return np.where(valid, q, np.float32(0.0))


def apply_depth_sensor(depth: np.ndarray, params: DepthSensorParams, rng: np.random.Generator,
                       fx: float, fy: float, cx: float, cy: float, rgb: np.ndarray | None = None) -> np.ndarray:
    """The sensor model on a (H, W) depth image in metres (module doc); returns a new float32
    image, missing pixels 0. With the identity parameters the image is returned as a copy,
    unchanged and without drawing from `rng`."""
    z = np.array(depth, np.float32)
    z = z[..., 0] if z.ndim == 3 else z
    if params.is_identity():
        return z
    valid = np.isfinite(z) & (z > 0)
    h, w = z.shape
    q = dropout_probability(z, params, fx, fy, cx, cy, rgb)
    lost = rng.random((h, w), dtype=np.float32) < q
    if params.pixel_dropout > 0:
        lost |= rng.random((h, w), dtype=np.float32) < params.pixel_dropout
    if params.holes > 0 and params.hole_radius > 0:
        blobs = np.zeros((h, w), np.uint8)
        for _ in range(int(rng.poisson(params.holes))):
            c = (int(rng.integers(w)), int(rng.integers(h)))
            ax = tuple(max(1, int(round(params.hole_radius * f))) for f in rng.uniform(0.5, 1.5, 2))
            cv2.ellipse(blobs, c, ax, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        lost |= blobs.astype(bool)
    if params.noise_a > 0 or params.noise_b > 0:
        sigma = params.noise_a + params.noise_b * np.square(np.where(valid, z, 0.0))
        z = np.where(valid, z + sigma * rng.standard_normal((h, w), dtype=np.float32), z)
    if params.disparity_step > 0 and params.focal_baseline > 0:
        with np.errstate(divide="ignore"):
            disp = np.round(params.focal_baseline / z / params.disparity_step) * params.disparity_step
            z = np.where(valid & (disp > 0), params.focal_baseline / np.maximum(disp, 1e-9), z)
    elif params.depth_unit > 0:
        z = np.where(valid, np.round(z / params.depth_unit) * params.depth_unit, z)
    z = np.where(valid & ~lost, z, np.where(valid, np.float32(0.0), z)).astype(np.float32)
    return z


class DepthSensorModel(LeafSystem):
    """The depth sensor model as a Drake system (module doc).

    Inputs ``depth_image`` (ImageDepth32F, metres: the RgbdSensor's depth_image_32F) and
    ``rgb_image`` (ImageRgba8U, optional: only the dark-surface dropout reads it); output
    ``depth_image`` (ImageDepth32F, missing pixels 0), computed on demand and cached per input
    and time. The draws of an image come from `image_rng(seed, camera_name, t)`.

    params: DepthSensorParams (or a preset name); intrinsics (width, height, fx, fy, cx, cy) of the
    depth camera (the normals of the grazing dropout need them).
    """

    def __init__(self, params: DepthSensorParams | str, intrinsics, seed: int = 0, camera_name: str = "camera"):
        super().__init__()
        self.params = depth_sensor_params(params) if isinstance(params, str) else params
        w, h, fx, fy, cx, cy = intrinsics
        self.width, self.height = int(w), int(h)
        self.fx, self.fy, self.cx, self.cy = float(fx), float(fy), float(cx), float(cy)
        self.seed, self.camera_name = int(seed), str(camera_name)
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.rgb_port = self.DeclareAbstractInputPort("rgb_image", AbstractValue.Make(ImageRgba8U(w, h)))
        self.DeclareAbstractOutputPort("depth_image", lambda: AbstractValue.Make(ImageDepth32F(w, h)), self._calc,
                                       prerequisites_of_calc={self.time_ticket(), self.all_input_ports_ticket()})

    @staticmethod
    def from_camera_info(params, info, seed: int = 0, camera_name: str = "camera") -> "DepthSensorModel":
        """From a Drake CameraInfo (e.g. RgbdSensor.default_depth_render_camera().core().intrinsics())."""
        return DepthSensorModel(params, (info.width(), info.height(), info.focal_x(), info.focal_y(),
                                         info.center_x(), info.center_y()), seed, camera_name)

    def _calc(self, context, output):
        if not self.depth_port.HasValue(context):
            raise ScenarioError(f"DepthSensorModel({self.camera_name}): connect the depth_image input "
                                "(the RgbdSensor's depth_image_32F output)")
        depth = self.depth_port.Eval(context)
        if depth.width() != self.width or depth.height() != self.height:
            raise ScenarioError(f"DepthSensorModel({self.camera_name}): depth image {depth.width()}x{depth.height()}, "
                                f"camera {self.width}x{self.height}; build the model from the camera's intrinsics")
        rgb = np.asarray(self.rgb_port.Eval(context).data) if self.rgb_port.HasValue(context) else None
        z = apply_depth_sensor(depth.data, self.params, image_rng(self.seed, self.camera_name, context.get_time()),
                               self.fx, self.fy, self.cx, self.cy, rgb)
        out = output.get_mutable_value()
        out.resize(self.width, self.height)
        out.mutable_data[:, :, 0] = z
