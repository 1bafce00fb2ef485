"""The rearrangement controller of Ch. 6.4 (lines 1078-1096) on the Panda, as one Drake Diagram
wired to the PandaTable station in three lines:

    station = builder.AddSystem(MakeStation(scenario))                 # or MakeStation(scenario, hardware=True)
    controller = builder.AddSystem(MakeRearrangementController(scenario, params, sim=...))
    connect_controller(builder, controller, station)

Inside, one LeafSystem (`RearrangementPlanner`) runs the reference's finite-state machine with its
five states, once per object, the objects in order:
  observe    the camera's depth image -> the scene cloud (world frame); the robot's points and the
             target's are found by the label image in simulation (the reference's ground-truth
             masks, `sim=RearrangeSimInfo`), by distance to the robot's own points (forward
             kinematics of the measured configuration) and Euclidean clusters without it (the
             hardware station); a jaw grasp on the target from the project's GraspPlanner (depth
             + the target's mask); its pre-grasp configuration by IK;
  pre-grasp  MPPI (ms_drake.planning.mppi) from the current configuration to the pre-grasp one,
             re-planned after each executed waypoint; the robot's links (points sampled on each
             link, ms_drake.planning.arm_model) checked against the scene cloud minus the robot by
             the SceneChecker of `params.method`; the robot against itself and the table by
             Drake's geometry (checked lazily, only where it decides the waypoint);
  grasp      preset: a straight approach along the tool axis, then the jaw closes;
  lift       preset: a straight lift; the jaw's measured opening says whether it holds something;
             the target's points (observed before the grasp) become the object in hand, fixed
             to the tool;
  place      placements sampled uniformly in the zone (a box on the table, `params.zone`), sorted
             by the scene's height there (lowest first); the first whose object-in-hand pose is
             collision-free (SceneChecker, the scene minus the robot and the target) and whose
             tool pose, and the pose `params.descent` above it, have IK solutions is the goal;
             MPPI to the pose above it with the object in hand checked too, then a preset straight
             descent (the object's last centimetres are next to the table, where a padded check
             would call every waypoint a collision);
  release    preset: the jaw opens, the tool retreats straight up, MPPI back to the home
             configuration, the robot's links checked against the scene as seen before the grasp
             without the target (the placed object is not in it: the tool leaves it upwards).
A failure (no grasp, no IK, MPPI blocked, nothing in the jaw, no placement) ends the attempt:
the arm returns home and the object is tried again, `params.attempts` times in all (the
reference gives two). Every motion is timed with ruckig (`plan_path_motion` along the executed
waypoints); the FSM's state is the Context's abstract state, updated every `params.period`.

`params.method`: a SceneChecker method (`net`, `pointnet_grid`, `coal_reconstruction`, `sdf`) or
`ik_line`: plain IK + a straight joint-space line to each goal, no collision checking (the
baseline without a collision checker).

Exported ports (the station's names): inputs <cam>.depth_image, panda.state_estimated,
panda_jaw.state_measured, and in simulation <cam>.label_image; outputs panda.position,
panda_jaw.position, panda_jaw.force_limit, plus status (RearrangeStatus) and history
(tuple[RearrangeOutcome]).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import BasicVector, Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.sensors import ImageDepth32F, ImageLabel16I
from scipy.spatial import cKDTree

from ms_drake.collision.baselines import clusters
from ms_drake.collision.checker import METHODS as CHECKER_METHODS
from ms_drake.collision.checker import SceneChecker
from ms_drake.execution.backends import grasp_tool_pose
from ms_drake.geometry import PinholeCamera
from ms_drake.grasping.planner import GraspPlanner
from ms_drake.perception.masks import object_labels
from ms_drake.planning import approach_pose, plan_cartesian_line, plan_path_motion
from ms_drake.planning.arm_model import ArmModel
from ms_drake.planning.mppi import MppiParams, mppi_step
from ms_drake.planning.sequences import arm_ik, nearest_equivalent
from ms_drake.policies.bin_search import ControllerError, connect_controller  # noqa: F401 (re-exported)
from ms_drake.types import InstanceMasks

METHODS = CHECKER_METHODS + ("ik_line",)
ARM, JAW = "panda", "panda_jaw"
OPEN, CLOSED = 0.10, 0.0


@dataclass(frozen=True)
class RearrangeParams:
    """Settings of the rearrangement controller.

    method: a SceneChecker method or "ik_line" (module doc); zone: (x_min, x_max, y_min, y_max) of
    the placement zone on the table [m, world]; trajectories / horizon / sigma / weighted: MPPI's
    T, H, per-joint standard deviation and update (the reference: 300, 40, sqrt(0.3), best
    waypoint); lazy: check the scene lazily (mppi_step's `lazy`; the same waypoints, fewer
    checks; the networks check every waypoint in one batch either way); max_steps: MPPI calls per
    motion before it counts as blocked; placements: candidates sampled in the zone; max_ik:
    IK solves tried on the collision-free candidates; approach / lift / retreat: the preset straight
    motions [m]; place_above: the object's bottom above the scene's height at the placement [m];
    min_move: placements at least this far (xy) from where the object was [m] (a different place);
    descent: MPPI brings the object this far above its placement, a preset straight line lowers it [m];
    attempts: tries per object; min_opening: the jaw's measured opening below which it holds
    nothing [m]; speed: Cartesian speed of the preset lines [m/s]; period: FSM update [s];
    camera: the station camera; points: points per robot link; padding: the robot's and the held
    object's points are pushed this far out from their centroid before checking [m] (a margin for
    the waypoints' spacing and the scene's unseen backs); seed: every random choice."""

    method: str = "coal_reconstruction"
    zone: list[float] = field(default_factory=lambda: [-0.35, 0.05, 0.05, 0.30])
    trajectories: int = 300
    horizon: int = 40
    sigma: float = float(np.sqrt(0.3))
    weighted: bool = False
    lazy: bool = True
    max_steps: int = 10
    placements: int = 200
    max_ik: int = 8
    approach: float = 0.10
    lift: float = 0.12
    retreat: float = 0.10
    place_above: float = 0.015
    min_move: float = 0.10
    descent: float = 0.06
    attempts: int = 2
    min_opening: float = 0.004
    force_limit: float = 40.0
    speed: float = 0.25
    close_time: float = 0.6
    open_time: float = 0.5
    period: float = 0.05
    camera: str = "front"
    points: int = 200
    padding: float = 0.01
    grasp_samples: int = 12
    seed: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ControllerError(f"rearrangement method {self.method!r} unknown; choose one of {', '.join(METHODS)}")
        z = tuple(float(v) for v in self.zone)
        if len(z) != 4 or not (z[0] < z[1] and z[2] < z[3]):
            raise ControllerError(f"zone must be (x_min, x_max, y_min, y_max) with min < max, got {self.zone!r}")
        for name in ("trajectories", "horizon", "max_steps", "placements", "max_ik", "attempts", "points"):
            if int(getattr(self, name)) < 1:
                raise ControllerError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if not self.period > 0 or self.sigma < 0:
            raise ControllerError(f"period must be > 0 and sigma >= 0, got {self.period!r}, {self.sigma!r}")

    def mppi(self) -> MppiParams:
        return MppiParams(int(self.trajectories), int(self.horizon), float(self.sigma), bool(self.weighted),
                          seed=int(self.seed))


@dataclass(frozen=True)
class RearrangeSimInfo:
    """What only a simulated station tells the controller: {render label: object id} of the objects,
    the render labels of the robot's and gripper's bodies, and the objects to move, in order."""

    labels: dict
    robot_labels: tuple
    targets: tuple

    def __post_init__(self):
        known = set(self.labels.values())
        missing = [t for t in self.targets if t not in known]
        if missing:
            raise ControllerError(f"RearrangeSimInfo: targets {missing} are not objects of the station "
                                  f"({', '.join(sorted(known)) or 'none'})")


@dataclass(frozen=True)
class RearrangeOutcome:
    """One attempt on one object: grasped / placed in the controller's view (the jaw held
    something; the object was released at a placement), why it ended, and its cost."""

    target: str
    attempt: int
    grasped: bool
    placed: bool
    status: str
    t_start: float
    t_end: float
    mppi_calls: int = 0
    plan_seconds: float = 0.0
    placement: tuple = ()


@dataclass(frozen=True)
class RearrangeStatus:
    phase: str = "observe"
    target: str = ""
    attempt: int = 0
    done: bool = False


@dataclass
class _Fsm:
    """The FSM's state (the Context's abstract state; copied shallowly: its arrays and checkers are
    never changed in place, each update makes a new _Fsm)."""

    phase: str = "observe"
    traj: object = None  # JointTrajectory being played
    t0: float = 0.0
    busy_until: float = 0.0
    q_cmd: np.ndarray | None = None
    jaw: float = OPEN
    target: str = ""
    attempt: int = 0
    tries: dict = field(default_factory=dict)  # target -> attempts made
    goal: np.ndarray | None = None
    after: str = ""  # the phase after the current MPPI motion
    steps: int = 0
    calls: int = 0
    plan_seconds: float = 0.0
    grasped: bool = False
    t_start: float = 0.0
    scene: np.ndarray | None = None  # scene cloud minus the robot (world)
    target_points: np.ndarray | None = None
    checker: object = None
    grasp_q: np.ndarray | None = None
    lines: dict = field(default_factory=dict)
    placement: tuple = ()
    history: tuple = ()
    done: bool = False

    def __deepcopy__(self, memo):
        return copy.copy(self)


# ------------------------------------------------------------------------------- perception
def cloud_from_depth(depth: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """(H, W, 3) world points of a depth image (NaN where there is no return)."""
    P_C = camera.deproject(np.asarray(depth, float).reshape(camera.height, camera.width))
    R, p = camera.X_WC.rotation().matrix(), camera.X_WC.translation()
    return P_C @ R.T + p


def segment_scene(P_W: np.ndarray, label: np.ndarray | None, sim: RearrangeSimInfo | None, robot_points=None,
                  table_top: float = 0.0, link: float = 0.012) -> np.ndarray:
    """(H, W) object id per pixel: "" for the table / no return, "robot" for the robot, else the
    object's id (sim: from the label image) or "cluster_k" (Euclidean clusters of the points above
    the table; `robot_points` (m, 3), the robot's own points at its measured configuration, claim
    the points within 2 cm as "robot")."""
    H, W, _ = P_W.shape
    out = np.full((H, W), "", dtype=object)
    valid = np.all(np.isfinite(P_W), axis=-1)
    if label is not None and sim is not None:
        lab = np.asarray(label).reshape(H, W)
        for value, oid in sim.labels.items():
            out[valid & (lab == value)] = oid
        out[valid & np.isin(lab, np.asarray(sim.robot_labels, int))] = "robot"
        return out
    above = valid & (P_W[..., 2] > table_top + 0.005)
    if robot_points is not None and len(robot_points):
        d, _ = cKDTree(robot_points).query(P_W[above], distance_upper_bound=0.02)
        rows, cols = np.nonzero(above)
        hit = np.isfinite(d)
        out[rows[hit], cols[hit]] = "robot"
        above[rows[hit], cols[hit]] = False
    rows, cols = np.nonzero(above)
    pts = P_W[rows, cols]
    ids = np.full(len(pts), -1)
    for k, c in enumerate(clusters(pts, link, min_points=30)):
        # clusters() returns point arrays: map them back through a tree of the points
        _, idx = cKDTree(pts).query(c)
        ids[idx] = k
    keep = ids >= 0
    out[rows[keep], cols[keep]] = np.array([f"cluster_{k}" for k in ids[keep]], dtype=object)
    return out


def downsample(points: np.ndarray, voxel: float = 0.005, limit: int = 20000, seed: int = 0) -> np.ndarray:
    """One point per `voxel` cube (the first), at most `limit` points (a seeded subset)."""
    if len(points) == 0:
        return points.reshape(0, 3)
    _, first = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_index=True)
    pts = points[np.sort(first)]
    if len(pts) > limit:
        pts = pts[np.random.default_rng(seed).choice(len(pts), limit, replace=False)]
    return pts


def pad(points: np.ndarray, margin: float) -> np.ndarray:
    """Points pushed `margin` further from their centroid (a point set grown by about `margin`)."""
    points = np.asarray(points, float)
    d = points - points.mean(axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return points + margin * d / np.maximum(n, 1e-9)


# ------------------------------------------------------------------------------- placements
def sample_placements(zone, scene: np.ndarray, held: np.ndarray, count: int, rng: np.random.Generator,
                      table_top: float = 0.0) -> np.ndarray:
    """(count, 3) placement points in the zone sorted by the scene's height there, lowest first:
    x, y uniform in the zone; z the highest scene point within the held object's footprint radius
    of (x, y) (the table top where there is none)."""
    x0, x1, y0, y1 = (float(v) for v in zone)
    xy = np.column_stack([rng.uniform(x0, x1, count), rng.uniform(y0, y1, count)])
    r = float(np.max(np.linalg.norm(held[:, :2] - held[:, :2].mean(axis=0), axis=1))) if len(held) else 0.03
    z = np.full(count, table_top)
    above = scene[scene[:, 2] > table_top + 0.003] if len(scene) else scene
    if len(above):
        tree = cKDTree(above[:, :2])
        for i, near in enumerate(tree.query_ball_point(xy, r)):
            if near:
                z[i] = max(table_top, float(above[near, 2].max()))
    order = np.argsort(z, kind="stable")
    return np.column_stack([xy, z])[order]


# ------------------------------------------------------------------------------- the FSM
class RearrangementPlanner(LeafSystem):
    """The FSM of the module doc. Inputs: ``depth_image`` (ImageDepth32F), ``label_image``
    (ImageLabel16I; simulation, optional), ``arm_state`` (14: q, v), ``jaw_state`` (2: opening,
    rate). Outputs: ``arm_position`` (7), ``jaw_position`` (1), ``jaw_force_limit`` (1), ``status``
    (RearrangeStatus), ``history`` (tuple[RearrangeOutcome])."""

    def __init__(self, scenario, params: RearrangeParams, sim: RearrangeSimInfo | None = None,
                 targets: int = 10, net=None):
        super().__init__()
        if params.camera not in scenario.cameras:
            raise ControllerError(f"camera {params.camera!r} is not a camera of the scenario "
                                  f"(cameras: {', '.join(scenario.cameras) or 'none'})")
        if scenario.robot.name != "panda":
            raise ControllerError(f"the rearrangement controller drives a Panda; the scenario's robot is "
                                  f"{scenario.robot.name!r} (use PandaTable)")
        self.params, self.sim, self.net = params, sim, net
        self.camera = PinholeCamera.from_config(scenario.cameras[params.camera])
        w, h = self.camera.width, self.camera.height
        # Ports first.
        self.depth_port = self.DeclareAbstractInputPort("depth_image", AbstractValue.Make(ImageDepth32F(w, h)))
        self.label_port = self.DeclareAbstractInputPort("label_image", AbstractValue.Make(ImageLabel16I(w, h)))
        self.arm_port = self.DeclareVectorInputPort("arm_state", 14)
        self.jaw_port = self.DeclareVectorInputPort("jaw_state", 2)
        self.ik, self.limits, self.q_home, self._keep = arm_ik(scenario, ARM, seed=params.seed)
        self.model = ArmModel(self.ik, points_per_body=params.points, seed=params.seed)
        # the base link turns about the vertical only, beside the table: not scene-checked
        self.scene_links = tuple(n for n in self.model.points if n != "panda_link1")
        self.X_body_tool = np.linalg.inv(self.model.link_poses(self.q_home[None])["body"][0]) @ \
            self.model.tool_pose(self.q_home)
        env = scenario.environment
        self.table_top = float(env.position[2])
        self.table_xy = np.asarray(env.position[:2], float)
        self.table_half = 0.5 * np.asarray(env.resolved_size()[:2], float)
        self.max_targets = int(targets)
        color, _ = scenario.cameras[params.camera].MakeCameras()
        self.grasps = GraspPlanner(color.core().intrinsics(), self.camera.X_WC, model="soft_point",
                                   num_samples=params.grasp_samples, seed=params.seed)
        init = _Fsm(q_cmd=self.q_home.copy())
        self._state = self.DeclareAbstractState(AbstractValue.Make(init))
        ticket = {self.abstract_state_ticket(self._state), self.time_ticket()}
        self.DeclareVectorOutputPort("arm_position", 7, self._calc_arm, prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort("jaw_position", 1, self._calc_jaw, prerequisites_of_calc=ticket)
        self.DeclareVectorOutputPort("jaw_force_limit", 1,
                                     lambda c, o: o.SetFromVector([params.force_limit]))
        self.DeclareAbstractOutputPort("status", lambda: AbstractValue.Make(RearrangeStatus()), self._calc_status,
                                       prerequisites_of_calc={self.abstract_state_ticket(self._state)})
        self.DeclareAbstractOutputPort("history", lambda: AbstractValue.Make(()), self._calc_history,
                                       prerequisites_of_calc={self.abstract_state_ticket(self._state)})
        self.DeclarePeriodicUnrestrictedUpdateEvent(params.period, 0.0, self._update)

    # ------------------------------------------------------------------ outputs
    def _fsm(self, context) -> _Fsm:
        return context.get_abstract_state(self._state).get_value()

    def _calc_arm(self, context, output: BasicVector):
        s = self._fsm(context)
        q = s.q_cmd if s.traj is None else s.traj.value(context.get_time() - s.t0)
        output.SetFromVector(np.asarray(q, float))

    def _calc_jaw(self, context, output: BasicVector):
        output.SetFromVector([self._fsm(context).jaw])

    def _calc_status(self, context, output):
        s = self._fsm(context)
        output.set_value(RearrangeStatus(s.phase, s.target, s.attempt, s.done))

    def _calc_history(self, context, output):
        output.set_value(self._fsm(context).history)

    # ------------------------------------------------------------------ helpers
    def _play(self, s: _Fsm, t: float, qs, hold: float = 0.0, speed: float | None = None, length=None) -> _Fsm:
        """s playing the joint path qs (ruckig along it) from time t, then holding `hold` s."""
        qs = np.asarray(qs, float)
        traj = plan_path_motion(qs, self.limits, length, max_speed=speed or 0.25) if len(qs) > 1 else None
        dur = traj.duration if traj is not None else 0.0
        return dataclasses.replace(s, traj=traj, t0=t, busy_until=t + dur + hold, q_cmd=qs[-1].copy())

    def _line(self, q, displacement):
        X = RigidTransform(self.model.tool_pose(q))
        plan = plan_cartesian_line(self.ik, X, displacement, q, self.limits, max_speed=self.params.speed)
        return plan

    def checker(self, scene: np.ndarray, held: np.ndarray | None = None):
        """A SceneChecker of params.method on `scene` with the robot's links (and the object in hand)."""
        c = SceneChecker(self.params.method, scene, net=self.net) if self.net is not None else \
            SceneChecker(self.params.method, scene)
        for name in self.scene_links:
            c.add(name, pad(self.model.points[name], self.params.padding))
        if held is not None:
            c.add("held", pad(held, self.params.padding))
        return c

    def scene_collides(self, checker, qs: np.ndarray, held: bool) -> np.ndarray:
        """(n,) bool: a robot link (or the object in hand) collides with the scene at configurations qs."""
        poses = self.model.link_poses(qs)
        hit = np.zeros(len(qs), bool)
        for name in self.scene_links:
            hit |= checker.collides(name, poses[name])
        if held:
            hit |= checker.collides("held", poses["body"] @ self.X_body_tool)
        return hit

    def _mppi(self, s: _Fsm, t: float) -> _Fsm:
        """One MPPI call of the current motion (or its end)."""
        q, goal = np.asarray(s.q_cmd, float), np.asarray(s.goal, float)
        if np.max(np.abs(q - goal)) < 1e-6:
            return dataclasses.replace(s, phase=s.after, traj=None, busy_until=t)
        p = self.params
        if p.method == "ik_line":
            return dataclasses.replace(self._play(s, t, [q, goal]), steps=s.steps + 1)
        if s.steps >= p.max_steps:
            return self._fail(s, t, f"mppi_blocked:{s.after}")
        held = s.phase == "place"
        if s.checker is None:  # no scene seen (a failed observation): the robot's own geometry only
            check = lambda qs: np.zeros(len(qs), bool)
        else:
            check = lambda qs: self.scene_collides(s.checker, qs, held)
        lazy_self = self.model.self_collides
        if p.lazy or p.method not in ("net", "pointnet_grid"):
            collides, lazy = None, (lambda qs: check(qs) | lazy_self(qs) if len(qs) else np.zeros(0, bool))
        else:
            collides, lazy = check, lazy_self
        rng = np.random.default_rng([p.seed, s.calls])
        start = time.process_time()
        best, info = mppi_step(q, goal, collides, self.ik.lower, self.ik.upper, p.mppi(), rng, lazy=lazy)
        s = dataclasses.replace(s, calls=s.calls + 1, steps=s.steps + 1,
                                plan_seconds=s.plan_seconds + time.process_time() - start)
        if best is None:
            return self._fail(s, t, f"mppi_no_free_waypoint:{s.after}")
        return self._play(s, t, np.vstack([q[None], info["path"]]))

    def _record(self, s: _Fsm, t: float, placed: bool, status: str) -> _Fsm:
        out = RearrangeOutcome(s.target, s.attempt, s.grasped, placed, status, s.t_start, t, s.calls,
                               s.plan_seconds, s.placement)
        return dataclasses.replace(s, history=s.history + (out,))

    def _fail(self, s: _Fsm, t: float, status: str) -> _Fsm:
        """End the attempt: record it, open the jaw, go home (straight up first when holding)."""
        s = self._record(s, t, False, status)
        s = dataclasses.replace(s, jaw=OPEN, grasped=False)
        return self._go_home(s, t, hold=self.params.open_time)

    def _go_home(self, s: _Fsm, t: float, hold: float = 0.0) -> _Fsm:
        q = np.asarray(s.q_cmd, float)
        up = self._line(q, [0, 0, self.params.retreat])
        path = up.trajectory if up.success else None
        qs = np.asarray(up.qs if up.success else [q], float)
        s = dataclasses.replace(s, phase="home", goal=self.q_home.copy(), after="observe", steps=0)
        if path is None:
            return dataclasses.replace(s, busy_until=t + hold)
        return self._play(s, t + hold, qs, speed=self.params.speed, length=self.params.retreat)

    def _observe(self, s: _Fsm, t: float, context) -> _Fsm:
        p = self.params
        depth = np.asarray(self.depth_port.Eval(context).data, float)[:, :, 0]
        label = None
        if self.sim is not None and self.label_port.HasValue(context):
            label = np.asarray(self.label_port.Eval(context).data)[:, :, 0]
        P_W = cloud_from_depth(depth, self.camera)
        robot = None
        if label is None:
            q_meas = self.arm_port.Eval(context)[:7]
            poses = self.model.link_poses(q_meas[None])
            robot = np.concatenate([self.model.points[n] @ poses[n][0, :3, :3].T + poses[n][0, :3, 3]
                                    for n in self.model.points])
        ids = segment_scene(P_W, label, self.sim, robot, self.table_top)
        # the target: the next object not done (sim: the given order; else the cluster of >= 100
        # points over the table, outside the zone, nearest the robot)
        tries = dict(s.tries)
        target = ""
        if self.sim is not None:
            visible = set(np.unique(ids[ids != ""]))
            target = next((o for o in self.sim.targets if tries.get(o, 0) < p.attempts and o in visible), "")
        else:
            x0, x1, y0, y1 = p.zone
            cands = []
            tx, ty = self.table_half
            for oid in np.unique(ids[(ids != "") & (ids != "robot")]):
                c = np.nanmean(P_W[ids == oid], axis=0)
                on_table = abs(c[0] - self.table_xy[0]) < tx and abs(c[1] - self.table_xy[1]) < ty
                if on_table and (ids == oid).sum() >= 100 and not (x0 <= c[0] <= x1 and y0 <= c[1] <= y1) \
                        and tries.get(oid, 0) < p.attempts:
                    cands.append((float(np.hypot(c[0] + 0.6, c[1])), oid))
            target = min(cands)[1] if cands else ""
        done_count = len({o.target for o in s.history})
        if not target or done_count >= self.max_targets and target not in tries:
            return dataclasses.replace(s, phase="done", done=True, busy_until=np.inf)
        attempt = tries.get(target, 0)
        tries[target] = attempt + 1
        scene_mask = (ids != "") & (ids != "robot") | (np.all(np.isfinite(P_W), axis=-1) & (ids == ""))
        scene = downsample(P_W[scene_mask & np.all(np.isfinite(P_W), axis=-1)], seed=p.seed)
        # crop to the table's neighbourhood (the room's floor and far walls are no obstacle)
        scene = scene[(scene[:, 2] > self.table_top - 0.02) & (scene[:, 2] < self.table_top + 1.0)]
        target_points = P_W[(ids == target) & np.all(np.isfinite(P_W), axis=-1)]
        s = dataclasses.replace(s, target=target, attempt=attempt, tries=tries, t_start=t, calls=0, plan_seconds=0.0,
                                grasped=False, placement=(), scene=scene, target_points=target_points, steps=0,
                                checker=None)
        start = time.process_time()
        masks = InstanceMasks((ids == target)[None], (target,), np.ones(1))
        grasps = self.grasps.plan(depth, masks, seed=p.seed * 1009 + attempt)
        if not grasps:
            return self._fail(s, t, "no_grasp")
        X_g = grasp_tool_pose(grasps[0]).GetAsMatrix4()
        s = dataclasses.replace(s, plan_seconds=s.plan_seconds + time.process_time() - start)
        plan = self._grasp_plan(X_g, s.q_cmd)
        s = dataclasses.replace(s, plan_seconds=s.plan_seconds + time.process_time() - start)
        if isinstance(plan, str):
            return self._fail(s, t, plan)
        q_pre, approach, lift = plan
        checker = None if p.method == "ik_line" else self.checker(scene)
        s = dataclasses.replace(s, lines={"approach": approach, "lift": lift}, grasp_q=approach[-1], checker=checker)
        return dataclasses.replace(s, phase="pregrasp", goal=q_pre, after="grasp", steps=0, busy_until=t)

    def _grasp_plan(self, X_g: np.ndarray, q_seed):
        """(q_pre, approach path, lift path) of a jaw grasp at the tool pose X_g (either jaw
        direction: the jaw is symmetric), or the IK status."""
        p = self.params
        status = "unreachable"
        for flip in (False, True):
            X = X_g.copy()
            if flip:
                X[:3, :2] = -X[:3, :2]  # half a turn about the tool axis
            pre = approach_pose(RigidTransform(X), p.approach)
            res = self.ik.solve(pre, q_seed=q_seed)
            if not res.success:
                status = res.status
                continue
            q_pre = nearest_equivalent(self.ik, res.q, q_seed)
            approach = plan_cartesian_line(self.ik, pre, p.approach * X[:3, 2], q_pre, self.limits,
                                           max_speed=p.speed)
            if not approach.success:
                status = f"approach_{approach.status}"
                continue
            lift = self._line(approach.qs[-1], [0, 0, p.lift])
            if not lift.success:
                status = f"lift_{lift.status}"
                continue
            return q_pre, approach.qs, lift.qs
        return status

    def _place_goal(self, s: _Fsm, held: np.ndarray):
        """(placement point, pre-place configuration `descent` above it, checker, the straight
        descent's joint path) or (None, status, None, None) (module doc)."""
        p = self.params
        scene = s.scene
        # the scene without the target's points (it is in the jaw)
        if len(s.target_points):
            d, _ = cKDTree(s.target_points).query(scene, distance_upper_bound=0.01)
            scene = scene[~np.isfinite(d)]
        if len(scene) < 10:
            scene = np.vstack([scene, [[0.0, 0.0, self.table_top]] * 10])
        checker = None if p.method == "ik_line" else self.checker(scene, held)
        rng = np.random.default_rng([p.seed, 7, s.attempt, len(s.history)])
        cands = sample_placements(p.zone, scene, held, p.placements, rng, self.table_top)
        if len(s.target_points):
            was = np.asarray(s.target_points, float)[:, :2].mean(axis=0)
            cands = cands[np.linalg.norm(cands[:, :2] - was, axis=1) >= p.min_move]
        X_grasp = self.model.tool_pose(s.grasp_q)
        R = X_grasp[:3, :3]
        held_W = held @ R.T  # the object's points in world orientation, tool at the origin
        bottom = float(held_W[:, 2].min())
        centre = held_W[:, :2].mean(axis=0)
        poses = np.tile(np.eye(4), (len(cands), 1, 1))
        poses[:, :3, :3] = R
        poses[:, :2, 3] = cands[:, :2] - centre
        poses[:, 2, 3] = cands[:, 2] - bottom + p.place_above
        free = np.ones(len(cands), bool) if checker is None else ~checker.collides("held", poses)
        for i in np.nonzero(free)[0][:p.max_ik]:
            above = poses[i].copy()
            above[2, 3] += p.descent
            res = self.ik.solve(RigidTransform(above), q_seed=s.q_cmd)
            if not res.success:
                continue
            q_above = nearest_equivalent(self.ik, res.q, s.q_cmd)
            down = plan_cartesian_line(self.ik, RigidTransform(above), [0, 0, -p.descent], q_above, self.limits,
                                       max_speed=p.speed)
            if down.success and not self.model.self_collides(down.qs).any():
                return tuple(float(v) for v in cands[i]), q_above, checker, down.qs
        return None, "no_placement" if free.any() else "no_free_placement", None, None

    # ------------------------------------------------------------------ the update
    def _update(self, context, state):
        s = self._fsm(context)
        t = context.get_time()
        if s.done or t + 1e-9 < s.busy_until:
            return
        new = self.step(s, t, context)
        state.get_mutable_abstract_state(self._state).set_value(new)

    def step(self, s: _Fsm, t: float, context) -> _Fsm:
        """The FSM's transition at time t from state s (the motion of s has ended)."""
        p = self.params
        if s.phase == "observe":
            return self._observe(s, t, context)
        if s.phase in ("pregrasp", "place", "home"):
            return self._mppi(s, t)
        if s.phase == "grasp":  # preset: straight approach, then close
            s = self._play(s, t, s.lines["approach"], speed=p.speed, length=p.approach)
            return dataclasses.replace(s, phase="close")
        if s.phase == "close":
            return dataclasses.replace(s, phase="lift", jaw=CLOSED, traj=None, busy_until=t + p.close_time)
        if s.phase == "lift":
            opening = float(self.jaw_port.Eval(context)[0])
            if opening < p.min_opening:
                return self._fail(s, t, "empty_jaw")
            s = self._play(dataclasses.replace(s, grasped=True), t, s.lines["lift"], speed=p.speed, length=p.lift)
            return dataclasses.replace(s, phase="place_plan")
        if s.phase == "place_plan":
            opening = float(self.jaw_port.Eval(context)[0])
            if opening < p.min_opening:
                return self._fail(dataclasses.replace(s, grasped=False), t, "dropped")
            held = self._held(s)
            start = time.process_time()
            where, goal, checker, down = self._place_goal(s, held)
            s = dataclasses.replace(s, plan_seconds=s.plan_seconds + time.process_time() - start)
            if where is None:
                return self._fail(s, t, goal)
            return dataclasses.replace(s, phase="place", goal=goal, after="descend", steps=0, checker=checker,
                                       placement=where, busy_until=t, lines={**s.lines, "descend": down})
        if s.phase == "descend":  # preset: straight down onto the placement
            s = self._play(s, t, s.lines["descend"], speed=p.speed, length=p.descent)
            return dataclasses.replace(s, phase="release")
        if s.phase == "release":
            s = self._record(s, t, True, "placed")
            s = dataclasses.replace(s, jaw=OPEN, tries={**s.tries, s.target: p.attempts})
            return self._go_home(s, t, hold=p.open_time)
        raise ControllerError(f"RearrangementPlanner: unknown phase {s.phase!r}")

    def _held(self, s: _Fsm) -> np.ndarray:
        """The target's observed points in the tool frame at the grasp (the object in hand)."""
        X = self.model.tool_pose(s.grasp_q)
        P = np.asarray(s.target_points, float)
        if len(P) > 2000:
            P = P[np.random.default_rng(self.params.seed).choice(len(P), 2000, replace=False)]
        P_T = (P - X[:3, 3]) @ X[:3, :3]
        if len(P_T) < 4:
            P_T = np.array([[0.02, 0.02, 0.0], [-0.02, 0.02, 0.0], [0.02, -0.02, 0.0], [0.0, 0.0, 0.03]])
        return P_T


