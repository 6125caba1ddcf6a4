"""The conversion functions of contract/conventions.py, against hand values."""

import math

import numpy as np
import pytest

from physbench.contract.conventions import planar_from_world, world_from_planar, world_quat_from_planar_rotation
from physbench.contract.rotation import body_to_world_angvel, quat_rotate, quat_to_matrix, world_to_body_angvel, wxyz_to_xyzw, xyzw_to_wxyz


def test_quaternion_order_round_trip():
    q = np.array([0.1, 0.2, 0.3, 0.9])
    assert wxyz_to_xyzw(q).tolist() == [0.2, 0.3, 0.9, 0.1]
    assert np.array_equal(xyzw_to_wxyz(wxyz_to_xyzw(q)), q)


def test_rotation_hand_values():
    # 90 degrees about z takes x to y
    q = np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    assert np.allclose(quat_rotate(q, [1.0, 0, 0]), [0, 1, 0])
    assert np.allclose(quat_to_matrix(q) @ [1.0, 0, 0], [0, 1, 0])
    # batched: (2, 4) with (2, 3)
    qs = np.stack([q, [1.0, 0, 0, 0]])
    assert np.allclose(quat_rotate(qs, np.eye(3)[:2]), [[0, 1, 0], [0, 1, 0]])


def test_angular_velocity_frames():
    # body tilted 90 degrees about x: body z is world -y
    q = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0])
    w_body = np.array([0, 0, 2.0])
    assert np.allclose(body_to_world_angvel(q, w_body), [0, -2.0, 0])
    assert np.allclose(world_to_body_angvel(q, [0, -2.0, 0]), w_body)


def test_planar_mapping_round_trip_and_sign():
    theta = 0.4
    q = np.array([math.cos(theta / 2), 0, -math.sin(theta / 2), 0])
    (x, y), (vx, vy), angle, w = planar_from_world(np.array([1.0, 0, 2.0]), np.array([3.0, 0, -1.0]), q,
                                                  np.array([0, -5.0, 0]))
    assert (x, y, vx, vy) == (1.0, 2.0, 3.0, -1.0)
    assert angle == pytest.approx(theta) and w == 5.0
    pos, quat, vel, ang = np.zeros(3), np.zeros(4), np.zeros(3), np.zeros(3)
    world_from_planar(x, y, vx, vy, angle, w, pos, quat, vel, ang)
    assert np.allclose(pos, [1, 0, 2]) and np.allclose(quat, q) and np.allclose(vel, [3, 0, -1])
    assert np.allclose(ang, [0, -5, 0])
    # a counter-clockwise 2D angle turns world +x toward +z
    assert np.allclose(quat_rotate(quat, [1.0, 0, 0]), [math.cos(theta), 0, math.sin(theta)])


EPS = np.finfo(float).eps


def _f32_rotations():
    """(cos, sin) pairs as a single-precision engine holds them (float32, so
    not exactly unit): uniform angles, clusters at 1e-3, 1e-7 and 1e-12 rad
    around 0, +-pi/2 and +-pi, and the exact edge values (signed zeros, the
    smallest float32 sine beside +-pi)."""
    rng = np.random.default_rng(11)
    a = np.concatenate([rng.uniform(-np.pi, np.pi, 20000)]
                       + [c + rng.normal(0.0, d, 2000) for c in (0.0, np.pi / 2, -np.pi / 2, np.pi, -np.pi)
                          for d in (1e-3, 1e-7, 1e-12)])
    c = np.concatenate([np.cos(a), [1, 1, -1, -1, 0, 0, -0.0, -0.0, 1, -1, -1, 1]]).astype(np.float32)
    s = np.concatenate([np.sin(a), [0, -0.0, 0, -0.0, 1, -1, 1, -1, 1e-45, 1e-45, -1e-45, -1e-45]]).astype(np.float32)
    return c, s


def _rotation_quat(c, s):
    w, y = np.full(c.shape, np.nan), np.full(c.shape, np.nan)
    world_quat_from_planar_rotation(c, s, w, y, np.full((4, *c.shape), np.nan))
    return w, y


