"""Scenario files: which environment, objects, cameras, robot and physics a station has.

A scenario file (``diagrams/scenarios.yaml``) holds one named entry per station; entries share
YAML anchors. `load_scenario(filename, scenario_name)` checks the entry against the dataclasses
below *before* handing it to Drake's `yaml_load_typed`, so that a bad file raises one
`ScenarioError` whose message names the file, the scenario, the key path, the bad value and
what is allowed. Unknown keys and wrong types are errors.
"""

# No `from __future__ import annotations`: Drake's yaml_load_typed reads the field types.

import copy
import dataclasses
import difflib
import importlib.util
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_load_data, yaml_load_typed
from pydrake.geometry import SceneGraphConfig
from pydrake.multibody.plant import MultibodyPlantConfig
from pydrake.systems.analysis import SimulatorConfig
from pydrake.systems.sensors import CameraConfig
from pydrake.visualization import VisualizationConfig

from ms_drake.errors import ObjectSetError, ScenarioError
from ms_drake.objects import available_sets, get_object
from ms_drake.robots import GRIPPERS, gripper_port_name, station_robot_spec

ENVIRONMENT_TYPES = ("bin", "shelf", "table")
ROBOTS = ("", "yumi", "panda", "fetch", "floating")
SPLITS = ("all", "train", "test")

#: The reference geometry of each environment (metres). bin: inner x, y, wall height;
#: shelf: inner width (x), depth (y), height (z) (0.6 m cube, Ch. 9); table: x, y, top thickness.
DEFAULT_SIZES = {"bin": [0.50, 0.40, 0.12], "shelf": [0.60, 0.60, 0.60], "table": [1.0, 0.8, 0.05]}


def default_scenarios_file() -> Path:
    """diagrams/scenarios.yaml of the checkout (or the installed copy)."""
    candidates = [Path(__file__).resolve().parent.parent / "diagrams" / "scenarios.yaml"]
    spec = importlib.util.find_spec("ms_drake_diagrams")  # installed from a wheel
    if spec is not None and spec.submodule_search_locations:
        candidates += [Path(p) / "scenarios.yaml" for p in spec.submodule_search_locations]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise ScenarioError("cannot find diagrams/scenarios.yaml; pass the scenario file explicitly")


@dataclass
class EnvironmentConfig:
    """The static environment. `size` is the inner size (see DEFAULT_SIZES); an empty list
    takes the default of `type`. `position` places the environment's origin (centre of the
    floor/support surface) in the world."""

    type: str = "bin"
    size: list[float] = field(default_factory=list)
    wall_thickness: float = 0.03
    position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    friction: float = 0.5

    def resolved_size(self) -> np.ndarray:
        return np.asarray(self.size if self.size else DEFAULT_SIZES[self.type], dtype=float)


OBJECT_COMPLIANCE = ("rigid", "compliant")


@dataclass
class ObjectsConfig:
    """Which objects the station holds. Either `names` (full names '<set>/<name>', e.g. from a
    saved heap) or `count` objects sampled from `set` / `split` with `seed` (None: the
    scenario's random_seed). `compliance`: the objects' contact -- "rigid" (rigid hydroelastic
    shapes plus small contact spheres: point contact against the rigid bin and each other) or
    "compliant" (compliant-hydroelastic objects, as in the heap generator's drop world, so a
    reloaded heap keeps the contact it settled with)."""

    set: str = "procedural"
    split: str = "all"
    count: int = 0
    seed: typing.Optional[int] = None
    names: list[str] = field(default_factory=list)
    friction: float = 0.5
    compliance: str = "rigid"


@dataclass
class ArmDriver:
    """Joint-stiffness position control of one arm (ms_drake.station.drivers). kp: one stiffness
    per joint [N m/rad or N/m], [] for the robot's default; damping from `damping_ratio` and the
    joint-space inertia; `status_timeout` [s] applies to hardware."""

    kp: list[float] = field(default_factory=list)
    damping_ratio: float = 1.0
    gravity_compensation: bool = True
    status_timeout: float = 0.1


