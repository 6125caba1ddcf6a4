"""The engine-neutral scene model that adapters build from.

A validated :class:`contract.spec.SpecModel` is compiled into a frozen
:class:`Scene`: patterns expanded into bodies, masses and principal inertias
computed, slopes turned into planes, materials resolved into the *pair*
values the spec asks for (with absent effects zeroing restitution and
friction).  Adapters never read TOML; they read a Scene.

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

from contract.models import model_refusal, scene_errors
from contract.phase import PhaseError, shift_scene
from contract.spec.bounds import bound_error
from contract.spec.errors import ModelRefusal, SpecError
from contract.spec.load import LoadedSpec, load_spec
from contract.spec.schema import BodySection, SpecModel

REPO_ROOT = Path(__file__).resolve().parent.parent
SCENARIO_DIR = REPO_ROOT / "scenarios"


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
            return float(np.linalg.norm(self.half_extents))
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
class Check:
    metric: str
    max: float | None = None
    min: float | None = None
    equals: float | bool | None = None
    tolerance: float = 0.0
    engines: tuple[str, ...] | None = None
    variants: tuple[str, ...] | None = None
    xfail: dict[str, str] = field(default_factory=dict)


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

    # ---- derived, engine-neutral helpers ---------------------------------

    @property
    def source(self) -> str:
        """The spec file as recorded in rows: relative to the repository
        when inside it (scenarios/...), else absolute; '' for an inline
        spec.  :func:`source_path` reads it back."""
        if self.path is None:
            return ""
        p = Path(self.path).resolve()
        try:
            return p.relative_to(REPO_ROOT).as_posix()
        except ValueError:
            return str(p)

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

    def body_index(self, name: str) -> int:
        for b in self.bodies:
            if b.name == name:
                return b.index
        raise KeyError(name)


def n_steps(duration: float, dt: float) -> int:
    """Number of fixed steps that cover ``duration`` (rounded, at least 1)."""
    return max(1, int(round(duration / dt)))


# --------------------------------------------------------------------------
# mass properties


def shape_volume(shape: str, radius: float, half_extents: np.ndarray | None, half_length: float) -> float:
    if shape == "sphere":
        return 4.0 / 3.0 * math.pi * radius**3
    if shape == "box":
        return 8.0 * float(np.prod(half_extents))
    if shape == "capsule":
        return math.pi * radius**2 * 2.0 * half_length + 4.0 / 3.0 * math.pi * radius**3
    return math.pi * radius**2 * 2.0 * half_length


def principal_inertia(shape: str, mass: float, radius: float, half_extents: np.ndarray | None, half_length: float) -> np.ndarray:
    """Principal moments (kg m^2) of a uniform solid about its centre, axes of
    the shape (capsule/cylinder along z)."""
    if shape == "sphere":
        i = 0.4 * mass * radius**2
        return np.array([i, i, i])
    if shape == "box":
        a, b, c = (float(x) for x in half_extents)
        return mass / 3.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    r, h = radius, half_length
    if shape == "cylinder":
        iz = 0.5 * mass * r * r
        ix = mass * (3 * r * r + (2 * h) ** 2) / 12.0
        return np.array([ix, ix, iz])
    # capsule: cylinder of length 2h plus two hemispheres sharing the mass by volume.
    vc = math.pi * r * r * 2 * h
    vs = 4.0 / 3.0 * math.pi * r**3
    mc = mass * vc / (vc + vs)
    ms = mass - mc
    iz = mc * r * r / 2 + ms * 2 * r * r / 5
    # each hemisphere: 83/320 m r^2 about its own centroid (3r/8 from the flat
    # face); moved to the capsule centre, the two together give
    # ms (2r^2/5 + h^2 + 3 h r / 4).
    ix = mc * (r * r / 4 + (2 * h) ** 2 / 12) + ms * (2 * r * r / 5 + h * h + 0.75 * h * r)
    return np.array([ix, ix, iz])


# --------------------------------------------------------------------------
# patterns


def _extent(b: BodySection) -> np.ndarray:
    """Half-size of the shape along world axes at its given orientation, taken
    as the axis-aligned half-size (patterns assume the identity orientation)."""
    if b.shape == "sphere":
        return np.full(3, b.radius)
    if b.shape == "box":
        return np.array(b.half_extents, float)
    return np.array([b.radius, b.radius, b.half_length + (b.radius if b.shape == "capsule" else 0.0)])


def expand_pattern(b: BodySection) -> list[tuple[str, np.ndarray]]:
    """Names and positions for a body entry's pattern (or the entry itself).

    column: ``count`` bodies up +z from ``position``; row: along +x;
    grid: ``counts`` [nx, ny, nz] along x, y, z; pyramid: ``count`` levels in
    the x-z plane, the base centred on ``position``; rack: a billiard triangle
    of ``count`` rows in the x-y plane, apex at ``position``, opening toward
    +x.  ``spacing`` is the centre distance (scalar or per axis); by default
    the shape's size plus ``gap``.
    """
    p0 = np.array(b.position, float)
    if b.pattern is None:
        return [(b.name, p0)]
    pat = b.pattern
    size = 2.0 * _extent(b) + pat.gap
    if pat.spacing is None:
        sp = size
    elif isinstance(pat.spacing, (int, float)):
        sp = np.full(3, float(pat.spacing))
    else:
        sp = np.array(pat.spacing, float)
    pts: list[np.ndarray] = []
    if pat.kind == "column":
        pts = [p0 + np.array([0, 0, k * sp[2]]) for k in range(pat.count)]
    elif pat.kind == "row":
        pts = [p0 + np.array([k * sp[0], 0, 0]) for k in range(pat.count)]
    elif pat.kind == "grid":
        nx, ny, nz = pat.counts
        pts = [p0 + np.array([i * sp[0], j * sp[1], k * sp[2]]) for k in range(nz) for j in range(ny) for i in range(nx)]
    elif pat.kind == "pyramid":
        n = pat.count
        for level in range(n):
            width = n - level
            for k in range(width):
                x = (k - (width - 1) / 2.0) * sp[0]
                pts.append(p0 + np.array([x, 0.0, level * sp[2]]))
    elif pat.kind == "rack":
        # rows of a triangle: row r has r+1 balls; rows spaced d*sqrt(3)/2 in x
        d = sp[0]
        for r in range(pat.count):
            for k in range(r + 1):
                pts.append(p0 + np.array([r * d * math.sqrt(3) / 2.0, (k - r / 2.0) * d, 0.0]))
    return [(f"{b.name}_{i}", p) for i, p in enumerate(pts)]


# --------------------------------------------------------------------------
# compile


def _id_for(path: Path | None, family: str) -> str:
    if path is None:
        return f"{family}.inline"
    try:
        rel = path.resolve().relative_to(SCENARIO_DIR.resolve())
        return ".".join(rel.with_suffix("").parts)
    except ValueError:
        return f"{family}.{path.stem}"


def compile_scene(spec: SpecModel, path: Path | None = None, variant: str | None = None,
                  variant_names: tuple[str, ...] = (), label: str | None = None) -> Scene:
    """Validated spec -> Scene.  Raises SpecError for problems that need the
    expanded scene (ambiguous material pairs, duplicate pattern names)."""
    label = label or (str(path) if path else "<inline>")
    errs: list[str] = []
    mats: dict[str, Material] = {
        "default": Material("default", 0.0, 0.0, 0.0, 0.0),
    }
    for name, m in spec.material.items():
        mats[name] = Material(
            name,
            m.restitution,
            m.friction,
            m.static_friction if m.static_friction is not None else m.friction,
            m.rolling_friction,
        )
    bodies: list[Body] = []
    seen: set[str] = set()
    for bi, b in enumerate(spec.body):
        he = np.array(b.half_extents, float) if b.half_extents is not None else None
        r = b.radius or 0.0
        h = b.half_length or 0.0
        mass = b.mass if b.mass is not None else b.density * shape_volume(b.shape, r, he, h)
        why = bound_error("mass", mass)
        if why:
            errs.append(f"{label}: body[{bi}].density: the mass it gives (density x volume) {why}")
            continue
        inertia = principal_inertia(b.shape, mass, r, he, h)
        for name, pos in expand_pattern(b):
            if name in seen:
                errs.append(f"{label}: body[{bi}].name: pattern makes a duplicate body name {name!r}")
            far = next((float(c) for c in pos if bound_error("position", float(c))), None)
            if far is not None:
                errs.append(f"{label}: body[{bi}].pattern: body {name!r} at {pos.tolist()}: position "
                            f"{bound_error('position', far)}")
                break
            seen.add(name)
            bodies.append(Body(
                index=len(bodies), name=name, shape=b.shape, mass=float(mass), inertia=inertia,
                position=pos, orientation=np.array(b.orientation, float),
                velocity=np.array(b.velocity, float), angular_velocity=np.array(b.angular_velocity, float),
                material=b.material, radius=r, half_extents=he, half_length=h,
                drag_linear=b.drag_linear, drag_quadratic=b.drag_quadratic,
            ))
    statics: list[Static] = []
    for si, s in enumerate(spec.static):
        name = s.name or f"static_{si}"
        if s.shape == "plane":
            n = np.array(s.normal, float)
            n /= np.linalg.norm(n)
            statics.append(Static(si, name, "plane", "plane", s.material, normal=n, offset=float(s.offset or 0.0)))
        elif s.shape == "slope":
            a = math.radians(s.angle)
            n = np.array([math.sin(a), 0.0, math.cos(a)])
            pt = np.array(s.point if s.point is not None else (0.0, 0.0, 0.0), float)
            statics.append(Static(si, name, "plane", "slope", s.material, normal=n, offset=float(n @ pt), angle=float(s.angle)))
        else:
            statics.append(Static(si, name, "box", "box", s.material,
                                  position=np.array(s.position, float),
                                  orientation=np.array(s.orientation or (1.0, 0.0, 0.0, 0.0), float),
                                  half_extents=np.array(s.half_extents, float)))
    # ambiguous material pairs: two different named materials that may touch
    if "contact" in spec.scenario.effects:
        used = sorted({b.material for b in bodies})
        used_static = sorted({s.material for s in statics})
        for i, ma in enumerate(used):
            others = used[i + 1:] + [m for m in used_static if m != ma]
            for mb in others:
                if "default" in (ma, mb) or ma == mb:
                    continue
                A, B = mats[ma], mats[mb]
                if (A.restitution, A.friction, A.static_friction, A.rolling_friction) != (
                        B.restitution, B.friction, B.static_friction, B.rolling_friction):
                    errs.append(
                        f"{label}: material.{mb}: materials {ma!r} and {mb!r} can touch but "
                        f"differ; the pair value would be ambiguous (give one of them the "
                        f"name 'default', or make their coefficients equal)")
    index = {b.name: b.index for b in bodies}
    springs = []
    for si, sp in enumerate(spec.spring):
        ia = -1 if sp.a == "world" else index.get(sp.a)
        ib = -1 if sp.b == "world" else index.get(sp.b)
        if ia is None or ib is None:
            errs.append(f"{label}: spring[{si}]: unknown body {sp.a if ia is None else sp.b!r}")
            continue
        springs.append(Spring(ia, ib, np.array(sp.anchor_a, float), np.array(sp.anchor_b, float),
                              sp.stiffness if "spring" in spec.scenario.effects else 0.0,
                              sp.rest_length,
                              sp.damping if "damper" in spec.scenario.effects else 0.0))
    if errs:
        raise SpecError(errs)
    sc = spec.scenario
    scene = Scene(
        id=_id_for(path, sc.family), variant=variant, path=path, family=sc.family, title=sc.title,
        duration=sc.duration, dt=sc.dt, effects=frozenset(sc.effects), planar=sc.planar,
        gravity_vector=np.array(sc.gravity, float), primary_metric=sc.primary_metric,
        tags=tuple(sc.tags), materials=mats, bodies=tuple(bodies), statics=tuple(statics),
        springs=tuple(springs),
        reference_model=spec.reference.model if spec.reference else None,
        reference_params=dict(spec.reference.params) if spec.reference else {},
        checks=tuple(Check(c.metric, c.max, c.min, c.equals, c.tolerance,
                           tuple(c.engines) if c.engines is not None else None,
                           tuple(c.variants) if c.variants is not None else None,
                           dict(c.xfail)) for c in spec.check),
        variant_names=variant_names,
        phases=sc.phases,
    )
    # the reference model must accept the scene, and every checked metric
    # must be produced for it (tests/test_models.py)
    errs = model_refusal(scene, label)
    if errs:
        raise ModelRefusal(errs)
    errs = scene_errors(scene, label)
    if errs:
        raise SpecError(errs)
    scene = dataclasses.replace(scene, content_hash=content_hash(scene))
    if scene.phases > 1:
        # every phase must be runnable: the start must be free flight
        try:
            shift_scene(scene, (scene.phases - 1) / scene.phases)
        except PhaseError as e:
            raise SpecError([f"{label}: scenario.phases: {scene.phases} step phases need a start in free flight: "
                             f"{e}"]) from None
    return scene


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
    carry them apart).  Pinned by tests/test_scene_identity.py."""
    doc = {k: _canonical(getattr(scene, k)) for k in _CONTENT_FIELDS}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def source_path(source: str) -> Path | None:
    """A row's ``scene_path`` (:attr:`Scene.source`) -> the file, or None."""
    if not source:
        return None
    p = Path(source)
    return p if p.is_absolute() else REPO_ROOT / p


