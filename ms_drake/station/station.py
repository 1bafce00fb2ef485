"""MakeStation(scenario): the simulated (or hardware) station as one Drake Diagram.

Build order follows Drake's hardware_sim example: plant + scene graph from the scenario's
configs, environment, objects, robot and grippers, Finalize, cameras, visualization.

Exported ports (names identical in sim and hardware; docs/concepts.md):
- ``<cam>.rgb_image``, ``<cam>.depth_image`` (32F metres), ``<cam>.label_image`` for each camera;
- sim-only: ``body_poses``, ``body_spatial_velocities``, ``query_object``, ``contact_results``, ``state``
  (plant state); input ``applied_spatial_force`` (external forces on bodies; stations without suction cups).
Robot ports (``<arm>.position`` ...) are added by the robot drivers.

Objects are model instances named ``obj<k>__<set>__<name>`` (see `station_objects`). Their
default poses are a tidy grid above the environment; `ms_drake.scenes` sets heap poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlant
from pydrake.multibody.tree import ModelInstanceIndex
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.lcm import ApplyLcmBusConfig
from pydrake.systems.sensors import ApplyCameraConfig
from pydrake.visualization import ApplyVisualizationConfig

from ms_drake.errors import ScenarioError
from ms_drake.objects import TARGET_RGBA, get_object, get_object_set
from ms_drake.objects.sdf import OBJECT_MODULUS
from ms_drake.paths import make_parser
from ms_drake.scenario import Scenario
from ms_drake.station import drivers, robots
from ms_drake.station import hardware as hw
from ms_drake.station.environments import environment_sdf
from ms_drake.station.labels import make_depth_label_image
from ms_drake.station.sensor_model import DepthSensorModel, depth_sensor_params

OBJECT_PREFIX = "obj"


@dataclass(frozen=True)
class StationObject:
    """One object model instance of a station."""

    index: int
    model_instance: object  # ModelInstanceIndex
    model_name: str
    full_name: str  # registry name '<set>/<name>'
    body_index: object  # BodyIndex of its (single) body


def object_model_name(k: int, full_name: str) -> str:
    set_name, name = full_name.split("/", 1)
    return f"{OBJECT_PREFIX}{k:02d}__{set_name}__{name}"


def resolve_object_names(scenario: Scenario) -> list[str]:
    """Full object names of the scenario: explicit `objects.names`, or `objects.count`
    sampled from the set with `objects.seed` (default: random_seed)."""
    ob = scenario.objects
    if ob.names:
        return list(ob.names)
    if ob.count == 0:
        return []
    seed = ob.seed if ob.seed is not None else scenario.random_seed
    rng = np.random.default_rng([seed, 7919])
    return [o.full_name for o in get_object_set(ob.set).sample(ob.count, rng, ob.split)]


def station_objects(plant: MultibodyPlant) -> list[StationObject]:
    """The objects of a station's plant, in order."""
    out = []
    for i in range(plant.num_model_instances()):
        mi = ModelInstanceIndex(i)
        name = plant.GetModelInstanceName(mi)
        if not name.startswith(OBJECT_PREFIX) or "__" not in name:
            continue
        head, set_name, obj = name.split("__", 2)
        bodies = plant.GetBodyIndices(mi)
        out.append(StationObject(int(head[len(OBJECT_PREFIX):]), mi, name, f"{set_name}/{obj}", bodies[0]))
    return sorted(out, key=lambda o: o.index)


def default_object_poses(scenario: Scenario, n: int) -> list[RigidTransform]:
    """A non-overlapping grid of poses above the environment (used before a heap is loaded)."""
    lo = -0.5 * np.asarray(scenario.environment.resolved_size()[:2]) + 0.06
    pos = np.asarray(scenario.environment.position, float)
    cols = 4
    out = []
    for k in range(n):
        r, c = divmod(k, cols)
        layer, r = divmod(r, 3)
        xy = lo + np.array([c * 0.12, r * 0.12])
        out.append(RigidTransform(RollPitchYaw(0, 0, 0), pos + [xy[0], xy[1], 0.25 + 0.25 * layer]))
    return out


def add_environment(plant: MultibodyPlant, scenario: Scenario, parser=None, dropoffs: bool = True):
    """The scenario's environment welded to the world (a bin's drop-off trays only with `dropoffs`)."""
    env = scenario.environment
    parser = parser or make_parser(plant)
    sdf = environment_sdf(env.type, env.resolved_size(), env.wall_thickness, env.friction, dropoffs=dropoffs)
    (mi,) = parser.AddModelsFromString(sdf, "sdf")
    body = plant.GetBodyByName(env.type, mi)
    plant.WeldFrames(plant.world_frame(), body.body_frame(), RigidTransform(list(env.position)))
    return mi


def object_contact(compliance: str) -> dict:
    """add_objects' contact options for ObjectsConfig.compliance: rigid (object_sdf's default)
    or compliant hydroelastic with the heap generator's modulus and no contact spheres."""
    if compliance == "compliant":
        return dict(compliance="compliant", contact_spheres=False, modulus=OBJECT_MODULUS)
    return {}


