"""The compiled scene: the frozen, engine-neutral data that adapters build
from (:class:`Scene` and its bodies, statics, springs, materials and checks),
and its content hash.  :mod:`contract.scene` compiles and loads scenes.

Conventions: SI units, Z up, quaternions (w, x, y, z), velocities in the world
frame about the centre of mass.  Body-frame principal axes are the shape's own
axes (a capsule or cylinder lies along its local z).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np



@dataclass(frozen=True)
class Material:
    """Material (or pair) coefficients: restitution e in [0, 1], kinetic and
    static Coulomb friction, rolling friction (m, as a lever arm)."""

    name: str
    restitution: float
    friction: float
    static_friction: float
    rolling_friction: float = 0.0


@dataclass(frozen=True)
class Body:
    """One dynamic rigid body.

    ``inertia`` holds the principal moments (kg m^2, shape (3,)) about the body
    axes; ``half_extents`` is (3,) for boxes, ``radius``/``half_length`` for
    round shapes (capsule and cylinder axis = body z).
    """

    index: int
    name: str
    shape: str
    mass: float
    inertia: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    material: str
    radius: float = 0.0
    half_extents: np.ndarray | None = None
    half_length: float = 0.0
    drag_linear: float = 0.0
    drag_quadratic: float = 0.0

    @property
    def bounding_radius(self) -> float:
        """Radius (m) of the smallest origin-centred sphere holding the shape."""
        if self.shape == "sphere":
            return self.radius
        if self.shape == "box":
            return math.sqrt(sum((float(h) * float(h) for h in self.half_extents), 0.0))  # no BLAS: contract.rotation.dot
        if self.shape == "capsule":
            return self.half_length + self.radius
        return math.hypot(self.half_length, self.radius)

    @property
    def min_extent(self) -> float:
        """Smallest half-size (m): how thin the shape is."""
        if self.shape == "sphere":
            return self.radius
        if self.shape == "box":
            return float(np.min(self.half_extents))
        return min(self.radius, self.half_length + (self.radius if self.shape == "capsule" else 0.0))


@dataclass(frozen=True)
class Static:
    """Fixed geometry.  ``shape`` is 'plane' or 'box'; ``kind`` remembers
    whether a plane came from a 'slope' (then ``angle`` is its incline in
    degrees, downhill +x).  A plane is {x : normal . x = offset}, solid below."""

    index: int
    name: str
    shape: str
    kind: str
    material: str
    normal: np.ndarray | None = None
    offset: float = 0.0
    position: np.ndarray | None = None
    orientation: np.ndarray | None = None
    half_extents: np.ndarray | None = None
    angle: float | None = None


@dataclass(frozen=True)
class Spring:
    """Hooke spring and/or dashpot between body ``a`` and ``b`` (indices; -1 is
    the world).  Anchors are in the body frame (world frame for the world)."""

    a: int
    b: int
    anchor_a: np.ndarray
    anchor_b: np.ndarray
    stiffness: float
    rest_length: float
    damping: float


@dataclass(frozen=True)
class Joint:
    """One ``[[joint]]``: body ``body`` held to ``other`` (indices; -1 is the
    world).  ``kind`` is revolute, spherical, prismatic or fixed.

    ``anchor`` (m, (3,)) is the joint's world point at the start and
    ``axis`` its unit world axis at the start ((3,); revolute: the hinge,
    prismatic: the slide; None for spherical and fixed).  The same point and
    axis are stored in each side's frame, the frame the joint moves with:
    ``anchor_body``/``axis_body`` in ``body``'s frame (from its centre of
    mass), ``anchor_other``/``axis_other`` in ``other``'s frame (the world
    frame when ``other`` is -1).  A joint holds while the two sides' anchors
    coincide (prismatic: differ along the axis only) and, revolute, their
    axes agree (harness/joints.py measures it)."""

    index: int
    name: str
    kind: str
    body: int
    other: int
    anchor: np.ndarray
    axis: np.ndarray | None
    anchor_body: np.ndarray
    anchor_other: np.ndarray
    axis_body: np.ndarray | None = None
    axis_other: np.ndarray | None = None


@dataclass(frozen=True)
class Check:
    metric: str
    max: float | None = None
    min: float | None = None
    equals: float | bool | None = None
    tolerance: float = 0.0
    engines: tuple[str, ...] | None = None
    variants: tuple[str, ...] | None = None
    #: engine -> known limitation (contract.xfail.Xfail; a plain reason
    #: string is accepted too: measured on contract.xfail.MEASURED_ON's version)
    xfail: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Scene:
    """Engine-neutral, immutable description of one scenario run."""

    id: str
    variant: str | None
    path: Path | None
    family: str
    title: str
    duration: float
    dt: float
    effects: frozenset[str]
    planar: bool
    gravity_vector: np.ndarray
    primary_metric: str | None
    tags: tuple[str, ...]
    materials: dict[str, Material]
    bodies: tuple[Body, ...]
    statics: tuple[Static, ...]
    springs: tuple[Spring, ...]
    reference_model: str | None
    reference_params: dict[str, Any]
    checks: tuple[Check, ...]
    variant_names: tuple[str, ...] = ()
    #: step phases the conformance checks run over (``[scenario] phases``)
    phases: int = 1
    #: :func:`content_hash` of the scene as compiled (kept by
    #: ``dataclasses.replace``, so a step-phase shift keeps the hash of the
    #: scene as written; the phase is recorded beside it)
    content_hash: str = ""
    #: per body (by Body.index), the spec's ``[[body]]`` entry it comes from
    #: and whether that entry's pattern made it: (entry, patterned); () for
    #: a scene built without a spec (not scene content: no part of the hash)
    body_entries: tuple[tuple[int, bool], ...] = ()
    #: the ``[perturbation]`` block as a dict (harness/ensemble.py), None
    #: without one; judges the scene, changes no run (not in the hash)
    perturbation: dict[str, Any] | None = None
    #: the ``[[joint]]`` tables, compiled (joint k is ``joint[k]`` in the spec)
    joints: tuple[Joint, ...] = ()

    # ---- derived, engine-neutral helpers ---------------------------------

    def body_key(self, i: int, field: str) -> str:
        """The spec key path body ``i``'s ``field`` is written under, for
        error messages: ``body[k].<field>`` of the ``[[body]]`` entry k it
        comes from (k counts the spec's entries, not the bodies a pattern
        expands to); a position a pattern made is the pattern's,
        ``body[k].pattern``; ``body[i].<field>`` for a scene built without a
        spec.  Test: tests/test_references.py::test_two_body_refusal_names_the_spec_entry."""
        if i >= len(self.body_entries):
            return f"body[{i}].{field}"
        entry, patterned = self.body_entries[i]
        return f"body[{entry}].pattern" if patterned and field == "position" else f"body[{entry}].{field}"

    @property
    def source(self) -> str:
        """The spec file as recorded in rows: relative to the package's
        folder when inside it (``scenarios/...``, the same for a checkout and
        an installed wheel: contract.data.recorded_path), else absolute; ''
        for an inline spec."""
        if self.path is None:
            return ""
        from physbench.contract.data import recorded_path

        return recorded_path(Path(self.path))

    def has(self, effect: str) -> bool:
        return effect in self.effects

    @property
    def gravity(self) -> np.ndarray:
        """Gravity actually applied (m/s^2, (3,)): zero without the effect."""
        return self.gravity_vector if "gravity" in self.effects else np.zeros(3)

    @property
    def n_bodies(self) -> int:
        return len(self.bodies)

    @property
    def n_steps(self) -> int:
        return n_steps(self.duration, self.dt)

    @property
    def masses(self) -> np.ndarray:
        return np.array([b.mass for b in self.bodies], dtype=float)

    @property
    def inertias(self) -> np.ndarray:
        """(n, 3) principal moments in the body frame."""
        return np.array([b.inertia for b in self.bodies], dtype=float).reshape(-1, 3)

    def initial_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x (n,3), q wxyz (n,4), v (n,3), w (n,3)) at t = 0."""
        return (
            np.array([b.position for b in self.bodies], float).reshape(-1, 3),
            np.array([b.orientation for b in self.bodies], float).reshape(-1, 4),
            np.array([b.velocity for b in self.bodies], float).reshape(-1, 3),
            np.array([b.angular_velocity for b in self.bodies], float).reshape(-1, 3),
        )

    def pair(self, mat_a: str, mat_b: str) -> Material:
        """The coefficients the spec asks for when ``mat_a`` meets ``mat_b``,
        with effects applied (no 'restitution' -> e = 0; no 'friction' -> 0;
        no 'rolling_friction' -> 0).

        Rule: equal materials give their own values; a named material meeting
        'default' gives the named material's values (a named material says how
        *it* behaves against the scene's default surface); two different named
        materials must agree on each coefficient, else the spec is ambiguous and
        compile_scene rejects it.
        """
        a, b = self.materials[mat_a], self.materials[mat_b]
        if mat_a == mat_b or mat_b == "default":
            m = a
        elif mat_a == "default":
            m = b
        else:
            m = a  # compile_scene verified that a and b agree
        return Material(
            name=f"{mat_a}|{mat_b}",
            restitution=m.restitution if "restitution" in self.effects else 0.0,
            friction=m.friction if "friction" in self.effects else 0.0,
            static_friction=m.static_friction if "friction" in self.effects else 0.0,
            rolling_friction=m.rolling_friction if "rolling_friction" in self.effects else 0.0,
        )

    def contact_pairs(self) -> list[tuple[str, int, str, int, Material]]:
        """Every pair that may touch, as (kind_a, index_a, kind_b, index_b,
        pair material) with kinds 'body' or 'static'.  Empty without 'contact'."""
        if "contact" not in self.effects:
            return []
        out = []
        n = len(self.bodies)
        for i in range(n):
            for j in range(i + 1, n):
                out.append(("body", i, "body", j, self.pair(self.bodies[i].material, self.bodies[j].material)))
            for s in self.statics:
                out.append(("body", i, "static", s.index, self.pair(self.bodies[i].material, s.material)))
        return out

    def contact_materials(self) -> list[Material]:
        """The pair materials of :meth:`contact_pairs`, each material
        combination once: O(n + k^2) for k materials in use, where
        :meth:`contact_pairs` is O(n^2) (50 million pairs at 10,000 bodies)."""
        if "contact" not in self.effects:
            return []
        count: dict[str, int] = {}
        for b in self.bodies:
            count[b.material] = count.get(b.material, 0) + 1
        mats = list(count)
        out = [self.pair(a, b) for i, a in enumerate(mats) for b in mats[i:] if a != b or count[a] >= 2]
        out += [self.pair(a, s.material) for a in mats for s in self.statics]
        return out

    def body_index(self, name: str) -> int:
        for b in self.bodies:
            if b.name == name:
                return b.index
        raise KeyError(name)


