"""The command line end to end, in subprocesses as a user runs it."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import HEAD_ON, ROOT

def _mjx_installed() -> bool:
    try:
        return importlib.util.find_spec("mujoco.mjx") is not None and importlib.util.find_spec("jax") is not None
    except ImportError:
        return False


#: the engines whose package is installed (rapier and box2d are extras: a
#: missing one is listed by `physbench engines` as unavailable)
ENGINES = ["reference", "mujoco", "pybullet", "pymunk"] + [
    e for e, mod in (("rapier", "rapier3d"), ("box2d", "pyb2d3"), ("drake", "pydrake"), ("mjx", "mujoco.mjx"))
    if importlib.util.find_spec(mod.split(".")[0]) is not None and (mod != "mujoco.mjx" or _mjx_installed())]
# metric names of DESIGN.md every run result carries
GENERIC = ["max_penetration", "mean_penetration", "energy_drift", "energy_gain", "linear_momentum_drift",
           "angular_momentum_drift", "stable", "cpu_s_per_sim_s", "wall_s_per_sim_s", "steps_per_s"]
COLLISION = ["post_impact_velocity_error", "trajectory_rmse", "final_position_error"]


def physbench(*args, check=False):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", *map(str, args)], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=300)
    if check:
        assert p.returncode == 0, p.stderr
    return p


@pytest.fixture(scope="module")
def head_on_runs():
    """`physbench run --json` of the head-on scene on every engine and
    variant: twelve independent subprocesses, run two at a time rather
    than one after another; each one's exit code, stdout and stderr."""
    from concurrent.futures import ThreadPoolExecutor

    keys = [(e, v) for e in ENGINES for v in (None, "elastic", "plastic")]

    def one(key):
        e, v = key
        p = physbench("run", HEAD_ON, "--engine", e, "--json", *(["--variant", v] if v else []))
        return p.returncode, p.stdout, p.stderr

    with ThreadPoolExecutor(max_workers=2) as pool:
        return dict(zip(keys, pool.map(one, keys)))


@pytest.mark.parametrize("engine", ENGINES)
def test_run_json_is_one_object_with_metric_names(head_on_runs, engine):
    for v in (None, "elastic", "plastic"):
        rc, stdout, stderr = head_on_runs[engine, v]
        lines = stdout.strip().splitlines()
        assert len(lines) == 1, f"stdout must be exactly one JSON object, got: {stdout[:300]!r}"
        d = json.loads(lines[0])
        # run evaluates the spec's checks: exit 1 exactly when one fails unexpectedly
        assert d["engine"] == engine and d["variant"] == v
        if d["status"] == "unsupported":  # Drake's discrete step cannot reach e = 0.9: said, never approximated
            assert d["message"] and all(c["outcome"] == "UNSUPPORTED" for c in d["checks"])
            assert rc == 1, stderr  # run exits 1 on any status but ok
            continue
        bad = [c for c in d["checks"] if c["outcome"] in ("FAIL", "XPASS", "ERROR")]
        assert rc == (1 if bad else 0), stderr
        assert d["status"] == "ok"
        for k in GENERIC + COLLISION:
            assert k in d, k
        assert isinstance(d["post_impact_velocity_error"], float)
        assert d["settings"]["dt"] == 0.001
        print(f"{engine:9s} {v or 'default':8s} post_impact_velocity_error {d['post_impact_velocity_error']:.3g} "
              f"max_penetration {d['max_penetration']:.3g}")


def test_reference_meets_newton_on_every_variant(head_on_runs):
    for v in (None, "elastic", "plastic"):
        d = json.loads(head_on_runs["reference", v][1])
        assert d["post_impact_velocity_error"] <= 1e-3
        assert d["linear_momentum_drift"] <= 1e-9
        assert d["max_penetration"] <= 0.002


def test_reference_stages_are_in_the_result(head_on_runs):
    d = json.loads(head_on_runs["reference", None][1])
    stages = d["stages"]
    assert "narrowphase" in stages and stages["narrowphase"]["calls"] > 0
    assert "gravity" not in stages  # the scene has no gravity effect


