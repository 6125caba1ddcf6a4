"""The time-of-impact search's gap of a followed pair (engine.ccd.pair_gap)
is one compiled kernel (engine.ccd_gap.gap); it must give what the numpy form
it replaced gave, bit for bit (the engine's final states depend on every
search's tau).  The numpy form is kept here as the reference, and both run
on random contacts with points followed, left out and feature ids."""

import numpy as np
import pytest

from physbench.engine import ccd_gap
from physbench.engine.mathutil import cross, quat_to_matrix


def _numpy_gap(point, gap, fid, ca, cb, normal, x1, q1, V, W, n, a, tol, loc, exclude, fids):
    """physbench.engine.ccd.pair_gap before it was compiled (numpy over the pair's
    contacts)."""
    p = None
    if (loc is not None and loc.size) or (exclude is not None and exclude.size):
        R1 = quat_to_matrix(q1[a:a + 1])[0]
        p = np.einsum("ki,ij->kj", point - x1[a], R1)
    g = gap
    if exclude is not None and exclude.size:
        gone = np.sum((p[:, None, :] - exclude[None, :, :]) ** 2, axis=-1).min(axis=1) <= tol * tol
        if gone.all():
            return np.inf, 0.0
        g = np.where(gone, np.inf, g)
    if loc is not None and loc.size:
        D2 = np.sum((p[:, None, :] - loc[None, :, :]) ** 2, axis=-1)
        D2[~np.isfinite(g)] = np.inf
        best = np.argmin(D2, axis=0)
        best = best[D2[best, np.arange(loc.shape[0])] <= tol * tol]
        same = None
        if fids is not None:
            same = (fid.reshape(-1, 1) == fids.reshape(1, -1)).any(axis=1) if fid.size and fids.size \
                else np.zeros(fid.shape, bool)
            same &= np.isfinite(g)
        if best.size or (same is not None and same.any()):
            follow = np.zeros(gap.size, bool)
            follow[best] = True
            if same is not None:
                follow |= same
            g = np.where(follow, gap, np.inf)
    k = int(np.argmin(g))
    ka, kb = int(ca[k]), int(cb[k])
    rA = point[k:k + 1] - (x1[ka:ka + 1] if ka < n else np.zeros((1, 3)))
    rB = point[k:k + 1] - (x1[kb:kb + 1] if kb < n else np.zeros((1, 3)))
    rel = V[cb[k:k + 1]] + cross(W[cb[k:k + 1]], rB) - V[ca[k:k + 1]] - cross(W[ca[k:k + 1]], rA)
    return float(gap[k]), float(np.einsum("ki,ki->k", rel, normal[k:k + 1])[0])


@pytest.mark.parametrize("seed", range(40))
def test_compiled_gap_is_the_numpy_gap_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    n = 4
    m = int(rng.integers(1, 9))
    a = int(rng.integers(0, n))
    static = bool(rng.integers(0, 2))
    ca = np.full(m, a, np.int64)
    cb = np.full(m, n if static else (a + 1) % n, np.int64)
    scale = 10.0 ** rng.uniform(-3, 1)
    x1 = rng.standard_normal((n, 3))
    q1 = rng.standard_normal((n, 4))
    q1 /= np.linalg.norm(q1, axis=1)[:, None]
    point = x1[a] + scale * rng.standard_normal((m, 3))
    normal = rng.standard_normal((m, 3))
    gap = scale * rng.standard_normal(m)
    fid = rng.integers(0, 4, m).astype(np.int64)
    V, W = rng.standard_normal((n + 1, 3)), rng.standard_normal((n + 1, 3))
    V[n] = W[n] = 0.0
    tol = 0.3 * scale
    R1 = quat_to_matrix(q1)
    local = np.einsum("ki,ij->kj", point - x1[a], R1[a])
    for case in range(6):
        # followed points: some exactly at contacts, some near, some far
        loc = local[rng.integers(0, m, int(rng.integers(0, 3)))] + tol * rng.uniform(0, 2) * rng.standard_normal(3)
        loc = loc if case % 2 else None
        excl = local[rng.integers(0, m, int(rng.integers(1, 3)))] if case in (2, 3, 5) else None
        fids = np.unique(fid[rng.integers(0, m, 2)]) if case >= 4 else None
        want = _numpy_gap(point, gap, fid, ca, cb, normal, x1, q1, V, W, n, a, tol, loc, excl, fids)
        got = ccd_gap.gap(point, gap, fid, ca, cb, normal, x1, R1[a], V, W, a, tol,
                          ccd_gap.NO_P3 if loc is None else np.ascontiguousarray(loc),
                          ccd_gap.NO_P3 if excl is None else np.ascontiguousarray(excl),
                          ccd_gap.NO_FID if fids is None else fids, np.empty((m, 5)))
        assert np.array_equal(np.array(got), np.array(want)), (case, got, want)


def test_collide_gap_gives_the_bits_of_the_colliders_run_and_gap(monkeypatch):
    """engine.ccd.pair_gap's one compiled call (ccd_gap.collide_gap: the
    followed pair's collision and its gap) against its other path (the
    collider's run, then ccd_gap.gap), taken when collide_gap reports a
    short buffer: the same final state, bit for bit, over a mixed bin's
    ~200 time-of-impact iterates (boxes, capsules, spheres; followed
    points, left-out points, feature ids)."""
    from physbench.adapters.reference import engine_for
    from physbench.contract.scene import load_scene
    from physbench.engine import ccd

    real, done = ccd._collide_gap, []

    def counting(*args):
        out = real(*args)
        done.append(out[0])
        return out

    monkeypatch.setattr(ccd, "_collide_gap", counting)
    a = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    a.step(40)
    assert sum(done) >= 100  # (the compiled call answered the iterates)
    monkeypatch.setattr(ccd, "_collide_gap", lambda *args: (False, np.inf, 0.0))
    b = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    b.step(40)
    assert a.profile.as_dict()["counters"]["toi_iterations"] >= 100
    assert a.profile.as_dict()["counters"] == b.profile.as_dict()["counters"]
    for u, v in ((a.state.x, b.state.x), (a.state.q, b.state.q), (a.state.v, b.state.v), (a.state.w, b.state.w)):
        assert np.array_equal(u, v)
