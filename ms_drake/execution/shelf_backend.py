"""ShelfBackend: the shelf actions of Ch. 9.2 (ShelfAction) on the Fetch with the bluction tool
(FetchShelf), planned with the project's IK + ruckig (ms_drake.planning) and executed through the
station's drivers (`fetch.position`, `fetch_bluction.position` = blade angle, `fetch_bluction.suction`)
by the same ActionExecutor as the bin backends (`plan(action, hold, step, poses)` -> Motion,
`outcome(...)`, `initial_commands()`).

Frames: the shelf frame S of ms_drake.shelf_geometry (x across the opening, y into the shelf, z up,
floor at 0, open front at y = -Y/2), placed at the environment's position. The tool is level and
points into the shelf (its z along +y), its body y up, so the blade hangs down at blade angle 0 and
stands up at pi (TOOL_ROTATION, as the fetch_push / fetch_suction pick tasks).

push (O, dx): blade down. The blade's centre (frame `blade_tcp`) goes beside O's trailing side at
  the height BLADE_Z, with the 3 cm shaft just clear of O (`shaft_clearance`), along O's front part as
  in FOSS (its front edge at O's front face). Park -> staging (in front of the shelf, `staging`
  m before the front plane) by a joint motion -> straight in along +y -> straight along x by |dx|
  plus the gap between the blade and O (so O itself moves |dx|) -> hold -> back off 5 mm along x
  -> straight out along -y -> park.
suction (O, dx, dy): blade up. The cup (frame `tcp`) on O's front face (its front-most point for a
  cylinder) at x = O.x, 2 cm below O's top; park -> staging -> straight in -> vacuum on 0.1 s
  before contact, hold -> lift (FOSS's rule: at least 2 cm, and 1 cm over every object of the
  sweeps to and from the front; `suction_lift`; plus O's depth times sin(SAG_DEG), as the held
  object hangs tilted on the cup, its back lower) -> pull out until O's back is 2 cm in front of
  the shelf -> translate dx along x -> push in until O's front face is dy behind the front plane ->
  lower onto the floor (3 mm into it: the cup gives) -> vacuum off, hold -> straight out -> park.
park: the tool level and pointing into the shelf, its tip 15 cm in front of the shelf's front plane
  at its floor's height (PARK_TIP; IK from PARK_SEED), the torso at 0.26 m, near
  the work poses' heights (the torso is slow: 0.1 m/s), the arm in the branch from which the
  most shelf actions plan (measured over sampled scenes): outside
  the front camera's view, which sees the shelf from above the robot, 30 degrees down (the
  reference's Fetch also parks the tool out of view before each image).

Reach (`feasible`, what the shelf controller's selector asks of every candidate before choosing
it): the plan above from the park pose in the scene, as the executor would make it (IK within the
joint limits and >= 5 mm from the shelf and the robot itself at every pose and every 2 cm of the
straight lines), and then that plan's whole path checked every `check_step` seconds
(`path_clear`): the Fetch's links and the tool (blade up or down as the action holds it) at least
`clearance` from every other occluder on the shelf (the object acted on is the tool's to touch;
the target is unknown to the robot; an object whose centre is off the shelf's floor has fallen off
it), the object held by the cup (from contact to release) clear of
the other occluders, and the joint motions from park and back clear of the shelf and of the robot
itself. The straight lines' IK knows only the shelf, so a shaft that sweeps over a neighbour
beside or in front of a pushed object, or a blade lowered into a narrow gap, is found here.

The scene an action is planned in: the objects observed in body_poses (simulation: the backend
knows the shelf bodies), or else the scene the action was chosen in (Action.scene: the controller's
estimate from the depth image, on the hardware station or a simulated one used as hardware).

Outcome (after the motion and the settle): the scene observed from body_poses (`observe`: each
object's footprint centre, its footprint from its rotated extents, toppled when tilted by more
than 20 degrees) against FOSS's prediction for the scene observed when the action was planned
(Foss.step on the full scene, the target included). The action is "successful" (executed, the
selector may move on) when the object moved by at least half the commanded displacement; the
message records whether physics and FOSS agree: `agree=1` when FOSS accepted the action, the moved
object's footprint centre ended within `tolerance` (2 cm) of FOSS's, no other object moved by more
than `tolerance`, and the action toppled nothing (`agree=0` otherwise), followed by the measured
errors (`toppled=`: every object lying toppled after the action). Without body_poses (or shelf
bodies) the outcome is "executed", `agree=nan`.
"""

from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np
from pydrake.math import RigidTransform, RotationMatrix

