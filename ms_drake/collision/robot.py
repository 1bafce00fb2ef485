"""Robot-scene collision checking from a point cloud (Ch. 6.3.2, line 1067), for batches of
configurations: what MPPI needs at every waypoint.

`RobotSceneCollision` registers the points an `ArmModel` (ms_drake.planning.arm_model) sampled
once on each link's collision geometry with a `SceneChecker` (so with the network the link
features are computed once per robot, as in the reference); at run time the model's batched
forward kinematics gives every link's pose at every configuration and one checker query per link
answers all of them. An object in hand is another point set attached to a body at a fixed pose
(`attach`). The table is checked analytically: a configuration collides when any link point
falls below `table_top` (the scene cloud's table points are removed before the checker sees
them). The robot's self-collisions are Drake's (`ArmModel.self_collides`, one configuration at a
time: MPPI checks them lazily, ms_drake.planning.mppi's `lazy`).
"""

from __future__ import annotations

import numpy as np

from ms_drake.collision.checker import SceneChecker
from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.planning.arm_model import ArmModel


class RobotSceneCollision:
    """P(collision) of an arm's links (+ an object in hand) with a scene cloud, per configuration.

    model: the arm's ArmModel; checker: a SceneChecker on the scene cloud; bodies: the body names
    to check (default: every body of the model with points); table_top: z of the table plane
    (None: no table check).
    """

    def __init__(self, model: ArmModel, checker: SceneChecker, bodies=None, table_top: float | None = 0.0,
                 threshold: float = 0.5):
        self.model, self.checker, self.table_top, self.threshold = model, checker, table_top, threshold
        self.bodies = tuple(bodies) if bodies is not None else tuple(model.points)
        missing = [b for b in self.bodies if b not in model.points]
        if missing:
            raise CollisionNetError(f"bodies {missing} have no points in the arm model; it has: "
                                    f"{', '.join(model.points)}")
        for name in self.bodies:
            checker.add(f"link:{name}", model.points[name])
        self.attached: dict[str, tuple[str, np.ndarray]] = {}

    def attach(self, name: str, points: np.ndarray, body: str, X_BO: np.ndarray) -> None:
        """Check `points` (object frame) held rigidly at X_BO (4x4) in the model's body `body`."""
        if body not in self.model.body_names:
            raise CollisionNetError(f"attach: {body!r} is not a body of the arm model "
                                    f"({', '.join(self.model.body_names)})")
        self.checker.add(f"held:{name}", points)
        self.attached[name] = (body, np.asarray(X_BO, float))

    def detach(self, name: str) -> None:
        self.attached.pop(name, None)

    def probabilities(self, q: np.ndarray) -> np.ndarray:
        """(N,) the largest P(collision) over the checked links and held objects at each configuration."""
        poses = self.model.link_poses(q)
        p = np.zeros(len(poses[self.model.base_name]))
        for name in self.bodies:
            X = poses[name]
            p = np.maximum(p, self.checker.query(f"link:{name}", X))
            if self.table_top is not None:
                z_min = (X[:, 2, :3] @ self.model.points[name].T).min(axis=1) + X[:, 2, 3]
                p[z_min < self.table_top] = 1.0
        for name, (body, X_BO) in self.attached.items():
            p = np.maximum(p, self.checker.query(f"held:{name}", poses[body] @ X_BO))
        return p

    def collides(self, q: np.ndarray) -> np.ndarray:
        """(N,) bool: some link or held object collides at that configuration."""
        return self.probabilities(q) > self.threshold
