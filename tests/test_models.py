"""Reference models a user can find and use: declarations (docs/MODELS.md,
`physbench models`), refusal at load time, and the three models of the
smooth forces and of sliding to rest against their closed forms."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from physbench.contract.metric_defs import GENERIC_METRICS
from physbench.harness.references import MODELS, describe, get_model, models_markdown
from physbench.harness.runner import run
from physbench.contract.scene import load_scene
from physbench.contract.spec import SpecError
from tests.conftest import ROOT

HEAD_ON_TEXT = (ROOT / "tests" / "data" / "head_on.toml").read_text()


def _load_text(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return load_scene(p)


def _errors(tmp_path, text) -> list[str]:
    with pytest.raises(SpecError) as ei:
        _load_text(tmp_path, text)
    return ei.value.errors


# ---------------------------------------------------------------------------
# declarations and their documents


def test_every_model_declares_params_metrics_and_primary():
    for d in describe():
        assert d["summary"] and d["takes"], d["name"]
        assert d["produces"] and d["primary"] in d["produces"], d["name"]
        for p in d["params"]:
            assert p["type"] in ("str", "int", "float", "list of str") and p["meaning"]


def test_models_md_is_written_from_the_declarations():
    assert (ROOT / "docs" / "MODELS.md").read_text() == models_markdown(), \
        "docs/MODELS.md is stale: write harness.references.models_markdown() to it"


def test_metrics_md_documents_every_harness_metric():
    from physbench.contract.metric_defs import CONSENSUS_METRICS, CONTACT_LAWS, ENSEMBLE_METRICS

    text = (ROOT / "docs" / "METRICS.md").read_text()
    for name in [*GENERIC_METRICS, *ENSEMBLE_METRICS, *CONSENSUS_METRICS, *CONTACT_LAWS]:
        assert f"`{name}`" in text, name


def test_models_cli_lists_the_judges_of_scenes_without_a_model(tmp_path):
    """``physbench models`` ends with what judges a scene without a closed
    form: the contact-law residuals, the ensemble's and the consensus's
    measures (docs/MODELS.md's last section, the same lines)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "models"], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    tail = p.stdout.split("Judging a scene without a model:")[1]
    for name in ("signorini_residual", "cone_violation", "predictable", "final_spread", "consensus_spread"):
        assert f"`{name}`" in tail, name


def test_models_cli_prints_the_declarations(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "models", "--json"], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout) == json.loads(json.dumps(describe()))
    assert {d["name"] for d in json.loads(p.stdout)} == set(MODELS)
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "models", "slide_to_rest"], capture_output=True,
                       text=True, cwd=tmp_path, env=env, timeout=120)
    assert p.returncode == 0 and "stop_distance_error" in p.stdout and "param slope" in p.stdout
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "models", "nosuch"], capture_output=True,
                       text=True, cwd=tmp_path, env=env, timeout=120)
    assert p.returncode == 2 and "unknown model 'nosuch'" in p.stderr and "Traceback" not in p.stderr


