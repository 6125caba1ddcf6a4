"""Known limitations hold for the engine versions they were measured on
(contract/xfail.py): inside the range an xfail is an xfail, outside it the
check is a plain check whose verdict names the version the limitation was
measured on.  Engine versions here are fakes on each side of a range."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from physbench.contract.scene import Check, load_scene
from physbench.contract.spec import SpecError
from physbench.contract.xfail import MEASURED_ON, Xfail, default_range, shipped_xfails, xfail_for
from physbench.harness import conformance as C
from physbench.harness.runner import RunResult

ROOT = Path(__file__).resolve().parent.parent
HEAD_ON = ROOT / "tests" / "data" / "head_on.toml"


def result(value: float, version: str, engine: str = "mujoco", status: str = "ok") -> RunResult:
    return RunResult(scenario="fam.scn", variant=None, engine=engine, engine_version=version, status=status,
                     message="boom" if status != "ok" else "", settings={}, metrics={"err": value})


def test_default_range_is_the_same_major_minor():
    assert default_range("4.0.0") == ">=4.0,<4.1"
    assert default_range("3.2.7") == ">=3.2,<3.3"
    assert Xfail("r", "7.3.1").range == ">=7.3,<7.4"
    assert Xfail("r", "7.3.1", ">=7,<9").range == ">=7,<9"


@pytest.mark.parametrize("version, inside", [
    ("4.0.0", True), ("4.0.9", True), ("4.0.1rc1", True),  # a release candidate of a patch release of 4.0
    ("4.1.0", False), ("3.9.9", False), ("4.1.0.dev1", False), ("5.0", False),
])
def test_a_measured_xfail_applies_within_its_major_minor_only(version, inside):
    check = Check("err", max=0.01, xfail={"mujoco": Xfail("soft contacts: measured 0.05", "4.0.0")})
    failing = C.evaluate_check(check, result(0.05, version))
    passing = C.evaluate_check(check, result(0.001, version))
    if inside:
        assert failing.outcome == C.XFAIL and failing.message.startswith("xfail: soft contacts: measured 0.05")
        assert passing.outcome == C.XPASS
    else:
        assert failing.outcome == C.FAIL and passing.outcome == C.PASS
        for o in (failing, passing):
            assert "measured on mujoco 4.0.0" in o.message and f"mujoco {version}" in o.message
            assert ">=4.0,<4.1" in o.message and "soft contacts: measured 0.05" in o.message


def test_a_declared_range_widens_or_narrows_the_default():
    check = Check("err", max=0.01, xfail={"mujoco": Xfail("known", "4.0.0", ">=4.0,<4.2")})
    assert C.evaluate_check(check, result(0.05, "4.1.5")).outcome == C.XFAIL
    assert C.evaluate_check(check, result(0.05, "4.2.0")).outcome == C.FAIL
    narrow = Check("err", max=0.01, xfail={"mujoco": Xfail("known", "4.0.0", "==4.0.0")})
    assert C.evaluate_check(narrow, result(0.05, "4.0.0")).outcome == C.XFAIL
    assert C.evaluate_check(narrow, result(0.05, "4.0.1")).outcome == C.FAIL


def test_a_plain_string_was_measured_on_the_recorded_version():
    """The shipped scenarios' plain-string xfails were measured on
    MEASURED_ON's version of each engine."""
    check = Check("err", max=0.01, xfail={"mujoco": "soft contacts"})
    measured = MEASURED_ON["mujoco"]
    major, minor = (int(x) for x in measured.split(".")[:2])
    assert C.evaluate_check(check, result(0.05, measured)).outcome == C.XFAIL
    outside = C.evaluate_check(check, result(0.05, f"{major}.{minor + 1}.0"))
    assert outside.outcome == C.FAIL and f"measured on mujoco {measured}" in outside.message
    # an engine with no recorded version (a plug-in): the reason holds for every version
    plug = Check("err", max=0.01, xfail={"myengine": "known"})
    assert C.evaluate_check(plug, result(0.05, "0.0.1", engine="myengine")).outcome == C.XFAIL
    assert xfail_for({"myengine": "known"}, "myengine", "99.0") == ("known", "")


def test_a_run_error_outside_the_range_is_an_error():
    check = Check("err", max=0.01, xfail={"mujoco": Xfail("blows up", "4.0.0")})
    assert C.evaluate_check(check, result(0.0, "4.0.2", status="error")).outcome == C.XFAIL
    o = C.evaluate_check(check, result(0.0, "4.1.0", status="error"))
    assert o.outcome == C.ERROR and "measured on mujoco 4.0.0" in o.message


def test_step_phases_follow_the_version_rule():
    check = Check("err", max=0.01, xfail={"mujoco": Xfail("no CCD", "4.0.0")})
    for version, expected in (("4.0.0", C.XFAIL), ("4.1.0", C.FAIL)):
        per = [C.evaluate_check(check, result(v, version)) for v in (0.001, 0.05)]
        assert C.verdicts.combine_phases(per, check).outcome == expected


def _spec_with_xfail(tmp_path: Path, xfail_toml: str) -> Path:
    text = HEAD_ON.read_text(encoding="utf-8").replace(
        'metric = "max_penetration"\nmax = 0.002\n', f'metric = "max_penetration"\nmax = 0.002\nxfail = {xfail_toml}\n')
    assert xfail_toml in text
    p = tmp_path / "head_on_x.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_the_table_form_loads_and_bad_ranges_are_spec_errors(tmp_path):
    p = _spec_with_xfail(tmp_path, '{ mujoco = { reason = "soft", measured_on = "4.0.0", versions = ">=4.0,<4.3" }, '
                                   'pymunk = "discrete" }')
    check = [c for c in load_scene(p).checks if c.metric == "max_penetration"][0]
    assert check.xfail["mujoco"] == Xfail("soft", "4.0.0", ">=4.0,<4.3")
    assert check.xfail["pymunk"] == Xfail("discrete", MEASURED_ON["pymunk"])
    for bad, why in (('{ mujoco = { reason = "soft", versions = "four" } }', "versions"),
                     ('{ mujoco = { reason = "soft", measured_on = "latest" } }', "measured_on"),
                     ('{ mujoco = { measured_on = "4.0.0" } }', "reason"),
                     ('{ mujoco = { reason = "soft", measure_on = "4.0.0" } }', "measure_on")):
        with pytest.raises(SpecError) as e:
            load_scene(_spec_with_xfail(tmp_path, bad))
        text = "\n".join(e.value.errors)
        assert "check[2].xfail.mujoco" in text and why in text, text


def test_engines_says_whether_each_version_is_inside_the_shipped_ranges(capsys):
    from physbench.harness.cli import main

    shipped = shipped_xfails()
    assert set(shipped) >= {"mujoco", "pybullet", "pymunk"}
    for engine, ranges in shipped.items():
        if engine not in MEASURED_ON:  # no recorded version (the reference engine's own): any version
            continue
        assert (MEASURED_ON[engine], default_range(MEASURED_ON[engine])) in ranges
    assert main(["engines", "--json"]) == 0
    rows = {r["engine"]: r for r in json.loads(capsys.readouterr().out)}
    for engine in ("mujoco", "pybullet", "pymunk"):
        installed = rows[engine]["version"]
        inside = Xfail("", MEASURED_ON[engine]).covers(installed)
        assert rows[engine]["xfail_ranges"].endswith("inside" if inside else "OUTSIDE: run as plain checks")
        assert f"measured on {MEASURED_ON[engine]}" in rows[engine]["xfail_ranges"]
        assert rows[engine]["origin"] == "physbench"
