"""The two execution fidelities (docs/concepts.md) behind one ActionExecutor.

PrimitiveBackend (floating gripper, large benchmarks):
  grasp  grasp_outcome "draw" (default): success with probability = the grasp's robust
         contact-model quality (Grasp.quality from the GraspPlanner), drawn from (seed, step);
         "threshold": success exactly when the quality is >= LIFT_THRESHOLD, a deterministic
         outcome as the reference's X-Ray simulation decides "whether it would result in the
         object being lifted" (lines 1504-1507; a failed grasp leaves the state unchanged, and the
         same state gives the same outcome); "checked": the same deterministic lift, and the search
         attempts only grasps that pass it (its selector's grasp threshold is LIFT_THRESHOLD: the
         lift check decides which grasps exist as well as their outcome, so no attempted grasp
         fails); "nominal": success exactly when the nominal (unperturbed) contact model lifts the
         object with the grasp (Grasp.lifts, set by the image GraspPlanner): the reference's
         quasi-static wrench-space lift check of the executed grasp, while the selector still
         ranks grasps by their robust quality (and, as the same state gives the same verdict,
         does not attempt a failed grasp again on it: SelectorParams.retry_failed). A successful grasp lifts the object out of
         the scene (the executor announces it on `removed`, the rollout driver moves it away) and
         the rest settle by simulation for `settle` s; the diagram's execution.ObjectCarrier takes the
  lifted object to a drop-off tray. The gripper does not enter the heap (the
         reference's simulation experiments do the same: a grasp is an evaluated primitive).
  push   the closed jaw moves along the push segment in simulation: park -> above the start
         (travel height above the walls) -> down to the start -> along the segment -> up -> park,
         each leg a smooth (cosine) profile at `travel_speed` / `push_speed` (the two transfers
         between park and above the segment, in free space above the walls, at `transfer_speed`
         when given); then `settle` s.
FullBackend (YuMi, Panda, floating gripper): IK + ruckig through ms_drake.planning.sequences
  (plan_pick / plan_push) from the arm's current configuration; parallel-jaw grasps and pushes on
  the arm with the jaw (compliant pads), suction grasps on the arm with the suction cup; a grasp
  succeeds when the object rose by more than half the lift; then the arm carries it to the
  nearest drop-off tray it reaches (station.environments.dropoff_points): straight up to the carry
  height over the walls, over the tray at that height, down; releases it there, in physics, and
  returns to park (out of the camera view).
Both: after an action, every object (other than the grasped one) that left the bin (fell over a
wall, or below the floor) is reported; the target among them sets message "target_removed".
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from ms_drake.execution.executor import ExecutionError, Motion
from ms_drake.geometry import as_rigid_transform
from ms_drake.planning import ik_pose, plan_cartesian_line, plan_joint_motion
from ms_drake.planning.sequences import Schedule, arm_ik, nearest_equivalent, nth_plan, pick_plans, plan_push
from ms_drake.robots import CLOSING_FORCE, GRIPPERS, ParallelJawConfig
from ms_drake.scenario import resolve_robot_config
from ms_drake.station.environments import dropoff_points
from ms_drake.types import Action, ActionOutcome, object_of

FIDELITIES = ("primitive", "full")
# PrimitiveBackend's grasp outcomes (module docstring).
GRASP_OUTCOMES = ("draw", "threshold", "checked", "nominal")
# "threshold": lifted when at least half of the quality's perturbed trials lift the object (our
# reading of a deterministic lift check on a robust quality).
LIFT_THRESHOLD = 0.5
# The plant step at which the primitive push agrees with the YuMi's [s]. At 10 ms (7 ms too) the
# compliant contact between the floating jaw and a pushed object launches it: a box pushed 7.5 cm
# along x ends 3.3 cm to the side, turned 98 degrees, pushed along the diagonal it flies 23 cm
# (slower pushes at 10 ms do no better, nor did the "similar" and "sap" contact approximations in
# a trial); at 6, 5 and 2 ms it moves as on the YuMi (6.6 cm straight; 7.2 cm along the
# diagonal, turned 13-20 degrees; docs/results/ch4_pushing.md). The push study and the search's
# pushing selectors simulate at this step; the other selectors keep 10 ms (they never push).
PRIMITIVE_PUSH_TIME_STEP = 0.005


def _smooth(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    return a + (b - a) * (0.5 - 0.5 * np.cos(np.pi * min(max(s, 0.0), 1.0)))


class _Path:
    """Piecewise smooth interpolation through waypoints with given leg durations (immutable)."""

    def __init__(self, points, durations):
        self.points = [np.asarray(p, float) for p in points]
        self.t = np.concatenate([[0.0], np.cumsum(durations)])

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def __call__(self, t):
        k = int(np.searchsorted(self.t, t, side="right") - 1)
        if k >= len(self.points) - 1:
            return self.points[-1]
        dt = self.t[k + 1] - self.t[k]
        return _smooth(self.points[k], self.points[k + 1], (t - self.t[k]) / dt if dt > 0 else 1.0)


class _Base:
    """objects: {id: body index}; workspace: the bin (perception.segmentation.Workspace)."""

    def __init__(self, objects: dict, workspace, target_id: str = "", seed: int = 0, settle: float = 0.5):
        self.objects = dict(objects)
        self.workspace = workspace
        self.target_id = target_id
        self.seed = int(seed)
        self.settle = float(settle)

    def left_bin(self, poses, removed=(), exclude=()) -> list[str]:
        """Ids of objects (not yet removed) outside the bin: beyond a wall or below the floor.
        poses: the plant's body poses by body index (RigidTransforms or 4x4 arrays), or None."""
        if poses is None:
            return []
        ws = self.workspace
        out = []
        for oid, b in self.objects.items():
            if oid in removed or oid in exclude:
                continue
            p = as_rigid_transform(poses[b], f"poses[{b}]").translation()
            if p[2] < ws.floor_z - 0.03 or not ws.inside_xy(p, margin=-0.02):
                out.append(oid)
        return out

    def _finish(self, action: Action, success: bool, grasped: str, poses, removed, message: str = ""):
        others = self.left_bin(poses, removed, exclude=(grasped,))
        removed_object = grasped if success else ""
        if self.target_id and self.target_id in others:
            message, removed_object = "target_removed", removed_object or self.target_id
        elif not removed_object and others:
            removed_object = others[0]
        return ActionOutcome(action, bool(success), removed_object, message), tuple(others)


