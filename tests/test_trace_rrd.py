"""physbench.harness.rerun_log.write_rrd: one .rrd with every run side by side.

Most tests use hand-made traces whose physics is known in closed form (two
spheres in free flight, no gravity, one spinning about z), so they do not
depend on any engine: the logged poses must equal the analytic motion, the
energy series must equal 1/2 m v^2 + 1/2 I w^2, the penetration series must
equal the analytic overlap 2r - |x_b - x_a| of spheres passing through each
other.  One test drives the real runner with the reference engine and skips
if that adapter is not there yet.

The file is read back with rerun 0.41's ``rerun.chunk.RrdReader`` (a chunk
has ``entity_path``, ``is_static`` and ``to_record_batch()``).  rerun stores
translations and quaternions as float32, scalars as float64.
"""

from __future__ import annotations

import math
import warnings
from collections import defaultdict

import numpy as np
import pandas as pd
import pytest

from physbench.harness.metrics import energy_series
from physbench.harness.trace import quat_z_to, write_rrd
from physbench.harness.runner import RunResult, Trace
from physbench.contract.scene import load_scene
from tests.conftest import HEAD_ON

rerun_chunk = pytest.importorskip("rerun.chunk")

F32 = dict(rtol=2e-6, atol=2e-7)  # float32 storage of poses

# two free-flight runs with different (known) velocities; b's cue also spins
SPEEDS = {"fake_a": 2.0, "fake_b": 1.0}
SPIN = {"fake_a": 0.0, "fake_b": 30.0}  # rad/s about z, for the cue


# ---------------------------------------------------------------------------
# helpers


def ballistic_result(scene, engine: str, speed: float, spin: float, n_frames: int = 501) -> RunResult:
    """RunResult whose trace is exact free flight: the cue moves along +x at
    ``speed`` and spins about z at ``spin``; the object sits still.  No
    collision response, so the spheres pass through each other."""
    n = scene.n_bodies
    tr = Trace.allocate(n_frames, n)
    t = np.arange(n_frames) * scene.dt
    tr.t[:] = t
    x0, q0, _, _ = scene.initial_state()
    v = np.zeros((n, 3))
    v[0, 0] = speed
    w = np.zeros((n, 3))
    w[0, 2] = spin
    tr.pos[:] = x0[None] + v[None] * t[:, None, None]
    tr.quat[:] = q0[None]
    # rotation by angle spin*t about z: q = (cos(a/2), 0, 0, sin(a/2))
    tr.quat[:, 0] = np.stack([np.cos(spin * t / 2), 0 * t, 0 * t, np.sin(spin * t / 2)], axis=1)
    tr.vel[:] = v[None]
    tr.angvel[:] = w[None]
    tr.n_frames = n_frames
    return RunResult(scene.id, scene.variant, engine, "0", "ok", "", {"dt": scene.dt}, trace=tr)


def read_rrd(path) -> dict[str, dict[str, list[pd.DataFrame]]]:
    """entity path -> {'static': [frames], 'temporal': [frames]}."""
    out: dict[str, dict[str, list[pd.DataFrame]]] = defaultdict(lambda: {"static": [], "temporal": []})
    with warnings.catch_warnings():
        # a missing footer (file not closed) would warn: make it fail
        warnings.simplefilter("error")
        reader = rerun_chunk.RrdReader(path)
        chunks = reader.stream().to_chunks()
    for c in chunks:
        out[c.entity_path]["static" if c.is_static else "temporal"].append(c.to_record_batch().to_pandas())
    return out


def temporal(data, entity: str) -> pd.DataFrame:
    frames = data[entity]["temporal"]
    assert frames, f"no temporal data at {entity}"
    return pd.concat(frames).sort_values("step").reset_index(drop=True)


def static_value(data, entity: str, column: str):
    for df in data[entity]["static"]:
        if column in df.columns:
            return df[column].iloc[0]
    raise AssertionError(f"{entity}: no static {column}; have {[list(d.columns) for d in data[entity]['static']]}")


