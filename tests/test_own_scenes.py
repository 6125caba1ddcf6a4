"""A user's own scenes, end to end (issue: checks anywhere, no silent ok):
``run`` evaluates the spec's checks; ``check`` and ``sweep`` take spec files
and folders outside scenarios/; a metric that fails makes the run an error;
the scene's content hash keys points and splits history series.  Every file
written goes under tmp_path."""

from __future__ import annotations

import json
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
import pytest

from physbench.harness import conformance as C
from physbench.harness import report as rp
from physbench.harness import suite as SU, sweep as S, sweep_store as ST
from physbench.harness.results import write_rows
from physbench.contract.scene import load_scene
from tests.test_cli import physbench

ROOT = Path(__file__).resolve().parent.parent

# a box sliding on a plane (pybullet: fast, and its contact always sinks
# ~0.6 mm, so a 1e-12 m penetration bound fails for certain)
BOX = """
[scenario]
family = "friction"
title = "box slides to a stop"
duration = {duration}
dt = 0.002
effects = ["gravity", "contact", "friction"]
primary_metric = "max_penetration"

[material.default]
friction = {friction}

[[body]]
name = "box"
shape = "box"
half_extents = [0.1, 0.1, 0.1]
mass = 1.0
position = [0.0, 0.0, 0.1]
velocity = [1.0, 0.0, 0.0]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]

[[check]]
metric = "stable"
equals = true

[[check]]
metric = "max_penetration"
max = {max_pen}
"""


def write_box(path: Path, friction: float = 0.5, max_pen: float = 1e-12, duration: float = 0.2) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(BOX.format(friction=friction, max_pen=max_pen, duration=duration))
    return path


# ---------------------------------------------------------------------------
# run evaluates the checks


def test_run_on_a_failing_check_exits_1_and_shows_the_check(tmp_path):
    spec = write_box(tmp_path / "my_scenes" / "box_slide.toml")
    p = physbench("run", spec, "--engine", "pybullet", "--json")
    assert p.returncode == 1, p.stderr
    d = json.loads(p.stdout)
    assert d["status"] == "ok"  # the run itself is fine: the verdict is the check's
    by = {c["metric"]: c for c in d["checks"]}
    assert by["stable"]["outcome"] == "PASS"
    pen = by["max_penetration"]
    assert pen["outcome"] == "FAIL" and pen["threshold"] == "<= 1e-12" and pen["value"] > 1e-12
    assert pen["value"] == d["max_penetration"] and "expected <= 1e-12" in pen["message"]
    # the table shows it too
    p = physbench("run", spec, "--engine", "pybullet")
    assert p.returncode == 1
    assert "max_penetration" in p.stdout and "FAIL" in p.stdout and "<= 1e-12" in p.stdout
    # the same spec with a bound pybullet meets: exit 0
    write_box(spec, max_pen=0.05)
    p = physbench("run", spec, "--engine", "pybullet", "--json")
    assert p.returncode == 0, p.stderr
    assert {c["outcome"] for c in json.loads(p.stdout)["checks"]} == {"PASS"}


def test_run_makes_the_runs_a_check_needs_as_check_does(tmp_path):
    """A check at another dt (and the hard tag's implicit ones) runs the
    extra run, with the user's settings and overrides under it."""
    spec = write_box(tmp_path / "box.toml", max_pen=0.05)
    text = spec.read_text().replace('primary_metric = "max_penetration"',
                                    'primary_metric = "max_penetration"\ntags = ["hard"]')
    text += '\n[[check]]\nmetric = "max_penetration@dt=1/30"\nmax = 1e-12\n'
    spec.write_text(text)
    p = physbench("run", spec, "--engine", "pybullet", "--json", "--set", "iterations=20")
    assert p.returncode == 1, p.stderr
    by = {c["metric"]: c for c in json.loads(p.stdout)["checks"]}
    assert set(by) == {"stable", "max_penetration", "max_penetration@dt=1/30", "stable@dt=1/30"}
    assert by["max_penetration@dt=1/30"]["outcome"] == "FAIL" and by["max_penetration@dt=1/30"]["value"] > 0
    assert by["max_penetration"]["outcome"] == "PASS"
    # the verdicts are check's: the same evaluation on the same runs
    sc = load_scene(spec)
    runs = C.scene_runs(sc, "pybullet", {"iterations": 20})
    assert [r.settings for r in runs] == [{"iterations": 20}, {"iterations": 20, "dt": pytest.approx(1 / 30)}]