def test_planar_rotation_quaternion_matches_the_angle_path():
    """world_quat_from_planar_rotation (square roots, no trigonometry) gives
    world_from_planar's quaternion of angle = atan2(s, c) for float32 (cos,
    sin) pairs all round the circle, to 2^-50 absolute per component: both
    compute one function of the same (exactly widened) inputs, the angle
    path within 2 eps (atan2 within an ulp of an angle <= pi, i.e. 2 eps,
    halved; cos/sin within an ulp of 1) and the formula within 2 eps (a
    square root halves the relative error of its argument, itself a few
    roundings).  Measured: 1.5 eps.  The sign bits agree exactly (signed
    zeros: the angle +-0 for c > 0, +-pi for c < 0).  The sample exercises
    what a careless formula gets wrong: pairs off unit norm by ~1e-8 (a
    formula without the normalisation is off by that much) and cosines of
    the half angle below 1e-9 beside +-pi (where sqrt((1 + c) / 2) loses
    every digit)."""
    c, s = _f32_rotations()
    w, y = _rotation_quat(c, s)
    want = np.full((4, c.size), np.nan)
    c64, s64 = c.astype(float), s.astype(float)
    world_from_planar(0.0, 0.0, 0.0, 0.0, np.arctan2(s64, c64), 0.0, np.zeros(3), want, np.zeros(3), np.zeros(3))
    assert np.abs(c64 * c64 + s64 * s64 - 1.0).max() > 1e-8
    assert np.sort(want[0])[10] < 1e-9
    assert max(np.abs(w - want[0]).max(), np.abs(y - want[2]).max()) <= 2.0 ** -50
    assert np.array_equal(np.signbit(w), np.signbit(want[0])) and np.array_equal(np.signbit(y), np.signbit(want[2]))
    assert np.abs(w * w + y * y - 1.0).max() <= 4 * EPS  # a unit quaternion, whatever the f32 pair's norm


def test_planar_rotation_quaternion_against_high_precision():
    """The formula against the half angle worked out in 150-digit decimal
    arithmetic from the exact float32 values (cos(a/2) = sqrt((1 + c/r)/2),
    |sin(a/2)| = sqrt((1 - c/r)/2), sin's sign that of s: the textbook
    formula, its cancellation beside +-pi drowned by the precision): within
    an ulp of 1 (measured 0.5 eps: as good as correctly rounded).  NaN in
    gives NaN out, and so does (0, 0), which is no rotation."""
    from decimal import Decimal, localcontext

    c, s = _f32_rotations()
    pick = np.r_[0:300, 20000:c.size:97, c.size - 12:c.size]
    c, s = c[pick], s[pick]
    w, y = _rotation_quat(c, s)
    with localcontext() as ctx:
        ctx.prec = 150
        for ci, si, wi, yi in zip(c, s, w, y):
            C, S = Decimal(float(ci)), Decimal(float(si))
            u = C / (C * C + S * S).sqrt()
            half = Decimal(1) / 2
            tw, ts = ((1 + u) * half).sqrt(), ((1 - u) * half).sqrt()
            ty = -ts if not np.signbit(si) else ts
            assert abs(wi - float(tw)) <= EPS and abs(yi - float(ty)) <= EPS, (ci, si, wi, yi)
    bad = np.array([np.nan, 1.0, 0.0], np.float32), np.array([0.0, np.nan, 0.0], np.float32)
    with np.errstate(invalid="ignore"):  # (0, 0): 0 / 0
        assert np.isnan(np.stack(_rotation_quat(*bad))).all()


def test_quat_rotate_equals_rotation_matrix_and_writes_in_place():
    """quat_rotate (per-component) against R(q) v for random stacks, with
    broadcasting of one vector over many quaternions, and with ``out``."""
    rng = np.random.default_rng(7)
    q = rng.normal(size=(50, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    v = rng.normal(size=(50, 3, 3))
    want = np.einsum("...ij,...j->...i", quat_to_matrix(q), v)
    np.testing.assert_allclose(quat_rotate(q, v), want, rtol=0, atol=1e-14)
    out = np.full((50, 3, 3), np.nan)
    assert quat_rotate(q, v, out=out) is out
    np.testing.assert_array_equal(out, quat_rotate(q, v))
    np.testing.assert_allclose(quat_rotate(q, [0.0, 0.0, 1.0]), quat_to_matrix(q)[..., :, 2], atol=1e-15)


def test_engine_rotation_copies_match_the_contract():
    """The engine is a leaf and keeps its own rotation helpers
    (engine/mathutil.py); they must agree with contract.rotation: the matrix
    bit for bit."""
    from physbench.engine import mathutil

    rng = np.random.default_rng(7)
    q = rng.normal(size=(64, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    assert np.array_equal(mathutil.quat_to_matrix(q), quat_to_matrix(q))
