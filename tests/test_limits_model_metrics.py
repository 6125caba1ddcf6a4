"""A breaking-point evaluation computes the reference model's metrics only when
its criterion reads one (harness/limit_eval.py ``skipped_model_metrics``)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from contract.scene import load_scene
from harness.limit_eval import LimitRequest, evaluate_point, judge, skipped_model_metrics
from harness.references import get_model


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
    assert "reference model metrics not computed" in row["notes"]
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


def test_judge_never_reads_a_skipped_metric():
    """A check or a bound on a metric the run skipped does not hold, even
    when the result carries a passing value under that name."""
    scene = load_scene("tunnelling.bullet_100")
    res = _ok_result(tunnelled=0.0)
    assert judge(scene, res, ("tunnelled",)) == (True, "")
    holds, why = judge(scene, res, ("tunnelled",), skipped=("tunnelled",))
    assert not holds and why.startswith("tunnelled: metric not computed")
    res = _ok_result(reflected_velocity_error=0.0)
    assert judge(scene, res, ("stable",), (("reflected_velocity_error", 0.02),)) == (True, "")
    holds, why = judge(scene, res, ("stable",), (("reflected_velocity_error", 0.02),),
                       skipped=("reflected_velocity_error",))
    assert not holds and "metric not computed" in why