def test_no_contact_means_no_collision_stage(tmp_path):
    # without the effects their coefficients go too (a coefficient without
    # its effect is a spec error)
    text = HEAD_ON.read_text().replace('effects = ["contact", "restitution"]', "effects = []") \
        .replace("restitution = 0.9\n", "").replace('"material.default.restitution" = 1.0', "") \
        .replace('"material.default.restitution" = 0.0', "")
    p = tmp_path / "ghosts.toml"
    p.write_text(text)
    r = physbench("run", p, "--engine", "reference", "--json")
    d = json.loads(r.stdout)
    # the spec's penetration check has no metric without contact: an ERROR, exit 1
    pen = [c for c in d["checks"] if c["metric"] == "max_penetration"]
    assert r.returncode == 1 and d["status"] == "ok" and pen and pen[0]["outcome"] == "ERROR"
    assert pen[0]["message"].startswith("metric not computed")
    assert not any(k in d["stages"] for k in ("broadphase", "narrowphase", "solve", "ccd")), d["stages"]
    # the balls pass through each other: the cue keeps its speed
    assert d["status"] == "ok"


def test_bad_spec_exits_2_naming_file_and_key(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(HEAD_ON.read_text().replace("mass = 0.17\nposition = [0.3", "mass = -1\nposition = [0.3"))
    r = physbench("run", p, "--json")
    assert r.returncode == 2
    assert f"{p}: body[1].mass: must be > 0, got -1" in r.stderr
    assert r.stdout == ""


def test_set_engine_setting_and_spec_key():
    r = physbench("run", HEAD_ON, "-e", "reference", "--json", "--set", "dt=0.002",
                  "--set", "material.default.restitution=0.5", check=True)
    d = json.loads(r.stdout)
    assert d["settings"]["dt"] == 0.002
    assert d["post_impact_velocity_error"] <= 1e-3  # against e = 0.5
    r = physbench("run", HEAD_ON, "-e", "mujoco", "--set", "integrator=leapfrog")
    assert r.returncode == 2 and "integrator" in r.stderr and "expected one of" in r.stderr
    r = physbench("run", HEAD_ON, "-e", "pymunk", "--set", "wobble=3")
    assert r.returncode == 2 and "wobble" in r.stderr


def test_engines_lists_all_four():
    from physbench.adapters import ENGINES as ALL

    r = physbench("engines", "--json", check=True)
    caps = {c["engine"]: c for c in json.loads(r.stdout)}
    assert set(caps) == set(ALL) >= set(ENGINES)  # the optional engines are listed, installed or not
    for name, c in caps.items():
        assert c["version"] and "dt" in c["settings"]
        assert c["available"] == (name in ENGINES), name
    assert caps["pymunk"]["dimensions"] == 2 and caps["mujoco"]["dimensions"] == 3


def test_trace_writes_side_by_side_recording(tmp_path):
    from rerun.chunk import RrdReader

    out = tmp_path / "head_on.rrd"
    physbench("trace", HEAD_ON, "--engines", "reference", "pymunk", "-o", out, check=True)
    chunks = RrdReader(str(out)).stream().to_chunks()
    paths = {c.entity_path for c in chunks}
    for e in ("reference", "pymunk"):
        assert f"/world/{e}/cue" in paths and f"/world/{e}/object" in paths
        assert f"/metrics/{e}/energy" in paths
    # the cue's logged x at the last frame: Newton's law for e = 0.9 gives 0.1 m/s
    # after the impact at t = (0.3 - 2r) / 2
    cue = [c for c in chunks if c.entity_path == "/world/reference/cue" and not c.is_static]
    df = cue[0].to_record_batch().to_pandas()
    col = [c for c in df.columns if "translation" in c.lower()][0]
    x_last = float(np.concatenate([np.asarray(v, float).ravel() for v in df[col].iloc[-1]])[0])
    t_c = (0.3 - 2 * 0.028575) / 2.0
    assert x_last == pytest.approx(2.0 * t_c + 0.1 * (0.5 - t_c), abs=1e-5)


def test_sweep_then_report_from_the_command_line(tmp_path, capsys):
    """`physbench sweep --suite smoke` then `physbench report` on its output:
    both exit 0, the sweep's rows land under the given root, and the page is
    written where asked."""
    from physbench.harness.cli import main

    sweeps = tmp_path / "sweeps"
    assert main(["sweep", "--suite", "smoke", "--out", str(sweeps), "--no-resume"]) == 0
    files = list(sweeps.rglob("*.parquet"))
    assert files, "no sweep rows written"
    import pandas as pd

    df = pd.concat([pd.read_parquet(f) for f in files])
    assert set(df["status"]) == {"ok"} and len(df) == df["point_key"].nunique()
    out = tmp_path / "page.html"
    assert main(["report", "--results-dir", str(tmp_path), "--out", str(out)]) == 0
    html = out.read_text(encoding="utf-8")
    assert "billiards.head_on" in html and "data:image/png;base64," in html


def test_sweep_bad_suite_is_exit_2(tmp_path, capsys):
    from physbench.harness.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text('[suite]\nengines = ["warp"]\n[[sweep]]\nscenarios = ["billiards.head_on"]\n', encoding="utf-8")
    assert main(["sweep", "--suite", str(bad), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "engines" in err


def test_run_phase_reproduces_a_phase_sweep_point_and_refuses_non_free_flight():
    """pymunk's plate at 1/240 s tunnels as written and is caught a quarter
    step earlier (the sweep's phase 0.25 point); a resting stack cannot be
    phase-shifted: exit 2 naming why."""
    out = physbench("run", "tunnelling.thin_box_on_thin_floor", "--engine", "pymunk", "--json")
    assert json.loads(out.stdout)["tunnelled"] == 1.0
    out = physbench("run", "tunnelling.thin_box_on_thin_floor", "--engine", "pymunk", "--phase", "0.25", "--json")
    d = json.loads(out.stdout)
    assert d["tunnelled"] == 0.0 and any("step phase 0.25" in n for n in d["notes"])
    out = physbench("run", "stacking.column_5", "--phase", "0.5")
    assert out.returncode == 2
    assert "--phase 0.5: stacking.column_5: phase shift needs free flight" in out.stderr


def test_run_phase_bad_dt_and_saved_rows_carry_the_phase(tmp_path):
    # (dt=1/30 is a number: --set takes fractions, test_set_takes_fractions_and_engine_settings)
    out = physbench("run", "tunnelling.thin_box_on_thin_floor", "-e", "pymunk", "--phase", "0.5", "--set", "dt=fast")
    assert out.returncode == 2 and "expected a number of seconds" in out.stderr
    import pandas as pd
    f = tmp_path / "rows.parquet"
    # exit 1 when a check fails unexpectedly in this phase (an XPASS of the
    # phase-combined xfail): the row is saved either way
    p = physbench("run", "tunnelling.thin_box_on_thin_floor", "-e", "pymunk", "--phase", "0.25", "--save", f)
    assert p.returncode in (0, 1) and "Traceback" not in p.stderr
    physbench("run", "tunnelling.thin_box_on_thin_floor", "-e", "pymunk", "--save", f)
    assert sorted(pd.read_parquet(f)["phase"]) == [0.0, 0.25]


def test_a_closed_pipe_is_not_a_traceback():
    """`physbench list | head -0`: the reader has closed the pipe before the
    first line (closed here before the command starts, so the outcome does
    not depend on timing); the command stops quietly (exit 141, 128 +
    SIGPIPE), with no BrokenPipeError traceback on stderr."""
    r, w = os.pipe()
    os.close(r)
    try:
        proc = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "list"], cwd=ROOT, stdout=w,
                              stderr=subprocess.PIPE, timeout=300)
    finally:
        os.close(w)
    err = proc.stderr.decode()
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    assert proc.returncode == 141, (proc.returncode, err)


# --- issue 40: wider --set, legible tables


def test_set_takes_fractions_and_engine_settings(monkeypatch):
    """--set dt=1/240 is 1/240 s (as @dt=1/30 in a check); ENGINE:KEY=VALUE
    sets one engine's setting in check and trace, validated up front."""
    from physbench.harness import cli
    from physbench.harness.cli.common import UsageError, split_sets, engine_sets, set_value

    assert set_value("1/240") == 1 / 240 and set_value("1e-3") == 1e-3 and set_value("rk4") == "rk4"
    assert split_sets(["dt=1/240", "scenario.dt=1/60"], {"dt"}) == ({"dt": 1 / 240}, {"scenario.dt": 1 / 60})
    per, rest = engine_sets(["mujoco:impratio=10", "dt=1/240", "material.default.friction=0.3"], ["mujoco", "pymunk"])
    assert per == {"mujoco": {"impratio": 10.0, "dt": 1 / 240}, "pymunk": {"dt": 1 / 240}}
    assert rest == ["material.default.friction=0.3"]
    for bad, why in ((["pybullet:erp=0.2"], "engine 'pybullet' is not among the engines"),
                     (["impratio=10"], "not a setting of pymunk; give it per engine as ENGINE:impratio=VALUE"),
                     (["mujoco:wobble=1"], "not a setting of mujoco"),
                     (["mujoco:impratio=-1"], "mujoco:impratio")):
        with pytest.raises(UsageError, match=why):
            engine_sets(bad, ["mujoco", "pymunk"])
    # check hands them to its runs: the settings arrive in check_main
    seen = {}
    monkeypatch.setattr("physbench.harness.cli.jobs.check_main", lambda **kw: seen.update(kw) or 0)
    assert cli.main(["check", "billiards.head_on", "--engines", "mujoco", "pymunk", "--set", "mujoco:impratio=10"]) == 0
    assert seen["settings"] == {"mujoco": {"impratio": 10.0}}
    assert cli.main(["check", "billiards.head_on", "--set", "body[0].mass=2"]) == 2
    # the settings reach the runs' keys (and so their rows)
    from physbench.harness import conformance as C

    runs, _ = C.plan(["billiards.head_on"], ["mujoco", "pymunk"], settings={"mujoco": {"impratio": 10.0}})
    assert {r.engine: r.settings.get("impratio") for r in runs} == {"mujoco": 10.0, "pymunk": None}


def test_run_set_dt_fraction():
    r = physbench("run", HEAD_ON, "-e", "reference", "--json", "--set", "dt=1/240", check=True)
    assert json.loads(r.stdout)["settings"]["dt"] == 1 / 240


def test_tables_keep_names_whole_without_a_terminal(monkeypatch):
    """Printed to a log (no terminal): 160 columns (or COLUMNS), and the
    scenario and test-case names are never cut or wrapped."""
    from io import StringIO

    from physbench.harness import conformance as C
    from physbench.harness.console import LOG_WIDTH, console

    monkeypatch.delenv("COLUMNS", raising=False)
    assert console(file=StringIO()).width == LOG_WIDTH == 160
    monkeypatch.setenv("COLUMNS", "220")
    assert console(file=StringIO()).width == 220
    monkeypatch.delenv("COLUMNS")
    long_s = "friction.a_rather_long_scenario_name_that_a_ci_log_must_show_whole"
    outs = [C.Outcome(e, long_s, "variant_with_a_long_name", "bounce_ratio_error@dt=1/30", C.FAIL, 0.5, "<= 0.1",
                      "bounce_ratio_error = 0.5, expected <= 0.1 " + "and a long message " * 8)
            for e in ("reference", "mujoco", "pybullet", "pymunk", "rapier")]
    buf = StringIO()
    C.summarize(outs, console(file=buf))
    text = buf.getvalue()
    assert all(len(line) <= LOG_WIDTH for line in text.splitlines())
    assert long_s in text
    assert f"{long_s}[variant_with_a_long_name]::bounce_ratio_error@dt=1/30" in text


def test_validate_reports_without_stepping(tmp_path, monkeypatch):
    """physbench validate: the compiled scene, initial contacts, the model's
    predictions and which checks apply to which engines; no run (the
    runner is never called); exit 2 on a bad spec."""
    import physbench.harness.runner as runner
    from physbench.harness import cli

    def no_runs(*a, **k):
        raise AssertionError("validate must not step")

    monkeypatch.setattr(runner, "run", no_runs)
    spec = (ROOT / "scenarios" / "friction" / "ball_rolls.toml").read_text()
    spec += '\n[[check]]\nmetric = "max_penetration"\nmax = 0.001\nengines = ["mujoco", "genesis"]\nxfail = { mujoco = "m" }\n'
    p = tmp_path / "ball.toml"
    p.write_text(spec)
    r = physbench("validate", p, "--json", "--engines", "reference", "mujoco", "pymunk")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["steps"] == 480 and [b["name"] for b in d["bodies"]] == ["ball"]
    # the ball rests on the slope: touching, measured by the harness's geometry
    (c,) = d["initial_contacts"]
    assert c["state"] == "touching" and abs(c["overlap_m"]) < 1e-15 and "slope 'slope'" in c["b"]
    # the model's prediction, against the closed form a = 5/7 g sin 20
    import math

    assert d["predictions"]["roll_accel_ref"] == pytest.approx(5 / 7 * 9.81 * math.sin(math.radians(20)), rel=1e-12)
    assert d["predictions_text"]["regime"] == "roll"
    checks = {x["metric"]: x for x in d["checks"]}
    scenes = ["base", *d["variants"]]
    assert d["variants"] == ["angle_30", "small_ball"]
    assert checks["roll_accel_error"]["applies_to"] == {v: ["reference", "mujoco", "pymunk"] for v in scenes}
    assert checks["max_penetration"]["applies_to"] == {v: ["mujoco"] for v in scenes}
    assert checks["max_penetration"]["xfail"] == ["mujoco"]
    from physbench.adapters import engine_names

    assert d["not_installed"] == [f"{p}: check[4].engines: engine 'genesis' is not installed here (engines here: "
                                  f"{', '.join(engine_names())}); its checks run only where it is"]
    # the text report, in this process (the runner patched above never runs)
    assert cli.main(["validate", str(p)]) == 0
    # a bad spec is exit 2 with the errors, as for every command
    p.write_text(spec.replace('engines = ["mujoco", "genesis"]', 'engines = ["mujoco", "mujocco"]'))
    r = physbench("validate", p)
    assert r.returncode == 2 and "check[4].engines: unknown engine 'mujocco'; did you mean 'mujoco'?" in r.stderr
    r = physbench("run", p, "--engine", "pymunk")
    assert r.returncode == 2 and "unknown engine 'mujocco'" in r.stderr


def test_run_shows_the_models_predictions():
    """run --json carries the model's predictions beside the measured values."""
    r = physbench("run", HEAD_ON, "-e", "reference", "--json", check=True)
    d = json.loads(r.stdout)
    # Newton's law of restitution, e = 0.9, equal masses, 2 m/s onto a ball at rest
    post = d["predictions"]["post_impact_velocity_ref"]
    assert post["cue"] == pytest.approx([0.1, 0.0, 0.0], abs=1e-12)
    assert post["object"] == pytest.approx([1.9, 0.0, 0.0], abs=1e-12)
    assert d["predictions"]["impact_time_ref"] == pytest.approx((0.3 - 2 * 0.028575) / 2.0, rel=1e-12)
    assert "impact time" in d["predictions_text"]
    r = physbench("run", ROOT / "scenarios" / "friction" / "ball_rolls.toml", "-e", "reference", check=True)
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("│ roll_accel "))
    assert line.count("2.39658") == 2  # measured and predicted, side by side
