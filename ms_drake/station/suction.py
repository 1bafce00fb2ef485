"""SuctionCup: a vacuum cup as externally applied forces (the idea of Drake's suction-gripper
example: a pulling force between the cup and the object it is sealed on).

Model (choices recorded here; the reference gives none beyond "seal feasibility"):
  * The cup is a disc of radius r (its lip) at frame C (the gripper's `tcp`, z = approach) on
    body B.
  * With vacuum on, the candidate object is the nearest geometry within `max_gap` of the cup
    centre that belongs to a body that is not welded to the world and not in `exclude_bodies`.
  * Lip opening s: the largest signed distance from `rim_samples` lip points to that object: how
    far the lip stands off the face where it is farthest from it (a face tilted by t against the
    cup, pressed in at one side, stands off about 2 r sin(t) minus that press at the other).
  * Seal: the surface normal (seen from max_gap back along the axis, outside the face even when
    the lip presses into a thin part) is within `max_tilt` of the cup axis and s <= max_gap +
    seal_tolerance. max_gap is the lip's reach (the bellows' travel: a cup whose lip stays within
    8 mm of the face all round keeps its vacuum, as the bellows follow the face); over the next
    seal_tolerance the lip leaks, and beyond it the seal is lost.
  * Pull: the vacuum's resultant f = max_force * clip((max_gap + seal_tolerance - s) /
    seal_tolerance, 0, 1) -- the full force while the lip reaches the face all round, fading to 0
    as it leaks -- along -z_C, at the object's point nearest to the cup centre (the pressure's
    resultant acts at the centre of the sealed disc); the opposite force acts on the cup body at
    the same point. The pull does not depend on the gap inside the seal: a sealed cup pulls with
    the pressure difference times its area whatever the lip's deflection.
  * Moment: the cup resists a moment about its lip as a real cup does. A load that peels the
    face off (e.g. an object held by a vertical face, its weight acting behind the cup) turns it
    about the lip point on the loaded side, where the cup's own compliant contact geometry
    presses on the face; about that point the pull at the centre gives a restoring moment up to
    f * r (0.6 N m at 40 N and r = 15 mm). Below that the face tilts on the compliant lip and
    stays sealed (on the bluction tool's cup, hydroelastic modulus 2e5 Pa: about 8 degrees at
    0.12 N m, 18-20 degrees at 0.44-0.6 N m; measured 2026-12-02, commit 51e2fb0); beyond it the face turns until
    the far lip leaks (s > max_gap + seal_tolerance, a tilt of about 25 degrees) and the object
    falls.
    There is no stiffness of its own in this model: the lip's resistance is the contact's, which
    Drake solves implicitly (stable at the station's 10 ms step for any held mass).
  * Stateless: releasing is turning the vacuum off (the force vanishes at once).
Defaults: max_force 40 N ~ 57 kPa vacuum over the 0.03 m diameter cup (the reference's bluction
cup, line 1608; typical of a small vacuum pump); max_gap 8 mm, the bellows' travel (as
max_deflection of ms_drake.grasping.suction); seal_tolerance 4 mm of leaking lip; max_tilt 30 degrees.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.geometry import QueryObject
from pydrake.math import RigidTransform
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import ExternallyAppliedSpatialForce
from pydrake.multibody.tree import BodyIndex
from pydrake.systems.framework import BasicVector, LeafSystem

from ms_drake.geometry import as_rigid_transform

# suction_state layout
HOLDING, BODY_INDEX, GAP = 0, 1, 2


class SuctionCup(LeafSystem):
    """Vacuum cup on one body of `plant`.

    Input ports:
      suction        (1)  vacuum command; on when > 0.5
      body_poses     abstract list[RigidTransform] (plant.get_body_poses_output_port())
      query_object   abstract QueryObject (scene_graph.get_query_output_port())
    Output ports:
      spatial_forces abstract list[ExternallyAppliedSpatialForce] -> plant's applied_spatial_force
      suction_state  (3) [holding (0/1), held body index (-1 if none), gap [m] (nan if none)]
    """

    def __init__(self, plant, cup_body, X_BC: RigidTransform, radius: float, max_gap: float = 0.008,
                 max_force: float = 40.0, seal_tolerance: float = 0.004, max_tilt_deg: float = 30.0,
                 rim_samples: int = 8, exclude_bodies=()):
        super().__init__()
        # ports first
        self._suction = self.DeclareVectorInputPort("suction", 1)
        self._poses = self.DeclareAbstractInputPort("body_poses", AbstractValue.Make([RigidTransform()]))
        self._query = self.DeclareAbstractInputPort("query_object", AbstractValue.Make(QueryObject()))
        self.DeclareAbstractOutputPort("spatial_forces", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
                                       self._calc_forces)
        self.DeclareVectorOutputPort("suction_state", 3, self._calc_state)

        if radius <= 0 or max_gap <= 0 or max_force < 0 or seal_tolerance <= 0:
            raise ValueError(f"SuctionCup: radius ({radius}), max_gap ({max_gap}) and seal_tolerance "
                             f"({seal_tolerance}) must be > 0 m and max_force ({max_force}) >= 0 N")
        self._plant = plant
        self._cup = cup_body.index()
        self._X_BC = as_rigid_transform(X_BC, "X_BC")
        self._r = radius
        self._max_gap = max_gap
        self._max_force = max_force
        self._seal_tol = seal_tolerance
        self._cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
        angles = np.linspace(0, 2 * np.pi, rim_samples, endpoint=False)
        self._rim_C = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros_like(angles)], 1)
        excluded = {int(b) for b in exclude_bodies} | {int(self._cup)}
        excluded |= {int(b.index()) for b in plant.GetBodiesWeldedTo(plant.world_body())}
        # every body of the cup's own model instance (e.g. the bluction blade)
        excluded |= {int(b) for b in plant.GetBodyIndices(cup_body.model_instance())}
        self._excluded = excluded

    # -- ports
    def suction_input(self):
        return self._suction

    def body_poses_input(self):
        return self._poses

    def query_object_input(self):
        return self._query

    # -- model
    def pull_fraction(self, opening: float) -> float:
        """The vacuum's pull as a fraction of max_force at lip opening `opening` [m] (module docstring)."""
        return float(np.clip((self._max_gap + self._seal_tol - opening) / self._seal_tol, 0.0, 1.0))

    def _body_of(self, inspector, geometry_id) -> int:
        return int(self._plant.GetBodyFromFrameId(inspector.GetFrameId(geometry_id)).index())

    def _nearest(self, query, p_W, body=None):
        """Nearest result among allowed bodies (or only `body`) within the search threshold."""
        inspector = query.inspector()
        best = None
        for res in query.ComputeSignedDistanceToPoint(p_W, self._max_gap + self._seal_tol + self._r):
            b = self._body_of(inspector, res.id_G)
            if (body is None and b in self._excluded) or (body is not None and b != body):
                continue
            if best is None or res.distance < best[0].distance:
                best = (res, b)
        return best

    def evaluate(self, context):
        """Returns (force [N], object body index, gap, p_W application point, axis z_C) or None."""
        if self._suction.Eval(context)[0] <= 0.5:
            return None
        poses = self._poses.Eval(context)
        query = self._query.Eval(context)
        X_WC = poses[int(self._cup)] @ self._X_BC
        p_WC = X_WC.translation()
        z = X_WC.rotation().matrix()[:, 2]
        hit = self._nearest(query, p_WC)
        if hit is None or hit[0].distance > self._max_gap:
            return None
        res, body = hit
        # The face's normal must face the cup (-normal ~ z_C). It is the distance's gradient seen from
        # a point backed off along the cup axis by the lip's reach, outside the face: at the cup
        # centre itself the gradient turns to the far side once the compliant lip presses the centre
        # past the middle of a thin part (a packaged object's few-mm backing), which read as a lost
        # seal for 10-30 ms at a time while the cup held the part.
        back = self._nearest(query, p_WC - self._max_gap * z, body=body)
        normal = (back[0] if back is not None else res).grad_W
        if -np.dot(normal, z) < self._cos_tilt:
            return None
        rim = []
        for p_C in self._rim_C:
            h = self._nearest(query, X_WC @ p_C, body=body)
            if h is None:
                return None
            rim.append(h[0].distance)
        rim = np.array(rim)
        opening = float(rim.max())
        force = self._max_force * self.pull_fraction(opening)
        if force <= 0:
            return None
        gap = max(float(res.distance), 0.0)
        X_WG = query.GetPoseInWorld(res.id_G)
        p_WN = X_WG @ res.p_GN
        return force, body, gap, p_WN, z

    def _calc_forces(self, context, output):
        hit = self.evaluate(context)
        if hit is None or hit[0] <= 0:
            output.set_value([])
            return
        force, body, _, p_WN, z = hit
        poses = self._poses.Eval(context)
        on_obj = ExternallyAppliedSpatialForce()
        on_obj.body_index = BodyIndex(body)
        on_obj.p_BoBq_B = poses[body].inverse() @ p_WN
        on_obj.F_Bq_W = SpatialForce(np.zeros(3), -force * z)
        on_cup = ExternallyAppliedSpatialForce()
        on_cup.body_index = self._cup
        on_cup.p_BoBq_B = poses[int(self._cup)].inverse() @ p_WN
        on_cup.F_Bq_W = SpatialForce(np.zeros(3), force * z)
        output.set_value([on_obj, on_cup])

    def _calc_state(self, context, output: BasicVector):
        hit = self.evaluate(context)
        if hit is None:
            output.SetFromVector([0.0, -1.0, np.nan])
        else:
            output.SetFromVector([1.0, float(hit[1]), hit[2]])


def add_suction_cup(builder, plant, scene_graph, gripper_instance, radius: float, tcp_frame: str = "tcp",
                    name: str = "suction", **kwargs) -> SuctionCup:
    """Add a SuctionCup for the gripper model `gripper_instance` (cup at its `tcp_frame`) and wire
    body_poses, query_object and spatial_forces. The caller exports `suction` / `suction_state`.

    If the plant's applied_spatial_force input is already used, combine forces yourself instead.
    """
    frame = plant.GetFrameByName(tcp_frame, gripper_instance)
    cup = SuctionCup(plant, frame.body(), frame.GetFixedPoseInBodyFrame(), radius, **kwargs)
    cup.set_name(name)
    builder.AddSystem(cup)
    builder.Connect(plant.get_body_poses_output_port(), cup.body_poses_input())
    builder.Connect(scene_graph.get_query_output_port(), cup.query_object_input())
    builder.Connect(cup.GetOutputPort("spatial_forces"), plant.get_applied_spatial_force_input_port())
    return cup