@dataclass
class JawDriver:
    """Parallel jaw: Drake's WSG position controller (its command gains) with a force limit [N].
    kp_command [N/m]: the grip force is min(kp_command * (opening - commanded opening), force
    limit). With 2000 a jaw commanded closed grips a 5 mm part with about 9 N and anything wider
    with the grasp models' 10 N (15 mm and wider at a 30 N limit), close to a force-limited servo
    gripper; Drake's WSG default (200) squeezes a 5 mm cardboard edge with 1 N under any limit."""

    default_force_limit: float = 40.0
    kp_command: float = 2000.0
    kd_command: float = 5.0
    status_timeout: float = 0.25


@dataclass
class SuctionDriver:
    """Vacuum cup (and the bluction blade's stiffness): max pulling force [N], seal gap [m]."""

    max_force: float = 40.0
    max_gap: float = 0.008
    seal_tolerance: float = 0.004
    max_tilt_deg: float = 30.0
    blade_kp: float = 20.0
    status_timeout: float = 0.25


@dataclass
class RobotConfig:
    """The robot and its grippers. name '' means no robot.
    grippers: one per arm in arm order ([] for the defaults). drivers: keyed by port prefix
    (arm or gripper name, e.g. yumi_right, yumi_right_jaw); missing entries use the defaults."""

    name: str = ""
    grippers: list[str] = field(default_factory=list)
    base_position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    base_yaw: float = 0.0
    drivers: typing.Mapping[str, typing.Union[ArmDriver, JawDriver, SuctionDriver]] = field(default_factory=dict)


#: Depth sensor presets (ms_drake.station.sensor_model.PRESETS holds their parameters).
DEPTH_SENSOR_PRESETS = ("none", "phoxi", "l515", "primesense")
#: Override fields of DepthSensorConfig that are probabilities (in [0, 1]).
_PROBABILITIES = ("edge_dropout", "grazing_dropout", "dark_threshold", "dark_dropout", "pixel_dropout")


@dataclass
class DepthSensorConfig:
    """The depth sensor model of one camera (ms_drake.station.sensor_model): a `preset` (none,
    phoxi, l515, primesense) and optional overrides of its parameters (unset: the preset's value;
    units and meaning: sensor_model.DepthSensorParams). Ignored by the hardware station."""

    preset: str = "none"
    noise_a: typing.Optional[float] = None
    noise_b: typing.Optional[float] = None
    depth_unit: typing.Optional[float] = None
    disparity_step: typing.Optional[float] = None
    focal_baseline: typing.Optional[float] = None
    edge_jump: typing.Optional[float] = None
    edge_width: typing.Optional[int] = None
    edge_dropout: typing.Optional[float] = None
    grazing_deg: typing.Optional[float] = None
    grazing_dropout: typing.Optional[float] = None
    dark_threshold: typing.Optional[float] = None
    dark_dropout: typing.Optional[float] = None
    holes: typing.Optional[float] = None
    hole_radius: typing.Optional[float] = None
    pixel_dropout: typing.Optional[float] = None


@dataclass
class Scenario:
    """One station. Every random choice of the station flows from `random_seed`. `depth_sensors`:
    the depth sensor model of each camera by camera name (cameras not listed: perfect depth)."""

    random_seed: int = 0
    environment: EnvironmentConfig = field(default_factory=EnvironmentConfig)
    objects: ObjectsConfig = field(default_factory=ObjectsConfig)
    robot: RobotConfig = field(default_factory=RobotConfig)
    cameras: typing.Mapping[str, CameraConfig] = field(default_factory=dict)
    depth_sensors: typing.Mapping[str, DepthSensorConfig] = field(default_factory=dict)
    plant_config: MultibodyPlantConfig = field(default_factory=MultibodyPlantConfig)
    scene_graph_config: SceneGraphConfig = field(default_factory=SceneGraphConfig)
    simulator_config: SimulatorConfig = field(default_factory=SimulatorConfig)
    visualization: VisualizationConfig = field(default_factory=VisualizationConfig)
    hardware: bool = False
    lcm_url: str = "memq://ms_drake"


# ---------------------------------------------------------------------------------------------
# Validation of the raw YAML against the schema.


def _fields(cls) -> typing.Optional[dict]:
    """Field name -> type for our dataclasses and Drake's serializable structs."""
    if dataclasses.is_dataclass(cls):
        return typing.get_type_hints(cls)
    if hasattr(cls, "__fields__") and isinstance(getattr(cls, "__fields__"), tuple):
        return {f.name: f.type for f in cls.__fields__}
    return None


