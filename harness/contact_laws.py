"""Contact-law residuals (the ContactBench criteria of Le Lidec et al.,
"Contact models in robotics: a comparative analysis"): how far recorded
contact forces are from what rigid contact with Coulomb friction allows.

Pure functions over arrays of contact rows, one row per contact per step
(every contact of every recorded step, flattened), in consistent units
(forces in N, or impulses over the step in N s: the residuals that are
ratios do not care which):

- ``lam_n`` (R,): normal force on body b along the contact normal (a -> b);
- ``lam_t`` (R, 3) or (R, 2): tangential (friction) force on body b,
  perpendicular to the normal;
- ``gap`` (R,) m: signed distance between the surfaces (> 0 apart,
  < 0 overlapping), from the harness's own geometry where the engine's is
  not trusted;
- ``slip`` (R, 3) or (R, 2) m/s: tangential velocity of b's surface point
  relative to a's, in the frame of ``lam_t``;
- ``mu`` (R,): the pair's friction coefficient (kinetic for sliding rows).

The laws and their residuals, each reported as the maximum and the mean
over its rows (``<name>_max``, ``<name>_mean``) and the row count
(``<name>_rows``):

- Signorini (no force without contact, no penetration, no pull):
  ``signorini_residual`` = |lam_n gap| over all rows (N m), beside
  ``separation_force`` = lam_n over rows apart by more than ``gap_tol``
  (N) and ``adhesion`` = max(0, -lam_n) over all rows (N);
- Coulomb: ``cone_violation`` = max(0, |lam_t| - mu lam_n) / lam_n over
  rows with lam_n > 0 (dimensionless, relative to the normal force);
- maximum dissipation, on sliding rows (|slip| > ``slip_tol``, default 1 cm/s): the
  friction force opposes the slip, ``dissipation_residual`` = the angle
  between lam_t and -slip (rad) over sliding rows with lam_t != 0, and it
  sits on the cone's edge, ``dissipation_shortfall`` = max(0, mu lam_n -
  |lam_t|) / (mu lam_n) over sliding rows with mu lam_n > 0.

A residual with no row to take it over (no contact, no sliding contact)
is ``undefined`` with the reason (harness.references.undefined), never 0:
"nothing was measured" is not "the law holds".  An engine that reports no
contact forces gets :func:`no_forces`: every residual undefined with the
adapter's reason.  tests/test_contact_laws.py plants forces that break each
law by a known amount and finds exactly that amount.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.contract.metric_defs import CONTACT_LAWS
from physbench.harness.references import undefined

#: the residual families (each gives _max and _mean and _rows columns): the
#: contract's list, so a check may name them (contract.metric_defs)
LAWS = CONTACT_LAWS
#: m: rows apart by more than this count as separated (separation_force)
GAP_TOL = 1e-6
#: m/s: rows whose slip speed exceeds this are sliding.  The slip is read
#: from the state after the step, where a sticking patch keeps the solver's
#: residual (measured up to 4.4e-4 m/s in stacking.pyramid and
#: stacking.poured_bin on the reference engine, friction well inside the
#: cone): 1 cm/s, the stacking scenes' "at rest"
SLIP_TOL = 1e-2


def _put(out: dict[str, Any], name: str, values: np.ndarray, why_empty: str) -> None:
    """``name``_max, _mean, _rows of ``values`` (R',) into ``out``; with
    no row, _max and _mean undefined with ``why_empty``."""
    out[f"{name}_rows"] = int(values.size)
    if values.size == 0:
        undefined(out, f"{name}_max", why_empty)
        undefined(out, f"{name}_mean", why_empty)
        return
    out[f"{name}_max"] = float(np.max(values))
    out[f"{name}_mean"] = float(np.mean(values))


def _tangent(x: np.ndarray, rows: int) -> np.ndarray:
    """``x`` as (rows, d) tangent vectors (d = 2 or 3; (0, 3) when empty)."""
    x = np.asarray(x, float)
    if x.size == 0:
        return np.zeros((rows, x.shape[-1] if x.ndim == 2 else 3))
    return x.reshape(rows, -1)


def signorini_residual(lam_n: np.ndarray, gap: np.ndarray, gap_tol: float = GAP_TOL) -> dict[str, Any]:
    """Signorini's residuals of rows (R,) ``lam_n``, ``gap`` (m):
    ``signorini_residual`` |lam_n gap|, ``separation_force`` lam_n where
    gap > ``gap_tol``, ``adhesion`` max(0, -lam_n); each _max/_mean/_rows."""
    lam_n = np.asarray(lam_n, float).ravel()
    gap = np.asarray(gap, float).ravel()
    out: dict[str, Any] = {}
    _put(out, "signorini_residual", np.abs(lam_n * gap), "no contact rows")
    _put(out, "separation_force", lam_n[gap > gap_tol], f"no contact row apart by more than {gap_tol:g} m")
    _put(out, "adhesion", np.maximum(0.0, -lam_n), "no contact rows")
    return out


def cone_violation(lam_n: np.ndarray, lam_t: np.ndarray, mu: np.ndarray) -> dict[str, Any]:
    """Coulomb's residual of rows: ``cone_violation`` max(0, |lam_t| - mu
    lam_n) / lam_n over rows with lam_n > 0; _max/_mean/_rows."""
    lam_n = np.asarray(lam_n, float).ravel()
    t = np.linalg.norm(_tangent(lam_t, lam_n.size), axis=1)
    mu = np.broadcast_to(np.asarray(mu, float), lam_n.shape)
    pressed = lam_n > 0
    v = np.maximum(0.0, t[pressed] - mu[pressed] * lam_n[pressed]) / lam_n[pressed]
    out: dict[str, Any] = {}
    _put(out, "cone_violation", v, "no contact row with a positive normal force")
    return out


def dissipation_residual(lam_n: np.ndarray, lam_t: np.ndarray, slip: np.ndarray, mu: np.ndarray,
                         slip_tol: float = SLIP_TOL) -> dict[str, Any]:
    """Maximum dissipation's residuals of the sliding rows (|slip| >
    ``slip_tol`` m/s): ``dissipation_residual`` the angle (rad) between
    lam_t and -slip (rows with lam_t != 0), ``dissipation_shortfall``
    max(0, mu lam_n - |lam_t|) / (mu lam_n) (rows with mu lam_n > 0)."""
    lam_n = np.asarray(lam_n, float).ravel()
    R = lam_n.size
    ft = _tangent(lam_t, R)
    s = _tangent(slip, R)
    mu = np.broadcast_to(np.asarray(mu, float), lam_n.shape)
    fn = np.linalg.norm(ft, axis=1)
    sn = np.linalg.norm(s, axis=1)
    sliding = sn > slip_tol
    out: dict[str, Any] = {}
    aim = sliding & (fn > 0)
    # angle between ft and -s: atan2(|ft x s|, -ft . s), exact for small angles
    a, b = ft[aim], -s[aim]
    if a.shape[1] == 2:
        cr = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    else:
        cr = np.linalg.norm(np.cross(a, b), axis=1)
    ang = np.arctan2(cr, np.sum(a * b, axis=1))
    _put(out, "dissipation_residual", ang, "no sliding contact row with a friction force")
    cone = mu * lam_n
    edge = sliding & (cone > 0)
    _put(out, "dissipation_shortfall", np.maximum(0.0, cone[edge] - fn[edge]) / cone[edge],
         "no sliding contact row with a positive mu lam_n")
    return out


def contact_law_metrics(lam_n, lam_t, gap, slip, mu, gap_tol: float = GAP_TOL,
                        slip_tol: float = SLIP_TOL) -> dict[str, Any]:
    """All three laws' residuals of the rows (see the module docstring)."""
    out: dict[str, Any] = {}
    for part in (signorini_residual(lam_n, gap, gap_tol), cone_violation(lam_n, lam_t, mu),
                 dissipation_residual(lam_n, lam_t, slip, mu, slip_tol)):
        _merge(out, part)
    return out


