"""Reference engine: narrow phase geometry, broad phase, CCD, stacking,
determinism.

Geometry is checked against hand-computed gaps, normals and points; the
bullet against a wall against the no-tunnelling requirement; the column
against "stays where it was put".
"""

from __future__ import annotations

import dataclasses

import hashlib
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.engine.broadphase import brute_pairs, sap_pairs
from physbench.engine.collision import (box_box, box_cylinder, box_plane, capsule_box, capsule_capsule, capsule_cylinder,
                              capsule_plane, cylinder_cylinder, cylinder_plane, sphere_box, sphere_capsule,
                              sphere_cylinder)
from physbench.engine.mathutil import quat_to_matrix
from physbench.contract.scene import load_scene

REPO = Path(__file__).resolve().parent.parent


def scene_from(tmp_path: Path, text: str, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return load_scene(p)


def rotz(deg):
    a = math.radians(deg)
    return np.array([math.cos(a / 2), 0, 0, math.sin(a / 2)])


# ---- narrow phase -----------------------------------------------------------

def test_sphere_box_outside_and_inside():
    I = np.eye(3)[None]
    h = np.array([[0.5, 0.5, 0.5]])
    # outside, near a corner
    k, n, p, g, _ = sphere_box(np.array([[1.0, 1.0, 0.0]]), np.array([0.2]), np.zeros((1, 3)), I, h)
    assert g[0] == pytest.approx(math.sqrt(0.5) - 0.2)
    assert np.allclose(n[0], -np.array([1, 1, 0]) / math.sqrt(2))  # from sphere toward box
    # centre inside: leaves through the nearest face (+x)
    k, n, p, g, _ = sphere_box(np.array([[0.4, 0.0, 0.1]]), np.array([0.2]), np.zeros((1, 3)), I, h)
    assert g[0] == pytest.approx(-0.1 - 0.2)
    assert np.allclose(n[0], [-1, 0, 0])


@pytest.mark.parametrize("centre, gap, normal", [
    # (cylinder frame: axis z, radius 0.3, half length 0.5; sphere radius 0.1)
    ([0.6, 0.0, 0.2], 0.2, [-1, 0, 0]),  # beside the side
    ([0.0, 0.2, 0.9], 0.3, [0, 0, -1]),  # above the cap
    ([0.3 + 0.3, 0.0, 0.5 + 0.4], 0.4, [-0.6, 0, -0.8]),  # beyond the rim: 0.5 from the edge circle
    ([0.25, 0.0, 0.1], -0.15, [-1, 0, 0]),  # centre inside, nearer the side
    ([0.0, 0.1, -0.45], -0.15, [0, 0, 1]),  # centre inside, nearer the bottom cap
    ([0.0, 0.0, 0.0], -0.4, [-1, 0, 0]),  # on the axis: leaves radially (+x)
])
def test_sphere_cylinder_closest_points(centre, gap, normal):
    """Exact gaps and normals (from the sphere toward the cylinder), the
    cylinder turned so that its axis is world x: the body frame is used."""
    q = np.array([math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0])  # body z -> world x
    R = quat_to_matrix(q)
    cc = np.array([1.0, 2.0, 3.0])
    c = cc + R @ np.array(centre, float)
    k, n, p, g, _ = sphere_cylinder(c[None], np.array([0.1]), cc[None], R[None], np.array([0.5]), np.array([0.3]))
    assert g[0] == pytest.approx(gap, abs=1e-12)
    assert np.allclose(n[0], R @ np.array(normal, float), atol=1e-12)
    # the point lies midway between the two surfaces
    assert np.allclose(p[0], c + n[0] * (0.1 + 0.5 * gap), atol=1e-12)


def test_box_plane_corners_of_a_tilted_box():
    q = np.array([math.cos(math.pi / 8), math.sin(math.pi / 8), 0, 0])  # 45 deg about x
    R = quat_to_matrix(q)[None]
    k, n, p, g, fid = box_plane(np.array([[0, 0, 0.5]]), R, np.array([[0.2, 0.3, 0.3]]),
                                np.array([[0, 0, 1.0]]), np.array([0.0]))
    lowest = 0.5 - 0.3 * math.sqrt(2)
    assert g.min() == pytest.approx(lowest)
    assert np.sum(np.isclose(g, lowest)) == 2  # the bottom edge: two corners
    assert np.allclose(n, [0, 0, -1])


def test_box_box_face_manifold_and_depth():
    # B rests on A, overlapping by 1 mm, rotated 30 deg about z: a polygon manifold
    I = np.eye(3)[None]
    RB = quat_to_matrix(rotz(30.0))[None]
    k, n, p, g, _ = box_box(np.zeros((1, 3)), I, np.array([[0.5, 0.5, 0.1]]),
                            np.array([[0.0, 0.0, 0.199]]), RB, np.array([[0.2, 0.2, 0.1]]), np.array([1e-3]))
    assert 3 <= k.size <= 4
    assert np.allclose(n, [0, 0, 1])  # from A (below) toward B
    assert np.allclose(g, -0.001)
    assert np.allclose(p[:, 2], 0.1 - 0.0005)  # midway between the faces
    # points are B's bottom corners (inside A's top face)
    c = 0.2 * math.sqrt(2)
    assert np.allclose(np.linalg.norm(p[:, :2], axis=1), c)


def test_box_box_clipped_manifold_offset():
    """B hangs half over A's edge: the manifold is clipped to A's face."""
    I = np.eye(3)[None]
    k, n, p, g, _ = box_box(np.zeros((1, 3)), I, np.array([[0.5, 0.5, 0.1]]),
                            np.array([[0.6, 0.0, 0.2]]), I, np.array([[0.2, 0.2, 0.1]]), np.array([1e-3]))
    assert k.size == 4
    assert np.allclose(g, 0.0)
    assert np.isclose(p[:, 0].max(), 0.5) and np.isclose(p[:, 0].min(), 0.4)


def test_box_box_edge_edge():
    """Two boxes crossed edge on edge (A's top edge along x, B's bottom edge along y)."""
    qa = np.array([math.cos(math.pi / 8), math.sin(math.pi / 8), 0, 0])  # 45 deg about x: ridge along x
    qb = np.array([math.cos(math.pi / 8), 0, math.sin(math.pi / 8), 0])  # 45 deg about y: ridge along y
    RA, RB = quat_to_matrix(qa)[None], quat_to_matrix(qb)[None]
    s = math.sqrt(2) * 0.1
    zb = 2 * s - 0.002  # 2 mm overlap
    k, n, p, g, fid = box_box(np.zeros((1, 3)), RA, np.full((1, 3), 0.1), np.array([[0, 0, zb]]), RB,
                              np.full((1, 3), 0.1), np.array([1e-3]))
    assert k.size == 1 and fid[0] >= 64
    assert g[0] == pytest.approx(-0.002, abs=1e-12)
    assert np.allclose(n[0], [0, 0, 1])
    assert np.allclose(p[0], [0, 0, s - 0.001])


def test_capsule_pairs():
    I = np.eye(3)[None]
    # lying capsule (axis along x) on a plane: both caps touch
    Rx = quat_to_matrix(np.array([math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0]))[None]
    k, n, p, g, _ = capsule_plane(np.array([[0, 0, 0.1]]), Rx, np.array([0.3]), np.array([0.1]),
                                  np.array([[0, 0, 1.0]]), np.array([0.0]))
    assert np.allclose(g, 0.0) and np.allclose(sorted(p[:, 0]), [-0.3, 0.3], atol=1e-12)
    # sphere over the middle of a lying capsule
    k, n, p, g, _ = sphere_capsule(np.array([[0.1, 0, 0.35]]), np.array([0.2]), np.array([[0, 0, 0.1]]), Rx,
                                   np.array([0.3]), np.array([0.1]))
    assert g[0] == pytest.approx(0.25 - 0.3) and np.allclose(n[0], [0, 0, -1])
    # crossed capsules: the segments' closest points
    Ry = quat_to_matrix(np.array([math.cos(math.pi / 4), -math.sin(math.pi / 4), 0, 0]))[None]
    k, n, p, g, _ = capsule_capsule(np.zeros((1, 3)), Rx, np.array([0.3]), np.array([0.1]),
                                    np.array([[0, 0, 0.19]]), Ry, np.array([0.3]), np.array([0.1]))
    assert g.min() == pytest.approx(-0.01)
    # capsule standing on a box top, 1 mm in
    k, n, p, g, _ = capsule_box(np.array([[0.1, 0, 0.5 + 0.4 - 0.001]]), I, np.array([0.3]), np.array([0.1]),
                                np.zeros((1, 3)), I, np.array([[0.5, 0.5, 0.5]]))
    assert g.min() == pytest.approx(-0.001, abs=1e-9) and np.allclose(n[np.argmin(g)], [0, 0, -1])


def _lying(deg):
    """The rotation of a capsule lying along x turned by ``deg`` about z."""
    a = math.radians(deg)
    q = np.array([math.cos(a / 2), 0, 0, math.sin(a / 2)])
    lie = np.array([math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0])
    w1, x1, y1, z1 = q
    w2, x2, y2, z2 = lie
    return quat_to_matrix(np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                                    w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]))


@pytest.mark.parametrize("deg, cx", [(8.0, 0.01), (8.0, -0.025), (2.0, 0.03), (0.0, 0.03), (30.0, 0.0)])
def test_capsule_capsule_clipped_manifold(deg, cx):
    """Capsule a along x at the origin, capsule b above it turned by
    ``deg`` about z, centre (cx, 0, z0): the segments cross (top view) at
    x = cx, where they are z0 apart (slot 0).  The overlap along a's axis
    is b's ends projected onto it, cx -/+ hl_b cos(deg), clipped to a's
    ends; at each end s, b's closest point is at u = (s - cx) cos(deg)
    along b, z0 above and s sin(deg) ... off a's line: gap = sqrt(z0^2 +
    ((s - cx) sin(deg))^2) - r_a - r_b, whatever the angle (no 5.7 degree
    gate).  An end within a tenth of the smaller radius of the closest
    point is that contact again and is not repeated (parallel: the closest
    points are one end of the overlap, so two contacts)."""
    ra, rb, hla, hlb, z0 = 0.03, 0.025, 0.04, 0.05, 0.0549
    th = math.radians(deg)
    k, n, p, g, f = capsule_capsule(np.zeros((1, 3)), _lying(0.0)[None], np.array([hla]), np.array([ra]),
                                    np.array([[cx, 0.0, z0]]), _lying(deg)[None], np.array([hlb]), np.array([rb]))
    lo = max(-hla, cx - hlb * math.cos(th))
    hi = min(hla, cx + hlb * math.cos(th))
    # parallel, every point of the overlap is closest: slot 0's is the
    # segment routine's choice, read back (its normal is vertical)
    sp = cx if deg else float(p[list(f).index(0), 0])
    want = {0: (sp, z0 - ra - rb)}
    for fid, s in ((1, lo), (2, hi)):
        if abs(s - sp) > 0.1 * rb:
            want[fid] = (s, math.sqrt(z0 ** 2 + ((s - cx) * math.sin(th)) ** 2) - ra - rb)
    assert sorted(f.tolist()) == sorted(want)
    for i, fid in enumerate(f):
        x, gap = want[int(fid)]
        assert g[i] == pytest.approx(gap, abs=1e-12)
        assert p[i, 0] == pytest.approx(x + (ra + 0.5 * gap) * n[i, 0], abs=1e-12)
        assert n[i, 2] > 0.0  # from a (below) toward b
    # crossing square (and b shorter than a tenth of r across a's axis):
    # one contact, the closest points
    k, n, p, g, f = capsule_capsule(np.zeros((1, 3)), _lying(0.0)[None], np.array([hla]), np.array([ra]),
                                    np.array([[cx, 0.0, z0]]), _lying(90.0)[None], np.array([hlb]), np.array([rb]))
    assert f.tolist() == [0] and g[0] == pytest.approx(z0 - ra - rb, abs=1e-12)