def column_array(df: pd.DataFrame, column: str) -> np.ndarray:
    """(rows, k) array from a list-of-fixed-size-list column (one instance per row)."""
    return np.array([np.asarray(list(v[0]), float) for v in df[column]])


@pytest.fixture(scope="module")
def scene():
    return load_scene(HEAD_ON)


@pytest.fixture(scope="module")
def two_runs(scene, tmp_path_factory):
    results = [ballistic_result(scene, e, SPEEDS[e], SPIN[e]) for e in SPEEDS]
    results.append(RunResult(scene.id, None, "pymunk", "7.3.1", "unsupported",
                             "pymunk is a 2D engine and the scene is not planar", {}))
    path = tmp_path_factory.mktemp("rrd") / "two.rrd"
    write_rrd(path, scene, results)
    return results, path, read_rrd(path)


# ---------------------------------------------------------------------------
# bodies and poses


def test_bodies_logged_per_engine_with_their_shape(scene, two_runs):
    _, _, data = two_runs
    for engine in SPEEDS:
        for body in scene.bodies:
            ent = f"/world/{engine}/{body.name}"
            assert ent in data, sorted(data)
            half = np.asarray(list(static_value(data, ent, "Ellipsoids3D:half_sizes")[0]), float)
            np.testing.assert_allclose(half, [body.radius] * 3, **F32)
            assert len(temporal(data, ent)) == 501


def test_translations_and_quaternions_equal_the_analytic_motion(scene, two_runs):
    _, _, data = two_runs
    x0 = scene.initial_state()[0]
    for engine, speed in SPEEDS.items():
        df = temporal(data, f"/world/{engine}/cue")
        t = np.asarray(df["sim_time"].dt.total_seconds(), float)
        np.testing.assert_allclose(t, np.arange(501) * scene.dt, atol=1e-9)
        assert df["step"].tolist() == list(range(501))  # record_every 1: step == frame
        pos = column_array(df, "Transform3D:translation")
        expect = x0[0] + np.outer(t, [speed, 0.0, 0.0])  # no offset: it sits on /world/<engine>
        np.testing.assert_allclose(pos, expect, **F32)
        q = column_array(df, "Transform3D:quaternion")  # rerun order xyzw
        a = SPIN[engine] * t
        np.testing.assert_allclose(q, np.stack([0 * t, 0 * t, np.sin(a / 2), np.cos(a / 2)], axis=1), **F32)
        obj = column_array(temporal(data, f"/world/{engine}/object"), "Transform3D:translation")
        np.testing.assert_allclose(obj, np.broadcast_to(x0[1], obj.shape), **F32)


def test_engines_are_offset_sideways_without_overlap(scene, two_runs):
    results, _, data = two_runs
    offsets = [np.asarray(list(static_value(data, f"/world/{e}", "Transform3D:translation")[0]), float)
               for e in SPEEDS]
    np.testing.assert_allclose(offsets[0], 0.0)
    assert offsets[1][0] == 0.0 and offsets[1][2] == 0.0
    # side by side along y, further apart than the scene is wide in y
    # (the balls' y-span over the runs is 2 r)
    assert offsets[1][1] > 2 * scene.bodies[0].radius
    # the failed run has no scene copy, hence no offset
    assert "/world/pymunk" not in data


# ---------------------------------------------------------------------------
# metric series


def test_energy_series_equals_analytic_kinetic_energy(scene, two_runs):
    _, _, data = two_runs
    m = scene.bodies[0].mass
    inertia = 0.4 * m * scene.bodies[0].radius ** 2  # solid sphere
    for engine, speed in SPEEDS.items():
        df = temporal(data, f"/metrics/{engine}/energy")
        e = np.array([v[0] for v in df["Scalars:scalars"]])
        expect = 0.5 * m * speed**2 + 0.5 * inertia * SPIN[engine] ** 2  # no gravity in head_on
        assert len(e) == 501
        np.testing.assert_allclose(e, expect, rtol=1e-12)


