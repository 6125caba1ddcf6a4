"""The impact solver's propagation is compiled (engine/contact/propagate.py)
and must give the bits of the numpy form it replaced: its sums are formed
in numpy's orders and its hypot is CPython's.  Each helper is pinned here
against what numpy and math compute, on random values over many scales
(the engine's final states, scenario by scenario, are compared with the
numpy form's by the determinism pins)."""

import math

import numpy as np
import pytest

from physbench.engine.contact import propagate as P


def _values(rng, *shape):
    return rng.standard_normal(shape) * 10.0 ** rng.uniform(-6, 6, shape)


@pytest.mark.parametrize("n", range(1, 20))
def test_contiguous_dot_is_einsums(n):
    rng = np.random.default_rng(n)
    for _ in range(200):
        A, y = _values(rng, 4, n), _values(rng, n)
        want = np.einsum("kj,j->k", A, y)
        got = np.array([P._edot(A[i], y, n) for i in range(4)])
        assert np.array_equal(got, want)


def test_row_speed_is_einsums_over_the_gathered_pair():
    rng = np.random.default_rng(0)
    for _ in range(500):
        J, U = _values(rng, 3, 12), _values(rng, 4, 6)
        ab = rng.integers(0, 4, (3, 2))
        want = np.einsum("kj,kj->k", J, U[ab].reshape(-1, 12))
        got = np.array([P._vn(J, r, U, ab[r, 0], ab[r, 1]) for r in range(3)])
        assert np.array_equal(got, want)


@pytest.mark.parametrize("n", range(1, 30))
def test_sum_is_numpys_pairwise_sum(n):
    rng = np.random.default_rng(n)
    for _ in range(200):
        x = np.abs(_values(rng, n))
        assert P._pwsum(x, n) == x.sum()


def test_hypot_is_cpythons():
    rng = np.random.default_rng(1)
    xs = _values(rng, 100000, 2) * 10.0 ** rng.uniform(-14, 14, (100000, 1))
    xs[::7, 1] = 0.0
    special = [(0.0, 0.0), (-0.0, 3.0), (1e-310, 2e-310), (5e-324, 0.0), (1e308, 1e308), (3.0, 4.0),
               (math.inf, 1.0), (1.0, -math.inf)]
    bad = [(x, y) for x, y in list(map(tuple, xs)) + special if P.hypot(x, y) != math.hypot(x, y)]
    assert not bad, bad[:5]
    assert math.isnan(P.hypot(math.nan, 1.0))


def test_block_normal_solves_the_pair_lcp():
    # two rows of one pair (a body on the world): the exact impulses make
    # both rows' speeds reach their targets (K lambda = r, lambda >= 0)
    rng = np.random.default_rng(3)
    J = np.zeros((2, 12))
    J[:, :6] = rng.standard_normal((2, 6))
    M = np.zeros((2, 12))
    M[:, :6] = J[:, :6] * 0.5  # M^-1 J^T with M^-1 = 0.5 I
    ab = np.array([[0, 1], [0, 1]], np.int64)
    idx = np.arange(2, dtype=np.int64)
    U = np.zeros((2, 6))
    U[0] = -J[:, :6].sum(axis=0)  # approaching on both rows
    K = np.empty((2, 2))
    P._pair_matrix(J, M, idx, 2, K)
    lam, r = np.empty(2), np.empty(2)
    P.block_normal(J, M, ab, idx, 2, np.zeros(2), U, K, 1, lam, r)
    vn = J[:, :6] @ U[0]
    assert np.all(lam >= 0.0)
    assert np.all(vn >= -1e-12)
    assert np.allclose(lam * vn, 0.0, atol=1e-12)  # complementarity
    assert np.all(U[1] == 0.0)  # the world row stays zero


def test_setup_is_the_numpy_form():
    """propagate.setup (one compiled call) gives impact._propagate's numpy
    index arrays and normal speeds exactly."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        m = int(rng.integers(1, 12))
        n = int(rng.integers(1, 6))
        a = rng.integers(0, n, m)
        b = np.where(rng.random(m) < 0.3, n, rng.integers(0, n, m))
        ab = np.stack([a, b], axis=1).astype(np.int64)
        code = (a * (n + 1) + b) * 3 + rng.integers(0, 2, m)
        J, U = _values(rng, m, 12), _values(rng, n + 1, 6)
        go, gs, inv, bo, b0, vcur = P.setup(code.astype(np.int64), ab, n, J, U)
        uniq, inv_w = np.unique(code, return_inverse=True)
        go_w = np.argsort(inv_w, kind="stable")
        gs_w = np.zeros(uniq.size + 1, np.int64)
        np.cumsum(np.bincount(inv_w, minlength=uniq.size), out=gs_w[1:])
        ab_rows = np.concatenate([a, b])
        bo_w = np.argsort(ab_rows, kind="stable") % m
        b0_w = np.zeros(n + 2, np.int64)
        np.cumsum(np.bincount(ab_rows, minlength=n + 1), out=b0_w[1:])
        vcur_w = np.einsum("kj,kj->k", J, U[ab].reshape(-1, 12))
        for got, want in ((go, go_w), (gs, gs_w), (inv, inv_w), (bo, bo_w), (b0, b0_w), (vcur, vcur_w)):
            assert np.array_equal(got, want)
