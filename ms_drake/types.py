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
    ids: length-K labels; in simulation the model-instance name of the object, else "seg_k". A
      segmenter that cuts one simulated object into pieces gives its largest piece the object's
      name and each other piece ``<name>@<k>`` (`object_of` gives the object back).
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


FRAGMENT_MARK = "@"


def object_of(mask_id: str) -> str:
    """The simulated object a mask id names: ``name@k`` (another piece of one object) -> ``name``."""
    return mask_id.split(FRAGMENT_MARK, 1)[0]


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
    quality: the robust quality (fraction of perturbed trials that lift the object); lifts: the
    nominal (unperturbed) contact model's verdict that the grasp lifts the object under
    quasi-static conditions (None: not evaluated, e.g. a pre-computed grasp set's grasp).
    posture: which of a robot's pick plans of the grasp to execute (the rank in
    planning.sequences.pick_plans; 0 the first that plans): the one a reach check found clear of
    the scene (execution.reach.PickReach).
    """

    kind: str
    center: tuple[float, float, float]
    approach: tuple[float, float, float]
    axis: tuple[float, float, float] = (0.0, 0.0, 0.0)
    width: float = 0.0
    quality: float = 0.0
    model: str = ""
    object_id: str = ""
    lifts: bool | None = None
    posture: int = 0


@dataclass(frozen=True)
class Push:
    """A linear push from `start` to `end` (world frame, constant height)."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    object_id: str = ""


@dataclass(frozen=True)
class ShelfAction:
    """A shelf action (Ch. 9.2) with the bluction tool, in the shelf frame (x across the opening,
    y into the shelf, z up; the open front at y = -depth/2).

    kind "push": the blade, inserted beside `object_id`, pushes it a signed distance `dx` along x
      (it stops earlier where it touches a neighbour).
    kind "suction": the cup grasps the object's front face, lifts it, pulls it out of the shelf,
      translates it by `dx` along x and pushes it back in until its front face is `dy` behind the
      shelf's front plane (the reference's "distance d_y into the shelf").
    """

    kind: str  # "push" | "suction"
    object_id: str
    dx: float = 0.0
    dy: float = 0.0


SHELF_OBJECT_KINDS = ("box", "cylinder")


@dataclass(frozen=True)
class ShelfObject:
    """An upright object on the shelf floor (shelf frame, metres): a box axis-aligned with the
    shelf (`width` along x, `depth` along y) or a cylinder (`width` = `depth` = diameter), its
    footprint centred at (x, y), standing on the floor (z from 0 to `height`)."""

    id: str
    kind: str  # "box" | "cylinder"
    x: float
    y: float
    width: float
    depth: float
    height: float

    def __post_init__(self):
        if self.kind not in SHELF_OBJECT_KINDS:
            raise ValueError(f"ShelfObject {self.id!r}: kind={self.kind!r}; use one of {', '.join(SHELF_OBJECT_KINDS)}")
        if min(self.width, self.depth, self.height) <= 0:
            raise ValueError(f"ShelfObject {self.id!r}: width, depth and height must be > 0, got "
                             f"{self.width}, {self.depth}, {self.height}")
        if self.kind == "cylinder" and abs(self.width - self.depth) > 1e-12:
            raise ValueError(f"ShelfObject {self.id!r}: a cylinder has width == depth (its diameter), got "
                             f"{self.width} and {self.depth}")

    def moved(self, x: float, y: float) -> "ShelfObject":
        return ShelfObject(self.id, self.kind, float(x), float(y), self.width, self.depth, self.height)


@dataclass(frozen=True)
class ShelfScene:
    """A shelf scene: the occluding objects, the target (None when unknown, e.g. to a policy) and
    the seed it was generated from."""

    objects: tuple[ShelfObject, ...]
    target: ShelfObject | None = None
    seed: int = -1

    def object(self, object_id: str) -> ShelfObject:
        for o in self.objects:
            if o.id == object_id:
                return o
        raise KeyError(f"no object {object_id!r} in the shelf scene; objects: {', '.join(o.id for o in self.objects)}")

    def without_target(self) -> "ShelfScene":
        return ShelfScene(self.objects, None, self.seed)


@dataclass(frozen=True, eq=False)
class ShelfOccupancy:
    """Target occupancy on a shelf (Ch. 9.4.2): `floor` (ny, nx) over target footprint centres on
    the shelf floor, cell (i, j) at (x0 + j * step, y0 + i * step) in the shelf frame; `image_x`
    (W,) the 1D distribution P_t(x) along the camera image's x axis. Each sums to 1, or is all 0
    when no placement is possible; the learned backend's `floor` is empty (shape (0, 0))."""

    floor: np.ndarray
    image_x: np.ndarray
    x0: float = 0.0
    y0: float = 0.0
    step: float = 0.0


@dataclass(frozen=True)
class Action:
    """What the PolicySelector asks the executor to do. kind: grasp | push | shelf | stop.
    scene: for a shelf action, the observed ShelfScene it was chosen in (a backend without the
    objects' true poses, e.g. on the hardware station, plans the action from it); None otherwise."""

    kind: str
    grasp: Grasp | None = None
    push: Push | None = None
    shelf: ShelfAction | None = None
    reason: str = ""
    scene: ShelfScene | None = None


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
