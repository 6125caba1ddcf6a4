"""Explicit forces for engines that have no element for an effect, and the
calibration of the engines' own drag models where they have one.

Drag uses the engine's own model where it reproduces the spec's law (each
calibrated to the spec's coefficients, as restitution is): MuJoCo's
ellipsoid fluid model for spheres (:func:`mujoco_fluid`), Bullet's
per-body ``linearDamping`` for linear drag (:func:`bullet_linear_damping`),
pymunk's ``space.damping`` for linear drag shared by every body
(:func:`pymunk_damping`).  Elsewhere drag is physbench's force law applied
as an external force each step, and the row says so (:data:`DRAG_EXTERNAL`
in ``notes`` and ``info["drag"]``).  Springs and dampers on pybullet are
external forces too (MuJoCo has tendons, pymunk has DampedSpring).  Each
external force is evaluated from the state at the start of an engine step
and held over it (explicit in time, like the engines' own gravity).

The laws, in world coordinates (SI units):

- drag on body i: F = -(c_linear + c_quadratic |v|) v at the centre of mass,
  no drag torque;
- spring/damper between anchors pa, pb (world points of the bodies'
  body-frame anchors, or world anchors), d = pb - pa, L = |d|, u = d / L:
  the force on a is (k (L - L0) + c (v_pb - v_pa) . u) u, on b its opposite.

Pinned by tests/test_adapter_pybullet.py (springs, dampers, drag against
analytic solutions), tests/test_adapter_mujoco.py,
tests/test_adapter_pymunk.py (drag), tests/test_adapter_rapier.py and
tests/test_adapter_box2d.py (:class:`StateForces`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.contract.conventions import DRAG_EXTERNAL  # noqa: F401 (the adapters' name for it)
from physbench.contract.rotation import quat_rotate
from physbench.contract.scene import Scene

DRAG_NOTE = (f"{DRAG_EXTERNAL}: F = -(c_linear + c_quadratic |v|) v on the centre of mass, evaluated at the "
             "velocity at the start of each engine step (explicit); no angular drag")


def drag_coefficients(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(c_linear (n,) kg/s, c_quadratic (n,) kg/m) per body, zero where the
    scene lacks the effect."""
    n = scene.n_bodies
    c1 = np.array([b.drag_linear for b in scene.bodies], float) if scene.has("drag_linear") else np.zeros(n)
    c2 = np.array([b.drag_quadratic for b in scene.bodies], float) if scene.has("drag_quadratic") else np.zeros(n)
    return c1, c2


def dragged(scene: Scene) -> list[tuple[int, float, float]]:
    """(body index, c_linear, c_quadratic) of every body with drag."""
    c1, c2 = drag_coefficients(scene)
    return [(i, float(c1[i]), float(c2[i])) for i in range(scene.n_bodies) if c1[i] > 0.0 or c2[i] > 0.0]


def _external(why: str) -> str:
    return f"{DRAG_EXTERNAL} ({why})"


