"""The one execution path (harness/execute.py): an engine that aborts,
segfaults or hangs inside one call costs its own run only, with --jobs 1
and 2; ``physbench run`` reports such a run as a status; a check killed
with SIGKILL and run again loses no finished row and reruns none; result
files are readable; MuJoCo writes no log file; ``--json`` is JSON only.
The faulty engine (tests/faulty_adapter.py) is pybullet that faults in
one scene on request.  No wall-clock assertions."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pandas as pd
import pytest

from physbench.adapters.base import _REGISTRY, register
from physbench.harness import conformance as C
from physbench.harness.execute import RunRequest, WorkerLost, WorkerPool, run_isolated
from tests.faulty_adapter import FAULT_ENV, FaultyAdapter, batch_item, die, worker_pid

ROOT = Path(__file__).resolve().parent.parent
FAULTY = "friction.ball_rolls"  # faulted in its base scene; its variants and block_slides pass on pybullet
GOOD = "friction.block_slides"
ADAPTER_REF = "faulty=tests.faulty_adapter:FaultyAdapter"


@pytest.fixture(autouse=True)
def _faulty_engine():
    register("faulty", lambda: FaultyAdapter)
    yield
    _REGISTRY.pop("faulty", None)


def _junit_cases(path: Path) -> dict[str, ET.Element]:
    root = ET.parse(path).getroot()
    return {tc.get("name"): tc for tc in root.iter("testcase")}


@pytest.mark.parametrize("jobs", [1, 2])
@pytest.mark.parametrize("fault,status,reason", [
    ("abort", "error", "SIGABRT"),
    ("segfault", "error", "SIGSEGV"),
    ("hang", "timeout", "worker killed"),
])
def test_a_fault_costs_only_its_own_run(tmp_path, monkeypatch, jobs, fault, status, reason):
    monkeypatch.setenv(FAULT_ENV, f"{FAULTY}:{fault}")
    junit = tmp_path / "junit.xml"
    rows = tmp_path / "check"
    timeout = 5.0 if fault == "hang" else 600.0
    code = C.check_main(["faulty"], None, str(junit), [GOOD, FAULTY], jobs=jobs, save_dir=rows, timeout_s=timeout)
    assert code == 1
    cases = _junit_cases(junit)  # the JUnit file is written
    bad = {n: tc for n, tc in cases.items() if n.startswith(FAULTY + "::")}
    good = {n: tc for n, tc in cases.items() if n not in bad}
    assert len(bad) >= 1 and len(good) >= 6
    for name, tc in good.items():  # every other check of the job still passes
        assert not list(tc), f"{name}: {[(c.tag, c.get('message')) for c in tc]}"
    for name, tc in bad.items():
        (child,) = list(tc)
        assert child.tag == "error" and child.get("message").startswith(f"{status}:"), child.get("message")
        assert reason in child.get("message")
    # the rows: the faulty run's status and reason; the others ok
    (f,) = rows.glob("*.parquet")
    df = pd.read_parquet(f)
    faulty = df[(df["scenario"] == FAULTY) & df["variant"].isna()]
    assert faulty["status"].tolist() == [status]
    assert (df.drop(faulty.index)["status"] == "ok").all() and df["run_key"].is_unique
    info = json.loads(faulty["info"].iat[0])
    if fault == "abort":  # the tail of the dead worker's stderr
        assert "Mass must be positive and finite" in info["stderr_tail"]
        assert "Mass must be positive and finite" in faulty["message"].iat[0]
        assert info["signal"] == "SIGABRT"


def test_run_command_reports_an_abort_as_a_status(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), PHYSBENCH_ADAPTERS=ADAPTER_REF, **{FAULT_ENV: f"{FAULTY}:abort"})
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "run", FAULTY, "-e", "faulty", "--json"],
                       capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert p.returncode == 1, p.stderr
    (line,) = p.stdout.strip().splitlines()  # one JSON object, no raw abort (exit 134)
    d = json.loads(line)
    assert d["status"] == "error" and "SIGABRT" in d["message"] and d["engine"] == "faulty"
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "run", FAULTY, "-e", "faulty", "--timeout", "0"],
                       capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert p.returncode == 2 and "--timeout" in p.stderr and "Traceback" not in p.stderr
    assert not list(tmp_path.iterdir())  # nothing written into the working directory


def test_a_killed_check_resumes_without_losing_or_rerunning_a_row(tmp_path):
    """SIGKILL of `physbench check` while its 4th run hangs: the three
    finished rows are stored as parts; the rerun reads them back, runs the
    rest, and the consolidated rows hold every run once, the first three
    exactly as they were stored."""
    rows = tmp_path / "check"
    env = dict(os.environ, PYTHONPATH=str(ROOT), PHYSBENCH_ADAPTERS=ADAPTER_REF, **{FAULT_ENV: f"{FAULTY}:hang"})
    code = f"import sys; from physbench.harness.conformance import check_main; sys.exit(check_main(['faulty'], None, " \
           f"{str(tmp_path / 'j.xml')!r}, {[GOOD, FAULTY]!r}, save_dir={str(rows)!r}))"
    proc = subprocess.Popen([sys.executable, "-c", "from physbench.harness.execute import register_env_adapters; "
                             "register_env_adapters(); " + code], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while len(list(rows.glob("*/part-*.parquet"))) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # the 4th run (the hang) is in its worker now
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    parts = sorted(rows.glob("*/part-*.parquet"))
    assert len(parts) == 3, parts  # GOOD's three variants, each stored as it finished
    before = pd.concat([pd.read_parquet(p) for p in parts]).set_index("run_key")
    assert not (tmp_path / "j.xml").exists()  # killed before the end
    # the rerun, without the fault: the same check (commit, engines, scenarios, specs, budget)
    assert C.check_main(["faulty"], None, str(tmp_path / "j.xml"), [GOOD, FAULTY], save_dir=rows) == 0
    (f,) = rows.glob("*.parquet")
    df = pd.read_parquet(f)
    assert df["run_key"].is_unique and (df["status"] == "ok").all()
    assert len(df) == 3 + 3  # GOOD's variants, FAULTY's base and variants: none lost
    man = json.loads(f.with_suffix(".manifest.json").read_text())
    assert len(man["resumed"]) == 1 and man["missing"] == [] and man["duplicates_dropped"] == 0
    kept = df.set_index("run_key").loc[before.index]
    assert (kept["timestamp"] == before["timestamp"]).all()  # not rerun: the stored rows
    assert (kept["timing.step_wall_s"] == before["timing.step_wall_s"]).all()
    assert not [d for d in rows.iterdir() if d.is_dir()]  # parts consolidated
    assert all(tc.get("name") for tc in _junit_cases(tmp_path / "j.xml").values())


def test_pool_reuses_workers_and_replaces_a_dead_one():
    with WorkerPool(1) as pool:
        out = dict(pool.map(worker_pid, [1, 2, 3]))
        assert len(set(out.values())) == 1 and pool.started == 1  # one worker for three items
        lost = dict(pool.map(die, [0]))[0]
        assert isinstance(lost, WorkerLost) and lost.kind == "died" and lost.signal == "SIGKILL"
        again = dict(pool.map(worker_pid, [4]))[4]
        assert again not in out.values() and pool.started == 2


def test_a_batch_keeps_its_finished_items_and_reruns_the_rest():
    """A Batch runs its items one after the other in one worker, each
    replied as it finishes and watched under its own budget: where the
    worker dies or hangs, the items before keep their values, the running
    one is lost (died / timeout), and the items after run in a fresh worker."""
    from physbench.harness.execute import Batch

    units = [Batch((("pid", 1), ("pid", 2), ("die", 3), ("pid", 4), ("pid", 5))),
             Batch((("pid", 6), ("hang", 7), ("pid", 8))), ("pid", 9)]
    budget = {"pid": 30.0, "die": 30.0, "hang": 1.0}
    starts = []
    with WorkerPool(1) as pool:
        out = list(pool.map(batch_item, units, budget_s=lambda it: budget[it[0]], on_start=starts.append))
        assert pool.started == 3, out  # the first worker died, the second was killed at item 7's budget
    got = dict(out)
    assert [it for it, _ in out] == [("pid", 1), ("pid", 2), ("die", 3), ("pid", 4), ("pid", 5), ("pid", 6),
                                     ("hang", 7), ("pid", 8), ("pid", 9)]
    assert sorted(starts) == sorted(it for it, _ in out)  # each item started once
    lost = got[("die", 3)]
    assert isinstance(lost, WorkerLost) and lost.kind == "died" and lost.signal == "SIGKILL"
    hung = got[("hang", 7)]
    assert isinstance(hung, WorkerLost) and hung.kind == "timeout" and "budget 1 s" in hung.message
    pids = {n: v[1] for (what, n), v in got.items() if what == "pid"}
    assert pids[1] == pids[2] != pids[4] == pids[5] == pids[6] != pids[8] == pids[9]
    assert all(got[("pid", n)][0] == n for n in pids)


def test_check_unknown_scenario_is_exit_2(capsys):
    from physbench.harness.cli import main

    assert main(["check", "--scenarios", "nosuch.thing"]) == 2
    assert "nosuch.thing" in capsys.readouterr().err


def test_result_files_are_readable(tmp_path):
    from physbench.harness.results import write_rows

    old = os.umask(0o022)
    try:
        p = write_rows([{"a": 1}], tmp_path / "r.parquet")
    finally:
        os.umask(old)
    assert p.stat().st_mode & 0o777 == 0o644


def test_mujoco_warnings_write_no_log_file(tmp_path, monkeypatch):
    import numpy as np

    import physbench.adapters.mujoco as am

    mujoco = am.mujoco
    monkeypatch.chdir(tmp_path)
    m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><freejoint/><geom size="0.1"/></body>'
                                       '</worldbody></mujoco>')
    d = mujoco.MjData(m)
    d.qvel[:] = np.nan  # MuJoCo warns: "Nan, Inf or huge value in QVEL"
    am._WARNINGS.clear()
    mujoco.mj_step(m, d)
    assert any("QVEL" in w for w in am._WARNINGS)
    am._WARNINGS.clear()
    assert not list(tmp_path.iterdir())  # no MUJOCO_LOG.TXT


def test_bench_json_is_json_only(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "bench", "isolation", "--repeats", "1", "--json"],
                       capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    (row,) = json.loads(p.stdout)  # stdout is the JSON and nothing else; the table went to stderr
    assert row["reused_worker_ms"] > 0 and row["fresh_worker_ms"] > 0 and "in a reused worker" in p.stderr


def test_run_isolated_equals_in_process():
    from physbench.harness.execute import execute_request

    req = RunRequest("billiards.head_on", "pybullet", phase=0.25)
    a, b = execute_request(req), run_isolated(req)
    assert a.status == b.status == "ok"
    assert a.metrics["post_impact_velocity_error"] == b.metrics["post_impact_velocity_error"]
    assert any("step phase 0.25" in n for n in b.notes)
