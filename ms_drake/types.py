"""Small value types that cross LeafSystem ports (and are saved to result files).

All are frozen dataclasses; arrays inside them are numpy arrays that must not be mutated.
Systems exchange these, never raw dicts. Poses are 4x4 homogeneous matrices in the world
frame (numpy) so that they pickle and serialize without Drake types.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class InstanceMasks:
    """Instance segmentation of one image.

    masks: (K, H, W) bool, one visible (modal) mask per instance.
    ids: length-K labels; in simulation the model-instance name of the object, else "seg_k".
    scores: length-K confidences in [0, 1].
    """

    masks: np.ndarray
    ids: tuple[str, ...]
    scores: np.ndarray

    def __post_init__(self):
        if self.masks.ndim != 3:
            raise ValueError(f"InstanceMasks.masks must be (K, H, W), got shape {self.masks.shape}")
        if len(self.ids) != self.masks.shape[0] or len(self.scores) != self.masks.shape[0]:
            raise ValueError("InstanceMasks: ids, scores and masks must have the same length")

    @staticmethod
    def empty(height: int, width: int) -> "InstanceMasks":
        return InstanceMasks(np.zeros((0, height, width), bool), (), np.zeros(0))

    def __len__(self) -> int:
        return self.masks.shape[0]

    def areas(self) -> np.ndarray:
        return self.masks.reshape(len(self), -1).sum(axis=1)


@dataclass(frozen=True, eq=False)
class TargetEstimate:
    """Where the target is visible. mask: (H, W) bool (all False when not visible)."""

    visible: bool
    mask: np.ndarray
    confidence: float = 0.0
    instance_index: int = -1  # index into InstanceMasks, -1 if none matched


@dataclass(frozen=True, eq=False)
class OccupancyMap:
    """Target occupancy distribution over the image (Ch. 8.3): (H, W) float, sums to 1 or all 0."""

    distribution: np.ndarray


@dataclass(frozen=True)
class Grasp:
    """A parallel-jaw or suction grasp in the world frame.

    kind: "parallel_jaw" | "suction". For a parallel-jaw grasp `axis` joins the jaws and
    `approach` is the approach direction; for suction `approach` is minus the surface normal.
    """

    kind: str
    center: tuple[float, float, float]
    approach: tuple[float, float, float]
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    width: float = 0.0
    quality: float = 0.0
    model: str = ""
    object_id: str = ""


@dataclass(frozen=True)
class Push:
    """A linear push from `start` to `end` (world frame, constant height)."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    object_id: str = ""


@dataclass(frozen=True)
class ShelfAction:
    """A shelf action (Ch. 9): blade push or suction pick-and-place of one object."""

    kind: str  # "push" | "suction"
    object_id: str
    dx: float = 0.0
    dy: float = 0.0


@dataclass(frozen=True)
class Action:
    """What the PolicySelector asks the executor to do. kind: grasp | push | shelf | stop."""

    kind: str
    grasp: Grasp | None = None
    push: Push | None = None
    shelf: ShelfAction | None = None
    reason: str = ""


@dataclass(frozen=True)
class ActionOutcome:
    """What happened when an action was executed."""

    action: Action
    success: bool
    removed_object: str = ""
    message: str = ""


@dataclass(frozen=True)
class ObjectPose:
    """One object of a scene: registry name (set/object) and its free-body state
    q = (qw, qx, qy, qz, x, y, z), exactly as the plant stores it (so a scene reloads bit for bit)."""

    name: str
    q: tuple[float, float, float, float, float, float, float]

    def matrix(self) -> np.ndarray:
        """4x4 world pose."""
        w, x, y, z = np.asarray(self.q[:4]) / np.linalg.norm(self.q[:4])  # the plant's may drift from 1
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = self.q[4:]
        return T


@dataclass(frozen=True)
class Heap:
    """A settled scene as data: reloadable into any station of the same environment."""

    seed: int
    environment: str
    objects: tuple[ObjectPose, ...]
    target: str = ""  # the `name` of the target entry, "" if none
    target_index: int = -1
    visible_ratios: tuple[float, ...] = field(default=())
    seconds: float = 0.0

    def object_names(self) -> list[str]:
        return [o.name for o in self.objects]


@dataclass(frozen=True, eq=False)
class ObjectGeometry:
    """Simulation ground truth for grasp planners: an object's surface mesh in its own frame
    (vertices (V, 3) float, faces (F, 3) int), its 4x4 world pose, mass and optional centre of
    mass (object frame; None = the mesh's volume centroid). `id` matches InstanceMasks.ids."""

    id: str
    vertices: np.ndarray
    faces: np.ndarray
    X_WO: np.ndarray
    mass: float
    com: tuple[float, float, float] | None = None


@dataclass(frozen=True, eq=False)
class JointLimits:
    """Per-joint velocity, acceleration and jerk limits of an arm (ruckig timing); the table of
    every station arm is ms_drake.robots (`arm_joint_limits(arm)`)."""

    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray

    @staticmethod
    def uniform(n: int, velocity: float, acceleration: float, jerk: float) -> "JointLimits":
        return JointLimits(np.full(n, velocity), np.full(n, acceleration), np.full(n, jerk))