_CAPSULE_ON_CAPSULE = """
[scenario]
family = "t"
title = "a capsule lands on another at 8 degrees"
duration = 1.0
dt = {dt!r}
effects = ["gravity", "contact", "friction"]
[material.default]
friction = 0.6
static_friction = 0.7
[[body]]
name = "low"
shape = "capsule"
radius = 0.03
half_length = 0.04
mass = 0.3
position = [0.0, 0.0, 0.03]
orientation = {low}
[[body]]
name = "up"
shape = "capsule"
radius = 0.03
half_length = 0.04
mass = 0.3
position = [0.02, {y!r}, {z!r}]
orientation = {up}
velocity = [0.0, 0.0, {vz!r}]
[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
offset = 0.0
"""


@pytest.mark.parametrize("dt, vz, drop", [(1 / 240, -1.0, 1e-3), (1 / 240, -2.0, 4e-3), (1 / 60, -1.0, 1e-3)])
def test_capsule_landing_on_another_at_8_degrees_stays_out(tmp_path, dt, vz, drop):
    """stacking.poured_bin's slap: a capsule lands flat on another lying on
    the floor, its axis 8 degrees off the lower one's, crossing it (top
    view) 2 cm from its own centre; it tips about the crossing, its far end
    slaps down along the lower capsule, and it rolls off.  The two are a
    line contact at a shallow angle: with a row only at the segments'
    closest points (the end rows came below 5.7 degrees only) the far end
    sank in with nothing there to stop it (measured 0.68, 1.02 and 4.65 mm
    for these cases).  With the overlap's clipped ends as rows whenever
    they are within the margin, the pair's deepest overlap (the harness's
    own geometry, every frame) stays below what position correction
    leaves a resting contact: correction_slop plus one step of gravity's
    approach, g dt^2 (0.27 mm at 1/240 s, 2.9 mm at 1/60 s)."""
    from physbench.engine import SETTINGS
    from physbench.harness.metrics import run_penetration
    from physbench.harness.runner import run

    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    a = math.radians(8.0)
    up = [math.cos(a / 2) * c, -math.sin(a / 2) * s, math.cos(a / 2) * s, math.sin(a / 2) * c]
    sc = scene_from(tmp_path, _CAPSULE_ON_CAPSULE.format(dt=dt, low=f"[{c!r}, 0.0, {s!r}, 0.0]", up=repr(up),
                                                          y=0.02 * math.tan(a), z=0.09 + drop, vz=vz))
    res = run(sc, "reference", compute_metrics=False)
    tr = res.trace.valid()
    assert res.status == "ok" and tr.n_frames == round(1.0 / dt) + 1
    pen = run_penetration(sc, tr)
    depth = pen.dense()[:, pen.pairs.index((0, "body", 1))]
    bound = SETTINGS["correction_slop"][0] + 9.81 * dt * dt
    assert np.all(np.isfinite(depth)) and depth.max() < bound, (depth.max(), bound)
    # it landed on the lower one (touching, 3 radii up) and left it for the floor
    assert np.any(np.abs(tr.pos[:, 1, 2] - 0.09) < 1e-3) and tr.pos[-1, 1, 2] == pytest.approx(0.03, abs=1e-3)


def test_cylinder_plane_deepest_point_and_supports():
    """The deepest of a cylinder's contact points is its exact lowest point,
    at any orientation: gap = n.c - hl |n.a| - r sqrt(1 - (n.a)^2) - o
    (a the axis); lying, it touches along the bottom line (two points at
    the caps); standing, on the cap's square of four rim points."""
    rng = np.random.default_rng(7)
    hl, r = 0.2, 0.1
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quat_to_matrix(q)
        c = rng.normal(size=3)
        pn = rng.normal(size=3)
        pn /= np.linalg.norm(pn)
        po = rng.normal()
        k, n, p, g, f = cylinder_plane(c[None], R[None], np.array([hl]), np.array([r]), pn[None], np.array([po]))
        na = abs(pn @ R[:, 2])
        exact = pn @ c - hl * na - r * math.sqrt(max(1 - na * na, 0.0)) - po
        assert g.min() == pytest.approx(exact, abs=1e-12)
        assert np.allclose(n, -pn)
        # points are midway between the surfaces: rim point + n gap / 2; a
        # cylinder whose caps face the plane within 45 deg has all four rim
        # points per cap, one lying more on its side only the deepest ones
        fin = np.isfinite(g)
        assert np.allclose(p[fin] @ pn - po, 0.5 * g[fin], atol=1e-12)
        assert fin.sum() == (8 if na >= math.sqrt(0.5) else 2) and np.all(np.isfinite(p))
    # lying across x (axis along y), 1 mm into the plane z = 0
    Ry = quat_to_matrix(np.array([math.cos(-math.pi / 4), math.sin(-math.pi / 4), 0, 0]))[None]
    k, n, p, g, f = cylinder_plane(np.array([[0.3, 0, r - 0.001]]), Ry, np.array([hl]), np.array([r]),
                                   np.array([[0, 0, 1.0]]), np.array([0.0]))
    touching = g < 0
    assert touching.sum() == 2 and np.allclose(g[touching], -0.001)
    assert np.allclose(np.sort(p[touching][:, 1]), [-hl, hl]) and np.allclose(p[touching][:, 0], 0.3)
    assert np.all(np.isinf(g[~touching]))  # no speculative points on the curved side
    # standing on its -z cap: four touching points on the rim, a square
    k, n, p, g, f = cylinder_plane(np.array([[0, 0, hl]]), np.eye(3)[None], np.array([hl]), np.array([r]),
                                   np.array([[0, 0, 1.0]]), np.array([0.0]))
    touching = np.abs(g) < 1e-12
    assert touching.sum() == 4 and np.allclose(np.linalg.norm(p[touching][:, :2], axis=1), r)
    assert np.allclose(p[touching][:, :2].mean(axis=0), 0.0)


# ---- broad phase ------------------------------------------------------------

def test_sap_matches_brute_force():
    rng = np.random.default_rng(3)
    n = 60
    c = rng.uniform(-1, 1, (n, 3))
    e = rng.uniform(0.01, 0.2, (n, 3))

    a1, b1 = sap_pairs(c - e, c + e)
    a2, b2 = brute_pairs(c - e, c + e)
    assert len(a1) > 0
    assert np.array_equal(a1, a2) and np.array_equal(b1, b2)


GRID = """
    [scenario]
    family = "t"
    title = "grid"
    duration = 0.5
    dt = 0.005
    effects = ["gravity", "contact", "restitution", "friction"]
    [material.default]
    restitution = 0.3
    friction = 0.4
    [[body]]
    name = "b"
    shape = "sphere"
    radius = 0.05
    mass = 0.2
    position = [0, 0, 0.3]
    velocity = [0.3, -0.2, 0]
    [body.pattern]
    kind = "grid"
    counts = [3, 3, 2]
    gap = 0.002
    [[body]]
    name = "c"
    shape = "box"
    half_extents = [0.05, 0.05, 0.05]
    mass = 0.3
    position = [0.05, 0.05, 0.05]
    angular_velocity = [0, 0, 2]
    [[static]]
    shape = "plane"
    normal = [0, 0, 1]
    """


def _state_hash(eng) -> str:
    s = eng.state
    return hashlib.sha256(b"".join(a.tobytes() for a in (s.x, s.q, s.v, s.w))).hexdigest()


def test_sap_and_brute_give_identical_runs(tmp_path):
    sc = scene_from(tmp_path, GRID)
    a = engine_for(sc, {"broadphase": "sap"})
    b = engine_for(sc, {"broadphase": "brute"})
    a.step(60)
    b.step(60)
    assert _state_hash(a) == _state_hash(b)


