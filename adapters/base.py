"""The adapter contract: one thin translation layer per engine.

Every adapter module defines one :class:`Adapter` subclass with:

- ``name`` and :meth:`capabilities` (dimensions, shapes, effects, settings with
  defaults and allowed values, engine version);
- :meth:`unsupported_reason` — why a scene cannot be modelled (a missing
  shape, effect or dimension), or ``None``;
- :meth:`build` — create the engine's world from a :class:`contract.scene.Scene`
  (never from TOML) and resolved settings;
- :meth:`step` — advance n fixed steps;
- :meth:`read_state` — write positions, wxyz quaternions and world-frame
  linear/angular velocities into preallocated arrays (frame ``k``);
- :meth:`close`.

Optionally ``batched = True`` with :meth:`build_batch`,
:meth:`read_state_batch` and :meth:`step_record_batch`: many starts of one
scene stepped in one call (MJX); harness/batch.py hands such batches over.

Adapters also fill ``self.notes`` (approximations the engine forces, e.g. a
missing static/kinetic friction split) and ``self.info`` (calibration
residuals, effective engine parameters) which land in the run result.
"""

from __future__ import annotations

import abc
import functools
import importlib
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from physbench.contract.scene import Scene


@dataclass(frozen=True)
class Setting:
    """An engine setting: default, and either a tuple of allowed ``choices`` or
    a numeric range [lo, hi].  ``default=None`` means 'from the scene' (dt)."""

    name: str
    default: Any
    kind: type
    doc: str
    choices: tuple[Any, ...] | None = None
    lo: float | None = None
    hi: float | None = None

    def coerce(self, value: Any) -> Any:
        """Validate ``value``; raise ValueError naming what was expected."""
        if self.kind is bool:
            if isinstance(value, str) and value.lower() in ("true", "false", "on", "off", "1", "0"):
                value = value.lower() in ("true", "on", "1")
            if not isinstance(value, bool):
                raise ValueError(f"setting {self.name}: expected true or false, got {value!r}")
        elif self.kind in (int, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                try:
                    value = self.kind(value)
                except (TypeError, ValueError):
                    raise ValueError(f"setting {self.name}: expected a number, got {value!r}") from None
            try:
                as_float = float(value)
            except OverflowError:
                as_float = math.inf
            if not math.isfinite(as_float):
                raise ValueError(f"setting {self.name}: expected a finite number, got {value!r}")
            if self.kind is int:
                if as_float != int(value):
                    raise ValueError(f"setting {self.name}: expected an integer, got {value!r}")
                value = int(value)
            else:
                value = as_float
            if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
                raise ValueError(f"setting {self.name}: expected a value in [{self.lo}, {self.hi}], got {value!r}")
        else:
            value = str(value)
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"setting {self.name}: expected one of {', '.join(map(str, self.choices))}, got {value!r}")
        return value

    def describe(self) -> str:
        if self.choices is not None:
            allowed = "|".join(map(str, self.choices))
        elif self.lo is not None or self.hi is not None:
            allowed = f"[{self.lo}, {self.hi}]"
        else:
            allowed = self.kind.__name__
        return allowed


@dataclass(frozen=True)
class Capabilities:
    engine: str
    version: str
    dimensions: int
    shapes: frozenset[str]
    static_shapes: frozenset[str]
    effects: frozenset[str]
    settings: dict[str, Setting]
    available: bool = True
    unavailable_reason: str = ""
    notes: tuple[str, ...] = ()
    #: the [[joint]] kinds the adapter builds (contract JOINT_KINDS); the
    #: 'joint' effect is declared apart, in ``effects``
    joint_kinds: frozenset[str] = frozenset()

    def as_dict(self) -> dict[str, Any]:
        return {
            "engine": self.engine,
            "version": self.version,
            "available": self.available,
            "dimensions": self.dimensions,
            "shapes": sorted(self.shapes),
            "static_shapes": sorted(self.static_shapes),
            "effects": sorted(self.effects),
            "joint_kinds": sorted(self.joint_kinds),
            "settings": {k: {"default": s.default, "allowed": s.describe(), "doc": s.doc} for k, s in self.settings.items()},
            "notes": list(self.notes),
        }


