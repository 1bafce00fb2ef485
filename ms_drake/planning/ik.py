"""Inverse kinematics for a gripper frame with Drake's InverseKinematics.

`ArmIk` solves for the joints of one arm so that a gripper frame (the `tcp`) reaches a target
pose, with every other position of the plant held at its current value, and (optionally) all
collision pairs of the plant at least `min_distance` apart (MinimumDistanceLowerBoundConstraint).
Build it on a plant that holds the robot, its grippers and the environment but not the object to
be grasped (the pads must touch that one); `make_ik_diagram` does that.

Targets:
  * full pose (position within `position_tolerance`, orientation within `angle_tolerance`), for
    parallel-jaw grasps and blade pushes;
  * `axis_only=True`: position + the tool's z axis along the target's z axis, free rotation about
    it (suction grasps with a round cup).
Result: `IkResult(success, q, status, ...)`; status "ok", "unreachable" (no solution satisfies the
pose constraints within the restarts) or "collision" (pose reached only in collision). `solve`
never raises on a failed solve, so it is safe inside a running diagram.
Restarts: the first solve starts at the given seed; then the first `restarts` of a fixed list of
configurations drawn once, within the joint limits, from `numpy.random.default_rng(seed)`. A solve
does not depend on the solves before it: the same target and seed give the same answer, so a
reach check and the station that executes the grasp agree. `solutions` yields the solution from
each seed in turn, for plans that need a configuration whose onward straight lines also solve.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.solvers import SnoptSolver, Solve
from pydrake.systems.framework import DiagramBuilder

from ms_drake.geometry import as_rigid_transform
from ms_drake.paths import make_parser
from ms_drake.robots import station_robot_spec
from ms_drake.station.robots import add_arm_gripper, add_floating_gripper, add_robot


@dataclass(frozen=True, eq=False)
class IkResult:
    success: bool
    q: np.ndarray  # arm joints in command order (the best iterate when unsuccessful)
    status: str  # ok | unreachable | collision
    position_error: float = np.inf
    angle_error: float = np.inf
    min_distance: float = np.nan
    message: str = ""

    @property
    def unreachable(self) -> bool:
        return self.status == "unreachable"


class ArmIk:
    """IK for `joint_names` of `plant` so that `frame` reaches a target (see module docstring).

    plant_context must be a context of `plant` inside a diagram with its SceneGraph when
    collision avoidance is on (min_distance is not None).
    """

    def __init__(self, plant, plant_context, joint_names, frame, min_distance: float | None = 0.005,
                 influence_distance: float = 0.03, position_tolerance: float = 1e-3,
                 angle_tolerance: float = 1e-2, restarts: int = 3, seed: int = 0, max_restarts: int = 16):
        self.plant = plant
        self.context = plant_context
        self.frame = frame
        self.joints = [plant.GetJointByName(n) for n in joint_names]
        self.idx = np.array([j.position_start() for j in self.joints])
        self.lower = plant.GetPositionLowerLimits()[self.idx]
        self.upper = plant.GetPositionUpperLimits()[self.idx]
        self.min_distance = min_distance
        self.influence = influence_distance
        self.pos_tol = position_tolerance
        self.ang_tol = angle_tolerance
        self.restarts = restarts
        lo = np.where(np.isfinite(self.lower), self.lower, -np.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, np.pi)
        rng = np.random.default_rng(seed)
        self.restart_seeds = [rng.uniform(lo, hi) for _ in range(max(int(max_restarts), int(restarts)))]
        self._snopt = SnoptSolver()

    def arm_positions(self) -> np.ndarray:
        return self.plant.GetPositions(self.context)[self.idx]

    def _errors(self, q_full, X_WT, axis_only):
        ctx = self.context
        old = self.plant.GetPositions(ctx).copy()
        self.plant.SetPositions(ctx, q_full)
        X = self.frame.CalcPoseInWorld(ctx)
        self.plant.SetPositions(ctx, old)
        pe = float(np.linalg.norm(X.translation() - X_WT.translation()))
        if axis_only:
            c = float(np.dot(X.rotation().matrix()[:, 2], X_WT.rotation().matrix()[:, 2]))
            ae = float(np.arccos(np.clip(c, -1, 1)))
        else:
            ae = float(X.rotation().InvertAndCompose(X_WT.rotation()).ToAngleAxis().angle())
        return pe, ae

    def _seeds(self, q_seed):
        seed = self.arm_positions() if q_seed is None else np.asarray(q_seed, float)
        return [np.clip(seed, self.lower, self.upper)] + self.restart_seeds[:self.restarts]

    def solve(self, X_WT: RigidTransform, q_seed=None, axis_only: bool = False) -> IkResult:
        """Arm joints that put the frame at X_WT (RigidTransform or 4x4 array): the first success
        from q_seed (default: the context's) and the restarts, else the best failed attempt. A
        failed solve is a result, never an exception; a pose that is not a rigid transform raises
        ValueError."""
        best = None
        for res in self._attempts(X_WT, q_seed, axis_only):
            if res.success:
                return res
            if best is None or res.position_error + res.angle_error < best.position_error + best.angle_error:
                best = res
        return best

    def solutions(self, X_WT: RigidTransform, q_seed=None, axis_only: bool = False):
        """Each successful solve, from q_seed and then from each restart in turn (lazily: stop
        iterating once one serves); the last item is the best failed attempt when none succeeded."""
        best, any_ok = None, False
        for res in self._attempts(X_WT, q_seed, axis_only):
            if res.success:
                any_ok = True
                yield res
            elif best is None or res.position_error + res.angle_error < best.position_error + best.angle_error:
                best = res
        if not any_ok:
            yield best

    def _attempts(self, X_WT, q_seed, axis_only):
        X_WT = as_rigid_transform(X_WT, "X_WT")
        q_now = self.plant.GetPositions(self.context).copy()
        for s in self._seeds(q_seed):
            try:
                # Lazy collision constraint: solve without it first (a few ms), add it only when
                # the solution is in collision (most targets in free space need no second solve).
                res = self._solve_once(X_WT, q_now, s, axis_only, with_collision=False)
                if res.status == "collision":
                    res = self._solve_once(X_WT, q_now, res.q, axis_only, with_collision=True)
            except RuntimeError as e:  # e.g. a geometry pair Drake cannot measure
                res = IkResult(False, s, "unreachable", message=str(e))
            finally:
                self.plant.SetPositions(self.context, q_now)  # the solver evaluates in this context
            yield res

    def _solve_once(self, X_WT, q_now, seed, axis_only, with_collision=True):
        ik = InverseKinematics(self.plant, self.context, with_joint_limits=True)
        prog = ik.get_mutable_prog()
        q = ik.q()
        others = np.setdiff1d(np.arange(self.plant.num_positions()), self.idx)
        if len(others):
            prog.AddBoundingBoxConstraint(q_now[others], q_now[others], q[others])
        p = X_WT.translation()
        tol = self.pos_tol / np.sqrt(3)
        ik.AddPositionConstraint(self.frame, np.zeros(3), self.plant.world_frame(), p - tol, p + tol)
        if axis_only:
            ik.AddAngleBetweenVectorsConstraint(self.frame, [0, 0, 1], self.plant.world_frame(),
                                                X_WT.rotation().matrix()[:, 2], 0.0, self.ang_tol)
        else:
            ik.AddOrientationConstraint(self.frame, RotationMatrix(), self.plant.world_frame(), X_WT.rotation(),
                                        self.ang_tol)
        if self.min_distance is not None and with_collision:
            ik.AddMinimumDistanceLowerBoundConstraint(self.min_distance, self.influence)
        q0 = q_now.copy()
        q0[self.idx] = seed
        prog.AddQuadraticErrorCost(np.eye(len(self.idx)) * 1e-2, seed, q[self.idx])
        prog.SetInitialGuess(q, q0)
        result = self._snopt.Solve(prog, q0) if self._snopt.available() else Solve(prog, q0)
        q_sol = result.GetSolution(q)
        pe, ae = self._errors(q_sol, X_WT, axis_only)
        pose_ok = pe <= self.pos_tol * 1.01 and ae <= self.ang_tol * 1.01
        within = np.all(q_sol[self.idx] >= self.lower - 1e-6) and np.all(q_sol[self.idx] <= self.upper + 1e-6)
        dmin = np.nan
        if self.min_distance is not None:
            dmin = self._min_distance(q_sol)
        coll_ok = self.min_distance is None or dmin >= self.min_distance - 1e-4
        if pose_ok and within and coll_ok:
            status = "ok"
        elif pose_ok and within:
            status = "collision"
        else:
            status = "unreachable"
        return IkResult(status == "ok", q_sol[self.idx], status, pe, ae, dmin, str(result.get_solution_result()))

    def _min_distance(self, q_full) -> float:
        old = self.plant.GetPositions(self.context).copy()
        self.plant.SetPositions(self.context, q_full)
        try:
            query = self.plant.get_geometry_query_input_port().Eval(self.context)
            pairs = query.ComputeSignedDistancePairwiseClosestPoints(self.influence + 0.05)
            return min((p.distance for p in pairs), default=np.inf)
        finally:
            self.plant.SetPositions(self.context, old)


def make_ik_diagram(robot: str, grippers: dict[str, str] | None = None, add_environment=None, X_WR=None):
    """A robot + grippers (+ environment) plant for IK. grippers: {arm: gripper name}, default
    each arm's default gripper. add_environment(plant, parser) adds static geometry.
    Returns (diagram, plant, robot_instance, {arm: gripper_instance}).
    """

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlantSceneGraph(builder, 0.0)
    parser = make_parser(plant)
    spec = station_robot_spec(robot)
    chosen = grippers or {arm: a.default_gripper for arm, a in spec.arms.items()}
    if robot == "floating":  # the gripper on its 6 base joints: arm `floating`
        (arm, name), = chosen.items()
        r, gripper = add_floating_gripper(plant, parser, name, X_WR, model_name=f"{arm}_gripper")
        g = {arm: gripper}
    else:
        r = add_robot(plant, parser, robot, X_WR)
        g = {arm: add_arm_gripper(plant, parser, r, robot, arm, name, model_name=f"{arm}_gripper")
             for arm, name in chosen.items()}
    if add_environment is not None:
        add_environment(plant, parser)
    plant.Finalize()
    return builder.Build(), plant, r, g
