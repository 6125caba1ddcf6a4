"""Which impact MuJoCo's restitution calibration replays for each contact
pair: the first impact predicted from the scene's initial state
(:func:`predict_impact`), and one calibration per group of pairs sharing
(e, gravity) (:func:`calibrate_pairs`, with
:func:`adapters.mujoco_calibration.calibrate`).  Pure scene kinematics
plus the calibration calls; the MJCF is written by :mod:`adapters.mjcf`.
Pinned by tests/test_adapter_mujoco.py (bounce heights and ratios against
e, the calibration notes and info).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters.mujoco_calibration import calibrate
from physbench.contract.rotation import quat_to_matrix
from physbench.contract.scene import Body, Scene, Static

#: an impact slower than this (m/s) is a resting contact: calibrate at the fallback speed
MIN_IMPACT_SPEED = 0.05


def _support(b: Body, n: np.ndarray) -> float:
    """Distance (m) from the body centre to its supporting plane with unit
    normal n (world), at the body's initial orientation."""
    if b.shape == "sphere":
        return b.radius
    nl = quat_to_matrix(b.orientation).T @ n
    if b.shape == "box":
        return float(np.abs(nl) @ np.asarray(b.half_extents, float))
    a = min(abs(float(nl[2])), 1.0)
    if b.shape == "capsule":
        return b.radius + b.half_length * a
    return b.half_length * a + b.radius * math.sqrt(max(0.0, 1.0 - a * a))


def _static_plane(s: Static, x: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit normal, offset) of the static's surface facing point x."""
    if s.shape == "plane":
        return np.asarray(s.normal, float), float(s.offset)
    # box: the face whose slab the point is farthest outside of
    R = quat_to_matrix(s.orientation)
    c = np.asarray(s.position, float)
    p = R.T @ (x - c)
    he = np.asarray(s.half_extents, float)
    k = int(np.argmax(np.abs(p) - he))
    sgn = 1.0 if p[k] >= 0 else -1.0
    n = sgn * R[:, k]
    return n, float(n @ c + he[k])


def predict_impact(scene: Scene, kind_b: str, ia: int, ib: int) -> dict[str, Any]:
    """Predict the first impact of a contact pair from the initial state.

    Returns ``speed`` (m/s, normal impact speed; 0 if none is predicted),
    ``gravity`` (m/s^2 pressing the pair together), and ``gap``/``v0`` for a
    1-D replay of the approach (None if the approach is not a straight
    normal one).  Body-static: motion along the surface normal under the
    normal gravity component.  Body-body: relative straight-line motion of
    the bounding supports (no gravity: it moves both alike); a body pair that
    is not approaching gets the full gravity magnitude (one may come to rest
    on the other; one group for all such pairs keeps calibrations few).
    """
    b = scene.bodies[ia]
    g = scene.gravity
    x = np.asarray(b.position, float)
    v = np.asarray(b.velocity, float)
    if kind_b == "static":
        n, off = _static_plane(scene.statics[ib], x)
        gap = float(n @ x - off - _support(b, n))
        v0 = float(-(v @ n))
        gn = float(-(g @ n))
        if gap < 0.0 or (v0 <= 0.0 and gn <= 0.0):
            return {"speed": 0.0, "gravity": max(gn, 0.0), "gap": None, "v0": None}
        speed = math.sqrt(max(v0 * v0 + 2.0 * gn * gap, 0.0))
        return {"speed": speed, "gravity": max(gn, 0.0), "gap": gap, "v0": v0}
    c = scene.bodies[ib]
    dvec = np.asarray(c.position, float) - x
    dist = float(np.linalg.norm(dvec))
    nhat = dvec / dist if dist > 0 else np.array([0.0, 0.0, 1.0])
    radii = _support(b, nhat) + _support(c, nhat)
    vrel = v - np.asarray(c.velocity, float)  # b's velocity relative to c
    gmag = float(np.linalg.norm(g))
    vv = float(vrel @ vrel)
    dv = float(dvec @ vrel)
    if dist <= radii or dv <= 0.0 or vv == 0.0:
        gap = max(dist - radii, 0.0)
        gn = abs(float(g @ nhat))  # falling onto the other, if that one is supported
        return {"speed": math.sqrt(2.0 * gn * gap), "gravity": gmag, "gap": None, "v0": None}
    disc = dv * dv - vv * (dist * dist - radii * radii)
    if disc < 0.0:  # they miss
        return {"speed": 0.0, "gravity": gmag, "gap": None, "v0": None}
    t = (dv - math.sqrt(disc)) / vv
    d_imp = dvec - vrel * t
    n_imp = d_imp / float(np.linalg.norm(d_imp))
    vn = float(vrel @ n_imp)
    # replay in 1-D: approach at the normal speed, arriving after the same time
    return {"speed": vn, "gravity": 0.0, "gap": vn * t, "v0": vn}


