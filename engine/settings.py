"""The reference engine's settings table, integrator names, joint kinds
and version: what an adapter's capabilities and the environment
fingerprint read, in a module that imports no numba (nor any other engine
module), so that reading them compiles and loads no kernel.
``physbench.engine`` re-exports every name here; importing this module
through it leaves numba unloaded (engine/__init__.py;
tests/test_engine_settings.py::test_settings_and_version_import_no_numba).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

#: the free-flight integrators (engine/integrate.py implements them, its ORDERS keyed by these names:
#: tests/test_engine_settings.py::test_integrator_and_joint_names_match_the_engine's)
INTEGRATORS = ("explicit_euler", "semi_implicit_euler", "midpoint", "heun", "rk4", "velocity_verlet")

#: the joint kinds the engine builds (engine/joints: ``physbench.engine.joints.KINDS``)
JOINT_KINDS = ("revolute", "spherical", "prismatic", "fixed")

#: Engine settings: name -> (default, type, doc, choices or (lo, hi)).  dt
#: defaults to the scene's step (None).
SETTINGS: dict[str, tuple[Any, type, str, Any]] = {
    "substeps": (1, int, "substeps per step (h = dt / substeps)", (1, 10000)),
    "integrator": ("rk4", str, "free-flight integrator for smooth forces", INTEGRATORS),
    "gyroscopic": ("energy_conserving", str,
                   "treatment of the w x I w term (only with the 'gyroscopic' effect)",
                   ("explicit", "implicit", "energy_conserving")),
    "iterations": (20, int, "sequential-impulse iterations per step", (1, 10000)),
    "position_correction": ("split_impulse", str, "how penetration is removed",
                            ("split_impulse", "baumgarte", "none")),
    "warm_starting": (True, bool, "start the solver from the previous step's impulses", None),
    "direct_start": (True, bool, "start the solver from the least-squares solution of the normal rows "
                     "(dense up to 400 rows, sparse above)", None),
    "broadphase": ("sap", str, "sweep-and-prune or all pairs", ("sap", "brute")),
    "ccd": ("events", str, "time-of-impact handling: every impact (events), fast bodies only (toi), none (off)",
            ("off", "toi", "events")),
    "ccd_motion_fraction": (0.25, float, "ccd=toi: a body is fast when it moves more than this fraction of its "
                            "smallest half-size in a step", (0.0, 100.0)),
    "max_rotation_per_step": (1.0, float, "with contacts: a step in which a non-round body would turn by more "
                              "than this (rad; about a cylinder's or capsule's own axis does not count) is split "
                              "into equal parts that do not; 0 = never split", (0.0, 100.0)),
    "friction_stops": (True, bool, "with friction: a step in which a sliding or rolling contact comes to rest "
                       "is cut where it does (from the kinetic slip's linear decay), so the rest of the step "
                       "sees it at rest: turnarounds exact instead of first order in the step", None),
    "ccd_max_events": (32, int, "time-of-impact events per substep before impacts become speculative contacts",
                       (0, 100000)),
    "contact_model": ("impulse", str, "sequential impulses or penalty springs", ("impulse", "penalty")),
    "plastic_impacts": ("simultaneous", str, "at a time of impact, an island of two or more touching pairs with "
                        "no restitution: one simultaneous plastic impact (Moreau) or pair-by-pair propagation",
                        ("simultaneous", "sequential")),
    "restitution_threshold": (0.01, float, "approach speed (m/s) below which contacts do not bounce", (0.0, 100.0)),
    "contact_margin": (1e-4, float, "distance (m) within which resting contacts are kept, beyond the motion "
                       "margin", (0.0, 1.0)),
    "correction_beta": (0.2, float, "fraction of the penetration removed per step", (0.0, 1.0)),
    "correction_slop": (1e-4, float, "penetration (m) left uncorrected", (0.0, 1.0)),
    "joint_solver": ("direct", str, "with joints: the joint forces solved exactly at every integrator stage "
                     "(direct), or velocity-level rows by sequential impulses with Baumgarte drift correction, "
                     "warm-started (sequential_impulse: needs integrator = semi_implicit_euler; `iterations` "
                     "passes)", ("direct", "sequential_impulse")),
    "joint_baumgarte": (0.2, float, "with joint_solver = sequential_impulse: the fraction of a joint's drift "
                        "removed per step", (0.0, 1.0)),
    "joint_projection": ("newton", str, "with joints: after each step the pose is projected back onto the joints "
                         "by Newton's method and the velocities onto their tangent (newton), or not (off: the "
                         "drift of the index-reduced equations grows)", ("newton", "off")),
    "joint_tolerance": (1e-12, float, "with joints: the largest joint residual the projection leaves (m; 1 for "
                        "the axis rows)", (1e-15, 1e-3)),
    "joint_max_turn": (0.02, float, "with joints: a step in which a body would turn by more than this (rad), at "
                       "its rate or the fastest gravity swing of a joint's arm, runs as equal parts that do not; "
                       "0 = never split", (0.0, 100.0)),
    "penalty_stiffness": (0.0, float, "penalty contact stiffness (N/m); 0 = auto from the effective mass",
                          (0.0, 1e12)),
}


@functools.cache
def version() -> str:
    """physbench's version (pyproject.toml, or installed metadata); read
    once a process (importlib.metadata parses the package's metadata file,
    ~1-3 ms, and every build's capabilities ask for it)."""
    try:
        from importlib.metadata import version as _v

        return _v("physbench")
    except Exception:
        pass
    try:
        import tomllib

        with open(Path(__file__).resolve().parent.parent / "pyproject.toml", "rb") as f:
            return tomllib.load(f)["project"]["version"]
    except Exception:  # pragma: no cover
        return "unknown"


def default_settings(inp) -> dict[str, Any]:
    """The default settings for ``inp`` (a :class:`engine.model.SceneInput`):
    SETTINGS' defaults, dt the scene's step."""
    out = {k: v[0] for k, v in SETTINGS.items()}
    out["dt"] = inp.dt
    return out


__all__ = ["INTEGRATORS", "JOINT_KINDS", "SETTINGS", "default_settings", "version"]
