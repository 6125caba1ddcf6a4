"""The CCD stage's end-pose check (engine.flight.end_pose_pairs): which
pairs are collided again at the end pose of a step to find missed impacts.

Pinned: (1) conservative -- a pair it leaves out cannot have closed by more
than the tolerance: for random spheres and boxes moved and turned by random
amounts, every left-out pair's exact gap at the end pose is at least its gap
at the start pose minus ``lim`` (so no missed impact deeper than the
tolerance can hide in it); (2) the selection is the boolean-mask selection
it replaced (the same pairs in the same order) and R1 is
mathutil.quat_to_matrix bit for bit, so the engine's results do not change.
"""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene
from physbench.engine import flight
from physbench.engine.collision import collide_pairs
from physbench.engine.geometry import EndPose, Pairs
from physbench.engine.mathutil import quat_to_matrix

SCENE = """
[scenario]
family = "t"
title = "end pose"
duration = 1.0
dt = 0.01
effects = ["gravity", "contact"]

[[body]]
name = "s0"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [0.0, 0.0, 1.0]

[[body]]
name = "s1"
shape = "sphere"
radius = 0.03
mass = 1.0
position = [0.2, 0.0, 1.0]

[[body]]
name = "b0"
shape = "box"
half_extents = [0.05, 0.02, 0.08]
mass = 1.0
position = [0.0, 0.2, 1.0]

[[body]]
name = "b1"
shape = "box"
half_extents = [0.04, 0.04, 0.04]
mass = 1.0
position = [0.2, 0.2, 1.0]

[[static]]
name = "ground"
shape = "plane"
normal = [0.0, 0.0, 1.0]
offset = 0.0
"""


def _unit(rng, k):
    q = rng.normal(size=(k, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _turned(rng, q, angle):
    """q (k, 4) turned by ``angle`` (k,) rad about random axes."""
    ax = rng.normal(size=(q.shape[0], 3))
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    d = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * ax], axis=1)
    w1, v1 = d[:, :1], d[:, 1:]
    w2, v2 = q[:, :1], q[:, 1:]
    out = np.concatenate([w1 * w2 - np.sum(v1 * v2, axis=1, keepdims=True),
                          w1 * v2 + w2 * v1 + np.cross(v1, v2)], axis=1)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _gaps(model, X, q, pi, pj, bp, pk):
    """Each pair's least gap (m) at the pose, all features (inf margin):
    exact signed distance for sphere-sphere, sphere-box and body-plane."""
    c = collide_pairs(model, X, quat_to_matrix(q), pi, pj, (bp, pk), (np.zeros(0, np.int64),) * 2,
                      np.full(pi.size, np.inf), np.full(bp.size, np.inf), np.zeros(0))
    n = model.n
    g = {}
    for a, b, gap in zip(c.a, c.b, c.gap):
        key = (int(min(a, b)), int(max(a, b)))
        g[key] = min(g.get(key, np.inf), float(gap))
    return [g.get((int(i), int(j)), np.inf) for i, j in zip(pi, pj)], [g.get((int(b), n), np.inf) for b in bp]


@pytest.mark.parametrize("seed", range(4))
def test_end_pose_pairs_is_conservative_and_matches_the_masks(tmp_path, seed):
    p = tmp_path / "s.toml"
    p.write_text(textwrap.dedent(SCENE))
    model = engine_for(load_scene(p)).model
    n = model.n
    rng = np.random.default_rng(seed)
    # body pairs the gap of which the collision gives exactly: sphere-sphere
    # and sphere-box (box-box's manifold is clipped), and every body on the plane
    pi = np.array([0, 0, 0, 1, 1], np.int64)
    pj = np.array([1, 2, 3, 2, 3], np.int64)
    bp = np.arange(n, dtype=np.int64)
    pk = np.zeros(n, np.int64)
    lim = 3e-4
    skipped = selected = 0
    for trial in range(300):
        x0 = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.2], size=(n, 3))
        q0 = _unit(rng, n)
        # moves up to 50 mm and turns up to 0.1 rad; or, around the
        # tolerance, moves up to 0.6 mm, or only turns up to 6 mrad (the
        # bound's rotation term alone: up to ~0.6 mm at these sizes)
        move, turn = ((0.05, 0.1), (6e-4, 0.0), (0.0, 6e-3), (3e-4, 3e-3))[trial % 4]
        x1 = x0 + rng.uniform(0, move, size=(n, 1)) * _unit(rng, n)[:, 1:]
        q1 = _turned(rng, q0, rng.uniform(0, turn, size=n))
        has_fast = bool(trial % 3 == 0)
        fast = rng.random(n) < 0.5
        out = [np.full(8, -7, np.int64) for _ in range(6)]
        sw, R1 = np.empty(n), np.empty((n, 3, 3))
        nb, npl, ns = flight.end_pose_pairs(x0, q0, x1, q1, model.bound_radius, lim, has_fast, fast,
                                            Pairs(pi=pi, pj=pj, bp=bp, pk=pk, bs=bp[:0], sk=pk[:0]),
                                            EndPose(*out, sw=sw, R1=R1))
        # the mask selection it replaced (engine.ccd before), and its R1
        sel = lambda a: a if not has_fast else fast[a]  # noqa: E731
        fb = (sw[pi] + sw[pj] > lim) & (sel(pi) | sel(pj) if has_fast else True)
        fp = (sw[bp] > lim) & (sel(bp) if has_fast else True)
        assert (nb, npl, ns) == (int(fb.sum()), int(fp.sum()), 0)
        assert np.array_equal(out[0][:nb], pi[fb]) and np.array_equal(out[1][:nb], pj[fb])
        assert np.array_equal(out[2][:npl], bp[fp]) and np.array_equal(out[3][:npl], pk[fp])
        if nb + npl:
            assert np.array_equal(R1, quat_to_matrix(q1))  # bit for bit
        # conservative: a pair left out for its motion closed by at most lim
        gb0, gp0 = _gaps(model, x0, q0, pi, pj, bp, pk)
        gb1, gp1 = _gaps(model, x1, q1, pi, pj, bp, pk)
        moved_b = sw[pi] + sw[pj] > lim
        moved_p = sw[bp] > lim
        for k in range(pi.size):
            if not moved_b[k]:
                skipped += 1
                assert gb1[k] >= gb0[k] - lim, (trial, k, gb0[k], gb1[k], sw[pi[k]] + sw[pj[k]])
            else:
                selected += 1
        for k in range(bp.size):
            if not moved_p[k]:
                skipped += 1
                assert gp1[k] >= gp0[k] - lim, (trial, k, gp0[k], gp1[k], sw[bp[k]])
            else:
                selected += 1
    assert skipped > 100 and selected > 100  # both sides of the tolerance exercised
