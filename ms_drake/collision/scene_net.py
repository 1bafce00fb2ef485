"""SceneCollisionNet (Ch. 6.3, lines 1053-1057) in pure torch, sized for the CPU; it computes on
the device its module is on (`.to(device)`), its inputs given there.

- Scene encoder: the scene point cloud (world frame) is cut into voxels of `NetConfig.voxel`
  (10 cm) over `SCENE_BOUNDS` (the table's volume: 10 x 8 x 5 voxels); each point, relative to its
  voxel's centre (in voxel units), goes through a shared point MLP and the features are max-pooled
  per voxel with `Tensor.scatter_reduce` (no torch_scatter); the voxel grid then goes through 3D
  convolutions, which share information between neighbouring voxels (the reference's point (2)).
- Object encoder: PointNet++-style set abstraction in pure torch: farthest-point sampling of
  `NetConfig.centroids` centroids, the k nearest points of each (relative to it) through a shared
  MLP and a max, then a global MLP and a max: one feature vector per object.
- PointNet-grid (the ablation of Table 6.1): `NetConfig(conv_layers=0)`, the pooled voxel
  features without the 3D convolutions, so no voxel sees its neighbours.
- Query classifier: for a pose X_WO of the object, the voxel nearest to its position, the pose
  relative to that voxel's centre (translation in voxel units, rotation as its first two columns,
  the 6D representation) and the two feature vectors -> MLP -> logit of P(collision).

Scene and object features are computed once per observation (`SceneCollisionNet.encode`); a
batch of queries then costs only the classifier (`SceneCollisionNet.query`). The classifier's
first layer is linear in the concatenation [voxel feature, object feature, pose], so `encode`
also precomputes its voxel and object parts: a query pays only the pose part, a gather, and the
layers after the first. `SceneCollisionNet.query_stacked` answers several point sets (a robot's
links) at once: their codes stacked, one gather, one matrix product per layer.

Hard-negative mining (line 1061): `mined_loss` back-propagates the binary cross-entropy of the
`hard` (10 %) highest-loss queries plus `random` (10 %) others drawn at random.

torch is imported inside functions only (optional heavy dependency).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ms_drake.errors import MsDrakeError

SCENE_BOUNDS = ((-0.5, 0.5), (-0.4, 0.4), (0.0, 0.5))  # m, world frame: the PandaTable table's volume


class CollisionNetError(MsDrakeError):
    """A collision network got inputs it cannot use."""


@dataclass(frozen=True)
class NetConfig:
    voxel: float = 0.1  # m
    point_features: int = 64
    voxel_features: int = 64
    centroids: int = 64
    neighbours: int = 16
    object_features: int = 128
    hidden: int = 128
    query_layers: int = 1  # hidden -> hidden layers of the query classifier after its first layer
    conv_layers: int = 3  # 0: the PointNet-grid ablation of Table 6.1 (voxel features straight from the pooling)


def grid_shape(cfg: NetConfig = NetConfig()) -> tuple[int, int, int]:
    return tuple(int(round((hi - lo) / cfg.voxel)) for lo, hi in SCENE_BOUNDS)


def voxel_centres(cfg: NetConfig = NetConfig()) -> np.ndarray:
    """(V, 3) world-frame centres of the voxels, in the order of the flattened (x, y, z) grid."""
    axes = [lo + cfg.voxel * (np.arange(n) + 0.5) for (lo, _), n in zip(SCENE_BOUNDS, grid_shape(cfg))]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def make_net(cfg: NetConfig = NetConfig()):
    """A SceneCollisionNet (an nn.Module; see the module doc)."""
    import torch  # optional heavy dependency: only the learned collision checker needs it
    from torch import nn

    shape = grid_shape(cfg)
    V = int(np.prod(shape))

    def mlp(*sizes, last_relu=True):
        layers = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
            layers.append(nn.Linear(a, b))
            if last_relu or i < len(sizes) - 2:
                layers.append(nn.ReLU(inplace=True))
        return nn.Sequential(*layers)

    class SceneCollisionNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.cfg = cfg
            self.register_buffer("centres", torch.tensor(voxel_centres(cfg), dtype=torch.float32))
            # the grid's lower corner; not saved (weights files hold the centres only)
            self.register_buffer("lo", torch.tensor([b[0] for b in SCENE_BOUNDS], dtype=torch.float32),
                                 persistent=False)
            self.point_mlp = mlp(3, 32, cfg.point_features)
            c = cfg.voxel_features
            if cfg.conv_layers == 0 and cfg.point_features != c:
                raise CollisionNetError(f"conv_layers=0 needs point_features == voxel_features, got "
                                        f"{cfg.point_features} and {c}")
            convs = []
            for i in range(cfg.conv_layers):
                convs += [nn.Conv3d(cfg.point_features if i == 0 else c, c, 3, padding=1), nn.ReLU(inplace=True)]
            self.convs = nn.Sequential(*convs)  # empty: identity
            self.group_mlp = mlp(3, 32, 64)
            self.object_mlp = mlp(64 + 3, 128, cfg.object_features)
            h = cfg.hidden
            self.first_voxel = nn.Linear(c, h)
            self.first_object = nn.Linear(cfg.object_features, h, bias=False)
            self.first_pose = nn.Linear(9, h, bias=False)
            self.rest = mlp(*([h] * (cfg.query_layers + 1)), 1, last_relu=False)

        # -- encoders ---------------------------------------------------------------------------
        def voxel_index(self, p):
            """(n,) flat voxel index of world points p (n, 3), clamped into the grid."""
            ijk = torch.floor((p - self.lo) / cfg.voxel).long()
            for a, n in enumerate(shape):
                ijk[:, a] = ijk[:, a].clamp(0, n - 1)
            return (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]

        def scene_features(self, points):
            """(V, voxel_features) from a scene cloud (n, 3) in the world frame."""
            idx = self.voxel_index(points)
            f = self.point_mlp((points - self.centres[idx]) / cfg.voxel)
            pooled = torch.zeros(V, f.shape[1], dtype=f.dtype, device=f.device)
            pooled = pooled.scatter_reduce(0, idx[:, None].expand_as(f), f, reduce="amax", include_self=True)
            grid = pooled.T.reshape(1, -1, *shape)
            return self.convs(grid).reshape(cfg.voxel_features, V).T

        def object_features(self, points):
            """(object_features,) from object points (m, 3) in the object's frame."""
            centroids = points[farthest_points(points, cfg.centroids)]
            d = torch.cdist(centroids, points)
            nn_idx = d.topk(min(cfg.neighbours, len(points)), largest=False).indices
            local = (points[nn_idx] - centroids[:, None]) / cfg.voxel
            g = self.group_mlp(local).amax(dim=1)
            return self.object_mlp(torch.cat([g, centroids / cfg.voxel], dim=1)).amax(dim=0)

        def encode(self, scene_points, object_points):
            """The per-observation part: the first layer's voxel and object terms."""
            vox = self.first_voxel(self.scene_features(scene_points))
            obj = self.first_object(self.object_features(object_points))
            return vox + obj  # (V, hidden)

        # -- queries ----------------------------------------------------------------------------
        def query(self, code, poses):
            """(q,) collision logits of poses (q, 4, 4) world-from-object, given `encode`'s code."""
            t = poses[:, :3, 3]
            idx = self.voxel_index(t)
            rel = torch.cat([(t - self.centres[idx]) / cfg.voxel, poses[:, :3, 0], poses[:, :3, 1]], dim=1)
            return self.rest(torch.relu(code[idx] + self.first_pose(rel)))[:, 0]

        def query_stacked(self, codes, poses):
            """(n, B) collision logits of B point sets at n poses each, in one pass: codes (B, V,
            hidden) from `encode` (one per set), poses (n, B, 4, 4) world-from-object; the same logits
            as B calls of `query`, to round-off. For inference (in-place activations)."""
            n, B = poses.shape[:2]
            flat = poses.reshape(n * B, 4, 4)
            t = flat[:, :3, 3]
            idx = self.voxel_index(t)
            rel = torch.cat([(t - self.centres[idx]) / cfg.voxel, flat[:, :3, 0], flat[:, :3, 1]], dim=1)
            rows = idx + (torch.arange(B, device=idx.device) * codes.shape[1]).repeat(n)
            h = codes.reshape(B * codes.shape[1], -1).index_select(0, rows)
            h.addmm_(rel, self.first_pose.weight.T).relu_()
            return self.rest(h)[:, 0].reshape(n, B)

        def forward(self, scene_points, object_points, poses):
            return self.query(self.encode(scene_points, object_points), poses)

    return SceneCollisionNet()


