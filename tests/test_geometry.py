"""physbench.contract.geometry: overlap depths against hand-computed values.

Scenes are built the way the harness builds them (spec dict -> validate_raw ->
compile_scene) and traces are filled by hand.  Every expected value below is
derived in the comment next to it; the random-pose tests compare the
support-function search with an independent brute-force minimisation over
directions (a property of the method, not a snapshot of its output).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from physbench.contract import geometry as geo
from physbench.harness.runner import Trace
from physbench.contract.scene import compile_scene
from physbench.contract.spec import validate_raw

S2 = math.sqrt(2.0)


# ---- helpers -----------------------------------------------------------------

def make_scene(bodies, statics=(), effects=("contact",)):
    raw = {
        # the poses come from the traces: the scene's own start may overlap
        "scenario": {"family": "test", "title": "geometry", "duration": 1.0, "dt": 0.01,
                     "effects": list(effects), "max_initial_overlap": 1e6},
        "body": [dict(b) for b in bodies],
        "static": [dict(s) for s in statics],
    }
    for b in raw["body"]:
        b.setdefault("mass", 1.0)
    return compile_scene(validate_raw(raw, "<test>"))


def make_trace(pos, quat=None):
    """Trace from positions (F, n, 3) and wxyz quaternions (F, n, 4) (identity
    when omitted)."""
    pos = np.asarray(pos, float)
    F, n = pos.shape[:2]
    if quat is None:
        quat = np.zeros((F, n, 4))
        quat[..., 0] = 1.0
    quat = np.broadcast_to(np.asarray(quat, float), (F, n, 4)).copy()
    z = np.zeros_like(pos)
    return Trace(np.arange(F) * 0.01, pos, quat, z, z.copy(), F)


def qaxis(axis, deg):
    """wxyz quaternion of a rotation by ``deg`` degrees about ``axis``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    h = math.radians(deg) / 2.0
    return [math.cos(h), *(math.sin(h) * a)]


DIMS = {
    "sphere": {"radius": 0.1},
    "capsule": {"radius": 0.05, "half_length": 0.15},
    "box": {"half_extents": [0.1, 0.2, 0.05]},
    "cylinder": {"radius": 0.08, "half_length": 0.12},
}
# half-size along world x of each shape at the identity orientation
X_EXTENT = {"sphere": 0.1, "capsule": 0.05, "box": 0.1, "cylinder": 0.08}


def body(name, shape, **kw):
    return {"name": name, "shape": shape, **DIMS[shape], **kw}


def depth_of(scene, pos, quat=None):
    """(F, P) depths and the column names."""
    m = geo.measure_penetration(scene, make_trace(pos, quat))
    return m.dense(), m.pairs


# ---- spheres and planes ----------------------------------------------------------

def test_two_spheres_overlap_by_known_amount():
    sc = make_scene([body("a", "sphere", radius=0.1), body("b", "sphere", radius=0.2)])
    # centres 0.25 apart, radii 0.1 + 0.2 = 0.3 -> overlap 0.05; then 0.31 apart -> 0
    d, pairs = depth_of(sc, [[[0, 0, 0], [0.25, 0, 0]], [[0, 0, 0], [0, 0.31, 0]]])
    assert pairs == [(0, "body", 1)]
    assert d[:, 0] == pytest.approx([0.05, 0.0], abs=1e-15)


def test_sphere_resting_on_plane():
    sc = make_scene([body("s", "sphere", radius=0.1)], [{"shape": "plane", "normal": [0, 0, 1]}])
    # centre at z = 0.09 -> the lowest point is 0.01 below z = 0; at 0.1 it touches
    d, _ = depth_of(sc, [[[0.3, -0.2, 0.09]], [[0, 0, 0.1]], [[0, 0, 0.5]]])
    assert d[:, 0] == pytest.approx([0.01, 0.0, 0.0], abs=1e-15)


def test_plane_with_offset():
    # plane z = 1 (normal (0,0,1), offset 1): a sphere centred at z = 1.05, r 0.1 -> 0.05
    sc = make_scene([body("s", "sphere", radius=0.1)], [{"shape": "plane", "normal": [0, 0, 2], "offset": 1.0}])
    d, _ = depth_of(sc, [[[0, 0, 1.05]]])
    assert d[0, 0] == pytest.approx(0.05, abs=1e-15)


def test_box_corner_below_tilted_plane():
    # plane through the origin with normal (3, 0, 4)/5; axis-aligned box with
    # half extents (0.1, 0.2, 0.3) centred at (0, 0, 0.3).  The corner furthest
    # along -n is (-0.1, +-0.2, 0): n.x = (3 (-0.1) + 4 (0)) / 5 = -0.06, so the
    # corner is 0.06 below the plane.
    sc = make_scene([body("b", "box", half_extents=[0.1, 0.2, 0.3])], [{"shape": "plane", "normal": [3, 0, 4]}])
    d, _ = depth_of(sc, [[[0, 0, 0.3]], [[0, 0, 0.37]]])
    # lifted by 0.07 along z the corner is at n.x = -0.06 + 4 (0.07) / 5 = -0.004
    assert d[:, 0] == pytest.approx([0.06, 0.004], abs=1e-15)


def test_box_on_edge_on_plane():
    # cube of half side 0.1 turned 45 degrees about y stands on an edge: the
    # edge is 0.1 sqrt(2) below the centre, so a centre at z = 0.14 is
    # 0.1 sqrt(2) - 0.14 = 0.0014214 deep.
    sc = make_scene([body("b", "box", half_extents=[0.1, 0.1, 0.1])], [{"shape": "plane", "normal": [0, 0, 1]}])
    d, _ = depth_of(sc, [[[0, 0, 0.14]]], [[qaxis([0, 1, 0], 45)]])
    assert d[0, 0] == pytest.approx(0.1 * S2 - 0.14, abs=1e-14)