def _type_name(t) -> str:
    return getattr(t, "__name__", None) or str(t).replace("typing.", "")


class _Checker:
    def __init__(self, filename: str, scenario: str):
        self.prefix = f"{filename}: scenario '{scenario}'"

    def fail(self, path: str, msg: str):
        raise ScenarioError(f"{self.prefix}: key '{path}': {msg}")

    def check(self, node, t, path: str):
        origin = typing.get_origin(t)
        args = typing.get_args(t)
        if t is typing.Any:
            return
        if origin is typing.Union:
            non_none = [a for a in args if a is not type(None)]
            if node is None and len(non_none) < len(args):
                return
            if isinstance(node, dict) and "_tag" in node:
                tag = node["_tag"].lstrip("!")
                for a in non_none:
                    if getattr(a, "__name__", "").split("𝓣")[0] == tag.split("_")[0] or \
                            getattr(a, "__name__", "") == tag:
                        return self.check({k: v for k, v in node.items() if k != "_tag"}, a, path)
                allowed = ", ".join("!" + getattr(a, "__name__", str(a)) for a in non_none)
                self.fail(path, f"unknown tag {node['_tag']}; allowed: {allowed}")
            errors = []
            for a in non_none:
                try:
                    return self.check(node, a, path)
                except ScenarioError as e:
                    errors.append(e)
            raise errors[0]
        if origin in (list, typing.List, tuple) or t is np.ndarray:
            if not isinstance(node, list):
                self.fail(path, f"expected a list, got {node!r}")
            inner = args[0] if args else (float if t is np.ndarray else typing.Any)
            for i, v in enumerate(node):
                self.check(v, inner, f"{path}[{i}]")
            return
        if origin in (dict, typing.Mapping, typing.Dict) or (origin is not None and
                                                              getattr(origin, "__name__", "") == "Mapping"):
            if not isinstance(node, dict):
                self.fail(path, f"expected a mapping, got {node!r}")
            for k, v in node.items():
                self.check(v, args[1] if len(args) > 1 else typing.Any, f"{path}.{k}")
            return
        if t is bool:
            if not isinstance(node, bool):
                self.fail(path, f"expected true or false, got {node!r}")
            return
        if t is int:
            if isinstance(node, bool) or not isinstance(node, int):
                self.fail(path, f"expected an integer, got {node!r}")
            return
        if t is float:
            if isinstance(node, bool) or not isinstance(node, (int, float)):
                self.fail(path, f"expected a number, got {node!r}")
            return
        if t is str:
            if not isinstance(node, str):
                self.fail(path, f"expected a string, got {node!r}")
            return
        fields = _fields(t)
        if fields is None:
            return  # an opaque Drake type: yaml_load_typed checks it below
        if not isinstance(node, dict):
            self.fail(path, f"expected a mapping of {_type_name(t)} fields, got {node!r}")
        for k, v in node.items():
            if k == "_tag":
                continue
            sub = f"{path}.{k}" if path else k
            if k not in fields:
                close = difflib.get_close_matches(k, list(fields), n=1)
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                self.fail(sub, f"unknown key{hint}; allowed keys of {_type_name(t)}: {', '.join(fields)}")
            self.check(v, fields[k], sub)


