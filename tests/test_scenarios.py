"""The scenario library: every spec loads, is complete, names metrics that
exist, and passes its own checks on the reference engine.

The conformance part runs each (scenario, variant) on the reference engine
with harness.runner.run at default settings and evaluates the spec's checks
with harness.conformance (hard scenarios also at dt = 1/30 s).  A check
xfailed for the reference engine becomes a pytest xfail; an unexpected pass
fails.  Long runs are marked ``slow``.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest

from physbench.harness import conformance as C
from physbench.harness.references import get_model
from physbench.harness.runner import Trace
from physbench.contract.scene import SCENARIO_DIR, load_scene, scenario_ids
from physbench.contract.spec import load_spec

FAMILIES = ("stacking", "tunnelling", "billiards", "friction", "gyroscopic", "forces")
IDS = scenario_ids()


def _cases():
    """(scenario id, variant or None) for every spec and variant."""
    out = []
    for sid in IDS:
        loaded = load_spec(SCENARIO_DIR.joinpath(*sid.split(".")).with_suffix(".toml"))
        out += [(sid, None)] + [(sid, v) for v in loaded.variants]
    return out


CASES = _cases()


def _case_id(case):
    sid, v = case
    return f"{sid}[{v}]" if v else sid


# ---------------------------------------------------------------------------
# the library itself


def test_library_size():
    assert len(IDS) >= 20
    fam = Counter(s.split(".")[0] for s in IDS)
    for f in FAMILIES:
        assert fam[f] >= 4, f"family {f} has {fam[f]} scenarios"


@pytest.mark.parametrize("sid", IDS)
def test_spec_is_complete(sid):
    sc = load_scene(sid)
    assert sc.family == sid.split(".")[0]
    assert set(sc.tags) & {"conformance", "hard"}, "tag it 'conformance' or 'hard'"
    assert sc.reference_model, "every scenario names a reference model"
    assert sc.checks, "every scenario has checks"
    known = set(sc.variant_names) | {C.BASE}
    from physbench.adapters import ENGINES

    for c in sc.checks:
        if c.variants is not None:
            assert set(c.variants) <= known, f"check {c.metric}: unknown variants {set(c.variants) - known}"
        for eng in c.xfail:
            assert eng in ENGINES, f"check {c.metric}: xfail for unknown engine {eng!r}"
        for eng in c.engines or ():
            assert eng in ENGINES
        C.split_metric(c.metric)  # well-formed @-suffix
    # every variant (and the base) is run by some check, except a base that
    # is deliberately left unchecked (critical_angle's marginal case)
    for v in [None, *sc.variant_names]:
        scv = load_scene(sid, v)
        assert any(C.check_applies(c, "reference", v) for c in scv.checks) or v is None


def _static_trace(sc, frames: int = 3) -> Trace:
    x, q, v, w = sc.initial_state()
    t = np.linspace(0.0, sc.duration, frames)
    rep = lambda a: np.repeat(a[None], frames, axis=0)  # noqa: E731
    return Trace(t, rep(x), rep(q), rep(v), rep(w), frames)


@pytest.mark.parametrize("case", CASES, ids=_case_id)
def test_variant_compiles_and_metrics_exist(case):
    """The reference model accepts the scene and every checked metric is one
    the harness produces for it (names are checked on a motionless trace)."""
    from physbench.contract.metric_defs import wants_contact_forces
    from physbench.harness.contact_laws import run_contact_laws
    from physbench.harness.metrics import compute_metrics

    sid, variant = case
    sc = load_scene(sid, variant)
    get_model(sc.reference_model)(sc)
    with np.errstate(all="ignore"):
        names = set(compute_metrics(sc, _static_trace(sc)))
    if wants_contact_forces(sc):  # the runner adds the contact-law residuals from the recorded forces
        names |= set(run_contact_laws(sc, [], _static_trace(sc)))
    for c in sc.checks:
        if c.variants is not None and (variant or C.BASE) not in c.variants:
            continue  # the check does not apply to this variant
        if C.judged_apart(c):
            continue  # an ensemble's or the consensus's measure: a run of its own (tests/test_ensemble.py)
        metric = C.split_metric(c.metric)[0]
        assert metric in names, f"check metric {metric!r} is not produced for {sid}[{variant}]"


# ---------------------------------------------------------------------------
# conformance on the reference engine

# Runs that take long on the reference engine (measured on 2 cores): the
# default pytest run stays a few minutes; `pytest -m slow` covers the rest.
SLOW_BASE = {
    "stacking.long_settle", "stacking.pyramid", "stacking.column_10", "friction.block_sticks",
    "billiards.break_16", "stacking.poured_bin",
}


def _marks(case):
    sid, variant = case
    slow = variant is not None or sid in SLOW_BASE
    return [pytest.mark.slow] if slow else []


def _reference_available() -> str | None:
    try:
        from physbench.adapters import get_adapter

        cls = get_adapter("reference")
        caps = cls.capabilities()
        if not caps.available:
            return caps.unavailable_reason
    except Exception as e:  # the engine is not there (yet)
        return f"{type(e).__name__}: {e}"
    return None


RUN_CASES = [pytest.param(c, marks=_marks(c), id=_case_id(c)) for c in CASES]


@pytest.mark.parametrize("case", RUN_CASES)
def test_reference_engine_conformance(case):
    why = _reference_available()
    if why:
        pytest.skip(f"reference engine unavailable: {why}")
    from physbench.harness.runner import run

    sid, variant = case
    sc = load_scene(sid, variant)
    checks = C.applicable_checks(sc, "reference") + C.hard_checks(sc)
    if not checks:
        pytest.skip("no check applies to this case on the reference engine")
    res = run(sc, "reference")
    extra = {}
    for c in checks:
        _, settings = C.split_metric(c.metric)
        if settings:
            extra[c.metric.partition("@")[2]] = run(sc, "reference", settings)
    outs = C.evaluate(sc, res, extra)
    bad = [o for o in outs if o.outcome in C.BAD]
    if bad:
        pytest.fail("\n".join(f"{o.name}: {o.outcome}: {o.message}" for o in bad), pytrace=False)
    if all(o.outcome == C.UNSUPPORTED for o in outs):
        pytest.skip(outs[0].message)
    xf = [o for o in outs if o.outcome == C.XFAIL]
    if xf:
        pytest.xfail("; ".join(f"{o.metric}: {o.message}" for o in xf))
    assert all(o.outcome in (C.PASS, C.UNSUPPORTED) for o in outs)
    assert not math.isnan(float(res.metrics.get("cpu_s_per_sim_s", 0.0)))


def _coefficients(materials) -> set:
    return {(m.friction, m.static_friction, m.rolling_friction, m.restitution) for m in materials}


@pytest.mark.parametrize("sid", scenario_ids())
def test_contact_materials_are_the_contact_pairs_materials(sid):
    """Scene.contact_materials (O(n + k^2), what the dissipation metric
    reads) holds the same pair coefficients as every contact pair."""
    s = load_scene(sid)
    assert _coefficients(s.contact_materials()) == _coefficients(m for *_, m in s.contact_pairs())
