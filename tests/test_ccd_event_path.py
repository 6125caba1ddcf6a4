"""The event path's kept state (engine/ccd.py, engine/contact/impact.py):
what an impact and a time-of-impact search build once instead of at every
event, with the same results (the bits script; the determinism pins)."""

from __future__ import annotations

import numpy as np

import physbench.engine.contact.impact as impact
import physbench.engine.contact.rows as rows
from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene


def test_a_bouncing_ball_builds_its_impact_topology_once(monkeypatch):
    """Every bounce of a ball on the floor is the same contact set: the
    impact stage keeps its topology (impact.ImpactKept) and its work arrays.
    On the code before, each impact built a Topology (and ~16 work arrays)
    again: 8 for 8 bounces."""
    built = []
    real = rows.Topology

    def counting(model, a, b, sidx, friction, colour):
        if not colour:  # the propagation's (the solve's are coloured)
            built.append(a.size)
        return real(model, a, b, sidx, friction, colour)

    monkeypatch.setattr(rows, "Topology", counting)
    monkeypatch.setattr(impact, "Topology", counting, raising=False)
    eng = engine_for(load_scene("billiards.ball_drop_bounce"), {"dt": 0.032})
    eng.step(47)
    n_impacts = eng.profile.as_dict()["counters"]["impacts"]
    assert n_impacts >= 5
    assert len(built) == 1


def test_kept_impact_state_gives_the_same_velocities():
    """The same impacts with the kept topologies and work arrays as with
    fresh ones (kept=None), bit for bit, over a mixed bin's events."""
    a = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    b = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    next(s for s in b.stages if s.family == "impact").kept = None
    a.step(40)
    b.step(40)
    assert a.profile.as_dict()["counters"]["impacts"] >= 10
    for u, v in ((a.state.x, b.state.x), (a.state.v, b.state.v), (a.state.w, b.state.w)):
        assert np.array_equal(u, v)


def test_contact_inertias_are_world_inv_inertia_bit_for_bit():
    """impact.contact_inertias: the contact bodies' world inverse inertias
    as mathutil.world_inv_inertia(quat_to_matrix(q)) gives them, zero for
    the other bodies and the world row."""
    from physbench.engine.mathutil import quat_to_matrix, world_inv_inertia

    rng = np.random.default_rng(3)
    n = 9
    for trial in range(50):
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        inv_I = 1.0 / rng.uniform(0.01, 3.0, size=(n, 3))
        a = rng.integers(0, n, size=5)
        b = np.where(rng.random(5) < 0.4, n, rng.integers(0, n, size=5))
        out = np.full((n + 1, 3, 3), np.nan)
        impact.contact_inertias(q, inv_I, a, b, out)
        want = np.zeros((n + 1, 3, 3))
        bodies = np.unique(np.concatenate([a, b[b < n]]))
        want[bodies] = world_inv_inertia(quat_to_matrix(q[bodies]), inv_I[bodies])
        assert np.array_equal(out, want)