from ms_drake.execution.executor import ExecutionError, Motion
from ms_drake.execution.reach import ArmLinks
from ms_drake.foss import Foss, shelf_action
from ms_drake.geometry import as_rigid_transform
from ms_drake.grasping.indexed import Scene
from ms_drake.planning import ik_pose, plan_cartesian_line, plan_joint_motion
from ms_drake.planning.sequences import Schedule, Timeline, arm_ik, nearest_equivalent
from ms_drake.robots import BluctionConfig, gripper_port_name
from ms_drake.shelf_geometry import ShelfGeometry
from ms_drake.types import Action, ActionOutcome, ShelfObject, ShelfScene

#: Tool level, pointing into the shelf (+y), body y up: the blade hangs down at angle 0.
TOOL_ROTATION = RotationMatrix(np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]))
BLADE_DOWN, BLADE_UP = 0.0, 3.14159  # the blade joint's limits are [0, 3.14159265]
#: The tool tip when parked, shelf frame: centred, 15 cm in front of the shelf's front plane, at its
#: floor's height (out of the front camera's view; module docstring).
PARK_TIP = (0.0, -0.15, 0.0)
#: The Fetch's arm joints the park IK starts from (torso 0.26 m; the branch from which the most
#: shelf actions plan).
PARK_SEED = (0.26, 1.6, 1.0, -0.16, 1.95, -1.63, 1.4, -0.18)
TOPPLE_DEGREES = 20.0
#: The tilt [deg] of a held object on the suction cup's compliant lip (its back lower than its
#: front) that the suction lift allows for (ms_drake.station.suction: a face held by the cup turns
#: about the loaded lip point until the moment is carried). Boxes with up to ~0.15 N m about the
#: cup tilt 1-8 degrees and hang clear; heavier ones, near the cup's limit (0.44-0.6 N m: 18-23
#: degrees hanging free, where the far lip leaks), rest their back edge on the floor while pulled
#: and placed, the floor carrying part of the weight (single suction actions on the Fetch,
#: 2026-12-02, commit 51e2fb0): a 16 x 19 x 14 cm box of 0.66 kg is placed with 12 degrees and falls with 20.
SAG_DEG = 12.0


@dataclass(frozen=True)
class ShelfBody:
    """A shelf object of the station: its plant body index and its dimensions (a ShelfObject whose
    x, y are where it was loaded)."""

    body_index: int
    shape: ShelfObject


def observe(poses, bodies: dict, origin, target_id: str = "") -> tuple[ShelfScene, tuple[str, ...]]:
    """The shelf scene in body_poses `poses` (list by body index of RigidTransforms / 4x4 arrays):
    (ShelfScene of the objects (the target as scene.target), ids of toppled objects). bodies:
    {object id: ShelfBody}. A tilted object's footprint is its rotated bounding box (a box)."""
    origin = np.asarray(origin, float)
    objs, target, toppled = [], None, []
    for oid, b in bodies.items():
        X = as_rigid_transform(poses[b.body_index], f"poses[{b.body_index}]")
        p = X.translation() - origin
        R = X.rotation().matrix()
        s = b.shape
        tilt = np.degrees(np.arccos(np.clip(R[2, 2], -1.0, 1.0)))
        if tilt > TOPPLE_DEGREES:
            toppled.append(oid)
            half = np.abs(R) @ (0.5 * np.array([s.width, s.depth, s.height]))
            o = ShelfObject(oid, "box", float(p[0]), float(p[1]), float(2 * half[0]), float(2 * half[1]),
                            float(2 * half[2]))
        else:
            o = s.moved(float(p[0]), float(p[1]))
        if oid == target_id:
            target = o
        else:
            objs.append(o)
    return ShelfScene(tuple(objs), target), tuple(toppled)


