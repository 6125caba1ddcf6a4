"""Every result row and sweep manifest names its machine by the environment
fingerprint (harness/fingerprint.py), the same way for run, check and sweep,
and the report groups rows by that id."""

from __future__ import annotations

import json

import pandas as pd

from physbench.harness import fingerprint as F
from physbench.harness import points as P, sweep as S, sweep_store as ST
from physbench.contract.scene import load_scene


def _machine_cols(row: dict) -> dict:
    return {k[len("machine."):]: v for k, v in row.items() if k.startswith("machine.")}


def test_run_and_status_rows_carry_the_fingerprint(head_on_path):
    from physbench.harness.runner import run

    res = run(load_scene(head_on_path), "mujoco")
    m = _machine_cols(res.row())
    fp = F.fingerprint()
    assert m["id"] == F.machine_id() == ST.machine_id()
    assert m["env_id"] == F.env_id()
    assert m["cpu"] == fp["cpu"]["model"]
    assert m["cpu_flags"] == " ".join(fp["cpu"]["flags"])
    assert m["numpy"] == fp["versions"]["numpy"] and m["scipy"] == fp["versions"]["scipy"]
    assert m["blas"] == "; ".join(f"{b['library']} {b['version']} {b['core_type']}".strip() for b in fp["blas"])
    # a row made without a run (scene failed to load, worker died) names the same machine
    point = P.Point("billiards.head_on", None, "mujoco", (("dt", 0.001),))
    status = P.failure_row(point.request(), "error", "test", 0.0)
    assert _machine_cols(status) == m


def test_check_rows_and_sweep_name_one_machine(tmp_path, capsys):
    from physbench.harness.conformance import check_main

    check_main(["mujoco"], None, None, ["billiards.head_on"], save_dir=tmp_path / "check")
    check = pd.concat(pd.read_parquet(p) for p in (tmp_path / "check").glob("*.parquet"))
    assert set(check["machine.id"]) == {ST.machine_id()}
    assert S.sweep_main("smoke", engines=["mujoco"], out_dir=tmp_path / "sweeps", resume=False) == 0
    man_path, = (tmp_path / "sweeps" / ST.machine_id() / "smoke").glob("*.manifest.json")
    man = json.loads(man_path.read_text())
    assert man["machine_id"] == ST.machine_id() == man["machine"]["id"]
    assert man["fingerprint"] == json.loads(json.dumps(F.fingerprint()))
    rows = pd.read_parquet(man_path.with_name(man_path.name.replace(".manifest.json", ".parquet")))
    assert set(rows["machine.id"]) == set(rows["machine_id"]) == {ST.machine_id()}

    # the report files check rows and sweep rows under the one machine id
    from physbench.harness.report import load_results

    df = load_results(tmp_path)
    assert set(df["machine_id"]) == {ST.machine_id()}, df["machine_id"].value_counts()


def test_report_groups_old_rows_by_host():
    """Rows written before the fingerprint (no machine.id) still group by host."""
    from physbench.harness.report import normalise

    df = pd.DataFrame([
        {"scenario": "a.b", "engine": "mujoco", "machine.host": "oldbox", "source": "check"},
        {"scenario": "a.b", "engine": "mujoco", "machine.host": "vm", "machine.id": "amd-epyc-1234abcd",
         "source": "check"},
        {"scenario": "a.b", "engine": "mujoco", "machine.host": "vm", "machine.id": "amd-epyc-1234abcd",
         "machine_id": "amd-epyc-1234abcd", "source": "sweep"},
    ])
    assert list(normalise(df)["machine_id"]) == ["oldbox", "amd-epyc-1234abcd", "amd-epyc-1234abcd"]


def test_rows_made_without_a_run_name_the_machine():
    """A RunResult built for a run that never started (a scene that failed to
    load, an engine that cannot be imported) still names its machine."""
    from physbench.harness.runner import RunResult

    row = RunResult("a.b", None, "no_such_engine", "", "error", "scene failed to load", {}).row()
    assert row["machine.id"] == F.machine_id() and row["machine.env_id"] == F.env_id()
