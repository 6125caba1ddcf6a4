"""Broad phase: ``sap_pairs`` returns exactly the pairs of a naive all-pairs
test (i < j, sorted lexicographically) on many random clouds, through each
of its paths (single-axis sweep, grid sweep with 2 x 2 or more cells per
box, boxes tested against all), and on degenerate input; so does the
broad-phase stage's compiled path (``stage_pairs``: a sweep along a kept
order, a uniform grid for dense clouds)."""

from __future__ import annotations

import warnings
import zlib

import numpy as np
import pytest

import physbench.engine.broadphase as bp
from physbench.engine.broadphase import brute_pairs, sap_pairs


def naive(lo, hi):
    n = lo.shape[0]
    a, b = [], []
    for i in range(n):
        ok = np.all((lo[i] <= hi[i + 1:]) & (lo[i + 1:] <= hi[i]), axis=1)
        js = i + 1 + np.flatnonzero(ok)
        a += [i] * js.size
        b += js.tolist()
    return np.array(a, np.int64), np.array(b, np.int64)


def check(lo, hi):
    """sap_pairs (the general path, the one the module's knobs steer) and
    the broad-phase stage's compiled sweep and grid (stage_pairs) against
    naive."""
    ra, rb = naive(lo, hi)
    for f in (bp.stage_pairs, sap_pairs):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            a, b = f(lo, hi)
        assert a.dtype == np.int64 and b.dtype == np.int64
        assert np.array_equal(a, ra) and np.array_equal(b, rb), (f.__name__, len(a), len(ra))
    return len(a)