# ---------------------------------------------------------------------------
# check and sweep on files and folders outside scenarios/


def test_check_runs_a_spec_file_and_a_folder_from_anywhere(tmp_path):
    mine = tmp_path / "my_scenes"
    write_box(mine / "box_slide.toml")
    write_box(mine / "sub" / "box_slow.toml", friction=0.3, max_pen=0.05)
    junit = tmp_path / "j.xml"
    # one file (this errored on every check before: no scenario with this id)
    code = C.check_main(["pybullet"], None, str(junit), [str(mine / "box_slide.toml")], save_dir=tmp_path / "rows")
    assert code == 1  # its penetration check fails on pybullet
    cases = {tc.get("name"): tc for tc in ET.parse(junit).getroot().iter("testcase")}
    assert set(cases) == {"friction.box_slide::stable", "friction.box_slide::max_penetration"}
    assert cases["friction.box_slide::max_penetration"].find("failure") is not None
    # a folder: every spec below it, ids family.stem
    code = C.check_main(["pybullet", "pymunk"], None, str(junit), [str(mine)], save_dir=tmp_path / "rows")
    assert code == 1
    names = {(tc.get("classname"), tc.get("name")) for tc in ET.parse(junit).getroot().iter("testcase")}
    assert ("physbench.pybullet.friction", "friction.box_slow::max_penetration") in names
    assert ("physbench.pymunk.friction", "friction.box_slide::stable") in names  # unsupported (3D): skipped
    # rows carry the path, the content hash, the primary threshold and the verdicts
    df = pd.concat([pd.read_parquet(f) for f in sorted((tmp_path / "rows").glob("*.parquet"))])
    r = df[(df["scenario"] == "friction.box_slow") & (df["engine"] == "pybullet")].iloc[0]
    assert r["scene_path"] == str((mine / "sub" / "box_slow.toml").resolve())
    assert r["scene_hash"] == load_scene(mine / "sub" / "box_slow.toml").content_hash
    assert r["primary_threshold"] == 0.05
    outs = {o["metric"]: o["outcome"] for o in json.loads(r["checks"])}
    assert outs == {"stable": "PASS", "max_penetration": "PASS"}


def test_check_runs_a_relative_spec_path_in_worker_processes(tmp_path, monkeypatch):
    # `physbench check ../shared/examples/head_on.toml` errored on every
    # check ("no such file"): the worker processes run in their own
    # directory and were handed the path as typed
    write_box(tmp_path / "mine" / "box_slide.toml", max_pen=0.05)
    monkeypatch.chdir(tmp_path / "mine")
    junit = tmp_path / "j.xml"
    code = C.check_main(["pybullet"], None, str(junit), ["../mine/box_slide.toml"], jobs=1, executor="process",
                        save_dir=tmp_path / "rows")
    cases = {tc.get("name"): tc for tc in ET.parse(junit).getroot().iter("testcase")}
    assert set(cases) == {"friction.box_slide::stable", "friction.box_slide::max_penetration"}
    assert all(tc.find("error") is None for tc in cases.values()), ET.tostring(ET.parse(junit).getroot())[:600]
    assert code == 0


def test_check_from_the_command_line_takes_paths_and_refuses_unknown_ids(tmp_path):
    write_box(tmp_path / "my_scenes" / "box_slide.toml", max_pen=0.05)
    p = physbench("check", "--scenarios", "friction.no_such_scene", "--engines", "pybullet")
    assert p.returncode == 2 and "friction.no_such_scene" in p.stderr and "Traceback" not in p.stderr
    p = physbench("check", tmp_path / "nowhere.toml", "--engines", "pybullet")
    assert p.returncode == 2 and "no such spec file" in p.stderr
    p = physbench("check", tmp_path / "empty_dir_that_is_not_there/", "--engines", "pybullet")
    assert p.returncode == 2
    # two files with one id (family.stem) cannot be told apart in rows
    write_box(tmp_path / "other" / "box_slide.toml")
    p = physbench("check", tmp_path / "my_scenes", tmp_path / "other", "--engines", "pybullet")
    assert p.returncode == 2 and "friction.box_slide" in p.stderr and "rename" in p.stderr