def calibrate_pairs(scene: Scene, settings: dict[str, Any], notes: list[str],
                    info: dict[str, Any]) -> dict[int, tuple[float, float]]:
    """solref (direct form: -stiffness 1/s^2, -damping 1/s) per contact pair
    (index into ``scene.contact_pairs()``), one calibration per group of
    pairs with the same (e, normal gravity), at the group's fastest
    predicted impact; appends the calibration's note to ``notes`` and its
    rows to ``info["restitution_calibration"]``."""
    dt = float(settings["dt"])
    integrator = settings["integrator"]
    pairs = scene.contact_pairs()
    # ---- restitution calibration, one per (e, gravity) group ---------------
    groups: dict[tuple[float, float], list[tuple[int, dict[str, Any], str]]] = {}
    for k, (ka, ia, kb, ib, mat) in enumerate(pairs):
        pred = predict_impact(scene, kb, ia, ib)
        label = f"{scene.bodies[ia].name}|{scene.statics[ib].name if kb == 'static' else scene.bodies[ib].name}"
        key = (float(mat.restitution), round(pred["gravity"], 6))
        groups.setdefault(key, []).append((k, pred, label))
    pair_solref: dict[int, tuple[float, float]] = {}
    calib_info = []
    for (e, gn), members in groups.items():
        _, lead, label = max(members, key=lambda m: m[1]["speed"])
        common = dict(integrator=integrator, contact_steps=float(settings["contact_steps"]),
                      speculative=bool(settings["speculative"]))
        replay = settings.get("restitution_phase", "first_impact") == "first_impact"
        if lead["speed"] >= MIN_IMPACT_SPEED and lead["gap"] is not None and replay:
            cal = calibrate(e, dt, lead["v0"], gn, gap=lead["gap"], **common)
            against = (f"first impact of {label} replayed from the initial state "
                       f"(gap {lead['gap']:.6g} m, normal speed {lead['v0']:.6g} m/s, "
                       f"gravity {gn:.6g} m/s^2): impact speed {cal.speed:.6g} m/s")
        elif lead["speed"] >= MIN_IMPACT_SPEED:
            cal = calibrate(e, dt, lead["speed"], gn, **common)
            against = (f"predicted impact speed {cal.speed:.6g} m/s of {label}, gravity {gn:.6g} m/s^2, "
                       f"averaged over 8 impact phases")
        else:
            cal = calibrate(e, dt, 0.0, gn, **common)
            against = (f"no impact predicted from the initial state (resting contacts); "
                       f"calibrated at {cal.speed:.6g} m/s, gravity {gn:.6g} m/s^2, averaged over 8 phases")
        for k, _, _ in members:
            pair_solref[k] = cal.solref
        row = cal.as_dict()
        row.update(pairs=len(members), calibrated_against=against,
                   restitution_effect=scene.has("restitution"))
        calib_info.append(row)
    if calib_info:
        info["restitution_calibration"] = calib_info
        worst = max(calib_info, key=lambda r: abs(r["residual"]))
        what = "restitution" if scene.has("restitution") else "inelastic contact (no 'restitution' effect, e = 0)"
        notes.append(
            f"MuJoCo has no restitution coefficient: {what} realised by calibrating each pair's "
            f"solref (direct form -stiffness, -damping) with a sphere-on-plane MuJoCo simulation at "
            f"this dt and integrator; worst residual {worst['residual']:+.4f} (e requested "
            f"{worst['requested']:g}, achieved {worst['achieved']:.4f}; {worst['calibrated_against']}); "
            f"impacts at other step phases bounce {worst['phase_spread'][0]:.3f}..{worst['phase_spread'][1]:.3f} "
            f"(mean {worst['phase_mean']:.3f}) with this solref")
    return pair_solref