def cloud(rng, kind: str, n: int):
    c = rng.uniform(-1, 1, (n, 3))
    e = rng.uniform(0.01, 0.2, (n, 3))
    if kind == "dense":  # constant-density spheres, some touching
        r = 0.05
        c = rng.uniform(0, 2.5 * r * max(n, 1) ** (1 / 3), (n, 3))
        e = np.full((n, 3), r)
    elif kind == "clustered":
        centres = rng.uniform(-5, 5, (4, 3))
        c = centres[rng.integers(0, 4, n)] + rng.normal(0, 0.2, (n, 3))
        e = rng.uniform(0.02, 0.1, (n, 3))
    elif kind == "mixed":  # a few huge boxes among small ones
        e = rng.uniform(0.01, 0.05, (n, 3))
        if n:
            e[rng.integers(0, n, 3)] *= rng.uniform(5, 100, (3, 1))
    elif kind == "one_huge":
        e = np.full((n, 3), 0.02)
        if n:
            e[0] = 50.0
    elif kind == "flat":  # a planar layer: no spread on z
        c[:, 2] = 0.3
    elif kind == "lattice":  # touching boxes with exactly equal bounds
        c = np.round(rng.uniform(-1, 1, (n, 3)) * 5) / 5
        e = np.full((n, 3), 0.1)
    elif kind == "identical":
        c = np.tile(rng.uniform(-1, 1, (1, 3)), (n, 1))
    elif kind == "points":  # zero-width boxes, some coincident
        c = np.round(c * 3) / 3
        e = np.zeros((n, 3))
    elif kind == "wide_spread":  # widths from tiny to large
        e = rng.uniform(0, 1, (n, 3)) ** 4
    elif kind == "far_apart":  # two tight clusters 1e6 apart: cells capped
        c = rng.normal(0, 0.1, (n, 3))
        c[: n // 2] += 1e6
        e = np.full((n, 3), 0.05)
    return c - e, c + e


KINDS = ["uniform", "dense", "clustered", "mixed", "one_huge", "flat", "lattice",
         "identical", "points", "wide_spread", "far_apart"]

#: module settings that force each path of sap_pairs
PATHS = {
    "default": {},
    "single_axis": {"_SWEEP_ONLY": 10 ** 9},
    "grid_2x2": {"_SWEEP_ONLY": 0},
    "grid_many_cells": {"_SWEEP_ONLY": 0, "_CELL_SCALE": 0.3},
    "grid_coarse": {"_SWEEP_ONLY": 0, "_MAX_CELLS": 3},
    "grid_many_big": {"_SWEEP_ONLY": 0, "_BIG_FACTOR": 1.0},
}


def use_path(monkeypatch, path: str) -> list:
    """Set the module's knobs for ``path``; returns a list that counts the
    grid sweeps run."""
    for k, v in PATHS[path].items():
        monkeypatch.setattr(bp, k, v)
    calls = []
    grid = bp._grid_pairs

    def counted(*a, **k):
        calls.append(1)
        return grid(*a, **k)

    monkeypatch.setattr(bp, "_grid_pairs", counted)
    return calls


@pytest.mark.parametrize("path", list(PATHS))
@pytest.mark.parametrize("kind", KINDS)
def test_sap_equals_naive_on_random_clouds(monkeypatch, path, kind):
    calls = use_path(monkeypatch, path)
    rng = np.random.default_rng(zlib.crc32(f"{path} {kind}".encode()))
    found = 0
    for n in (0, 1, 2, 3, 17, 60, 250):
        lo, hi = cloud(rng, kind, n)
        found += check(lo, hi)
    assert found > 0
    if path.startswith("grid"):
        assert calls
    elif path == "single_axis":
        assert not calls


@pytest.mark.parametrize("path", list(PATHS))
def test_sap_equals_naive_with_degenerate_rows(monkeypatch, path):
    """NaN bounds (the row overlaps nothing), lo > hi, infinite bounds: the
    same pairs as the naive test, as before."""
    use_path(monkeypatch, path)
    rng = np.random.default_rng(7)
    for trial in range(40):
        n = int(rng.integers(2, 200))
        lo, hi = cloud(rng, KINDS[trial % len(KINDS)], n)
        for _ in range(int(rng.integers(1, 6))):
            r, a = rng.integers(n), rng.integers(3)
            k = rng.integers(5)
            if k == 0:
                lo[r, a] = np.nan
            elif k == 1:
                hi[r, a] = np.nan
            elif k == 2:
                lo[r, a], hi[r, a] = hi[r, a] + 0.3, lo[r, a]
            elif k == 3:
                lo[r, a] = -np.inf
            else:
                hi[r, a] = np.inf
        check(lo, hi)


def test_all_nan_and_all_at_one_point():
    n = 50
    lo = np.full((n, 3), np.nan)
    assert check(lo, lo) == 0
    z = np.zeros((n, 3))
    assert check(z, z) == n * (n - 1) // 2


def test_matches_brute_pairs(monkeypatch):
    calls = use_path(monkeypatch, "default")
    rng = np.random.default_rng(11)
    n = 1500
    lo, hi = cloud(rng, "dense", n)

    a, b = sap_pairs(lo, hi)
    assert calls and len(a) > n  # dense enough to take the grid path
    for ra, rb in (brute_pairs(lo, hi),):
        assert np.array_equal(a, ra) and np.array_equal(b, rb)


@pytest.mark.parametrize("kind", ["lattice_moving", "blob", "sparse", "outliers", "one_huge"])
def test_stage_path_keeps_exact_pairs_as_boxes_move(kind):
    """The stage's state carried from step to step (the sweep's order and
    axis restored by insertion sort, the dense flag that keeps the uniform
    grid, hashed when far outliers make the grid large): exactly
    brute_pairs' pairs at every step, through each path."""
    rng = np.random.default_rng(zlib.crc32(kind.encode()))
    n = 300
    if kind in ("lattice_moving", "outliers"):
        s = 7
        c = np.stack(np.meshgrid(*[np.arange(s)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n] * 0.08
        n = c.shape[0]
        if kind == "outliers":
            c[:3] += rng.uniform(50, 100, (3, 3))
        e = np.full((n, 3), 0.05)
    elif kind == "blob":
        c, e = rng.uniform(0, 1, (n, 3)), rng.uniform(0.02, 0.12, (n, 3))
    elif kind == "sparse":
        c, e = rng.uniform(0, 30, (n, 3)), rng.uniform(0.01, 0.3, (n, 3))
    else:
        c, e = np.round(rng.uniform(0, 0.5, (n, 3)), 2), np.full((n, 3), 0.05)  # dense, with ties
        e[0] = 5.0
    buf = bp.SapBuffers(n)
    seen = set()
    for step in range(15):
        c = c + rng.normal(0, 0.01, c.shape) * (10 if step % 5 == 0 else 1)
        lo, hi = c - e, c + e
        k = buf.run(lo, hi)
        seen.add("fallback" if k == bp._FALLBACK else ("grid" if buf.state[1] else "sweep"))
        a, b = (buf.pi[:k], buf.pj[:k]) if k != bp._FALLBACK else sap_pairs(lo, hi)
        ra, rb = brute_pairs(lo, hi)
        assert np.array_equal(a, ra) and np.array_equal(b, rb), (kind, step)
    expected = {"lattice_moving": "grid", "blob": "grid", "sparse": "sweep", "outliers": "grid",
                "one_huge": "fallback"}[kind]
    assert expected in seen, seen