def test_sweep_runs_files_and_folders_named_relative_to_the_suite(tmp_path):
    mine = tmp_path / "my_scenes"
    write_box(mine / "box_slide.toml", max_pen=0.05)
    write_box(mine / "more" / "box_b.toml", friction=0.3)
    (tmp_path / "suites").mkdir()
    suite = tmp_path / "suites" / "mine.toml"
    suite.write_text(textwrap.dedent("""
        [suite]
        engines = ["pybullet"]
        repeats = 1
        [[sweep]]
        scenarios = ["../my_scenes/box_slide.toml", "../my_scenes/more/", "billiards.head_on"]
        grid = { dt = [0.002, 0.004] }
    """))
    pts = SU.expand(SU.load_suite(suite))
    assert sorted({(p.scenario, p.path is not None) for p in pts}) == [
        ("billiards.head_on", False), ("friction.box_b", True), ("friction.box_slide", True)]
    h = load_scene(mine / "box_slide.toml").content_hash
    assert [p.key for p in pts if p.scenario == "friction.box_slide"] == [
        f'friction.box_slide|pybullet|{{"dt":0.002}}|{h}', f'friction.box_slide|pybullet|{{"dt":0.004}}|{h}']
    out = tmp_path / "out"
    assert S.sweep_main(str(suite), out_dir=out) == 0
    df = ST.read_sweeps(out)
    assert len(df) == 6 and set(df["status"]) == {"ok"}
    box = df[df["scenario"] == "friction.box_slide"]
    assert set(box["scene_hash"]) == {h} and set(box["primary_threshold"]) == {0.05}
    assert all(json.loads(c)[0]["outcome"] in ("PASS", "FAIL") for c in box["checks"])
    # a suite naming a file that is not there: exit 2 naming the entry
    suite.write_text(suite.read_text().replace("../my_scenes/box_slide.toml", "../my_scenes/nope.toml"))
    assert S.sweep_main(str(suite), out_dir=out) == 2


# ---------------------------------------------------------------------------
# no ok without its metrics


def test_metric_exception_makes_the_run_an_error(tmp_path, monkeypatch):
    from physbench.harness import runner
    from physbench.harness.runner import run

    def broken(scene, trace, dt=None, model=True, pen=None):
        return 1.0 / 0.0

    monkeypatch.setattr(runner, "_metrics", broken)  # harness.metrics.compute_metrics as the runner calls it
    r = run(load_scene(write_box(tmp_path / "box.toml", max_pen=0.05)), "pybullet")
    assert r.status == "error" and r.message.startswith("metrics failed: ZeroDivisionError")
    outs = C.evaluate(load_scene(tmp_path / "box.toml"), r)
    assert {o.outcome for o in outs} == {C.ERROR}


# ---------------------------------------------------------------------------
# scene content hash and history


def test_content_hash_is_the_scene_not_the_file(tmp_path):
    a = write_box(tmp_path / "a" / "box.toml")
    b = tmp_path / "b" / "renamed.toml"
    b.parent.mkdir()
    b.write_text("# a comment and another layout\n" + a.read_text().replace("[[check]]\nmetric = \"stable\"\n"
                                                                               "equals = true\n", ""))
    ha, hb = load_scene(a).content_hash, load_scene(b).content_hash
    assert len(ha) == 16 and ha == hb  # path, name, comments and checks are not content
    assert load_scene(a, overrides={"material.default.friction": 0.3}).content_hash != ha
    assert load_scene(write_box(tmp_path / "c.toml", friction=0.3)).content_hash != ha
    assert load_scene(a, overrides={"scenario.dt": 0.001}).content_hash != ha
    # a step-phase shift keeps the hash of the scene as written
    from physbench.contract.phase import shift_scene

    drop = load_scene("tunnelling.thin_box_on_thin_floor")
    assert shift_scene(drop, 0.5).content_hash == drop.content_hash