def test_energy_series_is_the_metrics_definition(scene, two_runs):
    results, _, data = two_runs
    for r in results[:2]:
        df = temporal(data, f"/metrics/{r.engine}/energy")
        e = np.array([v[0] for v in df["Scalars:scalars"]])
        np.testing.assert_array_equal(e, energy_series(scene, r.trace.valid()))


def test_penetration_series_equals_analytic_overlap(scene, two_runs):
    _, _, data = two_runs
    r = scene.bodies[0].radius
    gap0 = scene.bodies[1].position[0] - scene.bodies[0].position[0]
    for engine, speed in SPEEDS.items():
        df = temporal(data, f"/metrics/{engine}/penetration")
        t = np.asarray(df["sim_time"].dt.total_seconds(), float)
        depth = np.array([v[0] for v in df["Scalars:scalars"]])
        expect = np.maximum(0.0, 2 * r - np.abs(gap0 - speed * t))
        np.testing.assert_allclose(depth, expect, atol=1e-12)
        assert depth.max() == pytest.approx(2 * r, rel=1e-2)  # they pass right through


def test_no_penetration_series_without_contact(tmp_path):
    from tests.conftest import without_effects

    scene = without_effects(load_scene(HEAD_ON), "contact", "restitution")
    assert not scene.has("contact")
    write_rrd(tmp_path / "g.rrd", scene, [ballistic_result(scene, "fake_a", 2.0, 0.0, 11)])
    data = read_rrd(tmp_path / "g.rrd")
    assert "/metrics/fake_a/energy" in data
    assert "/metrics/fake_a/penetration" not in data


# ---------------------------------------------------------------------------
# status, blueprint, file


def test_unsupported_run_is_a_status_document_only(two_runs):
    results, _, data = two_runs
    text = static_value(data, "/world/pymunk/status", "TextDocument:text")[0]
    assert text.startswith("unsupported: ") and results[2].message in text
    assert [e for e in data if e.startswith("/world/pymunk")] == ["/world/pymunk/status"]
    assert not [e for e in data if e.startswith("/metrics/pymunk")]
    # ok runs get no status document
    assert not [e for e in data if e.endswith("/status") and "pymunk" not in e]


def test_diverged_run_keeps_its_finite_frames_and_says_why(scene, tmp_path):
    res = ballistic_result(scene, "fake_a", 2.0, 0.0, 21)
    res.trace.pos[15:, 0] = np.nan  # the cue blows up at frame 15
    res.status, res.message = "diverged", "non-finite pos at t = 0.015 s (step 15)"
    write_rrd(tmp_path / "d.rrd", scene, [res])
    data = read_rrd(tmp_path / "d.rrd")
    assert len(temporal(data, "/world/fake_a/cue")) == 15
    assert len(temporal(data, "/world/fake_a/object")) == 21
    text = static_value(data, "/world/fake_a/status", "TextDocument:text")[0]
    assert text == "diverged: " + res.message


def test_default_blueprint_is_stored(two_runs):
    _, path, _ = two_runs
    reader = rerun_chunk.RrdReader(path)
    (bp,) = reader.blueprints()
    views, queries = {}, []
    for c in reader.stream(store=bp).to_chunks():
        df = c.to_record_batch().to_pandas()
        if "ViewBlueprint:class_identifier" in df.columns:
            views.setdefault(df["ViewBlueprint:class_identifier"].iloc[0][0], []).append(
                df["ViewBlueprint:space_origin"].iloc[0][0])
        if "ViewContents:query" in df.columns:
            queries.append(sorted(df["ViewContents:query"].iloc[0].tolist()))
    assert views["3D"] == ["/world"]
    assert views["TimeSeries"] == ["/metrics", "/metrics"]  # energy, penetration
    assert views["TextDocument"] == ["/world/pymunk/status"]
    # one plot per quantity, each holding the drawn runs' series
    for q in ("energy", "penetration"):
        assert sorted(f"/metrics/{e}/{q}" for e in SPEEDS) in queries
    (rec,) = reader.recordings()
    assert rec.application_id == "physbench"


