"""The report reads rows only: check and sweep rows carry their verdicts,
thresholds and tags in one schema (harness.results.VERDICT_COLUMNS), old
rows without them are "no verdict recorded" and never re-judged against
today's scenarios, and failing checks link to their traces."""

from __future__ import annotations

import json
import math
import re

import pandas as pd
import pytest

from physbench.harness import report as rp
from physbench.harness.results import VERDICT_COLUMNS, write_rows
from physbench.harness.sweep_store import SWEEP_COLUMNS
from tests.test_report import METRIC, S1, row, write_sweep


def _no_scene_loading(monkeypatch):
    """Loading a scene or reading a spec during the report fails the test."""
    import physbench.contract.scene
    from physbench import contract

    def refuse(*a, **k):
        raise AssertionError("the report loaded a scene")

    monkeypatch.setattr(contract.scene, "load_scene", refuse)
    monkeypatch.setattr(contract.scene, "resolve_scenario", refuse)


def test_old_rows_are_not_rejudged(tmp_path, monkeypatch):
    """head_on's check today is post_impact_velocity_error <= 0.02.  A row
    written with a verdict under a looser threshold (PASS at 0.05) keeps its
    verdict; a row written before rows carried verdicts is "no verdict
    recorded" (not failed against today's 0.02); neither loads the scene."""
    verdict = [{"metric": METRIC, "outcome": "PASS", "value": 0.03, "threshold": "<= 0.05", "message": "ok then"}]
    written = dict(row(scenario="billiards.head_on", engine="mujoco", dt=0.001, error=0.03, sweep_id=S1),
                   checks=json.dumps(verdict), primary_threshold=0.05, tags=json.dumps(["conformance"]))
    old = row(scenario="billiards.head_on", engine="reference", dt=0.001, error=0.03, sweep_id=S1)
    phased = [row(scenario="billiards.head_on", engine="reference", dt=0.002, error=0.03, sweep_id=S1,
                  **({} if i == 0 else {"phase": i / 2})) for i in range(2)]
    write_sweep(tmp_path, [written, old] + phased)
    _no_scene_loading(monkeypatch)
    df = rp.load_results(tmp_path)
    by = {(r["engine"], r["dt"]): r for r in df[df["phase"] == 0].to_dict("records")}
    assert rp.failed_checks(by[("mujoco", 0.001)]) == [] and rp.meets_checks(by[("mujoco", 0.001)]) is True
    assert rp.failed_checks(by[("reference", 0.001)]) is None and rp.meets_checks(by[("reference", 0.001)]) is None
    sm = rp.stability_matrix(df, scenarios=["billiards.head_on"]).set_index("engine")
    assert sm.loc["mujoco", "met_checks"] == 1 and sm.loc["mujoco", "no_verdict"] == 0
    assert sm.loc["reference", "met_checks"] == 0 and sm.loc["reference", "no_verdict"] == 2
    assert sm.loc["reference", "checks_failed"] == []
    # the target is the threshold the row was written with, not today's
    ct = rp.cost_to_target(df).set_index("engine")
    assert set(ct["target"]) == {0.05} and ct.loc["mujoco", "reached"]
    # step phases without verdicts: '?', counted neither as failed nor as passed
    pt = rp.phase_table(df)
    assert list(pt["pattern"]) == ["??"] and list(pt["failures"]) == [0] and math.isnan(pt["fraction"].iloc[0])
    # no tags recorded: no scenario is known to be hard
    assert rp.hard_scenarios(df) == set()
    assert rp.stability_matrix(df).attrs["selection"].startswith("all scenarios")
    page = rp.render_html(df, physbench_commit="x")
    stab = page.split('id="stability"')[1].split("</section>")[0]
    assert "2 with no verdict recorded" in stab


def _check_row(engine, verdicts, dt=0.001, scenario="tunnelling.bullet_100"):
    return {"scenario": scenario, "variant": None, "engine": engine, "engine_version": "1", "status": "ok",
            "message": "", "stable": True, "setting.dt": dt, "cpu_s_per_sim_s": 0.01, "machine.id": "m1",
            "commit": "c", "timestamp": "2026-11-24T00:00:00+00:00", "phase": 0.0,
            "primary_metric": "reflected_velocity_error", "primary_threshold": 0.02,
            "tags": json.dumps(["conformance"]), "checks": json.dumps(verdicts)}


