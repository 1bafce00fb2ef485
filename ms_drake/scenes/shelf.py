"""Shelf scenes with a fully hidden target (Ch. 9.4.1, lines 1629-1634 of the reference).

`generate_shelf_scene(geometry, seed, num_objects, target_size)`:
1. N occluders (N uniform in [2, 12] unless given), each a box (axis-aligned with the shelf) or an
   upright cylinder with width, depth and height uniform in [6, 20] cm (a box's three stable
   poses are its three faces down: drawing all three dimensions covers them), placed one by one at
   a uniform position on the floor; positions whose shapely footprint comes within `gap` of the
   walls or an earlier object are redrawn (`position_tries`), then the object's shape is redrawn
   (`shape_tries`);
2. the placements where the target would be fully hidden and in view
   (ms_drake.shelf_geometry.hidden_placements: 2D visibility polygon, Minkowski sums, 3D ray
   casts); the target takes one of them uniformly, checked once more without sampling
   (`exactly_hidden`, with a 2 mm margin);
3. the ground truth: the 2D distribution of hidden placements on the floor and the 1D distribution
   P(x) along the image x axis (ShelfOccupancy).
A scene where no placement hides the target is redrawn, at most `scene_tries` times; then
SceneError says what to change. Every draw comes from `seed`: the same seed gives the same scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from ms_drake.errors import SceneError
from ms_drake.shelf_geometry import Prisms, ShelfGeometry, circle_polygons, exactly_hidden, hidden_placements
from ms_drake.types import ShelfObject, ShelfOccupancy, ShelfScene

#: The reference's three target boxes (w, d, h) [m]: 6 x 6 x 6 cm by default.
TARGET_SIZES = {"cube": (0.06, 0.06, 0.06), "flat": (0.06, 0.06, 0.03), "tall": (0.06, 0.06, 0.12)}
DEFAULT_TARGET = TARGET_SIZES["cube"]
MIN_OBJECTS, MAX_OBJECTS = 2, 12
TARGET_ID = "target"


@dataclass(frozen=True)
class ShelfSceneParams:
    """Scene generation parameters (sizes in metres)."""

    min_size: float = 0.06
    max_size: float = 0.20
    cylinder_fraction: float = 0.5
    gap: float = 0.005  # least clearance between objects, the target and the walls
    position_tries: int = 40
    shape_tries: int = 10
    scene_tries: int = 30
    target_tries: int = 10
    grid_step: float = 0.005  # spacing of the candidate target centres
    hidden_margin: float = 0.002  # the target's exact check: hidden even when grown by this


@dataclass(frozen=True, eq=False)
class ShelfSceneSample:
    """A generated scene and its ground-truth target distributions; `tries`: scenes drawn."""

    scene: ShelfScene
    occupancy: ShelfOccupancy
    tries: int = 1


def object_id(k: int) -> str:
    return f"occ{k:02d}"


def _draw_shape(rng, k: int, p: ShelfSceneParams) -> ShelfObject:
    w, d, h = rng.uniform(p.min_size, p.max_size, 3)
    if rng.random() < p.cylinder_fraction:
        return ShelfObject(object_id(k), "cylinder", 0.0, 0.0, float(w), float(w), float(h))
    return ShelfObject(object_id(k), "box", 0.0, 0.0, float(w), float(d), float(h))


def _footprints(o: ShelfObject, xy: np.ndarray) -> np.ndarray:
    """Shapely footprints (T,) of object o centred at each of xy (T, 2)."""
    if o.kind == "box":
        return shapely.box(xy[:, 0] - o.width / 2, xy[:, 1] - o.depth / 2, xy[:, 0] + o.width / 2,
                           xy[:, 1] + o.depth / 2)
    return circle_polygons(xy, np.full(len(xy), o.width / 2), circumscribed=True)


def place_occluders(geometry: ShelfGeometry, n: int, rng, params: ShelfSceneParams) -> list[ShelfObject] | None:
    """n objects at uniform collision-free floor positions (module docstring, step 1); None if one
    could not be placed within the bounded tries. Cylinders are tested as circumscribed polygons."""
    hx, hy = geometry.half
    placed, feet = [], np.empty(0, object)
    for k in range(n):
        for _ in range(params.shape_tries):
            o = _draw_shape(rng, k, params)
            ax = hx - o.width / 2 - params.gap
            ay = hy - o.depth / 2 - params.gap
            if ax < 0 or ay < 0:
                continue
            xy = rng.uniform([-ax, -ay], [ax, ay], (params.position_tries, 2))
            cand = _footprints(o, xy)
            free = np.ones(len(xy), bool) if len(feet) == 0 else \
                ~shapely.dwithin(cand[:, None], feet[None, :], params.gap).any(axis=1)
            if free.any():
                i = int(np.argmax(free))  # the first free draw: the same as drawing one at a time
                placed.append(o.moved(*xy[i]))
                feet = np.append(feet, cand[i])
                break
        else:
            return None
    return placed


def check_request(geometry: ShelfGeometry, num_objects, target_size, params: ShelfSceneParams) -> tuple:
    """Validate the arguments of generate_shelf_scene; returns the target size as floats."""
    if num_objects is not None and (int(num_objects) != num_objects or not MIN_OBJECTS <= num_objects <= MAX_OBJECTS):
        raise SceneError(f"num_objects={num_objects}: shelf scenes have {MIN_OBJECTS} to {MAX_OBJECTS} occluders "
                         "(or None to draw the number from the seed)")
    try:
        w, d, h = (float(v) for v in target_size)
    except (TypeError, ValueError):
        raise SceneError(f"target_size={target_size!r}: give (width, depth, height) in metres, e.g. "
                         f"{DEFAULT_TARGET}") from None
    if min(w, d, h) <= 0:
        raise SceneError(f"target_size={target_size!r}: every dimension must be > 0")
    X, Y, Z = geometry.size
    if w + 2 * params.gap > X or d + 2 * params.gap > Y or h >= Z:
        raise SceneError(f"target_size={target_size!r} does not fit in the {X} x {Y} x {Z} m shelf with "
                         f"{params.gap} m clearance; use a smaller target (e.g. {DEFAULT_TARGET})")
    if not 0 < params.min_size <= params.max_size:
        raise SceneError(f"ShelfSceneParams: min_size={params.min_size}, max_size={params.max_size}: need "
                         "0 < min_size <= max_size")
    return w, d, h


def generate_shelf_scene(geometry: ShelfGeometry, seed: int, num_objects: int | None = None,
                         target_size=DEFAULT_TARGET, params: ShelfSceneParams | None = None) -> ShelfSceneSample:
    """A shelf scene with N occluders and a fully hidden target (module docstring)."""
    params = params or ShelfSceneParams()
    size = check_request(geometry, num_objects, target_size, params)
    rng = np.random.default_rng([int(seed), 0x5E1F])
    n = int(num_objects) if num_objects is not None else int(rng.integers(MIN_OBJECTS, MAX_OBJECTS + 1))
    for attempt in range(1, params.scene_tries + 1):
        occluders = place_occluders(geometry, n, rng, params)
        if occluders is None:
            continue
        prisms = Prisms.of(occluders)
        hidden = hidden_placements(geometry, prisms, size, params.grid_step, params.gap)
        centers = hidden.centers
        for k in rng.permutation(len(centers))[:params.target_tries]:
            if exactly_hidden(geometry, prisms, centers[k], size, params.hidden_margin):
                target = ShelfObject(TARGET_ID, "box", float(centers[k][0]), float(centers[k][1]), *size)
                return ShelfSceneSample(ShelfScene(tuple(occluders), target, int(seed)),
                                        hidden.occupancy(geometry), attempt)
    raise SceneError(f"no placement hides a {size[0]:g} x {size[1]:g} x {size[2]:g} m target behind {n} occluders "
                     f"in {params.scene_tries} scenes (seed {seed}); use a smaller target, more occluders, or raise "
                     "ShelfSceneParams.scene_tries")


def scene_to_dict(scene: ShelfScene) -> dict:
    def obj(o):
        return dict(id=o.id, kind=o.kind, x=o.x, y=o.y, width=o.width, depth=o.depth, height=o.height)

    return dict(seed=scene.seed, objects=[obj(o) for o in scene.objects],
                target=obj(scene.target) if scene.target is not None else None)


def scene_from_dict(d: dict) -> ShelfScene:
    objs = tuple(ShelfObject(**o) for o in d["objects"])
    return ShelfScene(objs, ShelfObject(**d["target"]) if d.get("target") else None, int(d.get("seed", -1)))
