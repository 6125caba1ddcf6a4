"""What of a scene Box2D v3 can hold, and as what: the Box2D adapter's
settings and capabilities, each body or static as a Box2D shape (its x-z
cross-section, as for pymunk), and the per-shape material values that
Box2D's mixing rules turn into the scene's pair values.  Layout and reasons
in the module docstring of :mod:`adapters.box2d`; pinned by
tests/test_adapter_box2d.py.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters.base import DT_SETTING, Capabilities, Setting
from physbench.adapters.box2d_joints import JOINT_KINDS
from physbench.adapters.planar import plane_line, planar_shape, static_box_pose
from physbench.contract.scene import Scene

#: a static plane is a box this long along the line and this deep on its
#: solid side (m); Box2D computes in f32, so vertices far from the contact
#: round its depth: 200 m keeps that rounding below 1.5e-5 m
PLANE_HALF_LENGTH = 200.0
PLANE_DEPTH = 10.0

SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
STATIC_SHAPES = frozenset({"plane", "slope", "box"})
EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction", "spring", "damper",
                     "drag_linear", "drag_quadratic"})


def settings() -> dict[str, Setting]:
    return {
        "dt": DT_SETTING,
        "substeps": Setting(
            "substeps", 4, int,
            "sub_step_count of b2World_Step: soft-step substeps per step (Box2D default 4)", lo=1, hi=1000),
        "contact_hertz": Setting(
            "contact_hertz", 30.0, float,
            "contactHertz: stiffness of the soft contact constraint (Hz); Box2D caps it at a quarter "
            "of the substep rate (Box2D default 30)", lo=0.1, hi=1e6),
        "contact_damping_ratio": Setting(
            "contact_damping_ratio", 10.0, float,
            "contactDampingRatio of the soft contact (Box2D default 10)", lo=0.0, hi=1e4),
        "contact_push_speed": Setting(
            "contact_push_speed", 3.0, float,
            "contactPushMaxVelocity (m/s): the largest speed at which overlap is pushed out "
            "(Box2D default 3)", lo=0.0, hi=1e5),
        "restitution_threshold": Setting(
            "restitution_threshold", 0.0, float,
            "restitutionThreshold (m/s): approaches slower than this do not bounce.  Box2D's default "
            "is 1 m/s, which would drop every bounce slower than 1 m/s the spec asks for; 0 applies "
            "e at every speed", lo=0.0, hi=1e4),
        "continuous": Setting(
            "continuous", True, bool,
            "enableContinuous: time-of-impact sweeps of dynamic bodies against static ones "
            "(Box2D default on)"),
        "bullets": Setting(
            "bullets", False, bool,
            "isBullet on every body: time-of-impact sweeps against dynamic bodies too "
            "(Box2D default off)"),
        "springs": Setting(
            "springs", "joint", str,
            "'joint': a spring anchored at centres of mass is a Box2D distance joint with a spring (implicit "
            "soft constraint); 'force': every spring and damper is an explicit force held over the step",
            choices=("joint", "force")),
        "max_linear_speed": Setting(
            "max_linear_speed", 400.0, float,
            "maximumLinearSpeed (m/s): Box2D clamps every body's speed to it (Box2D default "
            "4 m x 100 /s = 400 m/s)", lo=1e-3, hi=1e9),
    }


def declaration(engine: str, version: str, available: bool, why: str) -> Capabilities:
    return Capabilities(
        engine=engine, version=version, dimensions=2, shapes=SHAPES, static_shapes=STATIC_SHAPES,
        effects=EFFECTS | {"joint"}, joint_kinds=JOINT_KINDS, settings=settings(), available=available, unavailable_reason=why,
        notes=(
            "2D engine: planar scenes (x-z plane) only; single precision (f32)",
            "soft step: contacts are springs of contact_hertz solved over `substeps` substeps",
            "friction mixes as sqrt(f_a f_b), restitution as max(e_a, e_b), rolling resistance as "
            "max(c_a, c_b) x the larger shape radius",
            "one Coulomb coefficient: static friction = kinetic friction",
            "springs, dampers and drag are explicit forces from the state at the start of each step",
        ),
    )


def rot(b2: Any, angle: float) -> Any:
    """An exact Box2D rotation (b2MakeRot approximates cos and sin: 4.4e-4 off at 0.3 rad)."""
    r = b2.Rot()
    r.c, r.s = math.cos(angle), math.sin(angle)
    return r


def body_shape(b2: Any, b: Any) -> tuple[Any, float]:
    """(Box2D geometry of the body's planar stand-in
    (:func:`adapters.planar.planar_shape`) in its local frame, the shape's
    radius as Box2D's rolling resistance takes it: 0 for a box)."""
    p = planar_shape(b)
    if p.kind == "circle":
        return b2.circle(radius=p.radius), p.radius
    if p.kind == "box":
        return b2.box(p.half[0], p.half[1]), 0.0
    return b2.capsule((0.0, -p.half[1]), (0.0, p.half[1]), p.radius), p.radius  # capsule


def static_pose(s: Any) -> tuple[tuple[float, float], float, tuple[float, float], tuple[float, float]]:
    """((x, y) origin, angle, (hx, hy) half sizes, (cx, cy) local centre)
    of a static's Box2D box: a plane's origin lies on its line, with the box
    below it on the solid side."""
    if s.shape == "plane":
        origin, (nx, ny) = plane_line(s)
        angle = math.atan2(ny, nx) - 0.5 * math.pi  # local +y = the normal
        return origin, angle, (PLANE_HALF_LENGTH, PLANE_DEPTH), (0.0, -PLANE_DEPTH)
    centre, angle, half = static_box_pose(s)
    return centre, angle, half, (0.0, 0.0)


def shape_materials(scene: Scene, radii: list[float], notes: list[str], info: dict) -> np.ndarray:
    """(n_bodies + n_statics, 3) per-shape (friction, restitution, rolling
    resistance) under Box2D's default mixing: friction sqrt(f_a f_b),
    restitution max(e_a, e_b), rolling max(c_a, c_b) max(r_a, r_b) with r
    the shapes' radii (statics 0).  Each shape takes the smallest value its
    pairs ask for (restitution, rolling) or the product solution on f^2
    (friction); every pair is then re-mixed and the worst residual noted."""
    from physbench.adapters.materials import solve_product_values

    nb = scene.n_bodies
    n = nb + len(scene.statics)
    r = np.array(list(radii) + [0.0] * len(scene.statics))
    pairs = [(ia, ib if kb == "body" else nb + ib, m) for _, ia, kb, ib, m in scene.contact_pairs()]
    out = np.zeros((n, 3))
    if not pairs:
        return out
    f, _, _ = solve_product_values(n, [(a, b, m.friction ** 2) for a, b, m in pairs])
    out[:, 0] = f
    for col, want in ((1, lambda a, b, m: m.restitution),
                      (2, lambda a, b, m: m.rolling_friction / max(r[a], r[b]) if m.rolling_friction and max(r[a], r[b]) > 0 else 0.0)):
        v = np.full(n, np.inf)
        for a, b, m in pairs:
            x = want(a, b, m)
            v[a], v[b] = min(v[a], x), min(v[b], x)
        out[:, col] = np.where(np.isfinite(v), v, 0.0)
    names = [b.name for b in scene.bodies] + [s.name for s in scene.statics]
    worst: dict[str, tuple[float, str]] = {}
    for a, b, m in pairs:
        got = (math.sqrt(out[a, 0] * out[b, 0]), max(out[a, 1], out[b, 1]),
               max(out[a, 2], out[b, 2]) * max(r[a], r[b]))
        for what, g, w in zip(("friction", "restitution", "rolling_friction"), got,
                              (m.friction, m.restitution, m.rolling_friction)):
            err = abs(g - w) / w if w > 0 else abs(g)
            if err > worst.get(what, (0.0, ""))[0]:
                worst[what] = (err, f"{names[a]}|{names[b]} wants {w:g}, gets {g:g}")
    info["material_residuals"] = {k: v[0] for k, v in worst.items()}
    if scene.has("friction") and any(m.static_friction != m.friction for *_, m in pairs):
        notes.append("friction: Box2D has one Coulomb coefficient; the kinetic value is used for sticking too "
                     "(static_friction differs from friction in this scene)")
    for what, (err, where) in worst.items():
        if err > 1e-6:
            notes.append(f"Box2D cannot realise the spec's {what} pairs through its mixing rule; worst pair {where}")
    return out