def add_objects(plant: MultibodyPlant, names: list[str], friction: float = 0.5, parser=None,
                rgba_overrides: dict[int, tuple] | None = None, origin=(0.0, 0.0, 0.0), **contact) -> list:
    """Add the objects `names` (full names) as free bodies; returns their model instances.
    A fixture (a spec with ``meta["fixed_pose"]`` = (x, y, yaw), ms_drake.objects.registry) is
    welded to the world instead, standing on the support surface whose centre is `origin`, at
    (x, y) from it turned by yaw. `contact`: object contact options (see ms_drake.objects.sdf.object_sdf)."""
    parser = parser or make_parser(plant)
    out = []
    for k, full in enumerate(names):
        spec = get_object(full)
        rgba = (rgba_overrides or {}).get(k)
        (mi,) = parser.AddModelsFromString(
            spec.sdf(object_model_name(k, full), rgba=rgba, friction=friction, **contact), "sdf")
        if "fixed_pose" in spec.meta:
            plant.WeldFrames(plant.world_frame(), plant.get_body(plant.GetBodyIndices(mi)[0]).body_frame(),
                             fixture_pose(spec, origin))
        out.append(mi)
    return out


def fixture_pose(spec, origin=(0.0, 0.0, 0.0)) -> RigidTransform:
    """World pose of a fixture's frame (its centre) standing on the surface centred at `origin`."""
    x, y, yaw = spec.meta["fixed_pose"]
    return RigidTransform(RollPitchYaw(0.0, 0.0, yaw), np.asarray(origin, float) + [x, y, spec.extents[2] / 2])


def add_cameras(builder, cameras: list, plant, scene_graph) -> None:
    """ApplyCameraConfig for each camera config, without LCM: with no bus Drake would create
    a default (UDP multicast) LCM and publish, i.e. render, every camera at `fps` during every
    simulation. Images are read from the sensors' output ports instead."""
    buses = ApplyLcmBusConfig({cam.lcm_bus: None for cam in cameras}, builder)
    for cam in cameras:
        ApplyCameraConfig(config=cam, builder=builder, lcm_buses=buses, plant=plant, scene_graph=scene_graph)


def _label_image_port(builder, sensor, scene_graph, cam, label_images: str):
    """The sensor's rendered label port, or (label_images="depth") a DepthLabelImage fed by the
    depth image, with the rendered port as its lazily evaluated fallback."""
    if label_images != "depth" or not cam.depth:
        return sensor.label_image_output_port()

    try:
        labels = builder.AddNamedSystem(f"depth_label_{cam.name}", make_depth_label_image(sensor, scene_graph))
    except ValueError as e:
        raise ScenarioError(f"cameras.{cam.name}: {e}") from None
    builder.Connect(sensor.depth_image_32F_output_port(), labels.GetInputPort("depth_image"))
    builder.Connect(scene_graph.get_query_output_port(), labels.GetInputPort("query_object"))
    builder.Connect(sensor.label_image_output_port(), labels.GetInputPort("rendered_label_image"))
    return labels.GetOutputPort("label_image")


LABEL_IMAGES = ("render", "depth")


def _depth_image_port(builder, sensor, scenario: Scenario, cam_name: str):
    """The camera's depth image through its depth sensor model (scenario.depth_sensors; the
    RgbdSensor's own port when the model is `none`). Label images keep the perfect depth."""
    params = depth_sensor_params(scenario.depth_sensors.get(cam_name, "none"))
    if params.is_identity():
        return sensor.depth_image_32F_output_port()
    info = sensor.default_depth_render_camera().core().intrinsics()
    model = builder.AddNamedSystem(f"depth_sensor_{cam_name}", DepthSensorModel.from_camera_info(
        params, info, scenario.random_seed, cam_name))
    builder.Connect(sensor.depth_image_32F_output_port(), model.GetInputPort("depth_image"))
    if scenario.cameras[cam_name].rgb:
        builder.Connect(sensor.color_image_output_port(), model.GetInputPort("rgb_image"))
    return model.GetOutputPort("depth_image")