class PrimitiveBackend(_Base):
    """The floating gripper (FloatingGripperBin). tcp_offset: the tcp's z in the gripper body frame
    (`tcp_offset_of(plant)`); the body points down (roll = pi). A grasp's outcome is decided on the
    object its mask names (`types.object_of`: any piece of a cut object lifts the object); a grasp
    on a mask that names no object (a piece of bin) lifts nothing (message ``no_object``)."""

    def __init__(self, objects: dict, workspace, tcp_offset: float, target_id: str = "", seed: int = 0,
                 settle: float = 0.5, travel_speed: float = 0.5, push_speed: float = 0.15,
                 travel_height: float = 0.10, push_force: float = 40.0, transfer_speed: float | None = None,
                 grasp_outcome: str = "draw"):
        super().__init__(objects, workspace, target_id, seed, settle)
        if grasp_outcome not in GRASP_OUTCOMES:
            raise ExecutionError(f"grasp_outcome {grasp_outcome!r} unknown; choose one of {', '.join(GRASP_OUTCOMES)}")
        self.grasp_outcome = grasp_outcome
        self.tcp_offset = float(tcp_offset)
        self.travel_speed, self.push_speed = float(travel_speed), float(push_speed)
        self.transfer_speed = self.travel_speed if transfer_speed is None else float(transfer_speed)
        if self.transfer_speed <= 0:
            raise ValueError(f"transfer_speed must be > 0 m/s, got {transfer_speed}")
        self.travel_z = workspace.floor_z + workspace.wall_height + float(travel_height)
        cx, cy = workspace.center_xy
        # Parked beside the bin, out of the overhead camera's view (our choice).
        self.park = np.array([cx + 0.5 * workspace.size_xy[0] + 0.35, cy, self.travel_z + self.tcp_offset,
                              np.pi, 0.0, 0.0])
        self.push_force = float(push_force)

    def initial_commands(self) -> dict:
        return {"floating.position": self.park, "floating_jaw.position": [0.0],
                "floating_jaw.force_limit": [self.push_force]}

    def _q(self, tcp, yaw):
        """Floating-base positions putting the tcp at `tcp` with the tool pointing down and the
        jaw's world yaw `yaw` (R_WG = Rz(yaw) Rx(pi), FullBackend's push pose). The base's chain
        is R_WG = Rx(roll) Ry(pitch) Rz(q_yaw) (floating_gripper_positions), and
        Rx(pi) Rz(q) = Rz(-q) Rx(pi): the yaw joint is commanded -yaw, folded into (-pi/2, pi/2]
        (the closed jaw is symmetric under a half turn about the tool axis)."""
        q_yaw = -float(yaw)
        q_yaw = q_yaw - np.pi * np.ceil((q_yaw - 0.5 * np.pi) / np.pi)
        return np.array([tcp[0], tcp[1], tcp[2] + self.tcp_offset, np.pi, 0.0, q_yaw])

    def plan(self, action: Action, hold: dict, step: int, poses=None):
        if action.kind == "grasp":
            if action.grasp is None:
                raise ExecutionError("a grasp Action without its Grasp")
            return Motion({}, check_time=0.0, duration=self.settle, info={"step": step}, settle_from=0.0)
        if action.kind == "push":
            if action.push is None:
                raise ExecutionError("a push Action without its Push")
            a, b = np.asarray(action.push.start, float), np.asarray(action.push.end, float)
            d = b - a
            yaw = float(np.arctan2(d[1], d[0])) + np.pi / 2  # the closed jaws' broad side leads
            park = np.asarray(hold["floating.position"], float)
            wp = [park, self._q([a[0], a[1], self.travel_z], yaw), self._q(a, yaw), self._q(b, yaw),
                  self._q([b[0], b[1], self.travel_z], yaw), self.park]
            speeds = [self.transfer_speed, self.travel_speed, self.push_speed, self.travel_speed, self.transfer_speed]
            dur = [max(np.linalg.norm(wp[i + 1][:3] - wp[i][:3]) / v, 0.15) for i, v in enumerate(speeds)]
            path = _Path(wp, dur)
            return Motion({"floating.position": path}, check_time=path.duration + self.settle,
                          duration=path.duration + self.settle, info={"step": step}, settle_from=path.duration)
        raise ExecutionError(f"the primitive executor cannot execute an Action of kind {action.kind!r}")

    def outcome(self, action: Action, motion: Motion, poses, step: int, removed):
        if action.kind == "grasp":
            oid = object_of(action.grasp.object_id)
            if oid not in self.objects:  # a mask on no object (mostly bin): the cup or jaw lifts nothing
                return self._finish(action, False, "", poses, removed, "no_object")
            if self.grasp_outcome in ("threshold", "checked"):
                ok = float(action.grasp.quality) >= LIFT_THRESHOLD
            elif self.grasp_outcome == "nominal":
                if action.grasp.lifts is None:
                    raise ExecutionError(f"grasp outcome 'nominal' needs the grasp's nominal lift verdict (Grasp.lifts), "
                                         f"but the grasp on {action.grasp.object_id!r} (model {action.grasp.model!r}) "
                                         "has none: plan grasps with the image GraspPlanner (grasp_planner='image')")
                ok = bool(action.grasp.lifts)
            else:
                ok = bool(np.random.default_rng([self.seed, step, 4242]).random() < float(action.grasp.quality))
            return self._finish(action, ok, oid, poses, removed, "" if ok else "grasp_failed")
        return self._finish(action, True, "", poses, removed)


