"""Drake renders of a shelf scene (kept apart from the fast geometric generator: a render costs
tens of milliseconds, a scene a few).

`render_shelf_scene(scenario, scene)` builds the scenario's station with MakeStation -- its plant
config, shelf and cameras; no robot (the reference's Fetch parks the bluction tool out of view
before it looks) and no registry objects -- with every occluder and the target added as a box or
cylinder (`MakeStation(extra_objects=...)`, SDF from ms_drake.objects.sdf, the target in the target
colour), poses them on the shelf floor and renders one camera: depth (metres), label image (VTK's
own render by default) and colour.

`ShelfDepthCamera(scenario)`: a LeafSystem, input ``scene`` (ShelfScene) -> outputs
``depth_image`` (ImageDepth32F) and ``rgb_image`` (ImageRgba8U), the renders of the scene's
current state (FOSS has no station of its own; the learned shelf occupancy and the
ShelfSegmenter read these images). It keeps its station while the scene's
objects (ids, shapes and sizes) stay the same and only re-poses them, and keeps the last render.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from functools import partial

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageRgba8U

from ms_drake.errors import SceneError
from ms_drake.objects import TARGET_RGBA
from ms_drake.objects.sdf import Inertia, Shape, object_sdf
from ms_drake.scenario import Scenario
from ms_drake.station import MakeStation, get_plant, station_objects
from ms_drake.types import ShelfObject, ShelfScene

OCCLUDER_RGBA = (0.35, 0.55, 0.80, 1.0)
DENSITY = 400.0  # kg/m^3, as the procedural object set
SET = "shelf"  # the objects' set name in the station ('shelf/<object id>')


@dataclass(frozen=True, eq=False)
class ShelfRender:
    """One camera's images of a shelf scene; `labels` maps object id -> label image value."""

    depth: np.ndarray  # (H, W) metres, inf where nothing
    label: np.ndarray  # (H, W) int
    rgb: np.ndarray  # (H, W, 3) uint8
    labels: dict

    def mask(self, object_id: str) -> np.ndarray:
        return self.label == self.labels[object_id]


def object_sdf_text(o: ShelfObject, rgba, model_name: str) -> str:
    """SDF of a shelf object (a solid box or cylinder of DENSITY) with the model name given."""
    if o.kind == "box":
        shape = Shape("box", (o.width, o.depth, o.height))
        m = DENSITY * o.width * o.depth * o.height
        ixx, iyy, izz = (m * (o.depth ** 2 + o.height ** 2) / 12, m * (o.width ** 2 + o.height ** 2) / 12,
                         m * (o.width ** 2 + o.depth ** 2) / 12)
    else:
        r = o.width / 2
        shape = Shape("cylinder", (r, o.height))
        m = DENSITY * np.pi * r * r * o.height
        ixx = iyy = m * (3 * r * r + o.height ** 2) / 12
        izz = m * r * r / 2
    return object_sdf(model_name, Inertia(m, (0.0, 0.0, 0.0), ixx, iyy, izz), [(shape, rgba)], [shape],
                      contact_spheres=False)


def shelf_station(scenario: Scenario, scene: ShelfScene, label_images: str = "render"):
    """(station, context, {object id: label}) for `scene` in the scenario's shelf, objects posed."""
    if scenario.environment.type != "shelf":
        raise SceneError(f"environment.type is {scenario.environment.type!r}: render shelf scenes in a shelf "
                         "scenario (e.g. FetchShelf)")
    s = copy.deepcopy(scenario)
    s.robot.name, s.robot.grippers = "", []
    s.objects.names, s.objects.count = [], 0
    s.hardware = False
    objects = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    extra = [(f"{SET}/{o.id}", partial(object_sdf_text, o, TARGET_RGBA if o is scene.target else OCCLUDER_RGBA))
             for o in objects]
    station = MakeStation(s, label_images=label_images, extra_objects=extra)
    context = station.CreateDefaultContext()
    return station, context, pose_shelf_objects(station, context, scenario, scene)