def _check_values(s: Scenario, ck: _Checker):
    env = s.environment
    if env.type not in ENVIRONMENT_TYPES:
        ck.fail("environment.type", f"{env.type!r} is not an environment; allowed: {', '.join(ENVIRONMENT_TYPES)}")
    if env.size and (len(env.size) != 3 or min(env.size) <= 0):
        ck.fail("environment.size", f"{env.size!r}: give 3 positive sizes in metres [x, y, z] or [] for the default")
    if len(env.position) != 3:
        ck.fail("environment.position", f"{env.position!r}: give [x, y, z] in metres")
    if env.wall_thickness <= 0:
        ck.fail("environment.wall_thickness", f"{env.wall_thickness!r}: must be > 0 metres")
    ob = s.objects
    if ob.set not in available_sets():
        ck.fail("objects.set", f"unknown object set {ob.set!r}; available: {', '.join(available_sets())}")
    if ob.split not in SPLITS:
        ck.fail("objects.split", f"{ob.split!r}; allowed: {', '.join(SPLITS)}")
    if ob.count < 0 or ob.count > 60:
        ck.fail("objects.count", f"{ob.count!r}: must be between 0 and 60")
    for i, n in enumerate(ob.names):
        try:
            get_object(n)
        except ObjectSetError as e:
            ck.fail(f"objects.names[{i}]", str(e))
    if s.robot.name not in ROBOTS:
        ck.fail("robot.name", f"unknown robot {s.robot.name!r}; allowed: {', '.join(repr(r) for r in ROBOTS)}")
    if s.robot.name:
        try:
            resolve_robot_config(s.robot)
        except ScenarioError as e:
            ck.fail("robot", str(e))
    for name, cam in s.cameras.items():
        if cam.width <= 0 or cam.height <= 0:
            ck.fail(f"cameras.{name}", f"image size {cam.width}x{cam.height} must be positive")
    for name, ds in s.depth_sensors.items():
        _check_depth_sensor(s, name, ds, ck)
    if s.plant_config.time_step < 0:
        ck.fail("plant_config.time_step", f"{s.plant_config.time_step!r}: must be >= 0")
    contact_models = ("point", "hydroelastic", "hydroelastic_with_fallback")
    if s.plant_config.contact_model not in contact_models:
        ck.fail("plant_config.contact_model", f"{s.plant_config.contact_model!r}; allowed: {', '.join(contact_models)}")
    if s.objects.compliance not in OBJECT_COMPLIANCE:
        ck.fail("objects.compliance", f"{s.objects.compliance!r}; allowed: {', '.join(OBJECT_COMPLIANCE)}")


def _check_depth_sensor(s: Scenario, name: str, ds: DepthSensorConfig, ck: _Checker):
    key = f"depth_sensors.{name}"
    if name not in s.cameras:
        ck.fail(key, f"no camera named {name!r}; cameras of this scenario: {', '.join(s.cameras) or '(none)'}")
    if not s.cameras[name].depth:
        ck.fail(key, f"camera {name!r} renders no depth image (depth: false); set depth: true or remove {key}")
    if ds.preset not in DEPTH_SENSOR_PRESETS:
        ck.fail(f"{key}.preset", f"unknown preset {ds.preset!r}; allowed: {', '.join(DEPTH_SENSOR_PRESETS)}")
    for f in dataclasses.fields(DepthSensorConfig):
        v = getattr(ds, f.name)
        if f.name == "preset" or v is None:
            continue
        if f.name in _PROBABILITIES and not 0.0 <= v <= 1.0:
            ck.fail(f"{key}.{f.name}", f"{v!r}: must be between 0 and 1")
        if f.name == "grazing_deg" and not 0.0 <= v <= 90.0:
            ck.fail(f"{key}.{f.name}", f"{v!r}: must be between 0 and 90 degrees")
        if v < 0:
            ck.fail(f"{key}.{f.name}", f"{v!r}: must be >= 0")


def resolve_robot_config(robot_config):
    """Check a scenario's RobotConfig; returns [(arm, gripper name, gripper port)] and the
    driver of every port prefix ({prefix: driver dataclass}, defaults filled in).

    Errors (ScenarioError) name the key, the bad value and the valid names."""
    spec = station_robot_spec(robot_config.name)
    arms = list(spec.arms)
    names = list(robot_config.grippers)
    if len(names) > len(arms):
        raise ScenarioError(f"robot.grippers: {names} lists {len(names)} grippers but {robot_config.name!r} has "
                            f"{len(arms)} arm(s) ({', '.join(arms)}); give one gripper per arm, in that order")
    chosen = []
    for i, arm in enumerate(arms):
        g = names[i] if i < len(names) else spec.arms[arm].default_gripper
        if g not in GRIPPERS:
            raise ScenarioError(f"robot.grippers[{i}]: unknown gripper {g!r}; valid grippers: "
                                f"{', '.join(sorted(GRIPPERS))}")
        chosen.append((arm, g, gripper_port_name(arm, GRIPPERS[g].kind)))
    wanted = {arm: ArmDriver for arm in arms}
    wanted.update({port: JawDriver if GRIPPERS[g].kind == "parallel_jaw" else SuctionDriver
                   for _, g, port in chosen})
    drivers = {}
    for key, d in robot_config.drivers.items():
        if key not in wanted:
            raise ScenarioError(f"robot.drivers: no arm or gripper named {key!r} on {robot_config.name!r}; "
                                f"valid driver names: {', '.join(wanted)}")
        if not isinstance(d, wanted[key]):
            raise ScenarioError(f"robot.drivers.{key}: a {type(d).__name__} cannot drive {key!r}; "
                                f"use !{wanted[key].__name__}")
        drivers[key] = d
    for key, cls in wanted.items():
        drivers.setdefault(key, cls())
    for arm in arms:
        kp = drivers[arm].kp
        n = len(spec.arms[arm].joints)
        if kp and (len(kp) != n or min(kp) <= 0):
            raise ScenarioError(f"robot.drivers.{arm}.kp: give {n} positive stiffnesses (one per joint of "
                                f"{', '.join(spec.arms[arm].joints)}) or [] for the defaults; got {list(kp)}")
        if drivers[arm].damping_ratio < 0:
            raise ScenarioError(f"robot.drivers.{arm}.damping_ratio: must be >= 0, got {drivers[arm].damping_ratio}")
    return chosen, drivers


