"""The immutable engine model: everything about a scene that does not change
while it runs, as numpy arrays built once from a :class:`harness.scene.Scene`
and the resolved settings.

Index conventions
-----------------
* Bodies are ``0 .. n-1``.  Arrays used by the contact solver have one extra
  row ``n``: the *world* (inverse mass 0, inverse inertia 0, velocity 0), so a
  contact with static geometry is a contact with body ``n`` and needs no
  special case.
* Statics keep their scene index (``Scene.statics[k].index``); planes and
  static boxes are also gathered into their own arrays (``plane_*``,
  ``sbox_*``) with a map back to the static index.

Units: SI (m, kg, s, rad).  Quaternions (w, x, y, z).  Shapes' body axes are
their principal axes (capsule/cylinder axis = body z).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from harness.scene import Scene

# shape codes (body shapes)
SPHERE, BOX, CAPSULE, CYLINDER = 0, 1, 2, 3
SHAPE_CODES = {"sphere": SPHERE, "box": BOX, "capsule": CAPSULE, "cylinder": CYLINDER}
SHAPE_NAMES = {v: k for k, v in SHAPE_CODES.items()}

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
class Model:
    """Arrays over bodies (n), statics and pairs; settings; effects.

    Shapes: ``mass`` (n,), ``inv_mass`` (n+1,) with the world row 0,
    ``inertia_body`` (n, 3) principal moments, ``inv_inertia_body`` (n+1, 3),
    ``shape`` (n,) codes, ``radius`` (n,), ``half_extents`` (n, 3) (zeros for
    non-boxes), ``half_length`` (n,), ``bound_radius`` (n,), ``min_extent``
    (n,).  Pair tables ``e_bb``/``mus_bb``/``muk_bb``/``mur_bb`` (n, n) and
    ``e_bs``/``mus_bs``/``muk_bs``/``mur_bs`` (n, n_statics) hold the pair
    coefficients the scene asks for (Scene.pair, with absent effects already
    zeroed; ``mur`` is the rolling-friction coefficient, a length in m).
    ``rolling``: some pair has rolling friction (decided once: without it
    the solver has no rolling rows at all).
    """

    scene: Scene
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
    plane_normal: np.ndarray
    plane_offset: np.ndarray
    plane_static: np.ndarray
    sbox_pos: np.ndarray
    sbox_R: np.ndarray
    sbox_half: np.ndarray
    sbox_static: np.ndarray
    sbox_aabb_lo: np.ndarray
    sbox_aabb_hi: np.ndarray
    # pair materials
    e_bb: np.ndarray
    mus_bb: np.ndarray
    muk_bb: np.ndarray
    e_bs: np.ndarray
    mus_bs: np.ndarray
    muk_bs: np.ndarray
    mur_bb: np.ndarray
    mur_bs: np.ndarray
    rolling: bool
    # all body-body pairs (i < j), for the brute-force broad phase
    pair_i: np.ndarray
    pair_j: np.ndarray
    contact_lever: float
    info: Mapping[str, Any] = field(default_factory=dict)

    # ---- convenience --------------------------------------------------
    def setting(self, name: str) -> Any:
        return self.settings[name]

    def has(self, effect: str) -> bool:
        return effect in self.effects

    @property
    def h(self) -> float:
        """The length of one substep (s)."""
        return self.dt / self.substeps


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def build_model(scene: Scene, settings: Mapping[str, Any]) -> Model:
    """Compile ``scene`` and resolved ``settings`` into a :class:`Model`."""
    n = scene.n_bodies
    bodies = scene.bodies
    mass = np.array([b.mass for b in bodies], float).reshape(n)
    inertia = scene.inertias.reshape(n, 3)
    inv_mass = np.zeros(n + 1)
    inv_mass[:n] = 1.0 / mass
    inv_inertia = np.zeros((n + 1, 3))
    inv_inertia[:n] = 1.0 / inertia
    # "isotropic" bodies (spheres, cubes) have no gyroscopic term: w x I w = 0
    isotropic = np.array([np.ptp(I) <= 1e-12 * max(I) for I in inertia], bool).reshape(n)
    shape = np.array([SHAPE_CODES[b.shape] for b in bodies], np.int64).reshape(n)
    radius = np.array([b.radius for b in bodies], float).reshape(n)
    half = np.zeros((n, 3))
    for b in bodies:
        if b.half_extents is not None:
            half[b.index] = b.half_extents
    half_length = np.array([b.half_length for b in bodies], float).reshape(n)
    bound = np.array([b.bounding_radius for b in bodies], float).reshape(n)
    min_ext = np.array([b.min_extent for b in bodies], float).reshape(n)
    drag_l = np.array([b.drag_linear if scene.has("drag_linear") else 0.0 for b in bodies], float).reshape(n)
    drag_q = np.array([b.drag_quadratic if scene.has("drag_quadratic") else 0.0 for b in bodies], float).reshape(n)

    sp = scene.springs
    spring_a = np.array([s.a for s in sp], np.int64)
    spring_b = np.array([s.b for s in sp], np.int64)
    spring_anchor_a = np.array([s.anchor_a for s in sp], float).reshape(-1, 3)
    spring_anchor_b = np.array([s.anchor_b for s in sp], float).reshape(-1, 3)
    spring_k = np.array([s.stiffness for s in sp], float)
    spring_rest = np.array([s.rest_length for s in sp], float)
    spring_c = np.array([s.damping for s in sp], float)

    from adapters.conventions import quat_to_matrix

    planes = [s for s in scene.statics if s.shape == "plane"]
    boxes = [s for s in scene.statics if s.shape == "box"]
    plane_normal = np.array([s.normal for s in planes], float).reshape(-1, 3)
    plane_offset = np.array([s.offset for s in planes], float)
    plane_static = np.array([s.index for s in planes], np.int64)
    sbox_pos = np.array([s.position for s in boxes], float).reshape(-1, 3)
    sbox_R = quat_to_matrix(np.array([s.orientation for s in boxes], float).reshape(-1, 4))
    sbox_half = np.array([s.half_extents for s in boxes], float).reshape(-1, 3)
    sbox_static = np.array([s.index for s in boxes], np.int64)
    ext = np.einsum("kij,kj->ki", np.abs(sbox_R), sbox_half) if boxes else np.zeros((0, 3))
    ns = len(scene.statics)

    # pair material tables (per body-body and body-static pair)
    e_bb = np.zeros((n, n))
    mus_bb = np.zeros((n, n))
    muk_bb = np.zeros((n, n))
    e_bs = np.zeros((n, ns))
    mus_bs = np.zeros((n, ns))
    muk_bs = np.zeros((n, ns))
    mur_bb = np.zeros((n, n))
    mur_bs = np.zeros((n, ns))
    cache: dict[tuple[str, str], Any] = {}

    def pair(ma: str, mb: str):
        key = (ma, mb)
        if key not in cache:
            cache[key] = scene.pair(ma, mb)
        return cache[key]

    for bi in bodies:
        for bj in bodies:
            if bi.index == bj.index:
                continue
            m = pair(bi.material, bj.material)
            e_bb[bi.index, bj.index] = m.restitution
            mus_bb[bi.index, bj.index] = max(m.static_friction, m.friction)
            muk_bb[bi.index, bj.index] = m.friction
            mur_bb[bi.index, bj.index] = m.rolling_friction
        for s in scene.statics:
            m = pair(bi.material, s.material)
            e_bs[bi.index, s.index] = m.restitution
            mus_bs[bi.index, s.index] = max(m.static_friction, m.friction)
            muk_bs[bi.index, s.index] = m.friction
            mur_bs[bi.index, s.index] = m.rolling_friction

    pi, pj = np.triu_indices(n, 1)
    integrator = settings["integrator"]
    return Model(
        scene=scene, settings=MappingProxyType(dict(settings)), effects=frozenset(scene.effects), n=n,
        dt=float(settings["dt"]), substeps=int(settings["substeps"]), gravity=_ro(np.array(scene.gravity, float)),
        mass=_ro(mass), inv_mass=_ro(inv_mass), inertia_body=_ro(inertia), inv_inertia_body=_ro(inv_inertia),
        isotropic=_ro(isotropic), shape=_ro(shape), radius=_ro(radius), half_extents=_ro(half),
        half_length=_ro(half_length), bound_radius=_ro(bound), min_extent=_ro(min_ext),
        drag_linear=_ro(drag_l), drag_quadratic=_ro(drag_q),
        spring_a=_ro(spring_a), spring_b=_ro(spring_b), spring_anchor_a=_ro(spring_anchor_a),
        spring_anchor_b=_ro(spring_anchor_b), spring_k=_ro(spring_k), spring_rest=_ro(spring_rest),
        spring_c=_ro(spring_c),
        n_statics=ns, plane_normal=_ro(plane_normal), plane_offset=_ro(plane_offset),
        plane_static=_ro(plane_static), sbox_pos=_ro(sbox_pos), sbox_R=_ro(sbox_R), sbox_half=_ro(sbox_half),
        sbox_static=_ro(sbox_static), sbox_aabb_lo=_ro(sbox_pos - ext), sbox_aabb_hi=_ro(sbox_pos + ext),
        e_bb=_ro(e_bb), mus_bb=_ro(mus_bb), muk_bb=_ro(muk_bb), e_bs=_ro(e_bs), mus_bs=_ro(mus_bs),
        muk_bs=_ro(muk_bs), mur_bb=_ro(mur_bb), mur_bs=_ro(mur_bs),
        rolling=bool(scene.has("rolling_friction") and (mur_bb.any() or mur_bs.any())), pair_i=_ro(pi.astype(np.int64)), pair_j=_ro(pj.astype(np.int64)),
        contact_lever=CONTACT_LEVER[integrator],
    )
