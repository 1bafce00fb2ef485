"""Registry of named object sets, each split into train and test *by object*.

Sets:
- ``procedural``: boxes, cylinders and "packaged" objects (a shape glued on a flat cardboard
  backing, as in the reference's Dex-Net / Thingiverse "packaged" models), 2-20 cm, made by
  code from the object index (deterministic, no files). Density 400 kg/m^3 (a typical
  household item's average density), masses clipped to [0.02, 1.0] kg.
- mesh sets: any folder ``models/objects/<set>/`` with an ``index.json`` written by the
  converter (``python -m tools.convert_objects``). The index format is::

      {"set": "ycb", "source": "...", "license": "...", "density": 500.0,
       "objects": [{"name": "003_cracker_box", "split": "train", "mass": 0.41,
                    "com": [x, y, z], "inertia": [ixx, iyy, izz, ixy, ixz, iyz],
                    "extents": [dx, dy, dz], "visual": "003_cracker_box/visual.obj",
                    "collision": ["003_cracker_box/collision_00.obj", ...]}, ...]}

  paths relative to the set folder; inertia about the COM in the object frame.

- ``targets``: the flat box targets of Ch. 8.3.1, ``box_r<k>`` for aspect ratio k:1, k = 1..10,
  equal footprint area (3 x 3 cm ... 9.5 x 0.95 cm), 5 mm thick, 20 g (`TARGET_RATIOS`,
  `target_box_size`), and ``lid``, the 1:1 box at twice the size (6 x 6 x 0.5 cm; the reference's
  out-of-set "lid", and a target the 3 cm suction cup can seal on), and ``square45``, the 1:1 box
  at 1.5 times its size (4.5 x 4.5 x 0.5 cm: the 3 cm cup seals on it with 7.5 mm to spare a side,
  while the 3 cm box itself is too narrow for the cup; ms_drake.scenes.layouts), and ``square35``
  at 7 / 6 of its size (3.5 x 3.5 x 0.5 cm: 2.5 mm to spare a side). Not listed by
  available_sets() (no heap draws from it); heaps place one on the floor first
  (ms_drake.scenes.layouts).

- ``fixtures``: fixed parts of a scene, welded to the world where their spec's
  ``meta["fixed_pose"]`` (x, y, yaw on the environment's support surface, relative to its
  centre) puts them (ms_drake.station.add_objects): ``barrier``, a tall box (64 x 6 x 28 cm,
  `BARRIER_SIZE`) standing across the rearrangement table at x = -0.12 with its long side along
  y (`BARRIER_AT`; ms_drake.experiments.rearrange's `barrier` scenes). Not listed by
  available_sets().

An object's full name is ``<set>/<name>``.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from ms_drake.errors import ModelNotFoundError, ObjectSetError
from ms_drake.objects.sdf import Inertia, Shape, object_sdf
from ms_drake.paths import PACKAGE_NAME, models_dir

PROCEDURAL_COUNT = 400
PROCEDURAL_DENSITY = 400.0  # kg/m^3
CARDBOARD_DENSITY = 250.0
TEST_FRACTION = 0.2

# Object colours: muted, never saturated red (red is reserved for the target detector).
_PALETTE = [
    (0.85, 0.75, 0.45), (0.35, 0.55, 0.80), (0.45, 0.70, 0.45), (0.70, 0.55, 0.75),
    (0.90, 0.90, 0.85), (0.55, 0.45, 0.35), (0.30, 0.65, 0.65), (0.80, 0.65, 0.30),
    (0.50, 0.50, 0.55), (0.65, 0.80, 0.90), (0.75, 0.85, 0.55), (0.40, 0.40, 0.70),
]
TARGET_RGBA = (0.9, 0.08, 0.08, 1.0)


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a set: everything needed to add it to a plant or analyse its mesh."""

    set: str
    name: str
    split: str
    inertia: Inertia
    extents: tuple[float, float, float]
    visuals: tuple[Shape, ...]
    collisions: tuple[Shape, ...]
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    mesh_file: str = ""  # absolute path of the visual mesh for mesh sets
    meta: dict = field(default_factory=dict, compare=False, hash=False)

    @property
    def full_name(self) -> str:
        return f"{self.set}/{self.name}"

    @property
    def mass(self) -> float:
        return self.inertia.mass

    def sdf(self, model_name: str, rgba=None, friction: float = 0.5, **contact) -> str:
        """SDF text; `contact` goes to ms_drake.objects.sdf.object_sdf (compliance, modulus,
        contact_spheres, extra_points). Mesh objects carry their own support points (the
        converter's `contact_points`, on the hull), used as contact spheres unless given."""
        if "contact_points" in self.meta and "extra_points" not in contact:
            contact["extra_points"] = [tuple(p) for p in self.meta["contact_points"]]
        colors = [tuple(rgba) if rgba is not None else self.rgba] * len(self.visuals)
        if rgba is None and "backing_rgba" in self.meta:
            colors[0] = self.meta["backing_rgba"]
        return object_sdf(model_name, self.inertia, list(zip(self.visuals, colors)),
                          list(self.collisions), friction=friction, **contact)

    def trimesh(self):
        """The object's surface as a trimesh.Trimesh in the object frame (watertight for
        primitives; for mesh sets the converted visual mesh)."""
        if self.mesh_file:
            if not Path(self.mesh_file).is_file():
                raise ModelNotFoundError(f"object {self.full_name}: mesh file {self.mesh_file} is missing; "
                                         "rebuild the set with `python -m tools.convert_objects`")
            return trimesh.load(self.mesh_file, force="mesh", process=True)
        parts = []
        for s in self.collisions:
            if s.kind == "box":
                m = trimesh.creation.box(extents=s.size)
            elif s.kind == "cylinder":
                m = trimesh.creation.cylinder(radius=s.size[0], height=s.size[1], sections=32)
            elif s.kind == "sphere":
                m = trimesh.creation.icosphere(subdivisions=3, radius=s.size[0])
            else:
                raise ValueError(f"cannot mesh shape kind {s.kind}")

            T = np.eye(4)
            T[:3, :3] = Rotation.from_euler("xyz", s.pose[3:]).as_matrix()
            T[:3, 3] = s.pose[:3]
            m.apply_transform(T)
            parts.append(m)
        if len(parts) == 1:
            return parts[0]
        return trimesh.boolean.union(parts, engine="manifold")


