"""The conversion functions of contract/conventions.py, against hand values."""

import math

import numpy as np
import pytest

from physbench.contract.conventions import planar_from_world, world_from_planar
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