# ------------------------------------------------------------------------------- the diagram
class RearrangementController(Diagram):
    """The Diagram MakeRearrangementController builds; `planner` is its RearrangementPlanner,
    `initial_commands()` the station commands it starts from (the arm at home, the jaw open)."""

    def __init__(self, builder: DiagramBuilder, planner: RearrangementPlanner):
        super().__init__()
        builder.BuildInto(self)
        self.planner = planner

    def initial_commands(self) -> dict:
        p = self.planner
        return {f"{ARM}.position": p.q_home.copy(), f"{JAW}.position": [OPEN],
                f"{JAW}.force_limit": [p.params.force_limit]}


def MakeRearrangementController(scenario, params: RearrangeParams | None = None, sim: RearrangeSimInfo | None = None,
                                targets: int = 10, name: str = "rearrangement_controller",
                                net=None) -> RearrangementController:
    """The rearrangement controller Diagram for `scenario`'s Panda station (module doc). sim: the
    simulated station's labels and the objects to move (None: the hardware station's ports only);
    targets: at most this many objects are moved; net: a loaded collision network to share between
    controllers (default: the method's weights)."""
    params = params or RearrangeParams()
    builder = DiagramBuilder()
    planner = builder.AddSystem(RearrangementPlanner(scenario, params, sim, targets, net))
    planner.set_name("rearrangement_planner")
    cam = params.camera
    builder.ExportInput(planner.GetInputPort("depth_image"), f"{cam}.depth_image")
    if sim is not None:
        builder.ExportInput(planner.GetInputPort("label_image"), f"{cam}.label_image")
    builder.ExportInput(planner.GetInputPort("arm_state"), f"{ARM}.state_estimated")
    builder.ExportInput(planner.GetInputPort("jaw_state"), f"{JAW}.state_measured")
    builder.ExportOutput(planner.GetOutputPort("arm_position"), f"{ARM}.position")
    builder.ExportOutput(planner.GetOutputPort("jaw_position"), f"{JAW}.position")
    builder.ExportOutput(planner.GetOutputPort("jaw_force_limit"), f"{JAW}.force_limit")
    builder.ExportOutput(planner.GetOutputPort("status"), "status")
    builder.ExportOutput(planner.GetOutputPort("history"), "history")
    controller = RearrangementController(builder, planner)
    controller.set_name(name)
    return controller


def sim_info(plant, targets) -> RearrangeSimInfo:
    """RearrangeSimInfo of a simulated PandaTable station's plant: object labels (body indices, the
    station's label image), the labels of the robot's and the gripper's bodies, and `targets`
    (object model names) in order."""
    robot = tuple(int(b) for b in range(plant.num_bodies())
                  if plant.GetModelInstanceName(plant.get_body(BodyIndex(b)).model_instance()) in (ARM, JAW))
    return RearrangeSimInfo(object_labels(plant), robot, tuple(targets))
