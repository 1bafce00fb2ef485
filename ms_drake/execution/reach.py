"""PickReach: can a station's robot execute a grasp? The full backend's own pick plan (IK of the
pre-grasp from the park configuration, the straight approach, the straight lift; the jaw also
turned by pi about its axis) without simulating it, so a grasp planner can keep only the grasps
the robot reaches -- the primitive mode then executes the grasps the robot would (so that the two
fidelities agree).

Given the scene (the IndexedGraspPlanner's coal Scene of the objects and the bin), a reached
grasp must also keep the arm clear of it:
- along the planned approach, from the pre-grasp to the grasp, the arm's links (not the gripper,
  which the planner checks itself at the grasp) at `approach_samples` configurations may not
  intersect any object: the gripper alone being free is not enough, the wrist behind a tilted
  suction tool or a jaw runs into the neighbouring objects, and the approach then stops short;
- along the transit from park to above the pre-grasp (a joint-space move at the arm's full
  speed), the links and the tool (the gripper on the last link: the cup and its stem, the jaw's
  palm and its fingers as opened for the pick) at configurations at most `transit_step` seconds
  apart must stay `transit_clearance` from everything, the grasped object included: a joint
  motion tracked at ~0.8 m/s swept a cup within 2 mm of (and into) the box it was to grasp,
  knocking it 30-45 degrees over (YuMi fidelity heaps 5015, 5045, 5047), and an open finger
  knocked a grasped object over on fidelity heap 5092;
- along the straight descent from there to the pre-grasp (tracked at the approach speed), links
  and tool at most `transit_step` seconds apart stay `descent_clearance` from everything;
- along the approach, the tool too may not intersect the objects (but at contact, where the
  planner checked it).
"""

from __future__ import annotations

import dataclasses

import coal
import numpy as np
import trimesh
from pydrake.geometry import Box, Convex, Cylinder, Mesh, SceneGraph

from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import Solve

from ms_drake.execution.backends import FullBackend, grasp_tool_pose, pick_opening
from ms_drake.geometry import Workspace, coal_convex
from ms_drake.robots import PICK_APPROACH
from ms_drake.planning.cartesian import approach_pose
from ms_drake.planning.sequences import jaw_opening
from ms_drake.types import Grasp


def _hull_part(shape, X_BG: np.ndarray):
    """(coal convex, 4x4 pose in the body frame, bounding radius) of a Convex / Mesh shape's
    convex hull, its vertices centred so that the bounding sphere is tight."""
    mesh = shape.GetConvexHull()
    hull = trimesh.convex.convex_hull(np.array([mesh.vertex(i) for i in range(mesh.num_vertices())]))  # triangulated
    v = np.asarray(hull.vertices, float)
    c = v.mean(axis=0)
    T = np.eye(4)
    T[:3, 3] = c
    return coal_convex(v - c, hull.faces), X_BG @ T, float(np.max(np.linalg.norm(v - c, axis=1)))


def _tool_part(shape, X_BG: np.ndarray):
    """(coal shape, 4x4 pose in the body frame, bounding radius) of a tool's Box / Cylinder, or of
    a Convex / Mesh shape's hull."""
    if isinstance(shape, Box):
        return coal.Box(shape.width(), shape.depth(), shape.height()), X_BG, 0.5 * float(np.linalg.norm(shape.size()))
    if isinstance(shape, Cylinder):
        r, L = shape.radius(), shape.length()
        return coal.Cylinder(r, L), X_BG, float(np.hypot(r, L / 2))
    if isinstance(shape, (Convex, Mesh)):
        return _hull_part(shape, X_BG)
    raise ValueError(f"ArmLinks: tool shape of type {type(shape).__name__}; Box, Cylinder, Convex and Mesh are supported")


def _part_hits(part, shape, transform, margin: float) -> bool:
    """Whether an arm part (coal shape, 3x3 rotation, centre, radius) comes within `margin` of one
    scene shape at its coal transform."""
    request = coal.CollisionRequest()
    request.security_margin = float(margin)
    return coal.collide(part[0], coal.Transform3s(part[1], part[2]), shape, transform, request, coal.CollisionResult())


