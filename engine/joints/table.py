"""The joints as constraint rows (engine/joints/rows.py) and what the
joint step does not model; built once, with the model."""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass

import math

import numpy as np

from physbench.engine.joints import KINDS
from physbench.engine.joints.rows import DOT, POINT, SLIDE

#: explicit Runge-Kutta tableaus (A rows below the diagonal, B) of the
#: integrators the joint step runs
TABLEAUS = {
    "explicit_euler": ([], [1.0]),
    "midpoint": ([[0.5]], [0.0, 1.0]),
    "heun": ([[1.0]], [0.5, 0.5]),
    "rk4": ([[0.5], [0.0, 0.5], [0.0, 0.0, 1.0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6]),
}


#: the rows as the compiled kernels read them (:attr:`JointModel.table`)
Rows = namedtuple("Rows", ("rt", "ra", "rb", "rk", "pa", "pb", "s", "t"))


@dataclass(frozen=True, eq=False)
class JointModel:
    """The joints as rows (r rows; rows.py): ``rt`` (r,) row type, ``ra``
    (r,) body, ``rb`` (r,) other (-1 world), ``rk`` (r,) world axis of a
    POINT row, ``pa``/``pb`` (r, 3) anchors in a's/b's frame (m), ``s``
    (r, 3) a's vector, ``t`` (r, 3) b's vector; ``bw`` the band width of
    K (solve.py); ``joint_of_row`` (r,); ``kinds`` per joint."""

    rt: np.ndarray
    ra: np.ndarray
    rb: np.ndarray
    rk: np.ndarray
    pa: np.ndarray
    pb: np.ndarray
    s: np.ndarray
    t: np.ndarray
    bw: int
    joint_of_row: np.ndarray
    kinds: tuple

    @property
    def table(self) -> Rows:
        return Rows(rt=self.rt, ra=self.ra, rb=self.rb, rk=self.rk, pa=self.pa, pb=self.pb, s=self.s, t=self.t)

    @property
    def rows(self) -> int:
        return int(self.rt.shape[0])


def _norm(v: np.ndarray) -> float:
    """|v| of a 1-D vector, summed left to right: ``np.linalg.norm`` of a
    1-D array calls BLAS, whose rounding depends on the CPU kernel
    (tests/test_engine_blas_free.py)."""
    return math.sqrt(sum((float(x) * float(x) for x in v), 0.0))


def _perpendiculars(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit u to an orthonormal frame."""
    u = u / _norm(u)
    e = np.eye(3)[int(np.argmin(np.abs(u)))]
    p1 = np.cross(u, e)
    p1 /= _norm(p1)
    return p1, np.cross(u, p1)


def _rot(q: np.ndarray) -> np.ndarray:
    from physbench.engine.mathutil import quat_to_matrix

    q = np.asarray(q, float)
    return quat_to_matrix((q / _norm(q)).reshape(1, 4))[0]


def build_joints(inp) -> JointModel | None:
    """The rows of ``inp.joints`` (module doc), or None without joints."""
    joints = tuple(getattr(inp, "joints", ()) or ())
    if not joints:
        return None
    rows: list[tuple] = []
    q0 = np.asarray(inp.q, float).reshape(-1, 4)
    for ji, (kind, b, o, pa, pb, ua, ub) in enumerate(joints):
        if kind not in KINDS:
            raise ValueError(f"joint {ji}: unknown kind {kind!r}; expected one of {KINDS}")
        pa, pb = np.asarray(pa, float), np.asarray(pb, float)
        z = np.zeros(3)
        Ra = _rot(q0[b])
        Rb = np.eye(3) if o < 0 else _rot(q0[o])
        if kind in ("revolute", "spherical", "fixed"):
            rows += [(POINT, b, o, k, pa, pb, z, z, ji) for k in range(3)]
        if kind == "revolute":
            p1, p2 = _perpendiculars(np.asarray(ub, float))
            rows += [(DOT, b, o, 0, z, z, np.asarray(ua, float), p, ji) for p in (p1, p2)]
        if kind == "prismatic":
            p1, p2 = _perpendiculars(np.asarray(ub, float))
            rows += [(SLIDE, b, o, 0, pa, pb, z, p, ji) for p in (p1, p2)]
        if kind in ("fixed", "prismatic"):
            # the world's axes e_i in each side's frame at the start;
            # rows (1, 2), (2, 3), (3, 1) start perpendicular
            for i, j in ((0, 1), (1, 2), (2, 0)):
                rows.append((DOT, b, o, 0, z, z, Ra.T[:, i].copy(), Rb.T[:, j].copy(), ji))
    r = len(rows)
    rt = np.array([x[0] for x in rows], np.int64)
    ra = np.array([x[1] for x in rows], np.int64)
    rb = np.array([x[2] for x in rows], np.int64)
    bw = 0
    for i in range(r):
        for j in range(i):
            if {ra[i], rb[i]} & {ra[j], rb[j]} - {-1}:
                bw = max(bw, i - j)
    return JointModel(rt=rt, ra=ra, rb=rb, rk=np.array([x[3] for x in rows], np.int64),
                      pa=np.array([x[4] for x in rows], float).reshape(r, 3),
                      pb=np.array([x[5] for x in rows], float).reshape(r, 3),
                      s=np.array([x[6] for x in rows], float).reshape(r, 3),
                      t=np.array([x[7] for x in rows], float).reshape(r, 3), bw=bw,
                      joint_of_row=np.array([x[8] for x in rows], np.int64), kinds=tuple(j[0] for j in joints))


def unsupported_reason(model) -> str | None:
    """Why the engine cannot step ``model``'s joints as asked, or None."""
    if model.joints is None:
        return None
    if model.has("contact"):
        return ("joints with contact: the reference engine does not yet couple its joint solve with the contact "
                "solve")
    integ = model.setting("integrator")
    if model.setting("joint_solver") == "sequential_impulse":
        if integ != "semi_implicit_euler":
            return (f"joints: joint_solver = sequential_impulse runs with integrator = semi_implicit_euler (the "
                    f"velocity-level solve of Box2D and Bullet), not {integ}")
    elif integ not in TABLEAUS:
        return f"joints: the joint step has no {integ} integrator (it has {', '.join(TABLEAUS)})"
    if (model.has("gyroscopic") and np.any(~model.isotropic) and model.setting("gyroscopic") != "explicit"):
        return (f"joints: gyroscopic = {model.setting('gyroscopic')} is not in the joint step (it integrates "
                "w x I w explicitly: gyroscopic = explicit)")
    return None