def test_determinism_bit_identical(tmp_path):
    """Same scene + settings -> bit-identical states, in this process and in
    a fresh interpreter that gets this process's environment: the question is
    whether the engine is deterministic, not whether OpenBLAS picks the same
    kernel without OPENBLAS_CORETYPE (on a machine that sets it, a child
    without it ran other kernels and other bits: issue 20)."""
    sc = scene_from(tmp_path, GRID)
    runs = []
    for _ in range(2):
        e = engine_for(sc)
        e.step(60)
        runs.append(_state_hash(e))
    assert runs[0] == runs[1]
    code = textwrap.dedent(f"""
        import hashlib
        from physbench.adapters.reference import engine_for
        from physbench.contract.scene import load_scene
        e = engine_for(load_scene({str(tmp_path / 's.toml')!r}))
        e.step(60)
        s = e.state
        print(hashlib.sha256(b"".join(a.tobytes() for a in (s.x, s.q, s.v, s.w))).hexdigest())
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == runs[0]


# ---- CCD ----------------------------------------------------------------------

BULLET = """
    [scenario]
    family = "t"
    title = "bullet"
    duration = 0.05
    dt = {dt}
    effects = ["contact", "restitution"]
    [material.default]
    restitution = {e}
    [[body]]
    name = "ball"
    shape = "sphere"
    radius = 0.0025
    mass = 0.001
    position = [-1.0, 0, 0.5]
    velocity = [400.0, 0, 0]
    [[static]]
    shape = "box"
    half_extents = [0.002, 0.5, 0.5]
    position = [0, 0, 0.5]
    """


@pytest.mark.parametrize("ccd", ["events", "toi"])
@pytest.mark.parametrize("e", [0.0, 0.5])
def test_fast_ball_does_not_tunnel_thin_wall(tmp_path, ccd, e):
    """5 mm ball at 400 m/s against a 4 mm wall at dt = 1/240: it moves 1.67 m
    per step, 333 times its diameter."""
    sc = scene_from(tmp_path, BULLET.format(dt=1 / 240, e=e))
    eng = engine_for(sc, {"ccd": ccd})
    for _ in range(12):
        eng.step()
        assert eng.state.x[0, 0] <= -0.0045 + 1e-9  # never past the wall's near face
    assert eng.state.v[0, 0] == pytest.approx(-e * 400.0, abs=1e-9)


@pytest.mark.parametrize("dt", [1 / 240, 1 / 60, 1 / 30])
def test_spinning_bar_far_end_is_an_impact_not_a_speculative_row(dt):
    """tunnelling.spinning_long_box: the bar rests on one end and its spin
    brings the other end down onto the 4 mm slab at ~4.6 m/s.  That end is a
    new point of a pair that was already pressing: classified per pair
    (persistent contact, never an impact) it became a speculative row,
    stopped over the whole step, and sank 4.9 mm into the slab at 1/240 s;
    at 1/30 s 15 of 32 step phases tunnelled.  Classified per point (not
    pressed, approaching at the start of the step, and a speculative row --
    or, touching, a stop over the step -- would sink it beyond the slop) it
    is an impact event: over 8 phases of the steps (the start moved back
    along the exact free flight by f dt) the bar never tunnels, and in the
    scene as written it sinks no further than the slop.

    Two more ways the landing end was stopped as a speculative row, sinking
    h v / 2, in some phases (the largest overlaps over 16 phases at 1/30,
    1/60, 1/120, 1/240 s were 36, 37, 18, 9.6 mm): (1) a speculative row
    that pressed only to land the end exactly on the slab counted as a
    point pressed at rest, so the arriving end was not an impact; (2) the
    time-of-impact search followed the pair's deepest point -- the resting
    end, a hair inside the slab -- so it found tau ~ 0 again and again until
    the event budget ran out.  Now only points pressed while touching count,
    and the search follows the impact's own points: the largest overlap in
    any phase is 0.26, 0.019, 0.012, 0.064 mm (with the later fixes of the
    time-of-impact search)."""
    from physbench.harness.references import get_model
    from physbench.harness.runner import run
    base = load_scene("tunnelling.spinning_long_box")
    b = base.bodies[0]
    g = 9.81
    w = float(b.angular_velocity[1])
    for f in (0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875):
        tau = f * dt
        psi = -w * tau  # spin angle about y, back along the free flight
        over = {"scenario.dt": dt,
                "body[0].position": [0.0, 0.0, float(b.position[2]) - 0.5 * g * tau * tau],
                "body[0].velocity": [0.0, 0.0, g * tau],
                "body[0].orientation": [math.cos(psi / 2), 0.0, math.sin(psi / 2), 0.0]}
        sc = load_scene("tunnelling.spinning_long_box", None, over)
        res = run(sc, "reference")
        assert res.status == "ok", res.message
        assert get_model("no_tunnelling")(sc).metrics(res.trace)["tunnelled"] == 0.0, f
        assert res.stages["counters"]["impacts"] >= 1
        assert res.metrics["max_penetration"] <= 1e-3, (f, res.metrics["max_penetration"])
        if f == 0.0 and dt == 1 / 240:
            # within the position correction's slop (resting overlaps below it are left alone by
            # design; measured 1.8e-6 m when the bar settles at 1 cm/s), against 4.9 mm before
            assert res.metrics["max_penetration"] <= res.settings["correction_slop"]


def test_steps_are_split_where_a_body_turns_too_far(monkeypatch):
    """tunnelling.spinning_long_box[spin_80] at 1/30 s: the bar turns 2.7 rad
    per step, and a point on it strays from the chord of its step (along
    which impacts are detected) by up to r (1 - cos(theta / 2)) = 19 cm:
    with neither cure, its end dips into the 4 mm slab (measured: 174 mm in
    phase 6 of 16, 60 mm and 97 mm in two more).  With
    ``max_rotation_per_step`` (1 rad) such a step runs as three parts: no
    overlap beyond 1 mm in any phase.  Without the split, the end-pose check
    for missed impacts (``engine.ccd.missed_impacts``) finds the dips as
    impacts and resolves them at their time of impact instead.  Steps of
    bodies that turn slowly are never split."""
    import physbench.engine.ccd
    from physbench import engine
    from physbench.contract.phase import shift_scene
    from physbench.harness.runner import run

    base = load_scene("tunnelling.spinning_long_box", "spin_80")
    dt = 1 / 30
    worst, missed = {}, {}
    found = engine.ccd.missed_impacts
    for limit, check in ((1.0, True), (0.0, True), (0.0, False)):
        monkeypatch.setattr(engine.ccd, "missed_impacts", found if check else (lambda *a, **k: []))
        pens, n_missed = [], 0
        for i in range(16):
            sc = shift_scene(base, i / 16, dt)
            res = run(sc, "reference", {"dt": dt, "max_rotation_per_step": limit})
            assert res.status == "ok", res.message
            pens.append(res.metrics["max_penetration"])
            splits = res.stages["counters"].get("rotation_splits", 0)
            assert (splits > 0) == (limit > 0)
            n_missed += res.stages["counters"].get("missed_impacts", 0)
        worst[limit, check] = max(pens)
        missed[limit, check] = n_missed
    assert worst[1.0, True] <= 1e-3
    assert worst[0.0, True] <= 1e-3 and missed[0.0, True] >= 1  # measured: 5 missed impacts found
    assert worst[0.0, False] >= 0.05  # the limit these guard against, measured 0.174 m
    monkeypatch.setattr(engine.ccd, "missed_impacts", found)
    res = run(load_scene("tunnelling.spinning_long_box"), "reference")  # 40 rad/s at 1/240 s: 0.17 rad per step
    assert res.stages["counters"].get("rotation_splits", 0) == 0


DATA = Path(__file__).resolve().parent / "data"


def _without(monkeypatch, what: str) -> None:
    """Switch off one of the time-of-impact safeguards (to show what it
    removes): the end-pose check for missed impacts, the search's
    following of the impact's feature ids, the same left-out rows in every
    rerun, the check of the step's other impact pairs after the search,
    the end-pose check of pairs that are impacts already, the face-manifold
    points of box pairs whose least overlap is an edge
    axis, or the plain end of a step whose search found no impact."""
    import physbench.engine.ccd
    from physbench import engine
    import physbench.engine.collision.box
    from physbench import engine
    import physbench.engine.pipeline
    from physbench import engine

    if what == "missed":
        monkeypatch.setattr(engine.ccd, "missed_impacts", lambda *a, **k: [])
    elif what == "face_points":
        monkeypatch.setattr(engine.collision.box, "EDGE_FACE_POINTS", False)
    elif what == "missed_and_face_points":
        _without(monkeypatch, "missed")
        _without(monkeypatch, "face_points")
    elif what == "impact_pairs":
        check = engine.ccd.missed_impacts

        def other_pairs_only(model, state, ctx, skip, *args):
            out = check(model, state, ctx, skip, *args)
            return [m for m in out if not np.any(skip == engine.ccd._pair_codes_abs(model, m[1], m[2], m[3]))]

        monkeypatch.setattr(engine.ccd, "missed_impacts", other_pairs_only)
    elif what == "clear_end":
        search = engine.ccd._search

        def impact_at_the_end(model, state, ctx, *args):
            tau, _clear = search(model, state, ctx, *args)
            return tau, False

        monkeypatch.setattr(engine.ccd, "_search", impact_at_the_end)
    elif what == "fids":
        monkeypatch.setattr(engine.ccd, "_follow_fids", lambda *a, **k: None)
    elif what == "rows":
        search = engine.ccd._search

        def redecided(model, state, ctx, *args):
            ctx.drop_rows = None
            return search(model, state, ctx, *args)

        monkeypatch.setattr(engine.ccd, "_search", redecided)
    elif what == "others_and_rows":
        _without(monkeypatch, "others")
        _without(monkeypatch, "rows")
    else:
        search = engine.ccd.refine_toi

        def first_pair_only(model, state, ctx, main, profile):
            ctx.event = dataclasses.replace(ctx.event, others=())
            return search(model, state, ctx, main, profile)

        monkeypatch.setattr(engine.pipeline, "refine_toi", first_pair_only)


#: Time-of-impact cases from a random-pile fuzz, each a state in tests/data
#: (other bodies removed): (file, the safeguard, its counter or None,
#: deepest overlap allowed with it (m), least overlap without it (m)).
#:
#: * capsule_round_box_edge: a capsule spinning at ~32 rad/s comes round a
#:   box's edge onto its face within one step.  Along the start pose's edge
#:   normal its end closes only 18.6 of its 31.8 mm, so no contact row sees
#:   an impact; the end-pose check finds it (measured 0.02 mm; 18.1 mm
#:   without).
#: * box_beside_held_pair: a box falls at 4.9 m/s beside a capsule rolling
#:   on the floor.  The capsule's contact is the earliest estimated impact.
#:   When the reruns re-decided their impact rows, the capsule's was a
#:   speculative row before its estimate and held the capsule just clear,
#:   so the search ran to the end of the step, while the box's corner (an
#:   impact row, left out of the reruns) ended in the floor.  Two safeguards
#:   each prevent it: the reruns leave out the same rows at every tau (the
#:   capsule then meets the floor at its time), and the other impact pairs
#:   are checked at the time found (the next test).  Measured: 0.14 mm with
#:   both, 17.9 mm with neither.
#: * corner_onto_touching_box: at 1/60 s a box tumbling at 13 rad/s touches
#:   a box on the floor (0.1 mm) when its far corner swings down onto it.
#:   A deep point of a pair that touched at the start is a new impact when
#:   it lies far from every point that touched (measured 0.13 mm; 15.1 mm
#:   when the check skipped touching pairs, and without it).  The pair's
#:   least overlap is an edge axis; since such pairs keep their face
#:   manifold's points too, a row sees the corner come, so either safeguard
#:   alone stops it (0.15 mm with both, with either; 18.9 mm with neither).
#: * segment_slides_onto_box: a capsule's end is the impact on a box, but
#:   the capsule turns its middle down onto it within the step (1/240 s).
#:   The segment's closest point slides out of the matching radius of where
#:   it started; followed by its points alone, the search tracked the end,
#:   which never closed, and the segment ended inside the box.  The search
#:   follows the impact's feature ids too (measured 0.000 mm; 3.47 mm
#:   without, after 30 search iterations).
#:
#: Restitution below 1 creates no energy either way.
TOI_CASES = {
    "capsule_round_box_edge": ("missed_impact_capsule_box.toml", "missed", "missed_impacts", 1e-4, 0.01),
    "box_beside_held_pair": ("impact_behind_a_held_pair.toml", "others_and_rows", None, 3e-4, 0.01),
    "corner_onto_touching_box": ("missed_impact_onto_touching_box.toml", "missed_and_face_points", "missed_impacts", 3e-4,
                                 0.01),
    "segment_slides_onto_box": ("impact_segment_slides_onto_box.toml", "fids", "impacts", 3e-4, 3e-3),
}


@pytest.mark.parametrize("guard", [True, False])
@pytest.mark.parametrize("case", sorted(TOI_CASES))
def test_time_of_impact_safeguards(monkeypatch, case, guard):
    """Each fuzz case (``TOI_CASES``) with its safeguard on and off."""
    from physbench.harness.runner import run

    name, what, counter, bound, without = TOI_CASES[case]
    if not guard:
        _without(monkeypatch, what)
    res = run(load_scene(DATA / name), "reference")
    assert res.status == "ok", res.message
    assert res.metrics["energy_gain"] <= 1e-9
    if guard:
        if counter is not None:
            assert res.stages["counters"].get(counter, 0) >= 1
        assert res.metrics["max_penetration"] <= bound
    else:
        assert res.metrics["max_penetration"] >= without


@pytest.mark.parametrize("name", ["impact_search_corner_rocking_down.toml", "impact_search_corner_held_clear.toml"])
def test_impact_search_converges_in_a_few_reruns(name):
    """Each iteration of the time-of-impact search reruns the whole step, so
    a search that does not converge costs 30 steps.  Two box corners from a
    random pile (tests/data, see their comments): one curving in before its
    row's estimate (the reruns left it a speculative row, which held it on a
    plateau just clear of the floor), one held clear all step by the solve
    (bisection crept towards the end of the step).  Measured before the
    fixes: 60 and 32 search iterations for 2 impacts; now 6 for 1 and 4 for
    2."""
    from physbench.harness.runner import run

    res = run(load_scene(DATA / name), "reference")
    assert res.status == "ok", res.message
    ctr = res.stages["counters"]
    assert ctr["impacts"] >= 1
    assert ctr["toi_iterations"] <= 8 * ctr["impacts"]
    assert res.metrics["max_penetration"] <= 1e-4
    assert res.metrics["energy_gain"] <= 1e-9


@pytest.mark.parametrize("face_points", [True, False])
def test_box_edge_landing_keeps_the_face_points(monkeypatch, face_points):
    """A box spinning at 24 rad/s about an edge that crosses another box's
    edge brings the edge's end down onto that box's face at 2 m/s
    (tests/data/box_edge_landing_spinning.toml, one step at 1/240 s).  The
    pair's least overlap switches between the face axis and an edge axis as
    the box turns.  With an edge axis the manifold was one edge-edge point,
    blind to the face coming down; now it keeps the face manifold's points
    as well (their gaps clamped at the edge axis' overlap, the pair's
    least).  Measured: 4 search iterations for 1 impact, 0.55 mm at the end
    of the step (the edge contact sliding on while the box turns: the
    second-order drift left to position correction); with the edge point
    alone, 120 iterations for 3 impacts, an impact dropped, 5.7 mm."""
    from physbench.harness.runner import run

    if not face_points:
        _without(monkeypatch, "face_points")
    res = run(load_scene(DATA / "box_edge_landing_spinning.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.metrics["energy_gain"] <= 1e-9
    ctr = res.stages["counters"]
    if face_points:
        assert ctr.get("missed_dropped", 0) == 0
        assert ctr["toi_iterations"] <= 8 * ctr["impacts"]
        assert res.metrics["max_penetration"] <= 1e-3
    else:
        assert res.metrics["max_penetration"] >= 5e-3


@pytest.mark.parametrize("clear_end", [True, False])
def test_search_that_finds_no_impact_ends_a_plain_step(monkeypatch, clear_end):
    """A box at rest on the floor and against a wall, one corner 1.6 um
    clear, for 0.25 s (tests/data/box_resting_against_a_wall.toml).
    Gravity's approach makes the corner an impact by the step's mean
    motion, but the solve holds it clear: the search finds the pair still
    clear at the end of the step.  That step now ends there, and its solve
    warm-starts the next, where the resting pair is persistent and the
    corner no impact.  When the next step started cold, the corner was an
    impact again: measured 60 events in 60 steps, 1240 solver sweeps; now
    the first step's only (2 search iterations), 62 sweeps.  Either way
    the box stays put."""
    from physbench.harness.runner import run

    if not clear_end:
        _without(monkeypatch, "clear_end")
    res = run(load_scene(DATA / "box_resting_against_a_wall.toml"), "reference")
    assert res.status == "ok", res.message
    ctr = res.stages["counters"]
    pos = res.trace.valid().pos
    assert np.abs(pos[-1] - pos[0]).max() <= 1e-8
    assert res.metrics["max_penetration"] <= 1e-5
    if clear_end:
        assert ctr.get("impacts", 0) <= 1
        assert ctr.get("toi_iterations", 0) <= 4
    else:
        assert ctr["impacts"] >= 50


_SETTLING_COLUMN = """
    [scenario]
    family = "t"
    title = "ten spheres landing one by one"
    duration = 0.5
    dt = 0.004166666666666667
    effects = ["gravity", "contact", "friction"]
    [material.default]
    friction = 0.5
    [[body]]
    name = "ball"
    shape = "sphere"
    radius = 0.05
    mass = 0.1
    position = [0, 0, 0.06]
    [body.pattern]
    kind = "grid"
    counts = [1, 1, 10]
    spacing = 0.11
    [[static]]
    shape = "plane"
    normal = [0, 0, 1]
    """


@pytest.mark.parametrize("stall", [True, False])
def test_impact_search_stops_at_touching_when_it_stalls(tmp_path, monkeypatch, stall):
    """Ten spheres 1 cm apart drop and land one on another.  Solved by
    Gauss-Seidel alone (``direct_start = false``, 10 sweeps: the regime of
    big scenes, above the direct start's 400 rows) the column below is still
    settling into itself, its end pose moves with each rerun's length, and
    the gap of the landing pair flattens at its root: Newton takes off only
    30-40 % of it per rerun.  Touching, such a search stops
    (``toi_stalls``): measured 49 search iterations for 10 impacts (5
    stalls), 119 without the stop.  Every search still ends touching
    (largest |gap| at a stop 9.2e-7 m, 1.4e-9 m without), the column's
    overlap is the same (0.45 mm, from Gauss-Seidel alone) and it gains no
    energy."""
    import physbench.engine.ccd
    from physbench import engine
    from physbench.engine.solver import TOUCH_TOL
    from physbench.harness.runner import run

    if not stall:
        monkeypatch.setattr(engine.ccd, "STALL_RATIO", math.inf)
    gaps = []
    search = engine.ccd._search

    def recording(model, state, ctx, stages, profile, pair, *args):
        out = search(model, state, ctx, stages, profile, pair, *args)
        gaps.append(engine.ccd.pair_gap(model, ctx, pair.a, pair.b, pair.sidx, pair.loc, pair.excl, pair.fids)[0])
        return out

    monkeypatch.setattr(engine.ccd, "_search", recording)
    sc = scene_from(tmp_path, _SETTLING_COLUMN)
    res = run(sc, "reference", {"direct_start": False, "iterations": 10})
    assert res.status == "ok", res.message
    ctr = res.stages["counters"]
    assert ctr["impacts"] == 10
    assert len(gaps) >= 10 and max(abs(g) for g in gaps) <= TOUCH_TOL
    assert res.metrics["energy_gain"] <= 1e-9
    if stall:
        assert ctr["toi_stalls"] >= 1 and ctr["toi_iterations"] <= 6 * ctr["impacts"]
    else:
        assert "toi_stalls" not in ctr and ctr["toi_iterations"] >= 10 * ctr["impacts"]


def test_sparse_direct_start_matches_the_dense_one(tmp_path, monkeypatch):
    """Above DIRECT_MAX_ROWS rows the direct start is a sparse solve (it
    was skipped there, and Gauss-Seidel alone let big scenes' columns
    settle into one another: 0.79 mm on spheres_1000 in 1 s).  Forced on
    the ten-sphere landing column, the sparse path gives the dense path's
    trajectory (measured: identical) and the same overlap (1e-10 m);
    Gauss-Seidel alone leaves 0.45 mm (the stall test above)."""
    import physbench.engine.solver
    from physbench import engine
    from physbench.harness.runner import run

    sc = scene_from(tmp_path, _SETTLING_COLUMN)
    dense = run(sc, "reference", {"iterations": 10})
    monkeypatch.setattr(engine.solver, "DIRECT_MAX_ROWS", 0)
    monkeypatch.setattr(engine.solver, "PHASE_BY_PHASE", True)  # the path the spy can see
    calls = []
    to_sparse = engine.solver.Rows.sparse_normal_solve
    monkeypatch.setattr(engine.solver.Rows, "sparse_normal_solve", lambda self, *a: calls.append(1) or to_sparse(self, *a))
    sparse = run(sc, "reference", {"iterations": 10})
    assert len(calls) >= 100  # (every step with contacts)
    assert dense.status == sparse.status == "ok"
    assert dense.stages["counters"]["impacts"] == sparse.stages["counters"]["impacts"] == 10
    pd, ps = dense.trace.valid().pos, sparse.trace.valid().pos
    assert np.abs(pd - ps).max() <= 1e-9
    assert sparse.metrics["max_penetration"] <= 1e-6 and dense.metrics["max_penetration"] <= 1e-6


def test_impact_search_reruns_leave_out_the_same_rows_at_every_tau(monkeypatch):
    """The rows a search's reruns leave out are the step's impact rows
    (``ctx.drop_rows``), not re-decided with each rerun's length: with
    them re-decided, the rocking corner's search runs to the iteration
    limit."""
    import physbench.engine.ccd
    from physbench import engine
    from physbench.harness.runner import run

    _without(monkeypatch, "rows")
    res = run(load_scene(DATA / "impact_search_corner_rocking_down.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.stages["counters"]["toi_iterations"] >= engine.ccd.TOI_MAX_ITER


def test_other_impact_pairs_are_checked_at_the_time_found(monkeypatch):
    """The box beside the held capsule (``TOI_CASES``) with the reruns'
    rows re-decided as before: the search for the capsule runs to the end
    of the step, and it is the check of the step's other impact pairs at
    the time found that switches to the box's corner (measured 0.13 mm, 3
    switches; 17.9 mm without that check too)."""
    from physbench.harness.runner import run

    _without(monkeypatch, "rows")
    res = run(load_scene(DATA / "impact_behind_a_held_pair.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.stages["counters"].get("toi_switches", 0) >= 1
    assert res.metrics["max_penetration"] <= 3e-4
    assert res.metrics["energy_gain"] <= 1e-9


def test_missed_impact_search_leaves_out_where_the_pair_touched():
    """At 1/60 s a box tumbling at 15 rad/s lands at 3 m/s on a box it
    already overlaps by 1.6 mm elsewhere
    (tests/data/missed_impact_beside_an_overlap.toml).  The landing corner
    is a missed impact.  The search for its time leaves out the contacts
    near where the pair touched at the start, so it finds the time and the
    impact is resolved.  The deepest overlap stays near the one it started
    with: 2.2 mm (measured).  When the search counted the old overlap, it
    went to tau = 0, the impact was dropped, and the box sank 10.9 mm."""
    from physbench.harness.runner import run

    res = run(load_scene(DATA / "missed_impact_beside_an_overlap.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.metrics["energy_gain"] <= 1e-9
    assert res.stages["counters"].get("missed_impacts", 0) >= 1
    assert res.stages["counters"].get("missed_dropped", 0) == 0
    assert res.metrics["max_penetration"] <= 3e-3  # 1.6 mm at the start


@pytest.mark.parametrize("checked", [True, False])
def test_end_pose_check_covers_pairs_that_are_impacts_already(monkeypatch, checked):
    """The box landing on a box it overlaps elsewhere, with no floor
    (tests/data/missed_impact_of_an_impact_pair.toml, 1/60 s): the pair's
    own rows are the step's first impact, and the search finds them clear at
    the end of the step, while a corner no row saw swings into the other
    box.  The end-pose check now looks at impact pairs too (deep points far
    from their impact rows and touching points are another impact of the
    pair): measured 4.2 mm, the overlap the pair started with (1.6 mm)
    sliding on at 1/60 s; 13.7 mm when impact pairs were skipped."""
    from physbench.harness.runner import run

    if not checked:
        _without(monkeypatch, "impact_pairs")
    res = run(load_scene(DATA / "missed_impact_of_an_impact_pair.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.metrics["energy_gain"] <= 1e-9
    if checked:
        assert res.metrics["max_penetration"] <= 5e-3
    else:
        assert res.metrics["max_penetration"] >= 1e-2


def test_settling_stop_of_the_impact_search_is_kept():
    """A box slides on an edge 4 um above the floor at 1/60 s, its corners
    impacts by the step's mean motion, while another box tumbles down beside
    it (tests/data/impact_search_settling_box.toml).  The time-of-impact search
    stops where a corner settles (touching, no longer approaching) and
    commits there.  It used to go back to the last clear time, 0.05 ms in,
    32 times over: the event budget was spent, and the landing box was left
    a speculative row that ended 13.9 mm in the floor (44 impact events in
    3 steps).  Measured now: 0.01 mm, 25 events."""
    from physbench.harness.runner import run

    res = run(load_scene(DATA / "impact_search_settling_box.toml"), "reference")
    assert res.status == "ok", res.message
    assert res.metrics["energy_gain"] <= 1e-9
    assert res.metrics["max_penetration"] <= 3e-4
    # far from the budget: ccd_max_events per substep, 3 steps here
    assert res.stages["counters"]["impacts"] < int(res.settings["ccd_max_events"])


def test_impact_events_inside_a_rattling_gauss_seidel_column_add_no_energy():
    """column_5 solved by Gauss-Seidel alone (no direct start, 5 sweeps, dt
    0.008 s) rattles: its corners lift and come down, and some are impact
    events.  The impact solve stops every touching approach in the stack;
    re-applying the cached resting forces over the rest of the step counted
    them twice, and 5 sweeps could not take the excess out: the column
    gained 16 x its energy and was thrown 8 m.  The rest of a step after an
    event now starts cold: no energy gained, and the column drifts less
    than with no such events at all (5.4 cm)."""
    from physbench.harness.runner import run

    res = run(load_scene("stacking.column_5"), "reference", {"direct_start": False, "dt": 0.008, "iterations": 5})
    assert res.status == "ok"
    assert res.stages["counters"].get("impacts", 0) > 0  # the case this is about
    assert res.metrics["energy_gain"] <= 0.01
    assert res.metrics["stack_drift"] <= 0.054


@pytest.mark.parametrize("tilt", [2.0, 25.0])
def test_cylinder_settling_on_its_cap_raises_no_endless_impacts(tmp_path, tilt):
    """A cylinder dropped 5 cm onto its cap settles; its rim points that
    carry no load (support points that turn in the body frame as it rocks)
    close at -un = g h / 2 > the restitution threshold every step from
    gravity alone.  They are not new impacts (they were not approaching at
    the start of the step): at rest there are no impact events (per-point
    classification alone gave 4800 events a second)."""
    a = math.radians(tilt)
    sc = scene_from(tmp_path, f"""
        [scenario]
        family = "t"
        title = "cylinder on its cap"
        duration = 3.0
        dt = {1 / 240}
        effects = ["gravity", "contact", "friction", "gyroscopic"]
        [material.default]
        friction = 0.5
        [[body]]
        name = "c"
        shape = "cylinder"
        radius = 0.1
        half_length = 0.2
        mass = 1.0
        position = [0, 0, {0.2 * math.cos(a) + 0.1 * math.sin(a) + 0.05}]
        orientation = [{math.cos(a / 2)}, {math.sin(a / 2)}, 0.0, 0.0]
        [[static]]
        shape = "plane"
        normal = [0, 0, 1]
        offset = 0.0
        """)
    eng = engine_for(sc)
    eng.step(480)
    before = eng.profile.as_dict()["counters"].get("impacts", 0)
    assert before <= 40  # the landing and the rocking onto the cap
    eng.step(240)
    assert eng.profile.as_dict()["counters"].get("impacts", 0) == before
    assert eng.state.x[0][2] == pytest.approx(0.2, abs=1e-4)  # standing on its cap
    assert np.abs(eng.state.v[0]).max() < 1e-9 and np.abs(eng.state.w[0]).max() < 1e-9


def test_without_ccd_the_ball_tunnels(tmp_path):
    """The measured counterpart: ccd = off passes straight through."""
    sc = scene_from(tmp_path, BULLET.format(dt=1 / 240, e=0.5))
    eng = engine_for(sc, {"ccd": "off"})
    eng.step(12)
    assert eng.state.x[0, 0] > 1.0
    assert "ccd" not in eng.profile.calls


# ---- stacking -------------------------------------------------------------------

COLUMN = """
    [scenario]
    family = "t"
    title = "column"
    duration = {T}
    dt = {dt}
    effects = ["gravity", "contact", "friction"]
    [material.default]
    friction = 0.5
    [[body]]
    name = "box"
    shape = "box"
    half_extents = [0.1, 0.1, 0.1]
    mass = 1.0
    position = [0, 0, 0.1]
    [body.pattern]
    kind = "column"
    count = 10
    [[static]]
    shape = "plane"
    normal = [0, 0, 1]
    """


def _column(tmp_path, T, dt, **settings):
    sc = scene_from(tmp_path, COLUMN.format(T=T, dt=dt))
    eng = engine_for(sc, settings)
    x0 = eng.state.x.copy()
    drift = pen = 0.0
    for _ in range(int(round(T / dt))):
        eng.step()
        drift = max(drift, float(np.max(np.linalg.norm(eng.state.x - x0, axis=1))))
        z = eng.state.x[:, 2]
        pen = max(pen, 0.1 - z[0], float(np.max(0.2 - np.diff(z))))
    return drift, pen, eng


@pytest.mark.parametrize("dt", [1 / 60, 1 / 240])
def test_column_short(tmp_path, dt):
    drift, pen, eng = _column(tmp_path, 1.0, dt)
    assert drift <= 1e-6 and pen <= 1e-6  # requirement 5 mm; the direct start makes it exact


def test_column_gauss_seidel_only(tmp_path):
    """Without the direct start (plain warm-started Gauss-Seidel) the column
    sags but meets the requirement at dt = 1/240."""
    drift, pen, eng = _column(tmp_path, 1.0, 1 / 240, direct_start=False)
    assert drift <= 5e-3 and pen <= 5e-3


def test_heavy_on_light_mass_ratio_1000(tmp_path):
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "heavy on light"
        duration = 1.0
        dt = 0.004166666666666667
        effects = ["gravity", "contact", "friction"]
        [material.default]
        friction = 0.5
        [[body]]
        name = "light"
        shape = "box"
        half_extents = [0.05, 0.05, 0.05]
        mass = 1.0
        position = [0, 0, 0.05]
        [[body]]
        name = "heavy"
        shape = "box"
        half_extents = [0.05, 0.05, 0.05]
        mass = 1000.0
        position = [0, 0, 0.15]
        [[static]]
        shape = "plane"
        normal = [0, 0, 1]
        """)
    eng = engine_for(sc)
    x0 = eng.state.x.copy()
    eng.step(240)
    assert np.abs(eng.state.x - x0).max() <= 1e-6