def test_registry_imports_no_scene_and_no_model():
    code = ("import sys; import physbench.harness.references as r; "
            "print(sorted(m for m in sys.modules if m.startswith('physbench.harness')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "['physbench.harness', 'physbench.harness.references']"


# ---------------------------------------------------------------------------
# refusal at load time, as spec errors with the key path


def test_unknown_param_is_a_spec_error(tmp_path):
    errs = _errors(tmp_path, HEAD_ON_TEXT.replace('model = "two_body_collision"',
                                                  'model = "two_body_collision"\nparams = { nosuch = 1 }'))
    assert len(errs) == 1 and "s.toml: reference.params.nosuch:" in errs[0] and "allowed: ['bodies']" in errs[0]


def test_param_of_the_wrong_type_is_a_spec_error(tmp_path):
    errs = _errors(tmp_path, HEAD_ON_TEXT.replace('model = "two_body_collision"',
                                                  'model = "two_body_collision"\nparams = { bodies = "cue" }'))
    assert "reference.params.bodies: " in errs[0] and "expected list of str" in errs[0]


FLAT_BLOCK = """
[scenario]
family = "t"
title = "t"
duration = 1.0
dt = 0.001
planar = true
effects = ["gravity", "contact"{friction}]
{material}
[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
mass = 1.0
position = [0.0, 0.0, 0.05]
velocity = [{v}, 0.0, 0.0]

[[static]]
name = "floor"
{floor}

[reference]
model = "{model}"
{checks}
"""


def _flat(model="incline_block", v=1.0, friction=None, floor='shape = "slope"\nangle = 0.0', checks=""):
    mat = "" if friction is None else f"[material.default]\nfriction = {friction}\n"
    return FLAT_BLOCK.format(friction=', "friction"' if friction is not None else "", material=mat, v=v,
                             floor=floor, model=model, checks=checks)


def test_incline_block_on_a_flat_frictionless_slope_is_refused_at_load(tmp_path):
    errs = _errors(tmp_path, _flat())
    assert len(errs) == 1 and "s.toml: static[0]:" in errs[0] and "constant 1 m/s" in errs[0]


def test_incline_block_takes_a_level_plane(tmp_path):
    sc = _load_text(tmp_path, _flat(friction=0.5, floor='shape = "plane"\nnormal = [0.0, 0.0, 1.0]'))
    m = get_model("incline_block")(sc)
    assert m.theta == 0.0 and m.a_slide == pytest.approx(-0.5 * 9.81) and m.t_stop == pytest.approx(1 / 4.905)
    tilted = 'shape = "plane"\nnormal = [0.1, 0.0, 1.0]'
    errs = _errors(tmp_path, _flat(friction=0.5, floor=tilted))
    assert "s.toml: static:" in errs[0] and "slope" in errs[0]


def test_check_and_primary_metrics_must_be_produced(tmp_path):
    errs = _errors(tmp_path, HEAD_ON_TEXT + '\n[[check]]\nmetric = "nosuch_error"\nmax = 1\n')
    assert any("check[3].metric: 'nosuch_error' is not produced" in e for e in errs), errs
    # head_on has e = 0.9: impacts dissipate, so energy_drift is not produced
    errs = _errors(tmp_path, HEAD_ON_TEXT + '\n[[check]]\nmetric = "energy_drift"\nmax = 1\n')
    assert "check[3].metric: 'energy_drift'" in errs[0] and "impacts with e = 0.9 < 1" in errs[0]
    errs = _errors(tmp_path, HEAD_ON_TEXT.replace('primary_metric = "post_impact_velocity_error"',
                                                  'primary_metric = "stack_drift"'))
    assert "scenario.primary_metric: 'stack_drift' is not produced" in errs[0]
    # the elastic variant is conservative: energy_drift is the check there, energy_dissipated is refused
    text = HEAD_ON_TEXT.replace("restitution = 0.9", "restitution = 1.0")
    assert _load_text(tmp_path, text + '\n[[check]]\nmetric = "energy_drift"\nmax = 1\n').checks[-1].metric == \
        "energy_drift"
    errs = _errors(tmp_path, text + '\n[[check]]\nmetric = "energy_dissipated"\nmin = 0\n')
    assert "check[3].metric: 'energy_dissipated'" in errs[0] and "conservative" in errs[0]


def test_cli_run_reports_a_refused_scene_with_exit_2(tmp_path):
    p = tmp_path / "flat.toml"
    p.write_text(_flat())
    r = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "run", str(p)], capture_output=True, text=True,
                       cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=120)
    assert r.returncode == 2 and "static[0]" in r.stderr and "Traceback" not in r.stderr


# ---------------------------------------------------------------------------
# slide_to_rest


def test_slide_to_rest_refuses_what_it_cannot_model(tmp_path):
    # tan 30 = 0.577: steeper than atan(mu_k = 0.4) and atan(mu_s = 0.5)
    with pytest.raises(SpecError, match=r"static\[0\]: .*never stops"):
        _slope_scene(tmp_path, 30.0, 2.0)
    with pytest.raises(SpecError, match=r"static\[0\]: .*slides back down"):
        _slope_scene(tmp_path, 30.0, -2.0)
    errs = _errors(tmp_path, _flat(v=5.0, friction=0.4, model="slide_to_rest",
                                   floor='shape = "plane"\nnormal = [0.0, 0.0, 1.0]'))
    assert "scenario.duration" in errs[0]


def _slope_scene(tmp_path, angle, u0, mu=0.4, duration=1.5):
    a = math.radians(angle)
    pos = [0.05 * math.sin(a), 0.0, 0.05 * math.cos(a)]  # resting on the slope through the origin
    q = [math.cos(a / 2), 0.0, math.sin(a / 2), 0.0]
    v = [u0 * math.cos(a), 0.0, -u0 * math.sin(a)]
    text = f"""
[scenario]
family = "t"
title = "t"
duration = {duration}
dt = 0.001
planar = true
effects = ["gravity", "contact", "friction"]
[material.default]
friction = {mu}
static_friction = 0.5
[[body]]
name = "box"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
mass = 1.0
position = [{pos[0]!r}, 0.0, {pos[2]!r}]
orientation = [{q[0]!r}, 0.0, {q[2]!r}, 0.0]
velocity = [{v[0]!r}, 0.0, {v[2]!r}]
[[static]]
shape = "slope"
angle = {angle}
[reference]
model = "slide_to_rest"
"""
    return _load_text(tmp_path, text, f"slope_{angle}_{u0}.toml")


