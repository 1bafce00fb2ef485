"""The MPPI policy of Ch. 6.4.2 (lines 1078-1096) in joint space, and its LeafSystem.

One call (`mppi_step`) from configuration q towards a goal g, with d = g - q:

1. T directions d~_i = N(d + N(0, Sigma)) (N: rescaled to the length of d; the reference's
   "perturbing the straight-line trajectory ... and renormalizing"); the first is d itself, so
   the straight line is always among the candidates;
2. each trajectory is H waypoints q + (k / H) d~_i, k = 1..H, clipped to the joint limits at
   every step;
3. every waypoint is collision-checked (`collides`: a batch of configurations -> bool, e.g. the
   scene network for the robot's links and the object in hand plus Drake's geometry for the robot
   itself and the table; any callable; ms_drake.planning.batch_fk.BatchFK gives the link poses
   of all waypoints in one batched pass), and each trajectory is cut before its first colliding
   waypoint;
4. the cost of a waypoint is its joint-space distance to the goal (the final-state cost); the
   returned waypoint is the lowest-cost one over all kept waypoints (the reference executes the
   minimal-cost trajectory up to it until the policy is called again); None when every
   trajectory collides at its first waypoint.

`weighted=True` is the classical MPPI update as an option: the direction is the average of the
d~_i weighted by exp(-(c_i - min c) / lambda) over the trajectories' best costs c_i, followed
like the straight line (cut at its first collision as above); it falls back to the best waypoint
when that direction collides at once. The weighted mean can lead straight into an obstacle's
front face and stop there, where every next sample collides at once (tests/test_mppi.py: it
passes an obstacle beside the line, not one across it); the default minimum-cost waypoint does
not have that trap.

`MppiPlanner` wraps it as a LeafSystem: inputs ``q`` and ``goal`` (vectors), output
``waypoint`` (the next configuration; q itself when no waypoint is free) and ``free`` (1 when a
collision-free waypoint was found). Random draws come from (seed, call count).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem

from ms_drake.errors import MsDrakeError


class MppiError(MsDrakeError):
    """MPPI was given settings or inputs it cannot use."""


@dataclass(frozen=True)
class MppiParams:
    trajectories: int = 300  # T (the reference's)
    horizon: int = 40  # H
    sigma: float = float(np.sqrt(0.3))  # per-joint standard deviation: the reference's Sigma = 0.3 I
    weighted: bool = False
    temperature: float = 0.1  # lambda of the weighted update (rad)
    seed: int = 0

    def check(self) -> None:
        if self.trajectories < 1 or self.horizon < 1:
            raise MppiError(f"MPPI needs trajectories >= 1 and horizon >= 1, got {self.trajectories}, {self.horizon}")
        if self.sigma < 0 or self.temperature <= 0:
            raise MppiError(f"MPPI needs sigma >= 0 and temperature > 0, got {self.sigma}, {self.temperature}")


#: The reference's setting (T = 300, H = 40, Sigma = 0.3 I).
REFERENCE = MppiParams()


def rollouts(q: np.ndarray, goal: np.ndarray, lower: np.ndarray, upper: np.ndarray, params: MppiParams,
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(directions (T, n), waypoints (T, H, n)) of one MPPI call (module doc, steps 1-2)."""
    d = goal - q
    length = float(np.linalg.norm(d))
    T, H = params.trajectories, params.horizon
    noisy = d + rng.normal(0.0, params.sigma, (T, len(q)))
    noisy[0] = d
    norms = np.linalg.norm(noisy, axis=1, keepdims=True)
    dirs = np.where(norms > 1e-12, noisy / np.maximum(norms, 1e-12) * length, 0.0)
    steps = np.arange(1, H + 1)[None, :, None] / H
    way = np.clip(q + steps * dirs[:, None, :], lower, upper)
    return dirs, way


def _first_free(free: np.ndarray) -> np.ndarray:
    """(T,) number of waypoints before each trajectory's first collision."""
    hit = ~free
    return np.where(hit.any(axis=1), hit.argmax(axis=1), free.shape[1])