DT_SETTING = Setting("dt", None, float, "fixed time step (s); default: the scene's dt", lo=1e-7, hi=1.0)


class Unsupported(Exception):
    """Raised by build() when the scene needs something the engine cannot
    model; the run is recorded as ``unsupported`` with this message."""


class NotOneBatch(Exception):
    """Raised by build_batch() when the starts do not make one model for
    the engine (its model depends on the start: MuJoCo's explicit contact
    pairs come from the impacts predicted from it); the harness then runs
    the worlds one at a time and says why."""


class Adapter(abc.ABC):
    """Base class; see the module docstring for the contract."""

    name: str = ""
    #: the engine's name in messages when its gyroscopic term w x I w is
    #: always on (no switch): then :meth:`unsupported_reason` also refuses a
    #: scene without the ``gyroscopic`` effect unless the term is provably
    #: zero (:func:`gyroscopic_reason`); None for an engine that can leave
    #: the term out
    gyroscopic_always_on: str | None = None

    def __init__(self) -> None:
        self.notes: list[str] = []
        self.info: dict[str, Any] = {}
        self.stage_counts: dict[str, int] = {}

    # ---- declaration -------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def capabilities(cls) -> Capabilities: ...

    @classmethod
    def resolve_settings(cls, scene: Scene, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        """Defaults (dt from the scene) updated by ``overrides``, each
        validated.  Unknown names are errors listing the known ones."""
        caps = cls.capabilities()
        out: dict[str, Any] = {}
        for name, s in caps.settings.items():
            out[name] = scene.dt if (name == "dt" and s.default is None) else s.default
        for key, value in (overrides or {}).items():
            if key not in caps.settings:
                raise ValueError(f"setting {key}: unknown for engine {cls.name}; known: {', '.join(caps.settings)}")
            out[key] = caps.settings[key].coerce(value)
        return out

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        """Why this engine cannot model ``scene`` (None if it can).  The
        default checks dimensions, shapes and effects against capabilities,
        and the always-on gyroscopic term (:attr:`gyroscopic_always_on`)."""
        caps = cls.capabilities()
        if not caps.available:
            return f"{caps.engine} is not available: {caps.unavailable_reason}"
        if caps.dimensions == 2 and not scene.planar:
            return f"{caps.engine} is a 2D engine and the scene is not planar (planar = false)"
        missing = sorted({b.shape for b in scene.bodies} - caps.shapes)
        if missing:
            return f"{caps.engine} has no body shape {', '.join(missing)}"
        missing = sorted({s.kind for s in scene.statics} - caps.static_shapes)
        if missing:
            return f"{caps.engine} has no static shape {', '.join(missing)}"
        why = joint_reason(scene, caps)
        if why:
            return why
        missing = sorted(scene.effects - caps.effects)
        if missing:
            return f"{caps.engine} cannot model effect {', '.join(missing)}"
        if cls.gyroscopic_always_on is not None:
            return gyroscopic_reason(scene, cls.gyroscopic_always_on)
        return None

    @classmethod
    def pending_compile(cls, scene: Scene, settings: dict[str, Any]) -> dict[str, float]:
        """The groups of compiled code a build of ``scene`` with the
        resolved ``settings`` would compile before stepping, by the
        engine's own on-disk cache, as {group name: about how many CPU
        seconds} (empty: none, or the engine compiles nothing of its own).
        Read by the harness's scheduler (harness/execute.py ``ColdSplit``):
        two builds that would compile the same group are kept apart.  Never
        raises."""
        return {}

    # ---- life cycle --------------------------------------------------------
    @abc.abstractmethod
    def build(self, scene: Scene, settings: dict[str, Any]) -> None: ...

    @abc.abstractmethod
    def step(self, n: int = 1) -> None: ...

    @abc.abstractmethod
    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Write the current state into the given (n, 3), (n, 4) wxyz, (n, 3),
        (n, 3) arrays (world frame, about the centre of mass).  Must not
        allocate per call beyond what the engine's API forces."""

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Advance ``n`` steps, writing the state after step i+1 into row i of
        the (n, n_bodies, 3|4) output blocks.  The default is the plain loop
        of step(1) and read_state(); adapters override it where the engine can
        step and record a block in compiled code (MuJoCo's rollout) or where
        converting a block at once is cheaper than converting every step.
        ``self.block_done`` counts the rows written, so that a failure in the
        middle of a block loses no recorded frame."""
        self.block_done = 0
        for i in range(n):
            self.step(1)
            self.read_state(pos[i], quat[i], vel[i], angvel[i])
            self.block_done = i + 1

    # ---- batched worlds (optional) ------------------------------------------
    #: True when the adapter steps many copies of one scene, differing only
    #: in their start (positions, orientations, velocities), in one call
    #: (:meth:`build_batch`, :meth:`step_record_batch`); the harness hands
    #: it such batches (harness/batch.py) and runs one world at a time
    #: through :meth:`build` otherwise.
    batched: bool = False

    def build_batch(self, scenes: "list[Scene]", settings: dict[str, Any]) -> None:
        """Build W = len(scenes) worlds of one scene: the scenes differ only
        in their bodies' start (harness/batch.py checks it); any compile
        time goes into ``stages()['jit_s']``."""
        raise NotImplementedError(f"{self.name} runs no batches")

    def read_state_batch(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """:meth:`read_state` of every world into (W, n, 3|4) arrays."""
        raise NotImplementedError(f"{self.name} runs no batches")

    def step_record_batch(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray,
                          angvel: np.ndarray) -> None:
        """:meth:`step_record` of every world at once: ``n`` steps, the state
        after step i+1 of world w into [w, i] of the (W, n, n_bodies, 3|4)
        blocks."""
        raise NotImplementedError(f"{self.name} runs no batches")

    def bare_loop(self, n: int) -> None:
        """Advance ``n`` steps by the engine's public step call in a plain
        Python loop, recording nothing: the baseline of the overhead
        benchmark (``physbench bench overhead``).  The default is step(n);
        adapters whose step() is faster than that loop (a compiled multi-step
        call, a direct C entry point) override it."""
        self.step(n)

    def bare_record(self, n: int, n_bodies: int) -> None:
        """Advance ``n`` steps by the engine's public step call in a plain
        Python loop, reading after every step every body's position,
        orientation, linear and angular velocity by the engine's cheapest
        public read and keeping it, in the engine's own form (rows of a
        preallocated block, or a list of what the engine returns), converted
        to nothing: what any caller recording a trajectory pays at least, the
        baseline of ``physbench bench overhead``'s ``ratio``.  The default
        is step(1) and read_state() (which also converts) into rows of
        (n, ``n_bodies``, 3|4) blocks; adapters with a cheaper raw read
        override it."""
        pos, vel, angvel = (np.empty((n, n_bodies, 3)) for _ in range(3))
        quat = np.empty((n, n_bodies, 4))
        for i in range(n):
            self.step(1)
            self.read_state(pos[i], quat[i], vel[i], angvel[i])

    def close(self) -> None:  # noqa: B027 - optional
        pass

    def contacts(self) -> np.ndarray | None:
        """The engine's own contact points after the last step, as its API
        reports them: (k, 7) float array of rows [point x, y, z (m, world),
        unit normal x, y, z (world, oriented as the engine orients it),
        depth (m, > 0 = overlap)], or None when the adapter cannot read them.
        Called only when a run is traced (runner ``contact_cap``), never in a
        plain run."""
        return None

    #: why :meth:`contact_forces` gives None (the contact-law metrics are
    #: then undefined with this reason, never 0)
    contact_forces_reason: str = "the adapter reads no contact forces from its engine"
    #: why the rows of :meth:`contact_forces` carry NaN ``lam_t`` (the
    #: engine's friction cannot be read; "" when it can): the friction laws
    #: are then undefined with this reason, Signorini's still measured
    friction_forces_reason: str = ""

    def contact_forces(self) -> dict[str, np.ndarray] | None:
        """The engine's contact forces over the last step, one row per
        contact (or per contact patch, where the engine's friction acts on
        a patch): ``a`` (R,) int body index; ``b`` (R,) int body index, -1
        for a static; ``static`` (R,) int static index (scene.statics) or
        -1; ``point`` (R, 3) m world; ``normal`` (R, 3) unit, from a toward
        b; ``gap`` (R,) m signed (< 0 overlap) as the engine measured it;
        ``lam_n`` (R,) N the normal force on b along ``normal``; ``lam_t``
        (R, 3) N the friction force on b (world).  None when the adapter
        cannot read them (:attr:`contact_forces_reason`).  Called after
        every step only when a check or the scene asks for a contact-law
        metric (contract.metric_defs.wants_contact_forces), never in a
        plain run.  The shipped adapters' readers are in
        adapters/contact_forces.py, keyed by the adapter's name."""
        from physbench.adapters.contact_forces import READERS

        reader = READERS.get(self.name)
        return None if reader is None else reader(self)

    def stages(self) -> dict[str, Any]:
        """Per-stage counters/profile (reference engine) or the engine features
        switched on (other engines)."""
        return dict(self.stage_counts)


# ---- shared rules -------------------------------------------------------------

#: the reason of an adapter that builds no joints (tests/test_joints_spec.py)
NO_JOINTS_REASON = "joints: not yet modelled by this adapter"


def joint_reason(scene: Scene, caps: Capabilities) -> str | None:
    """Why ``caps`` cannot build the scene's joints, or None: no 'joint'
    effect (:data:`NO_JOINTS_REASON`), or a kind the adapter lacks.  Joints
    are never silently dropped."""
    joints = getattr(scene, "joints", ())
    if not joints and "joint" not in scene.effects:
        return None
    if "joint" not in caps.effects:
        return NO_JOINTS_REASON
    kinds = sorted({j.kind for j in joints} - caps.joint_kinds)
    if kinds:
        return f"joints: {caps.engine} has no {', '.join(kinds)} joint in this adapter"
    return None


def _unequal_inertia(inertia: np.ndarray) -> bool:
    i = np.asarray(inertia, float)
    return float(i.max() - i.min()) > 1e-9 * float(i.max())


def _about_principal_axis(w_body: np.ndarray, inertia: np.ndarray) -> bool:
    """Is the body-frame angular velocity an eigenvector of diag(inertia)
    (zero, or its non-zero components share one principal moment)?  Then
    w x I w = 0."""
    w = np.abs(np.asarray(w_body, float))
    if w.max() == 0.0:
        return True
    moments = np.asarray(inertia, float)[w > 1e-12 * w.max()]
    return float(moments.max() - moments.min()) <= 1e-9 * float(moments.max())


def planar_gyroscopic_reason(engine: str) -> str:
    """Why a 2D engine (pymunk, Box2D) cannot exercise the gyroscopic effect."""
    return (f"{engine} is 2D: bodies turn about one fixed axis (world y), which planar scenes make a "
            "principal axis, so the gyroscopic term w x I w is identically zero and the effect "
            "cannot be exercised")


def gyroscopic_reason(scene: Scene, engine: str) -> str | None:
    """Why an engine whose gyroscopic term w x I w is always on cannot run a
    scene that omits the ``gyroscopic`` effect, or None when the term is
    provably zero for the whole run.

    It vanishes while every body with unequal principal moments turns about a
    principal axis.  That holds for all time when (a) the scene is planar:
    every body turns about world y, a principal axis of each body (planar
    orientations are rotations about y), and every force lies in the x-z
    plane; or (b) the body starts at rest or spinning about a principal axis
    and nothing can exert a torque on it: no contacts, no spring or damper
    attached off its centre (gravity and drag act at the centre of mass).
    """
    from physbench.contract.rotation import world_to_body_angvel

    if "gyroscopic" in scene.effects or scene.planar:
        return None
    contact = "contact" in scene.effects
    pulled_off_centre = set()
    for sp in scene.springs:
        if sp.stiffness == 0.0 and sp.damping == 0.0:
            continue
        for i, anchor in ((sp.a, sp.anchor_a), (sp.b, sp.anchor_b)):
            if i >= 0 and np.any(np.asarray(anchor) != 0.0):
                pulled_off_centre.add(i)
    for b in scene.bodies:
        if not _unequal_inertia(b.inertia):
            continue
        if contact:
            why = "contacts can turn it about a non-principal axis"
        elif b.index in pulled_off_centre:
            why = "a spring attached off its centre of mass can turn it about a non-principal axis"
        elif not _about_principal_axis(world_to_body_angvel(b.orientation, b.angular_velocity), b.inertia):
            why = "it spins about a non-principal axis"
        else:
            continue
        return (f"{engine} always integrates the gyroscopic term w x I w and has no switch to turn it off; "
                f"body {b.name!r} has unequal principal moments {np.round(b.inertia, 9).tolist()} kg m^2, {why}, "
                f"and the scene does not list 'gyroscopic'")
    return None


# ---- registry ---------------------------------------------------------------

_REGISTRY: dict[str, Callable[[], type[Adapter]]] = {}
#: engine name -> where its adapter comes from: "physbench" (shipped), a
#: plug-in's distribution "name version", or "run time" (register() from code)
_ORIGINS: dict[str, str] = {}


def register(name: str, loader: Callable[[], type[Adapter]], origin: str = "run time") -> None:
    """Register the adapter class ``loader()`` returns under ``name`` (the
    loader runs when the engine is first asked for: a broken adapter costs
    its own runs only, as their ``failed`` rows)."""
    _REGISTRY[name] = loader
    _ORIGINS[name] = origin


def engine_names() -> list[str]:
    return list(_REGISTRY)


def set_origin(name: str, origin: str) -> None:
    """Record where engine ``name``'s adapter comes from."""
    _ORIGINS[name] = origin


def engine_origin(name: str) -> str:
    """Where engine ``name``'s adapter comes from (see :data:`_ORIGINS`)."""
    return _ORIGINS.get(name, "run time")


def get_adapter(name: str) -> type[Adapter]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown engine {name!r}; known: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]()