_CRADLE = """
    [scenario]
    family = "t"
    title = "cradle"
    duration = 0.3
    dt = 0.001
    effects = ["contact", "restitution"]
    [material.default]
    restitution = 1.0
    [[body]]
    name = "striker"
    shape = "sphere"
    radius = 0.025
    mass = 0.5
    position = [-0.1, 0, 0]
    velocity = [1.0, 0, 0]
    [[body]]
    name = "ball"
    shape = "sphere"
    radius = 0.025
    mass = 0.5
    [body.pattern]
    kind = "row"
    count = 4
    """


def test_newtons_cradle_hands_momentum_down_the_row(tmp_path):
    """A striker hits four touching equal balls (e = 1): impulse propagation
    gives the textbook result -- the last ball leaves with the striking
    speed, all others stop."""
    sc = scene_from(tmp_path, _CRADLE)
    eng = engine_for(sc)
    eng.step(300)
    assert np.allclose(eng.state.v[:, 0], [0, 0, 0, 0, 1.0], atol=1e-12)


# the cradle beside a row of clay balls (e = 0), struck at the same moment
_STRUCK_ROWS = _CRADLE.rstrip(" ") + """
    [material.clay]
    restitution = 0.0
    [[body]]
    name = "clay_striker"
    shape = "sphere"
    radius = 0.025
    mass = 0.5
    material = "clay"
    position = [-0.1, 0.2, 0]
    velocity = [1.0, 0, 0]
    [[body]]
    name = "clay"
    shape = "sphere"
    radius = 0.025
    mass = 0.5
    material = "clay"
    position = [0, 0.2, 0]
    [body.pattern]
    kind = "row"
    count = 4
    """