@pytest.mark.parametrize("angle,u0", [(0.0, 2.0), (10.0, 2.0), (15.0, -2.0)])
def test_slide_to_rest_closed_form_and_reference_engine(tmp_path, angle, u0):
    sc = _slope_scene(tmp_path, angle, u0)
    m = get_model("slide_to_rest")(sc)
    a = math.radians(angle)
    g, mu = 9.81, 0.4
    decel = g * (mu * math.cos(a) - math.copysign(math.sin(a), u0))  # along the motion
    assert m.d_stop == pytest.approx(u0 * u0 / (2 * decel), rel=1e-12)
    assert m.t_stop == pytest.approx(abs(u0) / decel, rel=1e-12)
    if angle == 0.0:
        assert m.d_stop == pytest.approx(u0 * u0 / (2 * mu * g), rel=1e-12)
    r = run(sc, "reference")
    assert r.status == "ok"
    out = r.metrics
    print(angle, u0, {k: out[k] for k in ("stop_distance_error", "stop_time_error", "stop_position_error", "creep")})
    assert out["stop_distance_error"] <= 1e-6
    assert out["stop_time_error"] <= 1e-6


# ---------------------------------------------------------------------------
# damped_oscillator


def test_damped_oscillator_solves_its_ode():
    """The closed form satisfies y'' + 2 gamma y' + w0^2 y = 0 with the start
    (y0, v0), under-, critically and over-damped (checked against an
    independent numerical solution)."""
    sc = load_scene("forces.damped_spring")
    m = get_model("damped_oscillator")(sc)
    t = np.linspace(0.0, 3.0, 301)
    for c in (0.4, 2 * math.sqrt(40.0), 30.0):
        sc_c = load_scene("forces.damped_spring", overrides={"spring[0].damping": c})
        mc = get_model("damped_oscillator")(sc_c)
        gam, w0 = c / 2.0, math.sqrt(40.0)
        sol = solve_ivp(lambda _t, y: [y[1], -2 * gam * y[1] - w0 * w0 * y[0]], (0, 3.0), [mc.y0, mc.v0],
                        t_eval=t, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(mc.y(t), sol.y[0], atol=1e-10)
    assert m.y0 == pytest.approx(0.1) and m.s_eq == pytest.approx(0.5 + 9.81 / 40.0)


@pytest.mark.parametrize("sid", ["forces.damped_spring", "forces.spring_pair"])
def test_damped_oscillator_on_the_reference_engine(sid):
    r = run(load_scene(sid), "reference")
    assert r.status == "ok"
    out = r.metrics
    print(sid, {k: out.get(k) for k in ("oscillator_position_error", "period_error", "decay_rate_error")})
    assert out["oscillator_position_error"] <= 1e-6
    assert out["period_error"] <= 1e-6
    if "decay_rate_error" in out:
        assert out["decay_rate_error"] <= 1e-6


def _lowest_by_ode(y0: float, v0: float, gam: float, w0: float, T: float) -> float:
    """min_t y over [0, T] of y'' + 2 gam y' + w0^2 y = 0 from (y0, v0),
    by an independent numerical solution with an event at y' = 0."""
    sol = solve_ivp(lambda _t, y: [y[1], -2 * gam * y[1] - w0 * w0 * y[0]], (0, T), [y0, v0],
                    events=lambda _t, y: y[1], rtol=1e-12, atol=1e-14, dense_output=True)
    cands = [y0, *sol.y_events[0][:, 0], sol.y[0, -1]]
    return float(min(cands))


@pytest.mark.parametrize("zeta,v0", [(2.0, 5.0), (2.0, 9.0), (1.0, 4.0), (0.3, 2.0), (0.0, 1.0), (3.0, -2.0)])
def test_damped_oscillator_bounds_the_real_motion(zeta, v0):
    """The anchor bound is the motion's real lowest point, damping included.
    forces.damped_spring (k 40 N/m, 1 kg: w0 = 6.3246 rad/s, s_eq =
    0.74525 m below the anchor) started at equilibrium, thrown up toward
    the anchor at v0: the undamped bound |y0| + v0 / w0 = 0.79 m for 5 m/s
    reached the anchor, though with zeta = 2 the body rises only 0.173 m.
    Checked against an independent numerical solution; a throw that does
    reach the anchor is still refused."""
    w0 = math.sqrt(40.0)
    c = 2 * zeta * w0
    z_eq = 2.0 - (0.5 + 9.81 / 40.0)
    over = {"spring[0].damping": c, "body[0].position": [0.0, 0.0, z_eq], "body[0].velocity": [0.0, 0.0, v0]}
    truth = _lowest_by_ode(0.0, -v0, zeta * w0, w0, 20.0)  # y along e = -z: thrown up is y' < 0
    if 0.74525 + truth > 0:
        m = get_model("damped_oscillator")(load_scene("forces.damped_spring", overrides=over))
        assert m.y0 == pytest.approx(0.0, abs=1e-9) and m.v0 == pytest.approx(-v0)
        assert m.lowest() == pytest.approx(truth, abs=1e-9)
    else:
        with pytest.raises(SpecError, match="would reach the spring's anchor"):
            load_scene("forces.damped_spring", overrides=over)


def test_damped_oscillator_overdamped_throw_loads():
    """The scene the old bound refused: zeta = 2, thrown up at 5 m/s from
    equilibrium; by hand y = v0 / (r1 - r2) (e^(r1 t) - e^(r2 t)) with
    r = -gamma +- sqrt(gamma^2 - w0^2) = -1.694659, -23.603562 1/s peaks at
    t = ln(r2 / r1) / (r1 - r2) = 0.120221 s, 0.172787 m above it."""
    w0 = math.sqrt(40.0)
    z_eq = 2.0 - (0.5 + 9.81 / 40.0)
    m = get_model("damped_oscillator")(load_scene("forces.damped_spring", overrides={
        "spring[0].damping": 4 * w0, "body[0].position": [0.0, 0.0, z_eq], "body[0].velocity": [0.0, 0.0, 5.0]}))
    assert m.stationary_times() == pytest.approx([0.120221], abs=1e-6)
    assert m.lowest() == pytest.approx(-0.172787, abs=1e-6)


def test_damped_oscillator_refuses_what_it_cannot_model():
    with pytest.raises(SpecError, match=r"spring\[0\]\.anchor_b"):
        load_scene("forces.damped_spring", overrides={"spring[0].anchor_b": [0.1, 0.0, 0.0]})
    with pytest.raises(SpecError, match=r"body: .*along the spring's line"):
        load_scene("forces.damped_spring", overrides={"body[0].velocity": [1.0, 0.0, 0.0]})
    with pytest.raises(SpecError, match="would reach the spring's anchor"):
        load_scene("forces.damped_spring", overrides={"body[0].position": [0.0, 0.0, 0.2]})


# ---------------------------------------------------------------------------
# drag_fall


@pytest.mark.parametrize("sid,quad", [("forces.drag_linear_fall", False), ("forces.drag_quadratic_fall", True)])
def test_drag_fall_closed_form_and_reference_engine(sid, quad):
    sc = load_scene(sid)
    m = get_model("drag_fall")(sc)
    b = sc.bodies[0]
    c = b.drag_quadratic if quad else b.drag_linear
    g = sc.gravity

    def f(_t, y):
        v = y[3:]
        drag = c * np.linalg.norm(v) * v if quad else c * v
        return [*v, *(g - drag / b.mass)]

    t = np.linspace(0.0, sc.duration, 201)
    sol = solve_ivp(f, (0.0, sc.duration), [*b.position, *b.velocity], t_eval=t, rtol=1e-12, atol=1e-12)
    x, v = m.state(t)
    np.testing.assert_allclose(x, sol.y[:3].T, atol=1e-8)
    np.testing.assert_allclose(v, sol.y[3:].T, atol=1e-8)
    r = run(sc, "reference")
    assert r.status == "ok"
    print(sid, {k: r.metrics[k] for k in ("drag_velocity_error", "final_speed_error", "trajectory_rmse")})
    assert r.metrics["drag_velocity_error"] <= 1e-6
    assert r.metrics["final_speed_error"] <= 1e-6


def test_drag_fall_refuses_an_upward_throw_against_quadratic_drag():
    with pytest.raises(SpecError, match="body: .*upward or sideways"):
        load_scene("forces.drag_quadratic_fall", overrides={"body[0].velocity": [0.0, 0.0, 3.0]})