def n_steps(duration: float, dt: float) -> int:
    """Number of fixed steps that cover ``duration`` (rounded, at least 1)."""
    return max(1, int(round(duration / dt)))



# Scene fields that say what is simulated and measured; everything else
# (id, path, title, tags, checks, variants, phases) names or judges a
# scene without changing any number a run records.
_CONTENT_FIELDS = ("duration", "dt", "effects", "planar", "gravity_vector", "primary_metric", "materials",
                   "bodies", "statics", "springs", "reference_model", "reference_params")


def _canonical(v: Any) -> Any:
    """JSON-able canonical form: floats by repr (exact round trip, -0.0 as
    0.0), arrays as lists, sets sorted, dataclasses as field dicts."""
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _canonical(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {str(k): _canonical(x) for k, x in sorted(v.items(), key=lambda kv: str(kv[0]))}
    if isinstance(v, (frozenset, set)):
        return sorted(_canonical(x) for x in v)
    if isinstance(v, np.ndarray):
        return [_canonical(x) for x in v.tolist()]
    if isinstance(v, (list, tuple)):
        return [_canonical(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return repr(float(v) + 0.0)
    return v


def content_hash(scene: Scene) -> str:
    """16 hex digits of sha256 over the compiled scene's content (the spec
    after its variant and overrides, patterns expanded): the same for the
    same physics and measurement whatever the file's name, path, layout or
    comments, different when anything simulated or measured changes (a
    friction coefficient, a body, dt, the reference model's params).  Checks,
    title and tags are left out: they judge or name the numbers, they do not
    change them.  Engine settings are not scene content (rows and point keys
    carry them apart).  Pinned by
    tests/test_own_scenes.py::test_content_hash_is_the_scene_not_the_file."""
    doc = {k: _canonical(getattr(scene, k)) for k in _CONTENT_FIELDS}
    if scene.joints:  # absent when empty: scenes without joints keep their hashes
        doc["joints"] = _canonical(scene.joints)
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]

