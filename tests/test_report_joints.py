"""The report covers the joints family like the others: its sweep rows in
the work-precision and cost sections (primary metrics period_error and
joint_drift, targets from the scenes' checks as the rows carry them), its
breaking-point rows (the nightly's [[limit]] blocks on joints scenes) in the
breaking points, and the family in the accuracy ladder.  Planted rows only:
the report reads rows, never a scene."""

from __future__ import annotations

import math

import numpy as np

from physbench.harness import report as rp
from physbench.harness.results import write_rows
from tests.test_report import as_written, row
from tests.test_report_rows import _no_scene_loading

SID = "20261206T010000Z-jjjj"
LADDER = (0.064, 0.032, 0.016, 0.008, 0.004, 0.002, 0.001, 0.0005)


def _sweep_rows() -> list[dict]:
    rows = []
    # the pendulum's period error: second order for the constraint engines,
    # fourth for the reference's rk4
    for en, order, c in (("reference", 4, 1.0), ("mujoco", 1, 0.05), ("pybullet", 1, 0.5)):
        for dt in LADDER:
            r = row(scenario="joints.pendulum", engine=en, dt=dt, error=c * dt ** order, cost=1e-4 / dt,
                    sweep_id=SID, metric="period_error")
            rows.append(as_written(r))
    # the 10-link chain, primary metric joint_drift (m); pymunk diverges at the coarse end
    for en, c in (("reference", 1e-9), ("pymunk", 0.2)):
        for dt in LADDER[2:]:
            bad = en == "pymunk" and dt >= 0.016
            r = row(scenario="joints.chain_10", engine=en, dt=dt, error=c * dt, cost=1e-3 / dt, sweep_id=SID,
                    metric="joint_drift", status="diverged" if bad else "ok")
            rows.append(as_written(r))
    return rows


#: (scenario, variant, parameter, engine -> limit, range) of the nightly's joints [[limit]] blocks
LIMITS = [("joints.chain_load_100", None, "body[1].mass", {"reference": 1000.0, "pybullet": 0.9, "pymunk": 0.35},
           (0.1, 1000.0)),
          ("joints.pendulum", "release_170", "dt", {"reference": 0.05, "mujoco": 0.011, "box2d": 0.0042},
           (0.00025, 0.05)),
          # the chain length: the pattern's count, whole links
          ("joints.chain_10", None, "body[0].pattern.count", {"reference": 200, "rapier": 112, "pymunk": 1},
           (1, 200))]


def _limit_rows() -> list[dict]:
    rows = []
    for sc, va, par, limits, (lo, hi) in LIMITS:
        for en, lv in limits.items():
            lid = f"{sc}-{va}-{par}-{en}"
            holds_all = lv >= hi
            for v in np.geomspace(lo, hi, 7):
                held = bool(v <= lv)
                r = row(scenario=sc, variant=va, engine=en, dt=0.001, error=1e-4 * v / lo, cost=0.01, sweep_id=SID,
                        metric="joint_drift")
                rows.append({**r, "row_kind": "limit_eval", "point_key": f"limit:{lid}|{v!r}", "limit_id": lid,
                             "limit_param": par, "limit_value": float(v), "limit_holds": held,
                             "limit_reason": "" if held else "joint_drift: 0.0012 > 0.001"})
            rows.append({"row_kind": "limit", "point_key": f"limit:{lid}", "limit_id": lid, "scenario": sc,
                         "variant": va, "engine": en, "status": "ok", "suite": "nightly", "sweep_id": SID,
                         "timestamp": "2026-12-06T01:00:00+00:00", "commit": "jjjj", "limit_param": par,
                         "primary_metric": "joint_drift",
                         "limit_outcome": "holds_throughout" if holds_all else "found",
                         "limit_value": hi if holds_all else lv, "limit_lo": math.nan if holds_all else lv,
                         "limit_hi": math.nan if holds_all else lv * 1.08, "limit_direction": "below",
                         "limit_failed_check": "" if holds_all else "joint_drift: 0.0012 > 0.001",
                         "limit_runs": 7, "limit_cpu_s": 0.5, "limit_range_lo": lo, "limit_range_hi": hi,
                         "limit_phases": 1, "limit_overrides": "{}", "schema_version": 1})
    return rows


