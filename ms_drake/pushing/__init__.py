"""Pushing: the free-space linear push of Ch. 7.3.2 (`plan_free_space_push`) and the PushPlanner
system; the five push policies of Ch. 4 (`plan_policy_push`) and the PushPolicySystem."""

from ms_drake.pushing.free_space import (  # noqa: F401
    ObstacleMap,
    PushError,
    PushParams,
    obstacle_map,
    plan_free_space_push,
    plan_pushes,
)
from ms_drake.pushing.planner import PushPlanner  # noqa: F401
from ms_drake.pushing.policies import (  # noqa: F401
    POLICIES,
    PolicyParams,
    PushScene,
    check_push_policy,
    image_scene,
    plan_policy_push,
    state_scene,
)
from ms_drake.pushing.policy_system import PushPolicySystem  # noqa: F401

__all__ = [
    "ObstacleMap",
    "PushError",
    "PushParams",
    "obstacle_map",
    "plan_free_space_push",
    "plan_pushes",
    "PushPlanner",
    "POLICIES",
    "PolicyParams",
    "PushScene",
    "check_push_policy",
    "image_scene",
    "plan_policy_push",
    "state_scene",
    "PushPolicySystem",
]
