"""``physbench sweep``: suite validation (messages naming file and key path),
expansion, the row contract, storage (parts, consolidation, manifest),
resume after a kill (no duplicates, no lost points, finished points not
rerun), failures as statuses, worker crashes, and process vs serial
executors giving the same metrics.  No wall-clock assertions."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

import pandas as pd
import pyarrow.parquet as pq
import pytest

from physbench.adapters.base import Adapter, Capabilities, DT_SETTING, Setting, engine_names, register
from physbench.harness import points as P, suite as SU, sweep as S, sweep_store as ST
from physbench.harness.results import SCHEMA_VERSION, write_json_atomic, write_parquet_atomic
from physbench.harness.runner import run as _REAL_RUN
from physbench.contract.scene import load_scene
from physbench.contract.spec import SpecError

ROOT = Path(__file__).resolve().parent.parent

# the row contract: RunResult.row()'s identity and status, plus the sweep columns
CONTRACT = ("scenario", "variant", "engine", "engine_version", "status", "message", "commit", "timestamp",
            "setting.dt", "suite", "sweep_id", "point_key", "point_settings", "primary_metric", "primary_error",
            "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min", "repeats", "schema_version", "machine_id",
            "sweep_jobs", "point_wall_s")
# columns that hold times (they differ between any two runs)
TIMING = {"cpu_s_per_sim_s", "wall_s_per_sim_s", "steps_per_s", "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min",
          "point_wall_s", "sweep_jobs"}


class FakeSweep(Adapter):
    """Free flight; misbehaves on request (setting ``fault``); ``sleep_s``
    seconds of sleep at build (for the kill test)."""

    name = "fake_sweep"

    @classmethod
    def capabilities(cls):
        return Capabilities("fake_sweep", "1", 3, frozenset({"sphere", "box"}), frozenset({"plane"}),
                            frozenset({"contact", "restitution"}),
                            {"dt": DT_SETTING,
                             "fault": Setting("fault", "none", str, "",
                                              choices=("none", "build", "step", "nan", "crash")),
                             "sleep_s": Setting("sleep_s", 0.0, float, "", lo=0.0, hi=10.0)})

    def build(self, scene, settings):
        self.fault = settings["fault"]
        if self.fault == "build":
            raise RuntimeError("model rejected")
        if self.fault == "crash":
            if os.environ.get("PHYSBENCH_WORKER") != "1":  # never kill the test process itself
                raise RuntimeError("crash requested in the main process")
            os.kill(os.getpid(), signal.SIGKILL)  # like a segfault inside an engine
        time.sleep(settings["sleep_s"])
        self.dt = settings["dt"]
        self.x, self.q, self.v, self.w = (a.copy() for a in scene.initial_state())
        self.k = 0

    def step(self, n=1):
        for _ in range(n):
            self.k += 1
            if self.fault == "step" and self.k == 300:
                raise FloatingPointError("solver exploded")
            if self.fault == "nan" and self.k == 400:
                self.v[:] = np.nan
            self.x += self.v * self.dt

    def read_state(self, pos, quat, vel, angvel):
        pos[...] = self.x
        quat[...] = self.q
        vel[...] = self.v
        angvel[...] = self.w


@pytest.fixture(autouse=True, scope="module")
def _fake_engine():
    from physbench.adapters import base

    register("fake_sweep", lambda: FakeSweep)
    yield
    base._REGISTRY.pop("fake_sweep", None)


def write(tmp_path: Path, text: str, name: str = "suite.toml") -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def errors_of(path: Path) -> list[str]:
    with pytest.raises(ST.SuiteError) as e:
        SU.load_suite(path)
    return e.value.errors


def consolidated(out: Path) -> tuple[pd.DataFrame, dict]:
    files = list(out.glob("*/*/*.parquet"))
    assert len(files) == 1, files
    return pd.read_parquet(files[0]), json.loads(files[0].with_suffix(".manifest.json").read_text())


def stored_rows(d: Path) -> int:
    """Rows in the parts under ``d`` (a part holds one or more rows)."""
    return sum(pq.read_metadata(p).num_rows for p in d.glob("**/part-*.parquet"))


def kill_after_parts(script: str, out: Path, rows: int, cwd: Path, deadline_s: float) -> pd.DataFrame:
    """Run ``script`` (a sweep) in a fresh interpreter, SIGKILL it once
    ``rows`` point rows are stored in parts under ``out`` (or after
    ``deadline_s``), and return the stored rows indexed by point key."""
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + deadline_s
        while stored_rows(out) < rows and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    return pd.concat([pd.read_parquet(f) for f in out.glob("*/*/*/part-*.parquet")]).set_index("point_key")


@pytest.fixture(scope="module")
def smoke_serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("smoke_serial")
    assert S.sweep_main("smoke", out_dir=out, executor="serial") == 0
    return out


# ---------------------------------------------------------------------------
# suites: loading and validation


def test_shipped_suites_load():
    smoke = SU.load_suite("smoke")
    assert smoke.name == "smoke" and smoke.path == ROOT / "suites" / "smoke.toml"
    assert len(SU.expand(smoke)) == 6
    nightly = SU.load_suite(ROOT / "suites" / "nightly.toml")
    pts = SU.expand(nightly)
    assert {p.engine for p in pts} == {"reference", "mujoco", "pybullet", "pymunk", "rapier", "box2d", "drake", "mjx"}
    assert len({p.key for p in pts}) == len(pts)
    # every nightly scenario has an analytic primary metric
    from physbench.contract.scene import load_scene

    for sid in {p.scenario for p in pts}:
        assert load_scene(sid).primary_metric and load_scene(sid).reference_model


def test_checking_the_nightly_does_not_import_scipy_special(tmp_path):
    """The suite check builds each scene's reference model, to refuse a scene
    its model cannot model; the pendulum model computes its elliptic
    integrals (scipy.special, 0.16 s of the client's CPU to import) on first
    use, after its refusals, so checking the nightly -- a pendulum among its
    scenes -- imports no scipy.special in a fresh process."""
    code = ("import sys\n"
            "from physbench.harness.suite import load_suite\n"
            "from physbench.harness.points import cached_scene\n"
            "s = load_suite('nightly')\n"
            "print(sorted({cached_scene(e.scenario, e.variant).reference_model\n"
            "              for b in s.sweeps for e in b.scenarios}))\n"
            "print('scipy.special' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    models, imported = out.stdout.strip().splitlines()[-2:]
    assert "'pendulum'" in models
    assert imported == "False"


def test_a_pendulum_model_refuses_as_before_and_computes_its_period_on_first_use():
    """The pendulum's refusals come before its elliptic integrals; its
    period is 4 K(k^2) / wn, K computed here by the arithmetic-geometric
    mean (K(m) = pi / (2 AGM(1, sqrt(1 - m))))."""
    from physbench.contract.models import get_model

    scene = load_scene("joints.pendulum")
    model = get_model("pendulum")(scene)
    assert "_elliptic" not in vars(model)  # not computed by the constructor
    a, b = 1.0, math.sqrt(1.0 - model.m)
    for _ in range(40):
        a, b = (a + b) / 2.0, math.sqrt(a * b)
    assert model.T == pytest.approx(4.0 * (math.pi / (2.0 * a)) / model.wn, rel=1e-12)
    # the refusal still comes at load, as a spec error naming the key (the suite check's message)
    with pytest.raises(SpecError, match=r"body\[0\].position: model 'pendulum' cannot model this scene: "
                                        r".*never swings"):
        load_scene("joints.pendulum", overrides={"body[0].position": [0.0, 0.0, 1.0]})


def test_cached_spec_loads_a_changed_file_afresh(tmp_path):
    f = tmp_path / "spec.toml"
    text = (ROOT / "scenarios" / "billiards" / "head_on.toml").read_text()
    f.write_text(text)
    a = P.cached_spec(f)
    assert P.cached_spec(f) is a  # same bytes: parsed once
    f.write_text(text.replace("restitution = 0.9", "restitution = 0.8"))  # same size, other content
    b = P.cached_spec(f)
    assert b is not a and b.raw != a.raw
    f.write_text(text.replace("restitution = 0.9", "restitution = 1.9"))
    msgs = []
    for _ in range(2):  # a file that does not load raises every time, with the same message
        with pytest.raises(SpecError) as e:
            P.cached_spec(f)
        msgs.append(e.value.errors)
    assert msgs[0] == msgs[1] and "restitution" in " ".join(msgs[0])
    f.unlink()
    with pytest.raises(SpecError, match="no such file"):
        P.cached_spec(f)


def test_a_suite_check_parses_each_spec_file_once(monkeypatch):
    """Checking the nightly (sweep blocks, scenes, record sizes, the
    searches' scenes at both ends of their ranges) reads each spec file once."""
    import physbench.contract.scene as CS

    real = P.load_spec
    counts: dict[str, int] = {}

    def counted(path):
        counts[str(Path(path).resolve())] = counts.get(str(Path(path).resolve()), 0) + 1
        return real(path)

    monkeypatch.setattr(P, "load_spec", counted)
    monkeypatch.setattr(CS, "load_spec", counted)
    monkeypatch.setattr(P, "_SPECS", {})
    P.cached_scene.cache_clear()
    try:
        s = SU.load_suite("nightly")
    finally:
        P.cached_scene.cache_clear()
    files = {str(Path(CS.resolve_scenario(e.scenario)).resolve()) for b in s.sweeps for e in b.scenarios}
    files |= {str(Path(CS.resolve_scenario(r.scenario)).resolve()) for r in s.limits}
    assert set(counts) == files and set(counts.values()) == {1}, counts


#: the nightly's dt ladder rule (suites/nightly.toml, docs/SWEEPS.md): at
#: least this many steps per run of every scenario of a block ...
LADDER_MIN_STEPS = 12
#: ... and no step coarser than this (s): twice the 1/30 s game-loop step
LADDER_CAP = 1.0 / 15.0


def test_nightly_dt_grids_follow_the_ladder_rule():
    """Every [[sweep]] block of the nightly (but the step-phase one, which
    repeats the hard cases' steps) sweeps dt as a ladder of factors of 2
    from its finest step up to the largest step with dt <= duration / 12
    for every scenario of the block and dt <= 1/15 s; every engine sweeps
    the same ladder (no engine's own dt axis).  A grid that stops short of
    the rule, or runs past it, or favours one engine, fails here."""
    nightly = SU.load_suite(ROOT / "suites" / "nightly.toml")
    seen = 0
    for block in nightly.sweeps:
        if block.phases > 1:
            continue
        ladders = {e: tuple(sorted(float(v) for v in block.axes[e]["dt"])) for e in block.engines}
        assert len(set(ladders.values())) == 1, (block.description, ladders)
        dts = next(iter(ladders.values()))
        assert all(b / a == pytest.approx(2.0, rel=1e-9) for a, b in zip(dts, dts[1:])), (block.description, dts)
        bound = min([LADDER_CAP] + [load_scene(e.scenario, e.variant).duration / LADDER_MIN_STEPS
                                    for e in block.scenarios])
        top = dts[-1]
        assert top <= bound * (1 + 1e-9) and 2 * top > bound, (block.description, top, bound)
        seen += 1
    assert seen >= 8


BASE = """
[suite]
engines = ["reference", "mujoco", "pymunk"]
[[sweep]]
scenarios = ["billiards.head_on"]
grid = { dt = [0.002, 0.001] }
"""


@pytest.mark.parametrize("old, new, expected", [
    ('"mujoco", "pymunk"]', '"bullet"]', "suite.engines[1]: unknown engine 'bullet'; known: {known}"),
    ("grid = { dt = [0.002, 0.001] }", "grid = { dt = [0.002, 5.0] }",
     "sweep[0].grid.dt[1]: expected a value in [1e-07, 1.0], got 5.0 (engines reference, mujoco, pymunk)"),
    ("grid = { dt = [0.002, 0.001] }", "grid = { dt = 0.001 }", "sweep[0].grid.dt: expected a list, got 0.001"),
    ("grid = { dt = [0.002, 0.001] }", "grid = { dt = [0.002, 0.002] }",
     "sweep[0].grid.dt[1]: value 0.002 is listed twice"),
    ("grid = { dt = [0.002, 0.001] }", 'grid = { dt = [0.002, [1]] }',
     "sweep[0].grid.dt[1]: expected a number, string or boolean, got [1]"),
    ('"billiards.head_on"]', '"billiards.head_on", "billiards.nope"]',
     "sweep[0].scenarios[1]: unknown scenario 'billiards.nope'; known ids: "),
    ('"billiards.head_on"]', '"billiards.head_on[bouncy]"]',
     "sweep[0].scenarios[0]: scenario 'billiards.head_on' has no variant 'bouncy'; its variants: elastic, "
     "plastic, half, heavy_object, heavy_object_elastic, light_object_plastic"),
    ("[suite]", '[suite]\nrepeats = "three"', "suite.repeats: expected an integer, got 'three'"),
    ("[suite]", "[suite]\nrepeats = 0", "suite.repeats: must be >= 1, got 0"),
    ("[suite]", '[suite]\nname = "my suite"',
     "suite.name: must be a plain name (letters, digits, '_', '-', '.'): it names a directory, got 'my suite'"),
    ("grid = {", "gird = {", "sweep[0].gird: unknown key"),
    ('engines = ["reference", "mujoco", "pymunk"]', "", "suite.engines: required key is missing"),
])
def test_validation_errors_name_file_and_key_path(tmp_path, old, new, expected):
    assert old in BASE
    p = write(tmp_path, BASE.replace(old, new))
    errs = errors_of(p)
    want = f"{p}: " + expected.format(known=", ".join(engine_names()))
    assert any(e == want or (expected.endswith(": ") and e.startswith(want)) for e in errs), errs


def test_unknown_settings_name_the_engine(tmp_path):
    p = write(tmp_path, BASE + """
[sweep.engine.mujoco]
grid = { iters = [10] }
[sweep.engine.reference]
grid = { integrator = ["rk5"] }
""")
    errs = errors_of(p)
    assert f"{p}: sweep[0].engine.mujoco.grid.iters: not a setting of engine mujoco; its settings: dt, integrator, " \
           "cone, impratio, noslip_iterations, iterations, speculative, contact_steps, restitution_phase" in errs
    assert any(e.startswith(f"{p}: sweep[0].engine.reference.grid.integrator[0]: expected one of explicit_euler, ")
               and e.endswith("got 'rk5'") for e in errs), errs
    # a common axis that one engine lacks
    p = write(tmp_path, BASE.replace("grid = { dt", 'grid = { integrator = ["rk4"], dt'), "b.toml")
    errs = errors_of(p)
    assert len(errs) == 1 and errs[0].startswith(
        f"{p}: sweep[0].grid.integrator: not a setting of engine pymunk (its settings: dt, iterations"), errs
    # an engine table for an engine the sweep does not run
    p = write(tmp_path, BASE.replace('"mujoco", ', "") + "[sweep.engine.mujoco]\ngrid = { iterations = [1] }\n",
              "c.toml")
    assert errors_of(p) == [f"{p}: sweep[0].engine.mujoco: engine 'mujoco' is not in suite.engines "
                            "(reference, pymunk)"]


def test_a_directory_of_a_suites_name_does_not_hide_the_suite(tmp_path, monkeypatch):
    """``--suite nightly`` run where a folder named ``nightly`` lies: the
    shipped suite (a folder is no suite file); a folder of no suite's name
    is an error that says it is a directory."""
    from physbench.harness.suite import SUITE_DIR, SuiteError, resolve_suite

    monkeypatch.chdir(tmp_path)
    (tmp_path / "nightly").mkdir()
    (tmp_path / "my_runs").mkdir()
    assert resolve_suite("nightly") == SUITE_DIR / "nightly.toml"
    with pytest.raises(SuiteError, match=r"my_runs: <suite>: is a directory, not a suite file \(\.toml\), and no "
                                         r"suite of this name in suites/"):
        resolve_suite("my_runs")
    (tmp_path / "mine").write_text("")  # a file of the name still comes first
    assert resolve_suite("mine") == Path("mine")


def test_bad_suite_exits_2_with_the_message(tmp_path, capsys):
    p = write(tmp_path, BASE.replace("0.001]", "-1.0]"))
    assert S.sweep_main(str(p), out_dir=tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert f"error: {p}: sweep[0].grid.dt[1]: expected a value in [1e-07, 1.0], got -1.0" in err
    assert S.sweep_main("no_such_suite", out_dir=tmp_path / "out") == 2
    assert "no such file and no suite of this name" in capsys.readouterr().err
    assert S.sweep_main("smoke", engines=["pybullet"], out_dir=tmp_path / "out") == 2
    assert "engine pybullet is not in suite smoke" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------
# expansion


def test_expansion_is_a_cartesian_product_with_engine_axes(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["reference", "mujoco", "pymunk"]
        repeats = 2
        [[sweep]]
        scenarios = ["billiards.head_on", "billiards.head_on[elastic]"]
        grid = { dt = [0.002, 1e-3] }
        [sweep.engine.reference]
        grid = { integrator = ["semi_implicit_euler", "rk4"] }
        [sweep.engine.mujoco]
        grid = { integrator = ["euler", "implicitfast", "rk4"], iterations = [10, 100] }
        [sweep.engine.pymunk]
        grid = { dt = [0.0005] }      # replaces the common dt axis
        [[sweep]]
        scenarios = ["billiards.head_on", "gyroscopic.dzhanibekov"]
        engines = ["pymunk"]
        repeats = 1
        grid = { dt = [0.0005, 0.004] }
    """)
    suite = SU.load_suite(p)
    pts = SU.expand(suite)
    by = {}
    for pt in pts:
        by.setdefault((pt.scenario, pt.variant, pt.engine), []).append(pt)
    for var in (None, "elastic"):
        assert len(by["billiards.head_on", var, "reference"]) == 2 * 2
        assert len(by["billiards.head_on", var, "mujoco"]) == 2 * 3 * 2
    assert [q.settings_dict for q in by["billiards.head_on", "elastic", "pymunk"]] == [{"dt": 0.0005}]
    # block 2: head_on at dt 0.0005 on pymunk repeats block 1's point -> kept once (the first)
    assert [q.settings_dict["dt"] for q in by["billiards.head_on", None, "pymunk"]] == [0.0005, 0.004]
    assert by["billiards.head_on", None, "pymunk"][0].repeats == 2
    # the 2D engine on a 3D scene: points present, they will be `unsupported` rows
    assert len(by["gyroscopic.dzhanibekov", None, "pymunk"]) == 2
    assert len(pts) == 2 * (4 + 12 + 1) + 1 + 2
    # values are coerced once: 1e-3 and 0.001 are one key; keys are stable text
    # ... and end with the scene's content hash (a changed scene is a new point)
    mj = by["billiards.head_on", None, "mujoco"][0]
    h, he = load_scene("billiards.head_on").content_hash, load_scene("billiards.head_on", "elastic").content_hash
    assert h != he
    assert mj.key == 'billiards.head_on|mujoco|{"dt":0.002,"integrator":"euler","iterations":10}|' + h
    assert by["billiards.head_on", "elastic", "reference"][-1].key == \
        'billiards.head_on[elastic]|reference|{"dt":0.001,"integrator":"rk4"}|' + he
    # restrictions
    assert {q.engine for q in SU.expand(suite, engines=["mujoco"])} == {"mujoco"}
    assert {q.variant for q in SU.expand(suite, scenarios=["billiards.head_on[elastic]"])} == {"elastic"}
    with pytest.raises(ValueError, match="scenario billiards.oblique is not in suite"):
        SU.expand(suite, scenarios=["billiards.oblique"])


def test_unsupported_points_give_unsupported_rows(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["mujoco", "pymunk"]
        repeats = 3
        [[sweep]]
        scenarios = ["gyroscopic.dzhanibekov"]
        grid = { dt = [0.004, 0.002] }
    """)
    out = tmp_path / "out"
    assert S.sweep_main(str(p), engines=["pymunk"], out_dir=out) == 0
    df, man = consolidated(out)
    assert list(df["status"]) == ["unsupported"] * 2 and man["filters"]["engines"] == ["pymunk"]
    assert df["message"].str.contains("2D engine").all()
    assert df["primary_error"].isna().all() and (df["repeats"] == 0).all()


# ---------------------------------------------------------------------------
# rows, storage


def test_rows_follow_the_contract(smoke_serial):
    df, man = consolidated(smoke_serial)
    suite = SU.load_suite("smoke")
    assert set(CONTRACT) <= set(df.columns)
    assert not [c for c in df.columns if "trace" in c]
    assert list(df["point_key"]) == [p.key for p in SU.expand(suite)]  # planned order, each once
    assert (df["status"] == "ok").all() and (df["suite"] == "smoke").all()
    assert df["sweep_id"].nunique() == 1 and df["sweep_id"].iat[0] == man["sweep_id"]
    assert (df["schema_version"] == SCHEMA_VERSION).all() and (df["machine_id"] == ST.machine_id()).all()
    assert (df["primary_metric"] == "post_impact_velocity_error").all()
    assert np.isfinite(df["primary_error"]).all()
    assert (df["primary_error"] == df["post_impact_velocity_error"]).all()
    for _, r in df.iterrows():
        assert json.loads(r["point_settings"]) == {"dt": r["setting.dt"]}
        assert r["repeats"] == 2 and r["cpu_s_per_sim_s_min"] <= r["cpu_s_per_sim_s_median"]


def test_head_on_on_reference_meets_the_analytic_velocities(smoke_serial):
    """The metric compares the simulated outgoing velocities with Newton's
    law of restitution, v1' = (1 - e) v / 2, v2' = (1 + e) v / 2 for equal
    masses: the reference engine resolves the impact at its time of impact,
    so it is exact to rounding at any dt."""
    df, _ = consolidated(smoke_serial)
    ref = df[df["engine"] == "reference"]
    assert len(ref) == 2 and (ref["primary_error"] < 1e-9).all()
    assert (ref["linear_momentum_drift"] < 1e-12).all()


def test_consolidation_and_manifest(smoke_serial):
    suite = SU.load_suite("smoke")
    sdir = smoke_serial / ST.machine_id() / "smoke"
    files = sorted(x.name for x in sdir.iterdir())
    sid = files[0].removesuffix(".manifest.json").removesuffix(".parquet")
    assert files == [f"{sid}.manifest.json", f"{sid}.parquet"]  # the part directory is gone
    man = json.loads((sdir / f"{sid}.manifest.json").read_text())
    assert man["suite"] == "smoke" and man["suite_hash"] == suite.file_hash and man["sweep_id"] == sid
    assert man["points"] == [p.key for p in SU.expand(suite)] and man["rows"] == 6 and man["missing"] == []
    assert man["started"] <= man["finished"] and man["machine_id"] == ST.machine_id()
    assert sid.endswith(man["commit"]) and man["machine"]["cores"] == str(os.cpu_count())
    meta = json.loads(pq.read_schema(sdir / f"{sid}.parquet").metadata[b"physbench"])
    assert meta["schema_version"] == SCHEMA_VERSION and meta["manifest"]["sweep_id"] == sid
    assert len(ST.read_sweeps(smoke_serial, suite="smoke")) == 6


def test_failures_are_recorded_as_statuses(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["fake_sweep"]
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { fault = ["none", "build", "step", "nan"] }
    """)
    out = tmp_path / "out"
    assert S.sweep_main(str(p), out_dir=out) == 0  # failed runs are data
    df, _ = consolidated(out)
    st = dict(zip(df["point_settings"].map(lambda s: json.loads(s)["fault"]), df.itertuples()))
    assert st["none"].status == "ok" and st["none"].repeats == 3
    assert st["build"].status == "failed" and "model rejected" in st["build"].message
    assert st["step"].status == "error" and "solver exploded" in st["step"].message
    assert st["nan"].status == "diverged"
    for f in ("build", "step", "nan"):
        assert math.isnan(st[f].primary_error) and st[f].repeats == 0  # neither repeated nor timed


# ---------------------------------------------------------------------------
# resume


class _Killed(BaseException):
    """Stands for the process dying: not an Exception, so nothing catches it."""


def _counting_run(monkeypatch, kill_at_point: int | None):
    """Patch harness.runner.run to record the point key of every call, and
    to die on the first call of the ``kill_at_point``-th point (0-based)."""
    from physbench.harness import runner

    real = _REAL_RUN  # not runner.run: that may be an earlier patch
    calls: list[str] = []

    def run(scene, engine, settings=None, **kw):
        key = P.Point(scene.id, scene.variant, engine, tuple(sorted((settings or {}).items())),
                      scene_hash=scene.content_hash).key
        if kill_at_point is not None and key not in calls and len(dict.fromkeys(calls)) == kill_at_point:
            raise _Killed()
        calls.append(key)
        return real(scene, engine, settings, **kw)

    monkeypatch.setattr(runner, "run", run)
    return calls


def test_resume_after_a_kill(tmp_path, monkeypatch):
    suite = SU.load_suite("smoke")
    keys = [p.key for p in SU.expand(suite)]
    out = tmp_path / "out"
    calls = _counting_run(monkeypatch, kill_at_point=4)
    with pytest.raises(_Killed):
        S.sweep_main("smoke", out_dir=out, executor="serial")
    finished = list(dict.fromkeys(calls))
    assert finished == keys[:4]
    sweep_dirs = [d for d in (out / ST.machine_id() / "smoke").iterdir() if d.is_dir()]
    assert len(sweep_dirs) == 1 and stored_rows(sweep_dirs[0]) == 4
    assert not list(out.glob("*/*/*.parquet"))  # not consolidated

    calls = _counting_run(monkeypatch, kill_at_point=None)
    assert S.sweep_main("smoke", out_dir=out, executor="serial") == 0  # resumes automatically: same suite, points, commit
    assert not set(calls) & set(finished)  # no finished point was run again
    assert list(dict.fromkeys(calls)) == keys[4:]
    df, man = consolidated(out)
    assert sorted(df["point_key"]) == sorted(keys) and df["point_key"].is_unique  # none lost, none twice
    assert df["sweep_id"].nunique() == 1 and man["sweep_id"] == sweep_dirs[0].name
    assert len(man["resumed"]) == 1 and not sweep_dirs[0].exists()


def _fail_writes_of_bad(monkeypatch) -> None:
    """Every part write of a row whose point_key is "bad" raises OSError
    ("disk full"); the others are written."""
    import physbench.harness.results as R

    real = R.write_table_atomic

    def failing(table, path, *a, **kw):
        if "bad" in table.column("point_key").to_pylist():
            raise OSError("disk full")
        return real(table, path, *a, **kw)

    monkeypatch.setattr(R, "write_table_atomic", failing)


def test_write_behind_stores_rows_in_order_and_surfaces_a_failed_write(tmp_path, monkeypatch):
    """The writer thread stores the queued rows (several to a part), in
    order, before drain returns; a failed write is raised to the caller (by a
    later write_point, or by drain/close), and close releases the lock."""
    from physbench.harness.results import list_parts, read_part

    _fail_writes_of_bad(monkeypatch)
    sd = ST.SweepDir(tmp_path, {"sweep_id": "s"}, os.open(tmp_path / "lock", os.O_CREAT | os.O_RDWR))
    sd.write_behind()
    for k in ("a", "b", "c"):
        assert sd.write_point({"point_key": k, "x": 1.0}) is None
    sd.drain()
    assert sd.done == {"a", "b", "c"}
    assert [k for p in list_parts(tmp_path) for k in read_part(p).column("point_key").to_pylist()] == ["a", "b", "c"]

    sd.write_behind()
    sd.write_point({"point_key": "bad", "x": 1.0})
    with pytest.raises(OSError, match="disk full"):
        sd.close()
    assert sd.lock_fd == -1 and "bad" not in sd.done

    sd = ST.SweepDir(tmp_path, {"sweep_id": "s"}, -1)
    sd.write_behind()
    sd.write_point({"point_key": "bad", "x": 1.0})
    deadline = time.monotonic() + 30
    with pytest.raises(OSError, match="disk full"):  # raised by a later write_point once the writer failed
        while time.monotonic() < deadline:
            sd.write_point({"point_key": "d", "x": 1.0})
            time.sleep(0.01)
    sd.close()


def test_the_writer_gathers_a_flush_of_rows_and_drain_does_not_wait_for_it(tmp_path, monkeypatch):
    """The part writer sleeps through its flush time (it is not woken by
    every row): rows queued within PART_FLUSH_S go into one part, and drain
    writes what is queued at once; a full batch (PART_MAX_ROWS) is written
    without waiting for the flush time."""
    from physbench.harness.results import list_parts, read_part

    monkeypatch.setattr(ST, "PART_FLUSH_S", 60.0)
    sd = ST.SweepDir(tmp_path, {"sweep_id": "s"}, os.open(tmp_path / "lock", os.O_CREAT | os.O_RDWR))
    sd.write_behind()
    for k in "abcde":
        sd.write_point({"point_key": k, "x": 1.0})
    t = time.monotonic()
    sd.drain()
    assert time.monotonic() - t < 30.0
    parts = list_parts(tmp_path)
    assert [read_part(p).column("point_key").to_pylist() for p in parts] == [list("abcde")]

    monkeypatch.setattr(ST, "PART_MAX_ROWS", 3)
    sd.write_behind()
    for k in "fgh":
        sd.write_point({"point_key": k, "x": 1.0})
    deadline = time.monotonic() + 30.0
    while len(list_parts(tmp_path)) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [read_part(p).column("point_key").to_pylist() for p in list_parts(tmp_path)][1:] == [list("fgh")]
    sd.close()


def test_a_failed_write_stays_failed(tmp_path, monkeypatch):
    """Once a queued write failed, every later write_point and drain raises
    its error and stores nothing more: no row is written after a lost one
    as if the sweep went on whole (rows queued behind the failed one are
    not in ``done``, so a resume runs them again).  close releases the lock
    and does not raise an error the caller was already given."""
    from physbench.harness.results import list_parts, read_part

    _fail_writes_of_bad(monkeypatch)
    sd = ST.SweepDir(tmp_path, {"sweep_id": "s"}, os.open(tmp_path / "lock", os.O_CREAT | os.O_RDWR))
    sd.write_behind()
    sd.write_point({"point_key": "a", "x": 1.0})
    deadline = time.monotonic() + 30
    while "a" not in sd.done and time.monotonic() < deadline:  # "a" on disk in a part of its own
        time.sleep(0.01)
    for k in ("bad", "b"):
        sd.write_point({"point_key": k, "x": 1.0})
    with pytest.raises(OSError, match="disk full"):
        sd.drain()
    sd.write_behind()
    for _ in range(2):  # the caller went on after the error: still refused
        with pytest.raises(OSError, match="disk full"):
            sd.write_point({"point_key": "c", "x": 1.0})
    with pytest.raises(OSError, match="disk full"):
        sd.drain()
    sd.close()
    assert sd.lock_fd == -1 and sd.done == {"a"}
    assert [k for p in list_parts(tmp_path) for k in read_part(p).column("point_key").to_pylist()] == ["a"]


def test_cpu_account_charges_the_part_writer_and_the_main_thread_apart():
    """physbench.harness.selfbench.sweep.CpuAccount: CPU spent on a thread named as the
    sweep's part writer counts as "part writer", the main thread's as
    "main thread" (CPU seconds, not wall time)."""
    import threading

    from physbench.harness.selfbench.sweep import CpuAccount

    def spin(cpu_s: float) -> None:
        t0 = time.thread_time()
        while time.thread_time() - t0 < cpu_s:
            pass

    release = threading.Event()
    writer = threading.Thread(target=lambda: (spin(0.3), release.wait(60)), name=ST.PART_WRITER, daemon=True)
    with CpuAccount(dt=0.05) as account:
        writer.start()
        spin(0.3)
        deadline = time.monotonic() + 60  # the writer spun and is still alive at the last sample
        while account.threads.get(writer.native_id, 0.0) < 0.29 and time.monotonic() < deadline:
            time.sleep(0.01)
    release.set()
    writer.join()
    r = account.report()
    assert r["part writer"] >= 0.25 and r["main thread"] >= 0.25
    assert r["part writer"] < 0.5  # its own 0.3 s, not the main thread's as well


def test_resume_rule_needs_the_same_suite_file(tmp_path, monkeypatch):
    p = write(tmp_path, (ROOT / "suites" / "smoke.toml").read_text(), "smoke.toml")
    out = tmp_path / "out"
    _counting_run(monkeypatch, kill_at_point=2)
    with pytest.raises(_Killed):
        S.sweep_main(str(p), out_dir=out, executor="serial")
    p.write_text(p.read_text() + "# edited\n")  # a different suite file: not resumed
    _counting_run(monkeypatch, kill_at_point=0)
    with pytest.raises(_Killed):
        S.sweep_main(str(p), out_dir=out, executor="serial")
    dirs = sorted(d for d in (out / ST.machine_id() / "smoke").iterdir() if d.is_dir())
    assert [stored_rows(d) for d in dirs] == [2, 0]
    # resume=True resumes the newest sweep of the same suite file and points
    calls = _counting_run(monkeypatch, kill_at_point=None)
    assert S.sweep_main(str(p), out_dir=out, resume=True, executor="serial") == 0
    assert len(calls) == 6 * 2  # the edited suite's sweep had no finished point: all 6, 2 repeats each
    assert not dirs[1].exists() and dirs[0].exists()


def test_resume_after_the_process_is_killed(tmp_path):
    """A real SIGKILL in the middle of a sweep: parts are whole files, the
    point in flight is lost and rerun, nothing else."""
    p = write(tmp_path, """
        [suite]
        engines = ["fake_sweep"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { sleep_s = [0.0, 0.001, 0.002, 0.003, 1.0, 1.001, 1.002, 1.003] }
    """)
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from physbench.adapters.base import register
        from tests.test_sweep import FakeSweep
        from physbench.harness import sweep_store
        from physbench.harness.sweep import sweep_main
        register("fake_sweep", lambda: FakeSweep)
        sweep_store.PART_FLUSH_S = 2.0  # the points' times below are set against a 2 s flush
        sweep_main({str(p)!r}, out_dir={str(out)!r})
    """)
    before = kill_after_parts(script, out, 5, ROOT, 60)
    assert 5 <= len(before) < 8 and before.index.is_unique
    assert S.sweep_main(str(p), out_dir=out) == 0
    df, man = consolidated(out)
    assert df["point_key"].is_unique and len(df) == 8 and (df["status"] == "ok").all()
    assert len(man["resumed"]) == 1 and man["duplicates_dropped"] == 0
    # the rows finished before the kill are the ones kept: not rerun
    kept = df.set_index("point_key").loc[before.index]
    assert (kept["point_wall_s"] == before["point_wall_s"]).all()


# ---------------------------------------------------------------------------
# parallel executors


def test_process_executor_gives_the_serial_metrics(tmp_path, smoke_serial):
    out = tmp_path / "out"
    assert S.sweep_main("smoke", jobs=2, out_dir=out) == 0
    a, _ = consolidated(smoke_serial)
    b, man = consolidated(out)
    assert man["executor"] == "process" and (b["sweep_jobs"] == 2).all()
    assert list(a["point_key"]) == list(b["point_key"])
    cols = [c for c in a.columns if c not in TIMING and not c.startswith("timing.")
            and pd.api.types.is_numeric_dtype(a[c]) and c != "schema_version"]
    assert "primary_error" in cols and "max_penetration" in cols
    for c in cols:
        np.testing.assert_array_equal(a[c].to_numpy(float), b[c].to_numpy(float), err_msg=c)
    assert list(a["status"]) == list(b["status"])


def test_a_worker_crash_becomes_an_error_row(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["fake_sweep"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { fault = ["none", "crash"], dt = [0.002, 0.001] }
    """)
    out = tmp_path / "out"
    assert S.sweep_main(str(p), jobs=2, executor="process", out_dir=out) == 0
    df, _ = consolidated(out)
    assert len(df) == 4 and df["point_key"].is_unique
    faults = df["point_settings"].map(lambda s: json.loads(s)["fault"])
    assert (df.loc[faults == "none", "status"] == "ok").all()
    crashed = df[faults == "crash"]
    assert (crashed["status"] == "error").all()
    assert crashed["message"].str.contains("worker process died").all()


# ---------------------------------------------------------------------------
# review fixes: consolidation types, a point that raises, a half-finished
# consolidation


def _sweep_dir_with_parts(tmp_path: Path, rows: list[dict]) -> Path:
    d = tmp_path / "m" / "s" / "20260101T000000Z-x"
    d.mkdir(parents=True)
    write_json_atomic({"sweep_id": d.name, "points": [r["point_key"] for r in rows]}, d / "manifest.json")
    for i, r in enumerate(rows, 1):
        write_parquet_atomic(pd.DataFrame([r]), d / f"part-{i:06d}.parquet")
    return d


def test_consolidation_keeps_int_and_float_parts_numeric(tmp_path):
    # one part with the column None, one int, one float: numbers, not text
    d = _sweep_dir_with_parts(tmp_path, [{"point_key": "a", "x": None}, {"point_key": "b", "x": 2},
                                         {"point_key": "c", "x": 2.5}])
    df = pd.read_parquet(ST.consolidate(d))
    assert pd.api.types.is_float_dtype(df["x"]), df["x"].tolist()
    assert math.isnan(df["x"].iat[0]) and df["x"].iat[1] == 2.0 and df["x"].iat[2] == 2.5


def test_consolidation_still_stores_bool_and_text_mixes_as_text(tmp_path):
    d = _sweep_dir_with_parts(tmp_path, [{"point_key": "a", "ccd": True}, {"point_key": "b", "ccd": "events"},
                                         {"point_key": "c", "ccd": None}])
    df = pd.read_parquet(ST.consolidate(d))
    assert df["ccd"].tolist()[:2] == ["True", "events"] and df["ccd"].isna().iat[2]


def test_a_point_that_raises_in_the_serial_executor_is_an_error_row(tmp_path, monkeypatch):
    real = P.request_row

    def request_row(r):
        if r.settings.get("dt") == 0.001 and r.engine == "mujoco":
            raise KeyError("bug in the row code")
        return real(r)

    monkeypatch.setattr(P, "request_row", request_row)
    out = tmp_path / "out"
    assert S.sweep_main("smoke", out_dir=out, executor="serial") == 0
    df, man = consolidated(out)
    assert len(df) == 6 and man["missing"] == []
    bad = df[(df["engine"] == "mujoco") & (df["setting.dt"] == 0.001)]
    assert bad["status"].tolist() == ["error"] and "bug in the row code" in bad["message"].iat[0]
    assert (df.drop(bad.index)["status"] == "ok").all()


def test_a_consolidated_sweep_whose_directory_was_not_removed(tmp_path, monkeypatch):
    """Consolidated file written, then the directory removal failed (or the
    process died before it): no rows twice, no rerun, and the next sweep
    finishes the removal."""
    out = tmp_path / "out"
    real_rmtree = shutil.rmtree

    def failing_rmtree(path, *a, **kw):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(shutil, "rmtree", failing_rmtree)
    assert S.sweep_main("smoke", out_dir=out, executor="serial") == 0  # the rows are safe: not a crash
    monkeypatch.setattr(shutil, "rmtree", real_rmtree)
    sdir = out / ST.machine_id() / "smoke"
    left = [d for d in sdir.iterdir() if d.is_dir()]
    assert len(left) == 1
    rows = ST.read_sweeps(out, unfinished=True)
    assert len(rows) == 6 and rows["point_key"].is_unique  # consolidated file wins over leftover parts
    # killed before the consolidated manifest too
    (sdir / f"{left[0].name}.manifest.json").unlink()
    calls = _counting_run(monkeypatch, kill_at_point=0)
    with pytest.raises(_Killed):  # a new sweep starts (the old one is complete) ...
        S.sweep_main("smoke", out_dir=out, executor="serial")
    assert not left[0].exists()  # ... after finishing the old one's consolidation
    man = json.loads((sdir / f"{left[0].name}.manifest.json").read_text())
    assert man["rows"] == 6 and man["missing"] == []
    assert len(pd.read_parquet(sdir / f"{left[0].name}.parquet")) == 6
    assert calls == []


# ---------------------------------------------------------------------------
# step phases


def test_phases_expand_to_shifted_points_with_phase_zero_as_the_plain_point(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["pymunk", "pybullet"]
        repeats = 1
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor"]
        grid = { dt = [0.004166666666666667] }
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor"]
        grid = { dt = [0.004166666666666667, 0.008333333333333333] }
        phases = 4
    """)
    pts = SU.expand(SU.load_suite(p))
    pb = [q for q in pts if q.engine == "pybullet"]
    assert [(q.settings_dict["dt"], q.phase) for q in pb] == \
        [(1 / 240, 0.0), (1 / 240, 0.25), (1 / 240, 0.5), (1 / 240, 0.75),
         (1 / 120, 0.0), (1 / 120, 0.25), (1 / 120, 0.5), (1 / 120, 0.75)]
    # phase 0 has no phase key: the same point (and history) as block 1's
    h = load_scene("tunnelling.thin_box_on_thin_floor").content_hash
    assert pb[0].key == 'tunnelling.thin_box_on_thin_floor|pybullet|{"dt":0.004166666666666667}|' + h
    assert pb[1].key.endswith('{"dt":0.004166666666666667,"phase":0.25}|' + h)
    assert pb[1].engine_settings == {"dt": 1 / 240}  # the engine never sees the phase
    assert len(pts) == 2 * 8


def test_phase_is_not_a_grid_axis(tmp_path):
    p = write(tmp_path, """
        [suite]
        engines = ["pymunk"]
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor"]
        grid = { dt = [0.004], phase = [0.0, 0.5] }
    """)
    errs = errors_of(p)
    assert any("sweep[0]: 'phase' is not a grid axis; give the number of step phases as 'phases = N'" in e
               for e in errs), errs
    p = write(tmp_path, """
        [suite]
        engines = ["pymunk"]
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor"]
        phases = 0
    """, name="zero.toml")
    assert any("sweep[0].phases" in e for e in errors_of(p))


def test_phase_sweep_measures_the_plate_tunnelling_law(tmp_path):
    """pymunk has no CCD: the 2 mm plate at 6.26 m/s is stopped only by a
    step that ends with its centre in the 3 mm window above the slab's
    mid-plane, so over 8 phases at 1/240 s (2.6 cm per step) most tunnel
    and at least one does not; the reference engine (CCD events) never
    tunnels.  A scene whose start is not free flight gives error rows
    naming the reason, not a crash."""
    p = write(tmp_path, """
        [suite]
        engines = ["pymunk", "reference"]
        repeats = 1
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor", "stacking.column_5"]
        grid = { dt = [0.004166666666666667] }
        phases = 8
    """)
    out = tmp_path / "out"
    S.sweep_main(str(p), out_dir=out, jobs=1)
    df, _ = consolidated(out)
    plate = df[df["scenario"] == "tunnelling.thin_box_on_thin_floor"]
    assert sorted(plate["phase"].unique()) == [i / 8 for i in range(8)]
    tun = plate.groupby("engine")["tunnelled"].sum()
    assert tun["reference"] == 0
    assert 4 <= tun["pymunk"] <= 7  # law: 1 - 3 mm / 26 mm = 0.88 of phases
    # the shifted start is higher and rising: the same fall, steps f dt earlier
    r = plate[(plate["engine"] == "pymunk")].set_index("phase")
    assert (r["status"] == "ok").all()
    col = df[(df["scenario"] == "stacking.column_5")]
    assert (col[col["phase"] == 0]["status"] == "ok").all()
    bad = col[col["phase"] > 0]
    assert len(bad) == 2 * 7 and (bad["status"] == "error").all()
    assert bad["message"].str.contains("phase shift needs free flight").all()


def test_the_start_up_objects_are_out_of_the_loop_s_collections(tmp_path, monkeypatch):
    """sweep_main freezes the objects its start-up made (gc.freeze) while
    the sweep's loop runs, so the garbage collector's full collections do
    not walk them for every few hundred rows, and gives them back after
    (a caller's later collections see them again), also when the loop
    raises."""
    import gc

    frozen = []

    def loop(*a, **kw):
        frozen.append(gc.get_freeze_count())
        if len(frozen) == 2:
            raise RuntimeError("the loop failed")

    monkeypatch.setattr(S, "run_schedule", loop)
    before = gc.get_freeze_count()
    assert S.sweep_main("smoke", executor="serial", out_dir=tmp_path / "a", resume=False) == 0
    assert frozen[0] > before + 10_000 and gc.get_freeze_count() == before
    with pytest.raises(RuntimeError, match="the loop failed"):
        S.sweep_main("smoke", executor="serial", out_dir=tmp_path / "b", resume=False)
    assert len(frozen) == 2 and gc.get_freeze_count() == before
