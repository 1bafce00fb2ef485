"""Bin action selection (Ch. 7.4, lines 1270-1282; App. C.4) and X-Ray (Ch. 8.4, lines 1481-1536).

Every selector is a pure function of small inputs: the visible masks, the target estimate, the
occupancy distribution (X-Ray), the grasp candidates with their qualities (Grasp.object_id =
the mask id; several per mask allowed, e.g. one parallel-jaw and one suction: the best counts;
or a Mapping object id -> best Grasp, e.g. grasping.planner.LazyGrasps, which plans an
object only when the selector looks it up -- the walk below stops at the first qualifying grasp),
the push candidates (Push.object_id = the mask id; present = quality 1), and the history of
ActionOutcome. Randomness comes from `SelectorParams.seed` and the step number, so a step is
reproducible from its inputs alone.

Selectors (the priority list decides which object is tried first):
  random                 all masks in random order, no preference for the target;
  preempted_random       the target mask first, the others in random order;
  preempted_random_push  the same, with pushing;
  largest                the target mask first, the others by visible area (largest first);
  largest_push           the same, with pushing;
  xray                   the target mask first when it is seen, then masks by sum(mask * occupancy)
                         (Ch. 8.4), ties by area;
  xray_expected          X-Ray with each mask's score times its best grasp's quality: the expected
                         support reduction when a grasp lifts with probability = quality (not the
                         reference's X-Ray: an ablation; masks without a grasp score 0);
  oracle                 the true target first, then the masks that cover the target's true amodal
                         mask most, then by area: a selector with the true state (an upper bound).

Execution criteria (Ch. 7.4): walk the priority list and execute the best grasp on the first
mask whose best grasp quality exceeds t(o) (with `retry_failed` False, a best grasp that failed
on the current state, or a re-plan of it that is no better (`same_grasp`), is passed over; with `skip_failed`, every mask a grasp failed on since the last
successful action): t(target) = t_thresh; t(other) = t_high with pushing,
t_thresh without. With pushing, when no grasp qualifies, walk the list again and push the first
object that has a valid push. Termination (an Action of kind "stop" with `reason`):
  success            the target was removed by a successful grasp (see `termination`);
  target_removed     the target left the bin by accident (a push or another object's grasp);
  horizon            `horizon` actions were taken (the harness sets 2N for Ch. 7, H = 10 for X-Ray);
  too_many_pushes    the next action would be a push after `max_consecutive_pushes` pushes in a row;
  no_action          no grasp qualifies and no push is valid (or pushing is off).
X-Ray and the oracle grasp only (Ch. 8.4 uses grasps), with t_thresh for every object (our
choice: the text gives no X-Ray threshold). X-Ray trying the seen target first is our reading of
lines 1473-1480 and 1514-1516: the reference's distribution collapses onto a seen target, so its
mask scores highest, and X-Ray removes an occluder "when a robust grasp is not available on the
target"; stated explicitly here so that a distribution spread by a few percent onto the
occluders cannot rank an occluder above a graspable seen target. Note for Table 8.2: Ch. 8's
baselines "Random" and "Largest" both try the target first (line 1510), i.e. they are
`preempted_random` and `largest` here; Ch. 7's `random` has no preference for the target.

Contract with the executor: ActionOutcome.removed_object is the true id of the object that left
the bin (in simulation the model-instance name, which is also the ground-truth mask id);
`message="target_removed"` flags an accidental removal of the target explicitly.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ms_drake.errors import MsDrakeError
from ms_drake.types import (
    Action,
    ActionOutcome,
    Grasp,
    InstanceMasks,
    OccupancyMap,
    Push,
    TargetEstimate,
)

POLICIES = ("random", "preempted_random", "preempted_random_push", "largest", "largest_push", "xray", "xray_expected",
            "oracle")
OCCUPANCY_POLICIES = ("xray", "xray_expected")  # the selectors that read the occupancy input
PUSHING = ("preempted_random_push", "largest_push")


class PolicyError(MsDrakeError, ValueError):
    """A selector was asked for with an unknown name or impossible parameters, or lacks an input it needs."""


@dataclass(frozen=True)
class SelectorParams:
    t_thresh: float = 0.15
    t_high: float = 0.3
    max_consecutive_pushes: int = 3
    horizon: int | None = None  # None: no limit from the selector
    seed: int = 0
    # False: a grasp that failed is not attempted again while the state is the one it failed on
    # (since the last successful action), as with a deterministic grasp outcome it would fail again
    retry_failed: bool = True
    # True: an object a grasp failed on is passed over (any grasp on it) until an action succeeds
    skip_failed: bool = False

    def __post_init__(self):
        if not (0.0 <= self.t_thresh <= 1.0 and 0.0 <= self.t_high <= 1.0):
            raise PolicyError(f"grasp thresholds must lie in [0, 1] (t_thresh={self.t_thresh}, t_high={self.t_high}); "
                              "the reference uses 0.15 and 0.3 in simulation")
        if self.horizon is not None and self.horizon < 1:
            raise PolicyError(f"horizon={self.horizon}: give at least 1 action (2N for Ch. 7, 10 for X-Ray) or None")
        if self.max_consecutive_pushes < 0:
            raise PolicyError("max_consecutive_pushes must be >= 0 (reference: 3)")


def check_policy(name: str) -> str:
    if name not in POLICIES:
        raise PolicyError(f"unknown policy {name!r}; choose one of {', '.join(POLICIES)}")
    return name


def _rng(params: SelectorParams, history) -> np.random.Generator:
    return np.random.default_rng([int(params.seed), len(history), 7477])


def target_index(masks: InstanceMasks, target: TargetEstimate | None) -> int:
    """Index of the mask identified as the target (-1 if none)."""
    if target is None or not target.visible or not 0 <= target.instance_index < len(masks):
        return -1
    return int(target.instance_index)


def priority_random(masks: InstanceMasks, rng: np.random.Generator) -> list[int]:
    return [int(i) for i in rng.permutation(len(masks))]


def priority_preempted_random(masks: InstanceMasks, target: TargetEstimate | None,
                              rng: np.random.Generator) -> list[int]:
    t = target_index(masks, target)
    rest = [i for i in priority_random(masks, rng) if i != t]
    return ([t] if t >= 0 else []) + rest


def priority_largest(masks: InstanceMasks, target: TargetEstimate | None) -> list[int]:
    t = target_index(masks, target)
    order = [int(i) for i in np.argsort(-masks.areas(), kind="stable")] if len(masks) else []
    return ([t] if t >= 0 else []) + [i for i in order if i != t]


def xray_scores(masks: InstanceMasks, occupancy: OccupancyMap) -> np.ndarray:
    """sum(mask * occupancy) per mask (Ch. 8.4)."""
    if len(masks) == 0:
        return np.zeros(0)
    rho = np.asarray(occupancy.distribution, float)
    if rho.shape != masks.masks.shape[1:]:
        raise PolicyError(f"occupancy is {rho.shape[1]}x{rho.shape[0]} but the masks are "
                          f"{masks.masks.shape[2]}x{masks.masks.shape[1]}; use the same camera")
    return (masks.masks.reshape(len(masks), -1).astype(float) @ rho.ravel())


def priority_xray(masks: InstanceMasks, occupancy: OccupancyMap, target: TargetEstimate | None = None,
                  weights: np.ndarray | None = None) -> list[int]:
    """The seen target first (see the module doc), then masks by X-Ray score (times `weights` per
    mask when given), ties by area."""
    s = xray_scores(masks, occupancy)
    if weights is not None:
        s = s * np.asarray(weights, float)
    order = [int(i) for i in np.lexsort((-masks.areas(), -s))] if len(masks) else []
    t = target_index(masks, target)
    return ([t] if t >= 0 else []) + [i for i in order if i != t]


def priority_oracle(masks: InstanceMasks, target_id: str, target_amodal: np.ndarray | None) -> list[int]:
    t = masks.ids.index(target_id) if target_id in masks.ids else -1
    if len(masks) == 0:
        return []
    cover = (masks.masks & np.asarray(target_amodal, bool)[None]).reshape(len(masks), -1).sum(axis=1) \
        if target_amodal is not None else np.zeros(len(masks))
    order = [int(i) for i in np.lexsort((-masks.areas(), -cover))]
    return ([t] if t >= 0 else []) + [i for i in order if i != t]


def best_grasps(grasps) -> dict[str, Grasp]:
    """The best grasp per object id."""
    best: dict[str, Grasp] = {}
    for g in grasps:
        if g.object_id not in best or g.quality > best[g.object_id].quality:
            best[g.object_id] = g
    return best


def termination(history, target_id: str = "", horizon: int | None = None) -> str | None:
    """Why the search is over before choosing a new action (None: go on). See the module doc."""
    for o in history:
        if o.message == "target_removed":
            return "target_removed"
        if target_id and o.removed_object == target_id:
            return "success" if (o.action.kind == "grasp" and o.success) else "target_removed"
    if horizon is not None and len(history) >= horizon:
        return "horizon"
    return None


def consecutive_pushes(history) -> int:
    n = 0
    for o in reversed(history):
        if o.action.kind != "push":
            break
        n += 1
    return n


def failed_on_this_state(history) -> list[Grasp]:
    """The grasps that failed since the last successful action (on the state the search is in)."""
    out = []
    for o in reversed(history):
        if o.success:
            break
        if o.action.kind == "grasp" and o.action.grasp is not None:
            out.append(o.action.grasp)
    return out


def same_grasp(a: Grasp, b: Grasp, tol: float = 0.005) -> bool:
    """A re-plan of failed grasp `b`: the same object and gripper kind, and the contact point within
    `tol` metres (perfect depth re-plans a grasp on a settled state to a fraction of a millimetre)
    or a quality no higher than `b`'s (a noisy camera re-plans it centimetres away, no better)."""
    return (a.object_id == b.object_id and a.kind == b.kind
            and (float(np.linalg.norm(np.subtract(a.center, b.center))) <= tol or a.quality <= b.quality))


