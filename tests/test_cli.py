"""The command line end to end, in subprocesses as a user runs it."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import HEAD_ON, ROOT

ENGINES = ["reference", "mujoco", "pybullet", "pymunk"]
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
        bad = [c for c in d["checks"] if c["outcome"] in ("FAIL", "XPASS", "ERROR")]
        assert rc == (1 if bad else 0), stderr
        assert d["status"] == "ok" and d["engine"] == engine and d["variant"] == v
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
    assert set(caps) == set(ALL) >= set(ENGINES)  # the optional drake and mjx are listed, installed or not
    for c in (caps[e] for e in ENGINES):
        assert c["available"] and c["version"] and "dt" in c["settings"]
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
    out = physbench("run", "tunnelling.thin_box_on_thin_floor", "-e", "pymunk", "--phase", "0.5", "--set", "dt=1/30")
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