def _box_inertia(m, x, y, z):
    return m * (y * y + z * z) / 12, m * (x * x + z * z) / 12, m * (x * x + y * y) / 12


def _cyl_inertia(m, r, h):
    ixx = m * (3 * r * r + h * h) / 12
    return ixx, ixx, m * r * r / 2


def _procedural(index: int) -> ObjectSpec:
    """Object `index` of the procedural set (deterministic in the index)."""
    rng = np.random.default_rng([20260101, index])
    kind = ("box", "cylinder", "packaged")[index % 3]
    split = "test" if (index % int(round(1 / TEST_FRACTION))) == 0 else "train"
    rgba = (*_PALETTE[index % len(_PALETTE)], 1.0)
    if kind == "box":
        dims = np.sort(rng.uniform(0.02, 0.20, 3))[::-1]
        dims[0] = max(dims[0], 0.04)
        x, y, z = (float(d) for d in dims)
        m = float(np.clip(PROCEDURAL_DENSITY * x * y * z, 0.02, 1.0))
        ixx, iyy, izz = _box_inertia(m, x, y, z)
        shape = Shape("box", (x, y, z))
        return ObjectSpec("procedural", f"box_{index:03d}", split, Inertia(m, (0, 0, 0), ixx, iyy, izz),
                          (x, y, z), (shape,), (shape,), rgba)
    if kind == "cylinder":
        r = float(rng.uniform(0.01, 0.05))
        h = float(rng.uniform(0.02, 0.20))
        m = float(np.clip(PROCEDURAL_DENSITY * np.pi * r * r * h, 0.02, 1.0))
        ixx, iyy, izz = _cyl_inertia(m, r, h)
        shape = Shape("cylinder", (r, h))
        return ObjectSpec("procedural", f"cylinder_{index:03d}", split, Inertia(m, (0, 0, 0), ixx, iyy, izz),
                          (2 * r, 2 * r, h), (shape,), (shape,), rgba)
    # packaged: cardboard backing (thin box) with a box or cylinder glued on top of it.
    bx, by = (float(v) for v in np.sort(rng.uniform(0.08, 0.20, 2))[::-1])
    bt = float(rng.uniform(0.003, 0.006))
    backing = Shape("box", (bx, by, bt), pose=(0, 0, bt / 2, 0, 0, 0))
    if rng.random() < 0.5:
        sx, sy = float(rng.uniform(0.03, bx * 0.8)), float(rng.uniform(0.03, by * 0.8))
        sz = float(rng.uniform(0.02, 0.06))
        item = Shape("box", (sx, sy, sz), pose=(0, 0, bt + sz / 2, 0, 0, 0))
        vi = sx * sy * sz
        ii = _box_inertia(1.0, sx, sy, sz)
    else:
        r = float(rng.uniform(0.015, min(bx, by) * 0.4))
        sz = float(rng.uniform(0.03, 0.10))
        item = Shape("cylinder", (r, sz), pose=(0, 0, bt + r, np.pi / 2, 0, 0))  # lying on the backing
        vi = np.pi * r * r * sz
        a, _, c = _cyl_inertia(1.0, r, sz)
        ii = (a, c, a)  # the roll turns the cylinder axis onto y
        sz = 2 * r
    mb = CARDBOARD_DENSITY * bx * by * bt
    mi = PROCEDURAL_DENSITY * vi
    m_total = mb + mi
    scale = float(np.clip(m_total, 0.02, 1.0)) / m_total
    mb, mi = mb * scale, mi * scale
    zb, zi = bt / 2, bt + sz / 2
    zc = (mb * zb + mi * zi) / (mb + mi)
    ib = _box_inertia(mb, bx, by, bt)
    ixx = ib[0] + mb * (zb - zc) ** 2 + mi * ii[0] + mi * (zi - zc) ** 2
    iyy = ib[1] + mb * (zb - zc) ** 2 + mi * ii[1] + mi * (zi - zc) ** 2
    izz = ib[2] + mi * ii[2]
    cardboard = (0.72, 0.58, 0.40, 1.0)
    spec = ObjectSpec(
        "procedural", f"packaged_{index:03d}", split, Inertia(mb + mi, (0, 0, zc), ixx, iyy, izz),
        (bx, by, bt + sz), (backing, item), (backing, item), rgba,
        meta={"backing_rgba": cardboard},
    )
    return spec