def tcp_offset_of(plant, gripper_model: str = "floating_jaw") -> float:
    """z of the tcp frame in its gripper body frame (the floating gripper's tool length)."""
    inst = plant.GetModelInstanceByName(gripper_model)
    f = plant.GetFrameByName("tcp", inst)
    return float(f.GetFixedPoseInBodyFrame().translation()[2])


def grasp_tool_pose(grasp) -> RigidTransform:
    """The tool pose of a Grasp: tcp at the centre, z along the approach, x along the jaw axis
    (suction: x = the world x made perpendicular to the approach)."""
    z = np.asarray(grasp.approach, float)
    z /= np.linalg.norm(z)
    x = np.asarray(grasp.axis, float)
    if grasp.kind != "parallel_jaw" or np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x - z * np.dot(x, z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return RigidTransform(RotationMatrix(R), np.asarray(grasp.center, float))


JAW = ParallelJawConfig()  # the stations' jaw (models/grippers/parallel_jaw.sdf)
JAW_OPENING = JAW.max_opening  # m, the jaw's opening at park and after a release
VIA_CLEARANCE = 0.25  # m over the bin's walls: the move from park to a grasp passes this high above it


def pick_opening(grasp) -> float:
    """The opening [m between the pads] the jaw comes down to a grasp with: the grasp's width (the
    planners' jaw opening: the contacts' distance and a margin each side, the opening the grasp
    planner checked the fingers at), at most JAW_OPENING; JAW_OPENING when the width is unknown (0)."""
    w = float(grasp.width)
    return min(JAW_OPENING, w) if w > 0 else JAW_OPENING


class FullBackend(_Base):
    """Any arm-and-gripper station (YuMiBin, PandaBin, FloatingGripperBin in full fidelity): IK +
    ruckig plans (ms_drake.planning.sequences) from the arm's current configuration, executed
    through the station's drivers. Parallel-jaw grasps and pushes go to the first arm carrying a
    parallel jaw, suction grasps to the first arm carrying a suction cup (`grasp_kinds` says which
    the robot can do). A grasp succeeds when the object rose by more than half the lift (needs
    body_poses; on hardware, without them, every grasp reports "not_lifted"); then the arm moves
    above the nearest drop-off tray it reaches (straight up to `via_z`, over the tray at that height,
    down to `drop_height` above the tray's floor, tool down),
    the gripper releases, and the arm returns to its park configuration out of the camera's view:
    ArmSpec.home for arms, beside the bin for the floating gripper. A station without trays (or
    none the arm reaches) releases the object at the top of the lift.
    scenario: the station's scenario (its robot, grippers and environment; objects are ignored).
    grip_force: the jaw's force limit while it grips [N]; by default the closing force the jaw
    grasp models score with (robots.CLOSING_FORCE), so the station executes a grasp
    with the force its quality assumed. via_clearance: the move from park to a grasp passes above
    its pre-grasp pose, this high over the bin's walls [m] (plan_pick's via_z)."""

    def __init__(self, scenario, objects: dict, workspace, target_id: str = "", seed: int = 0, settle: float = 0.5,
                 lift: float = 0.15, speed: float = 0.25, close_time: float = 0.5, hold_time: float = 0.3,
                 park_distance: float = 0.35, park_height: float = 0.10, grip_force: float = CLOSING_FORCE,
                 drop_height: float = 0.25, via_clearance: float = VIA_CLEARANCE):
        super().__init__(objects, workspace, target_id, seed, settle)
        if not scenario.robot.name:
            raise ExecutionError("full fidelity needs a robot: the scenario has none (robot.name is empty); "
                                 "use YuMiBin, PandaBin or FloatingGripperBin")
        chosen, _ = resolve_robot_config(scenario.robot)
        by_kind = {}
        for arm, gripper, port in chosen:
            by_kind.setdefault(GRIPPERS[gripper].kind, (arm, port))
        self.jaw = by_kind.get("parallel_jaw")  # (arm, gripper port) or None
        self.suction = by_kind.get("suction")
        if self.jaw is None and self.suction is None:
            raise ExecutionError(f"robot {scenario.robot.name!r} carries no parallel jaw or suction cup "
                                 f"(grippers: {', '.join(g for _, g, _ in chosen)}); a bin search needs one")
        self.lift, self.speed, self.close_time, self.hold_time = lift, speed, close_time, hold_time
        # The move from park to a grasp passes above its pre-grasp pose at this height: over the
        # walls and the heap, not through them.
        self.via_z = workspace.floor_z + workspace.wall_height + via_clearance
        if grip_force <= 0:
            raise ExecutionError(f"grip_force must be > 0 N, got {grip_force}")
        self.grip_force = float(grip_force)
        self.ik, self._keep = {}, []
        for arm in dict.fromkeys(tool[0] for tool in (self.jaw, self.suction) if tool is not None):
            ik, limits, q_home, keep = arm_ik(scenario, arm, seed=seed)
            if scenario.robot.name == "floating":  # park beside the bin, tool down, above the walls
                cx, cy = workspace.center_xy
                X_park = RigidTransform(RotationMatrix.MakeXRotation(np.pi),
                                        [cx + 0.5 * workspace.size_xy[0] + park_distance, cy,
                                         workspace.floor_z + workspace.wall_height + park_height])
                q_home = ik.solve(X_park, q_home).q
            self.ik[arm] = (ik, limits, np.asarray(q_home, float))
            self._keep.append(keep)
        # Each arm's drop-off configurations, nearest tray first: (tool down above the tray at the
        # carry height, and `drop_height` above its floor); the carry comes over the tray high and
        # then down, so a held object does not sweep across the bin's walls.
        self.drops = {}
        for arm, (ik, _, q_home) in self.ik.items():
            p_tool = ik_pose(ik, q_home).translation()
            qs = []
            for tray in sorted(dropoff_points(scenario.environment), key=lambda d: np.linalg.norm(d[:2] - p_tool[:2])):
                down = RotationMatrix.MakeXRotation(np.pi)
                high = ik.solve(RigidTransform(down, [tray[0], tray[1], max(self.via_z, tray[2] + drop_height)]), q_home)
                if not high.success:
                    continue
                q_high = nearest_equivalent(ik, high.q, q_home)
                low = ik.solve(RigidTransform(down, tray + np.array([0.0, 0.0, drop_height])), q_high)
                if low.success:
                    qs.append((q_high, nearest_equivalent(ik, low.q, q_high)))
            self.drops[arm] = qs

    @property
    def grasp_kinds(self) -> tuple[str, ...]:
        """The grasp kinds this robot executes ("parallel_jaw", "suction")."""
        return tuple(k for k, g in (("parallel_jaw", self.jaw), ("suction", self.suction)) if g is not None)

    def pick_plans(self, g, q_now=None):
        """Each pick plan of grasp g in turn (ms_drake.planning.sequences.pick_plans) by the arm
        carrying its gripper kind, from arm configuration q_now (default: park): the jaw comes down
        opened to pick_opening(g); the string "no_<kind>_gripper" when the robot has none."""
        tool = self.jaw if g.kind == "parallel_jaw" else self.suction
        if tool is None:
            return f"no_{g.kind}_gripper"
        arm, port = tool
        ik, limits, q_home = self.ik[arm]
        opening = pick_opening(g) if g.kind == "parallel_jaw" else JAW_OPENING
        return pick_plans(ik, limits, q_home if q_now is None else q_now, grasp_tool_pose(g), arm, port, g.kind,
                          lift=self.lift, speed=self.speed, close_time=self.close_time, hold_time=self.hold_time,
                          force_limit=self.grip_force, max_opening=opening, via_z=self.via_z)

    def plan_grasp(self, g, q_now=None):
        """The pick plan of grasp g (pick_plans): its plan number g.posture (the first when there
        are fewer), or the failed plan when none plans; "no_<kind>_gripper" when the robot has none."""
        plans = self.pick_plans(g, q_now)
        return plans if isinstance(plans, str) else nth_plan(plans, g.posture)

    def initial_commands(self) -> dict:
        out = {f"{arm}.position": q_home for arm, (_, _, q_home) in self.ik.items()}
        if self.jaw is not None:
            out.update({f"{self.jaw[1]}.position": [JAW_OPENING], f"{self.jaw[1]}.force_limit": [self.grip_force]})
        if self.suction is not None:
            out[f"{self.suction[1]}.suction"] = [0.0]
        return out

    def _finish_motion(self, plan, arm, release: dict, info: dict, drop: bool = False):
        """The plan's motion, then (drop) straight up to the carry height and to the arm's drop-off
        configuration; release; back to park."""
        ik, limits, q_home = self.ik[arm]
        tl = plan.timeline
        check = release_at = tl.duration
        if drop and self.drops.get(arm):
            rise = self._rise(ik, tl.final(), limits)
            if rise is not None:
                tl.play(rise)
            tl.play(plan_joint_motion([tl.final(), *self.drops[arm][0]], limits))
            release_at = tl.duration
            tl.hold(0.4)  # the gripper opens, the object falls into the tray
        tl.play(plan_joint_motion([tl.final(), q_home], limits))  # back to park, out of the camera's view
        commands = {f"{arm}.position": tl.value}
        for port, schedule in plan.commands.items():
            steps = list(schedule.steps) + [(release_at + 0.05, v) for p, v in release.items() if p == port]
            commands[port] = Schedule(steps)
        return Motion(commands, check_time=check, duration=tl.duration + self.settle, info=info,
                      settle_from=tl.duration)

    def _rise(self, ik, q, limits):
        """The tool's straight line up from arm configuration q to the carry height `via_z` (None
        when it is there already or the arm cannot follow the line): a held object leaves the bin
        upwards before the joint motion to the tray, which would sweep it low over the walls."""
        X = ik_pose(ik, q)
        up = self.via_z - X.translation()[2]
        if up < 0.01:
            return None
        line = plan_cartesian_line(ik, X, [0.0, 0.0, up], q, limits, max_speed=self.speed)
        return line.trajectory if line.success else None

    def plan(self, action: Action, hold: dict, step: int, poses=None):
        if action.kind == "grasp":
            g = action.grasp
            if g is None:
                raise ExecutionError("a grasp Action without its Grasp")
            tool = self.jaw if g.kind == "parallel_jaw" else self.suction
            if tool is None:
                return f"no_{g.kind}_gripper"
            arm, port = tool
            plan = self.plan_grasp(g, np.asarray(hold[f"{arm}.position"], float))
            if not plan.success:
                return plan.status
            b = self.objects.get(object_of(g.object_id))
            z0 = as_rigid_transform(poses[b], f"poses[{b}]").translation()[2] if poses is not None and b is not None \
                else None
            release = {f"{port}.position": [JAW_OPENING]} if g.kind == "parallel_jaw" else {f"{port}.suction": [0.0]}
            return self._finish_motion(plan, arm, release, {"z0": z0, "step": step}, drop=True)
        if action.kind == "push":
            if action.push is None:
                raise ExecutionError("a push Action without its Push")
            if self.jaw is None:
                return "no_parallel_jaw_gripper"
            arm, jaw = self.jaw
            p = action.push
            a, b = np.asarray(p.start, float), np.asarray(p.end, float)
            d = b - a
            yaw = float(np.arctan2(d[1], d[0])) + np.pi / 2
            ik, limits, _ = self.ik[arm]
            q_now = np.asarray(hold[f"{arm}.position"], float)
            # Straight back up to 5 cm above the walls after the push: the joint motion back to park,
            # which does not avoid collisions, starts above the bin (one from 5 cm above the push
            # can drag objects and catch on the walls).
            ws = self.workspace
            clear = max(0.05, ws.floor_z + ws.wall_height + 0.05 - float(a[2]))
            # The closed jaw is symmetric under a half turn about the tool axis: either yaw pushes
            # with the broad side; the second is tried when the arm cannot plan the first.
            plans = []
            for y in (yaw, yaw + np.pi):
                R = RotationMatrix.MakeZRotation(y) @ RotationMatrix.MakeXRotation(np.pi)
                plans.append(plan_push(ik, limits, q_now, RigidTransform(R, a), d, float(np.linalg.norm(d)), arm,
                                       retreat=clear, speed=min(self.speed, 0.1)))
                if plans[-1].success:
                    break
            plan = plans[-1]
            if not plan.success:
                return plans[0].status
            close = Schedule()
            close.set(0.0, 0.0)
            plan.commands[f"{jaw}.position"] = close
            return self._finish_motion(plan, arm, {f"{jaw}.position": [JAW_OPENING]}, {"step": step})
        raise ExecutionError(f"the full executor cannot execute an Action of kind {action.kind!r}")

    def outcome(self, action: Action, motion: Motion, poses, step: int, removed):
        if action.kind == "grasp":
            oid = object_of(action.grasp.object_id)
            z0 = motion.info.get("z0")
            b = self.objects.get(oid)
            ok = (poses is not None and z0 is not None and b is not None
                  and as_rigid_transform(poses[b], f"poses[{b}]").translation()[2] - z0 > 0.5 * self.lift)
            return self._finish(action, ok, oid, poses, removed, "" if ok else "not_lifted")
        return self._finish(action, True, "", poses, removed)