def test_recording_id_and_app_id(scene, tmp_path):
    write_rrd(tmp_path / "x.rrd", scene, [ballistic_result(scene, "fake_a", 1.0, 0.0, 3)],
              app_id="physbench_test", recording_id="fixed-id")
    (rec,) = rerun_chunk.RrdReader(tmp_path / "x.rrd").recordings()
    assert (rec.application_id, rec.recording_id) == ("physbench_test", "fixed-id")


# ---------------------------------------------------------------------------
# other shapes and statics

SHAPES_TOML = """
[scenario]
family = "misc"
title = "one of each"
duration = 0.01
dt = 0.001
effects = ["gravity", "contact"]

[[body]]
name = "brick"
shape = "box"
half_extents = [0.3, 0.2, 0.1]
mass = 1.0
position = [0.0, 0.0, 1.0]

[[body]]
name = "pill"
shape = "capsule"
radius = 0.05
half_length = 0.2
mass = 1.0
position = [1.0, 0.0, 1.0]

[[body]]
name = "can"
shape = "cylinder"
radius = 0.1
half_length = 0.15
mass = 1.0
position = [2.0, 0.0, 1.0]

[[static]]
name = "ramp"
shape = "slope"
angle = 30.0
point = [0.0, 0.0, 0.5]

[[static]]
name = "wall"
shape = "box"
half_extents = [0.05, 1.0, 0.5]
position = [3.0, 0.0, 0.5]
"""


def test_box_capsule_cylinder_and_statics(tmp_path):
    spec = tmp_path / "shapes.toml"
    spec.write_text(SHAPES_TOML)
    scene = load_scene(spec)
    res = ballistic_result(scene, "fake_a", 0.0, 0.0, 5)
    write_rrd(tmp_path / "s.rrd", scene, [res])
    data = read_rrd(tmp_path / "s.rrd")
    w = "/world/fake_a"
    np.testing.assert_allclose(list(static_value(data, f"{w}/brick", "Boxes3D:half_sizes")[0]), [0.3, 0.2, 0.1], **F32)
    # capsule: rerun's runs from z = 0 to z = length, shifted by -h to be centred
    assert static_value(data, f"{w}/pill", "Capsules3D:lengths")[0] == pytest.approx(0.4)
    assert static_value(data, f"{w}/pill", "Capsules3D:radii")[0] == pytest.approx(0.05)
    np.testing.assert_allclose(list(static_value(data, f"{w}/pill", "Capsules3D:translations")[0]), [0, 0, -0.2], **F32)
    assert static_value(data, f"{w}/can", "Cylinders3D:lengths")[0] == pytest.approx(0.3)
    assert static_value(data, f"{w}/can", "Cylinders3D:radii")[0] == pytest.approx(0.1)
    # static box: its pose and half extents
    np.testing.assert_allclose(list(static_value(data, f"{w}/static/wall", "Transform3D:translation")[0]), [3.0, 0.0, 0.5], **F32)
    np.testing.assert_allclose(list(static_value(data, f"{w}/static/wall", "Boxes3D:half_sizes")[0]), [0.05, 1.0, 0.5], **F32)
    # slope: a thin patch whose frame z is the normal (sin a, 0, cos a), centre
    # on the plane, top face on the plane (box centred at -thickness/2 along z)
    a = math.radians(30.0)
    n = np.array([math.sin(a), 0.0, math.cos(a)])
    ramp = f"{w}/static/ramp"
    c = np.asarray(list(static_value(data, ramp, "Transform3D:translation")[0]), float)
    assert c @ n == pytest.approx(0.5 * math.cos(a), abs=1e-6)
    x, y, z, qw = np.asarray(list(static_value(data, ramp, "Transform3D:quaternion")[0]), float)
    # rotate +z by q (xyzw): third column of R
    rz = np.array([2 * (x * z + qw * y), 2 * (y * z - qw * x), 1 - 2 * (x * x + y * y)])
    np.testing.assert_allclose(rz, n, atol=1e-6)
    half = np.asarray(list(static_value(data, ramp, "Boxes3D:half_sizes")[0]), float)
    centre = np.asarray(list(static_value(data, ramp, "Boxes3D:centers")[0]), float)
    np.testing.assert_allclose(centre, [0.0, 0.0, -half[2]], **F32)
    assert half[0] > 1.5 and half[1] > 0.5  # covers the bodies' footprint (x 0..2)


