"""The spec's schema: the effects, shapes and pattern kinds a spec may name,
and one strict pydantic model per TOML section (unknown keys are errors,
every float finite, physical values within contract/spec/bounds.py)."""

from __future__ import annotations

import math
import re
from typing import Any, Literal, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from physbench.contract.geometry.start import MAX_INITIAL_OVERLAP
from physbench.contract.models import MODELS
from physbench.contract.spec.bounds import BOUNDS, _bound, _bounded, _bounded_each, _bounded_norm, record_size_error

EFFECTS = (
    "gravity",
    "contact",
    "restitution",
    "friction",
    "rolling_friction",
    "drag_linear",
    "drag_quadratic",
    "spring",
    "damper",
    "gyroscopic",
    "joint",
)
#: the kinds a ``[[joint]]`` may be (docs/SCENARIO_FORMAT.md, "Joints")
JOINT_KINDS = ("revolute", "spherical", "prismatic", "fixed")
#: the kinds that take an ``axis`` (a hinge axis, a slide axis); the others refuse one
JOINT_AXIS_KINDS = ("revolute", "prismatic")
BODY_SHAPES = ("sphere", "box", "capsule", "cylinder")
STATIC_SHAPES = ("plane", "box", "slope")

# Which dimension keys each shape uses; any other dimension key is an error.
SHAPE_DIMENSIONS = {
    "sphere": ("radius",),
    "box": ("half_extents",),
    "capsule": ("radius", "half_length"),
    "cylinder": ("radius", "half_length"),
}
_ALL_DIMENSIONS = ("radius", "half_extents", "half_length")

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def _one_of(what: str, choices: tuple[str, ...]) -> Any:
    """A field validator admitting only ``choices``; the error names
    ``what`` ("shape", "static shape") and lists the choices."""

    def validate(cls: Any, v: str) -> str:
        if v not in choices:
            raise ValueError(f"unknown {what} {v!r}; expected one of {', '.join(choices)}")
        return v

    return validate



def _admits(annotation: Any, kinds: tuple[type, ...]) -> bool:
    """Whether a field's type admits a value of one of ``kinds`` anywhere
    in it (``str | None``, ``dict[str, str]``, ``tuple[float, ...]``: the
    outer type and its arguments)."""
    if annotation in kinds or annotation is Any:
        return True
    return any(_admits(a, kinds) for a in get_args(annotation))


def _parses(text: str) -> bool:
    """Whether ``text`` reads as a number or a boolean (a value quoted by slip)."""
    if text.strip().lower() in ("true", "false"):
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True


class _Strict(BaseModel):
    # allow_inf_nan=False: every float in a spec is finite ('finite_number')
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_type_slips(cls, v: Any, info: Any) -> Any:
        """A number written as text (``max = "0.001"``) or as true/false,
        where the key takes numbers, is refused, never converted
        (tests/test_spec.py::test_type_slips_are_refused): pydantic's lax
        mode would read "0.001" as 0.001 and true as 1.0."""
        ann = cls.model_fields[info.field_name].annotation
        items = v if isinstance(v, (list, tuple)) else [v]
        for x in items:
            if isinstance(x, str) and not _admits(ann, (str,)) and _admits(ann, (float, int, bool)):
                what = "a number" if _admits(ann, (float, int)) else "true or false"
                raise ValueError(f"expected {what}, got {x!r}" + (" (text, in quotes: write the value without them)"
                                                                 if _parses(x) else ""))
            if isinstance(x, bool) and not _admits(ann, (bool,)) and _admits(ann, (float, int)):
                raise ValueError(f"expected a number, got {str(x).lower()}")
        return v


def _finite(v: float, what: str = "a finite number") -> float:
    if isinstance(v, bool) or not math.isfinite(v):
        raise ValueError(f"must be {what}, got {v!r}")
    return v


