"""Joint violation measured from recorded states: ``joint_drift`` (m) and
``joint_axis_drift`` (rad), the same arithmetic for every engine (never an
engine's own constraint error; definitions in contract/metric_defs.py and
docs/METRICS.md).

Each side of a joint carries the joint's anchor and axis in its own frame
(:class:`contract.scene_model.Joint`); at frame f side s puts them in the
world as ``p_s = x_s + R(q_s) a_s`` and ``u_s = R(q_s) e_s`` (the world side
stays put).  Per kind:

- revolute: |p_b - p_o| (m) and the angle between u_b and u_o (rad);
- spherical: |p_b - p_o| (m);
- prismatic: the part of p_b - p_o off u_o (m) and the relative rotation
  since the start (rad: a slider neither turns nor twists);
- fixed: |p_b - p_o| (m) and the relative rotation since the start (rad).

Tests: tests/test_joint_drift.py (planted violations of known size).
"""

from __future__ import annotations

import numpy as np

from physbench.contract.rotation import quat_rotate


def _side(trace, i: int, v: np.ndarray, point: bool) -> np.ndarray:
    """World positions (point) or directions of the body-frame vector v (3,)
    carried by body i over the frames: (F, 3); body -1 (the world) keeps v."""
    F = trace.pos.shape[0]
    if i < 0:
        return np.broadcast_to(v, (F, 3))
    w = quat_rotate(trace.quat[:, i], np.broadcast_to(v, (F, 3)))
    return trace.pos[:, i] + w if point else w


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _relative(trace, i: int) -> np.ndarray:
    """Orientations (F, 4) wxyz of side i (identity for the world)."""
    F = trace.pos.shape[0]
    if i < 0:
        return np.tile([1.0, 0.0, 0.0, 0.0], (F, 1))
    return _unit(np.asarray(trace.quat[:, i], float))


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a b of quaternion rows (F, 4) wxyz."""
    w1, x1, y1, z1 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    w2, x2, y2, z2 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _rotation_since_start(trace, b: int, o: int) -> np.ndarray:
    """Angle (F,) rad of the relative rotation r(t) = q_o(t)^-1 q_b(t)
    against r(0): the angle of c = r(0)^-1 r(t), 2 atan2(|c_xyz|, |c_w|)
    (sign-blind, q and -q being one rotation; exact near 0, where acos of
    the dot product loses half the digits)."""
    r = _qmul(_conj(_relative(trace, o)), _relative(trace, b))
    c = _qmul(np.broadcast_to(_conj(r[0]), r.shape), r)
    return 2.0 * np.arctan2(np.linalg.norm(c[:, 1:], axis=-1), np.abs(c[:, 0]))


def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angle (F,) rad between direction rows u, v (F, 3), by atan2 (exact
    near 0, where acos loses half the digits)."""
    c = np.einsum("ij,ij->i", u, v)
    s = np.linalg.norm(np.cross(u, v), axis=-1)
    return np.arctan2(s, c)


def held_lowest_height(scene, body, up: np.ndarray) -> float | None:
    """The lowest height (m, along the unit ``up``) the centre of ``body``
    can reach while one joint holds it to the world, or None when no joint
    does (then free fall bounds it, harness.metrics.lowest_height).  Revolute:
    the bottom of the circle its centre turns on about the hinge line;
    spherical: the anchor's height less the centre's distance from it;
    fixed: where it starts; prismatic: its start lowered by the slide a
    frictionless axis allows in the scene's duration T (as on an incline).
    Held through other bodies (a chain), the world anchor's height less the
    length of the path of rigid pieces to it (anchor to anchor within each
    body, then to the centre), through revolute, spherical and fixed joints
    (a slider on the path: None).  Test:
    tests/test_joint_drift.py::test_energy_datum_of_a_held_body."""
    direct = _direct(scene, body, up)
    if direct is not None:
        return direct
    # breadth-first from the body to the world over the joints; each step
    # adds the distance from the point where we entered a body to its next anchor
    from collections import deque

    start = (body.index, body.position)
    seen = {body.index}
    queue = deque([(start, 0.0)])
    while queue:
        (i, entry), length = queue.popleft()
        for j in scene.joints:
            if i not in (j.body, j.other) or j.kind == "prismatic":
                continue
            nxt = j.other if j.body == i else j.body
            step = length + float(np.linalg.norm(j.anchor - entry))
            if nxt < 0:
                return min(float(body.position @ up), float(j.anchor @ up) - step)
            if nxt not in seen:
                seen.add(nxt)
                queue.append(((nxt, j.anchor), step))
    return None


