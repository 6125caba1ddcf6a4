"""Closed-form checks shared by the engines that have the shapes and
effects, one parametrised test each instead of one copy per adapter file:
Newton's law of restitution on the canonical head-on spec, free fall under
each engine's documented integration scheme, a bounce at e after a drop,
and a box sliding to rest at mu g.  Every expected value is computed here
from the scene; each engine's bound is stated beside it with the figure
measured (Rapier and Box2D compute in f32, pymunk in f64).  Checks of one
engine only stay in tests/test_adapter_<engine>.py.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from physbench.adapters import get_adapter
from physbench.contract.scene import load_scene
from physbench.harness.runner import run

G = 9.81
F32 = 2.0 ** -23  # f32 relative resolution (one unit in the last place at 1.0 is 2^-23)

ENGINES = ("rapier", "box2d", "pymunk")


def _engine(engine: str) -> str:
    if not get_adapter(engine).capabilities().available:
        pytest.skip(f"{engine} is not installed")
    return engine


def run_ok(scene, engine, settings=None):
    r = run(scene, engine, settings, compute_metrics=False)
    assert r.status == "ok", r.message
    return r, r.trace.valid()


def scene_from(tmp_path: Path, effects, bodies, statics="", duration=1.0, dt=0.001, material=""):
    """A planar spec (the 2D engines run only planar scenes; Rapier runs it as 3D)."""
    text = (f'[scenario]\nfamily = "test"\ntitle = "t"\nduration = {duration}\ndt = {dt}\nplanar = true\n'
            f'effects = {effects!r}\n'.replace("'", '"')
            + (f"\n[material.default]\n{material}\n" if material else "") + bodies + statics)
    p = tmp_path / "scene.toml"
    p.write_text(text, encoding="utf-8")
    return load_scene(p)


GROUND = '\n[[static]]\nname = "ground"\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\n'


def ball(z=0.1, r=0.1):
    return f'\n[[body]]\nname = "ball"\nshape = "sphere"\nradius = {r}\nmass = 1.0\nposition = [0.0, 0.0, {z}]\n'


# ---------------------------------------------------------------------------
# the canonical spec: Newton's law of restitution

#: per engine: bound on |v - Newton| (m/s), bound on the relative momentum
#: drift, with the figures measured
HEAD_ON_BOUNDS = {
    "rapier": (4 * 2.0 * F32 * 4, 1e-6),  # f32: measured 0 .. 7.2e-7 m/s at 2 m/s; drift <= 6.9e-7 (f32 sums)
    "box2d": (4 * 2.0 * F32 * 4, 1e-6),  # f32: measured 0 .. 6e-8 m/s; drift <= 1.2e-7
    "pymunk": (1e-12, 1e-12),  # one contact's bounce is exact: measured <= 2e-16 m/s; drift 0
}


@pytest.mark.parametrize("variant", [None, "elastic", "plastic"])
@pytest.mark.parametrize("engine", ENGINES)
def test_head_on_newton(head_on_path, engine, variant):
    """Post-impact velocities by Newton's law v1 = ((m1 - e m2) u1 + (1 + e)
    m2 u2) / (m1 + m2) (and symmetric), momentum held at every frame, the
    motion on the table's x axis (the planar engines: y exactly 0)."""
    _engine(engine)
    sc = load_scene(head_on_path, variant)
    r, tr = run_ok(sc, engine)
    m1, m2 = sc.masses
    e = sc.pair(sc.bodies[0].material, sc.bodies[1].material).restitution
    u1, u2 = sc.bodies[0].velocity[0], sc.bodies[1].velocity[0]
    v1 = ((m1 - e * m2) * u1 + (1 + e) * m2 * u2) / (m1 + m2)
    v2 = ((m2 - e * m1) * u2 + (1 + e) * m1 * u1) / (m1 + m2)
    err = np.abs(tr.vel[-1, :, 0] - [v1, v2]).max()
    P = tr.vel[:, :, 0] @ sc.masses
    drift = np.abs(P - P[0]).max() / abs(P[0])
    print(f"{engine} head_on[{variant}] e={e}: velocity error {err:.3g} m/s, momentum drift {drift:.3g}")
    max_err, max_drift = HEAD_ON_BOUNDS[engine]
    assert err <= max_err
    assert drift <= max_drift
    if engine == "rapier":
        assert r.info["material_mode"] == "per_material"  # per-material factors realise the pair exactly
    else:
        assert np.all(tr.vel[:, :, 1] == 0.0) and np.all(tr.pos[:, :, 1] == 0.0)
    if engine == "pymunk":
        assert r.stages["material_mode"] == "per_shape"  # no Python callback needed
        assert np.all(tr.vel[:, :, 2] == 0.0)