def mujoco_fluid(scene: Scene, mscale: float = 1.0) -> tuple[dict[str, Any] | None, str]:
    """MuJoCo's ellipsoid fluid model set to the spec's drag, or why not.

    For a sphere of radius r the model's force with only the blunt drag
    coefficient C_b and the viscosity beta (density rho; slender, angular,
    Kutta and Magnus coefficients 0) is F = -(6 pi r beta + C_b rho pi r^2
    |v|) v, the spec's law with c_linear = 6 pi r beta and c_quadratic =
    C_b rho pi r^2 (rho = 1 here; forces on MuJoCo's masses scaled by
    ``mscale``).  beta and rho are global: every body must be a sphere
    (a body without a fluid geom would get MuJoCo's inertia-box drag) with
    one beta for all (c_linear / (6 pi r) equal).  The model adds a torque
    -8 pi r^3 beta w and, with rho > 0, added-mass forces on a spinning
    body that the spec does not have: no body may spin (no initial angular
    velocity, no friction, no springs to turn one).  Returns ({"viscosity",
    "density", "blunt" (n,)}, "") or (None, the reason) when drag is present
    but the model cannot reproduce it; (None, "") without drag."""
    c1, c2 = drag_coefficients(scene)
    if not (np.any(c1 > 0) or np.any(c2 > 0)):
        return None, ""
    if any(b.shape != "sphere" for b in scene.bodies):
        return None, "MuJoCo's fluid model is isotropic only for spheres, and its density and viscosity are global"
    if scene.has("friction") or scene.springs or any(np.any(b.angular_velocity != 0) for b in scene.bodies):
        return None, "MuJoCo's fluid model adds a viscous torque and added-mass forces on a spinning body"
    r = np.array([b.radius for b in scene.bodies], float)
    beta = c1 * mscale / (6.0 * math.pi * r)
    if np.ptp(beta) > 1e-12 * max(float(np.max(beta)), 1e-300):
        return None, "the bodies' c_linear / (6 pi r) differ, and MuJoCo's viscosity is global"
    return {"viscosity": float(beta[0]), "density": 1.0 if np.any(c2 > 0) else 0.0,
            "blunt": c2 * mscale / (math.pi * r * r)}, ""


def bullet_linear_damping(scene: Scene) -> dict[int, float]:
    """Bullet's per-body ``linearDamping`` d for the spec's linear drag:
    Bullet scales the velocity by (1 - d)^dt each step, the exact decay
    e^(-c_linear dt / m) of m v' = -c_linear v when d = 1 - e^(-c_linear / m).
    {body index: d} for the bodies with linear drag."""
    c1, _ = drag_coefficients(scene)
    return {i: float(-math.expm1(-c1[i] / scene.bodies[i].mass)) for i in range(scene.n_bodies) if c1[i] > 0}


def bullet_drag_notes(scene: Scene, damping: dict[int, float], maximal: bool, notes: list[str],
                      info: dict[str, Any]) -> None:
    """Say in ``notes`` and ``info["drag"]`` which drag Bullet carries
    (``damping``: :func:`bullet_linear_damping`'s, empty on btMultiBody
    bases) and which is applied as an external force."""
    drag = dragged(scene)
    if not drag:
        return
    if damping:
        notes.append("linear drag: Bullet's linearDamping d = 1 - e^(-c_linear / m) per body (the velocity is "
                     "scaled by (1 - d)^dt each step, the exact decay of m v' = -c_linear v)")
    external = [(i, c1, c2) for i, c1, c2 in drag if c2 > 0 or i not in damping]
    if not external:
        info["drag"] = "Bullet's linearDamping = 1 - e^(-c_linear / m)"
        return
    why = ("Bullet has no quadratic drag" if any(c2 > 0 for _, _, c2 in external) else
           "a btMultiBody base's damping is -m d (1 + |v|) v, another law")
    if not maximal and any(c1 > 0 for _, c1, _ in external) and "quadratic" in why:
        why += "; a btMultiBody base's damping is another law"
    info["drag"] = f"{DRAG_EXTERNAL} ({why})" + ("; linear drag: Bullet's linearDamping" if damping else "")
    notes.append(f"{DRAG_NOTE} ({why})" if not damping else
                 f"quadratic drag: {DRAG_EXTERNAL}, F = -c_quadratic |v| v at the centre of mass from the velocity "
                 "at the start of each step (explicit)")


