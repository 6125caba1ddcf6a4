"""The end-pose check leaves out pairs whose end pose provably holds no
missed impact (engine.ccd_end.end_pose_clear), so rolling and sliding
contacts stay in the steady step's one compiled call.

Pinned: (1) sound -- for random spheres, boxes, capsules and cylinders
(body pairs, a plane, a tilted plane, a static box) moved and turned by
random amounts around the tolerance, every pair it leaves out has no
contact deeper than ``lim`` at the end pose (the end-pose collision of
engine.ccd.missed_impacts would find nothing in it), the pairs it keeps
are the moved ones in their order, and a planted pair ending 1 mm deep is
kept; (2) a ball rolling and a block sliding on the floor finish their
steps in the fused call (on the code before, every step returned to the
Python CCD stage: 187 of 188 steps of the rolling ball); (3) a ball that
ends a step inside the floor with no contact row that saw it coming (a
missed impact) is still found and searched for.
"""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene
from physbench.engine import ccd, ccd_end, flight
from physbench.engine.collision import collide_pairs
from physbench.engine.geometry import EndPose, Pairs, shapes_of, statics_of
from physbench.engine.mathutil import quat_to_matrix

SCENE = """
[scenario]
family = "t"
title = "end pose clear"
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
name = "c0"
shape = "capsule"
radius = 0.03
half_length = 0.06
mass = 1.0
position = [0.2, 0.2, 1.0]

[[body]]
name = "y0"
shape = "cylinder"
radius = 0.05
half_length = 0.04
mass = 1.0
position = [0.4, 0.2, 1.0]

[[static]]
name = "ground"
shape = "plane"
normal = [0.0, 0.0, 1.0]
offset = 0.0

[[static]]
name = "slope"
shape = "plane"
normal = [0.6, 0.0, 0.8]
offset = -0.05

[[static]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
position = [0.0, 0.0, -0.05]
"""


