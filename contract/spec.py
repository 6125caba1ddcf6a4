"""Scenario spec loading and validation: TOML -> validated pydantic spec.

The spec format is described in ``docs/SCENARIO_FORMAT.md`` (and in the shared
DESIGN.md).  This module only validates; :mod:`contract.scene` compiles a
validated spec into the engine-neutral scene model that adapters consume.

Every error names the file, the key path and what was expected, e.g.::

    scenarios/billiards/head_on.toml: body[1].mass: must be > 0, got -1

Unknown keys, effects and shapes are errors.  Every number must be finite,
and physical quantities must lie within the bounds of :data:`BOUNDS`
(documented in the bounds table of ``docs/SCENARIO_FORMAT.md``; the test
``tests/test_fuzz.py::test_bounds_table_matches_docs`` keeps the two equal).
"""

from __future__ import annotations

import copy
import math
import re
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from contract.models import MODELS, ReferenceError

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
)
BODY_SHAPES = ("sphere", "box", "capsule", "cylinder")
STATIC_SHAPES = ("plane", "box", "slope")
PATTERN_KINDS = ("column", "pyramid", "grid", "rack", "row")

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

# --------------------------------------------------------------------------
# physical bounds: a value outside them is a mistake (or a unit slip), and the
# engines would meet it as overflow, a warning flood or a diverged run.
# (lo, hi, unit, what); a vector's bound applies to its norm or components as
# the key's check says.  Speeds stay a decade below the runner's runaway
# threshold (harness/runner.py RUNAWAY_SPEED = 1e6), positions below its
# RUNAWAY_POSITION = 1e6 (pinned by tests/test_fuzz.py::test_bounds_below_runaway).

BOUNDS: dict[str, tuple[float, float, str, str]] = {
    "length": (1e-6, 1e4, "m", "radius, half_extents, half_length of bodies and static boxes"),
    "position": (-1e5, 1e5, "m", "each component of positions, points, spring anchors, pattern spacing; "
                                  "plane offset; every body after pattern expansion"),
    "mass": (1e-9, 1e9, "kg", "mass, and the mass a density gives"),
    "density": (1e-3, 1e6, "kg/m^3", "density"),
    "speed": (0.0, 1e5, "m/s", "norm of a body's velocity"),
    "angular_speed": (0.0, 1e5, "rad/s", "norm of a body's angular_velocity"),
    "gravity": (0.0, 1e4, "m/s^2", "norm of scenario.gravity"),
    "dt": (1e-7, 1.0, "s", "scenario.dt (the engines' dt setting has the same range)"),
    "duration": (1e-7, 1e6, "s", "scenario.duration"),
    "friction": (0.0, 100.0, "", "friction, static_friction"),
    "rolling_friction": (0.0, 1e4, "m", "rolling_friction (a lever arm)"),
    "drag": (0.0, 1e9, "N s/m, N s^2/m^2", "drag_linear, drag_quadratic"),
    "stiffness": (0.0, 1e12, "N/m", "spring stiffness"),
    "damping": (0.0, 1e9, "N s/m", "spring damping"),
    "rest_length": (0.0, 1e5, "m", "spring rest_length"),
    "normal": (1e-12, 1e5, "", "norm of a plane's normal (it is normalised)"),
    "bodies": (1, 10_000, "", "bodies in a scene after pattern expansion (count, counts)"),
    "steps": (1, 100_000_000, "", "steps of a run: duration / dt"),
    "recorded_bytes": (0, 1 << 30, "bytes", "recorded state of a run: frames x (8 + bodies x 13 x 8)"),
}


def bound_error(kind: str, value: float, *, norm: bool = False) -> str | None:
    """The complaint about ``value`` against ``BOUNDS[kind]``, or None when
    it lies within them (inclusive).  ``norm``: the value is a vector's norm."""
    lo, hi, unit, _ = BOUNDS[kind]
    if lo <= value <= hi:  # exact for ints of any size; False for nan
        return None
    u = f" {unit}" if unit else ""
    what = "norm " if norm else ""
    got = f"{value:g}" if isinstance(value, float) or abs(value) < 10**15 else f"an integer of {len(str(abs(value)))} digits"
    if lo <= 0.0 and kind not in ("position",):
        return f"{what}must be <= {hi:g}{u}, got {got}"
    return f"{what}must be within [{lo:g}, {hi:g}]{u}, got {got}"


