"""Drake renders of a shelf scene (kept apart from the fast geometric generator: a render costs
tens of milliseconds, a scene a few).

`render_shelf_scene(scenario, scene)` builds the shelf station's world for one ShelfScene -- the
scenario's plant config, its shelf (ms_drake.station.station.add_environment) and its cameras
(add_cameras), no robot (the reference's Fetch parks the bluction tool out of view before it looks)
-- with every occluder and the target as a box or cylinder welded at its pose (SDF from
ms_drake.objects.sdf, the target in the target colour), and renders one camera: depth (metres),
label image and colour. MakeStation itself takes objects by registry name; shelf scene objects
have drawn dimensions, hence this builder.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.systems.framework import DiagramBuilder

from ms_drake.errors import SceneError
from ms_drake.objects import TARGET_RGBA
from ms_drake.objects.sdf import Inertia, Shape, object_sdf
from ms_drake.paths import make_parser
from ms_drake.scenario import Scenario
from ms_drake.station.station import add_cameras, add_environment
from ms_drake.types import ShelfObject, ShelfScene

OCCLUDER_RGBA = (0.35, 0.55, 0.80, 1.0)
DENSITY = 400.0  # kg/m^3, as the procedural object set


@dataclass(frozen=True, eq=False)
class ShelfRender:
    """One camera's images of a shelf scene; `labels` maps object id -> label image value."""

    depth: np.ndarray  # (H, W) metres, inf where nothing
    label: np.ndarray  # (H, W) int
    rgb: np.ndarray  # (H, W, 3) uint8
    labels: dict

    def mask(self, object_id: str) -> np.ndarray:
        return self.label == self.labels[object_id]


def _object_sdf(o: ShelfObject, rgba) -> str:
    if o.kind == "box":
        shape = Shape("box", (o.width, o.depth, o.height))
        volume = o.width * o.depth * o.height
    else:
        shape = Shape("cylinder", (o.width / 2, o.height))
        volume = np.pi * (o.width / 2) ** 2 * o.height
    m = DENSITY * volume
    inertia = Inertia(m, (0.0, 0.0, 0.0), m * 1e-2, m * 1e-2, m * 1e-2)  # welded: never simulated
    return object_sdf(f"shelf_{o.id}", inertia, [(shape, rgba)], [shape], contact_spheres=False)


def build_shelf_world(scenario: Scenario, scene: ShelfScene, camera: str = "front"):
    """(diagram, {object id: body index}) for `scene` in the scenario's shelf, seen by `camera`."""
    if scenario.environment.type != "shelf":
        raise SceneError(f"environment.type is {scenario.environment.type!r}: render shelf scenes in a shelf "
                         "scenario (e.g. FetchShelf)")
    if camera not in scenario.cameras:
        raise SceneError(f"camera {camera!r} is not in the scenario's cameras ({', '.join(scenario.cameras)})")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    parser = make_parser(plant)
    add_environment(plant, scenario, parser)
    origin = np.asarray(scenario.environment.position, float)
    bodies = {}
    objects = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    for o in objects:
        rgba = TARGET_RGBA if scene.target is not None and o is scene.target else OCCLUDER_RGBA
        (mi,) = parser.AddModelsFromString(_object_sdf(o, rgba), "sdf")
        body = plant.GetBodyByName("body", mi)
        plant.WeldFrames(plant.world_frame(), body.body_frame(),
                         RigidTransform(origin + [o.x, o.y, o.height / 2]))
        bodies[o.id] = int(body.index())
    plant.Finalize()
    cfg = scenario.cameras[camera]
    add_cameras(builder, [cfg], plant, scene_graph)
    sensor = builder.GetSubsystemByName(f"rgbd_sensor_{cfg.name}")
    builder.ExportOutput(sensor.depth_image_32F_output_port(), "depth_image")
    builder.ExportOutput(sensor.label_image_output_port(), "label_image")
    builder.ExportOutput(sensor.color_image_output_port(), "rgb_image")
    return builder.Build(), bodies


def render_shelf_scene(scenario: Scenario, scene: ShelfScene, camera: str = "front") -> ShelfRender:
    """Depth, label and colour images of `scene` from the scenario's camera `camera`."""
    diagram, bodies = build_shelf_world(scenario, scene, camera)
    context = diagram.CreateDefaultContext()
    depth = np.array(diagram.GetOutputPort("depth_image").Eval(context).data)[:, :, 0].copy()
    label = np.array(diagram.GetOutputPort("label_image").Eval(context).data)[:, :, 0].astype(int)
    rgb = np.array(diagram.GetOutputPort("rgb_image").Eval(context).data)[:, :, :3].copy()
    return ShelfRender(depth, label, rgb, bodies)