def pose_shelf_objects(station, context, scenario: Scenario, scene: ShelfScene) -> dict:
    """Pose the station's shelf objects (made by shelf_station for objects of the same ids) where
    `scene` has them; returns {object id: label}."""
    plant = get_plant(station)
    plant_context = plant.GetMyMutableContextFromRoot(context)
    origin = np.asarray(scenario.environment.position, float)
    objects = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    by_id = {o.id: o for o in objects}
    labels = {}
    for so in station_objects(plant):
        o = by_id[so.full_name.split("/", 1)[1]]
        plant.SetFreeBodyPose(plant_context, plant.get_body(so.body_index),
                              RigidTransform(origin + [o.x, o.y, o.height / 2]))
        labels[o.id] = int(so.body_index)
    return labels


def render_shelf_scene(scenario: Scenario, scene: ShelfScene, camera: str = "front",
                       label_images: str = "render") -> ShelfRender:
    """Depth, label and colour images of `scene` from the scenario's camera `camera`."""
    station, context, labels = shelf_station(scenario, scene, label_images)
    if camera not in scenario.cameras:
        raise SceneError(f"camera {camera!r} is not in the scenario's cameras ({', '.join(scenario.cameras)})")
    depth = np.array(station.GetOutputPort(f"{camera}.depth_image").Eval(context).data)[:, :, 0].copy()
    label = np.array(station.GetOutputPort(f"{camera}.label_image").Eval(context).data)[:, :, 0].astype(int)
    rgb = np.array(station.GetOutputPort(f"{camera}.rgb_image").Eval(context).data)[:, :, :3].copy()
    return ShelfRender(depth, label, rgb, labels)


class ShelfDepthCamera(LeafSystem):
    """Ports (declared first): input ``scene`` (ShelfScene), outputs ``depth_image`` (ImageDepth32F,
    metres, inf where nothing) and ``rgb_image`` (ImageRgba8U; the target in the target colour) of
    the scenario's camera `camera`. Each output renders only its own image, once per scene."""

    def __init__(self, scenario: Scenario, camera: str = "front"):
        super().__init__()
        if camera not in scenario.cameras:
            raise SceneError(f"camera {camera!r} is not in the scenario's cameras ({', '.join(scenario.cameras)})")
        cam = scenario.cameras[camera]
        self.scene_port = self.DeclareAbstractInputPort("scene", AbstractValue.Make(ShelfScene(())))
        self.DeclareAbstractOutputPort("depth_image", lambda: AbstractValue.Make(ImageDepth32F(cam.width, cam.height)),
                                       partial(self._calc, "depth_image"))
        self.DeclareAbstractOutputPort("rgb_image", lambda: AbstractValue.Make(ImageRgba8U(cam.width, cam.height)),
                                       partial(self._calc, "rgb_image"))
        self.scenario, self.camera = scenario, camera
        self._last = {}  # image name -> (scene, image)
        self._station = None  # (objects' ids, shapes and sizes; station; its context; the scene it is posed at)

    def _posed_station(self, scene: ShelfScene):
        objects = list(scene.objects) + ([scene.target] if scene.target is not None else [])
        key = tuple((o.id, o.kind, o.width, o.depth, o.height) for o in objects)
        if self._station is None or self._station[0] != key:
            station, station_context, _ = shelf_station(self.scenario, scene)
            self._station = [key, station, station_context, scene]
        elif self._station[3] != scene:
            pose_shelf_objects(self._station[1], self._station[2], self.scenario, scene)
            self._station[3] = scene
        return self._station[1], self._station[2]

    def _calc(self, name: str, context, output):
        scene = self.scene_port.Eval(context)
        last = self._last.get(name)
        if last is None or last[0] != scene:
            station, station_context = self._posed_station(scene)
            data = np.array(station.GetOutputPort(f"{self.camera}.{name}").Eval(station_context).data)
            if name == "depth_image":
                image = ImageDepth32F(data.shape[1], data.shape[0])
            else:
                image = ImageRgba8U(data.shape[1], data.shape[0])
            image.mutable_data[:] = data
            last = self._last[name] = (scene, image)
        output.set_value(last[1])