@pytest.mark.parametrize("plastic", ["simultaneous", "sequential"])
def test_plastic_impact_on_a_row_is_one_simultaneous_impact(tmp_path, plastic):
    """Two strikers hit rows of four touching equal balls at the same
    moment (the impact solve itself, on the touching contacts): one row
    elastic (a Newton's cradle), one of clay (e = 0).  The impact solve
    splits them into islands.  The cradle is propagated pair by pair: the
    last ball leaves with the striking speed.  The clay row is one
    simultaneous plastic impact (Moreau's law, the default): all five balls
    leave together at v / 5 -- momentum kept, no contact approaching.
    Propagated instead ("sequential"), the clay pairs push one another back
    and forth until no pair approaches faster than the restitution
    threshold (0.01 m/s), then stop the slow approaches one sweep at a
    time: the balls leave with a spread of speeds (measured: 1.2e-2 m/s;
    simultaneous: 2.8e-10) that the next step's contact solve takes out."""
    from physbench.engine.collision import collide_pairs
    from physbench.engine.solver import impact_solve

    sc = scene_from(tmp_path, _STRUCK_ROWS.replace("[-0.1, 0, 0]", "[-0.05, 0, 0]")
                    .replace("[-0.1, 0.2, 0]", "[-0.05, 0.2, 0]"))
    eng = engine_for(sc)
    model, state = eng.model, eng.state
    pi, pj = np.triu_indices(model.n, 1)
    z = np.zeros(0, np.int64)
    c = collide_pairs(model, state.x, quat_to_matrix(state.q), pi, pj, (z, z), (z, z),
                      np.full(pi.size, 1e-5), z.astype(float), z.astype(float))
    assert c.m == 8 and np.abs(c.gap).max() <= 1e-12
    impact_solve(model, state, c, 10, 0.01, False, plastic)
    v = state.v[:, 0]
    assert np.allclose(v[:5], [0, 0, 0, 0, 1.0], atol=1e-12)  # the cradle, either way
    assert np.sum(v[5:]) == pytest.approx(1.0, abs=1e-12)  # momentum (equal masses)
    spread = float(np.ptp(v[5:]))
    if plastic == "simultaneous":
        assert np.allclose(v[5:], 0.2, atol=1e-9)
    else:
        assert spread > 1e-3, spread


@pytest.mark.slow
def test_column_ten_seconds(tmp_path):
    drift, pen, eng = _column(tmp_path, 10.0, 1 / 240)
    assert drift <= 5e-3 and pen <= 5e-3  # measured ~1e-14 m and 0
    assert np.abs(eng.state.v).max() <= 1e-3  # settled


def test_resting_column_is_not_collided_again_at_its_end_pose(tmp_path, monkeypatch):
    """The end-pose check for missed impacts collides only pairs whose
    bodies moved, start pose to end pose, far enough to overlap beyond its
    tolerance.  Bounded by the broad phase's sweep instead (the speeds
    before and after the solve: gravity's g h before it), every pair of the
    resting column was collided twice a step (590 us of its 2.4 ms,
    measured)."""
    import physbench.engine.ccd
    from physbench import engine
    from physbench.harness.runner import run

    calls = []
    collide = engine.ccd.collide_pairs
    monkeypatch.setattr(engine.ccd, "collide_pairs", lambda *a, **k: calls.append(1) or collide(*a, **k))
    drift, pen, eng = _column(tmp_path, 0.5, 1 / 240)
    assert drift <= 1e-6 and pen <= 1e-6
    assert len(calls) == 0
    # the check itself still runs where bodies move: the capsule swinging
    # round a box's edge (TOI_CASES) is found by it
    res = run(load_scene(DATA / "missed_impact_capsule_box.toml"), "reference")
    assert len(calls) > 0 and res.stages["counters"].get("missed_impacts", 0) >= 1


@pytest.mark.parametrize("ccd", ["toi", "events"])
def test_ccd_toi_leaves_slow_impacts_discrete(tmp_path, ccd):
    """ccd = "toi" resolves only fast bodies' impacts at their time; two
    spheres meeting at 1 m/s (4.2 mm a step at 1/240 s against 50 mm radii)
    collide discretely: they overlap, then separate, and no impact event
    is made -- neither from the contact rows nor from the end-pose check
    for missed impacts, which made every slow collision an event
    (spheres_1000 at the cheap settings: 1417 events in 120 steps, 8x the
    cost).  With ccd = "events" the same impact is an event and leaves no
    overlap."""
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "slow head-on"
        duration = 0.2
        dt = 0.004166666666666667
        effects = ["contact", "restitution"]
        [material.default]
        restitution = 1.0
        [[body]]
        name = "a"
        shape = "sphere"
        radius = 0.05
        mass = 1.0
        position = [-0.0513, 0, 0]
        velocity = [0.5, 0, 0]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = 1.0
        position = [0.0513, 0, 0]
        velocity = [-0.5, 0, 0]
        """)
    from physbench.harness.runner import run

    res = run(sc, "reference", {"ccd": ccd})
    assert res.status == "ok", res.message
    ctr = res.stages["counters"]
    x = res.trace.valid().pos
    assert x[-1, 0, 0] < -0.06 and x[-1, 1, 0] > 0.06  # they bounced apart
    overlap = float(np.max(0.1 - (x[:, 1, 0] - x[:, 0, 0])))
    if ccd == "toi":
        assert ctr.get("impacts", 0) == 0 and ctr.get("missed_impacts", 0) == 0
        assert overlap >= 1e-3  # discrete: 2.6 mm of gap closed at 1 m/s in a step of 4.2 mm
    else:
        assert ctr.get("impacts", 0) >= 1
        assert overlap <= 1e-9


def test_touching_points_that_no_event_resolves_stay_solver_rows():
    """With ccd = "toi" only fast bodies get impact events; a touching point
    approaching fast on a slow body is left to the solve, with its
    restitution target.  Treating it as an impact nobody resolves (dropped
    from the rows) let 100 falling spheres sink 0.46 m into each other;
    solved, the pile overlaps by at most 2.7 mm (measured, as before)."""
    from physbench.harness.bench import spheres_scene
    from physbench.harness.runner import run
    from physbench.contract.scene import Scene

    sc0 = spheres_scene(100)
    res = run(Scene(**{**sc0.__dict__, "duration": 1.5}), "reference",
              {"ccd": "toi", "integrator": "semi_implicit_euler"})
    assert res.status == "ok"
    assert res.metrics["max_penetration"] <= 0.01


def test_sphere_strikes_a_cylinder_head_on(tmp_path):
    """A 1 kg ball at 2 m/s strikes a 2 kg standing cylinder's side through
    its centre (no gravity, e = 0.8): the 1D law, v1 = (m1 - e m2) u / (m1 +
    m2) = -0.4 m/s, v2 = (1 + e) m1 u / (m1 + m2) = 1.2 m/s, no spin."""
    from physbench.harness.runner import run

    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "ball strikes a cylinder"
        duration = 0.3
        dt = 0.004166666666666667
        effects = ["contact", "restitution", "gyroscopic"]
        [material.default]
        restitution = 0.8
        [[body]]
        name = "ball"
        shape = "sphere"
        radius = 0.1
        mass = 1.0
        position = [-0.5, 0.0, 0.0]
        velocity = [2.0, 0.0, 0.0]
        [[body]]
        name = "drum"
        shape = "cylinder"
        radius = 0.2
        half_length = 0.3
        mass = 2.0
        """)
    res = run(sc, "reference")
    assert res.status == "ok", res.message
    tr = res.trace
    assert tr.vel[-1, 0] == pytest.approx([-0.4, 0.0, 0.0], abs=1e-9)
    assert tr.vel[-1, 1] == pytest.approx([1.2, 0.0, 0.0], abs=1e-9)
    assert np.abs(tr.angvel[-1]).max() <= 1e-9
    assert res.metrics["max_penetration"] <= 1e-9