def no_forces(reason: str) -> dict[str, Any]:
    """Every residual undefined with ``reason`` (an engine whose adapter
    reads no contact forces): never 0."""
    out: dict[str, Any] = {}
    for name in LAWS:
        undefined(out, f"{name}_max", reason)
        undefined(out, f"{name}_mean", reason)
    return out


def metric_names() -> list[str]:
    """Every column :func:`contact_law_metrics` can give."""
    return [f"{n}_{s}" for n in LAWS for s in ("max", "mean", "rows")]


def _merge(out: dict[str, Any], part: dict[str, Any]) -> None:
    from physbench.harness.references import UNDEFINED

    why = [w for w in (out.pop(UNDEFINED, ""), part.pop(UNDEFINED, "")) if w]
    out.update(part)
    if why:
        out[UNDEFINED] = "; ".join(why)


def slip_velocity(rows: dict[str, np.ndarray], pos: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> np.ndarray:
    """Tangential velocity (R, 3) m/s of body b's material point at each
    row's ``point`` relative to body a's (a static's is 0), from the
    recorded state (pos, vel, angvel (n, 3)) after the step, with the
    normal component removed."""
    p = rows["point"]

    def surface(idx: np.ndarray) -> np.ndarray:
        out = np.zeros((idx.size, 3))
        on = idx >= 0
        i = idx[on]
        out[on] = vel[i] + np.cross(angvel[i], p[on] - pos[i])
        return out

    rel = surface(rows["b"]) - surface(rows["a"])
    nrm = rows["normal"]
    return rel - np.sum(rel * nrm, axis=1, keepdims=True) * nrm


def own_gap(scene: Any, rows: dict[str, np.ndarray], pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """The rows' ``gap`` (R,) m, the harness's own where the adapter gives
    NaN (an engine whose gap is not trusted or not reported): the signed
    distance of the row's pair (body a and body b or static) at the
    recorded pose (pos (n, 3), quat (n, 4) wxyz, after the step), by
    contract.geometry (< 0 overlap; the pair's, not the point's: every
    row of a pair gets its deepest).  NaN where no kernel covers the pair.
    tests/test_contact_laws.py::test_a_nan_gap_is_the_harness_own."""
    gap = np.array(rows["gap"], float)
    todo = np.flatnonzero(np.isnan(gap))
    if todo.size == 0:
        return gap
    from physbench.contract.geometry.dispatch import signed_gap
    from physbench.contract.geometry.placed import placed_body, placed_static_box
    from physbench.contract.geometry.support import plane_gap

    statics = {x.index: x for x in scene.statics}
    for r in todo:
        a, b, s = int(rows["a"][r]), int(rows["b"][r]), int(rows["static"][r])
        A = placed_body(scene.bodies[a], pos[a:a + 1], quat[a:a + 1])
        if b >= 0:
            over = signed_gap(A, placed_body(scene.bodies[b], pos[b:b + 1], quat[b:b + 1]))
        else:
            st = statics[s]
            over = (plane_gap(A, st.normal, st.offset) if st.shape == "plane"
                    else signed_gap(A, placed_static_box(st, 1)))
        gap[r] = -float(over[0])
    return gap


def run_contact_laws(scene: Any, records: list | str, trace, friction_reason: str = "") -> dict[str, Any]:
    """The residuals of a run: ``records`` [(frame, rows)] of the
    adapter's contact_forces() after each recorded step (frame indexes
    ``trace``: harness.runner.Trace), or a str saying why there are none
    (:func:`no_forces`).  mu from the scene's pair materials: the static
    coefficient (at least the kinetic one) for the cone, where a sticking
    patch may go up to it; the kinetic one on sliding rows.  Rows whose
    lam_t is NaN (friction the engine does not expose) take part in
    Signorini's law only; with no other row the friction laws are
    undefined with ``friction_reason`` (the adapter's), never 0
    (tests/test_contact_laws.py::test_unread_friction_leaves_the_friction_laws_undefined)."""
    if isinstance(records, str):
        return no_forces(records)
    parts: dict[str, list] = {k: [] for k in ("lam_n", "lam_t", "gap", "slip", "mu_s", "mu_k")}
    mats: dict[tuple[int, int, int], tuple[float, float]] = {}
    statics = {x.index: x for x in scene.statics}
    for frame, rows in records:
        if len(rows["lam_n"]) == 0 or frame >= trace.pos.shape[0]:
            continue
        parts["lam_n"].append(rows["lam_n"])
        parts["lam_t"].append(rows["lam_t"])
        parts["gap"].append(own_gap(scene, rows, trace.pos[frame], trace.quat[frame]))
        parts["slip"].append(slip_velocity(rows, trace.pos[frame], trace.vel[frame], trace.angvel[frame]))
        ms, mk = [], []
        for a, s, b in zip(rows["a"], rows["static"], rows["b"]):
            key = (int(a), int(s), int(b))
            if key not in mats:
                other = statics[s].material if s >= 0 else scene.bodies[b].material
                pm = scene.pair(scene.bodies[a].material, other)
                mats[key] = (max(pm.static_friction, pm.friction), pm.friction)
            ms.append(mats[key][0])
            mk.append(mats[key][1])
        parts["mu_s"].append(np.array(ms))
        parts["mu_k"].append(np.array(mk))
    if not parts["lam_n"]:
        z = np.zeros(0)
        cat = {"lam_n": z, "lam_t": np.zeros((0, 3)), "gap": z, "slip": np.zeros((0, 3)), "mu_s": z, "mu_k": z}
    else:
        cat = {k: np.concatenate(v) for k, v in parts.items()}
    out: dict[str, Any] = {}
    _merge(out, signorini_residual(cat["lam_n"], cat["gap"]))
    read = np.all(np.isfinite(_tangent(cat["lam_t"], cat["lam_n"].size)), axis=1)
    if cat["lam_n"].size and not read.any():
        why = friction_reason or "the engine's friction forces were not read (NaN lam_t)"
        for name in ("cone_violation", "dissipation_residual", "dissipation_shortfall"):
            _put(out, name, np.zeros(0), why)
        return out
    f = {k: cat[k][read] for k in ("lam_n", "lam_t", "slip", "mu_s", "mu_k")}
    for part in (cone_violation(f["lam_n"], f["lam_t"], f["mu_s"]),
                 dissipation_residual(f["lam_n"], f["lam_t"], f["slip"], f["mu_k"])):
        _merge(out, part)
    return out


def merge_into(metrics: dict[str, Any], part: dict[str, Any]) -> None:
    """Add ``part``'s residuals to a run's ``metrics``, joining the
    undefined-metric reasons."""
    _merge(metrics, dict(part))
