"""Grasp value types of the grasping package (world or object frame, as the caller says)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ms_drake.errors import MsDrakeError
from ms_drake.types import Grasp


class GraspError(MsDrakeError, ValueError):
    """A grasp or evaluator was built with impossible values (names the field and the fix)."""


def _unit(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise GraspError(f"{name} must be a finite 3-vector, got {v!r}")
    n = np.linalg.norm(v)
    if n < 1e-9:
        raise GraspError(f"{name} must be non-zero, got {v!r}")
    return v / n


@dataclass(frozen=True, eq=False)
class ParallelJawGrasp:
    """A parallel-jaw grasp: jaws open `width` apart on the line through `center` along `axis`
    (the axis joins the jaws), the gripper approaching along `approach`.

    axis is normalized; approach is made orthogonal to axis and normalized.
    """

    center: np.ndarray
    axis: np.ndarray
    approach: np.ndarray
    width: float

    def __init__(self, center, axis, approach, width):
        c = np.asarray(center, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise GraspError(f"ParallelJawGrasp.center must be a finite 3-vector, got {center!r}")
        a = _unit(axis, "ParallelJawGrasp.axis")
        ap = np.asarray(approach, dtype=float).reshape(-1)
        if ap.shape != (3,) or not np.all(np.isfinite(ap)):
            raise GraspError(f"ParallelJawGrasp.approach must be a finite 3-vector, got {approach!r}")
        ap = ap - np.dot(ap, a) * a
        if np.linalg.norm(ap) < 1e-6:
            raise GraspError("ParallelJawGrasp.approach must not be parallel to the axis; pick a direction "
                             "orthogonal to the line joining the jaws")
        ap = ap / np.linalg.norm(ap)
        w = float(width)
        if not np.isfinite(w) or w <= 0:
            raise GraspError(f"ParallelJawGrasp.width must be > 0 (the jaw opening in metres), got {width!r}")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "axis", a)
        object.__setattr__(self, "approach", ap)
        object.__setattr__(self, "width", w)

    def transformed(self, X: np.ndarray) -> "ParallelJawGrasp":
        """This grasp moved by the 4x4 transform X (e.g. X_OW to go from world to object frame)."""
        R, p = X[:3, :3], X[:3, 3]
        return ParallelJawGrasp(R @ self.center + p, R @ self.axis, R @ self.approach, self.width)

    def rotation(self) -> np.ndarray:
        """Gripper frame as a rotation: columns x = approach, y = axis x approach, z = axis."""
        z = self.axis
        x = self.approach
        return np.column_stack([x, np.cross(z, x), z])

    def to_grasp(self, quality: float = 0.0, model: str = "", object_id: str = "", lifts: bool | None = None) -> Grasp:
        return Grasp("parallel_jaw", tuple(map(float, self.center)), tuple(map(float, self.approach)),
                     tuple(map(float, self.axis)), float(self.width), float(quality), model, object_id, lifts)

    @staticmethod
    def from_grasp(g: Grasp) -> "ParallelJawGrasp":
        if g.kind != "parallel_jaw":
            raise GraspError(f"Grasp.kind must be 'parallel_jaw' to make a ParallelJawGrasp, got {g.kind!r}")
        return ParallelJawGrasp(g.center, g.axis, g.approach, g.width)

    def __repr__(self):
        f = lambda v: "(" + ", ".join(f"{x:.4f}" for x in v) + ")"  # noqa: E731
        return (f"ParallelJawGrasp(center={f(self.center)}, axis={f(self.axis)}, "
                f"approach={f(self.approach)}, width={self.width:.4f})")


@dataclass(frozen=True, eq=False)
class SuctionGrasp:
    """A suction grasp: the cup touches `point` approaching along `approach` (minus the normal)."""

    point: np.ndarray
    approach: np.ndarray

    def __init__(self, point, approach):
        p = np.asarray(point, dtype=float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise GraspError(f"SuctionGrasp.point must be a finite 3-vector, got {point!r}")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "approach", _unit(approach, "SuctionGrasp.approach"))

    def transformed(self, X: np.ndarray) -> "SuctionGrasp":
        return SuctionGrasp(X[:3, :3] @ self.point + X[:3, 3], X[:3, :3] @ self.approach)

    def to_grasp(self, quality: float = 0.0, model: str = "suction", object_id: str = "",
                 lifts: bool | None = None) -> Grasp:
        return Grasp("suction", tuple(map(float, self.point)), tuple(map(float, self.approach)),
                     quality=float(quality), model=model, object_id=object_id, lifts=lifts)
