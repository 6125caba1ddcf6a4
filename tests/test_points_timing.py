"""A stored row's cost is the engine's stepping alone: the metrics run of
a scene with a contact-law metric reads the contact forces after every
step (harness/runner.py) and is not timed; one more run is
(harness.points.request_row)."""

from __future__ import annotations

import statistics

import pytest

from physbench.contract.metric_defs import wants_contact_forces
from physbench.contract.scene import load_scene
from physbench.harness import points, runner
from physbench.harness.execute import RunRequest

#: a short contact-law scene on the reference engine (its checks read the
#: contact forces: the runner steps it one step a call in the metrics run)
FORCES_SCENE = "friction.block_slides"
#: a scene whose checks need no contact forces
PLAIN_SCENE = "billiards.head_on"
SETTINGS = {"dt": 0.064}


def _spy(monkeypatch):
    calls = []
    real = runner.run

    def run(*a, **k):
        res = real(*a, **k)
        calls.append((bool(k.get("compute_metrics")), bool(res.info.get("contact_forces_per_step")),
                      float(res.metrics.get("cpu_s_per_sim_s"))))
        return res

    monkeypatch.setattr(runner, "run", run)
    return calls


def test_the_scenes_are_what_the_tests_need():
    assert wants_contact_forces(load_scene(FORCES_SCENE), "reference")
    assert not wants_contact_forces(load_scene(PLAIN_SCENE), "reference")


@pytest.mark.parametrize("repeats", [1, 2])
def test_the_run_that_read_contact_forces_every_step_is_not_timed(monkeypatch, repeats):
    calls = _spy(monkeypatch)
    row = points.request_row(RunRequest(FORCES_SCENE, "reference", settings=dict(SETTINGS), repeats=repeats))
    assert row["status"] == "ok"
    # the metrics run read the forces step by step; `repeats` more runs were timed, without reads
    assert [c[:2] for c in calls] == [(True, True)] + [(False, False)] * repeats
    timed = [c[2] for c in calls[1:]]
    assert row["repeats"] == repeats
    assert row["cpu_s_per_sim_s_median"] == statistics.median(timed)
    assert row["cpu_s_per_sim_s_min"] == min(timed)
    # the metrics come from the first run (its contact-law metrics are there)
    assert "contact_forces_per_step" in row["info"]


def test_a_scene_without_contact_law_metrics_times_its_metrics_run(monkeypatch):
    calls = _spy(monkeypatch)
    row = points.request_row(RunRequest(PLAIN_SCENE, "reference", settings=dict(SETTINGS), repeats=2))
    assert row["status"] == "ok"
    assert [c[:2] for c in calls] == [(True, False), (False, False)]
    assert row["cpu_s_per_sim_s_median"] == statistics.median(c[2] for c in calls)
