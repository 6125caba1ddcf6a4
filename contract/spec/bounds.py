"""Physical bounds of a spec's values (:data:`BOUNDS`, documented in the
bounds table of docs/SCENARIO_FORMAT.md), the complaint about a value
outside them, pydantic field validators holding fields to them, and the
recording-size check shared by load time and the runner."""

from __future__ import annotations

import math
from typing import Any

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