class ArmLinks:
    """The collision geometry of one arm's links (the bodies its joints move, convex hulls in
    coal) and of its tool (the bodies welded to the last link) on the IK plant, placed at arm
    configurations as planner parts."""

    def __init__(self, ik, diagram):
        plant = ik.plant
        sg = next(s for s in diagram.GetSystems() if isinstance(s, SceneGraph))
        inspector = sg.model_inspector()
        self.ik = ik
        self.parts = []  # (body, coal shape, X_BG 4x4, radius)
        self.plant = plant
        for joint in ik.joints:
            body = joint.child_body()
            for gid in plant.GetCollisionGeometriesForBody(body):
                shape = inspector.GetShape(gid)
                if not isinstance(shape, (Convex, Mesh)):
                    raise ValueError(f"ArmLinks: link {body.name()!r} has a collision shape of type "
                                     f"{type(shape).__name__}; only Convex / Mesh links are supported")
                X_BG = inspector.GetPoseInFrame(gid).GetAsMatrix4()
                self.parts.append((body, *_hull_part(shape, X_BG)))
        last = ik.joints[-1].child_body()
        welded = [b for b in plant.GetBodiesWeldedTo(last) if b.index() != last.index()]
        # the tool: the gripper models welded to the last link, with their moving parts (a jaw's
        # fingers, at the opening the IK context holds: wide open, as the pick's transit runs)
        tools = {b.model_instance() for b in welded} - {last.model_instance()}
        bodies = welded + [plant.get_body(i) for m in sorted(tools) for i in plant.GetBodyIndices(m)
                           if plant.get_body(i) not in welded]
        self.tool_parts = [(body, *_tool_part(inspector.GetShape(gid), inspector.GetPoseInFrame(gid).GetAsMatrix4()))
                           for body in bodies for gid in plant.GetCollisionGeometriesForBody(body)]

    def names(self, tool: bool = False) -> list[str]:
        """The body name of each part `at` returns, in its order."""
        return [b.name() for b, *_ in self.parts + (self.tool_parts if tool else [])]

    def at(self, q_arm, tool: bool = False) -> list:
        """[(coal shape, 3x3 rotation, world centre, radius)] of the links (and the tool) at arm
        configuration q_arm."""
        plant, ctx = self.ik.plant, self.ik.context
        old = plant.GetPositions(ctx).copy()
        q = old.copy()
        q[self.ik.idx] = q_arm
        plant.SetPositions(ctx, q)
        out = []
        for body, shape, X_BG, r in self.parts + (self.tool_parts if tool else []):
            X = plant.EvalBodyPoseInWorld(ctx, body).GetAsMatrix4() @ X_BG
            out.append((shape, X[:3, :3], X[:3, 3].copy(), r))
        plant.SetPositions(ctx, old)  # the IK solves with the other joints at the context's values
        return out