def test_capsule_lying_on_plane():
    # capsule r 0.05, half length 0.2, axis turned from z to x (90 degrees
    # about y): lying flat its lowest points are r below the centre.
    sc = make_scene([body("c", "capsule", radius=0.05, half_length=0.2)], [{"shape": "plane", "normal": [0, 0, 1]}])
    lying = qaxis([0, 1, 0], 90)
    tilted = qaxis([0, 1, 0], 30)  # axis 30 degrees from vertical: lowest point h cos30 + r below
    d, _ = depth_of(sc, [[[0, 0, 0.04]], [[0, 0, 0.2]]], [[lying], [tilted]])
    assert d[0, 0] == pytest.approx(0.01, abs=1e-15)
    assert d[1, 0] == pytest.approx(0.2 * math.cos(math.radians(30)) + 0.05 - 0.2, abs=1e-15)


def test_cylinder_on_plane_standing_and_tilted():
    sc = make_scene([body("y", "cylinder", radius=0.08, half_length=0.12)], [{"shape": "plane", "normal": [0, 0, 1]}])
    # standing: the cap is h = 0.12 below the centre.  Tilted 30 degrees the
    # lowest rim point is h cos30 + R sin30 below the centre.
    low = 0.12 * math.cos(math.radians(30)) + 0.08 * math.sin(math.radians(30))
    d, _ = depth_of(sc, [[[0, 0, 0.115]], [[0, 0, 0.1]]], [[qaxis([1, 0, 0], 0)], [qaxis([1, 0, 0], 30)]])
    assert d[:, 0] == pytest.approx([0.005, low - 0.1], abs=1e-15)


def test_slope_plane():
    # slope of 30 degrees through the origin: normal n = (sin30, 0, cos30),
    # downhill t = (cos30, 0, -sin30).  A sphere r 0.1 centred 1 m downhill and
    # 0.09 above the surface is 0.01 deep; a box (0.1, 0.1, 0.05) turned to sit
    # flat on the slope (30 degrees about +y maps z to n) centred 0.045 above it
    # is 0.005 deep.
    a = math.radians(30)
    n = np.array([math.sin(a), 0, math.cos(a)])
    t = np.array([math.cos(a), 0, -math.sin(a)])
    sc = make_scene([body("s", "sphere", radius=0.1), body("b", "box", half_extents=[0.1, 0.1, 0.05])],
                    [{"shape": "slope", "angle": 30.0}])
    pos = [[t + 0.09 * n, 2.0 * t + 0.045 * n]]
    quat = [[[1, 0, 0, 0], qaxis([0, 1, 0], 30)]]
    d, pairs = depth_of(sc, pos, quat)
    assert pairs == [(0, "static", 0), (1, "static", 0)]
    assert d[0] == pytest.approx([0.01, 0.005], abs=1e-14)


# ---- boxes ---------------------------------------------------------------------------

def test_rotated_box_vs_box_sat_depth():
    # A: cube of half side 0.5 at the origin.  B: the same cube turned 45
    # degrees about z, centred at x = 1.2: its corner reaches x = 1.2 - 0.5
    # sqrt(2) and enters A's face x = 0.5 by 0.5 + 0.5 sqrt(2) - 1.2 = 0.0071068.
    # The other axes overlap more (B's face normals: 0.5 sqrt(2) + 0.5 - 1.2 /
    # sqrt(2) = 0.3586; z: 1.0), so the SAT minimum is along x.
    sc = make_scene([body("a", "box", half_extents=[0.5, 0.5, 0.5]), body("b", "box", half_extents=[0.5, 0.5, 0.5])])
    quat = [[[1, 0, 0, 0], qaxis([0, 0, 1], 45)]] * 2
    d, _ = depth_of(sc, [[[0, 0, 0], [1.2, 0, 0]], [[0, 0, 0], [1.22, 0, 0]]], quat)
    assert d[0, 0] == pytest.approx(0.5 + 0.5 * S2 - 1.2, abs=1e-14)
    assert d[1, 0] == 0.0  # 1.22 > 0.5 + 0.5 sqrt(2): separated


