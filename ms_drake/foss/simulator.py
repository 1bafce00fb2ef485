"""FOSS, the first-order shelf simulator (Ch. 9.5.1; actions of Ch. 9.2).

Deterministic and quasi-static: objects are extruded footprints on the shelf floor (boxes
axis-aligned with the shelf, upright cylinders; ms_drake.shelf_geometry's rounded rectangles),
actions move one object, and nothing else ever moves. The bluction tool's two actions:

- push (object O, signed d_x): the blade (BLADE_THICKNESS along x, BLADE_WIDTH along y, from O's
  front face back) is inserted from the open front beside O's trailing side and pushes O along x.
  The blade's corridor from the front to its place must be free (no reaching behind other objects)
  and the blade must fit beside O; O and the blade then travel |d_x|, stopping where either would
  touch another object or O the wall (no multi-object pushes). Pushes shorter than MIN_PUSH are
  refused.
  `push_actions` proposes, for every object and both directions, the push up to its nearest
  neighbour (less CONTACT_GAP), the reference's candidates (Ch. 9.4.3); with leave_room=True also
  the same push stopped BLADE_ROOM + the blade's thickness short of the neighbour, so the blade
  still fits between the two (d_x is any real number in Ch. 9.2; the oracles use these).
- suction (O, d_x, d_y): the blade turned up, the tool's shaft (radius SHAFT_RADIUS) reaches
  straight in from the front to O's front face at the height of O's top less the cup's radius,
  passing over lower objects (anything in its corridor reaching that height blocks it); the cup
  seals, lifts O just above every object its sweep to the front crosses (by LIFT at least, O's top
  staying TOP_CLEARANCE under the shelf top), pulls it out along -y, translates it by d_x outside the
  shelf, and pushes it in -- lifted above the objects of that sweep -- until its front face is d_y
  behind the front plane, then lowers it onto the floor, where its footprint must be free, and
  withdraws the shaft (whose corridor must then be free up to the cup's height too). The tool stays
  within O's sweeps otherwise. `suction_actions` proposes the reference's placements: footprint
  centres x on the 50 segment centres across the width, front faces d_y on the 8 segment starts
  across the depth (d_y = 0: flush with the front). With `FossParams.max_lift` (SUCTION_LIFTS
  "floor") a lift higher than that is refused: the sweeps must then be clear of every object.
Every object in the scene is an obstacle, the target included (a push stops at the target; a
sweep through it is refused). The target can be pushed like any other object (`step`;
`push_actions(target=True)` proposes its pushes to a planner that knows where it is), not sucked.
A refused action changes nothing.

The target's visibility is the fraction of its image area the camera sees (ray casts,
ms_drake.shelf_geometry.visible_fraction); the search succeeds at VISIBILITY_THRESHOLD.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ms_drake.shelf_geometry import (
    Prisms,
    ShelfGeometry,
    contact_distance,
    overlap,
    visible_fraction,
)
from ms_drake.types import Action, ActionOutcome, ShelfAction, ShelfScene

BLADE_THICKNESS = 0.004  # m, along the push (x): the Fetch's bluction tool (ms_drake.robots.BluctionConfig)
BLADE_WIDTH = 0.065  # m, along y (the reference's blade: 6.5 cm wide, 7.5 cm high)
LIFT = 0.02  # m, least suction lift; more when the sweep passes over objects
LIFT_CLEARANCE = 0.01  # m, between a lifted object's bottom and the objects it passes over
TOP_CLEARANCE = 0.01  # m, between a lifted object's top and the shelf top
SHAFT_RADIUS = 0.015  # m: the 3 cm suction tube and cup
MIN_PUSH = 0.01  # m
CONTACT_GAP = 0.001  # m left between a pushed object and the one it stops at
BLADE_ROOM = 0.002  # m beyond the blade's thickness left by a push that stops short (leave_room)
SWEEP_CLEARANCE = 0.0005  # m, least gap between a suction sweep and the other objects (< CONTACT_GAP)
SUCTION_GRID = (50, 8)  # placements across the width (x) and the depth (y)
VISIBILITY_THRESHOLD = 0.8
OUTSIDE = 0.01  # m: a pulled-out object ends this far in front of the shelf
# How high a suction action may lift its object (FossParams.max_lift): "over" (the default) lifts it
# over every object its sweeps to and from the front cross; "floor" only LIFT off the floor, so
# those sweeps must be clear of every object in the overhead projection -- FOSS as the 2D overhead
# simulator of extruded footprints that the reference's oracles also plan in (Ch. 9.4.4). The
# reference gives no lift height (lines 1600-1606).
SUCTION_LIFTS = {"over": float("inf"), "floor": LIFT}


@dataclass(frozen=True)
class FossParams:
    blade_thickness: float = BLADE_THICKNESS
    blade_width: float = BLADE_WIDTH
    lift: float = LIFT
    lift_clearance: float = LIFT_CLEARANCE
    top_clearance: float = TOP_CLEARANCE
    shaft_radius: float = SHAFT_RADIUS
    min_push: float = MIN_PUSH
    contact_gap: float = CONTACT_GAP
    sweep_clearance: float = SWEEP_CLEARANCE
    suction_grid: tuple[int, int] = SUCTION_GRID
    visibility_threshold: float = VISIBILITY_THRESHOLD
    # Highest suction lift [m] (SUCTION_LIFTS; inf: over anything, the lifted object's top
    # staying under the shelf's)
    max_lift: float = float("inf")

    @classmethod
    def for_suction_lift(cls, name: str, **kw) -> "FossParams":
        """The parameters with suction lift rule `name` (SUCTION_LIFTS)."""
        if name not in SUCTION_LIFTS:
            raise ValueError(f"suction lift {name!r} unknown; choose one of {', '.join(SUCTION_LIFTS)}")
        return cls(max_lift=SUCTION_LIFTS[name], **kw)


def shelf_action(action) -> ShelfAction | None:
    """The ShelfAction of an Action (kind "shelf") or a ShelfAction itself; None otherwise."""
    if isinstance(action, ShelfAction):
        return action
    if isinstance(action, Action) and action.kind == "shelf":
        return action.shelf
    return None


class Foss:
    """The simulator for one shelf geometry (pure functions of the scene; no state)."""

    def __init__(self, geometry: ShelfGeometry, params: FossParams | None = None):
        self.geometry = geometry
        self.params = params or FossParams()
        hx, hy = geometry.half
        nx, ny = self.params.suction_grid
        if nx < 1 or ny < 1:
            raise ValueError(f"FossParams.suction_grid={self.params.suction_grid}: need >= 1 segment per axis")
        self.grid_x = -hx + (np.arange(nx) + 0.5) * (2 * hx / nx)
        self.grid_dy = np.arange(ny) * (2 * hy / ny)  # front-face depths

    # -- scene arrays -------------------------------------------------------------------------------

    @staticmethod
    def _bodies(scene: ShelfScene):
        """(Prisms of occluders then the target, number of movable objects)."""
        objs = list(scene.objects) + ([scene.target] if scene.target is not None else [])
        return Prisms.of(objs), len(scene.objects)

    @staticmethod
    def _is_target(scene: ShelfScene, object_id: str) -> bool:
        return scene.target is not None and object_id == scene.target.id

    @staticmethod
    def _index(scene: ShelfScene, object_id: str) -> int:
        for k, o in enumerate(scene.objects):
            if o.id == object_id:
                return k
        return -1

    # -- pushes -------------------------------------------------------------------------------------

    def _push_reach(self, P: Prisms, ks: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For pushes of objects ks (m,) in directions dirs (m,) (+1/-1): (blade fits and its corridor
        is free (m,), the largest travel before a contact (m,))."""
        p = self.params
        hx, hy = self.geometry.half
        n = len(P)
        ext = P.extent[ks]
        c = P.center[ks]
        bx = c[:, 0] - dirs * (ext[:, 0] + p.blade_thickness / 2)
        by = c[:, 1] - ext[:, 1] + p.blade_width / 2  # the blade along the object's front part
        blade_c = np.stack([bx, by], axis=1)
        blade_h = np.broadcast_to([p.blade_thickness / 2, p.blade_width / 2], blade_c.shape)
        y0, y1 = -hy - OUTSIDE - p.blade_width, by + p.blade_width / 2
        corr_c = np.stack([bx, (y0 + y1) / 2], axis=1)
        corr_h = np.stack([np.full(len(ks), p.blade_thickness / 2), (y1 - y0) / 2], axis=1)
        others = np.arange(n)[None, :] != ks[:, None]  # (m, n)
        blocked = overlap(corr_c[:, None], corr_h[:, None], 0.0, P.center[None], P.half[None], P.radius[None])
        fits = (np.abs(bx) + p.blade_thickness / 2 <= hx + 1e-9) & ~np.any(blocked & others, axis=1)
        d_obj = contact_distance(c[:, None], P.half[ks][:, None], P.radius[ks][:, None], P.center[None],
                                 P.half[None], P.radius[None], dirs[:, None])
        d_blade = contact_distance(blade_c[:, None], blade_h[:, None], 0.0, P.center[None], P.half[None],
                                   P.radius[None], dirs[:, None])
        d = np.where(others, np.minimum(d_obj, d_blade), np.inf).min(axis=1)
        wall = hx - dirs * c[:, 0] - ext[:, 0]
        return fits, np.minimum(d, wall)

    def push_actions(self, scene: ShelfScene, leave_room: bool = False, target: bool = False) -> list[ShelfAction]:
        """Every feasible push to the nearest neighbour (or wall), both directions, object order;
        leave_room: each followed by the same push stopped short by the blade's thickness +
        BLADE_ROOM (when that is still >= min_push); target: the target's pushes too (last; only a
        planner that knows where the target is can propose them: the oracles)."""
        P, n = self._bodies(scene)
        movable = n + 1 if target and scene.target is not None else n
        if movable == 0:
            return []
        p = self.params
        ks = np.repeat(np.arange(movable), 2)
        dirs = np.tile([-1.0, 1.0], movable)
        fits, reach = self._push_reach(P, ks, dirs)
        travel = reach - p.contact_gap
        ok = fits & (travel >= p.min_push)
        short = reach - p.blade_thickness - BLADE_ROOM
        ids = [o.id for o in scene.objects] + ([scene.target.id] if movable > n else [])
        out = []
        for k, s, t, t_short, good in zip(ks.tolist(), dirs.tolist(), travel.tolist(), short.tolist(), ok.tolist()):
            if good:
                out.append(ShelfAction("push", ids[k], s * t))
                if leave_room and t_short >= p.min_push:
                    out.append(ShelfAction("push", ids[k], s * t_short))
        return out

    # -- suction ------------------------------------------------------------------------------------

    def _lifts_ok(self, P: Prisms, k: int, xy: np.ndarray) -> np.ndarray:
        """Bool (m,): object k at footprint centres xy (m, 2) can be reached by the shaft and swept
        to / from the front lifted over what is in the way (module docstring)."""
        p = self.params
        hy = self.geometry.half[1]
        ext = P.extent[k]
        h = P.height[k]
        y_out = -hy - ext[1] - OUTSIDE
        others = np.arange(len(P)) != k
        oc, oh, orad, oz = P.center[others], P.half[others], P.radius[others], P.height[others]
        # The sweep between xy and the front: a rounded rectangle; lift over everything it crosses.
        c = np.stack([xy[:, 0], (xy[:, 1] + y_out) / 2], axis=1)
        half = np.stack([np.full(len(xy), P.half[k, 0]), P.half[k, 1] + (xy[:, 1] - y_out) / 2], axis=1)
        crossed = overlap(c[:, None], half[:, None], P.radius[k], oc[None], oh[None], orad[None],
                          tol=-p.sweep_clearance)
        lift = np.maximum(p.lift, np.where(crossed, oz[None] + p.lift_clearance, 0.0).max(axis=1, initial=0.0))
        ok = (h + lift <= self.geometry.size[2] - p.top_clearance + 1e-9) & (lift <= p.max_lift + 1e-9)
        # The shaft: from the front to the front face, at the cup's height.
        z_cup = max(h - p.shaft_radius, p.shaft_radius)
        face = xy[:, 1] - ext[1]
        sc = np.stack([xy[:, 0], (face + y_out) / 2], axis=1)
        sh = np.stack([np.full(len(xy), p.shaft_radius), np.maximum(face - y_out, 0.0) / 2], axis=1)
        in_way = overlap(sc[:, None], sh[:, None], 0.0, oc[None], oh[None], orad[None], tol=0.0)
        return ok & ~np.any(in_way & (oz[None] > z_cup - p.shaft_radius), axis=1)

    def _landing_ok(self, P: Prisms, k: int, xy: np.ndarray) -> np.ndarray:
        """Bool (m,): object k fits on the floor at footprint centres xy (m, 2), clear of the others."""
        hx, hy = self.geometry.half
        ext = P.extent[k]
        inside = (np.abs(xy[:, 0]) + ext[0] <= hx + 1e-9) & (np.abs(xy[:, 1]) + ext[1] <= hy + 1e-9)
        others = np.arange(len(P)) != k
        hit = overlap(xy[:, None], P.half[k], P.radius[k], P.center[None, others], P.half[None, others],
                      P.radius[None, others], tol=-self.params.sweep_clearance)
        return inside & ~hit.any(axis=1)

    def placement_center(self, o, dx: float, dy: float) -> tuple[float, float]:
        """Footprint centre of object o after a suction action (dx, dy): front face dy behind the front."""
        return o.x + dx, -self.geometry.half[1] + dy + (o.depth / 2)

    def suction_placements(self, scene: ShelfScene, object_id: str) -> np.ndarray:
        """(m, 2) footprint centres on the suction grid where object_id can be placed ((0, 2) if it
        cannot be picked); its current place excluded."""
        P, _ = self._bodies(scene)
        k = self._index(scene, object_id)
        if k < 0 or not self._lifts_ok(P, k, P.center[k][None])[0]:
            return np.zeros((0, 2))
        o = scene.objects[k]
        gx, gy = np.meshgrid(self.grid_x, -self.geometry.half[1] + self.grid_dy + o.depth / 2, indexing="ij")
        xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
        ok = self._landing_ok(P, k, xy) & (np.hypot(*(xy - P.center[k]).T) > 1e-9)
        ok[ok] = self._lifts_ok(P, k, xy[ok])
        return xy[ok]

    def suction_actions(self, scene: ShelfScene) -> list[ShelfAction]:
        """Every feasible suction action on the grid, object order then x then y."""
        hy = float(self.geometry.half[1])
        out = []
        for o in scene.objects:
            for x, y in self.suction_placements(scene, o.id).tolist():
                out.append(ShelfAction("suction", o.id, x - o.x, y - o.depth / 2 + hy))
        return out

    def actions(self, scene: ShelfScene, suction: bool = True) -> list[ShelfAction]:
        return self.push_actions(scene) + (self.suction_actions(scene) if suction else [])

    # -- stepping -----------------------------------------------------------------------------------

    def moved(self, scene: ShelfScene, action: ShelfAction) -> ShelfScene:
        """The scene after an action that push_actions / suction_actions proposed for this very
        scene (no feasibility check: planners use it to expand proposed actions quickly)."""
        if self._is_target(scene, action.object_id):
            t = scene.target
            return ShelfScene(scene.objects, t.moved(t.x + action.dx, t.y), scene.seed)
        k = self._index(scene, action.object_id)
        o = scene.objects[k]
        xy = (o.x + action.dx, o.y) if action.kind == "push" else self.placement_center(o, action.dx, action.dy)
        objects = scene.objects[:k] + (o.moved(*xy),) + scene.objects[k + 1:]
        return ShelfScene(objects, scene.target, scene.seed)

    def step(self, scene: ShelfScene, action) -> tuple[ShelfScene, ActionOutcome]:
        """Apply a ShelfAction (or Action of kind "shelf"); a refused action leaves the scene as it is."""
        a = shelf_action(action)
        wrapped = action if isinstance(action, Action) else Action("shelf", shelf=a)
        if a is None:
            return scene, ActionOutcome(wrapped, False, message=f"not a shelf action: {action!r}")
        P, n = self._bodies(scene)
        target = self._is_target(scene, a.object_id) and a.kind == "push"  # the target is pushed, never sucked
        k = n if target else self._index(scene, a.object_id)
        if k < 0:
            return scene, ActionOutcome(wrapped, False, message=f"no movable object {a.object_id!r}")
        o = scene.target if target else scene.objects[k]
        if a.kind == "push":
            if abs(a.dx) < self.params.min_push:
                return scene, ActionOutcome(wrapped, False, message=f"push of {abs(a.dx):.4f} m < min_push")
            s = float(np.sign(a.dx))
            fits, reach = self._push_reach(P, np.array([k]), np.array([s]))
            if not fits[0]:
                return scene, ActionOutcome(wrapped, False, message="blade does not fit / corridor blocked")
            travel = min(abs(a.dx), float(reach[0]) - self.params.contact_gap)
            if travel < self.params.min_push:
                return scene, ActionOutcome(wrapped, False, message="no room to push")
            new = o.moved(o.x + s * travel, o.y)
        elif a.kind == "suction":
            if not self._lifts_ok(P, k, P.center[k][None])[0]:
                return scene, ActionOutcome(wrapped, False, message="cannot reach, lift or pull out the object")
            xy = np.array([self.placement_center(o, a.dx, a.dy)])
            if not (self._landing_ok(P, k, xy)[0] and self._lifts_ok(P, k, xy)[0]):
                return scene, ActionOutcome(wrapped, False, message="placement blocked or off the shelf")
            new = o.moved(*xy[0])
        else:
            return scene, ActionOutcome(wrapped, False, message=f"unknown shelf action kind {a.kind!r}")
        if target:
            return ShelfScene(scene.objects, new, scene.seed), ActionOutcome(wrapped, True, message="ok")
        objects = scene.objects[:k] + (new,) + scene.objects[k + 1:]
        return ShelfScene(objects, scene.target, scene.seed), ActionOutcome(wrapped, True, message="ok")

    # -- observation --------------------------------------------------------------------------------

    def visible_fraction(self, scene: ShelfScene) -> float:
        if scene.target is None:
            raise ValueError("visible_fraction: the scene has no target")
        return visible_fraction(self.geometry, scene.target, Prisms.of(scene.objects))

    def revealed(self, scene: ShelfScene) -> bool:
        return self.visible_fraction(scene) >= self.params.visibility_threshold
