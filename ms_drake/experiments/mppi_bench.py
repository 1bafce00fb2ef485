"""Speed of one MPPI call on the Panda with a point-cloud collision checker (the speed goals: faster than pytorch_mppi):
`ms-drake bench mppi`.

Setup per scene seed: the PandaTable robot (Panda + jaw at its base, the table as environment),
the held-out tabletop scene `seed` of the Table 6.1 benchmark (collision_learning.bench_scene: its
camera point cloud, table points removed), a `RobotSceneCollision` over the arm's moving links and
the gripper (its ArmModel's points) with the chosen checker, a start and a goal configuration (IK to tool poses 3-8 cm over
the table, the start on its left half, the goal on its right, both free by the checker; seeded),
so the way between them passes over or around the scene's objects. A run makes `steps` MPPI calls from the start, each
moving to the returned waypoint (the reference executes the minimal-cost trajectory up to it), and
reports the CPU time per call (`threads` threads for torch and numpy's BLAS alike, so the CPU time is
that of one core at the default; link FK, the network's queries, sampling, selection),
the waypoints checked per second, and whether the goal was reached (joint distance < 0.05 rad).

Planners: `ours` checks all T x H waypoints in one batch (the reference's single forward pass);
`ours_lazy` gives the same waypoint with fewer checks (mppi_step's `lazy`: the lowest-cost
waypoint's trajectory is checked up to it, cut at its first collision, and the next lowest taken
until one passes), which pays when the best trajectories are free, as they mostly are.

`--against pytorch_mppi` runs pytorch_mppi's MPPI (the `bench` extra) on the same problem: the
same dynamics (the joint step x + u, clipped to the limits), the same cost (joint distance to the
goal, plus 1000 for a colliding configuration from the same checker), the same number of samples
T and horizon H; its running cost is evaluated once per horizon step on all samples, as its API
prescribes. The per-step noise is Sigma / H per joint, so its H-step rollouts spread like ours.

`device` (cpu | cuda | auto) is where the collision network answers its queries and where
pytorch_mppi samples and rolls out; the forward kinematics, ours' sampling and selection, and the
baselines stay on the CPU. The times are CPU times of this process (`time.process_time`).
"""

from __future__ import annotations

import time

import numpy as np
from pydrake.math import RigidTransform, RollPitchYaw
from threadpoolctl import threadpool_limits

from ms_drake.collision.checker import (
    NETWORKS,
    SceneChecker,
    default_weights,
    load_collision_net,
)
from ms_drake.collision.robot import RobotSceneCollision
from ms_drake.errors import MsDrakeError
from ms_drake.experiments.collision_learning import bench_scene
from ms_drake.planning.arm_model import ArmModel
from ms_drake.planning.mppi import MppiParams, mppi_step
from ms_drake.perception.weights import torch_device
from ms_drake.planning.sequences import arm_ik
from ms_drake.scenario import load_scenario

ARM = "panda"
GOAL_TOLERANCE = 0.05  # rad
PLANNERS = ("ours", "ours_lazy", "pytorch_mppi")


def mppi_problem(seed: int, method: str, cache=None, net=None):
    """(robot collision, start q, goal q, lower, upper, keep_alive) for scene `seed` (module doc)."""
    scenario = load_scenario(None, "PandaTable")
    ik, _, q_home, keep = arm_ik(scenario, ARM)
    s = bench_scene(seed, cache)
    top = float(scenario.environment.position[2])
    cloud = s["scene_points"][s["scene_points"][:, 2] > top + 0.005]
    model = ArmModel(ik, points_per_body=256, seed=seed)
    robot = RobotSceneCollision(model, SceneChecker(method, cloud, net=net), table_top=top)
    rng = np.random.default_rng(seed)
    ends = []
    for _ in range(60):  # start on one side of the table, goal on the other, both low over it
        side = 1.0 if not ends else -1.0
        X = RigidTransform(RollPitchYaw(np.pi, 0.0, rng.uniform(-1, 1)),
                           [rng.uniform(-0.1, 0.3), side * rng.uniform(0.15, 0.3), top + rng.uniform(0.03, 0.08)])
        res = ik.solve(X, q_seed=q_home)
        if res.success and not robot.collides(np.asarray(res.q, float)[None])[0]:
            ends.append(np.asarray(res.q, float))
            if len(ends) == 2:
                return robot, ends[0], ends[1], ik.lower, ik.upper, (keep, ik)
    raise MsDrakeError(f"scene {seed}: no collision-free start and goal over the table in 60 tries")