@dataclass(frozen=True)
class ObjectSet:
    name: str
    objects: tuple[ObjectSpec, ...]
    source: str = ""
    license: str = ""

    def names(self, split: str = "all") -> list[str]:
        return [o.name for o in self.split(split)]

    def split(self, split: str = "all") -> tuple[ObjectSpec, ...]:
        if split == "all":
            return self.objects
        if split not in ("train", "test"):
            raise ObjectSetError(f"unknown split {split!r} for object set {self.name!r}; use train, test or all")
        return tuple(o for o in self.objects if o.split == split)

    def get(self, name: str) -> ObjectSpec:
        for o in self.objects:
            if o.name == name:
                return o
        raise ObjectSetError(f"object set {self.name!r} has no object {name!r} "
                             f"({len(self.objects)} objects, e.g. {', '.join(self.names()[:3])})")

    def sample(self, count: int, rng: np.random.Generator, split: str = "all") -> list[ObjectSpec]:
        """`count` objects drawn uniformly with replacement from the split."""
        pool = self.split(split)
        if not pool:
            raise ObjectSetError(f"object set {self.name!r} has no {split} objects")
        idx = rng.integers(0, len(pool), size=count)
        return [pool[i] for i in idx]


def load_mesh_set(folder: Path) -> ObjectSet:
    """The mesh object set described by `folder/index.json` (format in the module docstring).

    Folders inside models/ get package://ms_drake_models URIs; any other folder (e.g. a copy
    under /tmp) gets file:// URIs. Raises ObjectSetError for a malformed index and
    ModelNotFoundError when a mesh file it lists is missing.
    """
    folder = Path(folder).resolve()
    index_file = folder / "index.json"
    rebuild = "rebuild it with `python -m tools.convert_objects --set <set>`"
    try:
        data = json.loads(index_file.read_text())
        entries = data["objects"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise ObjectSetError(f"{index_file}: cannot read the object-set index ({e!r}); {rebuild}") from None
    set_name = data.get("set", folder.name)
    try:
        rel_root = folder.relative_to(models_dir()).as_posix()
        uri = lambda p: f"package://{PACKAGE_NAME}/{rel_root}/{p}"  # noqa: E731
    except ValueError:
        uri = lambda p: (folder / p).as_uri()  # noqa: E731
    objs = []
    for k, o in enumerate(entries):
        try:
            i = o["inertia"]
            inertia = Inertia(float(o["mass"]), tuple(float(c) for c in o["com"]), *(float(v) for v in i[:6]))
            files = [o["visual"], *o["collision"]]
            spec = ObjectSpec(
                set_name, o["name"], o["split"], inertia, tuple(o["extents"]),
                (Shape("mesh", uri=uri(o["visual"])),),
                tuple(Shape("convex", uri=uri(c)) for c in o["collision"]),
                rgba=tuple(o.get("rgba", (*_PALETTE[k % len(_PALETTE)], 1.0))),
                mesh_file=str(folder / o["visual"]),
                meta={k2: v for k2, v in o.items() if k2 not in ("name", "split", "mass", "com", "inertia",
                                                              "extents", "visual", "collision", "rgba")},
            )
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise ObjectSetError(f"{index_file}: object #{k} ({o.get('name', '?') if isinstance(o, dict) else o!r}) "
                                 f"is malformed ({e!r}); {rebuild}") from None
        missing = [f for f in files if not (folder / f).is_file()]
        if missing:
            raise ModelNotFoundError(
                f"object {set_name}/{spec.name}: mesh file {folder / missing[0]} is missing "
                f"({len(missing)} of its {len(files)} files); restore it (git checkout) or {rebuild}")
        objs.append(spec)
    return ObjectSet(set_name, tuple(objs), data.get("source", ""), data.get("license", ""))


_load_mesh_set = load_mesh_set


#: Aspect ratios (length : width) of the ten equal-area box targets of Ch. 8.3.1.
TARGET_RATIOS = tuple(range(1, 11))
TARGET_AREA = 0.03 * 0.03  # m^2, every box target's footprint
TARGET_THICKNESS = 0.005  # m
TARGET_MASS = 0.02  # kg


def target_box_size(ratio: float) -> tuple[float, float, float]:
    """(length, width, thickness) [m] of the box target of aspect ratio `ratio`."""
    a = float(np.sqrt(TARGET_AREA))
    return a * float(np.sqrt(ratio)), a / float(np.sqrt(ratio)), TARGET_THICKNESS


def _target_box(ratio: int, scale: float = 1.0, name: str = "") -> ObjectSpec:
    x, y, z = target_box_size(ratio)
    x, y = scale * x, scale * y
    shape = Shape("box", (x, y, z))
    return ObjectSpec("targets", name or f"box_r{ratio}", "test", Inertia(TARGET_MASS, (0, 0, 0), *_box_inertia(TARGET_MASS, x, y, z)),
                      (x, y, z), (shape,), (shape,), TARGET_RGBA)


#: The barrier fixture's size (x, y, z) [m], mass [kg] and place (x, y [m], yaw [rad]) on the table.
BARRIER_SIZE = (0.64, 0.06, 0.28)
BARRIER_MASS = 20.0
BARRIER_AT = (-0.12, 0.0, float(np.pi / 2))


def _barrier() -> ObjectSpec:
    shape = Shape("box", BARRIER_SIZE)
    return ObjectSpec("fixtures", "barrier", "test", Inertia(BARRIER_MASS, (0, 0, 0), *_box_inertia(BARRIER_MASS, *BARRIER_SIZE)),
                      BARRIER_SIZE, (shape,), (shape,), (0.62, 0.50, 0.36, 1.0), meta={"fixed_pose": BARRIER_AT})


def available_sets() -> list[str]:
    """Names of all registered object sets."""
    root = models_dir() / "objects"
    mesh_sets = sorted(p.parent.name for p in root.glob("*/index.json")) if root.is_dir() else []
    return ["procedural", *mesh_sets]


@functools.cache
def get_object_set(name: str) -> ObjectSet:
    """The object set called `name` (see available_sets())."""
    if name == "procedural":
        return ObjectSet("procedural", tuple(_procedural(i) for i in range(PROCEDURAL_COUNT)),
                         source="generated by ms_drake.objects.registry", license="BSD-3-Clause")
    if name == "targets":
        return ObjectSet("targets", tuple(_target_box(r) for r in TARGET_RATIOS) + (_target_box(1, 2.0, "lid"),
                                                                                 _target_box(1, 1.5, "square45"),
                                                                                 _target_box(1, 3.5 / 3.0, "square35")),
                         source="generated by ms_drake.objects.registry", license="BSD-3-Clause")
    if name == "fixtures":
        return ObjectSet("fixtures", (_barrier(),), source="generated by ms_drake.objects.registry",
                         license="BSD-3-Clause")
    folder = models_dir() / "objects" / name
    if not (folder / "index.json").is_file():
        raise ObjectSetError(f"unknown object set {name!r}; available: {', '.join(available_sets())}. "
                             "Mesh sets are built with `python -m tools.convert_objects`.")
    return _load_mesh_set(folder)


def get_object(full_name: str) -> ObjectSpec:
    """An object by its full name ``<set>/<name>``."""
    if "/" not in full_name:
        raise ObjectSetError(f"object name {full_name!r} must be '<set>/<name>', e.g. 'procedural/box_001'")
    set_name, obj = full_name.split("/", 1)
    return get_object_set(set_name).get(obj)
