"""Breaking points (harness/limits.py, ``physbench limits``, ``[[limit]]``)."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest

from physbench.harness.limits import (EVAL_ROW, FAILS_THROUGHOUT, FOUND, HOLDS_THROUGHOUT, LimitRequest, Verdict,
                                      drive, run_search, search, search_steps)
from physbench.contract.phase import phase_values


def _threshold(t: float, below: bool = True):
    calls = []

    def crit(x: float) -> Verdict:
        calls.append(x)
        ok = x <= t if below else x >= t
        return Verdict(ok, "" if ok else f"x={x} past {t}", cpu_s=0.5)

    return crit, calls


@pytest.mark.parametrize("t", [1.7e-4, 0.0123, 0.37, 0.999])
@pytest.mark.parametrize("tol", [0.2, 0.05, 0.01])
def test_bisection_finds_known_threshold_to_tolerance(t, tol):
    crit, calls = _threshold(t)
    r = search(crit, 1e-4, 1.0, tol)
    assert r.outcome == FOUND and r.direction == "below"
    lo, hi = r.bracket
    assert lo <= t < hi  # the threshold is inside the bracket ...
    assert hi / lo - 1 <= tol  # ... which is as narrow as asked
    assert r.limit == lo and abs(r.limit - t) / t <= tol
    assert r.failed_check == f"x={hi} past {t}"
    assert r.runs == len(calls) == len(set(calls))  # no value evaluated twice
    assert r.cpu_s == pytest.approx(0.5 * len(calls))
    # walk of <= 8 steps, then bisection: log2(log(2.0..)/log(1+tol)) steps
    assert len(calls) <= 1 + 8 + math.ceil(math.log2(math.log(10 ** 0.5) / math.log(1 + tol))) + 1


def test_integer_setting_held_above_threshold():
    crit, _ = _threshold(37, below=False)  # like solver iterations: enough of them hold
    r = search(crit, 1, 200, 0.05, integer=True)
    assert r.outcome == FOUND and r.direction == "above"
    assert r.limit == 37 and r.bracket == (36, 37)
    assert all(isinstance(x, int) for x, _ in r.evaluations)


def test_linear_range_through_zero():
    crit, _ = _threshold(0.62)
    r = search(crit, 0.0, 1.0, 0.01)  # restitution-like: linear, tol relative to the range width
    lo, hi = r.bracket
    assert lo <= 0.62 < hi and hi - lo <= 0.01


def test_holds_and_fails_throughout():
    crit, _ = _threshold(10.0)
    r = search(crit, 0.1, 5.0)
    assert r.outcome == HOLDS_THROUGHOUT and r.limit == 5.0 and r.bracket is None
    crit, _ = _threshold(0.01)
    r = search(crit, 0.1, 5.0)
    assert r.outcome == FAILS_THROUGHOUT and r.limit is None and r.failed_check.startswith("x=0.1")


def test_first_breaking_point_when_not_monotone():
    # fails only in (0.1, 0.5]: bisecting the whole range would land past it
    r = search(lambda x: Verdict(not (0.1 < x <= 0.5), "window"), 0.01, 100.0, 0.02)
    assert r.outcome == FOUND and r.bracket[0] <= 0.1 < r.bracket[1]


@pytest.mark.parametrize("bad", [(1.0, 1.0), (2.0, 1.0), (math.nan, 1.0), (-1.0, 1.0)])
def test_bad_range(bad):
    with pytest.raises(ValueError, match="range"):
        search(lambda x: Verdict(True), *bad, log=True)


# --- stored rows: a rerun reads finished evaluations back --------------------


def _fake_rows(threshold: float):
    runs = []

    def evaluate(req, limit_id, value, phase):
        runs.append((value, phase))
        # phase 0.5 fails a little earlier: a value holds only in all phases
        ok = value <= (threshold * 0.97 if phase == 0.5 else threshold)
        return {"row_kind": EVAL_ROW, "point_key": req.eval_key(limit_id, value, phase), "limit_id": limit_id,
                "limit_value": value, "phase": phase, "limit_holds": ok, "limit_reason": "" if ok else "past",
                "limit_cpu_s": 0.25, "status": "ok"}

    return evaluate, runs


def test_search_resumes_from_stored_rows():
    req = LimitRequest("tunnelling.bullet_100", None, "pymunk", "dt", 1e-3, 0.1, phases=2, tol=0.05)
    evaluate, runs = _fake_rows(0.02)
    stored: dict = {}
    r1, s1 = run_search(req, lambda row: stored.__setitem__(row["point_key"], row), {}, evaluate)
    assert r1.outcome == FOUND and r1.bracket[0] <= 0.02 * 0.97 < r1.bracket[1]  # the worse phase decides
    assert s1["limit_new_runs"] == len(runs) == len(stored) == r1.runs
    # interrupted after 5 stored evaluations: the rerun runs only the rest
    evaluate2, runs2 = _fake_rows(0.02)
    first5 = dict(list(stored.items())[:5])
    r2, s2 = run_search(req, lambda row: None, first5, evaluate2)
    assert len(runs2) == len(runs) - 5 and s2["limit_new_runs"] == len(runs) - 5
    assert (r2.limit, r2.bracket, r2.runs) == (r1.limit, r1.bracket, r1.runs)
    # everything stored: no run at all
    evaluate3, runs3 = _fake_rows(0.02)
    r3, _ = run_search(req, lambda row: None, stored, evaluate3)
    assert runs3 == [] and r3.limit == r1.limit


# --- pymunk: the speed at which a bullet first passes a thin wall --------------


WALL_X, HALF_W, R, DT, N_PHASES = 0.05, 0.002, 0.005, 1 / 240, 16


def _caught_in_every_phase(v: float, duration: float) -> bool:
    """The step-geometry model (see the test's docstring): in phase f the
    centre after step k is at x_k = (k - f) v dt; the wall turns the sphere
    back iff some x_k lies in (WALL_X - HALF_W - R, WALL_X)."""
    a = WALL_X - HALF_W - R
    n = int(round(duration / DT))
    for f in phase_values(N_PHASES):
        if not any(a < (k - f) * v * DT < WALL_X for k in range(1, n + 1)):
            return False
    return True


def test_pymunk_tunnelling_speed_follows_step_geometry():
    """pymunk has no continuous collision detection: a sphere (radius r) that
    flies at v towards a wall of thickness w is only seen where a step ends.
    Chipmunk moves the bodies first, then finds the overlaps, so the contacts
    of step k see the centre at x_k = x_0 + k v dt.

    What decides whether some step catches the sphere: the sphere overlaps
    the wall when its centre is within r of it, x in (a - r, a + w) with a the
    near face.  What the contact then does: a circle whose centre lies inside
    a box is pushed out through the face it is nearest to.  Past the wall's
    mid-plane (x > a + w/2) that is the far face: the contact pushes the
    sphere on, and it is through.  So a step turns the sphere back only if its
    centre lands in the window (a - r, a + w/2), of length r + w/2.  Steps
    are v dt apart: every placement of the steps lands one in the window iff

        v dt < r + w/2,   v* = (r + w/2) / dt

    (not (2 r + w) / dt: a step deep in the wall's far half does not help).
    For r = 5 mm, w = 4 mm, dt = 1/240 s: v* = 1.68 m/s.  With N step phases
    (starts moved back by i/N dt) a speed fails once one of the N placements
    misses the window, which happens for v dt between r + w/2 and
    (r + w/2) N / (N - 1): the model above evaluates that exactly, phase by
    phase, and the search on it must find the same limit as on pymunk."""
    dur = 0.5
    req = LimitRequest("tunnelling.bullet_100", None, "pymunk", "body[0].velocity[0]", 0.3, 10.0,
                       phases=N_PHASES, tol=0.01, checks=("tunnelled",),
                       overrides=(("static[0].position", [WALL_X, 0.0, 0.0]), ("scenario.duration", dur),
                                  ("scenario.dt", DT)))
    res, summary = run_search(req, lambda row: None, {})
    assert res.outcome == FOUND and res.direction == "below"
    assert "tunnelled" in res.failed_check
    model = search(lambda v: Verdict(_caught_in_every_phase(v, dur)), 0.3, 10.0, 0.01)
    v_star = (R + HALF_W) / DT
    assert v_star <= model.bracket[1] and model.bracket[0] <= v_star * N_PHASES / (N_PHASES - 1)
    # pymunk's breaking point is the geometry's, to the search's tolerance
    assert res.bracket[0] <= model.bracket[1] and model.bracket[0] <= res.bracket[1]
    assert res.limit == pytest.approx(model.limit, rel=0.01)
    # and not the naive "any overlap catches it" speed (2 r + w) / dt = 3.12 m/s
    assert res.bracket[1] < (2 * R + 2 * HALF_W) / DT * 0.8
    assert summary["limit_runs"] == res.runs and summary["limit_outcome"] == FOUND


# --- the command line ---------------------------------------------------------


def _cli(args, capsys):
    from physbench.harness.cli import main

    rc = main(args)
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_json_only_and_rerun_reads_back(tmp_path, capsys):
    args = ["limits", "tunnelling.bullet_100", "--engine", "pymunk", "--param", "body[0].velocity[0]",
            "--range", "0.3", "10", "--phases", "4", "--tol", "0.1", "--check", "tunnelled",
            "--set", "static[0].position=[0.05,0,0]", "--set", "scenario.duration=0.5",
            "--out", str(tmp_path), "--json"]
    rc, out, err = _cli(args, capsys)
    assert rc == 0, err
    doc = json.loads(out)  # stdout is exactly one JSON object
    assert out.count("\n") == 1
    assert {"limit", "bracket", "failed_check", "runs", "cpu_s"} <= set(doc)
    lo, hi = doc["bracket"]
    assert lo == doc["limit"] and hi / lo - 1 <= 0.1 and 1.5 < lo < 2.2
    assert "tunnelled" in doc["failed_check"] and doc["runs"] >= 5 and doc["cpu_s"] > 0
    files = sorted(tmp_path.rglob("*.parquet"))
    assert len(files) == 1
    df = pd.read_parquet(files[0])
    evals = df[df["row_kind"] == EVAL_ROW]
    assert len(evals) == doc["runs"] and evals["point_key"].is_unique
    assert set(evals["phase"]) <= set(phase_values(4))
    summary = df[df["row_kind"] == "limit"].iloc[0]
    assert summary["limit_value"] == doc["limit"] and summary["limit_hi"] == hi
    # the same search again: every evaluation read back, nothing new stored
    rc, out2, err2 = _cli(args, capsys)
    assert rc == 0 and json.loads(out2) == doc and "read back" in err2
    assert sorted(tmp_path.rglob("*.parquet")) == files


@pytest.mark.parametrize("extra,needle", [
    (["--param", "body[9].mass", "--range", "1", "2"], "body[9]"),
    (["--param", "frobnicate", "--range", "1", "2"], "not a setting"),
    (["--param", "dt", "--range", "0.01", "0.001"], "LO < HI"),
    (["--param", "dt", "--range", "0.001", "x"], "expected a number"),
    (["--param", "body[0].mass", "--range", "-1", "2"], "body[0].mass"),
    (["--param", "dt", "--range", "0.001", "0.01", "--check", "nope"], "--check nope"),
])
def test_cli_bad_input_exit_2(extra, needle, tmp_path, capsys):
    rc, out, err = _cli(["limits", "tunnelling.bullet_100", "--engine", "pymunk", *extra, "--out", str(tmp_path)],
                        capsys)
    assert rc == 2 and needle in err and "Traceback" not in err and out == ""


def test_phases_need_free_flight(tmp_path, capsys):
    rc, _, err = _cli(["limits", "stacking.heavy_on_light", "--engine", "pymunk", "--param", "dt",
                       "--range", "0.001", "0.03", "--phases", "4", "--out", str(tmp_path)], capsys)
    assert rc == 2 and "free flight" in err


# --- [[limit]] suite blocks ---------------------------------------------------


def _suite(tmp_path, body: str):
    p = tmp_path / "s.toml"
    p.write_text('[suite]\nname = "lt"\nengines = ["pymunk", "mujoco"]\n' + body)
    return p


def _suite_errors(tmp_path, body: str) -> str:
    from physbench.harness.suite import load_suite
    from physbench.harness.sweep_store import SuiteError

    with pytest.raises(SuiteError) as ei:
        load_suite(_suite(tmp_path, body))
    return "\n".join(ei.value.errors)


def test_limit_block_validated(tmp_path):
    head = '[[limit]]\nscenarios = ["stacking.nope", "stacking.heavy_on_light"]\nparam = "dt"\n'
    text = _suite_errors(tmp_path, head + 'range = [0.03, 0.001]\nphases = 4\n')
    assert "limit[0].range" in text and "LO < HI" in text
    text = _suite_errors(tmp_path, head + 'range = [0.001, 0.03]\nphases = 4\nengines = ["pybullet"]\n')
    assert "limit[0].scenarios[0]" in text and "'stacking.nope'" in text
    assert "limit[0].engines[0]" in text and "pybullet" in text
    head = '[[limit]]\nscenarios = ["stacking.heavy_on_light"]\nparam = "dt"\n'
    assert "free flight" in _suite_errors(tmp_path, head + 'range = [0.001, 0.03]\nphases = 4\n')
    assert "bogus" in _suite_errors(tmp_path, head + 'range = [1, 30]\nset = { bogus = 1 }\n')


def test_sweep_computes_limit_blocks(tmp_path):
    from physbench.harness.suite import load_suite
    from physbench.harness.sweep import sweep_main
    from physbench.harness.sweep_store import read_sweeps

    p = _suite(tmp_path, '[[limit]]\nscenarios = ["tunnelling.bullet_100"]\nparam = "body[0].velocity[0]"\n'
                         'range = [0.3, 10]\nphases = 2\ntol = 0.2\nchecks = ["tunnelled"]\n'
                         'set = { "static[0].position" = [0.05, 0.0, 0.0], "scenario.duration" = 0.5 }\n')
    s = load_suite(p)
    assert [(r.engine, r.param) for r in s.limits] == [("pymunk", "body[0].velocity[0]"),
                                                        ("mujoco", "body[0].velocity[0]")]
    assert sweep_main(str(p), out_dir=tmp_path / "out") == 0
    df = read_sweeps(tmp_path / "out", suite="lt")
    res = df[df["row_kind"] == "limit"].set_index("engine")
    assert set(res.index) == {"pymunk", "mujoco"} and (res["limit_outcome"] == FOUND).all()
    for eng, r in res.iterrows():
        ev = df[(df["row_kind"] == EVAL_ROW) & (df["engine"] == eng)]
        assert r["limit_runs"] == len(ev)
        # the limit holds in every phase, the bracket's other end fails in one
        assert ev[ev["limit_value"] == r["limit_value"]]["limit_holds"].all()
        other = r["limit_hi"] if r["limit_direction"] == "below" else r["limit_lo"]
        assert not ev[ev["limit_value"] == other]["limit_holds"].all()


# --- rounds: several values at once, the same answer --------------------------


def _window(x: float) -> Verdict:
    return Verdict(not (0.1 < x <= 0.5), "window")


@pytest.mark.parametrize("case", [
    dict(crit=lambda x: Verdict(x <= 0.0123, "past"), lo=1e-4, hi=1.0, tol=0.01),
    dict(crit=lambda x: Verdict(x <= 0.37, "past"), lo=1e-4, hi=1.0, tol=0.05),
    dict(crit=lambda x: Verdict(x >= 37, "few"), lo=1, hi=200, tol=0.05, integer=True),
    dict(crit=lambda x: Verdict(x <= 0.62, "past"), lo=0.0, hi=1.0, tol=0.01),
    dict(crit=lambda x: Verdict(x <= 10.0, "past"), lo=0.1, hi=5.0, tol=0.05),
    dict(crit=lambda x: Verdict(x <= 0.01, "past"), lo=0.1, hi=5.0, tol=0.05),
    dict(crit=_window, lo=0.01, hi=100.0, tol=0.02),
])
def test_wider_rounds_give_the_same_answer_in_fewer_rounds(case):
    """Width 1 is the one-at-a-time search value for value (``search_steps``);
    wider rounds (2, 3, 7, 15 values) give the same outcome, limit, bracket,
    direction and failed check for monotone and non-monotone criteria, with
    every round's first value one the one-at-a-time search evaluates; the
    rounds drop once 3 or more values go at once (two bisection levels per
    round), and the wider search evaluates every value of the narrow one."""
    kw = {k: v for k, v in case.items() if k != "crit"}
    crit = case["crit"]
    serial_values = []
    one = drive(search_steps(**kw), lambda x: serial_values.append(x) or crit(x))
    assert [x for x, _ in one.evaluations] == serial_values and one.rounds == one.runs == len(serial_values)
    assert search(crit, **kw, width=1).evaluations == one.evaluations
    answer = (one.outcome, one.limit, one.bracket, one.direction, one.failed_check)
    for width in (2, 3, 7, 15):
        wide = search(crit, **kw, width=width)
        assert (wide.outcome, wide.limit, wide.bracket, wide.direction, wide.failed_check) == answer, width
        assert {x for x, _ in wide.evaluations} >= set(serial_values)
        assert wide.rounds <= one.rounds
        if one.outcome == FOUND and width >= 3:
            assert wide.rounds < one.rounds, (width, wide.rounds, one.rounds)
    if one.outcome == FOUND:
        # 7 values a round: three bisection levels per round, the walk 7 steps at a time
        assert search(crit, **kw, width=7).rounds <= 2 + math.ceil((one.rounds - 1) / 3)


def test_rounds_hold_the_bracket_of_a_monotone_threshold():
    """A deterministic monotone criterion: at every width the bracket holds
    the threshold, is as narrow as asked, and bisection rounds fall as
    log2(width + 1) levels each."""
    t, tol = 0.0123, 0.01
    crit = lambda x: Verdict(x <= t, "past")
    rounds = {}
    for width in (1, 3, 7, 15, 31):
        r = search(crit, 1e-4, 1.0, tol, width=width)
        lo, hi = r.bracket
        assert lo <= t < hi and hi / lo - 1 <= tol
        rounds[width] = r.rounds
    assert rounds[1] > rounds[3] > rounds[7] > rounds[15] >= rounds[31]
    assert rounds[31] <= 4, rounds
