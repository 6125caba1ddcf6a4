"""The reference engine is a leaf: ``engine/`` imports numpy, numba, scipy
and itself, nothing of the harness or the adapters; the reference adapter
translates the harness scene into the engine's own input.  And the model
scales: its size is O(n + materials^2), not O(n^2)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def test_import_engine_loads_no_harness_adapters_or_pydantic():
    code = textwrap.dedent("""
        import json, sys
        import physbench.engine, physbench.engine.model, physbench.engine.pipeline, physbench.engine.collision, physbench.engine.broadphase
        from physbench import engine
        bad = sorted(m for m in sys.modules
                     if m.startswith(("physbench.harness", "physbench.adapters", "pydantic")))
        print(json.dumps(bad))
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def _spheres(n: int, materials: int):
    """A SceneInput of n spheres on a plane, with ``materials`` materials."""
    from physbench.engine.model import SceneInput

    M = materials + 1
    rng = np.random.default_rng(0)
    tab = rng.uniform(0.1, 0.9, (M, M))
    tab = 0.5 * (tab + tab.T)
    z = np.zeros((n, 3))
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    x = np.stack([np.arange(n) * 0.3, np.zeros(n), np.full(n, 0.1)], axis=1)
    r = np.full(n, 0.1)
    return SceneInput(
        dt=1 / 240, effects=frozenset({"gravity", "contact", "friction", "restitution"}),
        gravity=np.array([0, 0, -9.81]), shape=("sphere",) * n, mass=np.ones(n), inertia=np.full((n, 3), 0.004),
        radius=r, half_extents=z, half_length=np.zeros(n), bound_radius=r, min_extent=r,
        drag_linear=np.zeros(n), drag_quadratic=np.zeros(n), material=np.arange(n) % materials,
        x=x, q=q, v=z, w=z, static_shape=("plane",), static_material=np.array([materials]),
        static_normal=np.array([[0.0, 0.0, 1.0]]), static_offset=np.zeros(1), static_position=np.zeros((1, 3)),
        static_orientation=np.array([[1.0, 0, 0, 0]]), static_half_extents=np.zeros((1, 3)),
        spring_a=np.zeros(0, np.int64), spring_b=np.zeros(0, np.int64), spring_anchor_a=np.zeros((0, 3)),
        spring_anchor_b=np.zeros((0, 3)), spring_k=np.zeros(0), spring_rest=np.zeros(0), spring_c=np.zeros(0),
        pair_e=tab, pair_mus=tab, pair_muk=0.5 * tab, pair_mur=np.zeros((M, M))), tab


def test_model_size_is_linear_in_bodies_and_coefficients_are_looked_up_per_pair():
    from physbench.engine import default_settings
    from physbench.engine.model import build_model

    n, mats = 3000, 3
    inp, tab = _spheres(n, mats)
    model = build_model(inp, default_settings(inp))
    arrays = [v for v in vars(model).values() if isinstance(v, np.ndarray)]
    # nothing of n^2 (9e6) entries: every array is O(n) or O(materials^2)
    assert max(a.size for a in arrays) <= 4 * (n + 1)
    for t in (model.pair_e, model.pair_mus, model.pair_muk, model.pair_mur):
        assert t.shape == (mats + 1, mats + 1)
    a = np.array([0, 1, 2, 5])
    b = np.array([4, 2, 3, n])
    s = np.array([-1, -1, -1, 0])
    e, mus, muk, _ = model.pair_coefficients(a, b, s)
    ma, mb = a % mats, np.array([4 % mats, 2 % mats, 3 % mats, mats])
    assert np.array_equal(e, tab[ma, mb]) and np.array_equal(muk, 0.5 * tab[ma, mb])