class ShelfBackend:
    """The Fetch's shelf actions (module docstring).

    scenario: a shelf scenario with the Fetch and the bluction tool (FetchShelf); bodies: {object
    id: ShelfBody} of the station's shelf objects (the target among them under `target_id`; empty:
    plan from each Action's scene, as on hardware); foss:
    the FOSS whose predictions the outcomes are compared with (default: the scenario's geometry).
    speed / push_speed / slow_speed: the tool's Cartesian speed limits [m/s] in free space, while
    pushing, and for the suction cup's contact, pull and placement lines; settle: the longest wait after a
    motion [s] (the executor ends it earlier once the scene is at rest); tolerance: the agreement
    tolerance [m] (module docstring); clearance [m] / check_step [s]: the reach check's least distance
    of the robot to the other occluders and its sampling of the planned path (`path_clear`)."""

    def __init__(self, scenario, bodies: dict, target_id: str = "", foss: Foss | None = None, seed: int = 0,
                 speed: float = 0.35, push_speed: float = 0.12, slow_speed: float = 0.15, settle: float = 1.0,
                 tolerance: float = 0.02,
                 staging: float = 0.08, shaft_clearance: float = 0.004, blade_z: float = 0.006,
                 line_step: float = 0.02, max_pull: float = 0.06, sag_deg: float = SAG_DEG,
                 clearance: float = 0.002, check_step: float = 0.02):
        if scenario.environment.type != "shelf" or scenario.robot.name != "fetch":
            raise ExecutionError(f"ShelfBackend drives the Fetch at a shelf (scenario FetchShelf); this scenario has "
                                 f"robot {scenario.robot.name!r} and environment {scenario.environment.type!r}")
        grippers = list(scenario.robot.grippers) or ["bluction"]
        if grippers[0] != "bluction":
            raise ExecutionError(f"ShelfBackend needs the bluction tool on the Fetch; robot.grippers is {grippers!r}: "
                                 "use [bluction]")
        self.arm = "fetch"
        self.tool = gripper_port_name(self.arm, "bluction")  # fetch_bluction
        self.bodies = dict(bodies)
        if target_id and target_id not in self.bodies:
            raise ExecutionError(f"target_id {target_id!r} is not one of the shelf bodies ({', '.join(self.bodies)})")
        self.target_id = target_id
        self.origin = np.asarray(scenario.environment.position, float)
        size = np.asarray(scenario.environment.resolved_size(), float)
        self.half = 0.5 * size
        self.foss = foss or Foss(ShelfGeometry.from_scenario(scenario))
        self.seed = int(seed)
        self.speed, self.push_speed, self.settle = float(speed), float(push_speed), float(settle)
        self.slow_speed = float(slow_speed)
        if min(self.speed, self.push_speed, self.slow_speed) <= 0:
            raise ExecutionError(f"ShelfBackend speeds must be > 0 m/s: speed={speed}, push_speed={push_speed}, "
                                 f"slow_speed={slow_speed}")
        self.tolerance, self.staging = float(tolerance), float(staging)
        self.shaft_clearance, self.line_step = float(shaft_clearance), float(line_step)
        self.max_pull = float(max_pull)
        if not 0.0 <= sag_deg < 45.0:
            raise ExecutionError(f"ShelfBackend sag_deg={sag_deg!r}: give the held object's tilt on the cup in degrees, "
                                 f"0 <= sag_deg < 45 (default {SAG_DEG})")
        self.sag_deg = float(sag_deg)
        if not (clearance >= 0 and check_step > 0):
            raise ExecutionError(f"ShelfBackend clearance={clearance!r} m must be >= 0 and check_step={check_step!r} s "
                                 "> 0 (defaults 0.002 m, 0.02 s)")
        self.clearance, self.check_step = float(clearance), float(check_step)
        self.cfg = BluctionConfig()
        self.r_shaft = self.cfg.shaft_diameter / 2
        self.blade_z = float(blade_z) + self.cfg.blade_height / 2  # blade centre above the floor
        # Tip of the tool ahead of the frames: the cup lip (tcp) is the tip; the blade's centre is
        # blade_offset back from the shaft's end, which is cup_height behind the lip.
        self.blade_to_tip = self.cfg.blade_offset + self.cfg.cup_height
        self.cup_ik, limits, q_home, keep_cup = arm_ik(scenario, self.arm, frame="tcp", seed=seed)
        self.blade_ik, _, _, keep_blade = arm_ik(scenario, self.arm, frame="blade_tcp", seed=seed)
        self._keep = (keep_cup, keep_blade)
        self.limits = limits
        self._set_blade(self.cup_ik, BLADE_UP)  # suction IK with the blade up, push IK with it down
        park = self.world([PARK_TIP[0], -self.half[1] + PARK_TIP[1], PARK_TIP[2]])
        q_seed = np.array(PARK_SEED, float)
        res = self.cup_ik.solve(RigidTransform(TOOL_ROTATION, park), q_seed)
        if not res.success:
            raise ExecutionError(f"the Fetch cannot reach its park pose (tool tip at {np.round(park, 3).tolist()}): "
                                 f"IK {res.status}; check the scenario's robot.base_position")
        self.q_park = nearest_equivalent(self.cup_ik, res.q, q_seed)
        self._feasible: dict = {}
        self._links: dict = {}  # "push" / "suction" -> ArmLinks (blade down / up), built on first use

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _set_blade(ik, angle: float):
        plant, ctx = ik.plant, ik.context
        q = plant.GetPositions(ctx)
        q[plant.GetJointByName("blade_joint").position_start()] = angle
        plant.SetPositions(ctx, q)

    def world(self, p_shelf) -> np.ndarray:
        return self.origin + np.asarray(p_shelf, float)

    def initial_commands(self) -> dict:
        return {f"{self.arm}.position": self.q_park, f"{self.tool}.position": [BLADE_UP],
                f"{self.tool}.suction": [0.0]}

    def observe(self, poses) -> tuple[ShelfScene, tuple[str, ...]]:
        return observe(poses, self.bodies, self.origin, self.target_id)

    def _path(self, ik, q_start, points, speeds):
        """Straight tool lines through `points` (world, the first = the tool's pose at q_start)
        at `speeds`; (list of JointTrajectory, final q) or (status, None)."""
        trajs, q = [], np.asarray(q_start, float)
        for a, b, v in zip(points[:-1], points[1:], speeds):
            d = np.asarray(b, float) - np.asarray(a, float)
            if np.linalg.norm(d) < 1e-6:
                trajs.append(None)
                continue
            line = plan_cartesian_line(ik, ik_pose(ik, q), d, q, self.limits, step=self.line_step, max_speed=v)
            if not line.success:
                return line.status, None
            trajs.append(line.trajectory)
            q = line.trajectory.final()
        return trajs, q

    def _to(self, ik, p, q_seed):
        res = ik.solve(RigidTransform(TOOL_ROTATION, p), q_seed)
        if not res.success:
            return None, res.status
        return nearest_equivalent(ik, res.q, q_seed), "ok"

    # ------------------------------------------------------------------ planning
    def plan(self, action: Action, hold: dict, step: int, poses=None):
        a = shelf_action(action)
        if a is None:
            raise ExecutionError(f"ShelfBackend executes Actions of kind 'shelf' (with a ShelfAction), got "
                                 f"{action.kind!r}")
        if poses is not None and self.bodies:
            scene, toppled = self.observe(poses)
        elif action.scene is not None:
            scene, toppled = action.scene, ()
        else:
            raise ExecutionError("ShelfBackend plans from the objects' poses or from the scene the action was chosen in: "
                                 "connect the executor's body_poses input (simulation, with the shelf bodies) or give "
                                 "the Action its scene (Action.scene, as the shelf controller's selector does)")
        return self.plan_scene(a, np.asarray(hold[f"{self.arm}.position"], float), scene, step, toppled)

    def plan_scene(self, a, q_now, scene: ShelfScene, step: int = 0, toppled=()):
        """The Motion of ShelfAction `a` from arm joints q_now in `scene` (its objects' footprints;
        the target, if any, only for FOSS's prediction; `toppled`: ids of objects already toppled),
        or the planner's status string."""
        try:
            o = scene.object(a.object_id)
        except KeyError:
            return f"unknown_object:{a.object_id}"
        predicted, foss_out = self.foss.step(scene, a)
        q_now = np.asarray(q_now, float)
        if a.kind == "push":
            built = self._plan_push(o, a, q_now, scene)
        elif a.kind == "suction":
            lift = self.suction_lift(scene, o, self.foss.placement_center(o, a.dx, a.dy))
            built = self._plan_suction(o, a, q_now, lift, scene)
        else:
            raise ExecutionError(f"unknown shelf action kind {a.kind!r}: push or suction")
        if isinstance(built, str):
            return built
        tl, commands = built
        target_xy = (o.x + a.dx, o.y) if a.kind == "push" else self.foss.placement_center(o, a.dx, a.dy)
        info = {"step": step, "before": scene, "predicted": predicted, "foss": foss_out.message if not foss_out.success
                else "ok", "goal_xy": tuple(map(float, target_xy)), "start_xy": (o.x, o.y),
                "toppled_before": tuple(toppled), "timeline": tl}
        commands[f"{self.arm}.position"] = tl.value
        return Motion(commands, check_time=tl.duration + self.settle, duration=tl.duration + self.settle, info=info,
                      settle_from=tl.duration)

    def feasible(self, a, scene: ShelfScene) -> str:
        """"ok" when the Fetch can execute ShelfAction `a` from its park pose in `scene` (the
        planner's status otherwise). Cached by the action and the scene's footprints to 1 mm, so
        a scene observed again after an action re-plans only what changed."""
        footprints = tuple((b.id, round(b.x, 3), round(b.y, 3)) for b in scene.objects)
        if a.kind == "suction" and any(b.id == a.object_id for b in scene.objects):
            o = scene.object(a.object_id)
            lift = self.suction_lift(scene, o, self.foss.placement_center(o, a.dx, a.dy)) + self._sag(o)
            reach = self.pulls_out(o, lift, footprints)
            if reach != "ok":
                return reach
        key = (a.kind, a.object_id, round(a.dx, 3), round(a.dy, 3), footprints)
        if key not in self._feasible:
            m = self.plan_scene(a, self.q_park, scene)
            self._feasible[key] = m if isinstance(m, str) else self.path_clear(m, a, scene)
        return self._feasible[key]

    def path_clear(self, motion: Motion, a, scene: ShelfScene) -> str:
        """"ok" when the planned `motion` of ShelfAction `a` (plan_scene's) keeps the robot clear
        along its whole path (module docstring, "Reach"), sampled every check_step seconds;
        otherwise "collision:<phase>:<what>-<what>": "collision:transit:<body>-<occluder>" or
        "collision:path:<body>-<occluder>" (a robot or tool body; transit: the joint motions from
        park and back, path: the rest), "collision:held:<id>-<occluder>" (the object on the cup),
        "collision:transit:shelf_or_self" (a joint motion into the shelf or the robot itself)."""
        tl = motion.info["timeline"]
        links = self._arm_links(a.kind)
        ik = links.ik
        # an object whose centre is off the shelf's floor has fallen off it (its height is unknown)
        obstacles = _Obstacles([b for b in scene.objects if b.id != a.object_id and abs(b.x) <= self.half[0]
                                and abs(b.y) <= self.half[1]], self.origin)
        names = links.names(tool=True)
        if a.kind == "suction":
            # Carried as FOSS carries it: translated with the cup, upright (the tilt the cup's lip
            # lets it hang at is in the lift, SAG_DEG); shrunk by the IK's position tolerance on
            # every side, as FOSS's own sweeps pass the others at 0.5 mm.
            o = scene.object(a.object_id)
            grip, release = tl.marks["contact"], tl.marks["placed"]
            held_shape = _object_shape(o, shrink=ik.pos_tol)
            held_radius = 0.5 * float(np.linalg.norm([o.width, o.depth, o.height]))
            start = _object_pose(o, self.origin)[:3, 3]
            held_offset = start - ik_pose(ik, tl.value(grip)).translation()
            # what it touches where it stands is FOSS's to judge (the observed footprints of objects
            # standing turned about z can overlap)
            held_obstacles = _Obstacles([b for b in obstacles.objects
                                         if _Obstacles([b], self.origin).hit([(held_shape, np.eye(3), start,
                                                                                held_radius)]) is None], self.origin)
        transits = ((0.0, tl.marks["staged"]), (tl.marks["leave"], tl.duration))
        q_full = ik.plant.GetPositions(ik.context).copy()
        for t in np.append(np.arange(0.0, tl.duration, self.check_step), tl.duration):
            q = tl.value(t)
            in_transit = any(t0 <= t <= t1 for t0, t1 in transits)
            hit = obstacles.hit(links.at(q, tool=True), self.clearance)
            if hit is not None:
                return f"collision:{'transit' if in_transit else 'path'}:{names[hit[0]]}-{hit[1]}"
            if a.kind == "suction" and grip <= t <= release:
                centre = ik_pose(ik, q).translation() + held_offset
                hit = held_obstacles.hit([(held_shape, np.eye(3), centre, held_radius)], 0.0)
                if hit is not None:
                    return f"collision:held:{a.object_id}-{hit[1]}"
            if in_transit:
                q_full[ik.idx] = q
                if ik._min_distance(q_full) < 0.0:
                    return "collision:transit:shelf_or_self"
        return "ok"

    def _arm_links(self, kind: str) -> ArmLinks:
        """The Fetch's links and tool as placed by the IK plant of `kind`'s actions (the blade down
        for pushes, up for suction)."""
        if kind not in self._links:
            ik, keep = (self.blade_ik, self._keep[1]) if kind == "push" else (self.cup_ik, self._keep[0])
            self._links[kind] = ArmLinks(ik, keep[0])
        return self._links[kind]

    def pulls_out(self, o: ShelfObject, lift: float, footprints: tuple) -> str:
        """"ok" when the Fetch, from its park pose, reaches O's front face with the cup (the joint
        motion to the staging point, the line in), lifts it by `lift` (the held object's sag
        included) and pulls it out of the shelf: the start that every suction of O with that lift
        shares, whatever its placement, so one plan rules out all of them when it fails. The
        planner's status otherwise; cached by O, the lift and the scene's `footprints` (feasible's)."""
        key = ("pull", o.id, round(lift, 3), footprints)
        if key not in self._feasible:
            stage, touch = self._suction_approach(o)
            up = touch + [0.0, 0.0, lift]
            pulled = up + [0.0, self._pulled_y(o) - o.y, 0.0]
            tl = self._stage(self.cup_ik, self.q_park, stage)
            if isinstance(tl, str):
                self._feasible[key] = tl
            else:
                trajs, q = self._path(self.cup_ik, tl.final(), [stage, touch, up, pulled],
                                      [self.speed, self.slow_speed, self.speed])
                self._feasible[key] = trajs if q is None else "ok"
        return self._feasible[key]

    def _pulled_y(self, o: ShelfObject) -> float:
        """O's centre y when pulled out: its back 2 cm in front of the shelf, or as far as the Fetch
        reaches (the tool's tip `max_pull` in front of the front plane)."""
        return max(-self.half[1] - 0.02 - 0.5 * o.depth, -self.half[1] - self.max_pull + 0.002 + 0.5 * o.depth)

    def _sag(self, o: ShelfObject) -> float:
        """The held object hangs tilted on the cup's compliant lip, its back lower than its front:
        the lift grows by its depth times sin(sag) so that its back clears what FOSS's lift clears."""
        return float(o.depth * np.sin(np.deg2rad(self.sag_deg)))

    def _suction_approach(self, o: ShelfObject):
        """(staging point, contact point) of the cup for a suction of O, world frame: level with
        a point 2 cm below O's top, in front of the shelf and on O's front face."""
        z_cup = max(o.height - 0.02, self.r_shaft + 0.003)
        stage = self.world([o.x, -self.half[1] - self.staging, z_cup])
        touch = self.world([o.x, o.y - 0.5 * o.depth - 0.002, z_cup])
        return stage, touch

    def _finish(self, ik, tl: Timeline, q_out, out_point, last_point):
        """Leave the shelf straight along -y to the staging point, then the joint motion to park."""
        trajs, q = self._path(ik, q_out, [last_point, out_point], [self.speed])
        if q is None:
            return trajs
        for t in trajs:
            if t is not None:
                tl.play(t)
        tl.mark("leave")
        tl.play(plan_joint_motion([tl.final(), self.q_park], self.limits))
        return None

    def _stage(self, ik, q_now, staging_point):
        """The timeline from q_now to the staging configuration (joint motion); or a status."""
        q_stage, status = self._to(ik, staging_point, q_now)
        if q_stage is None:
            return status
        tl = Timeline(q_now)
        tl.hold(0.05)
        tl.play(plan_joint_motion([q_now, q_stage], self.limits))
        tl.mark("staged")
        return tl

    def _plan_push(self, o: ShelfObject, a, q_now, scene: ShelfScene):
        s = float(np.sign(a.dx))
        if s == 0:
            return "zero_push"
        ext_x = 0.5 * o.width
        front = o.y - 0.5 * o.depth
        y_blade = front + self.cfg.blade_width / 2
        shaft_down = self.blade_z + self.cfg.blade_height / 2 + self.r_shaft  # shaft axis, blade down
        if self.trailing_gap(scene, o, s) >= 2 * (self.r_shaft + self.shaft_clearance):
            # The shaft fits beside O: blade low, shaft beside O (its blade a little away from O).
            x_tool = o.x - s * (ext_x + self.r_shaft + self.shaft_clearance)
            z_blade = self.blade_z
            gap = self.r_shaft + self.shaft_clearance - self.cfg.blade_thickness / 2
        else:
            # The shaft passes over O: blade beside O, raised so the shaft clears O's top.
            gap = self.shaft_clearance
            x_tool = o.x - s * (ext_x + self.cfg.blade_thickness / 2 + gap)
            z_blade = self.blade_z + max(0.0, o.height + self.r_shaft + 0.008 - shaft_down)
        y_stage = -self.half[1] - self.staging - (self.blade_to_tip - self.cfg.blade_width / 2)
        ik = self.blade_ik
        stage = self.world([x_tool, y_stage, z_blade])
        start = self.world([x_tool, y_blade, z_blade])
        end = start + [s * (abs(a.dx) + gap), 0.0, 0.0]
        back = end - [s * 0.005, 0.0, 0.0]
        out = np.array([back[0], stage[1], back[2]])
        tl = self._stage(ik, q_now, stage)
        if isinstance(tl, str):
            return tl
        trajs, q = self._path(ik, tl.final(), [stage, start, end], [self.speed, self.push_speed])
        if q is None:
            return trajs
        tl.play(trajs[0])
        tl.mark("push")
        tl.play(trajs[1])
        tl.hold(0.15)
        tl.mark("pushed")
        trajs, q = self._path(ik, q, [end, back], [self.push_speed])
        if q is None:
            return trajs
        tl.play(trajs[0])
        err = self._finish(ik, tl, q, out, back)
        if err:
            return err
        blade = Schedule()
        blade.set(0.0, BLADE_DOWN)
        blade.set(tl.duration, BLADE_UP)  # up again once parked
        return tl, {f"{self.tool}.position": blade}

    def trailing_gap(self, scene: ShelfScene, o: ShelfObject, s: float) -> float:
        """Free width beside O's trailing side (pushing along s * x) over the blade's y range: to the
        wall and to the occluders there (the target, unknown to the robot, is not counted)."""
        ext = 0.5 * o.width
        gap = self.half[0] + s * o.x - ext
        front = o.y - 0.5 * o.depth
        y0, y1 = front, front + self.cfg.blade_width
        for b in scene.objects:
            if b.id == o.id or b.y + 0.5 * b.depth < y0 - 0.05 or b.y - 0.5 * b.depth > y1:
                continue  # the corridor from the front is FOSS's check; here: beside the blade and before it
            d = s * (o.x - b.x) - ext - 0.5 * b.width
            if d > -1e-9:
                gap = min(gap, d)
        return float(gap)

    def suction_lift(self, scene: ShelfScene, o: ShelfObject, goal_xy) -> float:
        """FOSS's lift (module docstring of ms_drake.foss): >= 2 cm, and 1 cm over every other occluder
        whose footprint meets O's sweeps between its place or its goal and the front."""
        p = self.foss.params
        lift = p.lift
        others = [b for b in scene.objects if b.id != o.id]  # the occluders: the robot does not know the target
        for x, y in ((o.x, o.y), goal_xy):
            for b in others:
                if abs(b.x - x) < 0.5 * (b.width + o.width) + p.sweep_clearance and b.y - 0.5 * b.depth < y:
                    lift = max(lift, b.height + p.lift_clearance)
        return float(min(lift, self.half[2] * 2 - p.top_clearance - o.height))

    def _plan_suction(self, o: ShelfObject, a, q_now, lift: float, scene: ShelfScene):
        stage, touch = self._suction_approach(o)
        z_cup = stage[2] - self.origin[2]
        goal_x, goal_y = self.foss.placement_center(o, a.dx, a.dy)
        y_out_obj = self._pulled_y(o)
        # Across at the pulled-out depth: over every occluder the sweep there meets.
        lift2 = lift
        x0, x1 = min(o.x, goal_x) - 0.5 * o.width, max(o.x, goal_x) + 0.5 * o.width
        for b in scene.objects:
            if b.id != o.id and b.x + 0.5 * b.width > x0 and b.x - 0.5 * b.width < x1 and \
                    b.y - 0.5 * b.depth < y_out_obj + 0.5 * o.depth and b.y + 0.5 * b.depth > y_out_obj - 0.5 * o.depth:
                lift2 = max(lift2, b.height + self.foss.params.lift_clearance)
        sag = self._sag(o)
        lift, lift2 = lift + sag, lift2 + sag
        if z_cup + lift2 + self.r_shaft + self.cfg.blade_height > 2 * self.half[2] - 0.005:
            return "shelf_top"  # the raised blade would hit the shelf's top
        ik = self.cup_ik
        up = touch + [0.0, 0.0, lift]
        pulled = up + [0.0, y_out_obj - o.y, 0.0]
        raised = pulled + [0.0, 0.0, lift2 - lift]
        moved = raised + [goal_x - o.x, 0.0, 0.0]
        pushed = moved + [0.0, goal_y - y_out_obj, 0.0]
        down = pushed - [0.0, 0.0, lift2 + 0.003]
        out = np.array([down[0], stage[1], down[2]])
        tl = self._stage(ik, q_now, stage)
        if isinstance(tl, str):
            return tl
        trajs, q = self._path(ik, tl.final(), [stage, touch], [self.speed])
        if q is None:
            return trajs
        tl.play(trajs[0])
        tl.mark("contact")
        tl.hold(0.25)
        trajs, q = self._path(ik, q, [touch, up, pulled, raised, moved, pushed, down],
                              [self.slow_speed, self.speed, self.slow_speed, self.speed, self.speed,
                               self.slow_speed])
        if q is None:
            return trajs
        for t in trajs:
            if t is not None:
                tl.play(t)
        tl.mark("placed")
        release = tl.duration
        tl.hold(0.25)
        err = self._finish(ik, tl, q, out, down)
        if err:
            return err
        vac = Schedule()
        vac.set(0.0, 0.0)
        vac.set(tl.marks["contact"] - 0.1, 1.0)
        vac.set(release, 0.0)
        blade = Schedule()
        blade.set(0.0, BLADE_UP)
        return tl, {f"{self.tool}.suction": vac, f"{self.tool}.position": blade}

    # ------------------------------------------------------------------ outcome
    def outcome(self, action: Action, motion: Motion, poses, step: int, removed):
        a = shelf_action(action)
        if poses is None or not self.bodies:
            # Nothing but the cameras sees the result: the action counts as executed; the next
            # observation shows where the objects are.
            return ActionOutcome(action, True, message="agree=nan executed (no body_poses)"), ()
        after, toppled = self.observe(poses)
        before = motion.info["before"]
        predicted = motion.info["predicted"]

        def xy(scene):
            objs = list(scene.objects) + ([scene.target] if scene.target is not None else [])
            return {b.id: np.array([b.x, b.y]) for b in objs}

        p0, p1, pf = xy(before), xy(after), xy(predicted)
        err = float(np.linalg.norm(p1[a.object_id] - pf[a.object_id]))
        others = max((float(np.linalg.norm(p1[k] - p0[k])) for k in p0 if k != a.object_id and k in p1), default=0.0)
        commanded = float(np.linalg.norm(np.asarray(motion.info["goal_xy"]) - np.asarray(motion.info["start_xy"])))
        moved = float(np.linalg.norm(p1[a.object_id] - p0[a.object_id]))
        foss_ok = motion.info["foss"] == "ok"
        new_toppled = set(toppled) - set(motion.info.get("toppled_before", ()))
        agree = foss_ok and err <= self.tolerance and others <= self.tolerance and not new_toppled
        ok = moved >= 0.5 * commanded
        msg = (f"agree={int(agree)} err={err:.3f} moved={moved:.3f} commanded={commanded:.3f} others={others:.3f} "
               f"toppled={','.join(toppled) or '-'} foss={motion.info['foss']}")
        return ActionOutcome(action, bool(ok), message=msg), ()


