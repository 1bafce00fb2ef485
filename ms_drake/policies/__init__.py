"""Policies: bin selectors of Ch. 7.4, X-Ray (Ch. 8.4), an oracle, the PolicySelector system, and the
controller Diagram builders (bin_search.MakeBinSearchController)."""

from ms_drake.policies.bin_selectors import (  # noqa: F401
    POLICIES,
    PolicyError,
    SelectorParams,
    best_grasps,
    consecutive_pushes,
    priority_largest,
    priority_oracle,
    priority_preempted_random,
    priority_random,
    priority_xray,
    select_action,
    termination,
    xray_scores,
)
from ms_drake.policies.selector import PolicySelector  # noqa: F401

__all__ = [
    "POLICIES",
    "PolicyError",
    "SelectorParams",
    "best_grasps",
    "consecutive_pushes",
    "priority_largest",
    "priority_oracle",
    "priority_preempted_random",
    "priority_random",
    "priority_xray",
    "select_action",
    "termination",
    "xray_scores",
    "PolicySelector",
]