def pymunk_damping(scene: Scene) -> tuple[float | None, str]:
    """pymunk's ``space.damping`` (velocity kept per second) for the spec's
    linear drag, e^(-c_linear / m), or why not: it is one value for the
    whole space and damps the angular velocity too, so every body must have
    the same c_linear / m, no quadratic drag, and none may spin (no initial
    angular velocity, no friction or springs to turn one).  (None, "")
    without drag."""
    c1, c2 = drag_coefficients(scene)
    if not (np.any(c1 > 0) or np.any(c2 > 0)):
        return None, ""
    if np.any(c2 > 0):
        return None, "pymunk has no quadratic drag"
    k = c1 / np.array([b.mass for b in scene.bodies], float)
    if np.ptp(k) > 1e-12 * float(np.max(k)):
        return None, "the bodies' c_linear / m differ, and pymunk's damping is one value for the space"
    if scene.has("friction") or scene.springs or any(np.any(b.angular_velocity != 0) for b in scene.bodies):
        return None, "pymunk's damping damps the angular velocity too"
    return float(math.exp(-float(k[0]))), ""


class PybulletForces:
    """Springs, dampers and drag as pybullet world-frame external forces
    (``applyExternalForce(..., WORLD_FRAME)``, cleared by Bullet after each
    step), applied by :meth:`apply` before every step.

    The engine's own state is read in the engine's own terms (xyzw
    quaternions, world velocities); nothing is converted to physbench's
    conventions here."""

    def __init__(self, scene: Scene, damped: frozenset[int] = frozenset()) -> None:
        """``damped``: bodies whose linear drag Bullet's linearDamping
        carries (:func:`bullet_linear_damping`): their c_linear is left out
        here."""
        self.springs = [(sp.a, sp.b, tuple(map(float, sp.anchor_a)), tuple(map(float, sp.anchor_b)),
                         float(sp.stiffness), float(sp.rest_length), float(sp.damping))
                        for sp in scene.springs if sp.stiffness != 0.0 or sp.damping != 0.0]
        self.drag = [(i, 0.0 if i in damped else c1, c2) for i, c1, c2 in dragged(scene)
                     if c2 > 0.0 or i not in damped]
        involved = {i for sp in self.springs for i in sp[:2] if i >= 0} | {i for i, _, _ in self.drag}
        self.bodies = sorted(involved)
        self.kinds = sorted(({"spring"} if self.springs else set()) | ({"drag"} if self.drag else set()))
        self._state: dict[int, tuple] = {}  # index -> (pos, xyzw, v, w) of this step

    def __bool__(self) -> bool:
        return bool(self.springs or self.drag)

    def apply(self, p: Any, cid: int, ids: list[int]) -> None:
        """Apply every force from the current state of the bodies ``ids``
        (pybullet body ids in scene order) of client ``cid``."""
        st = self._state
        for i in self.bodies:
            pos, orn = p.getBasePositionAndOrientation(ids[i], physicsClientId=cid)
            v, w = p.getBaseVelocity(ids[i], physicsClientId=cid)
            st[i] = (pos, orn, v, w)
        wf = p.WORLD_FRAME
        for ia, ib, anc_a, anc_b, k, L0, c in self.springs:
            pa, va = self._anchor(p, ia, anc_a)
            pb, vb = self._anchor(p, ib, anc_b)
            d0, d1, d2 = pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]
            L = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if L < 1e-12:
                continue  # direction undefined; a zero-rest-length spring has zero force here anyway
            u0, u1, u2 = d0 / L, d1 / L, d2 / L
            rate = (vb[0] - va[0]) * u0 + (vb[1] - va[1]) * u1 + (vb[2] - va[2]) * u2
            mag = k * (L - L0) + c * rate
            F = (mag * u0, mag * u1, mag * u2)
            if ia >= 0:
                p.applyExternalForce(ids[ia], -1, F, pa, wf, physicsClientId=cid)
            if ib >= 0:
                p.applyExternalForce(ids[ib], -1, (-F[0], -F[1], -F[2]), pb, wf, physicsClientId=cid)
        # after the springs: Bullet sums forces in the order applied
        for i, cl, cq in self.drag:
            pos, _, v, _ = st[i]
            speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            c = cl + cq * speed
            if c * speed != 0.0:
                p.applyExternalForce(ids[i], -1, (-c * v[0], -c * v[1], -c * v[2]), pos, wf, physicsClientId=cid)

    def _anchor(self, p: Any, i: int, anchor: tuple[float, float, float]) -> tuple[tuple, tuple]:
        """World position and velocity of a body-frame anchor (world anchor if i < 0)."""
        if i < 0:
            return anchor, (0.0, 0.0, 0.0)
        pos, orn, v, w = self._state[i]
        # The engine's rotation matrix (double precision; p.multiplyTransforms
        # is single precision, measured 3e-8 m errors) rotates the anchor.
        m = p.getMatrixFromQuaternion(orn)
        a0, a1, a2 = anchor
        r0 = m[0] * a0 + m[1] * a1 + m[2] * a2
        r1 = m[3] * a0 + m[4] * a1 + m[5] * a2
        r2 = m[6] * a0 + m[7] * a1 + m[8] * a2
        world = (pos[0] + r0, pos[1] + r1, pos[2] + r2)
        vel = (v[0] + w[1] * r2 - w[2] * r1, v[1] + w[2] * r0 - w[0] * r2, v[2] + w[0] * r1 - w[1] * r0)
        return world, vel