def _load(tmp_path):
    write_rows(_sweep_rows() + _limit_rows(), tmp_path / "sweeps" / "m1" / "nightly" / f"{SID}.parquet",
               append=False)
    return rp.load_results(tmp_path)


def test_joints_scenarios_have_work_precision_lines_with_their_targets(tmp_path):
    df = _load(tmp_path)
    wp = rp.work_precision(df)
    pend, chain = wp[("joints.pendulum", "")], wp[("joints.chain_10", "")]
    assert pend["primary_metric"] == "period_error" and chain["primary_metric"] == "joint_drift"
    # the targets the rows carry: each scene's check max on its primary metric
    assert (pend["threshold"], pend["threshold_source"]) == (1e-3, "check max")
    assert (chain["threshold"], chain["threshold_source"]) == (1e-3, "check max")
    assert {l["engine"] for l in pend["lines"]} == {"reference", "mujoco", "pybullet"}
    ref = next(l for l in pend["lines"] if l["engine"] == "reference")
    assert [p["dt"] for p in ref["points"]] == sorted(LADDER)
    assert all(p["ok"] for p in ref["points"])
    assert ref["points"][-1]["error"] == 0.064 ** 4
    # the diverged chain points are listed, not drawn
    assert {(p["label"], p["status"]) for p in chain["not_ok"]} == {("pymunk", "diverged")}
    assert [p["dt"] for p in chain["not_ok"]] == [0.016]
    # the cost to reach each scene's target: pybullet's pendulum reaches 1e-3 at dt 0.002
    ct = rp.cost_to_target(df).set_index(["scenario", "engine"])
    assert ct.loc[("joints.pendulum", "pybullet"), "reached"]
    assert ct.loc[("joints.pendulum", "pybullet"), "dt"] == 0.002
    assert ct.loc[("joints.chain_10", "reference"), "reached"]


def test_joints_breaking_points_and_the_family_in_the_ladder(tmp_path):
    df = _load(tmp_path)
    bp = rp.breaking_points(df)
    got = {(r["scenario"], r["variant"], r["limit_param"], r["engine"]): r for r in bp.to_dict("records")}
    assert len(got) == sum(len(x[3]) for x in LIMITS)
    assert got[("joints.chain_load_100", "", "body[1].mass", "pybullet")]["limit_value"] == 0.9
    assert got[("joints.chain_load_100", "", "body[1].mass", "reference")]["limit_outcome"] == "holds_throughout"
    assert got[("joints.pendulum", "release_170", "dt", "box2d")]["limit_value"] == 0.0042
    assert got[("joints.chain_10", "", "body[0].pattern.count", "rapier")]["limit_value"] == 112
    assert rp.fmt_limit(got[("joints.chain_10", "", "body[0].pattern.count", "rapier")], short=True) == "\u2264 112"
    glance = rp.at_a_glance(df)
    assert "joints" in set(glance["family"])


def test_joints_family_on_the_page(tmp_path, monkeypatch):
    df = _load(tmp_path)
    _no_scene_loading(monkeypatch)  # the page reads the rows only
    page = rp.render_html(df, physbench_commit="x")
    wp = page.split('id="work-precision"')[1].split("</section>")[0]
    assert "<b>joints.pendulum</b>: primary metric <code>period_error</code>" in wp
    assert "<b>joints.chain_10</b>: primary metric <code>joint_drift</code>" in wp
    assert wp.count("<img") >= 2
    bp = page.split('id="breaking-points"')[1].split("</section>")[0]
    assert "joints.chain_load_100: <code>body[1].mass</code>" in bp
    assert "joints.pendulum / release_170: <code>dt</code>" in bp
    assert "joints.chain_10: <code>body[0].pattern.count</code>" in bp
    assert bp.count("<img") == len(LIMITS)  # each search's plot
    assert "joint_drift: 0.0012 &gt; 0.001" in bp