def mppi_step(q, goal, collides: Callable[[np.ndarray], np.ndarray] | None, lower, upper,
              params: MppiParams = REFERENCE, rng: np.random.Generator | None = None,
              lazy: Callable[[np.ndarray], np.ndarray] | None = None):
    """(next waypoint or None, info) of one MPPI call (module doc). `collides` (None: nothing
    collides) checks every waypoint in one batch; `lazy` (optional) is a second check applied only
    where it decides the answer: the lowest-cost kept waypoint's trajectory is checked up to it,
    cut at its first colliding waypoint, and the next lowest taken, until one passes (the same
    waypoint as checking every waypoint with both, at a fraction of the checks: for checkers that
    cost per configuration, e.g. Drake's geometry or coal). info["path"]: the chosen trajectory's
    waypoints up to the chosen one (to execute)."""
    params.check()
    q, goal = np.asarray(q, float), np.asarray(goal, float)
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if q.shape != goal.shape or q.shape != lower.shape or q.shape != upper.shape:
        raise MppiError(f"q, goal and the limits must have one shape, got {q.shape}, {goal.shape}, "
                        f"{lower.shape}, {upper.shape}")
    rng = rng if rng is not None else np.random.default_rng(params.seed)
    dirs, way = rollouts(q, goal, lower, upper, params, rng)
    T, H, n = way.shape
    if collides is None:
        free = np.ones((T, H), bool)
    else:
        free = np.asarray(collides(way.reshape(-1, n)), bool).reshape(T, H) == 0
    keep = _first_free(free)
    cost = np.linalg.norm(way - goal, axis=2)
    cost[np.arange(H)[None, :] >= keep[:, None]] = np.inf
    info = {"checks": T * H if collides is not None else 0, "lazy_checks": 0,
            "free_trajectories": int((keep == H).sum()), "blocked_at_once": int((keep == 0).sum())}
    if lazy is not None:
        verified = np.zeros(T, int)  # waypoints of each trajectory the lazy check has passed
        while np.isfinite(cost).any():
            t, k = np.unravel_index(np.argmin(cost), cost.shape)
            if verified[t] > k:
                break
            hit = np.asarray(lazy(way[t, verified[t]:k + 1]), bool)
            info["lazy_checks"] += len(hit)
            if hit.any():
                j = verified[t] + int(hit.argmax())
                cost[t, j:] = np.inf
                verified[t] = j
            else:
                verified[t] = k + 1
                break
    if not np.isfinite(cost).any():
        return None, info
    t, k = np.unravel_index(np.argmin(cost), cost.shape)
    best = way[t, k]
    info["path"] = way[t, :k + 1]
    if params.weighted:
        c = cost.min(axis=1)
        ok = np.isfinite(c)
        w = np.exp(-(c[ok] - c[ok].min()) / params.temperature)
        mean_dir = (w[:, None] * dirs[ok]).sum(axis=0) / w.sum()
        line = np.clip(q + np.arange(1, H + 1)[:, None] / H * mean_dir, lower, upper)
        lhit = np.zeros(H, bool) if collides is None else np.asarray(collides(line), bool)
        if lazy is not None:
            lhit = lhit | np.asarray(lazy(line), bool)
        m = int(_first_free(~lhit[None])[0])
        info["checks"] += H
        if m > 0:
            lcost = np.linalg.norm(line[:m] - goal, axis=1)
            j = int(np.argmin(lcost))
            best = line[j]
            info["path"] = line[:j + 1]
    info["cost"] = float(np.linalg.norm(best - goal))
    return best, info


class MppiPlanner(LeafSystem):
    """One MPPI call per evaluation (module doc): inputs ``q``, ``goal``; outputs ``waypoint``, ``free``."""

    def __init__(self, num_positions: int, collides: Callable[[np.ndarray], np.ndarray], lower, upper,
                 params: MppiParams = REFERENCE):
        super().__init__()
        params.check()
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        if lower.shape != (num_positions,) or upper.shape != (num_positions,):
            raise MppiError(f"joint limits must have {num_positions} entries, got {lower.shape} and {upper.shape}")
        # Ports first.
        self.q_port = self.DeclareVectorInputPort("q", num_positions)
        self.goal_port = self.DeclareVectorInputPort("goal", num_positions)
        self.DeclareVectorOutputPort("waypoint", num_positions, self._waypoint,
                                     prerequisites_of_calc={self.all_input_ports_ticket()})
        self.DeclareVectorOutputPort("free", 1, self._free, prerequisites_of_calc={self.all_input_ports_ticket()})
        self.collides, self.lower, self.upper, self.params = collides, lower, upper, params
        self.calls = 0
        self._memo = None

    def plan(self, q, goal):
        key = (tuple(np.round(q, 12)), tuple(np.round(goal, 12)))
        if self._memo is None or self._memo[0] != key:
            rng = np.random.default_rng([self.params.seed, self.calls])
            self.calls += 1
            self._memo = (key, mppi_step(q, goal, self.collides, self.lower, self.upper, self.params, rng))
        return self._memo[1]

    def _waypoint(self, context, output: BasicVector):
        q, goal = self.q_port.Eval(context), self.goal_port.Eval(context)
        best, _ = self.plan(q, goal)
        output.SetFromVector(q if best is None else best)

    def _free(self, context, output: BasicVector):
        best, _ = self.plan(self.q_port.Eval(context), self.goal_port.Eval(context))
        output.SetFromVector([0.0 if best is None else 1.0])