def _object_shape(o: ShelfObject, shrink: float = 0.0):
    """The coal shape of a shelf object (a box, or an upright cylinder), centred on its middle,
    `shrink` [m] smaller on every side."""
    if o.kind == "cylinder":
        return coal.Cylinder(0.5 * o.width - shrink, o.height - 2 * shrink)
    return coal.Box(o.width - 2 * shrink, o.depth - 2 * shrink, o.height - 2 * shrink)


def _object_pose(o: ShelfObject, origin) -> np.ndarray:
    """The world pose (4x4) of a shelf object's middle, standing on the floor of the shelf at `origin`."""
    X = np.eye(4)
    X[:3, 3] = np.asarray(origin, float) + [o.x, o.y, 0.5 * o.height]
    return X


class _Obstacles(Scene):
    """The occluders of a shelf scene as coal shapes (ms_drake.grasping.indexed.Scene), with
    `hit(parts, margin)`: (index of the first part that comes within `margin` of one, its id), or None."""

    def __init__(self, objects, origin):
        self.objects = list(objects)
        self.ids = [o.id for o in self.objects]
        objects = self.objects
        super().__init__([(_object_shape(o), _object_pose(o, origin), _object_pose(o, origin)[:3, 3],
                           0.5 * float(np.linalg.norm([o.width, o.depth, o.height]))) for o in objects])
        self._margin_request = {}

    def hit(self, parts: list, margin: float = 0.0):
        if not self.ids:
            return None
        if margin not in self._margin_request:
            request = coal.CollisionRequest()
            request.security_margin = float(margin)
            self._margin_request[margin] = request
        request = self._margin_request[margin]
        centres = np.array([p[2] for p in parts], float)
        reach = np.array([p[3] for p in parts], float)[:, None] + self.radii[None] + margin
        d2 = np.sum((centres[:, None, :] - self.centers[None]) ** 2, axis=2)
        for i, j in np.argwhere(d2 < reach * reach):  # bounding spheres first, in part order
            shape, R, c, _ = parts[i]
            if coal.collide(shape, coal.Transform3s(R, c), self.shapes[j], self.transforms[j], request,
                            coal.CollisionResult()):
                return int(i), self.ids[j]
        return None


def agreement(outcome: ActionOutcome) -> bool | None:
    """Whether physics and FOSS agreed on an executed shelf action (None: not recorded)."""
    for tok in outcome.message.split():
        if tok.startswith("agree="):
            return None if tok == "agree=nan" else tok == "agree=1"
    return None
