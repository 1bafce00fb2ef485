"""Pushing: the free-space linear push of Ch. 7.3.2 (`plan_free_space_push`) and the PushPlanner system."""

from ms_drake.pushing.free_space import (  # noqa: F401
    ObstacleMap,
    PushError,
    PushParams,
    obstacle_map,
    plan_free_space_push,
    plan_pushes,
)
from ms_drake.pushing.planner import PushPlanner  # noqa: F401

__all__ = [
    "ObstacleMap",
    "PushError",
    "PushParams",
    "obstacle_map",
    "plan_free_space_push",
    "plan_pushes",
    "PushPlanner",
]
