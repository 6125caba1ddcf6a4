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