# ---------------------------------------------------------------------------
# free fall: each engine's integration scheme

#: per engine: the setting that sets S substeps of h = dt / S, the scheme,
#: the bound (m, m/s) and the start height (m)
FREE_FALL = {
    # TGS-soft / soft step: velocity first, v += -g h, then x += v h
    "rapier": ("iterations", "velocity_first", 4 * F32, 1.0),
    "box2d": ("substeps", "velocity_first", 4 * F32, 1.0),
    # Chipmunk: positions first with the old velocity, x += v h, then v += -g h
    "pymunk": ("substeps", "position_first", 1e-14, 0.0),
}


@pytest.mark.parametrize("substeps", [1, 2, 4])
@pytest.mark.parametrize("engine", ENGINES)
def test_free_fall(tmp_path, engine, substeps):
    """After K = k S engine substeps of h: velocity first, z = z0 - g h^2
    K (K + 1) / 2 = z0 - g dt^2 k (k + 1/S) / 2; positions first, z = z0 -
    g h^2 K (K - 1) / 2; both v = -g K h."""
    _engine(engine)
    key, scheme, tol, z0 = FREE_FALL[engine]
    sc = scene_from(tmp_path, ["gravity"], ball(z=z0), duration=0.1, dt=0.01)
    r, tr = run_ok(sc, engine, {key: substeps})
    h = sc.dt / substeps
    K = np.round(tr.t / h)  # engine substeps done
    z = z0 - G * h * h * K * (K + (1.0 if scheme == "velocity_first" else -1.0)) / 2.0
    np.testing.assert_allclose(tr.pos[:, 0, 2], z, rtol=0, atol=tol)
    np.testing.assert_allclose(tr.vel[:, 0, 2], -G * K * h, rtol=0, atol=tol)
    if engine == "pymunk":
        assert r.stages["space_steps"] == 10 * substeps
        if substeps == 1:
            assert tr.pos[-1, 0, 2] == pytest.approx(-0.044145, abs=1e-15)  # the shared engine notes' figure


# ---------------------------------------------------------------------------
# a bounce at e


@pytest.mark.parametrize("e", [0.5, 0.8])
@pytest.mark.parametrize("engine", ENGINES)
def test_restitution_bounce_velocity(tmp_path, engine, e):
    """A ball falling from rest through h lands at v = sqrt(2 g h) and leaves
    at e v (Rapier's and Box2D's coefficients are native: no calibration).
    Measured: Rapier 0.4986 / 0.7981, Box2D within 0.01 (landing within a
    step of gravity)."""
    _engine(engine)
    h = 0.5
    sc = scene_from(tmp_path, ["gravity", "contact", "restitution"], ball(z=0.1 + h), GROUND,
                    duration=0.45, dt=0.001, material=f"restitution = {e}")
    _, tr = run_ok(sc, engine)
    vz = tr.vel[:, 0, 2]
    up = np.argmax(vz > 0)
    assert up > 0
    ratio = vz[up] / math.sqrt(2 * G * h)
    print(f"{engine} bounce ratio {ratio:.5f} for e = {e}")
    assert abs(ratio - e) <= 0.01


# ---------------------------------------------------------------------------
# sliding to rest at mu g


@pytest.mark.parametrize("engine", ENGINES)
def test_sliding_deceleration_mu_g(tmp_path, engine):
    """A box sliding on a level floor decelerates at mu g (measured 5e-6
    relative on Rapier) until it stops at v0^2 / (2 mu g)."""
    _engine(engine)
    mu, v0 = 0.4, 2.0
    box = ('\n[[body]]\nname = "box"\nshape = "box"\nhalf_extents = [0.1, 0.1, 0.1]\nmass = 1.0\n'
           f'position = [0.0, 0.0, 0.1]\nvelocity = [{v0}, 0.0, 0.0]\n')
    sc = scene_from(tmp_path, ["gravity", "contact", "friction"], box, GROUND, duration=0.8, dt=1 / 240,
                    material=f"friction = {mu}\nstatic_friction = {mu}")
    _, tr = run_ok(sc, engine)
    t, vx = tr.t, tr.vel[:, 0, 0]
    sliding = (t > 0.05) & (vx > 0.3)
    a = np.polyfit(t[sliding], vx[sliding], 1)[0]
    print(f"{engine} sliding deceleration {-a:.5f} vs mu g {mu * G:.5f}")
    assert abs(-a / (mu * G) - 1.0) <= 0.005
    assert abs(tr.pos[-1, 0, 0] - v0 ** 2 / (2 * mu * G)) <= 0.01