def test_sphere_rests_on_a_cylinder_cap(tmp_path):
    """A ball resting on a standing cylinder's cap (on the ground) stays put
    for 2 s; a ball dropped beside the axis lands on the cap and stays
    there too (its friction holds it, no contact point moves)."""
    from physbench.harness.runner import run

    text = """
        [scenario]
        family = "t"
        title = "ball on a drum"
        duration = 2.0
        dt = 0.004166666666666667
        effects = ["gravity", "contact", "friction", "gyroscopic"]
        [material.default]
        friction = 0.5
        static_friction = 0.5
        [[body]]
        name = "drum"
        shape = "cylinder"
        radius = 0.2
        half_length = 0.3
        mass = 2.0
        position = [0.0, 0.0, 0.3]
        [[body]]
        name = "ball"
        shape = "sphere"
        radius = 0.1
        mass = 1.0
        position = [X, 0.0, Z]
        [[static]]
        shape = "plane"
        normal = [0.0, 0.0, 1.0]
        """
    for x, z in ((0.0, 0.7), (0.1, 0.75)):
        res = run(scene_from(tmp_path, text.replace("X", repr(x)).replace("Z", repr(z))), "reference")
        assert res.status == "ok", res.message
        tr = res.trace
        assert tr.pos[-1, 1] == pytest.approx([x, 0.0, 0.7], abs=1e-5)
        assert tr.pos[-1, 0] == pytest.approx([0.0, 0.0, 0.3], abs=1e-5)
        assert res.metrics["max_penetration"] <= 1e-4
        assert res.metrics["energy_gain"] <= 1e-9


# ---------------------------------------------------------------------------
# cylinder-box and capsule-cylinder

def _cyl_sdf_local(u, hl, rc):
    """Signed distance of a point u (cylinder frame) to the solid cylinder,
    written out here (not the engine's) for the reference minimisations."""
    dr = math.hypot(u[0], u[1]) - rc
    dz = abs(u[2]) - hl
    return math.hypot(max(dr, 0.0), max(dz, 0.0)) + min(max(dr, dz), 0.0)


def _cyl_sdf_local_and_grad(u, hl, rc):
    """``_cyl_sdf_local`` (the value is its own) and its gradient in u,
    differentiated by hand piece by piece, for the reference minimisations'
    ``jac=True``: beyond the rim (radial and axial excess both positive) the
    gradient of the distance to the rim, beyond only the side or only a cap
    that excess's gradient, inside the larger excess's.  On the axis the
    radial direction is undefined and its part is taken as zero (a
    subgradient).  Checked against central differences at random points
    before use (agreement to 2e-9, the differences' own error)."""
    rho = math.hypot(u[0], u[1])
    dr = rho - rc
    dz = abs(u[2]) - hl
    g_r = np.array([u[0] / rho, u[1] / rho, 0.0]) if rho > 0.0 else np.zeros(3)
    g_z = np.array([0.0, 0.0, math.copysign(1.0, u[2])])
    if dr > 0.0 and dz > 0.0:
        g = (dr * g_r + dz * g_z) / math.hypot(dr, dz)
    elif dr > 0.0:
        g = g_r
    elif dz > 0.0:
        g = g_z
    else:
        g = g_r if dr >= dz else g_z
    return _cyl_sdf_local(u, hl, rc), g


def _lbfgsb_min(f, starts, bounds):
    """The smallest of the L-BFGS-B minima of f (which returns its value and
    gradient) from each of ``starts`` (ftol 1e-15, gtol 1e-12), for the
    reference minimisations.  BLAS is held to one thread while they run:
    scipy's L-BFGS-B calls OpenBLAS on its small matrices, whose woken
    threads busy-wait, and with another process on the other core that made
    these minimisations 20-40x slower; one thread gives the same minima bit
    for bit (value, point and iteration count of all 1265 runs checked)."""
    from scipy.optimize import minimize
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):
        return min(minimize(f, x0, jac=True, bounds=bounds, method="L-BFGS-B",
                            options={"ftol": 1e-15, "gtol": 1e-12}).fun for x0 in starts)


def _random_rotation(rng):
    q = rng.normal(size=4)
    return quat_to_matrix((q / np.linalg.norm(q))[None])[0]


def test_box_cylinder_gap_is_the_exact_distance():
    """Random separated poses: the smallest candidate gap equals the
    distance between the solids, found independently by minimising the
    cylinder's signed distance over the box (a convex problem: L-BFGS-B in
    the box's coordinates, from five starts, given the signed distance's
    gradient by the chain rule through the box's pose).  Every candidate's
    gap is the exact distance of its own point, so none may be smaller."""
    rng = np.random.default_rng(7)
    checked = 0
    while checked < 40:
        hb = rng.uniform(0.05, 0.3, 3)
        rc, hl = rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.3)
        Rb, Rc = _random_rotation(rng), _random_rotation(rng)
        d = rng.normal(size=3)
        cc = d / np.linalg.norm(d) * rng.uniform(0.1, 0.6)

        def f(u):
            # d/du of Rc.T (Rb u - cc) is Rc.T Rb: the gradient is Rb.T Rc grad
            val, grad = _cyl_sdf_local_and_grad(Rc.T @ (Rb @ u - cc), hl, rc)
            return val, Rb.T @ (Rc @ grad)

        true = _lbfgsb_min(f, [np.zeros(3)] + [rng.uniform(-hb, hb) for _ in range(4)], list(zip(-hb, hb)))
        if true <= 1e-4:
            continue  # overlapping or touching: the distance is what this test checks
        k, n, p, g, fid = box_cylinder(np.zeros((1, 3)), Rb[None], hb[None], cc[None], Rc[None],
                                       np.array([hl]), np.array([rc]))
        assert g.min() == pytest.approx(true, abs=1e-8)
        # the normals are unit, from the box toward the cylinder
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
        i = int(np.argmin(g))
        assert n[i] @ cc > 0.0 or g[i] < 0.05
        checked += 1


def test_capsule_cylinder_gap_is_the_exact_distance():
    """As for the box: random separated poses, the smallest gap against the
    minimum over the capsule's segment of the cylinder's signed distance,
    less the capsule's radius (bounded scalar minimisation)."""
    from scipy.optimize import minimize_scalar

    rng = np.random.default_rng(8)
    checked = 0
    while checked < 40:
        r, hlc = rng.uniform(0.02, 0.1), rng.uniform(0.05, 0.3)
        rc, hl = rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.3)
        Ra, Rc = _random_rotation(rng), _random_rotation(rng)
        d = rng.normal(size=3)
        cc = d / np.linalg.norm(d) * rng.uniform(0.1, 0.6)
        ax = Ra[:, 2]
        true = minimize_scalar(lambda t: _cyl_sdf_local(Rc.T @ (t * ax - cc), hl, rc), bounds=(-hlc, hlc),
                               method="bounded", options={"xatol": 1e-12}).fun - r
        if true <= 1e-4:
            continue
        k, n, p, g, fid = capsule_cylinder(np.zeros((1, 3)), Ra[None], np.array([hlc]), np.array([r]), cc[None],
                                           Rc[None], np.array([hl]), np.array([rc]))
        assert g.min() == pytest.approx(true, abs=1e-8)
        assert np.all(g >= true - 1e-8)
        checked += 1


def test_box_cylinder_features_on_a_cap_and_across_the_side():
    """Hand-placed contacts: a box lying on a standing cylinder's cap
    overhangs the rim, so it rests on its corners inside the cap and on
    the points where its edges cross the rim; a box edge across a lying
    cylinder touches at one point, the edge's minimum."""
    I = np.eye(3)[None]
    # cylinder r 0.2, hl 0.1 standing at the origin; box 0.5 x 0.1 x 0.1
    # resting on the cap (1 mm apart), centred, along x: its four bottom
    # corners lie beyond the rim (x = +-0.25 > 0.2)
    k, n, p, g, fid = box_cylinder(np.array([[0.0, 0.0, 0.151]]), I, np.array([[0.25, 0.05, 0.05]]),
                                   np.zeros((1, 3)), I, np.array([0.1]), np.array([0.2]))
    touching = g < 2e-3
    assert np.allclose(g[touching], 1e-3, atol=1e-12)
    assert np.allclose(n[touching], [0.0, 0.0, -1.0])
    # support: the four crossings of the long bottom edges with the rim
    xs = math.sqrt(0.2 ** 2 - 0.05 ** 2)
    for sx in (-1, 1):
        for sy in (-1, 1):
            assert any(np.allclose(q[:2], [sx * xs, sy * 0.05], atol=1e-9) for q in p[touching])
    # a box edge across a lying cylinder (axis x): the box turned 45 degrees
    # about y, its lowest edge along y at height 0.201 touches the top line
    # at one point
    Rc = quat_to_matrix(np.array([[math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]]))  # body z -> world x
    k, n, p, g, fid = box_cylinder(np.array([[0.0, 0.0, 0.201 + 0.1 * math.sqrt(2.0)]]),
                                   quat_to_matrix(np.array([[math.cos(math.pi / 8), 0.0, math.sin(math.pi / 8), 0.0]])),
                                   np.array([[0.1, 0.1, 0.1]]), np.zeros((1, 3)), Rc, np.array([0.3]), np.array([0.2]))
    i = int(np.argmin(g))
    assert g[i] == pytest.approx(1e-3, abs=1e-9)
    assert 8 <= fid[i] < 20  # an edge minimum, not a corner
    # (the search brackets the point to 4e-9 of the edge: 1e-9 m here,
    # which tilts the normal by ~1e-9 m / r)
    assert np.allclose(n[i], [0.0, 0.0, -1.0], atol=1e-7)
    assert np.allclose(p[i], [0.0, 0.0, 0.2005], atol=1e-8)


_CYL_SCENE = """
    [scenario]
    family = "t"
    title = "cylinder contacts"
    duration = DUR
    dt = 0.004166666666666667
    effects = EFFECTS
    [material.default]
    MATERIAL
    BODIES
    STATICS
    """


def _cyl_run(tmp_path, bodies: str, statics: str, duration: float = 2.0,
             effects=("gravity", "contact", "friction", "gyroscopic")):
    from physbench.harness.runner import run

    # friction 0.5 and restitution 0.5 where the scene has the effect (a
    # coefficient without its effect is a spec error)
    material = "\n    ".join([*(["friction = 0.5", "static_friction = 0.5"] if "friction" in effects else []),
                             *(["restitution = 0.5"] if "restitution" in effects else [])])
    text = (_CYL_SCENE.replace("DUR", repr(duration)).replace("EFFECTS", repr(list(effects)).replace("'", '"'))
            .replace("MATERIAL", material).replace("BODIES", bodies).replace("STATICS", statics))
    res = run(scene_from(tmp_path, text), "reference")
    assert res.status == "ok", res.message
    return res


_TABLE = """
    [[static]]
    shape = "box"
    half_extents = [0.5, 0.5, 0.25]
    position = [0.0, 0.0, 0.25]
    """
_GROUND = """
    [[static]]
    shape = "plane"
    normal = [0.0, 0.0, 1.0]
    """
_CAN = """
    [[body]]
    name = "can"
    shape = "cylinder"
    radius = 0.2
    half_length = 0.1
    mass = 2.0
    position = [0.0, 0.0, 0.1]
    """


@pytest.mark.parametrize("body", [
    # a can standing on a table (a static box)
    """
    [[body]]
    name = "can"
    shape = "cylinder"
    radius = 0.05
    half_length = 0.1
    mass = 1.0
    position = [0.1, 0.05, 0.6]
    """,
    # a drum lying on the table
    """
    [[body]]
    name = "drum"
    shape = "cylinder"
    radius = 0.05
    half_length = 0.15
    mass = 1.0
    position = [0.1, 0.05, 0.55]
    orientation = [0.7071067811865476, 0.7071067811865476, 0.0, 0.0]
    """,
], ids=["standing", "lying"])
def test_cylinder_rests_on_a_static_box(tmp_path, body):
    res = _cyl_run(tmp_path, body, _TABLE)
    tr = res.trace
    assert np.abs(tr.pos[-1, 0] - tr.pos[0, 0]).max() <= 1e-9
    assert np.abs(tr.quat[-1, 0] - tr.quat[0, 0]).max() <= 1e-9
    assert res.metrics["max_penetration"] <= 1e-9
    assert res.metrics["energy_gain"] <= 1e-9


