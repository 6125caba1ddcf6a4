"""The Dask executor (harness/dask_executor.py) on LocalClusters bound to
127.0.0.1: the serial executor's metrics, resume after the client is
killed, a Dask worker killed mid-run, a worker of another physbench
refused.  Every cluster is closed and no process is left behind."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from physbench.adapters.base import Setting, register
from physbench.harness import sweep as S
from tests.test_sweep import FakeSweep, consolidated, kill_after_parts, write

distributed = pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parent.parent
TIMING = {"cpu_s_per_sim_s", "wall_s_per_sim_s", "steps_per_s", "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min",
          "point_wall_s", "sweep_jobs"}
#: set in the test clusters' workers only: the one place DaskFake may kill a process
KILL_OK_ENV = "PHYSBENCH_TEST_DASK_KILL_OK"
MARKERS_ENV = "PHYSBENCH_TEST_DASK_MARKERS"


class DaskFake(FakeSweep):
    """tests/test_sweep.py's free flight, faulting otherwise: ``fault``
    ``kill_worker`` kills the Dask worker running it (the parent of its run
    process), ``kill_worker_once`` only the first time (a marker file)."""

    name = "dask_fake"

    @classmethod
    def capabilities(cls):
        caps = super().capabilities()
        fault = Setting("fault", "none", str, "", choices=("none", "kill_worker", "kill_worker_once"))
        return dataclasses.replace(caps, engine="dask_fake", settings={**caps.settings, "fault": fault})

    def build(self, scene, settings):
        fault = settings["fault"]
        if fault != "none":
            if os.environ.get(KILL_OK_ENV) != "1" or os.environ.get("PHYSBENCH_WORKER") != "1":
                raise RuntimeError("kill requested outside a test cluster's run process")
            marker = Path(os.environ[MARKERS_ENV]) / f"killed-{settings['dt']}"
            if fault == "kill_worker" or not marker.exists():
                marker.touch()
                os.kill(os.getppid(), signal.SIGKILL)  # the Dask worker, as an out-of-memory kill would
                time.sleep(60)
        super().build(scene, {**settings, "fault": "none"})


@pytest.fixture(autouse=True, scope="module")
def _fake_engine():
    from physbench.adapters import base

    register("dask_fake", lambda: DaskFake)
    yield
    base._REGISTRY.pop("dask_fake", None)


def _descendants() -> set[int]:
    """Pids of this process's descendants (Linux /proc), but for
    multiprocessing's resource tracker (started with the first spawned
    process, it lives as long as this process and leaves with it)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = set(), [os.getpid()]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return {p for p in out if b"resource_tracker" not in _cmdline(p)}


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def _wait_gone(pids: set[int], timeout: float = 30.0) -> set[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        left = {p for p in pids if Path(f"/proc/{p}").exists()
                and Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"}
        if not left:
            return set()
        time.sleep(0.2)
    return left


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A 2-worker LocalCluster on 127.0.0.1 (processes, one thread each),
    its scheduler not retrying a task whose worker died (the client
    retries), as DaskExecutor's own."""
    import dask
    from distributed import Client, LocalCluster

    markers = tmp_path_factory.mktemp("dask_markers")
    scratch = tmp_path_factory.mktemp("dask_tmp")  # a killed worker's run-process directory stays here
    before = _descendants()
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.scheduler.worker-saturation": 1.0}):
        lc = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address="127.0.0.1:0", silence_logs=50,
                          env={KILL_OK_ENV: "1", MARKERS_ENV: str(markers), "TMPDIR": str(scratch)})
    client = Client(lc)
    try:
        yield lc, client
    finally:
        client.close()
        lc.close()
        assert not _wait_gone(_descendants() - before), "the cluster left processes behind"


def _wait_workers(client, n: int = 2, timeout: float = 180.0) -> None:
    # a start-up wait, not a measurement: on a loaded 2-core machine (the
    # suite's other worker compiling) a dask worker took over 60 s to arrive
    client.wait_for_workers(n, timeout=timeout)


# ---------------------------------------------------------------------------


def test_dask_gives_the_serial_metrics_on_smoke_and_a_phases_block(tmp_path):
    """The smoke suite and a block of step phases: identical metrics and
    statuses to the serial executor; the LocalCluster is started (2
    workers) and closed by the executor, leaving no process behind."""
    smoke = (ROOT / "suites" / "smoke.toml").read_text()
    p = write(tmp_path, smoke + textwrap.dedent("""
        [[sweep]]
        scenarios = ["tunnelling.thin_box_on_thin_floor"]
        engines = ["pymunk", "mujoco"]
        grid = { dt = [0.004166666666666667] }
        phases = 4
    """))
    before = _descendants()
    a_out, b_out = tmp_path / "serial", tmp_path / "dask"
    assert S.sweep_main(str(p), out_dir=a_out, executor="serial") == 0
    assert S.sweep_main(str(p), jobs=2, out_dir=b_out, executor="dask") == 0
    assert not _wait_gone(_descendants() - before), "the executor left processes behind"
    a, _ = consolidated(a_out)
    b, man = consolidated(b_out)
    assert man["executor"] == "dask" and (b["sweep_jobs"] == 2).all()
    assert len(a) == 6 + 2 * 4 and list(a["point_key"]) == list(b["point_key"])
    assert sorted(b["phase"].unique()) == [0.0, 0.25, 0.5, 0.75]
    cols = [c for c in a.columns if c not in TIMING and not c.startswith("timing.")
            and pd.api.types.is_numeric_dtype(a[c]) and c != "schema_version"]
    assert "primary_error" in cols and "max_penetration" in cols
    for c in cols:
        np.testing.assert_array_equal(a[c].to_numpy(float), b[c].to_numpy(float), err_msg=c)
    assert list(a["status"]) == list(b["status"]) and (b["status"] == "ok").all()
    # rows carry the machine of the worker that made them (the same machine here)
    assert (b["machine.id"] == b["machine_id"]).all() and b["machine.env_id"].notna().all()


def test_killing_the_client_mid_sweep_resumes_without_loss_or_duplicates(tmp_path, cluster):
    lc, client = cluster
    _wait_workers(client)
    p = write(tmp_path, """
        [suite]
        engines = ["dask_fake"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { sleep_s = [0.0, 0.001, 0.002, 0.003, 2.5, 2.501, 2.502, 2.503, 2.504, 2.505] }
    """)
    # the six slow points take three rounds of 2.5 s on two workers, past two
    # part flushes (sweep_store.PART_FLUSH_S set to 2 s): the kill lands after 5
    # rows are stored and before the tenth (with 1 s points every row could
    # be done by the first flush that held 5)
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        from physbench.adapters.base import register
        from tests.test_dask_executor import DaskFake
        from physbench.harness import sweep_store
        from physbench.harness.sweep import sweep_main
        register("dask_fake", lambda: DaskFake)
        sweep_store.PART_FLUSH_S = 2.0  # the points' times below are set against a 2 s flush
        sweep_main({str(p)!r}, out_dir={str(out)!r}, executor="dask", scheduler={lc.scheduler_address!r})
    """)
    before = kill_after_parts(script, out, 5, tmp_path, 120)
    assert 5 <= len(before) < 10 and before.index.is_unique
    assert S.sweep_main(str(p), out_dir=out, executor="dask", scheduler=lc.scheduler_address) == 0
    df, man = consolidated(out)
    assert df["point_key"].is_unique and len(df) == 10 and (df["status"] == "ok").all()
    assert len(man["resumed"]) == 1 and man["duplicates_dropped"] == 0
    kept = df.set_index("point_key").loc[before.index]  # the rows written before the kill: not rerun
    assert (kept["point_wall_s"] == before["point_wall_s"]).all()


def test_a_dask_worker_killed_mid_run_is_retried_once_then_an_error_row(tmp_path, cluster, capsys):
    lc, client = cluster
    _wait_workers(client)
    p = write(tmp_path, """
        [suite]
        engines = ["dask_fake"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { fault = ["none"], dt = [0.002, 0.001] }
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { fault = ["kill_worker_once"], dt = [0.0025] }
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { fault = ["kill_worker"], dt = [0.0015] }
    """)
    out = tmp_path / "out"
    assert S.sweep_main(str(p), out_dir=out, executor="dask", scheduler=lc.scheduler_address) == 0
    df, _ = consolidated(out)
    assert len(df) == 4 and df["point_key"].is_unique
    fault = df["point_settings"].map(lambda s: json.loads(s)["fault"])
    assert (df.loc[fault == "none", "status"] == "ok").all(), df[["point_settings", "status", "message"]].to_dict("records")
    assert (df.loc[fault == "kill_worker_once", "status"] == "ok").all(), df[["point_settings", "status", "message"]].to_dict("records")  # retried on a fresh worker
    dead = df[fault == "kill_worker"]
    assert (dead["status"] == "error").all()
    assert dead["message"].str.contains("the Dask worker died while running this point, twice").all()
    assert dead["message"].str.contains("retried once").all()


def _pretend_other_commit(dask_worker=None):
    """Make this worker report another physbench commit (as a worker with
    another checkout installed would)."""
    from physbench.harness import dask_executor, runner

    runner._real_commit_id = getattr(runner, "_real_commit_id", runner.commit_id)
    runner.commit_id = lambda: "0123456789ab"
    dask_executor.worker_identity.cache_clear()


def _restore_commit(dask_worker=None):
    from physbench.harness import dask_executor, runner

    runner.commit_id = getattr(runner, "_real_commit_id", runner.commit_id)
    dask_executor.worker_identity.cache_clear()


def test_a_worker_of_another_physbench_is_refused(tmp_path, cluster, capsys):
    from physbench.harness.dask_executor import DaskExecutor, EnvironmentRefused
    from physbench.harness.points import run_point

    lc, client = cluster
    _wait_workers(client)
    p = write(tmp_path, """
        [suite]
        engines = ["dask_fake"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { dt = [0.002, 0.001] }
    """)
    out = tmp_path / "out"
    odd = sorted(client.scheduler_info()["workers"])[0]
    client.run(_pretend_other_commit, workers=[odd])
    try:
        capsys.readouterr()
        assert S.sweep_main(str(p), out_dir=out, executor="dask", scheduler=lc.scheduler_address) == 2
        err = capsys.readouterr().err
        assert f"dask worker {odd} runs another physbench environment than this client" in err
        assert "commit: client" in err and "worker '0123456789ab'" in err
        assert not out.exists()  # refused before the sweep directory is made
    finally:
        client.run(_restore_commit, workers=[odd])
    # a worker that turns odd after the start refuses its task: the map stops
    points = S.expand(S.load_suite(p))
    with DaskExecutor(scheduler=lc.scheduler_address, log=lambda _t: None) as ex:
        client.run(_pretend_other_commit)
        try:
            with pytest.raises(EnvironmentRefused, match="another physbench environment"):
                list(ex.map(run_point, points))
        finally:
            client.run(_restore_commit)


def _task_states(dask_scheduler=None) -> dict[str, int]:
    from collections import Counter

    return dict(Counter(ts.state for k, ts in dask_scheduler.tasks.items() if str(k).startswith("physbench-")))


def test_tasks_ahead_wait_on_the_scheduler_not_on_a_worker(cluster):
    """One task per worker thread runs and one more per thread waits, queued
    on the scheduler (so a free thread starts it without a round trip through
    the client, and a worker that dies holds only the task it runs: the
    retry test above)."""
    from physbench.harness.dask_executor import DaskExecutor
    from physbench.harness.selfbench.executors import sleep_task as _sleep

    lc, client = cluster
    _wait_workers(client)
    with DaskExecutor(scheduler=lc.scheduler_address, log=lambda _t: None) as ex:
        assert ex.jobs == 2 and ex.lookahead == 2
        seen = []
        for item, value in ex.map(_sleep, [0.4] * 8):
            assert value == item
            seen.append(client.run_on_scheduler(_task_states))
    # at each result: the next tasks were running on the two threads, those beyond queued on the scheduler
    assert all(s.get("processing", 0) <= 2 for s in seen), seen
    assert any(s.get("queued", 0) >= 1 for s in seen), seen


def test_check_on_dask_gives_the_inline_rows(tmp_path, cluster):
    from physbench.harness.conformance import check_main

    lc, client = cluster
    _wait_workers(client)
    args = dict(engines=["mujoco", "pymunk"], tags=None, junit=None, scenarios=["billiards.head_on"])
    a_dir, b_dir = tmp_path / "inline", tmp_path / "dask"
    code = check_main(**args, save_dir=a_dir, executor="inline")
    assert check_main(**args, save_dir=b_dir, executor="dask", scheduler=lc.scheduler_address) == code
    a = pd.read_parquet(next(a_dir.glob("*.parquet"))).set_index("run_key").sort_index()
    b = pd.read_parquet(next(b_dir.glob("*.parquet"))).set_index("run_key").sort_index()
    assert list(a.index) == list(b.index) and len(a) >= 2
    assert list(a["status"]) == list(b["status"]) and list(a["checks"]) == list(b["checks"])
    metrics = [c for c in ("max_penetration", "energy_drift", "momentum_drift") if c in a.columns]
    assert metrics
    for c in metrics:
        np.testing.assert_array_equal(a[c].to_numpy(float), b[c].to_numpy(float), err_msg=c)


def test_scheduler_needs_the_dask_executor(capsys):
    from physbench.harness.cli import main

    assert main(["sweep", "--suite", "smoke", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "--scheduler tcp://127.0.0.1:1: a scheduler address needs --executor dask" in capsys.readouterr().err


# ---------------------------------------------------------------------------
# a real cluster: `dask scheduler` and `dask worker` processes on loopback


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Cluster:
    """``dask scheduler`` and ``dask worker`` processes on 127.0.0.1, started
    as a team starts them (the recipe in docs/SWEEPS.md); each in its own
    session, so that stopping one stops its nanny's worker too."""

    def __init__(self, tmp: Path, env: dict[str, str]):
        import shutil

        self.dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
        if self.dask is None:
            pytest.skip("the dask command is not installed")
        self.tmp, self.env, self.procs = tmp, env, []
        self.address = f"tcp://127.0.0.1:{_free_port()}"

    def start(self, *args: str, extra_env: dict[str, str] | None = None):
        import subprocess

        log = open(self.tmp / f"dask-{len(self.procs)}.log", "wb")
        p = subprocess.Popen([self.dask, *args], cwd=self.tmp, env={**self.env, **(extra_env or {})},
                             stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(p)
        return p

    def worker(self, extra_env: dict[str, str] | None = None, *args: str):
        return self.start("worker", self.address, "--host", "127.0.0.1", "--nworkers", "1", "--nthreads", "1",
                          "--no-dashboard", "--death-timeout", "60", *args, extra_env=extra_env)

    def wait_workers(self, n: int, timeout: float = 120.0) -> None:
        from distributed import Client

        with Client(self.address, timeout="60s") as c:
            c.wait_for_workers(n, timeout=timeout)

    def stop(self, p) -> None:
        import subprocess

        try:
            os.killpg(p.pid, signal.SIGTERM)
            p.wait(timeout=20)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()

    def close(self) -> None:
        for p in reversed(self.procs):
            self.stop(p)


def test_a_real_cluster_gives_the_serial_metrics_keeps_a_killed_batch_and_refuses_another_physbench(tmp_path):
    """`dask scheduler` and two `dask worker` processes on 127.0.0.1;
    `physbench sweep --executor dask --scheduler ...` (a subprocess, as a
    team runs it): the serial executor's metrics (real engines and the fake
    one); a point that kills its Dask worker in the middle of a batch costs
    that point's error row only (every other point of the batch is ok) and
    the sweep finishes; a third worker of another physbench commit makes the
    sweep refuse the cluster (exit 2, the worker and the field named, nothing
    written).  Every process is stopped."""
    import subprocess

    from physbench.harness import schedule
    from physbench.harness.execute import Batch

    markers = tmp_path / "markers"
    markers.mkdir()
    suite = write(tmp_path, """
        [suite]
        engines = ["mujoco", "pymunk", "dask_fake"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        engines = ["mujoco", "pymunk"]
        grid = { dt = [0.002, 0.001] }
        [[sweep]]
        scenarios = ["billiards.head_on"]
        engines = ["dask_fake"]
        grid = { dt = [0.002, 0.001, 0.0025, 0.004], sleep_s = [0.0, 0.01], fault = ["none"] }
        [[sweep]]
        scenarios = ["billiards.head_on"]
        engines = ["dask_fake"]
        grid = { dt = [0.0015], fault = ["kill_worker"] }
    """)
    points = S.expand(S.load_suite(suite))
    cost, _ = schedule.expected_costs(tmp_path / "none", "suite", None, points, [])
    units = schedule.batched(sorted(points, key=lambda p: -cost(p)), cost, 0.1)
    killer = next(p for p in points if "kill_worker" in p.key)
    assert any(isinstance(u, Batch) and killer in u.items and len(u.items) > 1 for u in units)  # mid-batch

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0",
           # one task on a worker per thread (docs/SWEEPS.md's recipe): at the default 1.1 a
           # second task waits on the worker and dies with it, a point that never ran
           "DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION": "1.0",
           "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
           "PHYSBENCH_ADAPTERS": "dask_fake=tests.test_dask_executor:DaskFake"}
    worker_env = {KILL_OK_ENV: "1", MARKERS_ENV: str(markers), "TMPDIR": str(tmp_path)}
    cluster = _Cluster(tmp_path, env)
    before = _descendants()
    try:
        cluster.start("scheduler", "--host", "127.0.0.1", "--port", cluster.address.rsplit(":", 1)[1],
                      "--no-dashboard")
        for _ in range(2):
            cluster.worker(worker_env)
        cluster.wait_workers(2)

        def sweep(out: Path) -> subprocess.CompletedProcess:
            return subprocess.run([str(Path(sys.executable).parent / "physbench"), "sweep", "--suite", str(suite),
                                   "--executor", "dask", "--scheduler", cluster.address, "--out", str(out)],
                                  cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)

        serial, dask_out = tmp_path / "serial", tmp_path / "dask"
        assert S.sweep_main(str(suite), out_dir=serial, executor="serial",
                            engines=["mujoco", "pymunk"]) == 0
        r = sweep(dask_out)
        assert r.returncode == 0, r.stderr[-3000:]
        assert "note: the scheduler retries" not in r.stderr  # allowed-failures 0, as the recipe says
        b, man = consolidated(dask_out)
        assert man["executor"] == "dask" and len(b) == len(points) and b["point_key"].is_unique
        dead = b[b["point_key"] == killer.key]
        assert dead["status"].tolist() == ["error"]
        assert "the Dask worker died while running this point, twice" in dead["message"].iat[0]
        _o = b.drop(dead.index)
        assert (_o["status"] == "ok").all(), _o.loc[_o["status"] != "ok", ["point_key", "message"]].to_dict("records")
        a, _ = consolidated(serial)
        real = b[b["engine"].isin(["mujoco", "pymunk"])].set_index("point_key").loc[list(a["point_key"])]
        cols = [c for c in a.columns if c not in TIMING and not c.startswith("timing.")
                and pd.api.types.is_numeric_dtype(a[c]) and c != "schema_version"]
        assert "primary_error" in cols and "max_penetration" in cols
        for c in cols:
            np.testing.assert_array_equal(a[c].to_numpy(float), real[c].to_numpy(float), err_msg=c)
        assert list(a["status"]) == list(real["status"])

        # a third worker of another physbench commit (a preloaded module makes it report one)
        odd = tmp_path / "odd_physbench.py"
        odd.write_text("from physbench.harness import runner\nrunner.commit_id = lambda: '0123456789ab'\n")
        cluster.worker(worker_env, "--preload", str(odd))
        cluster.wait_workers(3)
        r = sweep(tmp_path / "refused")
        assert r.returncode == 2, r.stderr[-3000:]
        assert "runs another physbench environment than this client" in r.stderr
        assert "worker '0123456789ab'" in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "refused").exists()
    finally:
        cluster.close()
    assert not _wait_gone(_descendants() - before), "the cluster left processes behind"
