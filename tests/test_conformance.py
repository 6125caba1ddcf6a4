"""Conformance evaluation logic on synthetic run results, and the JUnit XML."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import pytest

from physbench.harness import conformance as C
from physbench.harness.conformance.junit import junit_xml
from physbench.harness.conformance.verdicts import describe_bound
from physbench.harness.runner import RunResult
from physbench.contract.scene import Check, load_scene
from physbench.contract.xfail import MEASURED_ON


def result(metrics=None, status="ok", message="", engine="mujoco", scenario="fam.scn", variant=None):
    # the engine version the shipped xfails were measured on (contract/xfail.py)
    return RunResult(scenario=scenario, variant=variant, engine=engine, engine_version=MEASURED_ON.get(engine, "1"),
                     status=status,
                     message=message, settings={}, metrics=dict(metrics or {}))


# ---------------------------------------------------------------------------
# single checks


def test_max_min_equals():
    r = result({"err": 0.01, "flag": True, "count": 3.0})
    assert C.evaluate_check(Check("err", max=0.02), r).outcome == C.PASS
    assert C.evaluate_check(Check("err", max=0.005), r).outcome == C.FAIL
    assert C.evaluate_check(Check("err", min=0.02), r).outcome == C.FAIL
    assert C.evaluate_check(Check("err", min=0.0, max=0.02), r).outcome == C.PASS
    assert C.evaluate_check(Check("flag", equals=True), r).outcome == C.PASS
    assert C.evaluate_check(Check("flag", equals=False), r).outcome == C.FAIL
    assert C.evaluate_check(Check("count", equals=3.0), r).outcome == C.PASS
    assert C.evaluate_check(Check("count", equals=3.1, tolerance=0.2), r).outcome == C.PASS
    assert C.evaluate_check(Check("count", equals=3.5, tolerance=0.2), r).outcome == C.FAIL
    # the boundary itself passes
    assert C.evaluate_check(Check("err", max=0.01), r).outcome == C.PASS


def test_bool_check_accepts_numpy_bool_and_0_1():
    import numpy as np

    assert C.evaluate_check(Check("stable", equals=True), result({"stable": np.bool_(True)})).outcome == C.PASS
    assert C.evaluate_check(Check("stable", equals=True), result({"stable": 1.0})).outcome == C.PASS
    assert C.evaluate_check(Check("stable", equals=True), result({"stable": 0.5})).outcome == C.FAIL


def test_fail_message_names_value_and_threshold():
    o = C.evaluate_check(Check("err", max=0.005), result({"err": 0.01}))
    assert o.outcome == C.FAIL
    assert "err = 0.01" in o.message and "<= 0.005" in o.message
    assert o.value == 0.01 and o.threshold == "<= 0.005"


def test_nan_or_missing_metric_is_an_error():
    """A check on a metric the ok run did not produce is an ERROR (never a
    silent skip, nor a plain FAIL), xfail or not: nothing was measured."""
    for metrics in ({"err": math.nan}, {}, {"err": None}):
        o = C.evaluate_check(Check("err", max=1.0), result(metrics))
        assert o.outcome == C.ERROR
        assert o.message.startswith("metric not computed: err is")
        xo = C.evaluate_check(Check("err", max=1.0, xfail={"mujoco": "known"}), result(metrics))
        assert xo.outcome == C.ERROR
    assert C.exit_code([C.evaluate_check(Check("err", max=1.0), result({}))]) == 1


def test_nan_metric_on_unsupported_engine_is_unsupported():
    o = C.evaluate_check(Check("err", max=1.0), result({"err": math.nan}, status="unsupported",
                                                        message="2D engine"))
    assert o.outcome == C.UNSUPPORTED
    assert "2D engine" in o.message


def test_xfail_and_xpass():
    c = Check("err", max=0.01, xfail={"mujoco": "soft contacts: measured 0.05"})
    o = C.evaluate_check(c, result({"err": 0.05}))
    assert o.outcome == C.XFAIL
    assert o.message.startswith("xfail: soft contacts: measured 0.05")
    o = C.evaluate_check(c, result({"err": 0.001}))
    assert o.outcome == C.XPASS
    assert o.message.startswith("unexpected pass")
    # other engines are not affected by mujoco's xfail
    assert C.evaluate_check(c, result({"err": 0.05}, engine="pybullet")).outcome == C.FAIL
    # a missing metric on an xfailed engine is an error: nothing was measured
    assert C.evaluate_check(c, result({})).outcome == C.ERROR


@pytest.mark.parametrize("status", ["error", "failed", "diverged", "timeout"])
def test_error_statuses(status):
    o = C.evaluate_check(Check("err", max=1.0), result({"err": 0.0}, status=status, message="boom"))
    assert o.outcome == C.ERROR
    assert status in o.message and "boom" in o.message
    c = Check("err", max=1.0, xfail={"mujoco": "known blow-up"})
    assert C.evaluate_check(c, result({}, status=status)).outcome == C.XFAIL


def test_unsupported():
    o = C.evaluate_check(Check("err", max=1.0), result({}, status="unsupported", message="no cylinders"))
    assert o.outcome == C.UNSUPPORTED


# ---------------------------------------------------------------------------
# applicability, @-suffixed checks, hard cases


def test_check_applies():
    c = Check("err", max=1.0, engines=("mujoco",))
    assert C.check_applies(c, "mujoco", None)
    assert not C.check_applies(c, "pymunk", None)
    c = Check("err", max=1.0, variants=("v1",))
    assert C.check_applies(c, "mujoco", "v1")
    assert not C.check_applies(c, "mujoco", None)
    assert not C.check_applies(c, "mujoco", "v2")
    c = Check("err", max=1.0, variants=("base", "v2"))
    assert C.check_applies(c, "mujoco", None)
    assert C.check_applies(c, "mujoco", "v2")
    assert C.check_applies(Check("err", max=1.0), "x", "anything")


def test_split_metric():
    assert C.split_metric("stable") == ("stable", {})
    name, st = C.split_metric("stable@dt=1/30")
    assert name == "stable" and st == {"dt": pytest.approx(1 / 30)}
    assert C.split_metric("err@iterations=20")[1] == {"iterations": 20}


def test_hard_scenarios_get_stability_checks():
    sc = load_scene("stacking.pyramid")
    assert "hard" in sc.tags
    metrics = [c.metric for c in C.hard_checks(sc)]
    assert metrics == ["stable", "stable@dt=1/30"]
    # variants of a hard scenario do not repeat them
    assert C.hard_checks(load_scene("stacking.pyramid", "levels_7")) == []
    # a non-hard scenario has none
    assert C.hard_checks(load_scene("stacking.column_5")) == []


def test_evaluate_uses_the_dt_run_for_suffixed_checks():
    sc = load_scene("stacking.pyramid")
    base = result({"stack_drift": 0.0, "residual_velocity": 0.0, "max_penetration": 0.0, "stable": True},
                  engine="pymunk", scenario=sc.id)
    coarse = result({"stable": False, "stability_reason": "energy gain 3 > 0.5"}, engine="pymunk",
                    scenario=sc.id)
    outs = {o.metric: o for o in C.evaluate(sc, base, {"dt=1/30": coarse})}
    assert outs["stable"].outcome == C.PASS
    assert outs["stable@dt=1/30"].outcome == C.FAIL
    assert "energy gain" in outs["stable@dt=1/30"].message
    assert outs["stable@dt=1/30"].name == "stacking.pyramid::stable@dt=1/30"
    # without the coarse run the suffixed check is an error, not a pass
    outs = {o.metric: o for o in C.evaluate(sc, base)}
    assert outs["stable@dt=1/30"].outcome == C.ERROR


def test_plan_runs_only_variants_with_checks_and_adds_dt_runs():
    runs, errors = C.plan(["friction.critical_angle", "stacking.pyramid"], ["mujoco", "pymunk"])
    assert not errors
    keys = {(r.scenario, r.variant, r.engine, tuple(r.settings)) for r in runs}
    # critical_angle: checks only on its two variants, none on the marginal base
    assert ("friction.critical_angle", None, "mujoco", ()) not in keys
    assert ("friction.critical_angle", "minus_1deg", "mujoco", ()) in keys
    assert ("friction.critical_angle", "plus_1deg", "pymunk", ()) in keys
    # pyramid is hard: a dt = 1/30 run per engine for the base scene only
    dt_runs = [r for r in runs if r.settings]
    assert {(r.scenario, r.variant, r.engine) for r in dt_runs} == {
        ("stacking.pyramid", None, "mujoco"), ("stacking.pyramid", None, "pymunk")}
    assert all(r.settings["dt"] == pytest.approx(1 / 30) for r in dt_runs)


def test_select_scenarios_by_tag():
    hard = C.select_scenarios(None, ["hard"])
    assert "stacking.pyramid" in hard and "stacking.column_5" not in hard
    assert C.select_scenarios(["billiards.head_on"], None) == ["billiards.head_on"]


# ---------------------------------------------------------------------------
# JUnit XML


def _outcomes():
    O = C.Outcome
    return [
        O("mujoco", "a.b", None, "err", C.PASS, 0.1, "<= 1", "ok"),
        O("mujoco", "a.b", "v1", "err", C.FAIL, 2.0, "<= 1", "err = 2, expected <= 1"),
        O("mujoco", "a.b", None, "stable@dt=1/30", C.XFAIL, False, "== True", "xfail: blows up"),
        O("pymunk", "a.b", None, "err", C.UNSUPPORTED, None, "<= 1", "unsupported: 2D"),
        O("pymunk", "a.c", None, "err", C.XPASS, 0.1, "<= 1", "unexpected pass: err = 0.1"),
        O("pymunk", "a.c", None, "other", C.ERROR, None, "<= 1", "diverged: non-finite pos"),
    ]


def test_junit_xml_parses_and_counts_match(tmp_path):
    path = tmp_path / "out" / "junit.xml"
    C.write_junit(_outcomes(), path)
    root = ET.parse(path).getroot()
    assert root.tag == "testsuites"
    suites = {s.get("name"): s for s in root.findall("testsuite")}
    assert set(suites) == {"mujoco", "pymunk"}
    for s in suites.values():
        cases = s.findall("testcase")
        assert int(s.get("tests")) == len(cases)
        assert int(s.get("failures")) == sum(c.find("failure") is not None for c in cases)
        assert int(s.get("errors")) == sum(c.find("error") is not None for c in cases)
        assert int(s.get("skipped")) == sum(c.find("skipped") is not None for c in cases)
    mj = {c.get("name"): c for c in suites["mujoco"].findall("testcase")}
    assert set(mj) == {"a.b::err", "a.b[v1]::err", "a.b::stable@dt=1/30"}
    assert mj["a.b[v1]::err"].find("failure") is not None
    assert mj["a.b::stable@dt=1/30"].find("skipped").get("message").startswith("xfail: ")
    pm = {c.get("name"): c for c in suites["pymunk"].findall("testcase")}
    assert pm["a.c::err"].find("failure").get("message").startswith("unexpected pass")
    assert pm["a.c::other"].find("error") is not None
    assert pm["a.b::err"].find("skipped") is not None
    assert root.get("tests") == "6" and root.get("failures") == "2" and root.get("errors") == "1"
    assert root.get("skipped") == "2"


def test_exit_code():
    outs = _outcomes()
    assert C.exit_code(outs) == 1
    ok = [o for o in outs if o.outcome in (C.PASS, C.XFAIL, C.UNSUPPORTED)]
    assert C.exit_code(ok) == 0
    for bad in (C.FAIL, C.XPASS, C.ERROR):
        assert C.exit_code(ok + [C.Outcome("e", "s", None, "m", bad)]) == 1


def test_summary_lists_failures():
    from io import StringIO

    from rich.console import Console

    buf = StringIO()
    C.summarize(_outcomes(), Console(file=buf, width=200))
    text = buf.getvalue()
    assert "a.b[v1]::err" in text and "unexpected pass" in text
    assert "a.c::other" in text and "diverged" in text
    assert "FAIL 1" in text and "XPASS 1" in text


# ---------------------------------------------------------------------------
# check_main end to end (synthetic engine runs)


def test_check_main_with_synthetic_runs(tmp_path, monkeypatch):
    def fake_execute(spec):
        # head_on: every check passes on 'good'; 'bad' misses the velocity check
        m = {"post_impact_velocity_error": 0.001 if spec.engine == "good" else 0.5,
             "linear_momentum_drift": 0.0, "max_penetration": 0.0, "stable": True}
        return result(m, engine=spec.engine, scenario=spec.scenario, variant=spec.variant)

    monkeypatch.setattr(C, "execute", fake_execute)
    junit = tmp_path / "j.xml"
    kw = dict(executor="inline", save_dir=tmp_path / "rows")  # the patched execute runs in this process
    assert C.check_main(["good"], None, str(junit), ["billiards.head_on"], **kw) == 0
    root = ET.parse(junit).getroot()
    n_variants = 1 + len(load_scene("billiards.head_on").variant_names)
    assert int(root.get("tests")) == 3 * n_variants
    assert C.check_main(["good", "bad"], None, str(junit), ["billiards.head_on"], **kw) == 1
    root = ET.parse(junit).getroot()
    assert int(root.get("failures")) == n_variants


def test_unknown_or_broken_engine_does_not_crash(tmp_path):
    # the engine cannot even be loaded: every run is recorded as failed -> ERROR
    junit = tmp_path / "j.xml"
    code = C.check_main(["no_such_engine"], None, str(junit), ["billiards.head_on"], save_dir=tmp_path / "rows")
    assert code == 1
    root = ET.parse(junit).getroot()
    assert int(root.get("errors")) == int(root.get("tests")) > 0
    res = C.execute(C.RunSpec("billiards.head_on", None, "no_such_engine"))
    assert res.status == "failed" and "no_such_engine" in res.message


# ---------------------------------------------------------------------------
# step phases ([scenario] phases)


def _o(outcome, value=0.0, message="m"):
    return C.Outcome("pymunk", "fam.scn", None, "tunnelled", outcome, value, "== 0", message, 0.1)


def test_combine_phases_holds_only_if_every_phase_holds():
    chk = Check("tunnelled", equals=0.0)
    xchk = Check("tunnelled", equals=0.0, xfail={"pymunk": "no CCD"})
    o = C.combine_phases([_o(C.PASS), _o(C.PASS), _o(C.PASS)], chk)
    assert o.outcome == C.PASS and o.message.startswith("all 3 step phases")
    o = C.combine_phases([_o(C.PASS), _o(C.FAIL, 1.0, "tunnelled = 1"), _o(C.PASS), _o(C.FAIL, 1.0)], chk)
    assert o.outcome == C.FAIL and o.value == 1.0
    assert o.message.startswith("failed in 2 of 4 step phases [.x.x]; phase 1/4: tunnelled = 1")
    # with an xfail: any failing phase is the expected failure; all passing is an unexpected pass
    assert C.combine_phases([_o(C.XPASS), _o(C.XFAIL), _o(C.XPASS)], xchk).outcome == C.XFAIL
    assert C.combine_phases([_o(C.XPASS), _o(C.XPASS)], xchk).outcome == C.XPASS
    # an errored phase makes the check an error
    assert C.combine_phases([_o(C.PASS), _o(C.ERROR, None, "diverged: nan")], chk).outcome == C.ERROR
    assert C.combine_phases([_o(C.UNSUPPORTED)] * 2, chk).outcome == C.UNSUPPORTED
    # unsupported in some phases only: inconsistent, an error either way round
    for per in ([_o(C.UNSUPPORTED), _o(C.PASS)], [_o(C.PASS), _o(C.UNSUPPORTED)]):
        o = C.combine_phases(per, chk)
        assert o.outcome == C.ERROR and "unsupported in some step phases only" in o.message


def test_scene_phases_run_every_phase_and_combine_them(tmp_path, monkeypatch):
    """The thin plate over 4 phases: pymunk (no CCD) fails in some of them
    (its expected failure), the reference engine passes in all."""
    import physbench.contract.scene as scene_mod

    spec = (load_scene("tunnelling.thin_box_on_thin_floor").path).read_text()
    assert "\nphases = 16\n" in spec
    spec = spec.replace("\nphases = 16\n", "\nphases = 4\n")
    (tmp_path / "tunnelling").mkdir()
    (tmp_path / "tunnelling" / "plate.toml").write_text(spec)
    monkeypatch.setattr(scene_mod, "SCENARIO_DIR", tmp_path)
    sc = load_scene("tunnelling.plate")
    assert sc.phases == 4
    runs, errors = C.plan(["tunnelling.plate"], ["pymunk", "reference"])
    assert not errors
    base = [r for r in runs if r.checks and r.variant is None]
    assert {r.engine: r.phases for r in base} == {"pymunk": 4, "reference": 4}
    assert sorted(r.phase for r in runs if r.variant is None and r.engine == "pymunk" and not r.settings) == \
        [0.0, 0.25, 0.5, 0.75]
    results = C.run_all(runs, progress=False, executor="inline")  # SCENARIO_DIR is patched in this process
    outs = [o for o in C.evaluate_runs(runs, results) if o.variant is None and o.metric == "tunnelled"]
    by = {o.engine: o for o in outs}
    assert by["reference"].outcome == C.PASS and "all 4 step phases" in by["reference"].message
    assert by["pymunk"].outcome == C.XFAIL and "step phases [" in by["pymunk"].message
    # every phase's row is saved, with its phase
    import pandas as pd
    df = pd.read_parquet(C.save_rows(results, tmp_path / "rows"))
    assert sorted(set(df[df["engine"] == "pymunk"]["phase"])) == [0.0, 0.25, 0.5, 0.75]


def test_phases_need_a_start_in_free_flight(tmp_path):
    from physbench.contract.spec import SpecError

    spec = load_scene("stacking.column_5").path.read_text()
    spec = spec.replace("[scenario]\n", "[scenario]\nphases = 4\n", 1)
    p = tmp_path / "col.toml"
    p.write_text(spec)
    with pytest.raises(SpecError, match=r"scenario.phases: 4 step phases need a start in free flight: .*box_0"):
        load_scene(p)


# ---------------------------------------------------------------------------
# issue 40: verdicts a newcomer can trust


def test_verdict_prints_the_digits_that_decide_it():
    """0.0010000000000002507 against max 0.001 is a FAIL, and the message
    shows the digits that make it one; a value far from its bound keeps 6."""
    o = C.evaluate_check(Check("max_penetration", max=0.001), result({"max_penetration": 0.0010000000000002507}))
    assert o.outcome == C.FAIL
    assert o.message == "max_penetration = 0.0010000000000003, expected <= 0.001"  # not "0.001"
    v = float(o.message.split(" = ")[1].split(",")[0])
    assert v > 0.001  # the printed text reads back on the failing side
    o = C.evaluate_check(Check("x", min=0.25), result({"x": 0.24999999}))
    assert o.message == "x = 0.24999999, expected >= 0.25"
    assert C.evaluate_check(Check("x", max=0.5), result({"x": 0.123456789})).message == "x = 0.123457, expected <= 0.5"
    # the bound is printed as written, not rounded
    assert describe_bound(Check("x", max=0.0123456789)) == "<= 0.0123456789"
    # the failures table and JUnit print the same digits
    from io import StringIO

    from rich.console import Console

    o = C.evaluate_check(Check("max_penetration", max=0.001), result({"max_penetration": 0.0010000000000002507}))
    buf = StringIO()
    C.summarize([o], Console(file=buf, width=250))
    assert "0.0010000000000003" in buf.getvalue()
    case = junit_xml([o]).getroot().find("testsuite/testcase")
    assert "value 0.0010000000000003, threshold <= 0.001" in case.find("failure").text


def test_junit_case_names_are_unique():
    """Two checks on one metric (different bounds, or the same twice) become
    distinct test cases that say what differs; other names stay as they were."""
    r = result({"max_penetration": 0.002, "err": 0.1}, scenario="fam.scn")
    outs = [C.evaluate_check(Check("max_penetration", max=0.001), r),
            C.evaluate_check(Check("max_penetration", max=0.01), r),
            C.evaluate_check(Check("err", max=1.0), r),
            C.evaluate_check(Check("err", max=1.0), r),
            C.evaluate_check(Check("err", max=1.0), result({"err": 0.1}, engine="pymunk", scenario="fam.scn"))]
    root = junit_xml(outs).getroot()
    names = [(s.get("name"), c.get("name")) for s in root.findall("testsuite") for c in s.findall("testcase")]
    assert names == [("mujoco", "fam.scn::max_penetration[<= 0.001]"), ("mujoco", "fam.scn::max_penetration[<= 0.01]"),
                     ("mujoco", "fam.scn::err[<= 1]"), ("mujoco", "fam.scn::err[<= 1]#2"),
                     ("pymunk", "fam.scn::err")]


def _spec_dir(tmp_path, text):
    d = tmp_path / "specs"
    d.mkdir(exist_ok=True)
    (d / "a.toml").write_text(text)
    return d


_BALL = """
[scenario]
family = "t"
title = "ball"
duration = 0.1
dt = 0.01
effects = ["gravity"]
[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
mass = 1.0
"""


def test_check_with_nothing_to_check_exits_5(tmp_path, capsys):
    """A check in which no check applies to anything exits 5 (as pytest) and
    says per scene why; no empty table."""
    d = _spec_dir(tmp_path, _BALL)
    (d / "b.toml").write_text(_BALL.replace('title = "ball"', 'title = "b"') +
                              '[[check]]\nmetric = "stable"\nequals = true\nengines = ["pybullet"]\n')
    code = C.check_main(["reference"], None, None, [str(d)], executor="inline", save_dir=tmp_path / "rows")
    err = capsys.readouterr().err
    assert code == C.NOTHING_CHECKED == 5
    assert "nothing to check: t.a: no [[check]] tables" in err
    assert "nothing to check: t.b: none of its 1 checks applies to engines reference (stable: engines ['pybullet'] only)" in err
    assert "conformance: checks per engine" not in err and not (tmp_path / "rows").exists()


def test_check_engine_names_are_validated(tmp_path):
    """A misspelt engine in a check's engines or xfail is a spec error (the
    scene is an ERROR in check, exit 2 in run); a name far from any engine
    here is taken as a plug-in not installed, and listed."""
    from physbench.harness.conformance.plan import engine_names_in_checks

    known = ["reference", "mujoco", "pybullet", "pymunk"]
    text = _BALL + ('[[check]]\nmetric = "stable"\nequals = true\nengines = ["mujocco", "mujoco_mjx"]\n'
                    '[[check]]\nmetric = "stable"\nequals = true\nxfail = { pybulet = "r", reference = "r" }\n')
    p = tmp_path / "c.toml"
    p.write_text(text)
    scene = load_scene(p)
    errors, absent = engine_names_in_checks(scene, "L", known)
    assert errors == [
        "L: check[0].engines: unknown engine 'mujocco'; did you mean 'mujoco'? (engines here: reference, mujoco, "
        "pybullet, pymunk)",
        "L: check[1].xfail.pybulet: unknown engine 'pybulet'; did you mean 'pybullet'? (engines here: reference, "
        "mujoco, pybullet, pymunk)"]
    assert absent == ["L: check[0].engines: engine 'mujoco_mjx' is not installed here (engines here: reference, "
                      "mujoco, pybullet, pymunk); its checks run only where it is"]
    # in a check: the scene does not run, every engine gets an ERROR naming the key path
    runs, errs = C.plan([str(p)], ["reference"])
    assert runs == [] and len(errs) == 1 and errs[0].outcome == C.ERROR
    assert "check[0].engines: unknown engine 'mujocco'; did you mean 'mujoco'?" in errs[0].message


def test_check_rows_carry_the_schema_version(tmp_path, monkeypatch):
    """check's Parquet has the schema_version column (the report reads it
    without a warning about the tool's own files)."""
    import pandas as pd

    from physbench.harness.report.loading import load_results
    from physbench.harness.results import SCHEMA_VERSION

    def fake_execute(spec):
        return result({"post_impact_velocity_error": 0.001, "linear_momentum_drift": 0.0, "max_penetration": 0.0,
                       "stable": True}, engine=spec.engine, scenario=spec.scenario, variant=spec.variant)

    monkeypatch.setattr(C, "execute", fake_execute)
    rows = tmp_path / "results" / "check"
    assert C.check_main(["good"], None, None, ["billiards.head_on"], executor="inline", save_dir=rows) == 0
    files = list(rows.glob("*.parquet"))
    assert len(files) == 1
    df = pd.read_parquet(files[0])
    assert (df["schema_version"] == SCHEMA_VERSION).all() and len(df) > 0
    assert not any("schema_version" in w for w in load_results(tmp_path / "results").attrs.get("warnings", []))