def MakeStation(scenario: Scenario, meshcat=None, hardware: bool | None = None, lcm=None,
                target_index: int = -1, name: str = "station", label_images: str = "depth",
                extra_objects=()):
    """Build the station Diagram for `scenario`.

    meshcat: a pydrake Meshcat to visualize into (None: no visualization).
    hardware: True swaps the plant for LCM drivers with the same ports (ms_drake.station.hardware;
      `lcm`: the bus, default DrakeLcm(scenario.lcm_url)); None (default): the scenario's `hardware`.
    target_index: index of the object drawn in the target colour (red), -1 for none.
    label_images: how ``<cam>.label_image`` is made (sim only). "depth" (default): computed
      from the depth image and the geometry poses (ms_drake.station.labels.DepthLabelImage, a
      numba kernel: ~1.8 ms per 640x480 image instead of a ~16 ms second render; 99.99 % of the
      pixels equal to the render's; it renders the label image itself whenever it cannot be
      exact, e.g. a mesh geometry in view). "render": a second VTK render (RgbdSensor's label
      port). Cameras without a depth image always render. The kernel compiles on its first use
      in a fresh install (~7 s, cached on disk afterwards).
    extra_objects: (full name '<set>/<name>', sdf(model_name) -> SDF text) pairs of objects that
      are not in the registry (e.g. a shelf scene's drawn boxes and cylinders); they follow the
      scenario's objects as free bodies named like them (`station_objects` lists them too).
    """
    if label_images not in LABEL_IMAGES:
        raise ScenarioError(f"MakeStation(label_images={label_images!r}): choose one of {', '.join(LABEL_IMAGES)}")
    if scenario.hardware if hardware is None else hardware:
        return hw.MakeHardwareStation(scenario, meshcat=meshcat, lcm=lcm)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    scene_graph.set_config(scenario.scene_graph_config)
    parser = make_parser(plant)
    add_environment(plant, scenario, parser)
    names = resolve_object_names(scenario)

    overrides = {target_index: TARGET_RGBA} if 0 <= target_index < len(names) else None
    instances = add_objects(plant, names, scenario.objects.friction, parser, overrides,
                            origin=scenario.environment.position, **object_contact(scenario.objects.compliance))
    for k, (full, sdf) in enumerate(extra_objects, start=len(names)):
        instances += parser.AddModelsFromString(sdf(object_model_name(k, full)), "sdf")
    robot_handle = None
    if scenario.robot.name:
        robot_handle = robots.add_robot_from_scenario(builder, plant, scene_graph, scenario, parser)
    plant.Finalize()
    if robot_handle is not None:
        drivers.apply_robot_drivers(builder, plant, scene_graph, robot_handle)
    for mi, X in zip(instances, default_object_poses(scenario, len(instances))):
        body = plant.GetBodyByName("body", mi)
        plant.SetDefaultFloatingBaseBodyPose(body, X)

    add_cameras(builder, list(scenario.cameras.values()), plant, scene_graph)
    for cam_name, cam in scenario.cameras.items():
        sensor = builder.GetSubsystemByName(f"rgbd_sensor_{cam.name}")
        if cam.rgb:
            builder.ExportOutput(sensor.color_image_output_port(), f"{cam_name}.rgb_image")
        if cam.depth:
            builder.ExportOutput(_depth_image_port(builder, sensor, scenario, cam_name), f"{cam_name}.depth_image")
        if cam.label:
            builder.ExportOutput(_label_image_port(builder, sensor, scene_graph, cam, label_images),
                                 f"{cam_name}.label_image")

    builder.ExportOutput(plant.get_body_poses_output_port(), "body_poses")
    builder.ExportOutput(plant.get_body_spatial_velocities_output_port(), "body_spatial_velocities")
    if not builder.IsConnectedOrExported(plant.get_applied_spatial_force_input_port()):
        # External forces on bodies (simulation only), e.g. execution.ObjectCarrier taking a lifted
        # object to a drop-off tray in the primitive mode; stations with suction cups use the
        # plant's input for the cups' forces and have no such port.
        builder.ExportInput(plant.get_applied_spatial_force_input_port(), "applied_spatial_force")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")
    builder.ExportOutput(plant.get_contact_results_output_port(), "contact_results")
    builder.ExportOutput(plant.get_state_output_port(), "state")
    if meshcat is not None:
        ApplyVisualizationConfig(scenario.visualization, builder, meshcat=meshcat)
        frame_meshcat_view(meshcat, scenario)
    diagram = builder.Build()
    diagram.set_name(name)
    return diagram


# Meshcat's viewpoint on each environment, relative to its origin: (camera, look-at point) [m].
MESHCAT_VIEWS = {
    "bin": ([-0.55, -0.75, 0.75], [0.0, 0.0, 0.0]),  # from the robot's side, above: the bin and its trays
    "shelf": ([0.55, -1.6, 0.9], [0.0, 0.0, 0.3]),  # in front of the open shelf, a little to the side
    "table": ([0.9, -1.2, 0.9], [0.0, 0.0, 0.05]),
}


def frame_meshcat_view(meshcat, scenario: Scenario) -> None:
    """Point Meshcat's camera at the scenario's environment (a recording then opens framed on the
    bin, shelf or table, not at Meshcat's default view from afar)."""
    env = scenario.environment
    if env.type not in MESHCAT_VIEWS:
        return
    origin = np.asarray(env.position, float)
    eye, at = MESHCAT_VIEWS[env.type]
    meshcat.SetCameraPose(origin + np.asarray(eye), origin + np.asarray(at))


def get_plant(station) -> MultibodyPlant:
    return station.GetSubsystemByName("plant")


def get_scene_graph(station):
    return station.GetSubsystemByName("scene_graph")