def test_failing_checks_section_lists_bad_verdicts_first_with_their_traces(tmp_path):
    trace = tmp_path / "traces" / "tunnelling.bullet_100--pymunk.rrd"
    verdicts = [
        {"metric": "tunnelled", "outcome": "XFAIL", "value": 1.0, "threshold": "== 0", "trace": str(trace),
         "message": "xfail: no continuous collision detection (tunnelled = 1, expected == 0)"},
        {"metric": "reflected_velocity_error", "outcome": "FAIL", "value": 1.7, "threshold": "<= 0.02",
         "message": "reflected_velocity_error = 1.7, expected <= 0.02", "trace": str(trace)},
        {"metric": "stable", "outcome": "PASS", "value": True, "threshold": "== True", "message": "", "trace": ""},
    ]
    rows = [_check_row("pymunk", verdicts),
            _check_row("reference", [dict(verdicts[2])]),
            dict(_check_row("mujoco", []), checks=None)]  # an old row: no verdict recorded
    write_rows(rows, tmp_path / "check" / "20261124T000000Z-c.parquet", append=False)
    df = rp.load_results(tmp_path)
    fc = rp.failing_checks(df)
    assert list(zip(fc["engine"], fc["metric"], fc["outcome"])) == [
        ("pymunk", "reflected_velocity_error", "FAIL"), ("pymunk", "tunnelled", "XFAIL")]
    assert list(fc["trace"]) == [str(trace)] * 2 and list(fc["threshold"]) == ["<= 0.02", "== 0"]
    assert fc.iloc[0]["value"] == 1.7 and "expected <= 0.02" in fc.iloc[0]["reason"]
    assert fc.attrs["no_verdict"] == 1
    out = tmp_path / "report.html"
    assert rp.report_main(tmp_path, out=out) == 0
    page = out.read_text()
    sec = page.split('id="failing-checks"')[1].split("</section>")[0]
    # linked relative to the page, named by case
    assert sec.count("href='traces/tunnelling.bullet_100--pymunk.rrd'") == 2
    assert "1 failing verdict(s)" in sec and "1 expected failure(s)" in sec
    assert "1 check row(s) written before rows carried their verdicts" in sec
    assert re.search(r"<code>reflected_velocity_error</code></td><td><span class='bad'>FAIL</span></td>"
                     r"<td>1\.7</td><td>&lt;= 0\.02</td>", sec)
    assert "stable" not in sec  # a PASS is not listed


def test_check_and_sweep_rows_share_the_verdict_columns(tmp_path):
    """One schema: a real check (with --traces) and a real sweep point of
    the same scene on the same engine store the same verdict columns, with
    the scene's threshold and tags and each check's verdict; the check's
    failing verdicts name their trace, and the report lists them."""
    pytest.importorskip("pymunk")
    from physbench.harness.conformance import check_main
    from physbench.harness.points import Point, run_point

    traces = tmp_path / "traces"
    code = check_main(["pymunk"], None, None, ["tunnelling.bullet_100"], save_dir=tmp_path / "check", traces=traces)
    (f,) = (tmp_path / "check").glob("*.parquet")
    check = pd.read_parquet(f)
    base = check[(check["phase"] == 0.0) & (check["setting.dt"] == check["setting.dt"].max())].iloc[0]
    sweep = run_point(Point("tunnelling.bullet_100", None, "pymunk", (("dt", float(base["setting.dt"])),)))
    assert set(VERDICT_COLUMNS) <= set(check.columns) and set(VERDICT_COLUMNS) <= set(sweep)
    assert set(VERDICT_COLUMNS) <= set(SWEEP_COLUMNS)
    for col in ("primary_metric", "primary_threshold", "tags"):
        assert base[col] == sweep[col], col
    assert json.loads(sweep["tags"]) == ["conformance"] and sweep["primary_threshold"] == 0.02
    cv = {v["metric"]: v for v in json.loads(base["checks"])}
    sv = {v["metric"]: v for v in json.loads(sweep["checks"])}
    assert {m: v["outcome"] for m, v in sv.items()} == {m: cv[m]["outcome"] for m in sv}
    assert cv["tunnelled"]["outcome"] == "XFAIL" and cv["tunnelled"]["threshold"]
    rrd = traces / "tunnelling.bullet_100--pymunk.rrd"
    assert rrd.is_file() and cv["tunnelled"]["trace"] == str(rrd)
    assert all(v["trace"] == "" for v in sv.values())  # a sweep writes no traces
    fc = rp.failing_checks(rp.load_results(tmp_path))
    assert ("tunnelled", "XFAIL", str(rrd)) in set(zip(fc["metric"], fc["outcome"], fc["trace"]))
    # the first screen and summary.json on the real check's rows: the check's own exit code, and
    # every verdict the check stored (phased runs carry theirs on phase 0 only) counted once
    assert rp.report_main(tmp_path) == 0
    sm = json.loads((tmp_path / "summary.json").read_text())
    (eng,) = sm["conformance"]["engines"]
    assert eng["engine"] == "pymunk" and eng["check_run"] == f.stem and eng["rows"] == len(check)
    stored = [v["outcome"] for c in check["checks"] for v in json.loads(c)]
    assert eng["counts"] == {o: stored.count(o) for o in eng["counts"]} and sum(eng["counts"].values()) == len(stored)
    assert eng["counts"]["XFAIL"] >= 1 and sm["conformance"]["passed"] is (code == 0)