def _unit(rng, k):
    q = rng.normal(size=(k, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _geometry(model):
    return shapes_of(model), statics_of(model)


def _deep(model, X, R, pi, pj, bp, pk, bs, sk, lim):
    """The pairs with a contact deeper than ``lim`` at the pose, as the
    end-pose collision of ccd.missed_impacts finds them (margin -lim)."""
    c = collide_pairs(model, X, R, pi, pj, (bp, pk), (bs, sk), np.full(pi.size, -lim), np.full(bp.size, -lim),
                      np.full(bs.size, -lim))
    n = model.n
    deep = set()
    for a, b, s in zip(c.a, c.b, c.sidx):
        deep.add((int(min(a, b)), int(max(a, b)), -1) if b < n else (int(a), n, int(s)))
    return deep


def _model(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text(textwrap.dedent(SCENE))
    return engine_for(load_scene(p)).model


@pytest.mark.parametrize("seed", range(3))
def test_end_pose_clear_leaves_out_only_pairs_with_nothing_deep(tmp_path, seed):
    model = _model(tmp_path)
    n = model.n
    geo = _geometry(model)
    rng = np.random.default_rng(seed)
    pi, pj = (np.array(a, np.int64) for a in np.triu_indices(n, 1))
    bp = np.repeat(np.arange(n, dtype=np.int64), 2)
    pk = np.tile(np.arange(2, dtype=np.int64), n)
    bs = np.arange(n, dtype=np.int64)
    sk = np.zeros(n, np.int64)
    sidx_plane = np.asarray(model.plane_static, np.int64)
    sidx_box = np.asarray(model.sbox_static, np.int64)
    lim = 3e-4
    left_out = kept_deep = 0
    for trial in range(400):
        # bodies placed so that their surfaces end around the tolerance:
        # each sits on the floor (or a partner) at a random depth in
        # [-2 lim, 2 lim] after a random move and turn
        q0 = _unit(rng, n)
        x0 = rng.uniform([-0.15, -0.15, 0.0], [0.15, 0.15, 0.15], size=(n, 3))
        q1 = _unit(rng, n) if trial % 2 else q0 + rng.normal(0, 0.01, size=(n, 4))
        q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
        R1 = quat_to_matrix(q1)
        x1 = x0 + rng.normal(0, 0.002, size=(n, 3))
        for k in range(n):  # the floor's gap of body k at the end: random around -lim
            c = collide_pairs(model, x1, R1, pi[:0], pj[:0], (bp[2 * k:2 * k + 1], pk[2 * k:2 * k + 1]),
                              (bs[:0], sk[:0]), np.zeros(0), np.full(1, np.inf), np.zeros(0))
            x1[k, 2] += -float(c.gap.min()) + rng.uniform(-2 * lim, 2 * lim)
        has_fast = trial % 5 == 0
        fast = rng.random(n) < 0.5
        sw = np.empty(n)
        out = [np.full(64, -7, np.int64) for _ in range(6)]
        R = np.empty((n, 3, 3))
        nb, npl, ns = flight.end_pose_pairs(x0, q0, x1, q1, model.bound_radius, lim, has_fast, fast,
                                            Pairs(pi=pi, pj=pj, bp=bp, pk=pk, bs=bs, sk=sk),
                                            EndPose(*[o.copy() for o in out], sw=sw, R1=R.copy()))
        moved_b = [(int(i), int(j)) for i, j in zip(pi, pj) if sw[i] + sw[j] > lim and (not has_fast or fast[i]
                                                                                       or fast[j])]
        moved_p = [(int(b), int(k)) for b, k in zip(bp, pk) if sw[b] > lim and (not has_fast or fast[b])]
        moved_s = [(int(b), int(k)) for b, k in zip(bs, sk) if sw[b] > lim and (not has_fast or fast[b])]
        assert (nb, npl, ns) == (len(moved_b), len(moved_p), len(moved_s))
        mb, mp, ms = ccd_end.end_pose_candidates(x0, q0, x1, q1, *geo, lim, has_fast, fast,
                                                 Pairs(pi=pi, pj=pj, bp=bp, pk=pk, bs=bs, sk=sk), EndPose(*out, sw, R))
        keep_b = list(zip(out[0][:mb].tolist(), out[1][:mb].tolist()))
        keep_p = list(zip(out[2][:mp].tolist(), out[3][:mp].tolist()))
        keep_s = list(zip(out[4][:ms].tolist(), out[5][:ms].tolist()))
        # what it keeps: moved pairs, in their order
        assert keep_b == [p for p in moved_b if p in keep_b]
        assert keep_p == [p for p in moved_p if p in keep_p]
        assert keep_s == [p for p in moved_s if p in keep_s]
        if mb + mp + ms:
            assert np.array_equal(R, quat_to_matrix(q1))  # bit for bit
        deep = _deep(model, x1, R1, pi, pj, bp, pk, bs, sk, lim)
        for i, j in moved_b:
            if (i, j) not in keep_b:
                left_out += 1
                assert (i, j, -1) not in deep, (trial, i, j)
            elif (i, j, -1) in deep:
                kept_deep += 1
        for (b, k) in moved_p:
            if (b, k) not in keep_p:
                left_out += 1
                assert (b, n, int(sidx_plane[k])) not in deep, (trial, b, k)
            elif (b, n, int(sidx_plane[k])) in deep:
                kept_deep += 1
        for (b, k) in moved_s:
            if (b, k) not in keep_s:
                left_out += 1
                assert (b, n, int(sidx_box[k])) not in deep, (trial, b, k)
    assert left_out > 300 and kept_deep > 50  # both sides exercised


def test_end_pose_clear_keeps_a_pair_ending_deep(tmp_path):
    """A planted case: every body 1 mm inside the floor at the end pose,
    apart from it at the start -- each plane pair is kept."""
    model = _model(tmp_path)
    n = model.n
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    R = quat_to_matrix(q)
    x1 = np.zeros((n, 3))
    x1[:, 0] = np.arange(n) * 0.5 + 2.0
    bp, pk = np.arange(n, dtype=np.int64), np.zeros(n, np.int64)
    c = collide_pairs(model, x1, R, np.zeros(0, np.int64), np.zeros(0, np.int64), (bp, pk),
                      (np.zeros(0, np.int64),) * 2, np.zeros(0), np.full(n, np.inf), np.zeros(0))
    for k in range(n):
        x1[k, 2] -= float(c.gap[c.a == k].min()) + 1e-3
    x0 = x1 + [0.0, 0.0, 0.01]
    z = np.zeros(0, np.int64)
    out = [np.full(n, -7, np.int64) for _ in range(6)]
    mb, mp, ms = ccd_end.end_pose_candidates(x0, q, x1, q.copy(), *_geometry(model), 3e-4, False,
                                             np.zeros(n, np.bool_), Pairs(pi=z, pj=z, bp=bp, pk=pk, bs=z, sk=z),
                                             EndPose(*out, np.empty(n), np.empty((n, 3, 3))))
    assert (mb, mp, ms) == (0, n, 0) and np.array_equal(out[2][:n], bp)


@pytest.mark.parametrize("sid", ["friction.ball_rolls", "friction.block_slides"])
def test_rolling_and_sliding_steps_stay_in_the_fused_call(sid):
    """A ball rolling (a block sliding) on the floor moves its surface by
    more than the end-pose tolerance every step, but ends it resting within
    the slop: its steps finish in the steady step's one call.  Before, the
    fused call returned CCD every step and the Python CCD stage collided
    the end pose to find nothing (187 of 188 steps of the rolling ball at
    dt 0.008)."""
    eng = engine_for(load_scene(sid), {"dt": 0.008})
    eng.step(150)
    prof = eng.profile.as_dict()
    assert prof["steady_step"]["calls"] >= 149
    assert prof["ccd"]["calls"] <= 1  # the first, staged step's


def test_a_missed_impact_on_the_floor_is_still_found(tmp_path, monkeypatch):
    """A ball whose contact row does not see it closing (the row is
    dropped before the CCD stage: no impact row) and that ends the step
    1 mm inside the floor is a missed impact: the end-pose check keeps its
    pair and missed_impacts finds it."""
    p = tmp_path / "drop.toml"
    p.write_text(textwrap.dedent("""
        [scenario]
        family = "t"
        title = "drop"
        duration = 0.1
        dt = 0.01
        effects = ["gravity", "contact"]

        [[body]]
        name = "s0"
        shape = "sphere"
        radius = 0.05
        mass = 1.0
        position = [0.0, 0.0, 0.0505]
        velocity = [0.3, 0.0, -0.15]

        [[static]]
        name = "ground"
        shape = "plane"
        normal = [0.0, 0.0, 1.0]
        offset = 0.0
    """))
    eng = engine_for(load_scene(p), {"restitution_threshold": 10.0})
    found = []
    real = ccd.missed_impacts

    def spy(model, state, ctx, skip, fast=None):
        # the end pose 1 mm deep, as if no row had seen the approach
        ctx.x1[0, 2] = 0.05 - 1e-3
        ctx.contacts = None
        out = real(model, state, ctx, skip, fast)
        found.append(len(out))
        return []

    monkeypatch.setattr(ccd, "missed_impacts", spy)
    # the staged CCD stage is the one spied on: the step runs stage by stage
    # (the build primes a resting start's first step as the fused steady
    # call, whose own end-pose check sees the real, shallow end pose)
    eng.profile.by_stage = True
    eng.step(1)
    assert found and found[0] == 1


DATA = __import__("pathlib").Path(__file__).parent / "data"


def _same(r1, r2):
    if len(r1) != len(r2):
        return False
    for m1, m2 in zip(r1, r2):
        for u, v in zip(m1, m2):
            if isinstance(u, np.ndarray) or isinstance(v, np.ndarray):
                if u is None or v is None or not np.array_equal(u, v):
                    return False
            elif u != v:
                return False
    return True


@pytest.mark.parametrize("case", ["missed_impact_beside_an_overlap", "missed_impact_capsule_box",
                                  "missed_impact_of_an_impact_pair", "missed_impact_onto_touching_box",
                                  "impact_segment_slides_onto_box", "spheres_landing"])
def test_missed_candidates_keep_every_missed_impact(monkeypatch, case):
    """The compiled pre-selection (ccd_end.missed_candidates, and before it
    ccd_end.missed_any, the same check in one call answering "none") lets
    the Python rule of ccd.missed_impacts run over its candidate pairs
    only: at every call, the result equals the rule's over every pair (no
    compiled answer, the candidates all True), and missed impacts are
    found."""
    from physbench.harness import bench

    if case == "spheres_landing":
        scene, settings, steps = bench.spheres_scene(100), {"iterations": 10}, 30
    else:
        scene, settings, steps = load_scene(DATA / f"{case}.toml"), {}, None
    eng = engine_for(scene, settings)
    real_cand, real = ccd.missed_candidates, ccd.missed_impacts

    def every(*args):
        m = args[1].gap.shape[0]  # the end-pose contacts
        args[-1][:m] = True
        return m

    calls = {"n": 0, "found": 0, "pruned": 0}

    def spy(model, state, ctx, skip, fast=None):
        with monkeypatch.context() as mp:
            mp.setattr(ccd, "_missed_any", lambda *a: -1)
            mp.setattr(ccd, "missed_candidates", every)
            ref = real(model, state, ctx, skip, fast)
        out = real(model, state, ctx, skip, fast)
        assert _same(out, ref), (calls, out, ref)
        calls["n"] += 1
        calls["found"] += len(out)
        return out

    monkeypatch.setattr(ccd, "missed_impacts", spy)
    eng.step(steps if steps is not None else int(round(min(scene.duration, 1.0) / eng.model.dt)))
    assert calls["n"] > 0
    if case.startswith("missed"):
        assert calls["found"] >= 1


def test_landing_spheres_skip_the_python_rule(monkeypatch):
    """Landing spheres overlap the floor and their neighbours beyond the
    tolerance at the end pose, every pair touching at the start (a sphere
    has one feature): no contact is a candidate, and the Python rule (its
    pair codes, groups, per-pair numpy) does not run.  On the code before
    it ran for every such step (~140 us a step of the landing's first 30)."""
    from physbench.harness import bench

    eng = engine_for(bench.spheres_scene(100), {"iterations": 10})
    inside = {"on": False, "codes": 0, "calls": 0}
    real, codes = ccd.missed_impacts, ccd._pair_codes

    def spy(*a, **k):
        inside["on"] = True
        inside["calls"] += 1
        try:
            return real(*a, **k)
        finally:
            inside["on"] = False

    def count(*a, **k):
        inside["codes"] += inside["on"]
        return codes(*a, **k)

    monkeypatch.setattr(ccd, "missed_impacts", spy)
    monkeypatch.setattr(ccd, "_pair_codes", count)
    # every step staged, so the staged CCD stage spied on runs in each
    # whatever the fast path's door tries (engine/fused: its backoff)
    eng.profile.by_stage = True
    eng.step(30)
    assert inside["calls"] >= 10
    assert inside["codes"] == 0
    assert eng.profile.as_dict()["counters"].get("missed_impacts", 0) == 0
