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

With a network checker the whole check is one torch graph (`SceneCollisionNet.query_stacked`):
forward kinematics of a chunk of `CHUNK` configurations (`ArmModel.link_poses_torch`), the table
test (a configuration with a link below the table is 1 without asking the network), and every
link's and held object's query in one gather and one matrix product per layer,
chunk by chunk so that the activations stay in the CPU's cache (the kinematics and the table
test run on the CPU; the poses go to the network's device for its queries). The table test
takes a link's lowest point over its points only where the link's bounding sphere reaches
below the table.
The answers are those of the per-link path that the baselines take (tests/test_robot_collision.py).
"""

from __future__ import annotations

import numpy as np

from ms_drake.collision.checker import SceneChecker
from ms_drake.collision.scene_net import CollisionNetError
from ms_drake.planning.arm_model import ArmModel

CHUNK = 512  # configurations per pass of the network path (module doc)


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
        self._graph = None  # the network path's constants, for one set of held objects

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
        if self.checker.net is not None:
            return self._net_probabilities(q)
        return self.per_link_probabilities(q)

    def per_link_probabilities(self, q: np.ndarray) -> np.ndarray:
        """`probabilities` one checker query per link and held object (any checker; the path of
        the baselines)."""
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

    def _constants(self):
        """Stacked codes, body slots, held objects' poses and the links' bounding spheres (built once
        per set of held objects)."""
        key = tuple((n, b, X.tobytes()) for n, (b, X) in self.attached.items())
        if self._graph is None or self._graph[0] != key:
            torch = self.checker.torch
            names = [f"link:{b}" for b in self.bodies] + [f"held:{n}" for n in self.attached]
            slot = {b: k for k, b in enumerate(self.model.body_names)}
            pts = [self.model.points[b] for b in self.bodies]
            centre = np.stack([p.mean(axis=0) for p in pts])
            radius = np.array([np.linalg.norm(p - c, axis=1).max() for p, c in zip(pts, centre)])
            self._graph = (key, dict(
                codes=self.checker.codes(names),
                links=torch.tensor([slot[b] for b in self.bodies]),
                held=[(slot[b], torch.tensor(X, dtype=torch.float64)) for b, X in self.attached.values()],
                points=[torch.tensor(p.T) for p in pts], centre=torch.tensor(centre),
                radius=torch.tensor(radius + 1e-9)))
        return self._graph[1]

    def _net_probabilities(self, q: np.ndarray) -> np.ndarray:
        torch = self.checker.torch
        q = np.atleast_2d(np.asarray(q, float))
        if q.shape[1] != self.model.num_positions:
            raise CollisionNetError(f"configurations must have {self.model.num_positions} joints, got shape {q.shape}")
        g = self._constants()
        out = np.empty(len(q))
        with torch.inference_mode():
            for start in range(0, len(q), CHUNK):
                X = self.model.link_poses_torch(torch.from_numpy(q[start:start + CHUNK]))
                p = out[start:start + len(X)]
                links = X[:, g["links"]]
                if self.table_top is not None:  # below the table: 1, whatever the network says
                    low = self._below_table(links, g)
                    p[low] = 1.0
                    if low.any():
                        keep = torch.from_numpy(~low)
                        X, links = X[keep], links[keep]
                else:
                    low = np.zeros(len(p), bool)
                if len(X):
                    poses = torch.cat([links] + [X[:, b:b + 1] @ X_BO for b, X_BO in g["held"]], dim=1)
                    logits = self.checker.net.query_stacked(g["codes"], poses.float().to(self.checker.device))
                    p[~low] = torch.sigmoid(logits).double().amax(dim=1).cpu().numpy()
        return out

    def _below_table(self, links, g) -> np.ndarray:
        """(n,) bool: a link's lowest point is below the table top; the exact minimum over a link's
        points only where its bounding sphere reaches the table."""
        torch = self.checker.torch
        row, z0 = links[:, :, 2, :3], links[:, :, 2, 3]
        near = (z0 + (row * g["centre"]).sum(dim=2) - g["radius"] < self.table_top).numpy()
        low = np.zeros(len(near), bool)
        for b in np.flatnonzero(near.any(axis=0)):
            rows = torch.from_numpy(np.flatnonzero(near[:, b] & ~low))
            z = (row[rows, b] @ g["points"][b]).amin(dim=1) + z0[rows, b]
            low[rows.numpy()[(z < self.table_top).numpy()]] = True
        return low

    def collides(self, q: np.ndarray) -> np.ndarray:
        """(N,) bool: some link or held object collides at that configuration."""
        return self.probabilities(q) > self.threshold
