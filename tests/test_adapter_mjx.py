"""MJX adapter: MuJoCo's model stepped by MJX in float64.  The physics is
checked against MuJoCo step for step (free flight: every state component
within 1e-12; an impact: Newton's law as well as MuJoCo meets it) and
against closed forms (drag's exact recursion); settings, the blocked scan,
jit_s and the compilation cache's place.  Every test builds few models:
each costs a trace and (without a warm cache) an XLA compile of seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco.mjx")
pytest.importorskip("jax")

from physbench.adapters import get_adapter  # noqa: E402
from physbench.adapters.mjx import BLOCK, MjxAdapter, cache_dir  # noqa: E402
from physbench.contract.scene import compile_scene  # noqa: E402
from physbench.contract.spec import validate_raw  # noqa: E402
from physbench.harness.runner import run  # noqa: E402

G = 9.81


@pytest.fixture(autouse=True)
def _cache_in_tmp(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSBENCH_JAX_CACHE", str(tmp_path / "jax"))


def scene(effects, body, static=(), material=None, duration=0.3, dt=0.002):
    raw = {"scenario": {"family": "mjx", "title": "t", "duration": duration, "dt": dt, "effects": list(effects)},
           "body": list(body), "static": list(static)}
    if material:
        raw["material"] = material
    return compile_scene(validate_raw(raw, "<mjx test>"))


def both(s, **settings):
    """The MJX run and the MuJoCo run of s (same settings)."""
    out = []
    for engine in ("mjx", "mujoco"):
        r = run(s, engine, settings or None, compute_metrics=False)
        assert r.status == "ok", r.message
        out.append((r, r.trace.valid()))
    return out


def test_registered_settings_and_cache_place(tmp_path, monkeypatch):
    assert get_adapter("mjx") is MjxAdapter
    caps = MjxAdapter.capabilities()
    assert caps.available and caps.version.startswith("3.")
    assert "noslip_iterations" not in caps.settings and "speculative" not in caps.settings
    assert caps.settings["ls_iterations"].default == 50
    assert set(caps.settings["integrator"].choices) == {"euler", "implicitfast", "rk4"}
    assert cache_dir() == tmp_path / "jax"
    monkeypatch.delenv("PHYSBENCH_JAX_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "physbench" / "jax"
    import physbench

    assert not str(cache_dir()).startswith(str(__import__("pathlib").Path(physbench.__file__).parent))


def test_free_flight_agrees_with_mujoco_step_for_step():
    # a tumbling box and a spinning capsule under gravity, 300 steps with the
    # Euler integrator: MJX and MuJoCo agree to 1e-12 in every state
    # component (measured 8e-16); the runs are blocked (BLOCK steps per
    # scan) with a partial last block.  implicitfast differs (MJX 3.17 vs
    # MuJoCo 4.0.0, docs/ENGINE_FINDINGS.md: 3.1e-4 rad/s in 50 steps)
    s = scene(["gravity", "gyroscopic"], [
        {"name": "box", "shape": "box", "half_extents": [0.3, 0.2, 0.05], "mass": 1.0, "position": [0, 0, 5],
         "velocity": [1.0, 0.0, 2.0], "angular_velocity": [0.1, 5.0, 0.2]},
        {"name": "cap", "shape": "capsule", "radius": 0.05, "half_length": 0.2, "mass": 0.5, "position": [2, 0, 5],
         "angular_velocity": [3.0, 0.5, 1.0]}], duration=0.6, dt=0.002)
    (rx, tx), (rm, tm) = both(s, integrator="euler")
    assert len(tx.t) == 301 > BLOCK
    for a, b in ((tx.pos, tm.pos), (tx.quat, tm.quat), (tx.vel, tm.vel), (tx.angvel, tm.angvel)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    assert rx.timing["jit_s"] > 0 and "jit_s" not in rm.timing
    assert rx.stages["float64"] and rx.stages["block"] == BLOCK


def test_impact_meets_newtons_law_like_mujoco():
    # the same calibrated solref: the post-impact velocities of two balls
    # (e 0.8) agree with MuJoCo's to 1e-9 m/s and with Newton's law to 2 %
    m1, m2, v1, e = 0.2, 0.1, 2.0, 0.8
    s = scene(["contact", "restitution"], [
        {"name": "a", "shape": "sphere", "radius": 0.03, "mass": m1, "position": [0, 0, 0], "velocity": [v1, 0, 0]},
        {"name": "b", "shape": "sphere", "radius": 0.03, "mass": m2, "position": [0.2, 0, 0]}],
        material={"default": {"restitution": e, "friction": 0.0, "static_friction": 0.0}}, duration=0.2, dt=0.001)
    (rx, tx), (rm, tm) = both(s)
    np.testing.assert_allclose(tx.vel, tm.vel, atol=1e-9)
    want = ((m1 - e * m2) * v1 / (m1 + m2), (1 + e) * m1 * v1 / (m1 + m2))
    np.testing.assert_allclose(tx.vel[-1, :, 0], want, rtol=0.02)
    assert any("pyramidal" in n for n in rx.notes)  # frictionless: MJX 3.17 needs the pyramidal cone


def test_drag_inside_the_scan_is_the_exact_recursion():
    # held drag force, semi-implicit Euler: v_n = vt (1 - (1 - c dt / m)^n)
    c, m, dt = 0.5, 2.0, 0.002
    s = scene(["gravity", "drag_linear"], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": m,
                                            "drag_linear": c}], duration=0.3, dt=dt)
    r = run(s, "mjx", None, compute_metrics=False)
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    n = np.arange(len(tr.t))
    np.testing.assert_allclose(tr.vel[:, 0, 2], -m * G / c * (1 - (1 - c * dt / m) ** n), atol=1e-12)
    assert r.stages["drag"]


def test_bad_and_unsupported():
    s = scene(["gravity"], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0}])
    with pytest.raises(ValueError, match="speculative"):
        MjxAdapter.resolve_settings(s, {"speculative": True})
    with pytest.raises(ValueError, match="integrator"):
        MjxAdapter.resolve_settings(s, {"integrator": "implicit"})
    # the gyroscopic term is always on, as in MuJoCo
    s = scene([], [{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.05], "mass": 1.0,
                    "angular_velocity": [0.1, 5.0, 0.2]}])
    r = run(s, "mjx", None, compute_metrics=False)
    assert r.status == "unsupported" and "gyroscopic" in r.message


def test_too_many_convex_pairs_are_unsupported():
    # MJX collides every body pair every step: stacking.column_10 (10
    # boxes, 45 pairs) runs; the pyramid (15 boxes, 105 pairs) and its
    # levels_7 variant (28 boxes, 378 pairs) are unsupported with the count
    # and the measured cost, never a timeout
    from physbench.adapters.mjx import MAX_CONVEX_PAIRS
    from physbench.contract.scene import load_scene

    assert MjxAdapter.unsupported_reason(load_scene("stacking.column_10")) is None
    for variant, text in ((None, "15 boxes and cylinders make 105 convex pairs"),
                          ("levels_7", "28 boxes and cylinders make 378 convex pairs")):
        why = MjxAdapter.unsupported_reason(load_scene("stacking.pyramid", variant))
        assert why is not None and text in why and f"beyond the {MAX_CONVEX_PAIRS}" in why
    assert 45 <= MAX_CONVEX_PAIRS < 105


@pytest.mark.parametrize("cone", ["elliptic", "pyramidal"])
def test_contact_forces_equal_mujocos(cone):
    """adapters.contact_forces.mjx_rows on a 2 kg box resting on the floor
    (a touching start, 0.3 s): MuJoCo's rows of the same model -- four
    corner points, each m g / 4 along the normal into the floor, the same
    gaps -- read from MJX's raw constraint forces (pyramids decoded).  The
    resting-cubes test of every engine is tests/test_contact_laws.py::
    test_resting_box_forces_on_every_engine."""
    s = scene(["gravity", "contact", "friction", "gyroscopic"],
              [{"name": "b", "shape": "box", "mass": 2.0, "half_extents": [0.1, 0.1, 0.05], "position": [0, 0, 0.05]}],
              [{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}],
              material={"default": {"friction": 0.5}})
    rows = {}
    for engine in ("mjx", "mujoco"):
        cls = get_adapter(engine)
        ad = cls()
        ad.build(s, cls.resolve_settings(s, {"cone": cone}))
        ad.step(150)
        r = ad.contact_forces()
        ad.close()
        order = np.lexsort(np.round(r["point"][:, :2], 6).T)  # the same points in the same order
        rows[engine] = {k: v[order] for k, v in r.items()}
    x, m = rows["mjx"], rows["mujoco"]
    assert len(x["a"]) == 4 and set(x["b"]) == {-1} and set(x["static"]) == {0}
    assert x["lam_n"].sum() == pytest.approx(2.0 * G, rel=1e-7)  # measured 2.6e-9, 9.8e-9
    np.testing.assert_allclose(x["normal"], np.tile([0.0, 0.0, -1.0], (4, 1)), atol=1e-12)
    for k in ("lam_n", "gap", "point"):
        np.testing.assert_allclose(x[k], m[k], rtol=0, atol=TOL_FORCES[k], err_msg=k)
    assert np.abs(x["lam_t"]).max() < 1e-9


#: MJX against MuJoCo on the resting box, measured (elliptic, pyramidal):
#: lam_n 1.6e-8, 4.8e-8 N; gap 1.8e-12, 6.5e-12 m; point 9e-13, 3.2e-12 m
TOL_FORCES = {"lam_n": 1e-6, "gap": 1e-10, "point": 1e-10}