def run_ours(robot, q0, goal, lower, upper, params: MppiParams, steps: int, lazy: bool = False) -> dict:
    q, times, checks = np.array(q0, float), [], 0
    for k in range(steps):
        t = time.process_time()
        rng = np.random.default_rng([params.seed, k])
        if lazy:
            best, info = mppi_step(q, goal, None, lower, upper, params, rng, lazy=robot.collides)
        else:
            best, info = mppi_step(q, goal, robot.collides, lower, upper, params, rng)
        times.append(time.process_time() - t)
        checks += info["checks"] + info.get("lazy_checks", 0)
        if best is None:
            break
        q = best
        if np.linalg.norm(q - goal) < GOAL_TOLERANCE:
            break
    return dict(ms_per_step=1e3 * float(np.median(times)), steps=len(times), checks_per_s=checks / sum(times),
                reached=bool(np.linalg.norm(q - goal) < GOAL_TOLERANCE), final_distance=float(np.linalg.norm(q - goal)))


def run_pytorch_mppi(robot, q0, goal, lower, upper, params: MppiParams, steps: int, device="cpu") -> dict:
    import torch  # optional heavy dependency
    from pytorch_mppi import MPPI  # the `bench` extra

    dev = torch_device(device)
    torch.manual_seed(params.seed)
    lo, hi = torch.tensor(lower, device=dev), torch.tensor(upper, device=dev)
    g = torch.tensor(goal, device=dev)
    H = params.horizon

    def dynamics(x, u):
        return torch.clamp(x + u, lo, hi)

    def running_cost(x, u):
        hit = torch.from_numpy(robot.collides(x.cpu().numpy()).astype(np.float64)).to(dev)
        return torch.linalg.norm(x - g, dim=1) + 1000.0 * hit

    n = len(q0)
    sigma = (params.sigma / H) ** 2 * torch.eye(n, dtype=torch.float64, device=dev)
    step = np.linalg.norm(goal - q0) / H
    mppi = MPPI(dynamics, running_cost, n, noise_sigma=sigma, num_samples=params.trajectories, horizon=H,
                lambda_=params.temperature, u_min=-torch.full((n,), 3 * step, device=dev),
                u_max=torch.full((n,), 3 * step, device=dev), device=dev)
    q, times = torch.tensor(q0, device=dev), []
    for _ in range(steps):
        t = time.process_time()
        u = mppi.command(q)
        times.append(time.process_time() - t)
        q = dynamics(q, u)
        if float(torch.linalg.norm(q - g)) < GOAL_TOLERANCE:
            break
    d = float(torch.linalg.norm(q - g))
    return dict(ms_per_step=1e3 * float(np.median(times)), steps=len(times),
                checks_per_s=params.trajectories * H * len(times) / sum(times), reached=d < GOAL_TOLERANCE,
                final_distance=d)


def bench_mppi(method: str, scenes: int, seed_start: int = 0, trajectories: int = 300, horizon: int = 40,
               steps: int = 5, planner: str = "ours", cache=None, weights=None, threads: int = 1, progress=None,
               device: str = "cpu") -> list[dict]:
    """One record per scene (module doc)."""
    if planner not in PLANNERS:
        raise MsDrakeError(f"planner {planner!r} unknown; choose one of {', '.join(PLANNERS)}")
    dev = torch_device(device)
    net = None
    if method in NETWORKS:
        import torch  # optional heavy dependency

        torch.set_num_threads(threads)
        net = load_collision_net(weights or default_weights(method), method, dev)[0]
    run = {"ours": run_ours, "ours_lazy": lambda *a: run_ours(*a, lazy=True),
           "pytorch_mppi": lambda *a: run_pytorch_mppi(*a, device=dev)}[planner]
    out = []
    for k in range(scenes):
        seed = seed_start + k
        robot, q0, goal, lo, hi, keep = mppi_problem(seed, method, cache, net)
        with threadpool_limits(limits=threads, user_api="blas"):
            r = run(robot, q0, goal, lo, hi, MppiParams(trajectories=trajectories, horizon=horizon, seed=seed), steps)
        out.append(dict(seed=seed, method=method, planner=planner, trajectories=trajectories, horizon=horizon,
                        threads=threads, device=str(dev), hz=1e3 / r["ms_per_step"], **r))
        del keep
        if progress is not None:
            progress(out[-1])
    return out