class PickReach:
    """reach(grasp[, scene]) -> True when the robot of `scenario` plans a pick of it from park
    (the FullBackend's arms, park configurations and pick settings) and, given a scene
    (ms_drake.grasping.indexed.Scene), its arm's links stay clear of the scene along the approach
    (module docstring). `checks` counts the calls, `reached` the grasps found reachable and
    `arm_blocked` those whose plan exists but whose arm runs into the scene.

    The plan is the backend's own, with the same IK (park first, then its fixed restarts; an IK
    solve does not depend on the solves before it), so a grasp reached here is one the backend
    plans. Of the grasp's pick plans (its arm postures, at most `max_postures`) the first whose arm
    clears the scene is taken: the call then returns the grasp with that plan's number
    (Grasp.posture), which the backend executes."""

    checks_scene = True  # IndexedGraspPlanner passes its Scene

    def __init__(self, scenario, seed: int = 0, approach_samples: int = 5, transit_step: float = 0.02,
                 transit_clearance: float = 0.02, descent_clearance: float = PICK_APPROACH.descent_clearance,
                 max_postures: int = 4):
        self.backend = FullBackend(scenario, {}, Workspace.from_scenario(scenario), seed=seed)
        self.links = {arm: ArmLinks(ik, keep[0])
                      for (arm, (ik, _, _)), keep in zip(self.backend.ik.items(), self.backend._keep)}
        self.approach_samples = int(approach_samples)
        if not transit_step > 0 or not transit_clearance >= 0 or not descent_clearance >= 0:
            raise ValueError(f"PickReach: transit_step={transit_step} s must be > 0 (e.g. 0.02), "
                             f"transit_clearance={transit_clearance} m and descent_clearance={descent_clearance} m "
                             f">= 0 (e.g. 0.02 and 0.005)")
        self.transit_step, self.transit_clearance = float(transit_step), float(transit_clearance)
        self.descent_clearance = float(descent_clearance)
        if int(max_postures) < 1:
            raise ValueError(f"PickReach: max_postures must be >= 1 pick plan per grasp, got {max_postures!r}")
        self.max_postures = int(max_postures)
        self.checks = self.reached = self.arm_blocked = 0

    def plan(self, grasp: Grasp):
        """The backend's pick plan of the grasp from park (FullBackend.plan_grasp), or the string
        "no_<kind>_gripper"."""
        return self.backend.plan_grasp(grasp)

    def choose(self, grasp: Grasp, scene=None):
        """(plan, posture, hit): of the grasp's pick plans from park (FullBackend.pick_plans, at
        most `max_postures`), the first whose arm stays clear of the scene, its number and "";
        when none does, the first plan, 0 and what of its arm hits the scene (arm_hit). The plan
        is the string "no_<kind>_gripper" when the robot has none, a failed plan when none plans."""
        plans = self.backend.pick_plans(grasp)
        if isinstance(plans, str):
            return plans, 0, ""
        first, first_hit = None, ""
        try:
            for k, plan in enumerate(plans):
                if not plan.success:
                    return plan, 0, ""
                hit = self.arm_hit(plan, scene) if scene is not None else ""
                if not hit:
                    return plan, k, ""
                if first is None:
                    first, first_hit = plan, hit
                if k + 1 >= self.max_postures:
                    break
        finally:
            plans.close()
        return first, 0, first_hit

    def status(self, grasp: Grasp) -> str:
        """"ok", the IK status of the failing step, or "no_<kind>_gripper"."""
        plan = self.plan(grasp)
        return plan if isinstance(plan, str) else plan.status

    def _segments(self, plan):
        """(where, times, with the tool, clearance) of the plan's checked stretches (module
        docstring), the transit's low end first."""
        tl = plan.timeline
        t0, t1 = tl.marks["approach"], tl.marks["contact"]
        td = tl.marks.get("descent", t0)

        def times(a, b):
            return np.linspace(a, b, max(2, int(np.ceil((b - a) / self.transit_step)) + 1))
        approach = np.linspace(t0, t1, self.approach_samples)
        return (("descent", times(td, t0)[::-1], True, self.descent_clearance) if td < t0 else None,
                ("transit", times(0.0, td)[::-1], True, self.transit_clearance),
                ("approach", approach[:-1], True, 0.0),
                ("approach", approach[-1:], False, 0.0))

    def arm_hit(self, plan, scene) -> str:
        """What of the arm hits the scene along the plan (module docstring): "transit:<body>><j>",
        "descent:<body>><j>" or "approach:<body>><j>" (the first found; j: the index of the scene
        part it hits), or "" when nothing does."""
        links = self.links[plan.arm]
        ik = self.backend.ik[plan.arm][0]
        with jaw_opening(ik, plan.opening):
            for seg in self._segments(plan):
                if seg is None:
                    continue
                where, times, tool, clearance = seg
                for t in times:
                    parts = links.at(plan.timeline.value(t), tool=tool)
                    if not scene.hits(parts, clearance):
                        continue
                    for name, part in zip(links.names(tool), parts):
                        if scene.hits([part], clearance):
                            j = next(j for j in range(len(scene.shapes))
                                     if _part_hits(part, scene.shapes[j], scene.transforms[j], clearance))
                            return f"{where}:{name}>{j}"
        return ""

    def arm_hits(self, plan, scene) -> bool:
        """True when the plan's arm (links, tool) hits the scene somewhere along it (arm_hit)."""
        return bool(self.arm_hit(plan, scene))

    def diagnose(self, grasp: Grasp, scene=None) -> dict:
        """Why the robot does or does not execute the grasp: {"reason", "step", "detail"}.
        reason: "ok"; "no_gripper"; "unreachable" (no arm configuration puts the tool at the
        step's pose, joint limits ignored: out of the arm's workspace); "joint_limits" (one
        exists, but not within the joint limits); "collision" (the IK's configurations come closer
        than its min_distance to the bin or the robot itself; detail: the closest pair of bodies);
        "arm_hits_scene" (a plan exists; the arm's links or its tool hit the objects: detail
        "<stretch>:<body>"). step: "pre_grasp" or "approach_or_lift" (the failing IK step), or the
        stretch of an arm_hits_scene ("transit", "descent", "approach"); "" when ok."""
        plan, _, hit = self.choose(grasp, scene)
        if isinstance(plan, str):
            return {"reason": "no_gripper", "step": "", "detail": plan}
        if plan.success:
            return {"reason": "arm_hits_scene", "step": hit.split(":", 1)[0],
                    "detail": hit} if hit else {"reason": "ok", "step": "", "detail": ""}
        b = self.backend
        arm = (b.jaw if grasp.kind == "parallel_jaw" else b.suction)[0]
        ik, _, q_home = b.ik[arm]
        axis_only = grasp.kind != "parallel_jaw"
        X = grasp_tool_pose(grasp)
        poses = [X] if axis_only else [X, X @ RigidTransform(RotationMatrix.MakeZRotation(np.pi))]
        with jaw_opening(ik, pick_opening(grasp) if grasp.kind == "parallel_jaw" else None):
            pre = [ik.solve(approach_pose(P, PICK_APPROACH.distance), q_seed=q_home, axis_only=axis_only) for P in poses]
            if any(r.success for r in pre):  # the straight approach or the lift fails
                r = next(r for r in pre if r.success)
                step = "approach_or_lift"
                status = plan.status
            else:
                step, status = "pre_grasp", pre[0].status
                r = pre[0]
            if status == "collision":
                return {"reason": "collision", "step": step, "detail": self._closest_pair(ik, r.q)}
        free = any(self._solves_without_limits(ik, approach_pose(P, PICK_APPROACH.distance) if step == "pre_grasp" else P, q_home,
                                               axis_only) for P in poses)
        return {"reason": "joint_limits" if free else "unreachable", "step": step, "detail": status}

    @staticmethod
    def _solves_without_limits(ik, X_WT, q_seed, axis_only: bool) -> bool:
        """Whether some arm configuration (joint limits ignored, no collision check) puts the tool
        at X_WT, from q_seed and from 4 seeds spread over [-pi, pi]."""
        plant, ctx = ik.plant, ik.context
        q_now = plant.GetPositions(ctx).copy()
        others = np.setdiff1d(np.arange(plant.num_positions()), ik.idx)
        rng = np.random.default_rng(0)
        for seed in [np.asarray(q_seed, float)] + [rng.uniform(-np.pi, np.pi, len(ik.idx)) for _ in range(4)]:
            prog_ik = InverseKinematics(plant, ctx, with_joint_limits=False)
            prog, q = prog_ik.get_mutable_prog(), prog_ik.q()
            if len(others):
                prog.AddBoundingBoxConstraint(q_now[others], q_now[others], q[others])
            p = X_WT.translation()
            tol = ik.pos_tol / np.sqrt(3)
            prog_ik.AddPositionConstraint(ik.frame, np.zeros(3), plant.world_frame(), p - tol, p + tol)
            if axis_only:
                prog_ik.AddAngleBetweenVectorsConstraint(ik.frame, [0, 0, 1], plant.world_frame(),
                                                         X_WT.rotation().matrix()[:, 2], 0.0, ik.ang_tol)
            else:
                prog_ik.AddOrientationConstraint(ik.frame, RotationMatrix(), plant.world_frame(), X_WT.rotation(),
                                                 ik.ang_tol)
            q0 = q_now.copy()
            q0[ik.idx] = seed
            res = Solve(prog, q0)
            if res.is_success():
                return True
        return False

    @staticmethod
    def _closest_pair(ik, q_arm) -> str:
        """"<body> - <body>" of the closest pair of collision geometries at arm configuration q_arm."""
        plant, ctx = ik.plant, ik.context
        old = plant.GetPositions(ctx).copy()
        q = old.copy()
        q[ik.idx] = q_arm
        plant.SetPositions(ctx, q)
        try:
            query = plant.get_geometry_query_input_port().Eval(ctx)
            pairs = query.ComputeSignedDistancePairwiseClosestPoints(ik.influence + 0.05)
            if not pairs:
                return ""
            p = min(pairs, key=lambda p: p.distance)
            insp = query.inspector()

            def body(g):
                return plant.GetBodyFromFrameId(insp.GetFrameId(g)).name()
            return f"{body(p.id_A)} - {body(p.id_B)} ({1000 * p.distance:.0f} mm)"
        finally:
            plant.SetPositions(ctx, old)

    def __call__(self, grasp: Grasp, scene=None):
        """False when the robot does not execute the grasp; else True, or the grasp with the
        posture (Grasp.posture) whose arm clears the scene when it is not the first plan."""
        self.checks += 1
        plan, posture, hit = self.choose(grasp, scene)
        ok = not isinstance(plan, str) and plan.success and not hit
        self.arm_blocked += bool(hit)
        self.reached += ok
        if ok and posture != grasp.posture:
            return dataclasses.replace(grasp, posture=posture)
        return ok
