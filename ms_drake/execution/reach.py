"""PickReach: can a station's robot execute a grasp? The full backend's own pick plan (IK of the
pre-grasp from the park configuration, the straight approach, the straight lift; the jaw also
turned by pi about its axis) without simulating it, so a grasp planner can keep only the grasps
the robot reaches -- the primitive mode then executes the grasps the robot would (issue #15, "The
two fidelities agree").
"""

from __future__ import annotations

from ms_drake.execution.backends import FullBackend, grasp_tool_pose
from ms_drake.geometry import Workspace
from ms_drake.planning.sequences import plan_pick
from ms_drake.types import Grasp


class PickReach:
    """reach(grasp) -> True when the robot of `scenario` plans a pick of it from park (the
    FullBackend's arms, park configurations and pick settings). `checks` counts the calls and
    `reached` the grasps found reachable.

    The pre-grasp IK is solved from the park configuration only, without the random restarts:
    the backend's IK tries that same seed first (and its straight lines have no restarts), so a
    grasp reached here is reached by the backend whatever state its random restarts are in;
    a grasp only a random restart reaches is left out (conservative)."""

    def __init__(self, scenario, seed: int = 0):
        self.backend = FullBackend(scenario, {}, Workspace.from_scenario(scenario), seed=seed)
        for ik, _, _ in self.backend.ik.values():
            ik.restarts = 0
        self.checks = self.reached = 0

    def status(self, grasp: Grasp) -> str:
        """"ok", the IK status of the failing step, or "no_<kind>_gripper"."""
        b = self.backend
        tool = b.jaw if grasp.kind == "parallel_jaw" else b.suction
        if tool is None:
            return f"no_{grasp.kind}_gripper"
        arm, port = tool
        ik, limits, q_home = b.ik[arm]
        plan = plan_pick(ik, limits, q_home, grasp_tool_pose(grasp), arm, port, grasp.kind, lift=b.lift,
                         speed=b.speed, close_time=b.close_time, hold_time=b.hold_time)
        return plan.status

    def __call__(self, grasp: Grasp) -> bool:
        self.checks += 1
        ok = self.status(grasp) == "ok"
        self.reached += ok
        return ok
