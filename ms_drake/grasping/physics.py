"""Physics grasp labels: close a compliant hydroelastic jaw pair on an object, lift, report.

`simulate_grasp(mesh, X_WO, grasp, mass)` builds, in its own MultibodyPlant (discrete, SAP),
a free-floating parallel-jaw gripper at the grasp pose and the object as a free rigid body:

- hand: a body on a prismatic joint along world z ("lift"), PD-driven (SAP implicit PD);
- two fingers on prismatic joints along the grasp axis, each carrying the station jaw's
  compliant hydroelastic pad (ms_drake.robots.PadConfig: outline, thickness, hydroelastic
  modulus, relaxation time under SAP, friction); each finger runs a velocity servo (SAP implicit PD with kp = 0) towards
  `close_speed`, its effort clamped at the closing force (the force limit), so a blocked finger
  squeezes with exactly f_C; a coupler constraint keeps the two fingers symmetric (a parallel
  gripper's linkage), so the first finger to touch pushes the object towards the centre;
- object: rigid hydroelastic surface mesh, mass and inertia from the mesh at uniform density
  (COM = volume centroid unless given).

Phases (our choice; the reference's Flex trials "move to the grasp pose, close, lift"):
  close (0.35 s, object weightless: an applied force cancels its gravity, so the first jaw to
  touch can push it but it does not fall before the grasp is made -- the quasi-static models'
  "both jaws touch simultaneously"), settle with gravity (0.1 s), lift `lift_height` on a
  smooth ramp (0.3 s), hold (0.2 s).
Success: the object rose by at least half the lift and moved less than `slip_tolerance`
relative to the hand between the end of closing and the end of the hold.

Perturbations (seeded, like the robust quality's): the grasp pose (sigma_t, sigma_r), the
friction coefficient and the mass. `label_grasp` runs `trials` seeded trials.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import trimesh
from pydrake.common import MemoryFile
from pydrake.common.value import AbstractValue
from pydrake.geometry import (
    AddCompliantHydroelasticProperties,
    AddContactMaterial,
    AddRigidHydroelasticProperties,
    Box,
    Convex,
    InMemoryMesh,
    Mesh,
    ProximityProperties,
)
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.math import SpatialForce
from pydrake.multibody.plant import (
    AddMultibodyPlant,
    CoulombFriction,
    ExternallyAppliedSpatialForce,
    MultibodyPlantConfig,
)
from pydrake.multibody.tree import (
    FixedOffsetFrame,
    PdControllerGains,
    PrismaticJoint,
    RotationalInertia,
    SpatialInertia,
    UnitInertia,
)
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial
from pydrake.visualization import AddDefaultVisualization
from scipy.spatial.transform import Rotation

from ms_drake.geometry import as_matrix4
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp
from ms_drake.robots import PadConfig


def _pad_polygon(pad: PadConfig) -> np.ndarray:
    """The pad's outline in the finger frame used here (x along the approach, y lateral): the
    station pad's (u lateral, v along the approach) swapped; the default rectangle is width (u)
    x length (v)."""
    if pad.polygon is None:
        u, v = 0.5 * pad.width, 0.5 * pad.length
        return np.array([[-v, -u], [v, -u], [v, u], [-v, u]], float)
    return np.asarray(pad.polygon, float)[:, ::-1].copy()


@dataclass(frozen=True)
class GraspOutcome:
    success: bool
    lifted: float  # m the object rose
    slip: float  # m the object moved relative to the hand after closing
    contact: bool  # both pads touched the object at the end of closing
    seconds: float  # wall time


def _obj_text(vertices: np.ndarray, faces: np.ndarray) -> str:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _pad_shape(pad: PadConfig):
    """(shape, X_FP): the pad geometry and its pose in the finger frame (pad face at z = 0,
    body towards -z, i.e. the pad pushes along +z): a box for the default rectangle, else the
    convex prism of the polygon (as the station's gripper model)."""
    p = _pad_polygon(pad)
    if pad.polygon is None:
        lo, hi = p.min(axis=0), p.max(axis=0)
        c = 0.5 * (lo + hi)
        return Box(*(hi - lo), pad.thickness), RigidTransform([c[0], c[1], -0.5 * pad.thickness])
    verts = np.vstack([np.column_stack([p, np.zeros(len(p))]),
                       np.column_stack([p, np.full(len(p), -pad.thickness)])])

    hull = trimesh.convex.convex_hull(verts)
    mesh = InMemoryMesh()
    mesh.mesh_file = MemoryFile(_obj_text(hull.vertices, hull.faces), ".obj", "pad.obj")
    return Convex(mesh), RigidTransform()


def _perturb(grasp: ParallelJawGrasp, friction: float, mass: float, rng, sigma_t, sigma_r, sigma_f, sigma_m):
    R = Rotation.from_rotvec(rng.normal(scale=sigma_r, size=3)).as_matrix()
    g = ParallelJawGrasp(grasp.center + rng.normal(scale=sigma_t, size=3), R @ grasp.axis, R @ grasp.approach,
                         grasp.width)
    return g, max(0.05, friction + rng.normal(scale=sigma_f)), mass * max(0.1, 1 + rng.normal(scale=sigma_m))


class CancelWeight(LeafSystem):
    """Output ``forces`` (list of one ExternallyAppliedSpatialForce, for the plant's applied spatial
    force input): on body `body_index` at its point `p_BoBq_B` (the centre of mass), the force
    -`weight_W` (the body's weight m g in world, N) while the time is before `until` [s], zero from
    then on."""

    def __init__(self, body_index, p_BoBq_B, weight_W, until: float):
        super().__init__()
        self.DeclareAbstractOutputPort("forces", lambda: AbstractValue.Make([ExternallyAppliedSpatialForce()]),
                                       self._calc)
        self.body_index = body_index
        self.p_BoBq_B = np.asarray(p_BoBq_B, float).reshape(3)
        self.weight_W = np.asarray(weight_W, float).reshape(3)
        self.until = float(until)

    def _calc(self, context, out):
        F = ExternallyAppliedSpatialForce()
        F.body_index = self.body_index
        F.p_BoBq_B = self.p_BoBq_B
        F.F_Bq_W = SpatialForce(np.zeros(3), -self.weight_W if context.get_time() < self.until else np.zeros(3))
        out.set_value([F])


def simulate_grasp(mesh, X_WO, grasp: ParallelJawGrasp, mass: float, *, pad: PadConfig | None = None,
                   closing_force: float = 10.0, friction: float | None = None, com=None,
                   lift_height: float = 0.08, slip_tolerance: float = 0.02, close_speed: float = 0.15,
                   time_step: float = 2e-3, seed: int | None = None, sigma_t: float = 0.002,
                   sigma_r: float = 0.03, sigma_friction: float = 0.1, sigma_mass: float = 0.1,
                   meshcat=None) -> GraspOutcome:
    """Simulate one grasp (world frame; X_WO: the object's pose, RigidTransform or 4x4 array).
    With `seed` set, the grasp pose, friction and mass are perturbed from
    numpy.random.default_rng(seed); seed=None runs the nominal grasp.
    pad: the station's jaw pad (ms_drake.robots.PadConfig, default: the one the station's parallel
    jaw carries); friction: the object-pad Coulomb coefficient, static and dynamic (default: the
    pad's mu_static / mu_dynamic)."""

    t_wall = time.perf_counter()
    X = as_matrix4(X_WO, "X_WO")
    pad = pad or PadConfig()
    mu_s, mu_d = (pad.mu_static, pad.mu_dynamic) if friction is None else (float(friction), float(friction))
    mu = mu_s
    if not isinstance(grasp, ParallelJawGrasp):
        grasp = ParallelJawGrasp.from_grasp(grasp)
    if not (mass > 0 and closing_force > 0 and mu > 0):
        raise GraspError(f"simulate_grasp needs mass, closing_force and friction > 0 "
                         f"(got {mass}, {closing_force}, {mu})")
    if not mesh.is_watertight:
        raise GraspError("simulate_grasp needs a watertight object mesh (for its volume and inertia)")
    if seed is not None:
        grasp, mu, mass = _perturb(grasp, mu, mass, np.random.default_rng(seed), sigma_t, sigma_r,
                                   sigma_friction, sigma_mass)
        mu_d = min(mu_d * mu / mu_s, mu)  # the perturbation scales both coefficients
        mu_s = mu

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=time_step, discrete_contact_approximation="sap",
                             contact_model="hydroelastic_with_fallback"), builder)

    # ---------------------------------------------------------------- object
    obj = plant.AddModelInstance("object")
    com_O = np.asarray(mesh.center_mass if com is None else com, float)
    Ic = np.asarray(mesh.moment_inertia, float) * (mass / mesh.volume)  # about the mesh's own COM
    body = plant.AddRigidBody("object", obj, SpatialInertia.MakeFromCentralInertia(
        mass, com_O, RotationalInertia(Ic[0, 0], Ic[1, 1], Ic[2, 2], Ic[0, 1], Ic[0, 2], Ic[1, 2])))
    mem = InMemoryMesh()
    mem.mesh_file = MemoryFile(_obj_text(np.asarray(mesh.vertices), np.asarray(mesh.faces)), ".obj", "object.obj")
    props = ProximityProperties()
    AddRigidHydroelasticProperties(0.005, props)
    AddContactMaterial(friction=CoulombFriction(mu_s, mu_d), properties=props)
    plant.RegisterCollisionGeometry(body, RigidTransform(), Mesh(mem), "object", props)

    # ---------------------------------------------------------------- gripper
    R_WG = np.column_stack([grasp.approach, np.cross(grasp.axis, grasp.approach), grasp.axis])
    X_WG = RigidTransform(RotationMatrix(R_WG), grasp.center)
    hand_mi = plant.AddModelInstance("hand")
    fing_mi = plant.AddModelInstance("fingers")
    unit = UnitInertia.SolidBox(0.04, 0.04, 0.04)
    hand = plant.AddRigidBody("hand", hand_mi, SpatialInertia(0.5, np.zeros(3), unit))
    G = plant.AddFrame(FixedOffsetFrame("grasp_frame", plant.world_frame(), X_WG))
    lift = plant.AddJoint(PrismaticJoint("lift", G, hand.body_frame(), R_WG.T @ np.array([0, 0, 1.0])))
    a_lift = plant.AddJointActuator("lift", lift, 1e4)
    a_lift.set_controller_gains(PdControllerGains(p=2e4, d=1.5e3))
    half = 0.5 * grasp.width
    shape, X_FP = _pad_shape(pad)
    pad_props = ProximityProperties()
    AddCompliantHydroelasticProperties(pad.resolution_hint, pad.hydroelastic_modulus, pad_props)
    AddContactMaterial(friction=CoulombFriction(mu_s, mu_d), properties=pad_props)
    pad_props.AddProperty("material", "relaxation_time", pad.relaxation_time)
    # velocity servo clamped at the force limit: u = clamp(kd (v_close - v), f_C); the free finger
    # closes at ~close_speed, a blocked one squeezes with f_C (kd v_close = 10 f_C)
    kd = 10.0 * closing_force / close_speed
    fingers = []
    for k, sign in enumerate((1.0, -1.0)):
        f = plant.AddRigidBody(f"finger{k}", fing_mi, SpatialInertia(0.03, np.zeros(3), unit))
        # finger frame: origin on the pad face, z = its closing direction (sign * grasp axis)
        R_HF = np.eye(3) if sign > 0 else np.diag([1.0, -1.0, -1.0])
        Fo = plant.AddFrame(FixedOffsetFrame(f"finger{k}_open", hand.body_frame(),
                                            RigidTransform(RotationMatrix(R_HF), [0, 0, -sign * half])))
        j = plant.AddJoint(PrismaticJoint(f"finger{k}_joint", Fo, f.body_frame(), [0, 0, 1.0],
                                          pos_lower_limit=-0.005, pos_upper_limit=half + 0.005))
        a = plant.AddJointActuator(f"finger{k}", j, closing_force)
        a.set_controller_gains(PdControllerGains(p=0.0, d=kd))
        plant.RegisterCollisionGeometry(f, X_FP, shape, f"pad{k}", pad_props)
        fingers.append((f, j))
    # the fingers move symmetrically, as a parallel gripper's linkage makes them (SAP coupler)
    plant.AddCouplerConstraint(fingers[0][1], fingers[1][1], 1.0, 0.0)
    plant.set_gravity_enabled(hand_mi, False)
    plant.set_gravity_enabled(fing_mi, False)
    plant.Finalize()

    # ---------------------------------------------------------------- inputs
    T_close, T_settle, T_lift, T_hold = 0.35, 0.1, 0.3, 0.2
    t1 = T_close + T_settle
    ts = np.array([0.0, t1, t1 + T_lift, t1 + T_lift + T_hold])
    zs = np.array([[0.0, 0.0, lift_height, lift_height]])
    lift_traj = PiecewisePolynomial.CubicHermite(ts, zs, np.zeros_like(zs))
    traj = builder.AddSystem(TrajectorySource(lift_traj, output_derivative_order=1))
    builder.Connect(traj.get_output_port(), plant.get_desired_state_input_port(hand_mi))
    closed = half + 0.005
    src = builder.AddSystem(ConstantVectorSource(np.array([closed, closed, close_speed, close_speed])))
    builder.Connect(src.get_output_port(), plant.get_desired_state_input_port(fing_mi))

    # the object is weightless until closing ends
    weight = mass * plant.gravity_field().gravity_vector()
    wl = builder.AddSystem(CancelWeight(body.index(), com_O, weight, T_close))
    builder.Connect(wl.get_output_port(), plant.get_applied_spatial_force_input_port())
    if meshcat is not None:
        AddDefaultVisualization(builder, meshcat)
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    pc = plant.GetMyMutableContextFromRoot(ctx)
    plant.SetFreeBodyPose(pc, body, RigidTransform(X))
    sim.Initialize()
    sim.AdvanceTo(T_close)
    X_WH0 = plant.EvalBodyPoseInWorld(pc, hand)
    X_HO0 = X_WH0.inverse() @ plant.EvalBodyPoseInWorld(pc, body)
    z0 = plant.EvalBodyPoseInWorld(pc, body).translation()[2]
    q_f = [j.get_translation(pc) for _, j in fingers]
    # both pads touch: each finger stopped short of closing fully
    contact = all(q < half - 1e-4 for q in q_f)
    if contact:
        def dropped(root_context):  # stop early once the object has clearly left the hand
            c = plant.GetMyContextFromRoot(root_context)
            X_HO = plant.EvalBodyPoseInWorld(c, hand).inverse() @ plant.EvalBodyPoseInWorld(c, body)
            if np.linalg.norm(X_HO.translation() - X_HO0.translation()) > 2 * slip_tolerance:
                return EventStatus.ReachedTermination(diagram, "object dropped")
            return EventStatus.Succeeded()

        sim.set_monitor(dropped)
        sim.AdvanceTo(ts[-1])
    X_WH = plant.EvalBodyPoseInWorld(pc, hand)
    X_WO_end = plant.EvalBodyPoseInWorld(pc, body)
    slip = float(np.linalg.norm((X_WH.inverse() @ X_WO_end).translation() - X_HO0.translation()))
    lifted = float(X_WO_end.translation()[2] - z0)
    ok = bool(contact and lifted >= 0.5 * lift_height and slip < slip_tolerance)
    return GraspOutcome(ok, lifted, slip, contact, time.perf_counter() - t_wall)


def label_grasp(mesh, X_WO, grasp, mass, trials: int = 3, seed: int = 0, **kwargs) -> list[GraspOutcome]:
    """`trials` perturbed physics trials, trial i seeded by (seed, i)."""
    return [simulate_grasp(mesh, X_WO, grasp, mass, seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]),
                           **kwargs) for i in range(trials)]
