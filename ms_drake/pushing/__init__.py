"""Pushing: the free-space linear push of Ch. 7.3.2 (`plan_free_space_push`) and the PushPlanner
system; the five push policies of Ch. 4 (`plan_policy_push`) and the PushPolicySystem."""

from ms_drake.pushing.free_space import (
    MAX_PUSH_HEIGHT,
    MIN_PUSH_HEIGHT,
    ObstacleMap,
    PushError,
    PushParams,
    obstacle_map,
    plan_free_space_push,
    plan_pushes,
    push_height,
)
from ms_drake.pushing.planner import PushPlanner
from ms_drake.pushing.policies import (
    POLICIES,
    PolicyParams,
    PushScene,
    check_push_policy,
    image_scene,
    plan_policy_push,
    state_scene,
)
from ms_drake.pushing.policy_system import PushPolicySystem

__all__ = [
    "MAX_PUSH_HEIGHT",
    "MIN_PUSH_HEIGHT",
    "POLICIES",
    "ObstacleMap",
    "PolicyParams",
    "PushError",
    "PushParams",
    "PushPlanner",
    "PushPolicySystem",
    "PushScene",
    "check_push_policy",
    "image_scene",
    "obstacle_map",
    "plan_free_space_push",
    "plan_policy_push",
    "plan_pushes",
    "push_height",
    "state_scene",
]