class ScenarioSection(_Strict):
    family: str = Field(min_length=1)
    title: str = Field(min_length=1)
    duration: float = Field(gt=0)
    dt: float = Field(gt=0)
    effects: list[str]
    planar: bool = False
    gravity: Vec3 = (0.0, 0.0, -9.81)
    primary_metric: str | None = None
    tags: list[str] = Field(default_factory=list)
    description: str | None = None
    #: step phases the conformance checks are evaluated over (contract/phase.py):
    #: 1 = the scene as written only; N > 1 = also N - 1 runs with the start
    #: moved back along the free flight by i/N dt, every one must pass
    phases: int = Field(default=1, ge=1, le=256)
    #: the deepest overlap (m) the initial poses may have (contract/geometry/start.py);
    #: raise it only where an overlap at the start is the point of the scene
    max_initial_overlap: float = Field(default=MAX_INITIAL_OVERLAP, ge=0.0, le=1e6)

    @field_validator("family")
    @classmethod
    def _family_plain(cls, v: str) -> str:
        return _plain(v)

    @field_validator("effects")
    @classmethod
    def _effects_known(cls, v: list[str]) -> list[str]:
        for i, e in enumerate(v):
            if e not in EFFECTS:
                raise ValueError(
                    f"[{i}] unknown effect {e!r}; expected one of {', '.join(EFFECTS)}"
                )
        if len(set(v)) != len(v):
            raise ValueError(f"effects are listed twice: {v}")
        return v

    _duration_bounded = field_validator("duration")(_bound("duration"))
    _dt_bounded = field_validator("dt")(_bound("dt"))
    _gravity_bounded = field_validator("gravity")(_bound("gravity", "norm"))

    @model_validator(mode="after")
    def _dt_fits(self) -> "ScenarioSection":
        if self.dt > self.duration:
            raise ValueError(
                f"dt ({self.dt}) must not exceed duration ({self.duration})"
            )
        steps = round(self.duration / self.dt)
        if steps > BOUNDS["steps"][1]:
            raise ValueError(f"duration / dt = {self.duration:g} / {self.dt:g}: "
                             f"{record_size_error(int(steps), 1)}")
        return self


class MaterialSection(_Strict):
    restitution: float = Field(default=0.0, ge=0.0, le=1.0)
    friction: float = Field(default=0.0, ge=0.0)
    static_friction: float | None = Field(default=None, ge=0.0)
    rolling_friction: float = Field(default=0.0, ge=0.0)

    _friction_bounded = field_validator("friction", "static_friction")(_bound("friction"))
    _rolling_bounded = field_validator("rolling_friction")(_bound("rolling_friction"))

    @model_validator(mode="after")
    def _static_ge_kinetic(self) -> "MaterialSection":
        if self.static_friction is not None and self.static_friction < self.friction:
            raise ValueError(
                f"static_friction ({self.static_friction}) must be >= friction "
                f"({self.friction})"
            )
        return self


class PatternSection(_Strict):
    kind: Literal["column", "pyramid", "grid", "rack", "row"]
    count: int | None = Field(default=None, ge=1)
    counts: tuple[int, int, int] | None = None
    spacing: float | Vec3 | None = None
    gap: float = Field(default=0.0, ge=0.0)

    _count_bounded = field_validator("count")(_bound("bodies"))
    _counts_bounded = field_validator("counts")(_bound("bodies", "each"))
    _gap_bounded = field_validator("gap")(_bound("position"))

    @field_validator("spacing")
    @classmethod
    def _spacing_bounded(cls, v: float | Vec3 | None) -> float | Vec3 | None:
        return _bounded("position", v) if isinstance(v, (int, float)) else _bounded_each("position", v)

    def n_bodies(self) -> int:
        """Bodies the pattern makes (pyramid: count levels, a rack: count rows)."""
        if self.kind == "grid":
            return math.prod(self.counts or (1,))
        n = self.count or 1
        return n * (n + 1) // 2 if self.kind in ("pyramid", "rack") else n

    @model_validator(mode="after")
    def _counts(self) -> "PatternSection":
        if self.kind == "grid":
            if self.counts is None:
                raise ValueError("kind 'grid' needs counts = [nx, ny, nz]")
            if any(c < 1 for c in self.counts):
                raise ValueError(f"counts must be >= 1 each, got {list(self.counts)}")
            if self.count is not None:
                raise ValueError("kind 'grid' takes counts, not count")
        else:
            if self.count is None:
                raise ValueError(f"kind {self.kind!r} needs count")
            if self.counts is not None:
                raise ValueError(f"kind {self.kind!r} takes count, not counts")
        return self


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def name_error(name: str) -> str | None:
    """Why ``name`` cannot name a body, static, material, variant or family,
    or None.  Any text is a name (quotes, '<', '&', long names: adapters
    escape them, tests/test_fuzz.py::test_hostile_names_run) except control
    characters: names land in tables, logs, JUnit XML (XML 1.0 cannot hold
    most of them) and rerun entity paths."""
    m = _CONTROL.search(name)
    if m:
        return (f"must not contain control characters (newline, tab, NUL, ...), got {m.group()!r} at "
                f"index {m.start()} of {name[:60]!r}{'...' if len(name) > 60 else ''}")
    return None


def _plain(v: str | None) -> str | None:
    if v is not None:
        msg = name_error(v)
        if msg:
            raise ValueError(msg)
    return v