def test_contact_laws_predictability_and_consensus_from_rows(tmp_path, monkeypatch):
    """Check rows carrying contact-law residuals, ensemble rows and a
    consensus row: the report's tables read them (the largest residual per
    engine and where, undefined never 0; the hard scenes' ensembles with
    their verdicts; the consensus) and its section shows them with one
    plot; ensemble and consensus rows are not runs of the stability
    matrix.  No scene is loaded."""
    laws = dict(signorini_residual_max=6.2e-11, cone_violation_max=0.0, dissipation_residual_max=1e-7,
                adhesion_max=0.0, separation_force_max=float("nan"))
    pb = dict(signorini_residual_max=3.2e-3, cone_violation_max=0.0243, dissipation_residual_max=0.786,
              adhesion_max=0.0, separation_force_max=float("nan"))
    nan = {k: float("nan") for k in laws}
    hard = json.dumps(["hard"])
    ens = json.dumps({"n": 8, "position": 1e-4, "threshold": 0.01})
    pv = [{"metric": "predictable", "outcome": "FAIL", "value": False, "threshold": "== True", "message": "m"}]
    rows = [
        dict(_check_row("reference", [], scenario="laws.stack"), **laws),
        dict(_check_row("reference", [], scenario="laws.slope"), **dict(laws, signorini_residual_max=2e-9)),
        dict(_check_row("pybullet", [], scenario="laws.stack"), **pb),
        dict(_check_row("rapier", [], scenario="laws.stack"), **nan,
             undefined_metrics="cone_violation_max: rapier: the adapter reads no contact forces from its engine"),
        dict(_check_row("reference", pv, scenario="hard.apex"), tags=hard, ensemble=ens, members=8, members_ok=8,
             final_spread=0.524, amplification=4.5e3, event_spread=3, ensemble_threshold=0.01, predictable=False,
             stable=None),
        dict(_check_row("mujoco", [dict(pv[0], outcome="PASS", value=True)], scenario="hard.apex"), tags=hard,
             ensemble=ens, members=8, members_ok=8, final_spread=1e-4, amplification=0.9, event_spread=0,
             ensemble_threshold=0.01, predictable=True, stable=None),
        dict(_check_row("reference", [], scenario="hard.apex"), tags=hard),  # its plain run
        dict(_check_row("consensus", [{"metric": "consensus_spread", "outcome": "PASS", "value": 1e-3,
                                       "threshold": "<= 0.01", "message": ""}], scenario="selfcheck.spring"),
             engine_version="reference 0.1.0, mujoco 4.0.0", consensus_spread=1.02e-3, consensus_spread_angle=0.0,
             message="2 engines at dt = 0.005 s; farthest apart: mujoco - reference 0.00102 m", stable=None),
    ]
    write_rows(rows, tmp_path / "check" / "20261124T000000Z-c.parquet", append=False)
    _no_scene_loading(monkeypatch)
    df = rp.load_results(tmp_path)
    cl = rp.contact_law_table(df).set_index("engine")
    assert list(cl.index) == ["pybullet", "reference"]  # rapier: no value, not a row of zeros
    assert cl.loc["reference", "signorini_residual_max"] == 2e-9
    assert cl.loc["reference", "signorini_residual_where"] == "laws.slope"
    assert cl.loc["reference", "rows"] == 2 and cl.loc["reference", "scenarios"] == 2
    assert cl.loc["pybullet", "cone_violation_max"] == 0.0243
    assert math.isnan(cl.loc["pybullet", "separation_force_max"])
    pt = rp.predictability_table(df)
    assert pt.attrs["selection"] == "scenarios tagged 'hard'"
    assert list(zip(pt["engine"], pt["predictable"], pt["verdict"])) == [("mujoco", True, "PASS"),
                                                                        ("reference", False, "FAIL")]
    assert list(pt["final_spread"]) == [1e-4, 0.524]
    ct = rp.consensus_table(df)
    assert list(ct["consensus_spread"]) == [1.02e-3] and ct["verdicts"][0] == "consensus_spread PASS"
    sm = rp.stability_matrix(df)
    assert set(sm["engine"]) == {"reference"} and list(sm["points"]) == [1]  # the plain run only
    page = rp.render_html(df, physbench_commit="x")
    sec = page.split('<section id="judging">')[1].split("</section>")[0]
    assert sec.count("<img ") == 1
    assert "3.2e-03" in sec or "0.0032" in sec
    assert "<span class='note'>undefined</span>" in sec  # separation_force: no row has a value
    assert sec.count("data-predictable='False'") == 1 and sec.count("data-predictable='True'") == 1
    assert "0.524" in sec and "not predictable</span> (FAIL)" in sec
    assert "consensus_spread PASS" in sec and "farthest apart: mujoco - reference" in sec


