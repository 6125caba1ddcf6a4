"""Consensus across engines (harness/consensus.py): the spread of planted
traces, and the engines' converged runs of a spring pair compared with
the same runs made independently here."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from physbench.harness.consensus import run_consensus, spread
from physbench.harness.runner import Trace


def _trace(x: float, F: int = 4) -> Trace:
    t = np.arange(F) * 0.1
    pos = np.zeros((F, 1, 3))
    pos[:, 0, 0] = x * np.arange(F)  # body drifts x per frame
    quat = np.tile([1.0, 0, 0, 0], (F, 1, 1))
    return Trace(t, pos, quat, np.zeros((F, 1, 3)), np.zeros((F, 1, 3)), F)


def test_spread_of_planted_traces():
    out = spread({"a": _trace(0.0), "b": _trace(0.1), "c": _trace(0.3)}, 0.1, "final_state")
    # final frame (index 3): positions 0, 0.3, 0.9 -> largest pair a-c 0.9
    assert out["consensus_spread"] == pytest.approx(0.9)
    assert {(p["a"], p["b"]): p["distance"] for p in out["pairs"]} == pytest.approx(
        {("a", "b"): 0.3, ("a", "c"): 0.9, ("b", "c"): 0.6})
    assert math.isnan(spread({"a": _trace(0.0)}, 0.1)["consensus_spread"])  # one engine: no spread


def test_consensus_of_a_spring_pair_is_the_distance_of_the_fine_runs(tmp_path, spring_pair):
    """Each engine at dt/4 through the executor; the spread is the largest
    distance between those runs, made again here with the runner.
    Measured (dt/4 = 5 ms): 1.02e-3 m, pymunk 7.3.1 against mujoco 4.0.0
    and pybullet 3.2.7 (which agree to the last bit); the reference
    engine's rk4 5.2e-4 m from mujoco."""
    from physbench.contract.scene import load_scene
    from physbench.harness.references.self_consistency import distances
    from physbench.harness.runner import run

    p = tmp_path / "spring.toml"
    p.write_text(textwrap.dedent(spring_pair.format(params="")))
    engines = ["reference", "mujoco", "pybullet", "pymunk"]
    out = run_consensus(str(p), engines, executor="inline")
    ran = [e for e in engines if out["runs"][e][0] == "ok"]
    assert "reference" in ran and len(ran) >= 2
    assert out["dt_fine"] == pytest.approx(0.005)
    sc = load_scene(str(p))
    fine = {e: run(sc, e, {"dt": 0.005}, record_every=4, compute_metrics=False).trace.valid() for e in ran}
    want = max(distances(fine[a], fine[b], 0.02, "trajectory")[0] for a in ran for b in ran if a < b)
    assert out["consensus_spread"] == pytest.approx(want, rel=1e-12)
    assert 1e-6 < out["consensus_spread"] < 1e-2


def test_cli_consensus(tmp_path, capsys, spring_pair):
    import json

    from physbench.harness.cli import main

    p = tmp_path / "spring.toml"
    p.write_text(textwrap.dedent(spring_pair.format(params="")))
    assert main(["consensus", str(p), "--engines", "reference", "mujoco", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [(q["a"], q["b"]) for q in out["pairs"]] == [("mujoco", "reference")]
    assert out["consensus_spread"] == out["pairs"][0]["distance"] > 0
    assert main(["consensus", str(p), "--engines", "reference", "--json"]) == 1  # one engine: no consensus
    assert main(["consensus", str(tmp_path / "missing.toml")]) == 2


def test_check_gives_a_consensus_row_and_case(tmp_path, spring_pair):
    """A scene with ``[[check]] metric = "consensus_spread"``: ``physbench
    check`` runs the checked engines at dt / k^2 as one run of its own, a
    row of engine ``consensus`` with the spread (as ``physbench consensus``
    gives it) and a JUnit case in the ``consensus`` suite; the plain runs'
    checks are not asked for it.  Two bounds either side of the measured
    spread: one PASSes, one FAILs (exit 1)."""
    import json
    import xml.etree.ElementTree as ET

    import pandas as pd

    from physbench.harness.cli import main
    from physbench.harness.conformance.plan import plan

    p = tmp_path / "spring.toml"
    p.write_text(textwrap.dedent(spring_pair.format(params="")))
    spread_ = run_consensus(str(p), ["reference", "mujoco"], executor="inline")["consensus_spread"]
    assert spread_ > 0
    checks = (f'\n[[check]]\nmetric = "consensus_spread"\nmax = {spread_ * 2}\n'
              f'\n[[check]]\nmetric = "consensus_spread"\nmax = {spread_ / 2}\n'
              f'engines = ["reference", "mujoco"]\n')
    p.write_text(textwrap.dedent(spring_pair.format(params="")) + checks)
    runs, errors = plan([str(p)], ["reference", "mujoco"])
    assert not errors and [r.engine for r in runs] == ["consensus"]  # no plain run is asked for it
    assert runs[0].consensus == ("reference", "mujoco") and len(runs[0].checks) == 2
    junit, rows = tmp_path / "out.xml", tmp_path / "rows"
    code = main(["check", str(p), "--engines", "reference", "mujoco", "--junit", str(junit),
                 "--results-dir", str(rows)])
    assert code == 1
    suites = {s.get("name"): s for s in ET.parse(junit).getroot().iter("testsuite")}
    assert set(suites) == {"consensus"}
    assert [tc.find("failure") is None for tc in suites["consensus"].iter("testcase")] == [True, False]
    df = pd.concat([pd.read_parquet(q) for q in rows.rglob("*.parquet")])
    (row,) = df.to_dict("records")
    assert row["engine"] == "consensus" and row["status"] == "ok"
    assert row["consensus_spread"] == pytest.approx(spread_, rel=1e-12)
    assert row["engine_version"].startswith("reference ") and ", mujoco " in row["engine_version"]
    assert [v["outcome"] for v in json.loads(row["checks"])] == ["PASS", "FAIL"]
