"""A breaking-point evaluation computes the reference model's metrics only when
its criterion reads one (harness/limit_eval.py ``skipped_model_metrics``)."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest

from physbench.contract.scene import load_scene
from physbench.harness.limit_eval import LimitRequest, evaluate_point, judge, skipped_model_metrics
from physbench.harness.references import get_model


@pytest.fixture
def spy(monkeypatch):
    """Counts calls of a reference model's ``metrics`` (the real one runs)."""
    calls: list[str] = []

    def install(model_name: str):
        cls = get_model(model_name)
        real = cls.metrics

        def metrics(self, trace):
            calls.append(model_name)
            return real(self, trace)

        monkeypatch.setattr(cls, "metrics", metrics)
        return calls

    return install


def test_generic_criterion_skips_the_model(spy):
    """The nightly's fast_spin search (stability and energy_gain only),
    shortened: the torque-free model is never solved, the row says which of
    its metrics were not computed, and the value holds on generic metrics."""
    calls = spy("torque_free_rigid_body")
    req = LimitRequest("gyroscopic.fast_spin", None, "reference", "body[0].angular_velocity[2]", 10.0, 5000.0,
                       checks=("stable",), bounds=(("energy_gain", 0.01),),
                       overrides=(("scenario.duration", 0.2),))
    row = evaluate_point(req, "x", 150.0, 0.0)
    assert calls == []
    skipped = row["limit_skipped_metrics"].split(",")
    assert set(skipped) == set(get_model("torque_free_rigid_body").produces)
    assert "angular_velocity_error" in skipped and "angular_velocity_error" not in row
    assert not any("angular_velocity_error" in n for n in row["notes"])  # one record: the column
    assert row["status"] == "ok" and row["limit_holds"], row["limit_reason"]
    assert 0.0 <= row["energy_gain"] <= 0.01


def test_all_checks_of_generic_metrics_skip_the_model():
    """With ``checks`` empty every check of fast_spin counts; all read
    harness metrics (energy_drift, angular_momentum_drift), so the model is
    still not needed; a bound on a model metric makes it needed."""
    scene = load_scene("gyroscopic.fast_spin")
    assert "angular_velocity_error" in skipped_model_metrics(scene, "reference")
    assert skipped_model_metrics(scene, "reference", bounds=(("angular_velocity_error", 1.0),)) == ()
    assert skipped_model_metrics(load_scene("gyroscopic.fast_spin"), "reference", ("energy_drift",)) != ()


def test_model_criterion_runs_the_model(spy):
    """A search whose check is a model metric (``tunnelled`` of
    no_tunnelling, as in the nightly's tunnelling block) computes it."""
    calls = spy("no_tunnelling")
    req = LimitRequest("tunnelling.bullet_100", None, "reference", "body[0].velocity[0]", 0.3, 1000.0,
                       checks=("tunnelled",))
    row = evaluate_point(req, "x", 100.0, 0.0)
    assert calls == ["no_tunnelling"]
    assert row["limit_skipped_metrics"] == ""
    assert row["tunnelled"] == 0.0 and row["limit_holds"], row["limit_reason"]


def test_model_bound_runs_the_model(spy):
    calls = spy("torque_free_rigid_body")
    req = LimitRequest("gyroscopic.fast_spin", None, "reference", "body[0].angular_velocity[2]", 10.0, 5000.0,
                       checks=("stable",), bounds=(("angular_velocity_error", 1.0),),
                       overrides=(("scenario.duration", 0.2),))
    row = evaluate_point(req, "x", 150.0, 0.0)
    assert calls == ["torque_free_rigid_body"]
    assert row["limit_skipped_metrics"] == "" and math.isfinite(row["angular_velocity_error"])


def _ok_result(**metrics):
    return SimpleNamespace(status="ok", message="", engine="reference", timing={}, notes=[],
                           scenario="tunnelling.bullet_100", variant=None,
                           metrics={"stable": True, "stability_reason": "", **metrics})