def _half_extents(cls: Any, v: Vec3 | None) -> Vec3 | None:
    """The field validator of a box's ``half_extents`` (bodies and statics):
    every component > 0 and within the 'length' bound; None passes."""
    if v is not None and any(c <= 0 for c in v):
        raise ValueError(f"must be > 0 in every component, got {list(v)}")
    return _bounded_each("length", v)


def _check_quat(q: tuple[float, ...]) -> tuple[float, ...]:
    n = math.sqrt(sum(c * c for c in q))
    if abs(n - 1.0) > 1e-6:
        raise ValueError(
            f"must be a unit quaternion (w, x, y, z), got {list(q)} with norm {n:.6g}"
        )
    return q


class BodySection(_Strict):
    name: str = Field(min_length=1)
    shape: str
    radius: float | None = Field(default=None, gt=0)
    half_extents: Vec3 | None = None
    half_length: float | None = Field(default=None, gt=0)
    mass: float | None = Field(default=None, gt=0)
    density: float | None = Field(default=None, gt=0)
    position: Vec3 = (0.0, 0.0, 0.0)
    orientation: Quat = (1.0, 0.0, 0.0, 0.0)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    material: str = "default"
    drag_linear: float = Field(default=0.0, ge=0.0)
    drag_quadratic: float = Field(default=0.0, ge=0.0)
    pattern: PatternSection | None = None

    _shape_known = field_validator("shape")(_one_of("shape", BODY_SHAPES))

    @field_validator("name", "material")
    @classmethod
    def _name_plain(cls, v: str) -> str:
        return _plain(v)

    _positive_extents = field_validator("half_extents")(_half_extents)

    _length_bounded = field_validator("radius", "half_length")(_bound("length"))
    _mass_bounded = field_validator("mass")(_bound("mass"))
    _density_bounded = field_validator("density")(_bound("density"))
    _position_bounded = field_validator("position")(_bound("position", "each"))
    _speed_bounded = field_validator("velocity")(_bound("speed", "norm"))
    _angular_speed_bounded = field_validator("angular_velocity")(_bound("angular_speed", "norm"))
    _drag_bounded = field_validator("drag_linear", "drag_quadratic")(_bound("drag"))

    @field_validator("orientation")
    @classmethod
    def _unit(cls, v: Quat) -> Quat:
        return _check_quat(v)

    @model_validator(mode="after")
    def _dims_and_mass(self) -> "BodySection":
        need = SHAPE_DIMENSIONS[self.shape]
        for key in _ALL_DIMENSIONS:
            given = getattr(self, key) is not None
            if key in need and not given:
                raise ValueError(f"shape {self.shape!r} needs {key}")
            if key not in need and given:
                raise ValueError(f"{key} is not a dimension of shape {self.shape!r}")
        if (self.mass is None) == (self.density is None):
            raise ValueError("give exactly one of mass or density")
        return self


