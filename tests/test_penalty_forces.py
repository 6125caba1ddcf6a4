"""The penalty model's normal forces are one compiled call
(engine.penalty.normal_forces); they must be what the numpy form it
replaced computed, bit for bit, on random contacts (body-body and against
a static), with the stiffness automatic and set."""

import numpy as np
import pytest

from physbench.engine import penalty
from physbench.engine.contact.rows import _pad, point_normal_velocity


def _numpy_forces(X, V0, W0, a, b, point, normal, gap, m_eff, k_setting, h, zeta, model_h):
    rA = point - _pad(X)[a]
    rB = point - _pad(X)[b]
    vn, _ = point_normal_velocity(V0, W0, a, b, rA, rB, normal)
    if k_setting > 0:
        k = np.full(gap.size, k_setting)
    else:
        T = penalty.PERIODS * model_h
        k = m_eff * (np.pi / T) ** 2
    damp = 2.0 * zeta * np.sqrt(k * m_eff)
    d_mid = -gap - 0.5 * h * vn
    return np.maximum(k * d_mid - damp * vn, 0.0)


@pytest.mark.parametrize("seed", range(30))
def test_normal_forces_are_the_numpy_forms(seed):
    rng = np.random.default_rng(seed)
    n, m = 5, int(rng.integers(1, 12))
    X = rng.standard_normal((n, 3))
    V0, W0 = _pad(rng.standard_normal((n, 3))), _pad(rng.standard_normal((n, 3)))
    a = rng.integers(0, n - 1, m).astype(np.int64)
    b = np.where(rng.random(m) < 0.5, n, a + 1).astype(np.int64)
    point = X[a] + 0.1 * rng.standard_normal((m, 3))
    normal = rng.standard_normal((m, 3))
    gap = -1e-3 * rng.random(m)
    m_eff = rng.uniform(0.1, 10.0, m)
    zeta = np.array([penalty.damping_ratio_for(float(e)) for e in rng.choice([0.0, 0.3, 0.9], m)])
    h = model_h = 1 / 240
    for k_setting in (0.0, 1e5):
        kfac = (np.pi / (penalty.PERIODS * model_h)) ** 2 if k_setting <= 0 else k_setting
        got = penalty.normal_forces(X, V0, W0, a, b, point, normal, gap, m_eff, k_setting > 0, kfac, zeta, h,
                                    np.empty(m))
        want = _numpy_forces(X, V0, W0, a, b, point, normal, gap, m_eff, k_setting, h, zeta, model_h)
        assert np.array_equal(got, want)
        assert np.all(got >= 0.0)