def test_consensus_is_no_engine_at_a_glance(tmp_path, monkeypatch):
    """A check file holding an engine's rows and a consensus row (engine
    ``consensus``) with a failed verdict: at a glance and in summary.json
    only the engine is an engine (its counts, its verdict: passed), the
    consensus's FAIL is no unexpected failure of an engine, now or as an
    earlier run's, and it is shown in the judging section."""
    from physbench.harness.report.glance import first_screen, summary

    ok = [{"metric": "stable", "outcome": "PASS", "value": True, "threshold": "== True", "message": ""}]
    bad = [{"metric": "consensus_spread", "outcome": "FAIL", "value": 0.3, "threshold": "<= 0.01",
            "message": "consensus_spread = 0.3, expected <= 0.01"}]
    cons = dict(_check_row("consensus", bad, scenario="selfcheck.spring"), engine_version="reference 0.1.0, mujoco 4",
                consensus_spread=0.3, consensus_spread_angle=0.0, stable=None,
                message="2 engines at dt = 0.005 s; farthest apart: mujoco - reference 0.3 m")
    write_rows([_check_row("reference", ok), cons], tmp_path / "check" / "20261124T000000Z-c.parquet", append=False)
    # a later check of the engine alone: the consensus's file is an earlier run
    write_rows([dict(_check_row("reference", ok), timestamp="2026-11-25T00:00:00+00:00")],
               tmp_path / "check" / "20261125T000000Z-c.parquet", append=False)
    _no_scene_loading(monkeypatch)
    df = rp.load_results(tmp_path)
    assert set(df["engine"]) == {"reference", "consensus"}  # both rows were read
    first = first_screen(df)
    assert list(first["runs"]["engine"]) == ["reference"]
    assert first["runs"]["PASS"].tolist() == [1] and first["runs"]["FAIL"].tolist() == [0]
    assert first["unexpected"].empty and first["earlier"].empty
    js = summary(first, generated="t", physbench_commit="x")
    assert [e["engine"] for e in js["conformance"]["engines"]] == ["reference"]
    assert js["conformance"]["passed"] is True and js["conformance"]["totals"]["FAIL"] == 0
    assert js["unexpected"] == [] and js["unexpected_earlier"] == []
    page = rp.render_html(df, physbench_commit="x")
    glance = page.split('<section id="at-a-glance">')[1].split("</section>")[0]
    assert "consensus" not in glance and "reference" in glance
    sec = page.split('<section id="judging">')[1].split("</section>")[0]
    assert "consensus_spread FAIL" in sec


def test_judging_section_without_rows(tmp_path):
    write_rows([_check_row("reference", [])], tmp_path / "check" / "20261124T000000Z-c.parquet", append=False)
    page = rp.render_html(rp.load_results(tmp_path), physbench_commit="x")
    sec = page.split('<section id="judging">')[1].split("</section>")[0]
    assert "No row carries contact-law residuals" in sec and "No ensemble rows" in sec
    assert "<img " not in sec