def _direct(scene, body, up: np.ndarray) -> float | None:
    """held_lowest_height for a body that a joint holds to the world
    directly, or None."""
    for j in scene.joints:
        if j.body != body.index or j.other >= 0:
            continue
        r = body.position - j.anchor
        h0 = float(body.position @ up)
        if j.kind == "fixed":
            return h0
        if j.kind == "spherical":
            return float(j.anchor @ up) - float(np.linalg.norm(r))
        u = j.axis
        if j.kind == "revolute":
            centre = j.anchor + (r @ u) * u
            radius = float(np.linalg.norm(r - (r @ u) * u))
            across = float(np.linalg.norm(up - (up @ u) * u))
            return min(h0, float(centre @ up) - radius * across)
        s = abs(float(u @ up))  # prismatic
        gn = float(np.linalg.norm(scene.gravity))
        T = scene.duration
        return h0 - s * (abs(float(body.velocity @ u)) * T + 0.5 * gn * s * T * T)
    return None


def joint_world(scene, trace) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]]:
    """Per joint of ``scene`` (in order), where its two sides hold it in the
    world over the trace's frames: (anchor point of ``body`` (F, 3) m,
    anchor point of ``other`` (F, 3) m, axis carried by ``body`` (F, 3),
    axis carried by ``other`` (F, 3)); the axes are unit directions for
    revolute and prismatic joints, None for spherical and fixed ones.  The
    world side (other = -1) stays at the joint's start.  What
    :func:`joint_violations` measures and what a trace draws
    (harness/trace/writer.py, tests/test_trace_joints.py)."""
    out = []
    for j in scene.joints:
        pb = _side(trace, j.body, j.anchor_body, True)
        po = _side(trace, j.other, j.anchor_other, True)
        ub = uo = None
        if j.kind in ("revolute", "prismatic"):
            ub = _side(trace, j.body, j.axis_body, False)
            uo = _side(trace, j.other, j.axis_other, False)
            ub = ub / np.linalg.norm(ub, axis=-1, keepdims=True)
            uo = uo / np.linalg.norm(uo, axis=-1, keepdims=True)
        out.append((pb, po, ub, uo))
    return out


def joint_violations(scene, trace) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per joint of ``scene`` (in order), (positional violation (F,) m,
    angular violation (F,) rad) over the trace's frames."""
    out = []
    for j, (pb, po, ub, uo) in zip(scene.joints, joint_world(scene, trace)):
        d = pb - po
        zero = np.zeros(d.shape[0])
        if j.kind == "prismatic":
            u = uo
            off = d - np.einsum("ij,ij->i", d, u)[:, None] * u
            out.append((np.linalg.norm(off, axis=-1), _rotation_since_start(trace, j.body, j.other)))
            continue
        sep = np.linalg.norm(d, axis=-1)
        if j.kind == "revolute":
            out.append((sep, _angle(ub, uo)))
        elif j.kind == "fixed":
            out.append((sep, _rotation_since_start(trace, j.body, j.other)))
        else:  # spherical: a point constraint only
            out.append((sep, zero))
    return out


def joint_metrics(scene, trace) -> dict[str, float]:
    """``joint_drift`` (m) and ``joint_axis_drift`` (rad): the largest
    violation over frames and joints; {} for a scene without joints.  A
    non-finite state gives NaN (the run is then not stable anyway)."""
    if not scene.joints:
        return {}
    v = joint_violations(scene, trace)
    lin = np.concatenate([a for a, _ in v])
    ang = np.concatenate([b for _, b in v])
    return {"joint_drift": float(np.max(lin)) if np.isfinite(lin).all() else float("nan"),
            "joint_axis_drift": float(np.max(ang)) if np.isfinite(ang).all() else float("nan")}
