"""Shelf search policies (Ch. 9.4.3-9.4.4) and the ShelfPolicySelector LeafSystem.

Every policy acts on a ShelfScene through FOSS's actions (ms_drake.foss). The distribution policies
see the target occupancy and the occluders the camera sees (`segment`: FOSS's idealised
segmentation, i.e. the footprint and height of every occluder with a visible point, and its mask as
the visible points of its surface), never the target nor fully hidden occluders; their action
candidates are FOSS's feasible actions for those occluders alone (so a push may stop early at a
hidden object, and FOSS refuses a sweep through one). Actions refused since the last executed one
are not proposed again. An object's mask moves with it: its points are moved by the action and
projected again (the reference's "deprojecting into the camera frame, applying the action and
projecting back"), occlusions unchanged.

- random: a uniformly random feasible action, pushes and suction (seeded by (seed, step)).
- dar (Distribution Area Reduction, LAX-RAY): the push maximising the support reduction
  dr(O) = r_t(O) - r_{t+1}(O), r(O) = sum of P'_t over the image columns spanned by O's mask, before
  and after the action (Ch. 9.4.3).
- der3 (Distribution Entropy Reduction over 3 steps, LAX-RAY): the first push of the 3-push sequence
  whose predicted distribution has the least entropy. Prediction (LAX-RAY's 1D model): after a push,
  the columns that no object's mask spans any more cannot hide the target and lose their mass; the
  rest is renormalised. A sequence ending early (no push left) is scored where it ends.
- bluction_dar: dar over pushes and suction actions, suction reductions divided by psi (1.3);
  the first of the sorted list (every candidate is kinematically feasible in FOSS).
All three keep the history P'_t = min(P_t, P'_{t-1}) (P'_0 = P_0), renormalised.
- oracle_p / oracle_ps: full state. A* over action sequences of at most the remaining budget (cost
  n_p + psi * n_s) to a state where FOSS sees the target (visibility v). The target's view is
  scored as FOSS scores it: rays from the camera to visible_fraction's points on the target, in 3D
  (the reference's oracles clear the overhead visibility triangle, equivalent to 3D visibility for
  a camera level with the objects (Ch. 9.4.4); FetchShelf's camera looks 30 degrees down from
  0.75 m, so an object in the overhead triangle that is low or near the camera often hides
  nothing). A*'s estimate is the least number of occluders whose removal alone (every other one
  where it is) lets FOSS see the target: a plan must move each of one such set at least once, at
  cost >= 1 each, so it is admissible, and A* returns a cheapest plan (fewest actions, suction
  weighted by psi) among the actions it branches on.
  oracle_p branches on every feasible push (to the neighbour; in the later stages below also
  stopped short so the blade still fits between, Foss.push_actions(leave_room=True): d_x is any
  real number in Ch. 9.2, and a push to contact leaves the neighbour unpushable from that side);
  oracle_ps also on suction actions of the occluders, each taken to grid placements where it
  blocks none of the target's view rays (per side of the target, the ones farthest from the
  overhead triangle, in distinct grid rows): up to `oracle_placements` for the occluders that
  block the view and those in the way of their sweeps to the front, 2 for the others (which may
  have to make room), instead of all 400: the reference's exhaustive trees are out of reach in
  Python. So "cheapest" holds within that branching, not over every real d_x and grid placement.
  After `oracle_max_nodes` expansions (or a quarter of `oracle_max_seconds`) without a plan, A*
  gives way to a greedy best-first search
  (3 * oracle_max_nodes expansions; finds a plan, not the cheapest) whose estimate also counts,
  for each occluder of a removal set, the objects that must move before it can leave the view: in
  its cheapest way out (push left, push right, pick), the objects in the blade's corridor, in the
  push's path over the travel that clears the view, in the shaft's way, or 1 when no free grid
  placement clears the view; and theirs, two levels down (not admissible: a relaxed plan count).
  If neither finds a plan, both run again with the pushes that stop short added (more branches:
  found to lose plans to the node limits when used from the start). The oracle stops once the
  stages have used `oracle_max_seconds` of CPU time (a bound on the time per scene). oracle_p
  first asks push_locked whether some occluder cannot leave the view by pushes at all (pushes
  keep every object's y and nothing passes anything, so rows keep their order) and stops at once
  if so. When the stages find nothing, oracle_p then searches exhaustively, as the reference's
  oracles do (exhaustive_push_plan: breadth first over every push, duplicate states merged,
  states that need more objects moved than actions are left dropped; a shortest push plan),
  and oracle_ps searches wider (wide_plan: the greedy search with the stopped-short pushes, twice
  the placements for the occluders in the way and no expansion limit; a plan, not the cheapest),
  each for up to `oracle_exhaustive_seconds` of CPU (default: ORACLE_EXHAUSTIVE_SECONDS for
  oracle_p, ORACLE_WIDE_SECONDS for oracle_ps). Plans are cached by scene content, so executing
  one re-plans nothing.
  With `oracle_push_target` the oracles also push the target itself (the reference's target is
  one of the shelf's objects, and a push acts on "object O", Ch. 9.2; only a planner that knows
  where the target is can propose it). push_locked's proof then does not apply (it assumes the
  target stays), and the estimates, taken at the target's current place, are no longer bounds.
"""

from __future__ import annotations

import heapq
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import shapely
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ms_drake.foss import Foss, shelf_action
from ms_drake.foss.simulator import OUTSIDE
from ms_drake.policies.bin_selectors import PolicyError
from ms_drake.shelf_geometry import (
    Prisms,
    ShelfGeometry,
    occlusion_matrix,
    overlap,
    target_view_points,
    visible_surface,
)
from ms_drake.types import Action, ShelfAction, ShelfOccupancy, ShelfScene

SHELF_POLICIES = ("random", "dar", "der3", "bluction_dar", "oracle_p", "oracle_ps")
PSI = 1.3


#: Oracle-P's exhaustive push search after its staged one [CPU s]: the reference's Oracle-P is
#: exhaustive (capped at H); 60 s decide all but 6 of the 29 scenes of Table 9.1 the staged search
#: leaves, and keep the 400-scene run at 14 CPU-min (docs/results/ch9_shelf.md).
ORACLE_EXHAUSTIVE_SECONDS = 60.0
#: Oracle-P+S's wide search after its staged one [CPU s] (wide_plan): the one scene of Table 9.1
#: the staged search leaves (8 occluders, seed 22) needs ~70 s.
ORACLE_WIDE_SECONDS = 120.0