def resolve_scenario(name: str | Path) -> Path:
    """A scenario id ('billiards.head_on') or a path -> the spec file's path."""
    p = Path(name)
    if p.suffix == ".toml" or p.exists():
        return p
    parts = str(name).split(".")
    cand = SCENARIO_DIR.joinpath(*parts).with_suffix(".toml")
    if cand.is_file():
        return cand
    import difflib

    ids = scenario_ids()
    near = difflib.get_close_matches(str(name), ids, n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(near)}? " if near else ""
    raise SpecError([f"{name}: <scenario>: no spec file and no scenario with this id; {hint}"
                     f"{len(ids)} scenarios are known ('physbench list' names them)"])


def spec_targets(entry: str | Path, base: Path | None = None) -> list[str]:
    """One selection entry -> the specs it names: a scenario id stays the
    id; a spec file (``*.toml``, anywhere) is its path; a folder is every
    ``*.toml`` below it (sorted, hidden files skipped).  Relative paths are
    taken from ``base`` when given (a suite file's folder), else from the
    working directory.  Anything else raises SpecError naming the entry."""
    text = str(entry)
    p = Path(text)
    if base is not None and not p.is_absolute():
        p = base / p
    pathlike = p.suffix == ".toml" or "/" in text or p.exists()
    if p.is_dir():
        files = sorted(q for q in p.rglob("*.toml")
                       if not any(part.startswith(".") for part in q.relative_to(p).parts))
        if not files:
            raise SpecError([f"{text}: <scenario>: a folder without spec files (*.toml)"])
        return [str(q) for q in files]
    if pathlike:
        if not p.is_file():
            raise SpecError([f"{text}: <scenario>: no such spec file" + (f" (looked for {p})" if p != Path(text) else "")])
        return [str(p)]
    resolve_scenario(text)  # an id: raises SpecError naming the known ones
    return [text]


def canonical_example() -> Path:
    """The canonical spec: ../shared/examples/head_on.toml beside the
    repository, else the copy kept under tests/data."""
    shared = REPO_ROOT.parent / "shared" / "examples" / "head_on.toml"
    return shared if shared.is_file() else REPO_ROOT / "tests" / "data" / "head_on.toml"


def scenario_ids() -> list[str]:
    return sorted(".".join(p.relative_to(SCENARIO_DIR).with_suffix("").parts)
                  for p in SCENARIO_DIR.rglob("*.toml"))


def load_scene(name: str | Path, variant: str | None = None, overrides: dict[str, Any] | None = None,
               loaded: LoadedSpec | None = None) -> Scene:
    """Load, validate and compile one scene (optionally a variant, optionally
    with dotted-key ``overrides``).  Raises SpecError."""
    if loaded is None:
        loaded = load_spec(resolve_scenario(name))
    spec = loaded.validated(variant, overrides)
    return compile_scene(spec, loaded.path, variant, tuple(loaded.variants), loaded.label)