@pytest.mark.parametrize("n", [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.5, 0.8]])
def test_quat_z_to_maps_z_onto_the_normal(n):
    from physbench.contract.rotation import quat_rotate

    n = np.asarray(n, float) / np.linalg.norm(n)
    q = quat_z_to(n)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(quat_rotate(q, np.array([0.0, 0.0, 1.0])), n, atol=1e-12)


# ---------------------------------------------------------------------------
# the real runner


def test_real_reference_run_round_trips(scene, tmp_path):
    from physbench.harness.runner import run

    try:
        result = run(scene, "reference")
    except ModuleNotFoundError as e:
        pytest.skip(f"reference adapter not available yet: {e}")
    write_rrd(tmp_path / "ref.rrd", scene, [result])
    data = read_rrd(tmp_path / "ref.rrd")
    if result.status not in ("ok", "diverged") or result.trace is None:
        text = static_value(data, "/world/reference/status", "TextDocument:text")[0]
        assert text.startswith(result.status)
        return
    tr = result.trace.valid()
    for i, body in enumerate(scene.bodies):
        df = temporal(data, f"/world/reference/{body.name}")
        k = len(df) // 2
        np.testing.assert_allclose(column_array(df, "Transform3D:translation")[k], tr.pos[k, i], **F32)
    e = np.array([v[0] for v in temporal(data, "/metrics/reference/energy")["Scalars:scalars"]])
    np.testing.assert_allclose(e, energy_series(scene, tr), rtol=1e-12)


# ---------------------------------------------------------------------------
# what the write computes: once, or not at all where the run measured it


@pytest.mark.parametrize("diagnose", [False, True])
def test_energy_is_computed_once_per_drawn_run(scene, tmp_path, monkeypatch, diagnose):
    """The energy plot, the diagnosis' energy bands and its crossings read
    one computation of E(t) per drawn run (harness.metrics.energy_series)."""
    import physbench.harness.metrics as M

    calls = []
    real = M.energy_series

    def counted(sc, tr, datum=True):
        calls.append(tr.pos.shape[0])
        return real(sc, tr, datum)

    monkeypatch.setattr(M, "energy_series", counted)
    results = [ballistic_result(scene, e, SPEEDS[e], SPIN[e]) for e in SPEEDS]
    checks = {c.metric: c for c in scene.checks}
    write_rrd(tmp_path / "e.rrd", scene, results, diagnose=diagnose, checks=checks if diagnose else None)
    assert calls == [501, 501]


def test_the_runs_penetration_is_handed_to_the_trace(tmp_path, monkeypatch):
    """A run of the runner carries the metrics' penetration measurement of
    its frames on its trace; the write plots it without measuring again,
    and measures a trace that does not carry one."""
    import physbench.harness.trace.writer as G  # measure_penetration as the writer calls it
    from physbench.harness.runner import run

    scene = load_scene(HEAD_ON)
    res = run(scene, "reference")
    tr = res.trace.valid()
    assert res.status == "ok" and tr.penetration is not None and tr.penetration.n_frames == tr.n_frames
    assert float(tr.penetration.frame_max().max()) == res.metrics["max_penetration"]
    calls = []
    real = G.measure_penetration
    monkeypatch.setattr(G, "measure_penetration", lambda sc, t: calls.append(1) or real(sc, t))
    write_rrd(tmp_path / "run.rrd", scene, [res])
    assert calls == []
    depth = np.array([v[0] for v in temporal(read_rrd(tmp_path / "run.rrd"),
                                             "/metrics/reference/penetration")["Scalars:scalars"]])
    np.testing.assert_array_equal(depth, tr.penetration.frame_max())
    write_rrd(tmp_path / "fake.rrd", scene, [ballistic_result(scene, "fake_a", 2.0, 0.0)])
    assert calls == [1]
