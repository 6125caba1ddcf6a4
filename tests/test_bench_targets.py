"""``physbench bench targets`` (harness/bench_targets.py): the cost-to-target
table's points, timed again side by side."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from physbench.harness import bench_targets as bt


def _table(rows):
    cols = ["scenario", "variant", "engine", "reached", "point_settings", "cost", "ratio", "dt"]
    return pd.DataFrame([dict(zip(cols, r)) for r in rows], columns=cols)


def test_pairs_take_the_reference_and_the_cheapest_other_engine_that_reached():
    t = _table([
        ("a.x", "", "reference", True, '{"dt":0.01}', 3.0, 3.0, 0.01),
        ("a.x", "", "pymunk", True, '{"dt":0.02}', 1.0, 1.0, 0.02),
        ("a.x", "", "mujoco", True, '{"dt":0.01}', 2.0, 2.0, 0.01),
        ("a.x", "", "box2d", False, "", math.nan, math.nan, math.nan),  # not reached: never the other
        ("b.y", "", "mujoco", True, '{"dt":0.01}', 1.0, 1.0, 0.01),  # reference did not reach: no pair
        ("c.z", "", "reference", True, '{"dt":0.01}', 1.0, 1.0, 0.01),  # alone: the other is None
    ])
    got = bt.pairs(t)
    assert [p["reference"]["scenario"] for p in got] == ["a.x", "c.z"]
    assert got[0]["other"]["engine"] == "pymunk" and got[0]["other"]["point_settings"] == '{"dt":0.02}'
    assert got[1]["other"] is None


def test_side_by_side_alternates_the_order_and_takes_medians():
    ref = {"scenario": "a.x", "variant": "", "engine": "reference", "point_settings": "{}", "cost": 3.0, "ratio": 3.0,
           "dt": 0.01}
    oth = {**ref, "engine": "pymunk", "ratio": 1.0}
    calls = []
    costs = {"reference": iter([9.0, 0.3, 0.4, 0.2]), "pymunk": iter([9.0, 0.1, 0.1, 0.1])}

    def run(p):
        calls.append(p["engine"])
        return next(costs[p["engine"]])

    row = bt.side_by_side({"reference": ref, "other": oth}, 3, run)
    # one untimed run each, then A B, B A, A B: the untimed 9.0 is in no median
    assert calls == ["reference", "pymunk", "reference", "pymunk", "pymunk", "reference", "reference", "pymunk"]
    assert row["reference_ms_per_sim_s"] == pytest.approx(300.0)
    assert row["other_ms_per_sim_s"] == pytest.approx(100.0)
    assert row["ratio"] == pytest.approx(3.0)
    assert (row["ratio_lo"], row["ratio_hi"]) == (pytest.approx(2.0), pytest.approx(4.0))
    assert row["table_ratio"] == 3.0 and row["note"] == ""


def test_a_repeat_that_does_not_end_ok_is_left_out_and_said():
    ref = {"scenario": "a.x", "variant": "v", "engine": "reference", "point_settings": "{}", "cost": 1.0,
           "ratio": 1.0, "dt": 0.01}
    vals = iter([1.0, 1.0, math.nan, 1.0, 1.0, 2.0])  # untimed A B; A B (A failed); B A

    row = bt.side_by_side({"reference": ref, "other": {**ref, "engine": "mujoco"}}, 2, lambda p: next(vals))
    assert row["scenario"] == "a.x[v]"
    assert row["ratio"] == pytest.approx(2.0)  # the one good repeat
    assert "1 of 2 repeats did not end ok" in row["note"]


def test_the_point_settings_are_run_as_the_sweep_ran_them(monkeypatch):
    """The row's settings reach the runner, the phase the scene, and the
    run's CPU per simulated second is what is returned."""
    from physbench.harness import runner

    seen = {}

    class R:
        status = "ok"
        metrics = {"cpu_s_per_sim_s": 0.25}

    def fake_run(scene, engine, settings, **kw):
        seen.update(engine=engine, settings=settings, dt=scene.dt, kw=kw)
        return R()

    monkeypatch.setattr(runner, "run", fake_run)
    p = {"scenario": "billiards.head_on", "variant": "", "engine": "pymunk",
         "point_settings": json.dumps({"dt": 0.004, "iterations": 10}), "cost": 1.0, "ratio": 1.0, "dt": 0.004}
    assert bt.timed_run(p) == 0.25
    assert seen["engine"] == "pymunk" and seen["settings"] == {"dt": 0.004, "iterations": 10}
    assert seen["kw"]["compute_metrics"] is False


def test_no_results_is_a_clear_error_and_exit_2(tmp_path, capsys):
    """An empty results directory: a clear error, exit 2, no traceback."""
    from physbench.harness.cli import main

    assert main(["bench", "targets", "--results-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "physbench bench targets:" in err and "physbench sweep" in err