class StaticSection(_Strict):
    name: str | None = None
    shape: str
    normal: Vec3 | None = None
    offset: float | None = None
    half_extents: Vec3 | None = None
    position: Vec3 | None = None
    orientation: Quat | None = None
    point: Vec3 | None = None
    angle: float | None = None
    material: str = "default"

    _shape_known = field_validator("shape")(_one_of("static shape", STATIC_SHAPES))

    @field_validator("orientation")
    @classmethod
    def _unit(cls, v: Quat | None) -> Quat | None:
        return None if v is None else _check_quat(v)

    _position_bounded = field_validator("position", "point")(_bound("position", "each"))

    @field_validator("name", "material")
    @classmethod
    def _name_plain(cls, v: str | None) -> str | None:
        return _plain(v)

    _extents_bounded = field_validator("half_extents")(_half_extents)

    _offset_bounded = field_validator("offset")(_bound("position"))

    @field_validator("normal")
    @classmethod
    def _normal_bounded(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and math.sqrt(sum(c * c for c in v)) < 1e-12:
            raise ValueError("must be a non-zero vector")
        return _bounded_norm("normal", v)

    @model_validator(mode="after")
    def _keys_for_shape(self) -> "StaticSection":
        allowed = {
            "plane": {"normal", "offset"},
            "box": {"half_extents", "position", "orientation"},
            "slope": {"point", "angle"},
        }[self.shape]
        required = {
            "plane": {"normal"},
            "box": {"half_extents", "position"},
            "slope": {"angle"},
        }[self.shape]
        for key in ("normal", "offset", "half_extents", "position", "orientation", "point", "angle"):
            given = getattr(self, key) is not None
            if given and key not in allowed:
                raise ValueError(f"{key} is not a key of static shape {self.shape!r}")
            if not given and key in required:
                raise ValueError(f"static shape {self.shape!r} needs {key}")

        if self.angle is not None and not -90.0 < self.angle < 90.0:
            raise ValueError(f"angle must be in (-90, 90) degrees, got {self.angle}")
        return self


class ReferenceSection(_Strict):
    model: str
    params: dict[str, Any] = Field(default_factory=dict)

    @field_validator("params")
    @classmethod
    def _params_finite(cls, v: dict[str, Any]) -> dict[str, Any]:
        def walk(x: Any, where: str) -> None:
            if isinstance(x, float) and not math.isfinite(x):
                raise ValueError(f"{where}: must be a finite number, got {x!r}")
            if isinstance(x, int) and not isinstance(x, bool) and abs(x) > 2**53:
                raise ValueError(f"{where}: must be an integer within +-2**53, got {x}")
            if isinstance(x, dict):
                for k, y in x.items():
                    walk(y, f"{where}.{k}")
            elif isinstance(x, list):
                for i, y in enumerate(x):
                    walk(y, f"{where}[{i}]")

        for k, x in v.items():
            walk(x, k)
        return v

    @field_validator("model")
    @classmethod
    def _model_known(cls, v: str) -> str:
        if v not in MODELS:
            raise ValueError(
                f"unknown reference model {v!r}; expected one of {', '.join(sorted(MODELS))}"
            )
        return v


class SpringSection(_Strict):
    a: str
    b: str
    anchor_a: Vec3 = (0.0, 0.0, 0.0)
    anchor_b: Vec3 = (0.0, 0.0, 0.0)
    stiffness: float = Field(default=0.0, ge=0.0)
    rest_length: float = Field(default=0.0, ge=0.0)
    damping: float = Field(default=0.0, ge=0.0)

    _anchor_bounded = field_validator("anchor_a", "anchor_b")(_bound("position", "each"))
    _stiffness_bounded = field_validator("stiffness")(_bound("stiffness"))
    _damping_bounded = field_validator("damping")(_bound("damping"))
    _rest_length_bounded = field_validator("rest_length")(_bound("rest_length"))


class XfailSection(_Strict):
    """The table form of a known limitation (contract/xfail.py)."""

    reason: str
    measured_on: str | None = None
    versions: str | None = None
    #: the spec's variants it holds in ("base": the scene as written); None: every one
    variants: list[str] | None = None

    @model_validator(mode="after")
    def _versions(self) -> "XfailSection":
        from physbench.contract.xfail import spec_error

        why = spec_error("", self.model_dump())
        if why:
            raise ValueError(why)
        return self


class JointSection(_Strict):
    """``[[joint]]``: ``body`` held to ``other`` ("world" or a body's name)
    at the world point ``anchor`` (m, at the start); ``axis`` (world frame,
    any length > 0, normalised on compile) is the hinge axis of a revolute
    joint and the slide axis of a prismatic one, and is refused for the
    other kinds (it would be ignored).

    ``chain`` instead of ``body``: the name of a ``row`` or ``column``
    pattern of bodies, joined link to link, one joint per link (compiled in
    contract.scene._compile_joints): ``<chain>_0`` held to ``other`` at
    ``anchor``, ``<chain>_i`` to ``<chain>_<i-1>`` at ``anchor`` moved by
    the pattern's offset of link i from link 0.  The chain's length is
    the pattern's ``count``, a spec key (``body[k].pattern.count``) that
    variants, ``--set`` and breaking-point searches can vary.  Tests:
    tests/test_joint_chain.py."""

    name: str | None = Field(default=None, min_length=1)
    kind: str
    body: str | None = Field(default=None, min_length=1)
    chain: str | None = Field(default=None, min_length=1)
    other: str = Field(default="world", min_length=1)
    anchor: Vec3
    axis: Vec3 | None = None

    _kind_known = field_validator("kind")(_one_of("joint kind", JOINT_KINDS))
    _anchor_bounded = field_validator("anchor")(_bound("position", "each"))

    @model_validator(mode="after")
    def _body_or_chain(self) -> "JointSection":
        if self.body is None and self.chain is None:
            raise ValueError("a joint needs body = <a body's name> (or chain = <a patterned body's name>)")
        if self.body is not None and self.chain is not None:
            raise ValueError(f"give body or chain, not both (body = {self.body!r}, chain = {self.chain!r})")
        return self

    @field_validator("name", "body", "chain", "other")
    @classmethod
    def _name_plain(cls, v: str | None) -> str | None:
        return _plain(v)

    @field_validator("axis")
    @classmethod
    def _axis_nonzero(cls, v: Vec3 | None) -> Vec3 | None:
        # tests/test_joints_spec.py::test_zero_axis_names_the_key
        if v is not None and math.sqrt(sum(c * c for c in v)) < 1e-12:
            raise ValueError(f"the axis must have a non-zero length, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _axis_for_kind(self) -> "JointSection":
        if self.kind in JOINT_AXIS_KINDS and self.axis is None:
            raise ValueError(f"a {self.kind} joint needs axis = [x, y, z] (world frame, at the start)")
        if self.kind not in JOINT_AXIS_KINDS and self.axis is not None:
            raise ValueError(f"a {self.kind} joint takes no axis (only {' and '.join(JOINT_AXIS_KINDS)} joints do)")
        return self


class CheckSection(_Strict):
    metric: str
    max: float | None = None
    min: float | None = None
    equals: float | bool | None = None
    tolerance: float = Field(default=0.0, ge=0.0)
    engines: list[str] | None = None
    variants: list[str] | None = None
    #: engine -> known limitation: a reason (measured on contract.xfail.MEASURED_ON's
    #: version) or a table with reason, measured_on, versions, variants
    xfail: dict[str, str | XfailSection] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_bound(self) -> "CheckSection":
        if self.max is None and self.min is None and self.equals is None:
            raise ValueError("a check needs max, min or equals")
        if self.equals is not None and (self.max is not None or self.min is not None):
            raise ValueError("equals cannot be combined with max or min")
        if self.max is not None and self.min is not None:
            # one bound per check (tests/test_spec.py::test_type_slips_are_refused)
            raise ValueError(f"give one of max or min, not both (max = {self.max!r}, min = {self.min!r}); "
                             f"write two [[check]] tables for a range")
        return self


class PerturbationSection(_Strict):
    """``[perturbation]``: the ensemble of perturbed starts that judges the
    scene's predictability (harness/ensemble.py): ``n`` members, Gaussian
    standard deviations per component (m, m/s, rad, rad/s), the seed, the
    perturbed bodies (default all), the bound on the final spread (m)."""

    n: int = Field(default=16, ge=2, le=1000)
    position: float = Field(default=0.0, ge=0.0, le=1.0)
    velocity: float = Field(default=0.0, ge=0.0, le=100.0)
    orientation: float = Field(default=0.0, ge=0.0, le=math.pi)
    angular_velocity: float = Field(default=0.0, ge=0.0, le=1000.0)
    seed: int = Field(default=0, ge=0, le=2**32 - 1)
    bodies: list[str] | None = None
    threshold: float = Field(default=0.01, gt=0.0, le=1e6)

    @model_validator(mode="after")
    def _some_noise(self) -> "PerturbationSection":
        if not (self.position or self.velocity or self.orientation or self.angular_velocity):
            raise ValueError("every standard deviation (position, velocity, orientation, angular_velocity) is 0: "
                             "the members would all be the same run")
        return self


class SpecModel(_Strict):
    scenario: ScenarioSection
    material: dict[str, MaterialSection] = Field(default_factory=dict)
    body: list[BodySection] = Field(default_factory=list)
    static: list[StaticSection] = Field(default_factory=list)
    spring: list[SpringSection] = Field(default_factory=list)
    joint: list[JointSection] = Field(default_factory=list)
    reference: ReferenceSection | None = None
    check: list[CheckSection] = Field(default_factory=list)
    perturbation: PerturbationSection | None = None



def integer_key(path: str) -> bool:
    """Whether the dotted spec key ``path`` ('body[0].pattern.count') holds
    an integer in the schema (a count), so that a breaking-point search
    over it steps in whole numbers; False for any other key and for a path
    the schema does not have.  Test:
    tests/test_joint_chain.py::test_integer_spec_keys."""
    import types
    import typing

    from physbench.contract.spec.overrides import parse_key_path

    def unwrap(t: Any) -> Any:
        if typing.get_origin(t) in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(t) if a is not type(None)]
            return args[0] if len(args) == 1 else None
        return t

    try:
        parts = parse_key_path(path)
    except ValueError:
        return False
    t: Any = SpecModel
    for part in parts:
        t = unwrap(t)
        if isinstance(part, int):
            if typing.get_origin(t) is not list:
                return False
            t = typing.get_args(t)[0]
        elif isinstance(t, type) and issubclass(t, BaseModel):
            f = t.model_fields.get(part)
            if f is None:
                return False
            t = f.annotation
        elif typing.get_origin(t) is dict:
            t = typing.get_args(t)[1]
        else:
            return False
    return unwrap(t) is int