#: Scenarios already loaded and checked, keyed by (file, its mtime and size, name): parsing the
#: file costs 20-65 ms of PyYAML per load, paid at every rollout of a benchmark.
_LOADED: dict = {}


def load_scenario(filename: typing.Union[str, Path, None] = None, scenario_name: str = "EmptyBin") -> Scenario:
    """Load `scenario_name` from `filename` (default: diagrams/scenarios.yaml). Each call returns a
    new Scenario (callers may edit it); a file is parsed again when its mtime or size changed."""
    filename = Path(filename) if filename is not None else default_scenarios_file()
    if not filename.is_file():
        raise ScenarioError(f"{filename}: no such scenario file")
    st = filename.stat()
    key = (str(filename.resolve()), st.st_mtime_ns, st.st_size, scenario_name)
    if key not in _LOADED:
        if len(_LOADED) > 64:
            _LOADED.clear()
        _LOADED[key] = _load_scenario(filename, scenario_name)
    return copy.deepcopy(_LOADED[key])


@dataclass(frozen=True)
class ScenarioRef:
    """A scenario named in a scenario file (file None: diagrams/scenarios.yaml), to hand to worker
    processes (a Scenario holds Drake config objects that do not pickle). `ScenarioRef.of("YuMiBin")`
    takes a name too."""

    name: str
    file: typing.Optional[str] = None

    @staticmethod
    def of(scenario: typing.Union[str, "ScenarioRef"]) -> "ScenarioRef":
        return scenario if isinstance(scenario, ScenarioRef) else ScenarioRef(str(scenario))

    def load(self) -> Scenario:
        return load_scenario(self.file, self.name)

    def __str__(self) -> str:
        return self.name if self.file is None else f"{self.name} of {self.file}"


def _load_scenario(filename: Path, scenario_name: str) -> Scenario:
    try:
        raw = yaml_load_data(filename.read_text())
    except Exception as e:  # noqa: BLE001 - YAML syntax errors of any kind
        raise ScenarioError(f"{filename}: not valid YAML: {e}") from None
    if not isinstance(raw, dict) or scenario_name not in raw:
        names = [k for k in (raw or {}) if not str(k).startswith(".")] if isinstance(raw, dict) else []
        raise ScenarioError(f"{filename}: no scenario named {scenario_name!r}; scenarios in the file: "
                            f"{', '.join(names) or '(none)'}")
    ck = _Checker(str(filename), scenario_name)
    ck.check(raw[scenario_name], Scenario, "")
    try:
        scenario = yaml_load_typed(schema=Scenario, filename=str(filename), child_name=scenario_name,
                                   defaults=Scenario())
    except Exception as e:  # noqa: BLE001 - Drake's own checks (variants, numbers) -> our error
        raise ScenarioError(f"{ck.prefix}: {e}") from None
    _check_values(scenario, ck)
    return scenario


def scenario_names(filename: typing.Union[str, Path, None] = None) -> list[str]:
    filename = Path(filename) if filename is not None else default_scenarios_file()
    raw = yaml_load_data(filename.read_text())
    return [k for k, v in raw.items() if isinstance(v, dict) and not k.startswith(".")]