@functools.lru_cache(maxsize=None)
def optional_import(module: str, *also: str) -> tuple[Any, str]:
    """(the engine's package, "") or (None, why it is unavailable):
    ``module`` (and the submodules ``also``, e.g. ``pymunk.batch``) imported
    once, on first use.  A missing or broken engine only makes its own runs
    unavailable (its capabilities say why), never the others'."""
    try:
        mod = importlib.import_module(module)
        for sub in also:
            importlib.import_module(sub)
    except Exception as e:  # pragma: no cover - depends on the environment
        return None, f"import {module} failed: {type(e).__name__}: {e}"
    return mod, ""


def not_installed(*dists: str) -> str:
    """Why an engine whose distributions are ``dists`` cannot run here, ''
    when all are installed: read from the installed packages' metadata,
    nothing imported (an adapter whose engine is slow to import checks
    this in its capabilities and imports the engine at its first build,
    where a broken install fails that run with the reason)."""
    from importlib.metadata import PackageNotFoundError, version

    lost = []
    for d in dists:
        try:
            version(d)
        except PackageNotFoundError:
            lost.append(d)
    return f"not installed: {', '.join(lost)}" if lost else ""


def module_version(mod_name: str) -> str:
    try:
        from importlib.metadata import version

        return version(mod_name)
    except Exception:  # pragma: no cover - metadata missing
        return "unknown"