def oracle_last_stage_seconds(policy: str) -> float:
    """The default CPU budget of an oracle's last stage (Oracle-P: exhaustive_push_plan; Oracle-P+S:
    wide_plan); 0 for the other policies."""
    return {"oracle_p": ORACLE_EXHAUSTIVE_SECONDS, "oracle_ps": ORACLE_WIDE_SECONDS}.get(policy, 0.0)


@dataclass(frozen=True)
class ShelfPolicyParams:
    psi: float = PSI  # suction / push action cost ratio
    seed: int = 0  # random policy
    lookahead: int = 3  # der<n>
    horizon: int | None = None  # action budget H (None: 2n); the oracles plan within what is left
    oracle_max_nodes: int = 500  # A*'s expansions per stage; each greedy fallback gets three times as many
    oracle_max_seconds: float = 8.0  # CPU seconds of one plan (A* and fallback together)
    # when those stages find nothing, the oracle's last stage with this CPU budget [s] (Oracle-P:
    # exhaustive_push_plan, Oracle-P+S: wide_plan; None: oracle_last_stage_seconds(policy); 0: off)
    oracle_exhaustive_seconds: float | None = None
    oracle_placements: int = 4
    # the oracles also push the target itself (Foss.push_actions(target=True)): the reference's
    # target is one of the shelf's objects and a push acts on "object O" (Ch. 9.2); off by default
    oracle_push_target: bool = False
    # The distribution policies on a robot, whose actions place objects to within ~1-2 cm (0: off, as in FOSS):
    min_move: float = 0.0  # m: candidates FOSS moves their object less than this are not proposed
    nil_move: float = 0.0  # m: an executed action that moved its object less than this is not repeated (nil_effect)
    revisit: float = 0.0  # m: candidates FOSS predicts to lead back to an observed scene (within this) are not proposed


def check_shelf_policy(name: str) -> str:
    if name not in SHELF_POLICIES:
        raise PolicyError(f"unknown shelf policy {name!r}; choose one of {', '.join(SHELF_POLICIES)}")
    return name


# -- segmentation and image-column supports ----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Segmentation:
    """What the distribution policies observe: the occluders the camera sees (FOSS's idealised
    segmentation: the full footprint and height of every object with a visible pixel, as a scene
    without target) and, per object, the visible points of its surface (its segmentation mask)."""

    known: ShelfScene
    points: dict  # object id -> (V, 3) visible surface points (shelf frame)


def segment(geometry: ShelfGeometry, scene: ShelfScene, samples: int = 6) -> Segmentation:
    bodies = list(scene.objects) + ([scene.target] if scene.target is not None else [])
    pts, seen = visible_surface(geometry, Prisms.of(bodies), samples)
    points = {o.id: pts[k][seen[k]] for k, o in enumerate(scene.objects) if seen[k].any()}
    known = ShelfScene(tuple(o for o in scene.objects if o.id in points), None, scene.seed)
    return Segmentation(known, points)


