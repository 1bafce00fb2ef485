"""Building blocks for contact wrench sets (shared by every contact model).

A contact wrench set is written either as the convex hull of generator wrenches (vertex form,
`hull`) or as linear inequalities on a wrench variable (`halfspaces`, used by MFE and 6DFC).
Wrenches are about the object's centre of mass, in object-frame axes: w = [f; (p - com) x f].
"""

from __future__ import annotations

import functools

import numpy as np

from ms_drake.grasping.geometry import cross
from ms_drake.grasping.wrench_qp import WrenchProblem


def wrench(points: np.ndarray, forces: np.ndarray, com: np.ndarray, torques: np.ndarray | None = None) -> np.ndarray:
    """(6, K) wrenches of forces (K, 3) applied at points (K, 3) (plus pure torques (K, 3))."""
    forces = np.atleast_2d(forces)
    tau = cross(np.atleast_2d(points) - com, forces)
    if torques is not None:
        tau = tau + torques
    return np.vstack([forces.T, tau.T])


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to unit n (and to each other)."""
    helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = cross(n, helper)
    t1 /= np.linalg.norm(t1)
    return t1, cross(n, t1)


@functools.cache
def sphere_samples(count: int = 18) -> np.ndarray:
    """Deterministic, antipodally symmetric unit vectors on S^2 used to linearize 3D ellipsoidal
    limit surfaces. count = 18 (the reference's j = 18, line 185): the 6 axis directions plus the
    12 icosahedron vertices. Other even counts: symmetric Fibonacci points."""
    if count == 18:
        g = (1 + 5 ** 0.5) / 2
        ico = np.array([[0, s1, s2 * g] for s1 in (-1, 1) for s2 in (-1, 1)]
                       + [[s1, s2 * g, 0] for s1 in (-1, 1) for s2 in (-1, 1)]
                       + [[s2 * g, 0, s1] for s1 in (-1, 1) for s2 in (-1, 1)], float)
        ico /= np.linalg.norm(ico, axis=1, keepdims=True)
        return np.vstack([np.eye(3), -np.eye(3), ico])
    if count % 2:
        raise ValueError("sphere_samples needs an even count (antipodal pairs)")
    half = count // 2
    i = np.arange(half) + 0.5
    z = 1 - i / half  # upper hemisphere
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(np.maximum(1 - z * z, 0))
    up = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return np.vstack([up, -up])


def normalizer(mass: float, gravity: float, length: float) -> np.ndarray:
    """Diagonal of W: forces / (m g), torques / (m g L)."""
    mg = mass * gravity
    return np.concatenate([np.full(3, 1.0 / mg), np.full(3, 1.0 / (mg * length))])


def hull(generators: np.ndarray, include_origin: bool) -> WrenchProblem:
    """conv(generators) (sum of weights = 1) or conv({0} u generators) (sum <= 1)."""
    k = generators.shape[1]
    return WrenchProblem(
        G=generators, t=np.zeros(6), A=np.ones((1, k)),
        lo=np.array([-np.inf if include_origin else 1.0]), hi=np.ones(1),
        lb=np.zeros(k), ub=np.full(k, np.inf), blocks=[(0, k, include_origin)])


def halfspaces(G: np.ndarray, A: np.ndarray, hi: np.ndarray, lb: np.ndarray, ub: np.ndarray) -> WrenchProblem:
    """{G x : A x <= hi, lb <= x <= ub}."""
    return WrenchProblem(G=G, t=np.zeros(6), A=A, lo=np.full(len(hi), -np.inf), hi=hi, lb=lb, ub=ub)


def ellipsoid_generators(point, normal_in, com, f_t_max, tau_max, samples: np.ndarray, t1=None, t2=None):
    """Friction wrenches on the boundary of the 3D limit-surface ellipsoid
    ||f_t||^2 / f_t_max^2 + tau^2 / tau_max^2 = 1 at one point with inward normal `normal_in`."""
    if t1 is None:
        t1, t2 = tangent_basis(normal_in)
    forces = f_t_max * (samples[:, 0:1] * t1 + samples[:, 1:2] * t2)
    torques = tau_max * samples[:, 2:3] * normal_in
    return wrench(np.broadcast_to(point, forces.shape), forces, com, torques)