def farthest_points(points, k: int):
    """Indices of k farthest-point-sampled points of (n, 3) (the first is point 0; deterministic)."""
    import torch  # optional heavy dependency

    n = len(points)
    if n == 0:
        raise CollisionNetError("the object point cloud is empty")
    k = min(k, n)
    chosen = torch.zeros(k, dtype=torch.long, device=points.device)
    dist = torch.full((n,), float("inf"), device=points.device)
    last = 0
    for i in range(1, k):
        dist = torch.minimum(dist, ((points - points[last]) ** 2).sum(dim=1))
        last = int(torch.argmax(dist))
        chosen[i] = last
    return chosen


def mined_loss(logits, labels, hard: float = 0.1, random: float = 0.1, generator=None):
    """Mean BCE over the `hard` fraction of highest-loss queries plus a `random` fraction of the
    others (hard-negative mining, line 1061)."""
    import torch  # optional heavy dependency

    if not 0 < hard <= 1 or not 0 <= random <= 1:
        raise CollisionNetError(f"mined_loss: hard={hard} must be in (0, 1], random={random} in [0, 1]")
    loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, labels.to(logits.dtype), reduction="none")
    n = loss.numel()
    k = max(1, int(round(hard * n)))
    top = loss.topk(k).indices
    rest = torch.ones(n, dtype=torch.bool, device=loss.device)
    rest[top] = False
    others = torch.nonzero(rest)[:, 0]
    m = min(len(others), int(round(random * n)))
    pick = others[torch.randperm(len(others), generator=generator)[:m].to(others.device)]
    return loss[torch.cat([top, pick])].mean()
