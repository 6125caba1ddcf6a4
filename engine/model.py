"""The immutable engine model: everything about a scene that does not change
while it runs, as numpy arrays built once from a :class:`SceneInput` (the
engine's own, engine-neutral input; ``adapters/reference.py`` translates the
harness scene into it) and the resolved settings.

Index conventions
-----------------
* Bodies are ``0 .. n-1``.  Arrays used by the contact solver have one extra
  row ``n``: the *world* (inverse mass 0, inverse inertia 0, velocity 0), so a
  contact with static geometry is a contact with body ``n`` and needs no
  special case.
* Statics keep their input index (``0 .. n_statics-1``); planes and static
  boxes are also gathered into their own arrays (``plane_*``, ``sbox_*``)
  with a map back to the static index.
* Materials are ``0 .. n_materials-1``: each body and static has one, and
  the pair coefficients are (n_materials, n_materials) tables looked up at
  contact time (:meth:`Model.pair_coefficients`), so the model's size is
  O(n + n_statics + n_materials^2).

Units: SI (m, kg, s, rad).  Quaternions (w, x, y, z).  Shapes' body axes are
their principal axes (capsule/cylinder axis = body z).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from physbench.engine.mathutil import quat_to_matrix

# shape codes (body shapes)
SPHERE, BOX, CAPSULE, CYLINDER = 0, 1, 2, 3
SHAPE_CODES = {"sphere": SPHERE, "box": BOX, "capsule": CAPSULE, "cylinder": CYLINDER}
SHAPE_NAMES = {v: k for k, v in SHAPE_CODES.items()}
# static shape codes
S_PLANE, S_BOX = 0, 1
STATIC_CODES = {"plane": S_PLANE, "box": S_BOX}

# Integrators whose position update is x1 = x0 + h v1 (velocity first) take a
# contact impulse's full effect on the position ("lever" c = 1); the others
# treat the contact impulse as a constant force over the step, whose effect
# on the position is h/2 * dv (c = 1/2).  See solver.py.
CONTACT_LEVER = {
    "semi_implicit_euler": 1.0,
    "explicit_euler": 0.5,
    "midpoint": 0.5,
    "heun": 0.5,
    "rk4": 0.5,
    "velocity_verlet": 0.5,
}


@dataclass(frozen=True, eq=False)
class SceneInput:
    """What the engine needs of a scene, as plain arrays (n bodies, ns
    statics, ns_p springs, M materials); built by the caller (the reference
    adapter translates the harness scene).  Units SI, quaternions wxyz.

    Bodies: ``shape`` (n,) names ('sphere', 'box', 'capsule', 'cylinder'),
    ``mass`` (n,) kg, ``inertia`` (n, 3) principal moments kg m^2,
    ``radius``/``half_length`` (n,) m, ``half_extents`` (n, 3) m (zeros for
    non-boxes), ``bound_radius`` (n,) m (smallest origin-centred sphere
    holding the shape), ``min_extent`` (n,) m (smallest half-size),
    ``drag_linear``/``drag_quadratic`` (n,), ``material`` (n,) int,
    initial ``x`` (n, 3), ``q`` (n, 4), ``v`` (n, 3), ``w`` (n, 3).
    Statics: ``static_shape`` (ns,) names ('plane' or 'box'),
    ``static_material`` (ns,) int, ``static_normal`` (ns, 3) and
    ``static_offset`` (ns,) for planes ({x: n.x = offset}, solid below),
    ``static_position`` (ns, 3), ``static_orientation`` (ns, 4),
    ``static_half_extents`` (ns, 3) for boxes (rows of the other kind are
    ignored).  Springs: ``spring_a``/``spring_b`` (ns_p,) body indices (-1
    the world), anchors (ns_p, 3) in the body frame, ``spring_k`` N/m,
    ``spring_rest`` m, ``spring_c`` N s/m.  Materials: ``pair_e``,
    ``pair_mus``, ``pair_muk``, ``pair_mur`` (M, M): restitution, static
    and kinetic friction, rolling friction (m) when material i meets j, with
    the scene's absent effects already zeroed.  ``effects``: the effect
    names; ``gravity`` (3,) m/s^2 as applied; ``dt`` s.  ``scene``: the
    caller's own scene object, kept on the model for the caller and never
    read by the engine.  ``joints``: one tuple per joint (engine/joints/,
    its module doc), empty without joints."""

    dt: float
    effects: frozenset
    gravity: np.ndarray
    shape: tuple
    mass: np.ndarray
    inertia: np.ndarray
    radius: np.ndarray
    half_extents: np.ndarray
    half_length: np.ndarray
    bound_radius: np.ndarray
    min_extent: np.ndarray
    drag_linear: np.ndarray
    drag_quadratic: np.ndarray
    material: np.ndarray
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
    static_shape: tuple
    static_material: np.ndarray
    static_normal: np.ndarray
    static_offset: np.ndarray
    static_position: np.ndarray
    static_orientation: np.ndarray
    static_half_extents: np.ndarray
    spring_a: np.ndarray
    spring_b: np.ndarray
    spring_anchor_a: np.ndarray
    spring_anchor_b: np.ndarray
    spring_k: np.ndarray
    spring_rest: np.ndarray
    spring_c: np.ndarray
    pair_e: np.ndarray
    pair_mus: np.ndarray
    pair_muk: np.ndarray
    pair_mur: np.ndarray
    scene: Any = None
    joints: tuple = ()

    @property
    def n_bodies(self) -> int:
        return len(self.shape)

    def has(self, effect: str) -> bool:
        return effect in self.effects


@dataclass(frozen=True, eq=False)
class Model:
    """Arrays over bodies (n), statics and materials; settings; effects.

    Shapes: ``mass`` (n,), ``inv_mass`` (n+1,) with the world row 0,
    ``inertia_body`` (n, 3) principal moments, ``inv_inertia_body`` (n+1, 3),
    ``shape`` (n,) codes, ``radius`` (n,), ``half_extents`` (n, 3) (zeros for
    non-boxes), ``half_length`` (n,), ``bound_radius`` (n,), ``min_extent``
    (n,).  ``static_shape`` (n_statics,) codes (S_PLANE, S_BOX).  Materials:
    ``body_material`` (n,), ``static_material`` (n_statics,) indices into
    the pair tables ``pair_e``/``pair_mus``/``pair_muk``/``pair_mur``
    (n_materials, n_materials): the pair coefficients the scene asks for
    (absent effects zeroed; ``mur`` is the rolling-friction coefficient, a
    length in m), looked up per contact (:meth:`pair_coefficients`).
    ``rolling``: some pair that can touch has rolling friction (decided
    once: without it the solver has no rolling rows at all).  ``x0``,
    ``q0``, ``v0``, ``w0``: the initial state.  ``scene``: the caller's
    scene object (opaque; never read by the engine).
    """

    scene: Any
    settings: Mapping[str, Any]
    effects: frozenset
    n: int
    dt: float
    substeps: int
    gravity: np.ndarray
    mass: np.ndarray
    inv_mass: np.ndarray
    inertia_body: np.ndarray
    inv_inertia_body: np.ndarray
    isotropic: np.ndarray
    shape: np.ndarray
    radius: np.ndarray
    half_extents: np.ndarray
    half_length: np.ndarray
    bound_radius: np.ndarray
    min_extent: np.ndarray
    drag_linear: np.ndarray
    drag_quadratic: np.ndarray
    x0: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    w0: np.ndarray
    # springs
    spring_a: np.ndarray
    spring_b: np.ndarray
    spring_anchor_a: np.ndarray
    spring_anchor_b: np.ndarray
    spring_k: np.ndarray
    spring_rest: np.ndarray
    spring_c: np.ndarray
    # statics
    n_statics: int
    static_shape: np.ndarray
    plane_normal: np.ndarray
    plane_offset: np.ndarray
    plane_static: np.ndarray
    sbox_pos: np.ndarray
    sbox_R: np.ndarray
    sbox_half: np.ndarray
    sbox_static: np.ndarray
    sbox_aabb_lo: np.ndarray
    sbox_aabb_hi: np.ndarray
    # materials
    body_material: np.ndarray
    static_material: np.ndarray
    pair_e: np.ndarray
    pair_mus: np.ndarray
    pair_muk: np.ndarray
    pair_mur: np.ndarray
    rolling: bool
    contact_lever: float
    info: Mapping[str, Any] = field(default_factory=dict)
    #: the joints as constraint rows (engine.joints.table.JointModel), None without
    joints: Any = None

    # ---- convenience --------------------------------------------------
    def setting(self, name: str) -> Any:
        return self.settings[name]

    def has(self, effect: str) -> bool:
        return effect in self.effects

    @property
    def h(self) -> float:
        """The length of one substep (s)."""
        return self.dt / self.substeps

    @property
    def collides(self) -> bool:
        """Whether the step has contact stages: the contact effect and
        something to collide (two bodies, or a body and a static)."""
        return self.has("contact") and (self.n >= 2 or self.n_statics > 0) and self.n > 0

    def pair_coefficients(self, a: np.ndarray, b: np.ndarray, sidx: np.ndarray) -> tuple[np.ndarray, ...]:
        """(e, mus, muk, mur), each (m,), of contacts between bodies ``a``
        (m,) and bodies ``b`` (m,), or, where ``sidx`` >= 0, the static
        ``sidx`` (then ``b`` is n, the world)."""
        ma = self.body_material[a]
        mb = np.where(sidx >= 0, -1, self.body_material[np.minimum(b, self.n - 1)])
        st = sidx >= 0
        mb[st] = self.static_material[sidx[st]]
        return self.pair_e[ma, mb], self.pair_mus[ma, mb], self.pair_muk[ma, mb], self.pair_mur[ma, mb]


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _rolling(inp: SceneInput) -> bool:
    """Whether some pair that can touch has a rolling-friction coefficient:
    two distinct bodies (the same material only when two bodies have it),
    or a body and a static."""
    if not inp.has("rolling_friction"):
        return False
    mur = np.asarray(inp.pair_mur, float)
    used, count = np.unique(np.asarray(inp.material, np.int64), return_counts=True)
    sub = mur[np.ix_(used, used)].copy()
    np.fill_diagonal(sub, np.where(count >= 2, np.diag(sub), 0.0))
    if sub.any():
        return True
    st = np.unique(np.asarray(inp.static_material, np.int64))
    return bool(st.size and mur[np.ix_(used, st)].any())


def build_model(inp: SceneInput, settings: Mapping[str, Any]) -> Model:
    """Compile the scene input and resolved ``settings`` into a
    :class:`Model`: O(n + n_statics + n_materials^2) time and memory."""
    n = inp.n_bodies
    mass = np.asarray(inp.mass, float).reshape(n)
    inertia = np.asarray(inp.inertia, float).reshape(n, 3)
    inv_mass = np.zeros(n + 1)
    inv_mass[:n] = 1.0 / mass
    inv_inertia = np.zeros((n + 1, 3))
    inv_inertia[:n] = 1.0 / inertia
    # "isotropic" bodies (spheres, cubes) have no gyroscopic term: w x I w = 0
    isotropic = np.ptp(inertia, axis=1) <= 1e-12 * inertia.max(axis=1, initial=0.0)
    shape = np.array([SHAPE_CODES[s] for s in inp.shape], np.int64).reshape(n)
    zeros = np.zeros(n)
    drag_l = np.asarray(inp.drag_linear, float).reshape(n) if inp.has("drag_linear") else zeros
    drag_q = np.asarray(inp.drag_quadratic, float).reshape(n) if inp.has("drag_quadratic") else zeros

    ns = len(inp.static_shape)
    static_shape = np.array([STATIC_CODES[s] for s in inp.static_shape], np.int64).reshape(ns)
    planes = np.flatnonzero(static_shape == S_PLANE)
    boxes = np.flatnonzero(static_shape == S_BOX)
    plane_normal = np.asarray(inp.static_normal, float).reshape(ns, 3)[planes]
    plane_offset = np.asarray(inp.static_offset, float).reshape(ns)[planes]
    sbox_pos = np.asarray(inp.static_position, float).reshape(ns, 3)[boxes]
    sbox_R = quat_to_matrix(np.asarray(inp.static_orientation, float).reshape(ns, 4)[boxes])
    sbox_half = np.asarray(inp.static_half_extents, float).reshape(ns, 3)[boxes]
    ext = np.einsum("kij,kj->ki", np.abs(sbox_R), sbox_half) if boxes.size else np.zeros((0, 3))

    integrator = settings["integrator"]
    f = lambda a: _ro(np.asarray(a, float))  # noqa: E731
    return Model(
        scene=inp.scene, settings=MappingProxyType(dict(settings)), effects=frozenset(inp.effects), n=n,
        dt=float(settings["dt"]), substeps=int(settings["substeps"]), gravity=f(inp.gravity),
        mass=_ro(mass), inv_mass=_ro(inv_mass), inertia_body=_ro(inertia), inv_inertia_body=_ro(inv_inertia),
        isotropic=_ro(isotropic), shape=_ro(shape), radius=_ro(np.asarray(inp.radius, float).reshape(n)),
        half_extents=_ro(np.asarray(inp.half_extents, float).reshape(n, 3)),
        half_length=_ro(np.asarray(inp.half_length, float).reshape(n)),
        bound_radius=_ro(np.asarray(inp.bound_radius, float).reshape(n)),
        min_extent=_ro(np.asarray(inp.min_extent, float).reshape(n)),
        drag_linear=_ro(drag_l), drag_quadratic=_ro(drag_q),
        x0=f(np.reshape(inp.x, (n, 3))), q0=f(np.reshape(inp.q, (n, 4))), v0=f(np.reshape(inp.v, (n, 3))),
        w0=f(np.reshape(inp.w, (n, 3))),
        spring_a=_ro(np.asarray(inp.spring_a, np.int64)), spring_b=_ro(np.asarray(inp.spring_b, np.int64)),
        spring_anchor_a=f(np.reshape(inp.spring_anchor_a, (-1, 3))),
        spring_anchor_b=f(np.reshape(inp.spring_anchor_b, (-1, 3))), spring_k=f(inp.spring_k),
        spring_rest=f(inp.spring_rest), spring_c=f(inp.spring_c),
        n_statics=ns, static_shape=_ro(static_shape), plane_normal=_ro(plane_normal),
        plane_offset=_ro(plane_offset), plane_static=_ro(planes.astype(np.int64)), sbox_pos=_ro(sbox_pos),
        sbox_R=_ro(sbox_R), sbox_half=_ro(sbox_half), sbox_static=_ro(boxes.astype(np.int64)),
        sbox_aabb_lo=_ro(sbox_pos - ext), sbox_aabb_hi=_ro(sbox_pos + ext),
        body_material=_ro(np.asarray(inp.material, np.int64).reshape(n)),
        static_material=_ro(np.asarray(inp.static_material, np.int64).reshape(ns)),
        pair_e=f(inp.pair_e), pair_mus=f(inp.pair_mus), pair_muk=f(inp.pair_muk), pair_mur=f(inp.pair_mur),
        rolling=_rolling(inp), contact_lever=CONTACT_LEVER[integrator], joints=_joints(inp),
    )


def _joints(inp: SceneInput):
    """The joint rows (engine/joints/), None for a scene without joints."""
    if not getattr(inp, "joints", ()):
        return None
    from physbench.engine.joints.table import build_joints

    return build_joints(inp)