def _bounded(kind: str, v: float | None) -> float | None:
    if v is not None:
        msg = bound_error(kind, v)
        if msg:
            raise ValueError(msg)
    return v


def _bounded_each(kind: str, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
    if v is not None:
        for i, c in enumerate(v):
            msg = bound_error(kind, c)
            if msg:
                raise ValueError(f"[{i}] {msg}")
    return v


def _bounded_norm(kind: str, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
    if v is not None:
        n = math.hypot(*v)  # inf, not OverflowError, past 1e154
        msg = bound_error(kind, n, norm=True)
        if msg:
            raise ValueError(f"{msg}: {list(v)}")
    return v


def _bound(kind: str, how: str = "value") -> Any:
    """A field validator holding the field(s) to ``BOUNDS[kind]``: the value
    itself, each component (``how="each"``) or the norm (``"norm"``).
    None (an absent optional key) passes."""
    check = {"value": _bounded, "each": _bounded_each, "norm": _bounded_norm}[how]

    def validate(cls: Any, v: Any) -> Any:
        return check(kind, v)

    return validate


def _one_of(what: str, choices: tuple[str, ...]) -> Any:
    """A field validator admitting only ``choices``; the error names
    ``what`` ("shape", "static shape") and lists the choices."""

    def validate(cls: Any, v: str) -> str:
        if v not in choices:
            raise ValueError(f"unknown {what} {v!r}; expected one of {', '.join(choices)}")
        return v

    return validate


def record_size_error(n_steps: int, n_bodies: int, record_every: int = 1) -> str | None:
    """Why a run of ``n_steps`` steps recording ``n_bodies`` bodies every
    ``record_every`` steps is too large to allocate (BOUNDS 'steps' and
    'recorded_bytes'), or None.  Checked before anything is allocated: at
    load (the scene's own dt, every step) and by the runner (its dt and
    record_every)."""
    max_steps = int(BOUNDS["steps"][1])
    if n_steps > max_steps:
        return f"{n_steps:.4g} steps (duration / dt) exceed the bound of {max_steps:.4g} steps"
    frames = n_steps // max(1, record_every) + 2
    nbytes = frames * (8 + n_bodies * 13 * 8)
    cap = int(BOUNDS["recorded_bytes"][1])
    if nbytes > cap:
        return (f"recording {frames} frames of {n_bodies} bodies takes {nbytes / 2**20:.4g} MiB, beyond the "
                f"bound of {cap / 2**20:g} MiB (record fewer frames, a shorter duration or a larger dt)")
    return None


class SpecError(ValueError):
    """A scenario spec failed to load.  ``errors`` holds one line per problem,
    each ``<file>: <key path>: <what was expected, what was found>``."""

    def __init__(self, errors: list[str]):
        self.errors = list(errors)
        super().__init__("\n".join(self.errors))


class ModelRefusal(SpecError, ReferenceError):
    """The scene's reference model refused the scene at load time: a spec
    error (file, key path, exit 2) that is also the model's
    :class:`contract.models.ReferenceError`."""


class _Strict(BaseModel):
    # allow_inf_nan=False: every float in a spec is finite ('finite_number')
    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)


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

    @field_validator("half_extents")
    @classmethod
    def _positive_extents(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and any(c <= 0 for c in v):
            raise ValueError(f"must be > 0 in every component, got {list(v)}")
        return _bounded_each("length", v)

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

    @field_validator("half_extents")
    @classmethod
    def _extents_bounded(cls, v: Vec3 | None) -> Vec3 | None:
        if v is not None and any(c <= 0 for c in v):
            raise ValueError(f"must be > 0 in every component, got {list(v)}")
        return _bounded_each("length", v)

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


class CheckSection(_Strict):
    metric: str
    max: float | None = None
    min: float | None = None
    equals: float | bool | None = None
    tolerance: float = Field(default=0.0, ge=0.0)
    engines: list[str] | None = None
    variants: list[str] | None = None
    xfail: dict[str, str] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _one_bound(self) -> "CheckSection":
        if self.max is None and self.min is None and self.equals is None:
            raise ValueError("a check needs max, min or equals")
        if self.equals is not None and (self.max is not None or self.min is not None):
            raise ValueError("equals cannot be combined with max or min")
        return self


class SpecModel(_Strict):
    scenario: ScenarioSection
    material: dict[str, MaterialSection] = Field(default_factory=dict)
    body: list[BodySection] = Field(default_factory=list)
    static: list[StaticSection] = Field(default_factory=list)
    spring: list[SpringSection] = Field(default_factory=list)
    reference: ReferenceSection | None = None
    check: list[CheckSection] = Field(default_factory=list)


# --------------------------------------------------------------------------
# error formatting


def _loc_to_path(loc: tuple[Any, ...]) -> str:
    """pydantic loc ('body', 1, 'mass') -> 'body[1].mass'."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after[_dims_and_mass(), BodySection]",):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out


_CMP = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _describe(err: dict[str, Any]) -> str:
    t = err["type"]
    ctx = err.get("ctx") or {}
    got = err.get("input")
    if t in _CMP:
        bound = next(iter(ctx.values()))
        if isinstance(bound, float) and bound.is_integer():
            bound = int(bound)
        return f"must be {_CMP[t]} {bound}, got {got!r}"
    if t == "extra_forbidden":
        return "unknown key"
    if t == "missing":
        return "required key is missing"
    if t == "finite_number":
        return f"must be a finite number, got {got!r}"
    if t in ("float_parsing", "float_type"):
        return f"expected a number, got {got!r}"
    if t in ("int_parsing", "int_type", "int_from_float"):
        return f"expected an integer, got {got!r}"
    if t in ("bool_type", "bool_parsing"):
        return f"expected true or false, got {got!r}"
    if t in ("string_type",):
        return f"expected a string, got {got!r}"
    if t in ("list_type", "tuple_type"):
        return f"expected a list, got {got!r}"
    if t in ("dict_type", "model_type", "model_attributes_type"):
        return f"expected a table, got {got!r}"
    if t == "too_short" or t == "too_long":
        exp = ctx.get("min_length") if t == "too_short" else ctx.get("max_length")
        n = ctx.get("actual_length")
        if isinstance(got, (list, tuple)):
            return f"expected {exp} values, got {n}: {list(got)}"
        return f"expected length {'>=' if t == 'too_short' else '<='} {exp}, got {got!r}"
    if t == "string_too_short":
        return "must not be empty"
    if t == "literal_error":
        return f"expected one of {ctx.get('expected')}, got {got!r}"
    if t == "value_error":
        msg = str(ctx.get("error", err["msg"]))
        return msg
    return f"{err['msg']}, got {got!r}"


_VECTOR_LEN = {"orientation": 4, "counts": 3}


def _lookup(raw: Any, loc: tuple[Any, ...]) -> Any:
    node = raw
    for part in loc:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            return None
    return node


def _format_errors(file: str, exc: ValidationError, raw: Any = None) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and "[" in p and "(" in p))
        # Union members add their type name to loc ('float', 'tuple[...]'); drop them.
        loc = tuple(
            p for p in loc if not (isinstance(p, str) and (p in ("float", "bool", "int") or p.startswith("tuple[")))
        )
        if err["type"] in ("missing", "too_long") and loc and isinstance(loc[-1], int) or (
                err["type"] == "too_long" and isinstance(err.get("input"), (list, tuple))):
            # a fixed-length vector with too few / too many values
            if isinstance(loc[-1], int):
                loc = loc[:-1]
            want = _VECTOR_LEN.get(str(loc[-1]), 3) if loc else 3
            got = _lookup(raw, loc)
            lines.append(f"{file}: {_loc_to_path(loc)}: expected {want} numbers, got {len(got) if isinstance(got, (list, tuple)) else got!r}: {got!r}")
            continue
        path = _loc_to_path(loc)
        msg = _describe(err)
        # value errors raised about an element carry their own '[i]' prefix
        m = re.match(r"^\[(\d+)\] (.*)$", msg)
        if m:
            path, msg = f"{path}[{m.group(1)}]", m.group(2)
        lines.append(f"{file}: {path or '<top>'}: {msg}")
    # unions can report the same problem once per member: keep first of each path
    seen: dict[str, str] = {}
    for line in lines:
        key = line.rsplit(": ", 1)[0]
        seen.setdefault(key, line)
    return list(seen.values())


# --------------------------------------------------------------------------
# dotted-key overrides (variants and --set)

_TOKEN = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def parse_key_path(path: str) -> list[str | int]:
    """'body[1].mass' or 'body.1.mass' -> ['body', 1, 'mass'].  Quoted table
    names are not needed: material names cannot contain dots."""
    parts: list[str | int] = []
    pos = 0
    for m in _TOKEN.finditer(path):
        if m.start() != pos and path[pos:m.start()] != ".":
            raise ValueError(f"malformed key path {path!r}")
        pos = m.end()
        if m.group(2) is not None:
            parts.append(int(m.group(2)))
        else:
            tok = m.group(1)
            parts.append(int(tok) if tok.isdigit() else tok)
    if pos != len(path) or not parts:
        raise ValueError(f"malformed key path {path!r}")
    return parts


def apply_override(raw: dict[str, Any], path: str, value: Any) -> None:
    """Set ``value`` at dotted ``path`` inside ``raw`` (in place).  The parent
    table must exist; list indices must be in range.  Raises ValueError with a
    message naming the path."""
    parts = parse_key_path(path)
    node: Any = raw
    for i, part in enumerate(parts[:-1]):
        where = _loc_to_path(tuple(parts[: i + 1]))
        if isinstance(part, int):
            if not isinstance(node, list) or not -len(node) <= part < len(node):
                n = len(node) if isinstance(node, list) else 0
                raise ValueError(f"{where}: no such entry (there are {n})")
            node = node[part]
        else:
            if not isinstance(node, dict):
                raise ValueError(f"{where}: parent is not a table")
            if part not in node:
                if part in ("material", "reference") or (i >= 1 and parts[0] in ("material",)):
                    node[part] = {}
                else:
                    raise ValueError(f"{where}: no such table")
            node = node[part]
    last = parts[-1]
    if isinstance(last, int):
        if not isinstance(node, list) or not -len(node) <= last < len(node):
            raise ValueError(f"{_loc_to_path(tuple(parts))}: no such entry")
        node[last] = value
    else:
        if not isinstance(node, dict):
            raise ValueError(f"{_loc_to_path(tuple(parts))}: parent is not a table")
        node[last] = value


def parse_value(text: str) -> Any:
    """Parse a --set value as a TOML value ('1e-3', 'true', '[1,2,3]', '"rk4"');
    bare words are taken as strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        return text


# --------------------------------------------------------------------------
# loading


class LoadedSpec:
    """A validated spec with its variants.  ``raw`` is the TOML document minus
    the variant tables; ``variants`` maps variant name -> overrides."""

    def __init__(self, path: Path, raw: dict[str, Any], variants: dict[str, dict[str, Any]]):
        self.path = path
        self.raw = raw
        self.variants = variants

    @property
    def label(self) -> str:
        return _display(self.path)

    def validated(self, variant: str | None = None, overrides: dict[str, Any] | None = None) -> SpecModel:
        """The spec with ``variant`` and then ``overrides`` applied, validated."""
        raw = copy.deepcopy(self.raw)
        label = self.label
        errors: list[str] = []
        if variant is not None:
            if variant not in self.variants:
                names = ", ".join(self.variants) or "none"
                raise SpecError([f"{label}: variant: unknown variant {variant!r}; this spec has: {names}"])
            for key, value in self.variants[variant].items():
                try:
                    apply_override(raw, key, value)
                except ValueError as e:
                    errors.append(f"{label}: variant[{variant}].{key}: {e}")
        for key, value in (overrides or {}).items():
            try:
                apply_override(raw, key, value)
            except ValueError as e:
                errors.append(f"{label}: --set {key}: {e}")
        if errors:
            raise SpecError(errors)
        return validate_raw(raw, label)


def _display(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def validate_raw(raw: dict[str, Any], label: str) -> SpecModel:
    try:
        spec = SpecModel.model_validate(raw)
    except ValidationError as exc:
        raise SpecError(_format_errors(label, exc, raw)) from None
    errors = _cross_checks(spec, label)
    if errors:
        raise SpecError(errors)
    return spec


def _cross_checks(spec: SpecModel, label: str) -> list[str]:
    """Checks that span sections: names, material references, planar rules."""
    errs: list[str] = []
    materials = set(spec.material) | {"default"}
    for m in spec.material:
        why = name_error(m)
        if why:
            errs.append(f"{label}: material: the name {why}")
    names: dict[str, int] = {}
    for i, b in enumerate(spec.body):
        if b.name in names:
            errs.append(f"{label}: body[{i}].name: duplicate body name {b.name!r} (also body[{names[b.name]}])")
        names.setdefault(b.name, i)
        if b.material not in materials:
            errs.append(f"{label}: body[{i}].material: unknown material {b.material!r}; defined: {', '.join(sorted(materials))}")
    for i, s in enumerate(spec.static):
        if s.material not in materials:
            errs.append(f"{label}: static[{i}].material: unknown material {s.material!r}; defined: {', '.join(sorted(materials))}")
    effects = set(spec.scenario.effects)
    for i, sp in enumerate(spec.spring):
        for end in ("a", "b"):
            who = getattr(sp, end)
            if who != "world" and who not in names and not any(
                b.pattern is not None and who.startswith(b.name + "_") for b in spec.body
            ):
                errs.append(f"{label}: spring[{i}].{end}: unknown body {who!r}; expected a body name or 'world'")
        if sp.stiffness > 0 and "spring" not in effects:
            errs.append(f"{label}: spring[{i}].stiffness: the scene has springs but 'spring' is not in scenario.effects")
        if sp.damping > 0 and "damper" not in effects:
            errs.append(f"{label}: spring[{i}].damping: the spring is damped but 'damper' is not in scenario.effects")
    errs += _material_effects(spec, label)
    if ("spring" in effects or "damper" in effects) and not spec.spring:
        errs.append(f"{label}: scenario.effects: 'spring'/'damper' listed but there is no [[spring]] table")
    for i, b in enumerate(spec.body):
        if b.drag_linear > 0 and "drag_linear" not in effects:
            errs.append(f"{label}: body[{i}].drag_linear: set but 'drag_linear' is not in scenario.effects")
        if b.drag_quadratic > 0 and "drag_quadratic" not in effects:
            errs.append(f"{label}: body[{i}].drag_quadratic: set but 'drag_quadratic' is not in scenario.effects")
    if spec.scenario.planar:
        g = spec.scenario.gravity
        if abs(g[1]) > 0:
            errs.append(f"{label}: scenario.gravity: a planar scene lies in the x-z plane, so gravity[1] must be 0, got {list(g)}")
        for i, b in enumerate(spec.body):
            p = f"{label}: body[{i}]"
            if abs(b.position[1]) > 0:
                errs.append(f"{p}.position: a planar scene lies in the x-z plane, so y must be 0, got {list(b.position)}")
            if abs(b.velocity[1]) > 0:
                errs.append(f"{p}.velocity: a planar scene lies in the x-z plane, so y must be 0, got {list(b.velocity)}")
            w = b.angular_velocity
            if abs(w[0]) > 0 or abs(w[2]) > 0:
                errs.append(f"{p}.angular_velocity: a planar scene turns about y only, so x and z must be 0, got {list(w)}")
            q = b.orientation
            if abs(q[1]) > 0 or abs(q[3]) > 0:
                errs.append(f"{p}.orientation: a planar scene turns about y only, so x and z must be 0, got {list(q)}")
            if b.pattern is not None and b.pattern.kind in ("rack", "grid") and b.pattern.kind == "rack":
                errs.append(f"{p}.pattern.kind: a 'rack' lies in the x-y plane and cannot be planar")
        for i, s in enumerate(spec.static):
            if s.normal is not None and abs(s.normal[1]) > 1e-12:
                errs.append(f"{label}: static[{i}].normal: a planar scene lies in the x-z plane, so normal[1] must be 0, got {list(s.normal)}")
            if s.orientation is not None and (abs(s.orientation[1]) > 0 or abs(s.orientation[3]) > 0):
                errs.append(f"{label}: static[{i}].orientation: a planar scene turns about y only, got {list(s.orientation)}")
    n_bodies = sum(1 if b.pattern is None else b.pattern.n_bodies() for b in spec.body)
    if n_bodies < BOUNDS["bodies"][0]:  # tests/test_fuzz.py::test_a_spec_without_bodies_is_rejected
        errs.append(f"{label}: body: the scene has no bodies; expected at least {BOUNDS['bodies'][0]:g} [[body]] table")
    elif n_bodies > BOUNDS["bodies"][1]:
        errs.append(f"{label}: body: the scene has {n_bodies} bodies after pattern expansion, beyond the bound "
                    f"of {BOUNDS['bodies'][1]:g}")
    else:
        sc = spec.scenario
        why = record_size_error(max(1, round(sc.duration / sc.dt)), n_bodies)
        if why:
            errs.append(f"{label}: scenario.duration: {why}")
    for i, c in enumerate(spec.check):
        for eng in c.xfail:
            if c.engines is not None and eng not in c.engines:
                errs.append(f"{label}: check[{i}].xfail.{eng}: engine is not in this check's engines {c.engines}")
    if spec.scenario.primary_metric is not None and spec.reference is None and spec.scenario.primary_metric in (
        "post_impact_velocity_error", "trajectory_rmse", "final_position_error"):
        errs.append(f"{label}: scenario.primary_metric: {spec.scenario.primary_metric!r} needs a [reference] model")
    return errs


#: material coefficient -> the effect without which it would be ignored
MATERIAL_EFFECTS = {"restitution": "restitution", "friction": "friction", "static_friction": "friction",
                    "rolling_friction": "rolling_friction"}


def _material_effects(spec: SpecModel, label: str) -> list[str]:
    """A non-zero material coefficient whose effect the scene does not list
    would be dropped by Scene.pair without a word: an error, as for body and
    spring coefficients (tests/test_spec.py::test_material_coefficient_needs_its_effect)."""
    effects = set(spec.scenario.effects)
    errs = []
    for name, m in spec.material.items():
        for key, effect in MATERIAL_EFFECTS.items():
            value = getattr(m, key)
            if value and effect not in effects:
                errs.append(f"{label}: material.{name}.{key}: set to {value!r} but {effect!r} is not in "
                            f"scenario.effects (add the effect, or leave the coefficient out)")
    return errs


def read_toml(p: Path, label: str, error: type[SpecError] = SpecError) -> tuple[dict[str, Any], bytes]:
    """The TOML document in file ``p`` and the file's bytes.  A missing file, a directory, an
    unreadable file, bytes that are not UTF-8 and invalid TOML raise
    ``error`` (a SpecError: exit 2) naming the file."""
    if p.is_dir():
        raise error([f"{label}: <file>: is a directory; expected a spec file (.toml)"])
    if not p.is_file():
        raise error([f"{label}: <file>: no such file"])
    try:
        data = p.read_bytes()
    except OSError as e:
        raise error([f"{label}: <file>: cannot read: {e.strerror or e}"]) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error([f"{label}: <file>: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); "
                     f"expected a TOML spec"]) from None
    try:
        return tomllib.loads(text), data
    except tomllib.TOMLDecodeError as e:
        raise error([f"{label}: <toml>: not valid TOML: {e}"]) from None
    except RecursionError:
        raise error([f"{label}: <toml>: not valid TOML: arrays or tables nested too deeply"]) from None


def load_spec(path: str | Path) -> LoadedSpec:
    """Read and validate a spec file (base and every variant).  Raises SpecError."""
    p = Path(path)
    label = _display(p)
    raw, _ = read_toml(p, label, SpecError)
    variants_raw = raw.pop("variant", [])
    errors: list[str] = []
    variants: dict[str, dict[str, Any]] = {}
    if not isinstance(variants_raw, list):
        errors.append(f"{label}: variant: expected an array of tables [[variant]], got {type(variants_raw).__name__}")
        variants_raw = []
    for i, v in enumerate(variants_raw):
        if not isinstance(v, dict):
            errors.append(f"{label}: variant[{i}]: expected a table")
            continue
        name = v.get("name")
        if not isinstance(name, str) or not name:
            errors.append(f"{label}: variant[{i}].name: required key is missing")
            continue
        if name_error(name):
            errors.append(f"{label}: variant[{i}].name: {name_error(name)}")
        if name in variants:
            errors.append(f"{label}: variant[{i}].name: duplicate variant name {name!r}")
        variants[name] = {k: val for k, val in v.items() if k != "name"}
    if errors:
        raise SpecError(errors)
    loaded = LoadedSpec(p, raw, variants)
    loaded.validated()
    for name in variants:
        loaded.validated(name)
    return loaded