def test_box_box_matches_the_cross_product_form():
    """The box-box kernel writes the edge axes e_i x b_k out instead of
    calling np.cross: the same depths bit for bit (random poses, parallel
    edges, non-finite poses give NaN), so penetration metrics are unchanged."""
    from physbench.contract.geometry.exact import _k_box_box
    from physbench.contract.geometry.placed import Placed
    from physbench.contract.geometry.vector import _norm

    def cross_form(A, B):
        C = np.einsum("nji,njk->nik", A.R, B.R)
        t = np.einsum("nj,nji->ni", B.c - A.c, A.R)
        eye = np.broadcast_to(np.eye(3), (A.n, 3, 3))
        bax = np.swapaxes(C, 1, 2)
        cross = np.cross(eye[:, :, None, :], bax[:, None, :, :]).reshape(A.n, 9, 3)
        axes = np.concatenate([eye, bax, cross], axis=1)
        nrm = _norm(axes)
        ok = nrm > 1e-12
        L = axes / np.where(ok, nrm, 1.0)[..., None]
        ra = np.einsum("nmi,ni->nm", np.abs(L), A.half_extents)
        rb = np.einsum("nmk,nk->nm", np.abs(L @ C), B.half_extents)
        ov = np.where(ok, ra + rb - np.abs(np.einsum("nmi,ni->nm", L, t)), np.inf)
        return ov.min(axis=1)

    rng = np.random.default_rng(3)
    n = 2000
    q = rng.normal(size=(2, n, 4))
    q[:, : n // 4] = [1.0, 0.0, 0.0, 0.0]  # aligned boxes: parallel edges
    q[1, n // 4: n // 2] = q[0, n // 4: n // 2]
    pos = rng.uniform(-1.0, 1.0, (2, n, 3))
    pos[1, 7], q[0, 8, 2], q[1, 9] = np.inf, np.nan, np.nan
    he = rng.uniform(0.05, 0.8, (2, n, 3))
    with np.errstate(invalid="ignore"):
        A, B = (Placed.from_pose("box", pos[k], q[k], half_extents=he[k]) for k in (0, 1))
        got, want = _k_box_box(A, B), cross_form(A, B)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.isnan(got[[7, 8, 9]]).all() and np.isfinite(np.delete(got, [7, 8, 9])).all()
    assert (got > 0).sum() > n // 10  # overlapping pairs are among them


def test_box_edge_on_box_face():
    # A axis-aligned cube (half 0.5); B the same cube turned 45 degrees about y
    # stands on A's top face on its lowest edge (parallel to y, 0.5 sqrt(2)
    # below its centre): centre at z = 0.5 + 0.5 sqrt(2) - 0.003 -> 0.003 deep.
    sc = make_scene([body("a", "box", half_extents=[0.5, 0.5, 0.5]), body("b", "box", half_extents=[0.5, 0.5, 0.5])])
    d, _ = depth_of(sc, [[[0, 0, 0], [0.1, 0.2, 0.5 + 0.5 * S2 - 0.003]]], [[[1, 0, 0, 0], qaxis([0, 1, 0], 45)]])
    assert d[0, 0] == pytest.approx(0.003, abs=1e-13)


@pytest.mark.parametrize("static", [False, True])
def test_sphere_inside_and_outside_a_box(static):
    # box half extents (0.2, 0.3, 0.4) at the origin, identity orientation.
    #  (0.22, 0, 0), r 0.05: 0.02 outside the x face -> 0.03 deep
    #  (0.15, 0.05, 0), r 0.05: inside, nearest face x at 0.05 -> r + 0.05 = 0.1
    #  (0.23, 0.34, 0), r 0.06: outside an edge, distance hypot(0.03, 0.04) = 0.05 -> 0.01
    #  (0.3, 0, 0), r 0.05: 0.1 outside -> 0
    he = [0.2, 0.3, 0.4]
    pts = [[0.22, 0, 0], [0.15, 0.05, 0], [0.23, 0.34, 0], [0.3, 0, 0]]
    radii = [0.05, 0.05, 0.06, 0.05]
    want = [0.03, 0.1, 0.01, 0.0]
    for p, r, w in zip(pts, radii, want):
        if static:
            sc = make_scene([body("s", "sphere", radius=r)],
                            [{"shape": "box", "half_extents": he, "position": [0, 0, 0]}])
            d, pairs = depth_of(sc, [[p]])
            got = d[0, 0] if pairs else 0.0
        else:
            sc = make_scene([body("b", "box", half_extents=he), body("s", "sphere", radius=r)])
            d, pairs = depth_of(sc, [[[0, 0, 0], p]])
            got = d[0, 0] if pairs else 0.0
        assert got == pytest.approx(w, abs=1e-14), (p, r)


def test_box_in_rotated_static_box():
    # static box half (1, 1, 0.1) turned 90 degrees about x (so its thin axis
    # is world y) at y = 0; a sphere r 0.1 centred at y = 0.15 overlaps the
    # face y = 0.1 by 0.05.
    sc = make_scene([body("s", "sphere", radius=0.1)],
                    [{"shape": "box", "half_extents": [1, 1, 0.1], "position": [0, 0, 0],
                      "orientation": qaxis([1, 0, 0], 90)}])
    d, _ = depth_of(sc, [[[0.3, 0.15, -0.2]]])
    assert d[0, 0] == pytest.approx(0.05, abs=1e-14)


# ---- capsules ------------------------------------------------------------------------

def test_capsule_capsule_crossing():
    # A along x, B along y (90 degrees about x turns z to -y) 0.08 above it:
    # the segments cross at distance 0.08, radii 0.05 + 0.05 -> 0.02 deep.
    sc = make_scene([body("a", "capsule", radius=0.05, half_length=0.2),
                     body("b", "capsule", radius=0.05, half_length=0.2)])
    quat = [[qaxis([0, 1, 0], 90), qaxis([1, 0, 0], 90)]]
    d, _ = depth_of(sc, [[[0, 0, 0], [0.05, -0.1, 0.08]]], quat)
    assert d[0, 0] == pytest.approx(0.02, abs=1e-15)


def test_capsule_capsule_parallel_and_end_to_end():
    sc = make_scene([body("a", "capsule", radius=0.05, half_length=0.2),
                     body("b", "capsule", radius=0.05, half_length=0.2)])
    along_x = qaxis([0, 1, 0], 90)
    # parallel, side by side 0.09 apart with overlapping spans -> 0.01
    # end to end: ends at x = 0.2 and x = 0.49 - 0.2 = 0.29 -> distance 0.09 -> 0.01
    # end to end 0.11 apart -> 0
    pos = [[[0, 0, 0], [0.3, 0.09, 0]], [[0, 0, 0], [0.49, 0, 0]], [[0, 0, 0], [0.51, 0, 0]]]
    d, _ = depth_of(sc, pos, [[along_x, along_x]] * 3)
    assert d[:, 0] == pytest.approx([0.01, 0.01, 0.0], abs=1e-15)


def test_capsule_box():
    # box half (0.5, 0.5, 0.1) at the origin; capsule r 0.05, half length 0.3:
    #  lying along x on the top face at z = 0.14: 0.1 + 0.05 - 0.14 = 0.01 deep
    #  standing on the top face, end cap centre at z = 0.1 + 0.05 - 0.02 -> 0.02
    #  lying 0.01 above the top face -> 0
    #  core segment through the box (centre at z = 0, along x, length 0.6 < 1):
    #  the shortest way out is up or down: 0.1 + 0.05 = 0.15
    sc = make_scene([body("c", "capsule", radius=0.05, half_length=0.3)],
                    [{"shape": "box", "half_extents": [0.5, 0.5, 0.1], "position": [0, 0, 0]}])
    along_x = qaxis([0, 1, 0], 90)
    pos = [[[0.1, 0, 0.14]], [[0, 0, 0.1 + 0.05 + 0.3 - 0.02]], [[0, 0, 0.16]], [[0, 0, 0]]]
    quat = [[along_x], [[1, 0, 0, 0]], [along_x], [along_x]]
    d, _ = depth_of(sc, pos, quat)
    assert d[:, 0] == pytest.approx([0.01, 0.02, 0.0, 0.15], abs=1e-12)


def test_capsule_tilted_over_box_edge():
    # box half (0.5, 0.5, 0.5); a capsule r 0.1 lying along y just beyond the
    # edge x = 0.5, z = 0.5, its axis at (0.5 + 0.06, y, 0.5 + 0.06): distance to
    # the edge line 0.06 sqrt(2) -> depth 0.1 - 0.06 sqrt(2) = 0.015147
    sc = make_scene([body("b", "box", half_extents=[0.5, 0.5, 0.5]),
                     body("c", "capsule", radius=0.1, half_length=0.3)])
    d, _ = depth_of(sc, [[[0, 0, 0], [0.56, 0.1, 0.56]]], [[[1, 0, 0, 0], qaxis([1, 0, 0], 90)]])
    assert d[0, 0] == pytest.approx(0.1 - 0.06 * S2, abs=1e-12)


# ---- cylinders -------------------------------------------------------------------------

def test_cylinders_stacked_and_crossed():
    sc = make_scene([body("a", "cylinder", radius=0.08, half_length=0.12),
                     body("b", "cylinder", radius=0.05, half_length=0.1)])
    ident = [1, 0, 0, 0]
    # coaxial stack: caps 0.12 + 0.1 from the centres; centres 0.217 apart -> 0.003
    # lying crossed (A along x, B along y), centres 0.08 + 0.05 - 0.004 apart
    # vertically: side on side -> 0.004
    # coaxial but 0.001 apart -> 0
    pos = [[[0, 0, 0], [0.01, 0.02, 0.217]], [[0, 0, 0], [0.03, -0.02, 0.126]], [[0, 0, 0], [0, 0, 0.221]]]
    quat = [[ident, ident], [qaxis([0, 1, 0], 90), qaxis([1, 0, 0], 90)], [ident, ident]]
    d, _ = depth_of(sc, pos, quat)
    assert d[:, 0] == pytest.approx([0.003, 0.004, 0.0], abs=1e-12)


def test_cylinder_on_static_box_lying_standing_tilted():
    # table: static box half (1, 1, 0.1), top face z = 0.1.  Cylinder R 0.08, h 0.12.
    #  lying (axis along x), centre z = 0.1 + 0.08 - 0.002 -> 0.002
    #  standing, centre z = 0.1 + 0.12 - 0.001 -> 0.001
    #  tilted 30 degrees about x: lowest rim point h cos30 + R sin30 below the centre
    low = 0.12 * math.cos(math.radians(30)) + 0.08 * math.sin(math.radians(30))
    sc = make_scene([body("y", "cylinder", radius=0.08, half_length=0.12)],
                    [{"shape": "box", "half_extents": [1, 1, 0.1], "position": [0, 0, 0]}])
    pos = [[[0.2, 0.1, 0.178]], [[0, 0, 0.219]], [[0, 0, 0.1 + low - 0.0025]], [[0, 0, 0.1 + low + 0.0001]]]
    quat = [[qaxis([0, 1, 0], 90)], [[1, 0, 0, 0]], [qaxis([1, 0, 0], 30)], [qaxis([1, 0, 0], 30)]]
    d, _ = depth_of(sc, pos, quat)
    assert d[:, 0] == pytest.approx([0.002, 0.001, 0.0025, 0.0], abs=1e-12)


def test_box_vertex_just_off_cylinder_rim_is_separated():
    # Cylinder R 0.1, h 0.1 standing at the origin; its rim point (0.1, 0, 0.1)
    # is extreme along every n = (sin b, 0, cos b), 0 < b < 90 degrees; take
    # b = 30.  A cube (half 0.05) turned so that its body diagonal (1, 1, 1)
    # points along n has its vertex -(0.05, 0.05, 0.05) extreme along -n.
    # With that vertex at rim + g n, the plane n.x = n.rim + g/2 separates
    # them: depth 0 (a vertex grazing a rim, no face or cap normal along n).
    # The bounding spheres (0.1414 and 0.0866) do meet: |rim + 0.0866 n| =
    # 0.2262 < 0.228, so the pair reaches the narrow phase.
    b = math.radians(30)
    n = np.array([math.sin(b), 0.0, math.cos(b)])
    v = np.ones(3) / math.sqrt(3.0)
    q = qaxis(np.cross(v, n), math.degrees(math.acos(v @ n)))
    sc = make_scene([body("y", "cylinder", radius=0.1, half_length=0.1),
                     body("b", "box", half_extents=[0.05, 0.05, 0.05])])
    rim = np.array([0.1, 0.0, 0.1])
    for gap in (1e-6, 1e-4):
        centre = rim + gap * n + 0.05 * math.sqrt(3.0) * n
        d, pairs = depth_of(sc, [[[0, 0, 0], centre]], [[[1, 0, 0, 0], q]])
        assert pairs == [(0, "body", 1)]
        assert d[0, 0] == 0.0, gap


def test_sphere_against_cylinder_side_cap_and_inside():
    # cylinder R 0.1, h 0.2 standing at the origin; sphere r 0.05:
    #  beside it at x = 0.14 -> 0.01;  above the cap at z = 0.24 -> 0.01;
    #  off the rim at (0.13, 0, 0.24): distance hypot(0.03, 0.04) = 0.05 -> 0
    #  inside at (0.07, 0, 0): nearest surface the side, 0.03 away -> 0.05 + 0.03
    sc = make_scene([body("y", "cylinder", radius=0.1, half_length=0.2), body("s", "sphere", radius=0.05)])
    pts = [[0.14, 0, 0], [0, 0.02, 0.24], [0.13, 0, 0.24], [0.07, 0, 0]]
    d, pairs = depth_of(sc, [[[0, 0, 0], p] for p in pts])
    assert pairs == [(0, "body", 1)]
    assert d[:, 0] == pytest.approx([0.01, 0.01, 0.0, 0.08], abs=1e-14)


def test_capsule_against_cylinder():
    # cylinder R 0.1, h 0.2 standing; capsule r 0.05, half length 0.1 lying
    # along y across the top at z = 0.2 + 0.05 - 0.006 -> 0.006 deep; standing
    # beside it, axis 0.14 from the cylinder's axis -> 0.01 deep; core through
    # the cylinder along x at z = 0.15 (segment inside: |x| <= 0.1 = R): the
    # shortest way out is up through the cap: 0.2 - 0.15 + 0.05 = 0.1.
    sc = make_scene([body("y", "cylinder", radius=0.1, half_length=0.2),
                     body("c", "capsule", radius=0.05, half_length=0.1)])
    pos = [[[0, 0, 0], [0.02, 0, 0.244]], [[0, 0, 0], [0, 0.14, 0.05]], [[0, 0, 0], [0, 0, 0.15]]]
    quat = [[[1, 0, 0, 0], qaxis([1, 0, 0], 90)], [[1, 0, 0, 0], [1, 0, 0, 0]],
            [[1, 0, 0, 0], qaxis([0, 1, 0], 90)]]
    d, _ = depth_of(sc, pos, quat)
    assert d[:, 0] == pytest.approx([0.006, 0.01, 0.1], abs=1e-12)


# ---- every pair: the separated side is 0, the overlapping side is exact --------------

PAIRS = [(a, b) for i, a in enumerate(geo.SHAPES) for b in geo.SHAPES[i:]]


@pytest.mark.parametrize("ka,kb", PAIRS)
def test_every_pair_gap_and_overlap_along_x(ka, kb):
    # At the identity orientation every shape's x extent is X_EXTENT, and two
    # shapes centred on the x axis (round sides or flat faces facing each
    # other) touch at distance X_EXTENT[a] + X_EXTENT[b]; 1e-4 closer is a
    # 1e-4 overlap whose shortest way out is back along x; 1e-9 further is 0.
    sc = make_scene([body("a", ka), body("b", kb)])
    reach = X_EXTENT[ka] + X_EXTENT[kb]
    pos = [[[0, 0, 0], [reach + 1e-4, 0, 0]], [[0, 0, 0], [reach - 1e-4, 0, 0]],
           [[0, 0, 0], [reach + 1e-9, 0, 0]]]
    d, pairs = depth_of(sc, pos)
    assert pairs == [(0, "body", 1)]
    assert d[:, 0] == pytest.approx([0.0, 1e-4, 0.0], abs=1e-13)


@pytest.mark.parametrize("kind", geo.SHAPES)
def test_every_shape_against_static_box(kind):
    # static slab half (1, 1, 0.1), top at z = 0.1; each shape upright with
    # its lowest point (z half-size below the centre) 0.002 into the slab.
    zhalf = {"sphere": 0.1, "capsule": 0.15 + 0.05, "box": 0.05, "cylinder": 0.12}[kind]
    sc = make_scene([body("a", kind)], [{"shape": "box", "half_extents": [1, 1, 0.1], "position": [0, 0, 0]}])
    d, _ = depth_of(sc, [[[0.3, -0.2, 0.1 + zhalf - 0.002]], [[0.3, -0.2, 0.1 + zhalf + 1e-6]]])
    assert d[:, 0] == pytest.approx([0.002, 0.0], abs=1e-13)


# ---- support-function search against brute force ------------------------------------

def _fib_dirs(n):
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    ph = math.pi * (1 + 5 ** 0.5) * k
    return np.stack([r * np.cos(ph), r * np.sin(ph), z], axis=1)


def _nelder_mead_batch(f, x0, step, xatol, fatol, maxiter):
    """Nelder-Mead as scipy.optimize.minimize(method="Nelder-Mead") does it
    (adaptive=False: reflection 1, expansion 2, contraction 1/2, shrink
    1/2; the same order of tests and the same stopping rule: every vertex
    within xatol of the best and every value within fatol of its value, or
    ``maxiter`` iterations counted from 1), for many independent problems in
    lockstep: x0 (..., k) holds one start per problem, the initial simplex
    is x0 and x0 + step along each axis, and f maps points (..., k) to
    values (...) -- so each step evaluates f once for all problems at once
    instead of once per problem.  A problem that has stopped is left as it
    is.  Returns the best value of each problem (...)."""
    k = x0.shape[-1]
    sim = x0[..., None, :] + np.concatenate([np.zeros((1, k)), step * np.eye(k)])  # (..., k + 1, k)
    fsim = np.stack([f(sim[..., j, :]) for j in range(k + 1)], axis=-1)

    def sort(sim, fsim):
        i = np.argsort(fsim, axis=-1)
        return np.take_along_axis(sim, i[..., None], -2), np.take_along_axis(fsim, i, -1)

    sim, fsim = sort(sim, fsim)
    active = np.ones(fsim.shape[:-1], bool)
    for _ in range(1, maxiter):
        active &= ~((np.abs(sim[..., 1:, :] - sim[..., :1, :]).max(axis=(-2, -1)) <= xatol)
                    & (np.abs(fsim[..., :1] - fsim[..., 1:]).max(axis=-1) <= fatol))
        if not active.any():
            break
        xbar = sim[..., :-1, :].sum(axis=-2) / k
        worst, f_worst = sim[..., -1, :], fsim[..., -1]
        xr = 2.0 * xbar - worst
        fxr = f(xr)
        expand = fxr < fsim[..., 0]
        reflect = ~expand & (fxr < fsim[..., -2])
        outside = ~expand & ~reflect & (fxr < f_worst)  # contract outside, else inside
        x2 = np.where(expand[..., None], 3.0 * xbar - 2.0 * worst,
                      np.where(outside[..., None], 1.5 * xbar - 0.5 * worst, 0.5 * xbar + 0.5 * worst))
        f2 = f(x2)
        take2 = np.where(expand, f2 < fxr, np.where(outside, f2 <= fxr, f2 < f_worst)) & ~reflect
        shrink = active & ~expand & ~reflect & ~take2
        replace = active & ~shrink
        new_x = np.where(take2[..., None], x2, xr)
        new_f = np.where(take2, f2, fxr)
        sim[..., -1, :] = np.where(replace[..., None], new_x, worst)
        fsim[..., -1] = np.where(replace, new_f, f_worst)
        if shrink.any():
            shrunk = sim[..., :1, :] + 0.5 * (sim[..., 1:, :] - sim[..., :1, :])
            f_shrunk = np.stack([f(shrunk[..., j, :]) for j in range(k)], axis=-1)
            sim[..., 1:, :] = np.where(shrink[..., None, None], shrunk, sim[..., 1:, :])
            fsim[..., 1:] = np.where(shrink[..., None], f_shrunk, fsim[..., 1:])
        sim, fsim = sort(sim, fsim)
    return fsim[..., 0]


def _brute_min_phi(A, B, n_dirs=20000, starts=5):
    """min over unit n of phi, by a Fibonacci sphere and then Nelder-Mead (in
    angles about the start direction) from the best starts: an upper bound of
    the true minimum, found without any knowledge of the shapes' features.
    The Nelder-Mead runs of every pair and start go in lockstep
    (_nelder_mead_batch), phi evaluated for all of them at once."""
    D = _fib_dirs(n_dirs)
    d = B.c - A.c
    best = np.empty(A.n)
    n0 = np.empty((A.n, starts, 3))
    for e in range(A.n):
        v = geo.projection_overlap(A.take([e]), B.take([e]), d[e:e + 1], D[None])[0]
        best[e] = v.min()
        n0[e] = D[np.argsort(v)[:starts]]
    t1 = np.cross(n0, np.where(np.abs(n0[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(n0, t1)

    def f(x):  # (A.n, starts, 2) -> (A.n, starts)
        n = n0 + x[..., :1] * t1 + x[..., 1:] * t2
        return geo.projection_overlap(A, B, d, n / np.linalg.norm(n, axis=-1, keepdims=True))

    fun = _nelder_mead_batch(f, np.zeros((A.n, starts, 2)), step=0.02, xatol=1e-12, fatol=1e-15, maxiter=2000)
    return np.minimum(best, fun.min(axis=1))


def _random_placed(rng, kind, dims, centres):
    from scipy.spatial.transform import Rotation

    q = Rotation.random(len(centres), random_state=rng).as_quat()[:, [3, 0, 1, 2]]
    return geo.Placed.from_pose(kind, centres, q, dims.get("radius", 0.0), dims.get("half_length", 0.0),
                                dims.get("half_extents"))


@pytest.mark.parametrize("ka,da,kb,db", [
    ("box", {"half_extents": [0.1, 0.2, 0.05]}, "cylinder", {"radius": 0.08, "half_length": 0.12}),
    ("cylinder", {"radius": 0.08, "half_length": 0.12}, "cylinder", {"radius": 0.08, "half_length": 0.12}),
    ("cylinder", {"radius": 0.2, "half_length": 0.005}, "cylinder", {"radius": 0.01, "half_length": 0.25}),
    # short wide cylinders: about a third of random contacts are rim on rim
    ("cylinder", {"radius": 0.1, "half_length": 0.02}, "cylinder", {"radius": 0.1, "half_length": 0.02}),
    ("capsule", {"radius": 0.03, "half_length": 0.15}, "cylinder", {"radius": 0.08, "half_length": 0.12}),
    ("box", {"half_extents": [0.3, 0.004, 0.2]}, "cylinder", {"radius": 0.2, "half_length": 0.005}),
])
def test_search_matches_brute_force_near_contact(ka, da, kb, db):
    """Random poses moved along a random direction until the measured depth is
    0.04 (for the capsule, deeper than its radius: the core segment is inside
    the cylinder), 1e-3, 1e-6 or -1e-6 (separated): a dense brute-force
    minimisation over directions must find nothing lower, and the separated
    poses stay at 0."""
    rng = np.random.default_rng(1234)
    N = 6
    for target in (0.04, 1e-3, 1e-6, -1e-6):
        u = rng.normal(size=(N, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        A = _random_placed(rng, ka, da, np.zeros((N, 3)))
        qb = _random_placed(rng, kb, db, np.zeros((N, 3))).R
        lo, hi = np.zeros(N), np.full(N, 2.0)
        for _ in range(70):  # bisect the distance along u for signed gap = target
            mid = 0.5 * (lo + hi)
            B = geo.Placed(kb, mid[:, None] * u, qb, db.get("radius", 0.0), db.get("half_length", 0.0),
                           db.get("half_extents"))
            over = geo.signed_gap(A, B) > target
            lo, hi = np.where(over, mid, lo), np.where(over, hi, mid)
        B = geo.Placed(kb, hi[:, None] * u, qb, db.get("radius", 0.0), db.get("half_length", 0.0),
                       db.get("half_extents"))
        ours = geo.pair_depth(A, B)
        brute = np.maximum(0.0, _brute_min_phi(A, B))
        # The brute force is an upper bound of the true minimum, so finding
        # nothing lower than ours is the test; ours is one too (phi at unit
        # directions), so the two agree up to the brute force's convergence.
        assert np.all(ours <= brute + 1e-11), (target, ours - brute)
        assert np.all(ours >= brute - 1e-8), (target, ours - brute)
        if target < 0:
            assert np.all(ours == 0.0)


def test_capsule_core_through_a_coin_matches_brute_force():
    """A long thin capsule pushed through a coin (its core segment crosses the
    coin): the way out is often over the rim, with a normal perpendicular to
    the capsule's axis.  Brute force must find nothing lower."""
    rng = np.random.default_rng(99)
    N = 8
    C = _random_placed(rng, "capsule", {"radius": 0.01, "half_length": 0.3}, rng.normal(0, 0.03, (N, 3)))
    Y = _random_placed(rng, "cylinder", {"radius": 0.2, "half_length": 0.01}, np.zeros((N, 3)))
    ours = geo.pair_depth(C, Y)
    brute = np.maximum(0.0, _brute_min_phi(C, Y))
    assert np.all(ours > 0.01)  # deeper than the capsule's radius: the core is inside
    assert np.all(ours <= brute + 1e-11), ours - brute
    assert np.all(ours >= brute - 1e-8), ours - brute


def test_support_functions_match_sampled_shapes():
    """h(n) = max over the shape of n.(x - c): box corners, sphere and
    capsule end-sphere points, cylinder rims sampled finely (the sample max is
    <= h, and within the sampling error of it)."""
    rng = np.random.default_rng(7)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for kind, dims in DIMS.items():
        G = _random_placed(rng, "box" if kind == "sphere" else kind, dims, np.zeros((1, 3)))
        G.kind = kind  # a sphere with a rotation, so the sampled points can be turned alike
        h = geo._support(G, n[None])[0]
        if kind == "sphere":
            pts = 0.1 * _fib_dirs(4000)
        elif kind == "box":
            pts = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * dims["half_extents"]
        elif kind == "capsule":
            sph = dims["radius"] * _fib_dirs(4000)
            pts = np.concatenate([sph + [0, 0, dims["half_length"]], sph - [0, 0, dims["half_length"]]])
        else:
            ang = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
            ring = dims["radius"] * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
            pts = np.concatenate([ring + [0, 0, dims["half_length"]], ring - [0, 0, dims["half_length"]]])
        world = pts @ G.R[0].T
        sampled = (n @ world.T).max(axis=1)
        # sampling error: Fibonacci spacing ~0.056 rad on a 0.1 or 0.05 sphere
        # (r (1 - cos 0.028) < 4e-5), 4000 rim points (R (1 - cos(pi/4000)) < 3e-8)
        tol = {"sphere": 1e-4, "capsule": 1e-4, "box": 1e-15, "cylinder": 1e-7}[kind]
        assert np.all(sampled <= h + 1e-15), kind
        assert np.all(h - sampled <= tol), kind


# ---- the whole-scene matrix ------------------------------------------------------------

def test_matrix_shape_columns_and_culling():
    # three spheres r 0.1 on a plane, two statics (the plane and a far box):
    # columns are every body against the plane, body-box pairs that come
    # within reach (none), then body pairs within reach: only (0, 1).
    sc = make_scene([body("a", "sphere"), body("b", "sphere"), body("c", "sphere")],
                    [{"shape": "plane", "normal": [0, 0, 1]},
                     {"shape": "box", "half_extents": [0.1, 0.1, 0.1], "position": [10, 0, 0]}])
    F = 5
    pos = np.zeros((F, 3, 3))
    pos[:, 0] = [0, 0, 0.1]
    pos[:, 1, 0] = np.linspace(0.3, 0.15, F)  # approaches a: overlap 0.05 at the end
    pos[:, 1, 2] = 0.1
    pos[:, 2] = [5, 0, 0.095]  # 0.005 into the plane
    m = geo.measure_penetration(sc, make_trace(pos))
    d = m.dense()
    assert m.pairs == [(0, "static", 0), (1, "static", 0), (2, "static", 0), (0, "body", 1)]
    assert d.shape == (F, 4)
    assert d[:, 2] == pytest.approx(0.005, abs=1e-15)
    assert d[:, 3] == pytest.approx(np.maximum(0.0, 0.2 - np.linspace(0.3, 0.15, F)), abs=1e-15)
    assert np.array_equal(geo.penetration_depths(sc, make_trace(pos)), d)
    assert m.frame_max() == pytest.approx(np.nanmax(d, axis=1), abs=0)
    assert not m.unknown().any()


def test_no_pairs_gives_empty_matrix():
    sc = make_scene([body("a", "sphere"), body("b", "sphere")])
    d = geo.penetration_depths(sc, make_trace(np.array([[[0, 0, 0], [5, 0, 0]]] * 3)))
    assert d.shape == (3, 0)


def test_nan_for_a_pair_without_kernel(monkeypatch):
    # Without a box-box kernel the pair's depth is unknown wherever the
    # bounding spheres meet (NaN), and 0 where they provably do not.
    monkeypatch.delitem(geo.PAIR_KERNELS, ("box", "box"))
    sc = make_scene([body("a", "box", half_extents=[0.1, 0.1, 0.1]),
                     body("b", "box", half_extents=[0.1, 0.1, 0.1]),
                     body("s", "sphere", radius=0.1)])
    pos = [[[0, 0, 0], [0.15, 0, 0], [-0.15, 0, 0]], [[0, 0, 0], [3, 0, 0], [-0.15, 0, 0]]]
    m = geo.measure_penetration(sc, make_trace(pos))
    d = m.dense()
    cols = {p: k for k, p in enumerate(m.pairs)}
    assert np.isnan(d[0, cols[(0, "body", 1)]]) and d[1, cols[(0, "body", 1)]] == 0.0
    assert d[:, cols[(0, "body", 2)]] == pytest.approx([0.05, 0.05], abs=1e-15)  # sphere-box still known
    assert m.unknown().tolist() == [True, False]
    assert m.frame_max() == pytest.approx([0.05, 0.05], abs=1e-15)


def test_nan_for_non_finite_pose():
    sc = make_scene([body("a", "sphere"), body("b", "sphere")], [{"shape": "plane", "normal": [0, 0, 1]}])
    # frame 0: both spheres (r 0.1) 0.05 into the plane, 0.15 apart -> 0.05 each;
    # frame 1: b's position is NaN -> its columns are unknown, a's stays known
    pos = np.array([[[0, 0, 0.05], [0.15, 0, 0.05]], [[0, 0, 0.05], [np.nan, 0, 0.05]]])
    m = geo.measure_penetration(sc, make_trace(pos))
    d = m.dense()
    assert m.pairs == [(0, "static", 0), (1, "static", 0), (0, "body", 1)]
    assert d[0] == pytest.approx([0.05, 0.05, 0.05], abs=1e-15)
    assert d[1, 0] == pytest.approx(0.05) and np.isnan(d[1, 1]) and np.isnan(d[1, 2])
    assert m.unknown().tolist() == [False, True]


def test_large_scene_broad_phase_is_exact():
    """Above the all-pairs limit the broad phase uses KD-trees per frame with
    bodies bucketed by radius; every overlapping pair must still be found:
    compare with r_i + r_j - |x_i - x_j| over all pairs."""
    rng = np.random.default_rng(3)
    n, F = 240, 4
    radii = np.where(np.arange(n) < 8, 0.5, 0.05)  # a few large spheres among many small ones
    bodies = [{"name": f"s{i}", "shape": "sphere", "radius": float(radii[i])} for i in range(n)]
    sc = make_scene(bodies)
    pos = rng.uniform(0, 1.5, size=(F, n, 3))
    m = geo.measure_penetration(sc, make_trace(pos))
    i, j = np.triu_indices(n, 1)
    want = np.maximum(0.0, radii[i] + radii[j] - np.linalg.norm(pos[:, i] - pos[:, j], axis=-1))  # (F, pairs)
    got = np.zeros_like(want)
    col_of = {(a, b): k for k, (a, _, b) in enumerate(m.pairs)}
    d = m.dense()
    idx = np.array([col_of.get((a, b), -1) for a, b in zip(i, j)])
    have = idx >= 0
    got[:, have] = d[:, idx[have]]
    assert n * (n - 1) // 2 > geo._ALL_PAIRS_MAX
    assert np.abs(got - want).max() < 1e-14
    assert (want > 0).sum() > 100


def test_public_pair_tables():
    sc = make_scene([body("a", "box", half_extents=[0.5, 0.5, 0.5]), body("b", "capsule", radius=0.1, half_length=0.3)],
                    [{"shape": "plane", "normal": [0, 0, 1]},
                     {"shape": "box", "half_extents": [1, 1, 0.1], "position": [0, 0, -0.1]}])
    a, b = sc.bodies
    pa, qa = np.array([[0, 0, 0.49]]), np.array([[1.0, 0, 0, 0]])
    pb, qb = np.array([[0.6 - 0.02, 0, 0]]), np.array([[1.0, 0, 0, 0]])
    assert geo.BODY_PAIRS[("box", "capsule")](a, b, pa, qa, pb, qb) == pytest.approx([0.02], abs=1e-12)
    assert geo.BODY_PAIRS[("capsule", "box")](b, a, pb, qb, pa, qa) == pytest.approx([0.02], abs=1e-12)
    assert geo.STATIC_PAIRS[("box", "plane")](a, sc.statics[0], pa, qa) == pytest.approx([0.01], abs=1e-15)
    assert geo.STATIC_PAIRS[("box", "box")](a, sc.statics[1], pa, qa) == pytest.approx([0.01], abs=1e-15)