def _sweep_row(sweep_id: str, scene_hash: str, error: float) -> dict:
    series = 'friction.box_slide|pybullet|{"dt":0.002}'
    return {"scenario": "friction.box_slide", "variant": None, "engine": "pybullet", "engine_version": "3",
            "status": "ok", "message": "", "cpu_s_per_sim_s": 0.1, "stable": True, "max_penetration": error,
            "setting.dt": 0.002, "commit": "c", "timestamp": f"2026-11-{sweep_id[6:8]}T01:00:00+00:00",
            "suite": "mine", "sweep_id": sweep_id, "point_key": f"{series}|{scene_hash}" if scene_hash else series,
            "point_settings": '{"dt":0.002}', "primary_metric": "max_penetration", "primary_error": error,
            "cpu_s_per_sim_s_median": 0.1, "cpu_s_per_sim_s_min": 0.099, "repeats": 3,
            "scene_hash": scene_hash, "scene_path": "/elsewhere/box_slide.toml"}


def _write(root: Path, rows: list[dict]) -> None:
    for r in rows:
        write_rows([r], root / "sweeps" / "m1" / "mine" / f"{r['sweep_id']}.parquet", append=False)


def test_changed_scene_starts_a_new_series_not_a_regression(tmp_path, capsys):
    """friction 0.5 -> 0.3 in a scene outside scenarios/, swept again: the
    error grew 73 %, but the scene changed, so the report starts a new
    series and says so instead of flagging a regression."""
    _write(tmp_path, [_sweep_row("20261120T010000Z-c", "aaaa000000000000", 1.0e-3),
                      _sweep_row("20261121T010000Z-c", "aaaa000000000000", 1.0e-3),
                      _sweep_row("20261122T010000Z-c", "bbbb000000000000", 1.73e-3)])
    df = rp.load_results(tmp_path)
    assert rp.regressions(df).empty
    assert rp.history(df) == {}  # the new content has one sweep only
    ch = rp.scene_changes(df)
    assert len(ch) == 1 and ch.iloc[0]["date"] == "2026-11-22" and ch.iloc[0]["points"] == 1
    line = rp.scene_change_lines(ch)[0]
    assert line.startswith("friction.box_slide: scene changed on 2026-11-22") and "new series" in line
    assert rp.report_main(results_dir=tmp_path, out=tmp_path / "r.html") == 0
    out = capsys.readouterr().out
    assert "scene changed on 2026-11-22" in out and "regression" not in out
    assert "scene changed on 2026-11-22" in (tmp_path / "r.html").read_text()
    # the same content again: one series of two, and the 73 % is flagged
    _write(tmp_path, [_sweep_row("20261123T010000Z-c", "bbbb000000000000", 3.0e-3)])
    reg = rp.regressions(rp.load_results(tmp_path))
    assert list(reg["kind"]) == ["accuracy"] and reg.iloc[0]["direction"] == "regression"
    assert reg.iloc[0]["previous_sweep"] == "20261122T010000Z-c"  # never the old content's sweeps


def test_report_reads_thresholds_from_rows_not_scenarios(tmp_path, monkeypatch):
    """Rows of a file outside scenarios/ carry their threshold: the report
    needs no scene to reload (the path recorded no longer exists)."""
    import physbench.contract.scene
    from physbench import contract

    monkeypatch.setattr(contract.scene, "load_scene", lambda *a, **k: pytest.fail("the report reloaded a scene"))
    rows = [dict(_sweep_row("20261120T010000Z-c", "aaaa000000000000", 1e-3), primary_threshold=2e-3,
                 checks=json.dumps([{"metric": "max_penetration", "outcome": "PASS"}]))]
    _write(tmp_path, rows)
    wp = rp.work_precision(rp.load_results(tmp_path))
    assert wp["friction.box_slide", ""]["threshold"] == 2e-3
    assert wp["friction.box_slide", ""]["threshold_source"] == "check max"


def test_trace_takes_a_spec_file_from_anywhere(tmp_path):
    spec = write_box(tmp_path / "my_scenes" / "box_slide.toml", max_pen=0.05)
    out = tmp_path / "box.rrd"
    p = physbench("trace", spec, "--engines", "pybullet", "-o", out)
    assert p.returncode == 0, p.stderr
    assert out.stat().st_size > 0 and "pybullet: ok" in p.stderr
    p = physbench("trace", tmp_path / "my_scenes" / "nope.toml", "--engines", "pybullet", "-o", out)
    assert p.returncode == 2 and "nope.toml" in p.stderr
