"""Diagnosing traces (issue 25), read back with rerun.chunk.RrdReader: the
model's ghost, per-body error series, contacts, event markers, context
documents, and ``check --traces``."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from physbench.harness.runner import RunResult, Trace, run
from physbench.contract.scene import load_scene
from physbench.harness.trace import write_rrd
from physbench.harness.trace.contacts import harness_contacts
from tests.test_trace_rrd import F32, column_array, read_rrd, static_value, temporal

pytest.importorskip("rerun.chunk")


def still_result(scene, engine: str, n_frames: int) -> RunResult:
    """Every body sits at its initial pose for n_frames frames of scene.dt."""
    n = scene.n_bodies
    tr = Trace.allocate(n_frames, n)
    tr.t[:] = np.arange(n_frames) * scene.dt
    x0, q0, _, _ = scene.initial_state()
    tr.pos[:], tr.quat[:] = x0[None], q0[None]
    tr.vel[:] = 0.0
    tr.angvel[:] = 0.0
    tr.n_frames = n_frames
    return RunResult(scene.id, scene.variant, engine, "0", "ok", "", {"dt": scene.dt}, trace=tr)


def model_of(scene):
    from physbench.harness.references import get_model

    return get_model(scene.reference_model)(scene)


# ---------------------------------------------------------------------------
# ghost and error


@pytest.mark.parametrize("sid", ["billiards.head_on", "gyroscopic.dzhanibekov"])
def test_ghost_equals_the_model_and_error_is_the_distance_to_it(sid, tmp_path):
    scene = load_scene(sid)
    F = 301
    res = still_result(scene, "fake", F)
    write_rrd(tmp_path / "g.rrd", scene, [res], diagnose=True)
    data = read_rrd(tmp_path / "g.rrd")
    model = model_of(scene)
    t_all = res.trace.t
    pos_ref, quat_ref = model.trajectory(t_all)
    for i, body in enumerate(scene.bodies):
        df = temporal(data, f"/world/model/{body.name}")
        steps = df["step"].to_numpy()
        assert len(df) == F
        sample = np.array([0, F // 3, F // 2, F - 1])
        pos = column_array(df, "Transform3D:translation")[sample]
        np.testing.assert_allclose(pos, pos_ref[steps[sample], i], **F32)
        if quat_ref is not None:  # dzhanibekov: the model's orientation, xyzw in rerun
            q = column_array(df, "Transform3D:quaternion")[sample]
            expect = quat_ref[steps[sample], i][:, [1, 2, 3, 0]]
            np.testing.assert_allclose(q, expect, **F32)
        # the error series: |x0 - x_ref(t)| (the fake body never moves)
        err = np.array([v[0] for v in temporal(data, f"/metrics/fake/error/{body.name}")["Scalars:scalars"]])
        np.testing.assert_allclose(err, np.linalg.norm(res.trace.pos[:, i] - pos_ref[:, i], axis=1), rtol=1e-12)
    # the ghost is translucent and the model's predictions are in the file
    text = static_value(data, "/context/model", "TextDocument:text")[0]
    assert scene.reference_model in text
    if sid == "billiards.head_on":
        assert "velocity after impact" in text
        assert f"{model.v2_post[0]:.6g}" in text
    else:
        assert "flip period" in text


def test_without_diagnose_the_plain_layout_has_no_ghost(tmp_path):
    scene = load_scene("billiards.head_on")
    write_rrd(tmp_path / "w.rrd", scene, [still_result(scene, "fake", 11)])
    data = read_rrd(tmp_path / "w.rrd")
    assert not [e for e in data if e.startswith(("/world/model", "/events", "/context"))]


# ---------------------------------------------------------------------------
# a planted failure: the bullet through the wall on pymunk


@pytest.fixture(scope="module")
def bullet(tmp_path_factory):
    pytest.importorskip("pymunk")
    scene = load_scene("tunnelling.bullet_100")
    res = run(scene, "pymunk", contact_cap=16)
    assert res.status == "ok" and res.metrics["tunnelled"] == 1.0  # pymunk has no CCD: the planted failure
    from physbench.harness.conformance import evaluate

    outcomes = [o for o in evaluate(scene, res) if "@" not in o.metric]
    path = tmp_path_factory.mktemp("bullet") / "b.rrd"
    write_rrd(path, scene, [res], diagnose=True, outcomes=outcomes, checks={c.metric: c for c in scene.checks})
    return scene, res, read_rrd(path)


def test_tunnelling_marker_at_the_step_the_bullet_passes_the_wall(bullet):
    scene, res, data = bullet
    wall = scene.statics[0]
    x = res.trace.valid().pos[:, 0, 0]
    passed = int(np.nonzero(x > wall.position[0])[0][0])  # first frame beyond the wall's mid-plane
    ev = temporal(data, "/events/pymunk")
    texts = [v for v in ev["TextLog:text"]]
    hits = [s for s, txt in zip(ev["step"], texts) if "tunnelling" in str(txt)]
    assert hits == [passed]
    level = ev["TextLog:level"][[i for i, txt in enumerate(texts) if "tunnelling" in str(txt)][0]]
    assert "ERROR" in str(level)


def test_context_document_has_settings_checks_and_verdicts(bullet):
    _, res, data = bullet
    text = static_value(data, "/context/pymunk", "TextDocument:text")[0]
    assert "| tunnelled | == 0 | 1 | XFAIL |" in text
    assert f"- dt = {res.settings['dt']:.6g}" in text
    for note in res.notes:
        assert note in text


# ---------------------------------------------------------------------------
# contacts


def test_harness_contact_of_a_sphere_in_a_plane_is_exact():
    scene = load_scene("billiards.ball_drop_bounce")
    r = scene.bodies[0].radius
    tr = Trace.allocate(2, 1)
    tr.t[:] = [0.0, scene.dt]
    tr.pos[:] = [[[0.3, 0.1, r + 1.0]], [[0.3, 0.1, r - 0.002]]]  # frame 1: 2 mm into the ground
    tr.quat[:] = [1.0, 0.0, 0.0, 0.0]
    tr.vel[:] = tr.angvel[:] = 0.0
    tr.n_frames = 2
    (frame, rows), = harness_contacts(scene, tr)
    assert frame == 1 and rows.shape == (1, 7)
    np.testing.assert_allclose(rows[0, 3:6], [0.0, 0.0, -1.0])  # from the body into the plane
    assert rows[0, 6] == pytest.approx(0.002, abs=1e-12)
    np.testing.assert_allclose(rows[0, 0:3], [0.3, 0.1, -0.001], atol=1e-12)  # midway between the surfaces


def test_harness_contact_normal_of_two_boxes_is_the_separating_axis():
    from physbench.contract.geometry import Placed
    from physbench.harness.trace.contacts import pair_normals

    R = np.eye(3)[None]
    A = Placed("box", np.array([[0.0, 0.0, 0.0]]), R, half_extents=[0.5, 0.5, 0.5])
    B = Placed("box", np.array([[0.2, 0.1, 0.95]]), R, half_extents=[0.5, 0.5, 0.5])
    np.testing.assert_allclose(pair_normals(A, B)[0], [0.0, 0.0, 1.0])  # least overlap along z


def test_contacts_in_a_column_on_pymunk(tmp_path):
    pytest.importorskip("pymunk")
    scene = load_scene("stacking.column_5")
    res = run(scene, "pymunk", contact_cap=4)
    write_rrd(tmp_path / "c.rrd", scene, [res], diagnose=True, contact_cap=3)
    data = read_rrd(tmp_path / "c.rrd")
    pen = temporal(data, "/metrics/pymunk/penetration")
    depth = dict(zip(pen["step"], (v[0] for v in pen["Scalars:scalars"])))
    arrows = temporal(data, "/world/pymunk/contacts/normals")
    assert len(arrows) == sum(d > 0 for d in depth.values())  # only frames with contact
    for step, vec in zip(arrows["step"], arrows["Arrows3D:vectors"]):
        lengths = np.linalg.norm(np.array([list(v) for v in vec], float), axis=1)
        assert len(lengths) <= 3  # the cap
        assert lengths.max() == pytest.approx(depth[step], rel=1e-5)  # the deepest is the frame's penetration
    # the engine's own contact points, at most 4 per frame
    eng = temporal(data, "/world/pymunk/engine_contacts")
    assert len(eng) > 0 and max(len(v) for v in eng["Points3D:positions"]) <= 4
    pts = np.concatenate([np.array([list(p) for p in v], float) for v in eng["Points3D:positions"]])
    assert np.all(np.abs(pts[:, 1]) < 1e-12)  # pymunk is planar: the x-z plane


def test_plain_run_records_no_contacts():
    scene = load_scene("billiards.head_on")
    assert run(scene, "reference").contacts is None


# ---------------------------------------------------------------------------
# check --traces


def test_check_traces_writes_exactly_the_failing_cases(tmp_path):
    pytest.importorskip("pymunk")
    from physbench.harness.conformance import FAIL, XFAIL, ERROR, check_main

    junit = tmp_path / "j.xml"
    traces = tmp_path / "traces"
    check_main(["pymunk", "reference"], None, str(junit), ["tunnelling.bullet_100"], save_dir=tmp_path / "rows",
               traces=traces)
    root = ET.parse(junit).getroot()
    failing, linked = set(), set()
    for tc in root.iter("testcase"):
        bad = [c for c in tc if c.tag in ("failure", "error", "skipped") and c.get("type") in (FAIL, XFAIL, ERROR)]
        props = {p.get("name"): p.get("value") for p in tc.iter("property")}
        if bad:
            assert "trace" in props, tc.get("name")
            failing.add(tc.get("classname").split(".")[1])
            linked.add(props["trace"])
            assert f"trace: {props['trace']}" in tc.find("system-out").text
        else:
            assert "trace" not in props
    files = {str(p) for p in traces.glob("*.rrd")}
    assert files == linked and files  # one file per failing case, no other
    assert failing == {"pymunk"}  # the reference engine's CCD passes the bullet checks
    assert str(traces / "tunnelling.bullet_100--pymunk.rrd") in files
    # the result rows carry the same absolute path in each failing check's ``trace``
    (rows,) = list((tmp_path / "rows").glob("*.parquet"))

    def case(r, metric):  # the JUnit testcase name of a row's check
        v = r["variant"] if isinstance(r["variant"], str) and r["variant"] else None
        return f"{r['scenario']}" + (f"[{v}]" if v else "") + f"::{metric}"

    in_rows = {(r["engine"], case(r, c["metric"])): c["trace"]
               for _, r in pd.read_parquet(rows).iterrows() for c in json.loads(r["checks"])}
    junit_links = {(tc.get("classname").split(".")[1], tc.get("name")):
                   {p.get("name"): p.get("value") for p in tc.iter("property")}.get("trace", "")
                   for tc in root.iter("testcase")}
    assert set(junit_links) <= set(in_rows)
    assert {k: v for k, v in in_rows.items() if k in junit_links} == junit_links
    assert {v for v in in_rows.values() if v} == files and all(Path(v).is_absolute() for v in files)
