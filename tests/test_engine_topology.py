"""The contact graph's topology (engine/contact/topology.py) is built by one
compiled call (``Topology._compiled``) and must hold exactly the arrays the
numpy form (``Topology._numpy``) computes: the colouring, the pair codes and
their stable sort, the friction patches (np.unique's first rows and inverse,
coloured), their counts -- on random contact graphs, with and without
colouring and friction, including graphs that need a 64th colour (where the
compiled call declines and the numpy form runs)."""

from types import SimpleNamespace

import numpy as np
import pytest

from physbench.engine.contact.topology import Topology


def _graph(rng, n, ns, m):
    a = rng.integers(0, n, m).astype(np.int64)
    b = rng.integers(0, n + 1, m).astype(np.int64)
    b = np.where(b == a, n, b)
    if ns:
        sidx = np.where(b == n, rng.integers(-1, ns, m), -1).astype(np.int64)
    else:
        sidx = np.full(m, -1, np.int64)
    return a, b, sidx


def _same(t1: Topology, t2: Topology) -> None:
    d1, d2 = t1.__dict__, t2.__dict__
    assert d1.keys() == d2.keys()
    for k in d1:
        x, y = d1[k], d2[k]
        if isinstance(y, np.ndarray):
            assert isinstance(x, np.ndarray) and x.dtype == y.dtype and x.shape == y.shape, k
            assert np.array_equal(x, y), k
        else:
            assert x == y, k


@pytest.mark.parametrize("seed", range(6))
def test_compiled_topology_is_the_numpy_one(seed):
    rng = np.random.default_rng(seed)
    for _ in range(150):
        n, ns, m = int(rng.integers(1, 12)), int(rng.integers(0, 3)), int(rng.integers(1, 40))
        model = SimpleNamespace(n=n, n_statics=ns, inv_mass=np.concatenate([rng.random(n), [0.0]]))
        a, b, sidx = _graph(rng, n, ns, m)
        for friction in (False, True):
            for colour in (False, True):
                t1 = Topology.__new__(Topology)
                assert t1._compiled(model, a, b, sidx, friction, colour)
                t2 = Topology.__new__(Topology)
                t2._numpy(model, a, b, sidx, friction, colour)
                _same(t1, t2)
                _same(Topology(model, a, b, sidx, friction, colour), t2)


def test_a_64th_colour_falls_back_to_numpy():
    # 100 rows between the same two bodies: each needs its own colour
    model = SimpleNamespace(n=2, n_statics=0, inv_mass=np.array([1.0, 0.5, 0.0]))
    a, b, sidx = np.zeros(100, np.int64), np.ones(100, np.int64), np.full(100, -1, np.int64)
    t1 = Topology.__new__(Topology)
    assert not t1._compiled(model, a, b, sidx, True, True)
    assert not t1.__dict__  # nothing set
    t2 = Topology.__new__(Topology)
    t2._numpy(model, a, b, sidx, True, True)
    _same(Topology(model, a, b, sidx, True, True), t2)
    assert len(t2.slices) == 100