def _columns(spans: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    lo = np.clip(np.floor(spans[..., 0] + 0.5).astype(int), 0, width)
    hi = np.clip(np.floor(spans[..., 1] + 0.5).astype(int) + 1, 0, width)
    return lo, np.maximum(hi, lo)


def _extent(geometry: ShelfGeometry, points: np.ndarray) -> np.ndarray:
    """(..., 2) image column extent (u_min, u_max) of point sets (..., V, 3)."""
    u, _, _ = geometry.project(points)
    return np.stack([u.min(axis=-1), u.max(axis=-1)], axis=-1)


def mask_extents(geometry: ShelfGeometry, seg: Segmentation) -> np.ndarray:
    """(n, 2) column extents of the known objects' masks, in seg.known's order."""
    return np.array([_extent(geometry, seg.points[o.id]) for o in seg.known.objects]).reshape(-1, 2)


def moved_extents(geometry: ShelfGeometry, seg: Segmentation, actions: list[ShelfAction]) -> tuple[np.ndarray, np.ndarray]:
    """(object index in seg.known (m,), column extent (m, 2) of its mask after each action): the
    mask's points moved with the object and projected again (Ch. 9.4.3)."""
    index = {o.id: k for k, o in enumerate(seg.known.objects)}
    ks = np.array([index[a.object_id] for a in actions], int)
    out = np.zeros((len(actions), 2))
    hy = geometry.half[1]
    for k in np.unique(ks):
        o = seg.known.objects[k]
        rows = np.nonzero(ks == k)[0]
        shift = np.zeros((len(rows), 1, 3))
        shift[:, 0, 0] = [actions[i].dx for i in rows]
        shift[:, 0, 1] = [(-hy + actions[i].dy + o.depth / 2 - o.y) if actions[i].kind == "suction" else 0.0
                          for i in rows]
        out[rows] = _extent(geometry, seg.points[o.id][None] + shift)
    return ks, out


def support_reduction(geometry: ShelfGeometry, seg: Segmentation, dist: np.ndarray,
                      actions: list[ShelfAction]) -> np.ndarray:
    """dr (m,) of each action: the distribution summed over the moved object's mask columns before
    minus after (Ch. 9.4.3)."""
    if not actions:
        return np.zeros(0)
    width = len(dist)
    C = np.concatenate([[0.0], np.cumsum(dist)])
    ks, after = moved_extents(geometry, seg, actions)
    lo0, hi0 = _columns(mask_extents(geometry, seg)[ks], width)
    lo1, hi1 = _columns(after, width)
    return (C[hi0] - C[lo0]) - (C[hi1] - C[lo1])


def _covered(spans: np.ndarray, width: int) -> np.ndarray:
    """(m, width) bool: columns covered by any of the spans (m, n, 2)."""
    m = spans.shape[0]
    lo, hi = _columns(spans, width)
    diff = np.zeros((m, width + 1))
    rows = np.repeat(np.arange(m), spans.shape[1])
    np.add.at(diff, (rows, lo.ravel()), 1.0)
    np.add.at(diff, (rows, hi.ravel()), -1.0)
    return np.cumsum(diff[:, :width], axis=1) > 0.5


def _entropy(p: np.ndarray) -> np.ndarray:
    """Entropy of each row's renormalised distribution (0 for an empty row)."""
    s = p.sum(axis=-1, keepdims=True)
    q = np.where(s > 0, p / np.where(s > 0, s, 1.0), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.where(q > 0, q * np.log(q), 0.0).sum(axis=-1)


def der_scores(foss: Foss, seg: Segmentation, dist: np.ndarray, depth: int, first: list[ShelfAction]) -> np.ndarray:
    """Least predicted entropy after `depth` pushes, for each first push in `first` (module docstring).
    Masks move with their objects (as in support_reduction); pushes are re-planned in each state."""
    geometry = foss.geometry
    width = len(dist)

    def children(s, spans, p, actions):
        ks, new = moved_extents(geometry, s, actions)
        all_spans = np.repeat(spans[None], len(actions), axis=0)
        all_spans[np.arange(len(actions)), ks] = new
        return all_spans, p[None] * _covered(all_spans, width)

    def moved(s, a):
        points = dict(s.points)
        points[a.object_id] = s.points[a.object_id] + [a.dx, 0.0, 0.0]
        return Segmentation(foss.moved(s.known, a), points)

    def value(s, spans, p, d):
        actions = foss.push_actions(s.known) if d > 0 else []
        if not actions:
            return float(_entropy(p))
        child_spans, child_p = children(s, spans, p, actions)
        if d == 1:
            return float(_entropy(child_p).min())
        return min(value(moved(s, a), child_spans[i], child_p[i], d - 1) for i, a in enumerate(actions))

    child_spans, child_p = children(seg, mask_extents(geometry, seg), dist, first)
    return np.array([value(moved(seg, a), child_spans[i], child_p[i], depth - 1) for i, a in enumerate(first)])


# -- the oracles --------------------------------------------------------------------------------------


def visibility_triangle(geometry: ShelfGeometry, target) -> shapely.Polygon:
    """Overhead: the triangle from the camera's floor point to the target's front face."""
    hx, hy = target.width / 2, target.depth / 2
    pts = [tuple(geometry.eye[:2]), (target.x - hx, target.y - hy), (target.x + hx, target.y - hy)]
    return shapely.Polygon(pts)


class _View:
    """The target's view as FOSS scores it (visible_fraction's ray-cast points and weights) and, for a
    state, the least number of occluders whose removal alone would let the camera see the target."""

    def __init__(self, foss: Foss, target):
        p, w = target_view_points(foss.geometry, target)
        inview = foss.geometry.in_view(p)
        self.eye = foss.geometry.eye
        self.points, self.weights = p[inview], w[inview]
        self.need = foss.params.visibility_threshold * w.sum() - 1e-12

    def blockers(self, scene: ShelfScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(indices of the occluders that block some ray (m,), every removal set as a bit mask over
        those m): the sets of them whose removal alone (every other occluder where it is) lets FOSS
        see the target. A plan ends in such a state only if it moves every object of one of them."""
        B = occlusion_matrix(self.eye, self.points, Prisms.of(scene.objects))  # (P, n)
        cols = np.nonzero(B.any(axis=0))[0]
        if len(cols) > 16:
            raise PolicyError(f"oracle: {len(cols)} occluders block the target; at most 16 supported")
        masks = (B[:, cols].astype(np.int64) << np.arange(len(cols))).sum(axis=1)  # (P,)
        subsets = np.arange(1 << len(cols), dtype=np.int64)
        seen = (masks[None, :] & ~subsets[:, None]) == 0
        ok = subsets[seen.astype(float) @ self.weights >= self.need]
        return cols, ok

class _Views:
    """_View and the overhead triangle per target position (the target moves only when an oracle
    pushes it, ShelfPolicyParams.oracle_push_target)."""

    def __init__(self, foss: Foss):
        self.foss = foss
        self._cache: dict = {}

    def __call__(self, scene: ShelfScene) -> tuple[_View, shapely.Polygon]:
        t = scene.target
        key = (round(t.x, 6), round(t.y, 6))
        if key not in self._cache:
            self._cache[key] = (_View(self.foss, t), visibility_triangle(self.foss.geometry, t))
        return self._cache[key]


def _movers(scene: ShelfScene, inside: np.ndarray) -> np.ndarray:
    """Bool (n,): the occluders in the triangle and those in the way of their sweeps to the front."""
    P = Prisms.of(scene.objects)
    out = inside.copy()
    front = -1e3
    for k in np.nonzero(inside)[0]:
        c = np.array([P.center[k, 0], (P.center[k, 1] + front) / 2])
        h = np.array([P.extent[k, 0], (P.center[k, 1] - front) / 2])
        out |= overlap(c, h, 0.0, P.center, P.half, P.radius)
    return out


def _oracle_suction(foss: Foss, scene: ShelfScene, tri, movers: np.ndarray, per_object: int,
                    view: _View) -> list[ShelfAction]:
    """Suction actions to grid placements where the object blocks none of the target's view rays,
    per side of the target the ones farthest from the visibility triangle in distinct grid rows: up
    to `per_object` for the movers, 2 for the others (which may need to make room)."""
    hy = foss.geometry.half[1]
    out = []
    tx = scene.target.x
    P, _ = foss._bodies(scene)
    for k, (o, mover) in enumerate(zip(scene.objects, movers)):
        # Foss.suction_placements, with the (costly) sweep check only for the candidates ranked first.
        if not foss._lifts_ok(P, k, P.center[k][None])[0]:
            continue
        gx, gy = np.meshgrid(foss.grid_x, -hy + foss.grid_dy + o.depth / 2, indexing="ij")
        xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
        xy = xy[foss._landing_ok(P, k, xy) & (np.hypot(*(xy - P.center[k]).T) > 1e-9)]
        m = len(xy)
        if m == 0:
            continue
        at = Prisms(xy, np.repeat(P.half[k][None], m, axis=0), np.full(m, P.radius[k]), np.full(m, P.height[k]))
        xy = xy[~occlusion_matrix(view.eye, view.points, at).any(axis=0)]
        if len(xy) == 0:
            continue
        dist = shapely.distance(tri, shapely.points(xy))
        per_side = max(1, (per_object if mover else 2) // 2)
        for side in (xy[:, 0] < tx, xy[:, 0] >= tx):
            ranked = xy[side][np.argsort(-dist[side], kind="stable")]
            rows = set()
            for start in range(0, len(ranked), 16):
                chunk = ranked[start:start + 16]
                for (x, y), ok in zip(chunk.tolist(), foss._lifts_ok(P, k, chunk)):
                    if not ok or round(y, 6) in rows:
                        continue
                    rows.add(round(y, 6))
                    out.append(ShelfAction("suction", o.id, float(x - o.x), float(y - o.depth / 2 + hy)))
                    if len(rows) >= per_side:
                        break
                if len(rows) >= per_side:
                    break
    return out


_SHIFTS = np.arange(1, 61) * 0.01  # m: the travels tried when asking how far an object must go
_NO_WAY = 3  # the estimate's count for an object with no way out yet


def _ways(foss: Foss, P: Prisms, n: int, k: int, clear, suction: bool) -> list[tuple[int, list]]:
    """The ways of taking object k (of bodies P, the first n movable) out of what `clear` asks
    (clear(centres (m, 2)) -> bool (m,): k placed there is out of the way): push left, push right,
    and with suction pick. Each as (bit mask of the objects that must move first: in the blade's
    corridor, in the push's path over the travel that satisfies `clear`, in the shaft's way and,
    when FossParams.max_lift is finite, in the object's sweep to the front that the lift cannot clear;
    the regions (centre, half-extents) those objects must then leave; 1 if a pick has no free grid
    placement that satisfies `clear`, so something else must make room, else 0). Ways that cannot
    work whatever moves first (the wall or the target in the way, too tall to lift) are left out."""
    p = foss.params
    hx, hy = foss.geometry.half
    c, ext = P.center[k], P.extent[k]
    others = np.arange(len(P)) != k
    bits = np.where(np.arange(len(P)) < n, 1 << np.arange(len(P)), 0)  # the target: no bit (never moves)
    out = []
    for s in (-1.0, 1.0):
        bx = c[0] - s * (ext[0] + p.blade_thickness / 2)
        if abs(bx) + p.blade_thickness / 2 > hx + 1e-9:
            continue
        cs = np.repeat(c[None], len(_SHIFTS), axis=0)
        cs[:, 0] += s * _SHIFTS
        ok = (np.abs(cs[:, 0]) + ext[0] <= hx + 1e-9) & clear(cs)
        if not ok.any():
            continue
        d = _SHIFTS[np.argmax(ok)]
        by = c[1] - ext[1] + p.blade_width / 2
        y0, y1 = -hy - OUTSIDE - p.blade_width, by + p.blade_width / 2
        regions = [(np.array([bx, (y0 + y1) / 2]), np.array([p.blade_thickness / 2, (y1 - y0) / 2])),
                   (np.array([c[0] + s * d / 2, c[1]]), np.array([ext[0] + d / 2, ext[1]]))]
        way = others & np.any([overlap(rc, rh, 0.0, P.center, P.half, P.radius) for rc, rh in regions], axis=0)
        if not way[n:].any():
            out.append((int(bits[way].sum()), regions, 0))
    z_cup = max(P.height[k] - p.shaft_radius, p.shaft_radius)
    if suction and P.height[k] + p.lift <= foss.geometry.size[2] - p.top_clearance + 1e-9:
        y_out = -hy - ext[1] - OUTSIDE
        face = c[1] - ext[1]
        region = (np.array([c[0], (face + y_out) / 2]), np.array([p.shaft_radius, max(face - y_out, 0.0) / 2]))
        way = others & (P.height > z_cup - p.shaft_radius) & overlap(*region, 0.0, P.center, P.half, P.radius, tol=0.0)
        regions = [region]
        if np.isfinite(p.max_lift):  # the lift cannot clear them: the objects in k's sweep to the front
            sweep = (np.array([c[0], (c[1] + y_out) / 2]), np.array([ext[0], ext[1] + (c[1] - y_out) / 2]))
            way |= others & (P.height + p.lift_clearance > p.max_lift) & overlap(*sweep, 0.0, P.center, P.half,
                                                                                  P.radius, tol=0.0)
            regions.append(sweep)
        if not way[n:].any():
            gx, gy = np.meshgrid(foss.grid_x, -hy + foss.grid_dy + ext[1], indexing="ij")
            xy = np.stack([gx.ravel(), gy.ravel()], axis=1)
            land = xy[foss._landing_ok(P, k, xy)]
            room = len(land) > 0 and bool(clear(land).any())
            out.append((int(bits[way].sum()), regions, 0 if room else 1))
    return out


def _view_clear(P: Prisms, k: int, view: _View):
    """clear() for _ways: object k placed at the centres blocks none of the target's view rays."""
    def clear(cs):
        m = len(cs)
        at = Prisms(cs, np.repeat(P.half[k][None], m, axis=0), np.full(m, P.radius[k]), np.full(m, P.height[k]))
        return ~occlusion_matrix(view.eye, view.points, at).any(axis=0)
    return clear


def _regions_clear(P: Prisms, k: int, regions: list):
    """clear() for _ways: object k placed at the centres overlaps none of the regions."""
    def clear(cs):
        hit = np.zeros(len(cs), bool)
        for rc, rh in regions:
            hit |= overlap(cs, P.half[k], P.radius[k], rc, rh, 0.0)
        return ~hit
    return clear


def _cost_out(foss: Foss, P: Prisms, n: int, k: int, clear, skip: int, suction: bool, depth: int) -> int:
    """Relaxed count of the other actions object k needs before it can leave (`clear`): over k's
    ways, the objects that must move first and are not in the bit mask `skip` (each 1, plus its own
    count, `depth` levels down); _NO_WAY when k has no way."""
    ways = _ways(foss, P, n, k, clear, suction)
    if not ways:
        return _NO_WAY
    best = _NO_WAY
    for mask, regions, extra in ways:
        total = extra
        for j in range(n):
            if mask >> j & 1 and not skip >> j & 1:
                total += 1
                if depth > 0:
                    total += _cost_out(foss, P, n, j, _regions_clear(P, j, regions), skip | (1 << k), suction,
                                       depth - 1)
            if total >= best:
                break
        best = min(best, total)
    return best


def push_locked(foss: Foss, scene: ShelfScene, step: float = 0.001) -> list[str]:
    """The occluders that no sequence of pushes can take out of the target's view. Pushes move one
    object along x and nothing passes another: two bodies that overlap when aligned in x (at their
    y) keep their x order, and the target never moves. So an object's centre stays between the
    wall (or the target) plus the least separations along the longest chain of such bodies to its
    left, and likewise on its right (contact gaps and the blade ignored: the interval is, if
    anything, too wide). If with every other occluder gone the camera sees less than v of the
    target at every x of that interval (`step` apart), no push plan exists."""
    if scene.target is None:
        raise PolicyError("push_locked needs the full state: a scene with its target")
    P, n = foss._bodies(scene)
    hx = foss.geometry.half[0]
    c = P.center
    dy = np.abs(c[:, None, 1] - c[None, :, 1])
    B = P.half[:, None, 1] + P.half[None, :, 1]
    R = P.radius[:, None] + P.radius[None, :]
    over = np.clip(dy - B, 0.0, None)
    reach = np.where(dy <= B, R, np.sqrt(np.clip(R * R - over * over, 0.0, None)))
    blocks = (dy < B - 1e-6) | (over < R - 1e-6)  # would overlap when aligned in x
    sep = P.half[:, None, 0] + P.half[None, :, 0] + reach  # least centre distance along x
    lo, hi = -hx + P.extent[:, 0], hx - P.extent[:, 0]
    lo[n] = hi[n] = c[n, 0]
    order = np.argsort(c[:, 0], kind="stable")
    for i, k in enumerate(order):
        if k != n:
            for j in order[:i]:
                if blocks[j, k]:
                    lo[k] = max(lo[k], lo[j] + sep[j, k])
    for i, k in enumerate(order[::-1]):
        if k != n:
            for j in order[::-1][:i]:
                if blocks[j, k]:
                    hi[k] = min(hi[k], hi[j] - sep[j, k])
    view = _View(foss, scene.target)
    out = []
    for k in range(n):
        xs = np.arange(lo[k], hi[k] + 1e-9, step) if hi[k] >= lo[k] else c[k:k + 1, 0]
        m = len(xs)
        at = Prisms(np.stack([xs, np.full(m, c[k, 1])], axis=1), np.repeat(P.half[k][None], m, axis=0),
                    np.full(m, P.radius[k]), np.full(m, P.height[k]))
        if not np.any(view.weights @ ~occlusion_matrix(view.eye, view.points, at) >= view.need):
            out.append(scene.objects[k].id)
    return out


def _key(scene: ShelfScene) -> tuple:
    objects = scene.objects + ((scene.target,) if scene.target is not None else ())
    return tuple((round(o.x, 6), round(o.y, 6)) for o in objects)


def oracle_plan(foss: Foss, scene: ShelfScene, suction: bool, budget: int, psi: float = PSI,
                max_nodes: int = 500, placements: int = 4, max_seconds: float = 8.0,
                exhaustive_seconds: float = 0.0, exhaustive_states: int = 400_000,
                push_target: bool = False) -> tuple[ShelfAction, ...] | None:
    """An action sequence (<= budget actions) after which FOSS sees the target, in stages until one
    finds it: A* (the cheapest within its branching; admissible estimate; max_nodes expansions and
    at most max_seconds / 4) then greedy best-first (relaxed estimate; 3 * max_nodes), over
    pushes to the neighbour, then the same two with the pushes that stop short added
    (Foss.push_actions(leave_room=True)); None if none finds one, once the stages have used
    max_seconds of CPU time, or at once when pushes alone cannot do it (push_locked) (module
    docstring). Then, with exhaustive_seconds > 0, the last stage with that CPU budget: pushes only
    (suction=False), the exhaustive push search (`exhaustive_push_plan`, at most exhaustive_states
    states); with suction, the wide search (`wide_plan`). push_target: the target's own pushes are
    actions too (Foss.push_actions(target=True)); push_locked, which assumes the target stays,
    is then not asked, and the estimates (the least removal set at the target's current place)
    are no longer bounds, so a plan need not be the cheapest and "no plan" proves nothing."""
    if not max_seconds > 0:
        raise PolicyError(f"oracle max_seconds={max_seconds}: must be > 0 (e.g. 8.0)")
    if exhaustive_seconds < 0:
        raise PolicyError(f"oracle exhaustive_seconds={exhaustive_seconds}: must be >= 0 (0: off)")
    deadline = time.process_time() + max_seconds
    if not suction and not push_target and push_locked(foss, scene):
        return None
    for leave_room in (False, True):
        for greedy, nodes in ((False, max_nodes), (True, 3 * max_nodes)):
            # A* gets at most a quarter of the bound: when it needs more it rarely finishes at all.
            until = deadline if greedy else min(deadline, time.process_time() + max_seconds / 4)
            plan = _search(foss, scene, suction, budget, psi, nodes, placements, greedy=greedy, deadline=until,
                           leave_room=leave_room, push_target=push_target)
            if plan is not None:
                return plan
    if exhaustive_seconds > 0:
        if suction:
            return wide_plan(foss, scene, budget, psi, placements, exhaustive_seconds, push_target=push_target)
        return exhaustive_push_plan(foss, scene, budget, exhaustive_seconds, exhaustive_states, push_target=push_target)
    return None


def wide_plan(foss: Foss, scene: ShelfScene, budget: int, psi: float = PSI, placements: int = 4,
              max_seconds: float = ORACLE_WIDE_SECONDS, push_target: bool = False) -> tuple[ShelfAction, ...] | None:
    """Oracle-P+S's last stage: the greedy best-first search of the staged one with the pushes that
    stop short, twice the suction placements for the occluders that block the view or are in the
    way of their sweeps (2 * placements; 2 for the others, as there) and no expansion limit, until
    `max_seconds` of CPU. It finds a plan (<= budget actions), not the cheapest; None when the
    states ran out or the time did. The tree with every grid placement is out of reach."""
    return _search(foss, scene, True, budget, psi, max_nodes=np.iinfo(np.int64).max, placements=2 * placements,
                   greedy=True, deadline=time.process_time() + max_seconds, leave_room=True, push_target=push_target)


def exhaustive_push_plan(foss: Foss, scene: ShelfScene, budget: int, max_seconds: float,
                         max_states: int = 400_000, push_target: bool = False) -> tuple[ShelfAction, ...] | None:
    """The reference's exhaustive push tree capped at H, breadth first: every push FOSS allows (to
    the neighbour and stopped short with room for the blade), duplicate states merged (object
    positions to 1 um), a state dropped when it needs more objects moved than the budget has
    actions left (the least removal set; admissible). Returns a shortest push plan (<= budget
    actions) after which FOSS sees the target, or None when there is none (the states ran out or
    every branch reached the budget) or the CPU budget `max_seconds` / `max_states` ran out first.
    The discrete push lengths are FOSS's; the reference's d_x is any real number. push_target: the
    target's pushes too (the pruning then uses the least removal set at the target's current place,
    which is no longer a bound: a plan is found, "none" proves nothing)."""
    if scene.target is None:
        raise PolicyError("the oracles need the full state: connect a scene with its target")
    deadline = time.process_time() + max_seconds
    views = _Views(foss)

    def least(sc) -> int | None:
        _, sets = views(sc)[0].blockers(sc)
        return int(np.bitwise_count(sets).min()) if len(sets) else None

    if least(scene) is None:
        return None
    frontier, seen = [(scene, ())], {_key(scene)}
    for depth in range(1, budget + 1):
        nxt = []
        for sc, plan in frontier:
            if time.process_time() > deadline or len(seen) > max_states:
                return None
            for a in foss.push_actions(sc, leave_room=True, target=push_target):
                s2 = foss.moved(sc, a)
                k = _key(s2)
                if k in seen:
                    continue
                seen.add(k)
                m = least(s2)
                if m == 0:
                    return plan + (a,)
                if m is not None and depth + m <= budget:
                    nxt.append((s2, plan + (a,)))
        if not nxt:
            return None
        frontier = nxt
    return None


def _greedy_estimate(foss: Foss, sc: ShelfScene, cols: np.ndarray, sets: np.ndarray, size: np.ndarray,
                     suction: bool, view: _View, depth: int = 2) -> int:
    """Over the removal sets of at most one more object than the least: the set's objects plus, for
    each, the relaxed count of the actions it needs first (_cost_out: the objects in its cheapest way
    out, and theirs, `depth` levels)."""
    P, n = foss._bodies(sc)
    cost = {}
    best = np.inf
    for m in sets[size <= size.min() + 1].tolist():
        members = [int(cols[i]) for i in range(len(cols)) if m >> i & 1]
        skip = sum(1 << j for j in members)
        total = len(members)
        for j in members:
            if (j, skip) not in cost:
                cost[(j, skip)] = _cost_out(foss, P, n, j, _view_clear(P, j, view), skip, suction, depth)
            total += cost[(j, skip)]
        best = min(best, total)
    return int(best)


def _search(foss: Foss, scene: ShelfScene, suction: bool, budget: int, psi: float, max_nodes: int,
            placements: int, greedy: bool, deadline: float = np.inf,
            leave_room: bool = False, push_target: bool = False) -> tuple[ShelfAction, ...] | None:
    if scene.target is None:
        raise PolicyError("the oracles need the full state: connect a scene with its target")
    views = _Views(foss)
    n = len(scene.objects)

    def evaluate(sc):
        """(estimate, least objects to move, the occluders blocking the view (n,) bool) of a state;
        (None, None, None) when no plan can reveal the target."""
        view = views(sc)[0]
        cols, sets = view.blockers(sc)
        if len(sets) == 0:
            return None, None, None
        size = np.bitwise_count(sets).astype(int)
        h = least = int(size.min())
        if greedy and h:  # not admissible: add the objects that must move first (_obstructors)
            h = _greedy_estimate(foss, sc, cols, sets, size, suction, view)
        inside = np.zeros(n, bool)
        inside[cols] = True
        return h, least, inside

    h0, _, inside = evaluate(scene)
    if h0 is None:
        return None
    heap = [(float(h0), h0, 0, 0.0, scene, (), inside)]  # (priority, h, tie, g, scene, plan, blockers)
    best = {_key(scene): 0.0}
    counter, expanded = 1, 0
    while heap and expanded < max_nodes and time.process_time() < deadline:
        _, h, _, g, sc, plan, inside = heapq.heappop(heap)
        if h == 0:
            return plan
        if len(plan) >= budget or (not greedy and g > best.get(_key(sc), np.inf) + 1e-9):
            continue
        expanded += 1
        actions = [(a, 1.0) for a in foss.push_actions(sc, leave_room=leave_room, target=push_target)]
        if suction:
            view, tri = views(sc)
            actions += [(a, psi) for a in _oracle_suction(foss, sc, tri, _movers(sc, inside), placements, view)]
        for a, cost in actions:
            nxt = foss.moved(sc, a)
            key, g2 = _key(nxt), g + cost
            if best.get(key, np.inf) <= g2 + 1e-9:
                continue
            best[key] = g2
            h2, least, ins = evaluate(nxt)
            if h2 is None or len(plan) + 1 + least > budget:  # each action moves one object
                continue
            heapq.heappush(heap, (h2 if greedy else g2 + h2, h2, counter, g2, nxt, plan + (a,), ins))
            counter += 1
    return None


# -- selection ----------------------------------------------------------------------------------------


def _action_key(a: ShelfAction) -> tuple:
    """An action up to 1 mm in dx and dy: a scene observed again in physics (objects settled by a few
    microns) proposes the same action with slightly different numbers."""
    return a.kind, a.object_id, round(a.dx, 3), round(a.dy, 3)


def _rejected(history) -> set:
    """Keys (`_action_key`) of the shelf actions refused since the last executed one."""
    out = set()
    for outcome in reversed(tuple(history)):
        if outcome.success:
            break
        a = shelf_action(outcome.action)
        if a is not None:
            out.add(_action_key(a))
    return out


def like_key(a: ShelfAction) -> tuple:
    """What an action that changed nothing rules out: a suction of the object (the same grasp,
    whatever the placement) or a push of it in the same direction."""
    return a.kind, a.object_id, float(np.sign(a.dx)) if a.kind == "push" else 0.0


def footprint_change(p, q) -> float:
    """The largest change [m] of an object's footprint centre or size between two observations."""
    return max(abs(p.x - q.x), abs(p.y - q.y), abs(p.width - q.width), abs(p.depth - q.depth), abs(p.height - q.height))


def centre_distance(p, q) -> float:
    """How far [m] an object's footprint centre lies between two observations (the backend's
    "moved"); a lying object's footprint (its rotated bounding box) may change size where it is."""
    return float(np.hypot(p.x - q.x, p.y - q.y))


def nil_effect(history, scene: ShelfScene, tolerance: float) -> set:
    """`like_key`s of the executed shelf actions whose observed effect was nil and whose object is
    unchanged since: the object's footprint centre moved less than `tolerance` [m] between the
    scene the action was chosen in (Action.scene) and the next observation (the next action's
    scene, or `scene` after the last), and `scene` shows it within `tolerance` of where that
    observation did (`centre_distance`: the footprint's size is not compared).
    Such an action (an object lying toppled that neither tool moves, a re-placement the cup drops
    where it was) would do nothing again, with whatever numbers FOSS proposes for it next. Actions
    without a scene (FOSS's rollouts) and plan failures (nothing executed) do not count."""
    hist = tuple(history)
    out = set()
    for i, o in enumerate(hist):
        a = shelf_action(o.action)
        before = o.action.scene
        if a is None or before is None or o.message.startswith("plan_failed"):
            continue
        after = next((h.action.scene for h in hist[i + 1:] if h.action.scene is not None), scene)
        seen = {b.id: b for b in before.objects}, {b.id: b for b in after.objects}, {b.id: b for b in scene.objects}
        if any(a.object_id not in objs for objs in seen):
            continue
        p, q, now = (objs[a.object_id] for objs in seen)
        if centre_distance(p, q) < tolerance and centre_distance(q, now) < tolerance:
            out.add(like_key(a))
    return out


def returns(history, scene: ShelfScene, tolerance: float) -> dict:
    """{object id: [(x, y), ...]}: where one object's footprint centre would take the search back to
    a scene it has observed (every Action.scene of the history, and `scene`): an observed scene with
    the same objects as `scene` in which every object but that one lies within `tolerance` [m] of
    where `scene` shows it contributes that object's centre there (all objects' centres when none
    differs: staying is a return too)."""
    now = {o.id: o for o in scene.objects}
    out: dict = {}
    for seen in [o.action.scene for o in history if o.action.scene is not None] + [scene]:
        then = {o.id: o for o in seen.objects}
        if then.keys() != now.keys():
            continue
        differ = [k for k in now if centre_distance(now[k], then[k]) >= tolerance]
        if len(differ) <= 1:
            for k in differ or now:
                out.setdefault(k, []).append((then[k].x, then[k].y))
    return out


class ShelfPolicies:
    """The decision rules (module docstring), with the oracles' plan cache (keyed by scene content).
    On a robot (params.min_move, params.nil_move, params.revisit > 0) the distribution policies also
    drop, before ranking, the candidates like an executed action whose effect was nil
    (`nil_effect`), those FOSS moves their object less than min_move (a placement within the
    robot's precision of where the object is) and those FOSS predicts to lead back to a scene
    observed in this search (`returns`: no revisit of states, e.g. an object sucked away and pushed
    back in turn). The action's reason counts the candidates each rule dropped, in that order."""

    CACHE = 4096

    def __init__(self, policy: str, foss: Foss, params: ShelfPolicyParams | None = None):
        self.policy = check_shelf_policy(policy)
        self.foss = foss
        self.params = params or ShelfPolicyParams()
        if self.params.psi <= 0 or self.params.lookahead < 1:
            raise PolicyError(f"ShelfPolicyParams: psi={self.params.psi} must be > 0 and lookahead="
                              f"{self.params.lookahead} >= 1")
        self._plans: OrderedDict = OrderedDict()
        last = self.params.oracle_exhaustive_seconds
        self.last_stage_seconds = oracle_last_stage_seconds(self.policy) if last is None else float(last)

    def budget(self, scene: ShelfScene, steps: int) -> int:
        horizon = self.params.horizon if self.params.horizon is not None else 2 * len(scene.objects)
        return max(0, horizon - steps)

    def select(self, scene: ShelfScene, dist: np.ndarray, history=()) -> Action:
        """The next action for `scene` (full state; non-oracles drop the target), P'_t `dist`."""
        rejected = _rejected(history)
        if self.policy in ("oracle_p", "oracle_ps"):
            return self._oracle(scene, len(tuple(history)), rejected)
        seg = segment(self.foss.geometry, scene)
        suction = self.policy in ("random", "bluction_dar")
        actions = [a for a in self.foss.actions(seg.known, suction=suction) if _action_key(a) not in rejected]
        dropped = []

        def drop(rule: str, keep) -> None:
            nonlocal actions
            kept = [a for a in actions if keep(a)]
            dropped.append(f"{rule} {len(actions) - len(kept)}")
            actions = kept

        if self.params.nil_move > 0:
            nil = nil_effect(history, scene, self.params.nil_move)
            drop("nil_move", lambda a: like_key(a) not in nil)
        if self.params.min_move > 0:
            drop("min_move", lambda a: self.displacement(seg.known, a) >= self.params.min_move)
        if self.params.revisit > 0:
            back = returns(tuple(history), scene, self.params.revisit)
            drop("revisit", lambda a: all(np.hypot(*np.subtract(self.predicted_centre(seg.known, a), c))
                                          >= self.params.revisit for c in back.get(a.object_id, ())))
        refused = f" [refused: {', '.join(dropped)}]" if dropped else ""
        if not actions:
            return Action("stop", reason=f"{self.policy}: no feasible action{refused}")
        if self.policy == "random":
            rng = np.random.default_rng([int(self.params.seed), len(tuple(history)), 0x5A17])
            return Action("shelf", shelf=actions[int(rng.integers(len(actions)))], reason=f"random{refused}")
        if self.policy == "der3":
            scores = -der_scores(self.foss, seg, dist, self.params.lookahead, actions)
        else:
            scores = support_reduction(self.foss.geometry, seg, dist, actions)
            scores = np.where([a.kind == "suction" for a in actions], scores / self.params.psi, scores)
        best = int(np.argmax(scores))  # the first of equals: pushes before suction, object order
        return Action("shelf", shelf=actions[best], reason=f"{self.policy}: score {scores[best]:.4g}{refused}")

    def predicted_centre(self, scene: ShelfScene, a: ShelfAction) -> tuple[float, float]:
        """Where FOSS puts the footprint centre of the object of `a` (a push moves it in x only)."""
        o = scene.object(a.object_id)
        return (o.x + a.dx, o.y) if a.kind == "push" else self.foss.placement_center(o, a.dx, a.dy)

    def displacement(self, scene: ShelfScene, a: ShelfAction) -> float:
        """How far [m] FOSS moves the object of `a` (a push: |dx|; a suction: to its placement)."""
        o = scene.object(a.object_id)
        x, y = self.predicted_centre(scene, a)
        return float(np.hypot(x - o.x, y - o.y))

    def _oracle(self, scene: ShelfScene, steps: int, rejected: set) -> Action:
        suction = self.policy == "oracle_ps"
        key = (suction, _key(scene))
        plan = self._plans.get(key)
        if plan is None or (plan and _action_key(plan[0]) in rejected):
            plan = oracle_plan(self.foss, scene, suction, self.budget(scene, steps), self.params.psi,
                               self.params.oracle_max_nodes, self.params.oracle_placements,
                               self.params.oracle_max_seconds, self.last_stage_seconds,
                               push_target=self.params.oracle_push_target)
            if plan is None:
                locked = push_locked(self.foss, scene) if not (suction or self.params.oracle_push_target) else []
                why = (f"no push sequence can take {', '.join(locked)} out of the view" if locked
                       else "no plan clears the view within the budget")
                return Action("stop", reason=f"{self.policy}: {why}")
            sc = scene
            for k in range(len(plan)):  # every state along the plan knows the rest of it
                self._remember((suction, _key(sc)), plan[k:])
                sc = self.foss.moved(sc, plan[k])
        if not plan:
            return Action("stop", reason=f"{self.policy}: the target is already seen")
        return Action("shelf", shelf=plan[0], reason=f"{self.policy}: {len(plan)} actions to go")

    def _remember(self, key, plan):
        self._plans[key] = plan
        self._plans.move_to_end(key)
        while len(self._plans) > self.CACHE:
            self._plans.popitem(last=False)


def history_min(current: ShelfOccupancy, previous: ShelfOccupancy | None) -> ShelfOccupancy:
    """P'_t = min(P_t, P'_{t-1}), renormalised (P_t itself when the minimum is empty or no P'_{t-1})."""
    if previous is None or previous.image_x.shape != current.image_x.shape:
        return current

    def mix(a, b):
        if a.shape != b.shape:
            return a
        m = np.minimum(a, b)
        s = m.sum()
        return m / s if s > 0 else a

    return ShelfOccupancy(mix(current.floor, previous.floor), mix(current.image_x, previous.image_x),
                          current.x0, current.y0, current.step)


class ShelfPolicySelector(LeafSystem):
    """One LeafSystem for every shelf policy.

    Ports (declared first):
      inputs  scene              ShelfScene (FossSystem's; the distribution policies use only its occluders)
              occupancy          ShelfOccupancy P_t (ShelfOccupancyEstimator)
              history            tuple[ActionOutcome] (FossSystem's; optional: unconnected = first step)
      outputs action             Action (kind "shelf" or "stop")
              occupancy_history  ShelfOccupancy P'_t = min(P_t, P'_{t-1})
    State: P'_{t-1} (abstract; None before the first step), set to P'_t by a periodic update every
    `period` s (first at t = period), in step with FossSystem applying the action.
    per_action=True (a controller whose actions last many periods, e.g. the physics controller of
    ms_drake.policies.shelf_search): the state is (history length n, P'_n) instead and advances only
    when the history input has grown, so each executed action adds one observation; P'_t is the
    stored P'_n while the history still has n outcomes.
    """

    def __init__(self, policy: str, foss: Foss, params: ShelfPolicyParams | None = None, period: float = 1.0,
                 per_action: bool = False):
        super().__init__()
        self.rules = ShelfPolicies(policy, foss, params)
        width = foss.geometry.camera.width
        empty = ShelfOccupancy(np.zeros((1, 1)), np.zeros(width))
        # Ports first.
        self.scene_port = self.DeclareAbstractInputPort("scene", AbstractValue.Make(ShelfScene(())))
        self.occupancy_port = self.DeclareAbstractInputPort("occupancy", AbstractValue.Make(empty))
        self.history_port = self.DeclareAbstractInputPort("history", AbstractValue.Make(()))
        self._previous = self.DeclareAbstractState(AbstractValue.Make(None))
        self.DeclareAbstractOutputPort("action", lambda: AbstractValue.Make(Action("stop")), self._calc_action,
                                       prerequisites_of_calc={self.all_sources_ticket()})
        self.DeclareAbstractOutputPort("occupancy_history", lambda: AbstractValue.Make(empty), self._calc_history,
                                       prerequisites_of_calc={self.all_sources_ticket()})
        self.DeclarePeriodicUnrestrictedUpdateEvent(period, period, self._update)
        self.policy = policy
        self.per_action = bool(per_action)
        self._count = self.DeclareAbstractState(AbstractValue.Make(-1))  # per_action: n of the stored P'_n

    def _steps(self, context) -> int:
        return len(tuple(self.history_port.Eval(context))) if self.history_port.HasValue(context) else 0

    def _current(self, context) -> ShelfOccupancy:
        if not self.occupancy_port.HasValue(context):
            raise PolicyError(f"ShelfPolicySelector({self.policy!r}): connect the occupancy input "
                              "(ShelfOccupancyEstimator)")
        previous = context.get_abstract_state(self._previous).get_value()
        if self.per_action and previous is not None and \
                context.get_abstract_state(self._count).get_value() == self._steps(context):
            return previous
        return history_min(self.occupancy_port.Eval(context), previous)

    def _calc_history(self, context, output):
        output.set_value(self._current(context))

    def _calc_action(self, context, output):
        if not self.scene_port.HasValue(context):
            raise PolicyError(f"ShelfPolicySelector({self.policy!r}): connect the scene input (FossSystem)")
        scene = self.scene_port.Eval(context)
        history = self.history_port.Eval(context) if self.history_port.HasValue(context) else ()
        dist = None if self.rules.policy.startswith("oracle") else self._current(context).image_x
        output.set_value(self.rules.select(scene, dist, history))

    def _update(self, context, state):
        if not self.occupancy_port.HasValue(context):
            return
        if self.per_action:
            n = self._steps(context)
            if context.get_abstract_state(self._count).get_value() == n:
                return
            state.get_mutable_abstract_state(self._count).set_value(n)
        state.get_mutable_abstract_state(self._previous).set_value(self._current(context))