@pytest.mark.parametrize("body", [
    # a box on the cap, within the rim: rests on its corners
    """
    [[body]]
    name = "box"
    shape = "box"
    half_extents = [0.1, 0.08, 0.05]
    mass = 1.0
    position = [0.03, 0.02, 0.25]
    """,
    # a long box over the cap, its corners beyond the rim: rests on the
    # points where its edges cross the rim
    """
    [[body]]
    name = "box"
    shape = "box"
    half_extents = [0.25, 0.05, 0.05]
    mass = 1.0
    position = [0.0, 0.0, 0.25]
    """,
    # a capsule lying across the cap: rests on the chord's ends
    """
    [[body]]
    name = "stick"
    shape = "capsule"
    radius = 0.03
    half_length = 0.3
    mass = 1.0
    position = [0.02, 0.05, 0.23]
    orientation = [0.7071067811865476, 0.0, 0.7071067811865476, 0.0]
    """,
], ids=["box", "long_box", "capsule"])
def test_bodies_rest_on_a_cylinder_cap(tmp_path, body):
    """Each of these tips over unless its support spans its centre of mass
    with the right points: every point must be where it truly touches."""
    res = _cyl_run(tmp_path, _CAN + body, _GROUND)
    tr = res.trace
    assert np.abs(tr.pos[-1] - tr.pos[0]).max() <= 1e-8
    assert np.abs(tr.quat[-1] - tr.quat[0]).max() <= 1e-8
    assert res.metrics["max_penetration"] <= 1e-8
    assert res.metrics["energy_gain"] <= 1e-9


def test_drum_rolls_down_a_tilted_static_box_as_on_a_slope(tmp_path):
    """A solid cylinder rolling without slipping down a 15 degree incline
    made of a tilted static box: s = 1/2 (2/3 g sin th) t^2, as on a plane
    slope (mu 0.5 > tan(th) / 3), and it stays on the surface."""
    th = math.radians(15.0)
    q = [math.cos(-th / 2), 0.0, math.sin(-th / 2), 0.0]
    Rb = quat_to_matrix(np.array([q]))[0]
    nrm = Rb[:, 2]
    down = np.array([-nrm[2], 0.0, nrm[0]])
    c0 = nrm * 0.1
    body = f"""
    [[body]]
    name = "drum"
    shape = "cylinder"
    radius = 0.1
    half_length = 0.15
    mass = 1.0
    position = {[float(x) for x in c0]}
    orientation = [0.7071067811865476, 0.7071067811865476, 0.0, 0.0]
    """
    static = f"""
    [[static]]
    shape = "box"
    half_extents = [3.0, 1.0, 0.2]
    position = {[float(x) for x in -nrm * 0.2]}
    orientation = {q}
    """
    res = _cyl_run(tmp_path, body, static, duration=1.0)
    tr = res.trace
    s = (tr.pos[:, 0] - c0) @ down
    a = 2.0 / 3.0 * 9.81 * math.sin(th)
    assert s[-1] == pytest.approx(0.5 * a * tr.t[-1] ** 2, rel=1e-9)
    assert np.abs((tr.pos[:, 0] - c0) @ nrm).max() <= 1e-9
    assert res.metrics["energy_gain"] <= 1e-9


def test_drum_dropped_flat_on_a_table_bounces_by_restitution(tmp_path):
    """A lying drum dropped 0.2 m onto a static box (e = 0.5) lands on its
    side line -- two contact points at once -- and rises back to e^2 of
    the drop with no spin and no sideways motion."""
    body = """
    [[body]]
    name = "drum"
    shape = "cylinder"
    radius = 0.05
    half_length = 0.15
    mass = 1.0
    position = [0.0, 0.0, 0.75]
    orientation = [0.7071067811865476, 0.7071067811865476, 0.0, 0.0]
    """
    res = _cyl_run(tmp_path, body, _TABLE, duration=0.6, effects=("gravity", "contact", "restitution"))
    tr = res.trace
    vz, z = tr.vel[:, 0, 2], tr.pos[:, 0, 2]
    after = np.flatnonzero(vz > 0.0)
    assert after.size
    i = int(after[0])
    # ballistic after the bounce: its energy above the resting height is e^2 of the drop's
    e_after = 0.5 * vz[i] ** 2 + 9.81 * (z[i] - 0.55)
    # (to the time-of-impact tolerance, 1e-9 m of height: 1e-8 of the energy)
    assert e_after == pytest.approx(0.25 * 9.81 * 0.2, rel=1e-7)
    assert np.abs(tr.angvel).max() <= 1e-9
    assert np.abs(tr.pos[:, 0, :2]).max() <= 1e-12
    assert res.metrics["max_penetration"] <= 1e-9


# ---------------------------------------------------------------------------
# cylinder-cylinder

def test_cylinder_cylinder_gap_is_the_exact_distance():
    """Random separated poses: the smallest gap equals the distance between
    the solids, found independently by minimising the second cylinder's
    signed distance over the first (L-BFGS-B in polar coordinates of the
    first, from twelve starts; the polar map is not convex, hence the
    starts; the signed distance's gradient is given by the chain rule
    through the polar map and the poses).  Every candidate's gap is the
    exact distance of its own point, so none may be smaller."""
    rng = np.random.default_rng(9)
    checked = 0
    while checked < 40:
        ra, hla = rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.3)
        rb, hlb = rng.uniform(0.05, 0.2), rng.uniform(0.05, 0.3)
        Ra, Rb = _random_rotation(rng), _random_rotation(rng)
        d = rng.normal(size=3)
        cb = d / np.linalg.norm(d) * rng.uniform(0.1, 0.7)

        def f(x):
            c, s = math.cos(x[1]), math.sin(x[1])
            p = Ra @ np.array([x[0] * c, x[0] * s, x[2]])
            val, grad = _cyl_sdf_local_and_grad(Rb.T @ (p - cb), hlb, rb)
            # gradient in q = (r cos t, r sin t, z) (the first's frame), then
            # through d q / d (r, t, z)
            gq = Ra.T @ (Rb @ grad)
            return val, np.array([gq[0] * c + gq[1] * s, x[0] * (gq[1] * c - gq[0] * s), gq[2]])

        starts = [np.array([rng.uniform(0, ra), rng.uniform(0, 2 * math.pi), rng.uniform(-hla, hla)])
                  for _ in range(12)]
        true = _lbfgsb_min(f, starts, [(0, ra), (None, None), (-hla, hla)])
        if true <= 1e-4:
            continue
        k, n, p, g, fid = cylinder_cylinder(np.zeros((1, 3)), Ra[None], np.array([hla]), np.array([ra]), cb[None],
                                            Rb[None], np.array([hlb]), np.array([rb]))
        assert g.min() == pytest.approx(true, abs=1e-8)
        assert np.all(g >= true - 1e-8)
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
        checked += 1


def test_cylinder_cylinder_features_of_stacked_cans():
    """Hand-placed: equal cans stacked coaxially (their rims coincide, the
    case where a point's nearest face is decided by round-off) touch on
    four points of the rim with the axis as normal; offset, they touch on
    the ends of the two discs' overlap (the rims' crossings) and on the
    rim points reaching farthest into the other disc."""
    I = np.eye(3)[None]
    one = np.array([0.1])
    k, n, p, g, fid = cylinder_cylinder(np.zeros((1, 3)), I, one, one, np.array([[0.0, 0.0, 0.2 - 1e-6]]), I,
                                        one, one, np.array([0.01]))
    assert k.size == 4
    assert np.allclose(g, -1e-6, atol=1e-15)
    assert np.allclose(n, [0.0, 0.0, 1.0])
    assert np.allclose(np.hypot(p[:, 0], p[:, 1]), 0.1)
    # offset by (0.053, 0.017): at most four points (the reduction), every
    # one in both discs (their lens), spanning both axes -- so that the
    # support holds whichever can is on top
    from scipy.spatial import Delaunay

    c = np.array([0.053, 0.017])
    k, n, p, g, fid = cylinder_cylinder(np.zeros((1, 3)), I, one, one, np.array([[c[0], c[1], 0.2 - 1e-6]]), I,
                                        one, one, np.array([0.01]))
    assert 3 <= k.size <= 4
    assert np.allclose(g, -1e-6, atol=1e-15)
    assert np.allclose(n, [0.0, 0.0, 1.0])
    assert np.all(np.hypot(p[:, 0], p[:, 1]) <= 0.1 + 1e-10)
    assert np.all(np.hypot(p[:, 0] - c[0], p[:, 1] - c[1]) <= 0.1 + 1e-10)
    hull = Delaunay(p[:, :2])
    assert np.all(hull.find_simplex(np.array([[0.0, 0.0], c])) >= 0)


def _can(name, r, hl, pos, q=(1.0, 0.0, 0.0, 0.0), mass=1.0):
    return f"""
    [[body]]
    name = "{name}"
    shape = "cylinder"
    radius = {r}
    half_length = {hl}
    mass = {mass}
    position = {list(pos)}
    orientation = {list(q)}
    """


_S2 = math.sqrt(0.5)
_ALONG_X = (_S2, 0.0, _S2, 0.0)  # body z -> world x
_ALONG_Y = (_S2, _S2, 0.0, 0.0)  # body z -> world -y
_Q30 = (math.cos(math.pi / 12), 0.0, 0.0, math.sin(math.pi / 12))  # 30 degrees about z


@pytest.mark.parametrize("bodies,tol", [
    ([_can("a", .1, .1, (0, 0, .1)), _can("b", .1, .1, (0, 0, .3)), _can("c", .1, .1, (0, 0, .5))], 1e-9),
    ([_can("a", .1, .1, (0, 0, .1)), _can("b", .1, .1, (0.053, 0.017, .3))], 1e-9),
    ([_can("a", .1, .1, (0, 0, .1)), _can("b", .12, .1, (0.071, -0.013, .3), _Q30)], 1e-9),
    ([_can("a", .2, .1, (0, 0, .1)), _can("b", .05, .1, (0.1, 0.05, .3))], 1e-9),
    ([_can("a", .05, .1, (0, 0, .1)), _can("b", .2, .05, (0.01, 0.02, .25))], 1e-9),
    ([_can("a", .1, .1, (0, 0, .1)), _can("b", .1, .1, (0.05, 0.2, .1))], 1e-9),
    ([_can("a", .1, .3, (0, 0, .1), _ALONG_X), _can("b", .1, .3, (0.05, 0.2, .1), _ALONG_X)], 1e-9),
    # a side on a rim or a point contact: balanced only by the symmetric
    # support, which round-off tips (measured 3e-8 .. 5e-7 over 2 s)
    ([_can("a", .1, .1, (0, 0, .1)), _can("b", .05, .3, (0.01, 0.02, .25), _ALONG_X)], 1e-6),
    ([_can("a", .2, .1, (0, 0, .1)), _can("b", .05, .1, (0.01, 0.02, .25), _ALONG_X)], 1e-6),
    ([_can("a", .1, .3, (0, 0, .1), _ALONG_X), _can("b", .1, .3, (0, 0, .3), _ALONG_Y)], 1e-6),
], ids=["stack_of_3", "offset", "offset_wider_turned", "small_on_big", "big_on_small", "side_by_side",
        "logs_side_by_side", "log_across_a_can", "short_log_on_a_can", "logs_crossed"])
def test_cylinders_rest_on_cylinders(tmp_path, bodies, tol):
    """Cans and logs at rest on each other and on the ground for 2 s: every
    support must be where the bodies truly touch, or they tip.  The offset
    stacks rest on the rims' crossings; the wider turned can offset near
    its support's edge needs the direct start's active set (clipped alone,
    the start left it turning at 5e-5 rad/s, and its quaternion moved 8e-5)."""
    res = _cyl_run(tmp_path, "".join(bodies), _GROUND)
    tr = res.trace
    assert np.abs(tr.pos[-1] - tr.pos[0]).max() <= tol
    assert np.abs(tr.quat[-1] - tr.quat[0]).max() <= tol
    assert res.metrics["max_penetration"] <= 1e-9
    assert res.metrics["energy_gain"] <= 1e-9