def test_the_criterion_never_reads_a_skipped_metric():
    """An evaluation skips the model's metrics only when its criterion reads
    harness metrics alone, and no model produces a harness metric's name:
    so every check and bound a skipping evaluation judges is of a metric it
    computed (harness/limit_eval.py ``skipped_model_metrics``; ``judge``
    needs no list of skipped metrics)."""
    from physbench.contract.metric_defs import GENERIC_METRICS
    from physbench.contract.models import MODELS
    from physbench.contract.scene import scenario_ids
    from physbench.harness.conformance import split_metric
    from physbench.harness.limit_eval import _criterion_checks

    for name in MODELS:
        assert not set(get_model(name).produces) & set(GENERIC_METRICS), name
    seen = 0
    for sid in scenario_ids():
        scene = load_scene(sid)
        if not scene.reference_model:
            continue
        for checks, bounds in [((), ()), (("stable",), (("energy_gain", 0.01),)),
                               ((), ((next(iter(get_model(scene.reference_model).produces)), 1.0),))]:
            skipped = set(skipped_model_metrics(scene, "reference", checks, bounds))
            read = {split_metric(c.metric)[0] for c in _criterion_checks(scene, "reference", checks)}
            assert not skipped & (read | {m for m, _ in bounds}), (sid, checks, bounds)
            seen += bool(skipped)
    assert seen > 0


def test_judge_reads_the_result():
    """A check or a bound holds on the value the result carries, fails on a
    missing one."""
    scene = load_scene("tunnelling.bullet_100")
    res = _ok_result(tunnelled=0.0)
    assert judge(scene, res, ("tunnelled",)) == (True, "")
    assert judge(scene, _ok_result(tunnelled=1.0), ("tunnelled",))[0] is False
    res = _ok_result(reflected_velocity_error=0.0)
    assert judge(scene, res, ("stable",), (("reflected_velocity_error", 0.02),)) == (True, "")
    holds, why = judge(scene, _ok_result(), ("stable",), (("reflected_velocity_error", 0.02),))
    assert not holds and why == "reflected_velocity_error: metric not computed"


def test_every_eval_row_records_the_skipped_metrics_once():
    """A run's row, a row whose value makes the spec invalid and the row of
    an evaluation whose worker died carry the same evaluation columns, with
    ``limit_skipped_metrics`` in each (the one record of what was skipped)."""
    from physbench.harness.limit_eval import EvalItem, lost_eval_row
    from physbench.harness.workers import WorkerLost

    req = LimitRequest("gyroscopic.fast_spin", None, "reference", "body[0].angular_velocity[2]", 10.0, 5000.0,
                       checks=("stable",), bounds=(("energy_gain", 0.01),),
                       overrides=(("scenario.duration", 0.05),))
    ran = evaluate_point(req, "x", 150.0, 0.0)
    bad = evaluate_point(dataclasses.replace(req, param="body[0].mass"), "x", -1.0, 0.0)
    lost = lost_eval_row(EvalItem(req, "x", 150.0, 0.5), WorkerLost("died", "worker process died: SIGKILL"))
    cols = {"row_kind", "point_key", "limit_id", "limit_param", "limit_value", "phase", "limit_holds",
            "limit_reason", "limit_unsupported", "limit_cpu_s", "limit_skipped_metrics"}
    for row in (ran, bad, lost):
        assert cols <= set(row), cols - set(row)
    assert set(ran["limit_skipped_metrics"].split(",")) == set(get_model("torque_free_rigid_body").produces)
    assert bad["status"] == "error" and not bad["limit_holds"] and bad["limit_skipped_metrics"] == ""
    assert lost["status"] == "error" and lost["limit_skipped_metrics"] == "" and lost["phase"] == 0.5
    assert lost["point_key"] == req.eval_key("x", 150.0, 0.5) and "SIGKILL" in lost["limit_reason"]