def select_action(policy: str, masks: InstanceMasks, target: TargetEstimate | None = None,
                  grasps: tuple[Grasp, ...] | Mapping = (), pushes: tuple[Push, ...] = (),
                  history: tuple[ActionOutcome, ...] = (), occupancy: OccupancyMap | None = None,
                  params: SelectorParams = SelectorParams(), target_id: str = "",
                  target_amodal: np.ndarray | None = None) -> Action:
    """One step of the selector `policy` (see the module doc)."""
    check_policy(policy)
    stop = termination(history, target_id, params.horizon)
    if stop is not None:
        return Action("stop", reason=stop)
    rng = _rng(params, history)
    best = grasps if isinstance(grasps, Mapping) else best_grasps(grasps)
    if policy == "random":
        order = priority_random(masks, rng)
    elif policy in ("preempted_random", "preempted_random_push"):
        order = priority_preempted_random(masks, target, rng)
    elif policy in ("largest", "largest_push"):
        order = priority_largest(masks, target)
    elif policy in OCCUPANCY_POLICIES:
        if occupancy is None:
            raise PolicyError(f"the {policy} policy needs the occupancy input (OccupancyEstimator)")
        weights = None
        if policy == "xray_expected":  # every mask's best grasp is looked up (a lazy planner plans them all)
            weights = [(g.quality if (g := best.get(i)) is not None else 0.0) for i in masks.ids]
        order = priority_xray(masks, occupancy, target, weights)
    else:
        order = priority_oracle(masks, target_id, target_amodal)
    t_idx = masks.ids.index(target_id) if policy == "oracle" and target_id in masks.ids else target_index(masks, target)
    pushing = policy in PUSHING
    failed = () if params.retry_failed and not params.skip_failed else failed_on_this_state(history)
    failed_objects = {f.object_id for f in failed} if params.skip_failed else set()
    for i in order:
        if masks.ids[i] in failed_objects:
            continue
        g = best.get(masks.ids[i])
        if g is None or any(same_grasp(g, f) for f in failed):
            continue
        t = params.t_thresh if (i == t_idx or not pushing) else params.t_high
        if g.quality > t:
            who = "target" if i == t_idx else f"rank {order.index(i)}"
            return Action("grasp", grasp=g, reason=f"{policy}: grasp {g.object_id} ({who}, quality {g.quality:.2f})")
    if pushing:
        by_id = {p.object_id: p for p in pushes}
        for i in order:
            p = by_id.get(masks.ids[i])
            if p is None:
                continue
            if consecutive_pushes(history) >= params.max_consecutive_pushes:
                return Action("stop", reason="too_many_pushes")
            return Action("push", push=p, reason=f"{policy}: push {p.object_id}")
    return Action("stop", reason="no_action")
