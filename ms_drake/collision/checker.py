"""One interface to every point-cloud collision checker of Ch. 6: P(collision) of known point sets
(an object in hand, the robot's links) at many poses against one scene point cloud.

    checker = SceneChecker("net", scene_points)          # or pointnet_grid, coal_reconstruction, sdf
    checker.add("mug", mug_points)                        # points in the object's own frame
    p = checker.query("mug", poses)                       # (n, 4, 4) world-from-object -> (n,) in [0, 1]

- `net` / `pointnet_grid`: SceneCollisionNet (ms_drake.collision.scene_net); the scene's voxel
  features are computed once in the constructor, each added point set's object features once in
  `add`, so a query costs only the classifier (the reference's robot checking, line 1067: link
  features once per robot, link poses from forward kinematics at run time).
- `coal_reconstruction` / `sdf`: the baselines of ms_drake.collision.baselines, built per added
  point set (their scene reconstruction is redone for each; a handful of point sets per scene).

Baselines answer 0 or 1; the networks a probability; `collides` thresholds either at 0.5.
The network's weights default to models/weights/collision.pt (pointnet_grid:
collision_pointnet_grid.pt); it runs on the device it was loaded to (`load_collision_net(...,
device=)`, `SceneChecker(..., device=)`: cpu | cuda | auto); points and poses go in and
probabilities come out as numpy arrays either way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ms_drake.collision.baselines import BASELINES, make_baseline
from ms_drake.collision.scene_net import CollisionNetError, NetConfig, make_net
from ms_drake.paths import model_path
from ms_drake.perception.weights import torch_device

NETWORKS = ("net", "pointnet_grid")
METHODS = NETWORKS + BASELINES
WEIGHTS = {"net": "weights/collision.pt", "pointnet_grid": "weights/collision_pointnet_grid.pt"}


def default_weights(method: str) -> Path:
    if method not in WEIGHTS:
        raise CollisionNetError(f"collision method {method!r} has no weights; networks: {', '.join(NETWORKS)}")
    return model_path(WEIGHTS[method])


def load_collision_net(path, method: str | None = None, device="cpu"):
    """(network in eval mode on `device` (cpu | cuda | auto), checkpoint dict) from a weights file of
    `ms-drake train collision`; with `method`, checks that the file holds that kind of network."""
    import torch  # optional heavy dependency: only the learned checkers need it

    dev = torch_device(device)
    path = Path(path)
    if not path.is_file():
        raise CollisionNetError(f"collision weights {path} not found: train them with `ms-drake train collision`"
                                + (" --pointnet-grid" if method == "pointnet_grid" else ""))
    fix = "give a weights file written by `ms-drake train collision`" + (" --pointnet-grid" if method == "pointnet_grid"
                                                                          else "")
    try:
        ck = torch.load(path, map_location=dev, weights_only=False)
    except Exception as e:  # garbage bytes, a truncated file: torch / pickle raise many types
        raise CollisionNetError(f"collision weights {path} cannot be read ({type(e).__name__}: "
                                f"{str(e).splitlines()[0] if str(e) else 'unreadable'}); {fix}") from None
    if not isinstance(ck, dict) or not isinstance(ck.get("config"), dict) or "model" not in ck:
        raise CollisionNetError(f"{path} is not a collision network checkpoint (no 'model'/'config'); {fix}")
    conv = ck["config"].get("conv_layers", 3)
    if method is not None and (conv == 0) != (method == "pointnet_grid"):
        raise CollisionNetError(f"weights {path} hold a network with conv_layers={conv}: not a {method!r} network; "
                                f"{fix}")
    try:
        net = make_net(NetConfig(**ck["config"])).to(dev)
        net.load_state_dict(ck["model"])
    except Exception as e:  # another network's file: unknown config keys, missing / mis-shaped tensors
        raise CollisionNetError(f"{path} does not hold a collision network ({type(e).__name__}: "
                                f"{str(e).splitlines()[0] if str(e) else 'mismatch'}); {fix}") from None
    return net.eval(), ck


class SceneChecker:
    """P(collision) of named point sets at poses against one scene cloud (module doc). A given `net`
    runs on its own device; one loaded here (from `weights`) on `device`."""

    def __init__(self, method: str, scene_points: np.ndarray, weights=None, net=None, device="cpu"):
        if method not in METHODS:
            raise CollisionNetError(f"collision method {method!r} unknown; choose one of {', '.join(METHODS)}")
        scene_points = np.asarray(scene_points, np.float32)
        if scene_points.ndim != 2 or scene_points.shape[1] != 3 or len(scene_points) == 0:
            raise CollisionNetError(f"scene_points must be a non-empty (n, 3) array, got shape {scene_points.shape}")
        self.method = method
        self.scene_points = scene_points
        self._sets: dict[str, object] = {}
        self.net = None
        if method in NETWORKS:
            import torch  # optional heavy dependency

            self.torch = torch
            self.net = net if net is not None else \
                load_collision_net(weights or default_weights(method), method, device)[0]
            self.device = self.net.centres.device
            with torch.inference_mode():
                self._voxels = self.net.first_voxel(self.net.scene_features(self._tensor(scene_points)))

    def _tensor(self, a: np.ndarray):
        return self.torch.from_numpy(a).to(self.device)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._sets)

    def add(self, name: str, points: np.ndarray) -> None:
        """Register a point set (its own frame) under `name`; replaces one of the same name."""
        points = np.asarray(points, np.float32)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
            raise CollisionNetError(f"point set {name!r} must be an (m >= 4, 3) array, got shape {points.shape}")
        if self.net is not None:
            with self.torch.inference_mode():
                obj = self.net.first_object(self.net.object_features(self._tensor(points)))
                self._sets[name] = self._voxels + obj
        else:
            self._sets[name] = make_baseline(self.method, self.scene_points, points)

    def codes(self, names) -> object:
        """(len(names), V, hidden) torch tensor: the network's per-set codes, stacked, for
        `SceneCollisionNet.query_stacked` (networks only)."""
        if self.net is None:
            raise CollisionNetError(f"codes: the {self.method!r} checker has no network codes")
        missing = [n for n in names if n not in self._sets]
        if missing:
            raise CollisionNetError(f"point sets {missing} not added; added: {', '.join(self._sets) or 'none'}")
        return self.torch.stack([self._sets[n] for n in names])

    def query(self, name: str, poses: np.ndarray) -> np.ndarray:
        """(n,) P(collision) of point set `name` at poses (n, 4, 4) world-from-object."""
        if name not in self._sets:
            raise CollisionNetError(f"point set {name!r} not added; added: {', '.join(self._sets) or 'none'}")
        poses = np.asarray(poses, np.float32).reshape(-1, 4, 4)
        if len(poses) == 0:
            return np.zeros(0)
        if self.net is not None:
            with self.torch.inference_mode():
                logits = self.net.query(self._sets[name], self._tensor(poses))
                return self.torch.sigmoid(logits).cpu().numpy().astype(float)
        return self._sets[name].query(poses).astype(float)

    def collides(self, name: str, poses: np.ndarray) -> np.ndarray:
        """(n,) bool: P(collision) > 0.5."""
        return self.query(name, poses) > 0.5