def test_can_dropped_flat_on_a_can_bounces_by_restitution(tmp_path):
    """A can dropped 0.2 m flat onto a can 1e6 times heavier standing on the
    ground (e = 0.5) rises back to e^2 of the drop (to the mass ratio), with
    no spin and no sideways motion.  (Onto an equal can the impact is a
    chain of pairwise events -- can on can, lower can on the ground -- and
    the upper can keeps 5 % of its energy: a Newton's-cradle outcome, not a
    rigid support's.)"""
    bodies = _can("a", .1, .1, (0, 0, .1), mass=1e6) + _can("b", .1, .1, (0, 0, .5))
    res = _cyl_run(tmp_path, bodies, _GROUND, duration=0.4, effects=("gravity", "contact", "restitution"))
    tr = res.trace
    vz, z = tr.vel[:, 1, 2], tr.pos[:, 1, 2]
    after = np.flatnonzero(vz > 0.0)
    assert after.size
    i = int(after[0])
    e_after = 0.5 * vz[i] ** 2 + 9.81 * (z[i] - 0.3)
    assert e_after == pytest.approx(0.25 * 9.81 * 0.2, rel=1e-5)
    assert np.abs(tr.angvel).max() <= 1e-9
    assert np.abs(tr.pos[:, :, :2]).max() <= 1e-12
    assert res.metrics["max_penetration"] <= 1e-9


@pytest.mark.parametrize("slide", [0.0, 1e-9, -1e-7, 8e-7, -1e-5, 1e-3, -0.02])
def test_cylinder_cylinder_equal_logs_side_by_side(slide):
    """Two logs of one length lying side by side, overlapping 1e-9 m, one
    slid along the axes: the line contact is held by exactly its two ends,
    each with the pair's normal and depth, spanning the overlap of the two
    lengths.  With the ends coplanar to round-off, the longer log's rim
    end lies just past the shorter one's cap with a normal along the axes,
    and its rim crosses the other's radius 7e-6 m round from the contact
    line with a normal turned by 1.4e-4 rad; either, kept in place of the
    true end, sank the top log of a pile or turned its friction."""
    R = quat_to_matrix(np.array([[math.sqrt(0.5), -math.sqrt(0.5), 0.0, 0.0]]))  # axes along y
    hl, r = np.array([0.15]), np.array([0.05])
    k, n, p, g, fid = cylinder_cylinder(np.zeros((1, 3)), R, hl, r, np.array([[0.1 - 1e-9, slide, 0.0]]), R, hl, r,
                                        np.array([0.01]))
    assert k.size == 2
    assert np.allclose(n, [1.0, 0.0, 0.0], rtol=0, atol=1e-12)
    assert np.allclose(g, -1e-9, rtol=0, atol=1e-15)
    assert np.allclose(p[:, [0, 2]], [0.05, 0.0], rtol=0, atol=1e-9)
    assert sorted(p[:, 1]) == pytest.approx([max(-0.15, slide - 0.15), min(0.15, slide + 0.15)], abs=1e-12)


LOG_PILE = Path(__file__).resolve().parents[1] / "scenarios" / "stacking" / "log_pile.toml"


@pytest.mark.parametrize("share,holds", [(1.02, True), (0.98, False)])
def test_log_pile_holds_exactly_from_the_friction_statics_needs(tmp_path, share, holds):
    """Three logs in a pile (stacking.log_pile): statics needs friction
    tan(th / 2) = 0.2742 between the logs (the log_pile model).  2 % above
    it the reference engine holds the top log within 1e-6 m for 1.5 s; 2 %
    below, the lower logs roll apart and the top one falls to the ground.
    (Measured: the threshold lies between 0.273 and 0.276; before the
    cylinder pair dropped points reaching round the other's edge, the pile
    held at 0.22.)"""
    from physbench.harness.references import get_model
    from physbench.harness.runner import run

    mu = 0.2741678 * share
    text = LOG_PILE.read_text().replace("friction = 0.32\nstatic_friction = 0.32",
                                        f"friction = {mu}\nstatic_friction = {mu}").replace(
        "duration = 3.0", "duration = 1.5")
    sc = scene_from(tmp_path, text)
    assert get_model("log_pile")(sc).holds == holds
    res = run(sc, "reference")
    assert res.status == "ok", res.message
    assert res.metrics["outcome_ok"] is True
    assert res.metrics["max_penetration"] <= 1e-4
    assert res.metrics["energy_gain"] <= 1e-6
    if holds:
        assert res.metrics["top_drop"] <= 1e-6
        assert res.metrics["stack_drift"] <= 1e-4
    else:
        assert res.metrics["top_drop"] >= 0.5 * 0.0860174


def test_direct_start_clips_what_its_last_active_set_pass_pulls(tmp_path, monkeypatch):
    """The direct start's active set lets rows that pull go and solves
    again, ACTIVE_SET_PASSES times; rows still pulling after the last pass
    are clipped.  With a single pass the turned can offset near its
    support's edge pulls on the first one, which the active set once met by
    letting those rows go without solving again (a shape mismatch that
    stopped the run: found at 200 iterations on stacking.log_pile)."""
    from physbench.engine import solver

    monkeypatch.setattr(solver, "ACTIVE_SET_PASSES", 1)
    pulled = []
    orig = solver.dense_direct_solve

    def spy(*args):
        lam, ok, pull = orig(*args)
        pulled.append(bool(pull))
        return lam, ok, pull

    monkeypatch.setattr(solver, "dense_direct_solve", spy)
    monkeypatch.setattr(solver, "PHASE_BY_PHASE", True)  # the path the spy can see
    res = _cyl_run(tmp_path, _can("a", .1, .1, (0, 0, .1)) + _can("b", .12, .1, (0.071, -0.013, .3), _Q30),
                   _GROUND, duration=0.25)
    assert any(pulled)
    # one pass, clipped, is the weaker start (measured 1.6e-5 m here; 1e-9
    # with the default passes), not a broken one
    assert res.metrics["max_penetration"] <= 1e-4


def test_driver_families_follow_the_scene():
    """collide.families: the families of the shapes present -- every
    body-body family between two of them (a shape with itself too), each
    against a plane and a static box -- and no other."""
    from physbench.engine.collision.collide import (F_BB, F_BY, F_PB, F_PS, F_PY, F_SB, F_SS, F_SY, F_XB, F_XS,
                                                    F_XY, F_YY, N_FAMILIES, families)
    from physbench.engine.model import BOX, CYLINDER, SPHERE

    def on(fams):
        return {f for f in range(N_FAMILIES) if fams[f] is True}

    assert all(f is None or f is True for f in families([SPHERE, SPHERE]))
    assert on(families([SPHERE, SPHERE])) == on(families([SPHERE])) == {F_SS, F_PS, F_XS}
    assert on(families([SPHERE, BOX])) == {F_SS, F_SB, F_BB, F_PS, F_PB, F_XS, F_XB}
    assert on(families([CYLINDER, BOX, SPHERE])) == {F_SS, F_SB, F_BB, F_SY, F_BY, F_YY, F_PS, F_PB, F_PY, F_XS,
                                                      F_XB, F_XY}


def test_driver_type_is_the_same_for_every_family_set():
    """The narrow phase's buffers, as the driver and the fused steps take
    them (the Collider's Pack), have one numba type whatever shapes a scene
    has: the families' functions sit behind one first-class function type
    (collide.family_table), so the driver and each fused step compile once,
    not once per set of shapes (issue 42); a scene's families are still
    only its own (each family's function compiled only where present)."""
    from itertools import combinations
    from types import SimpleNamespace

    from numba import typeof

    from physbench.engine.collision.collide import N_FAMILIES, _missing, families, family_table
    from physbench.engine.collision.dispatch import Collider
    from physbench.engine.model import BOX, CAPSULE, CYLINDER, SPHERE

    def model(shapes):
        n = len(shapes)
        z = np.zeros(0, np.int64)
        return SimpleNamespace(
            n=n, shape=np.array(shapes, np.int64), radius=np.full(n, 0.1), half_extents=np.full((n, 3), 0.1),
            half_length=np.zeros(n), body_material=np.zeros(n, np.int64), plane_normal=np.zeros((0, 3)),
            plane_offset=np.zeros(0), plane_static=z, sbox_pos=np.zeros((0, 3)), sbox_R=np.zeros((0, 3, 3)),
            sbox_half=np.zeros((0, 3)), sbox_static=z, static_material=z, pair_e=np.zeros((1, 1)),
            pair_mus=np.zeros((1, 1)), pair_muk=np.zeros((1, 1)), pair_mur=np.zeros((1, 1)))

    shapes = (SPHERE, BOX, CAPSULE, CYLINDER)
    mixes = [list(c) for k in range(1, 5) for c in combinations(shapes, k)]
    assert len({families(m) for m in mixes}) == len(mixes)  # 15 sets of families ...
    assert len({typeof(Collider(model(m)).packed()) for m in mixes}) == 1  # ... one type
    table = family_table(families([SPHERE, SPHERE]))
    assert len(table) == N_FAMILIES
    assert sum(f.py_func is not _missing for f in table) == 3  # sphere-sphere, -plane, -static box


def test_driver_compiles_only_the_scenes_families(tmp_path):
    """A two-sphere scene's narrow phase compiles the kernels of the
    sphere's families (sphere-sphere, -plane, -box) and no other (issue
    42: a two-sphere scene must not compile box-cylinder); a pair of a family the driver was not compiled for
    raises instead of giving no contact.  A fresh process on an empty
    compiled-kernel cache (numba's ``numba:compile`` events: only
    compiles, never cache hits)."""
    code = textwrap.dedent("""
        import numpy as np
        from numba.core import event
        with event.install_recorder("numba:compile") as rec:
            from physbench.engine.collision import dispatch
            from physbench.engine.collision.collide import families
            dispatch.warm_up(families([0, 0]))
        print(sorted({e.data["dispatcher"].py_func.__qualname__ for _, e in rec.buffer if e.is_start}))
        """)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr
    names = out.stdout.strip()
    for own in ("_sphere_sphere_kernel", "_sphere_plane_kernel", "_sphere_box_kernel"):
        assert f"'{own}'" in names, own
    for other in ("_box_box_kernel", "_sphere_capsule_kernel", "_capsule_box_kernel",
                  "_capsule_capsule_kernel", "_sphere_cylinder_kernel", "_box_cylinder_kernel",
                  "_capsule_cylinder_kernel", "_cylinder_cylinder_kernel", "_box_plane_kernel",
                  "_capsule_plane_kernel", "_cylinder_plane_kernel"):
        assert f"'{other}'" not in names, other


def test_a_pair_of_a_family_not_compiled_raises():
    """The driver compiled for spheres meets a sphere-capsule pair: it
    raises (never a silent lack of contact)."""
    from physbench.engine.collision.collide import families
    from physbench.engine.collision.dispatch import Collider
    from physbench.engine.model import CAPSULE, SPHERE
    from physbench.engine.pack import KeptPack
    from types import SimpleNamespace

    n = 2
    z = np.zeros(0, np.int64)
    model = SimpleNamespace(
        n=n, shape=np.array([SPHERE, CAPSULE]), radius=np.full(n, 0.1), half_extents=np.full((n, 3), 0.1),
        half_length=np.zeros(n), body_material=np.zeros(n, np.int64), plane_normal=np.zeros((0, 3)),
        plane_offset=np.zeros(0), plane_static=z, sbox_pos=np.zeros((0, 3)), sbox_R=np.zeros((0, 3, 3)),
        sbox_half=np.zeros((0, 3)), sbox_static=z, static_material=z, pair_e=np.zeros((1, 1)),
        pair_mus=np.zeros((1, 1)), pair_muk=np.zeros((1, 1)), pair_mur=np.zeros((1, 1)))
    col = Collider(model)
    col.fams = families([SPHERE, SPHERE])
    col._kept = KeptPack()
    X = np.array([[0.0, 0.0, 0.0], [0.15, 0.0, 0.0]])
    with pytest.raises(RuntimeError, match="not compiled for"):
        col.run(X, np.tile(np.eye(3), (n, 1, 1)), np.array([0]), np.array([1]), (z, z), (z, z), margin=0.1,
                sweep=np.zeros(n))