class StateForces:
    """Springs, dampers and drag from the bodies' world state arrays, for
    engines whose force input is a per-body force and torque about the
    centre of mass (Rapier, Box2D).  The same laws as
    :class:`PybulletForces` (module docstring), evaluated once per engine
    step from the state at its start and held over the step's substeps.

    :meth:`evaluate` takes positions (n, 3) m, wxyz quaternions (n, 4),
    linear (n, 3) m/s and angular (n, 3) rad/s velocities, world frame, and
    returns (force (n, 3) N, torque (n, 3) N m, world frame), arrays owned
    by this object and overwritten by the next call."""

    def __init__(self, scene: Scene, springs: bool | list = True) -> None:
        """``springs``: True for every spring of the scene, False for none
        (the engine has its own element), or the list of Scene springs to
        apply as forces."""
        chosen = scene.springs if springs is True else (springs or [])
        self.springs = [(sp.a, sp.b, np.asarray(sp.anchor_a, float), np.asarray(sp.anchor_b, float),
                         float(sp.stiffness), float(sp.rest_length), float(sp.damping))
                        for sp in chosen if sp.stiffness != 0.0 or sp.damping != 0.0]
        self.drag = dragged(scene)
        self.bodies = sorted({i for sp in self.springs for i in sp[:2] if i >= 0} | {i for i, _, _ in self.drag})
        self.kinds = sorted(({"spring"} if self.springs else set()) | ({"drag"} if self.drag else set()))
        n = scene.n_bodies
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))

    def __bool__(self) -> bool:
        return bool(self.springs or self.drag)

    def evaluate(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray,
                 angvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        F, T = self.force, self.torque
        F[...] = 0.0
        T[...] = 0.0
        for ia, ib, anc_a, anc_b, k, L0, c in self.springs:
            ends = []
            for i, anc in ((ia, anc_a), (ib, anc_b)):
                if i < 0:
                    ends.append((anc, np.zeros(3), None))
                else:
                    r = quat_rotate(quat[i], anc)
                    ends.append((pos[i] + r, vel[i] + np.cross(angvel[i], r), r))
            (pa, va, ra), (pb, vb, rb) = ends
            d = pb - pa
            L = float(np.linalg.norm(d))
            if L < 1e-12:
                continue  # direction undefined
            u = d / L
            f = (k * (L - L0) + c * float((vb - va) @ u)) * u  # on a; -f on b
            if ia >= 0:
                F[ia] += f
                T[ia] += np.cross(ra, f)
            if ib >= 0:
                F[ib] -= f
                T[ib] -= np.cross(rb, f)
        for i, cl, cq in self.drag:
            v = vel[i]
            F[i] -= (cl + cq * float(np.linalg.norm(v))) * v
        return F, T
