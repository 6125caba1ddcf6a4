"""Part of the contract between the staged and the fused step (stated in
tests/test_engine_steady.py): contact scenes with a gyroscopic stage take
the fused steady step (engine/fused/steady.py with engine/fused/gyro.py): each of the three
gyroscopic treatments (the energy-conserving rotation, the implicit
update, the explicit torque) runs inside the fused call at its place of
the staged pipeline, and every recorded frame is bit for bit the staged
step's (one ``pipeline.step`` per step with ``Profile.by_stage``), whether
the steps run one fused call each or many to a compiled loop
(``pipeline.advance``).  Likewise rolling friction with friction stops
(engine/fused/stops.py: the stop gate's rolling half)."""

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene
from physbench.engine import pipeline
from physbench.engine.fused.steady import FREE_NAME, NAME
from physbench.engine.fused.gyro import ENERGY, IMPLICIT, NO_GYRO
from physbench.engine.gyroscopic import no_gyro


def _frames(eng, steps, by_stage):
    """One pipeline.step per step (fused calls unless ``by_stage``), each
    step's state recorded: (pos, quat, vel, angvel) arrays (steps, n, 3|4)."""
    eng.profile.by_stage = by_stage
    out = []
    for _ in range(steps):
        pipeline.step(eng.model, eng.state, eng.stages, eng.profile)
        s = eng.state
        out.append([a.copy() for a in (s.x, s.q, s.v, s.w)])
    return [np.array([f[i] for f in out]) for i in range(4)]


def _looped(eng, steps, chunks=(7, 1, 50)):
    """pipeline.advance over blocks of the given lengths, recording."""
    nb = eng.model.n
    rec = (np.full((steps, nb, 3), np.nan), np.full((steps, nb, 4), np.nan), np.full((steps, nb, 3), np.nan),
           np.full((steps, nb, 3), np.nan))
    k, i = 0, 0
    while k < steps:
        m = min(chunks[i % len(chunks)], steps - k)
        pipeline.advance(eng.model, eng.state, eng.stages, eng.profile, m, tuple(a[k:k + m] for a in rec))
        k += m
        i += 1
    return list(rec)


def _plan(eng):
    """The engine's plan, made before its first step."""
    ctx = pipeline.context(eng.model, eng.state, eng.profile)
    return pipeline._plan_of(eng.model, ctx, eng.stages)


def _calls(eng, name):
    return eng.profile.as_dict().get(name, {}).get("calls", 0)


CASES = [
    # (scene, settings, steps, the gyroscopic stage's code, explicit torque, share of the steps fused)
    ("friction.cylinder_rolls", {}, 240, ENERGY, False, 0.9),
    ("friction.cylinder_rolls", {"dt": 0.064}, 31, ENERGY, False, 0.9),
    ("friction.cylinder_rolls", {"gyroscopic": "implicit", "integrator": "midpoint"}, 240, IMPLICIT, False, 0.9),
    ("friction.cylinder_rolls", {"gyroscopic": "explicit", "integrator": "heun"}, 240, NO_GYRO, True, 0.9),
    ("friction.capsule_spins_to_rest", {}, 120, ENERGY, False, 0.9),
    ("friction.capsule_spins_to_rest", {"dt": 0.032, "integrator": "semi_implicit_euler"}, 16, ENERGY, False, 0.9),
    ("friction.capsule_spins_to_rest", {"gyroscopic": "implicit", "integrator": "rk4"}, 120, IMPLICIT, False, 0.9),
    ("friction.capsule_spins_to_rest", {"gyroscopic": "explicit"}, 120, NO_GYRO, True, 0.9),
    ("friction.cylinder_slips", {"dt": 0.016}, 120, ENERGY, False, 0.9),
    ("stacking.log_pile", {"dt": 0.016}, 120, ENERGY, False, 0.9),
]


@pytest.mark.parametrize("sid,settings,steps,code,torque,share", CASES,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(CASES)])
def test_gyroscopic_contact_scene_takes_the_fused_step_with_the_staged_bits(sid, settings, steps, code, torque,
                                                                            share):
    scene = load_scene(sid)
    ref = engine_for(scene, settings)
    staged = _frames(ref, steps, True)
    assert _calls(ref, "gyroscopic") == steps  # the scene has the stage (or the torque), every step
    assert NAME not in ref.profile.as_dict() and FREE_NAME not in ref.profile.as_dict()

    one = engine_for(scene, settings)
    fused = _plan(one).fast
    assert fused is not None  # decided once, with the plan: the scene is covered
    assert fused.gyro.code == code
    assert (fused.fly.fm.g_idx.size > 0) == torque  # (the explicit torque: a force stage)
    frames = _frames(one, steps, False)
    for x, y in zip(staged, frames):
        assert np.array_equal(x, y)  # every frame, bit for bit
    fused_calls = _calls(one, NAME) + _calls(one, FREE_NAME)
    assert fused_calls >= share * steps
    # the stage runs by itself only where a step is not fused
    assert _calls(one, "gyroscopic") <= (1 - share) * steps

    many = engine_for(scene, settings)
    looped = _looped(many, steps)
    for x, y in zip(staged, looped):
        assert np.array_equal(x, y)
    assert _calls(many, NAME) + _calls(many, FREE_NAME) >= share * steps


@pytest.mark.parametrize("sid,settings,steps", [
    ("friction.cylinder_rolls", {}, 60),
    ("friction.cylinder_rolls", {"gyroscopic": "implicit"}, 60),
    ("friction.capsule_spins_to_rest", {"gyroscopic": "explicit", "integrator": "rk4"}, 60),
])
def test_the_comparison_sees_the_gyroscopic_stage(sid, settings, steps):
    """The comparison above can fail: the fused step with its gyroscopic
    part switched off (the plan's gyroscopic arrays emptied before the
    first step; for the explicit torque, the free flight's force model's)
    gives other frames than the staged step."""
    scene = load_scene(sid)
    staged = _frames(engine_for(scene, settings), steps, True)
    eng = engine_for(scene, settings)
    fused = _plan(eng).fast
    z3, zi = np.zeros((0, 3)), np.zeros(0, np.int64)
    if fused.fly.fm.g_idx.size:
        fused.fly.ig = fused.fly.ig._replace(fm=fused.fly.fm._replace(g_idx=zi, g_I=z3))
        fused.fly._pack_ctx = None  # (the flight's Pack is made again from it)
    else:
        fused.gyro = no_gyro()
        fused._ks_key = None  # (the engine made its settings Pack at build: pipeline.prepare)
    off = _frames(eng, steps, False)
    assert _calls(eng, NAME) >= 0.5 * steps
    assert not all(np.array_equal(x, y) for x, y in zip(off, staged))


ROLLING = [
    ("friction.rolling_resistance", None, {}),
    ("friction.rolling_resistance", "uphill_5deg", {}),
    ("friction.rolling_resistance", "uphill_5deg", {"dt": 0.016}),
    ("friction.cylinder_rolling_resistance", None, {"dt": 0.016}),
    ("friction.cylinder_rolling_resistance", "uphill_5deg", {"dt": 0.016}),
]


@pytest.mark.parametrize("sid,variant,settings", ROLLING, ids=[f"{c[0]}-{i}" for i, c in enumerate(ROLLING)])
def test_rolling_friction_with_stops_takes_the_fused_step(sid, variant, settings):
    """Rolling friction with friction stops (engine/fused/stops.py): the
    fused step's gate falls back to the staged step wherever the staged
    solve's stop test could find a rolling stop; every frame of the whole
    run is the staged step's, bit for bit, the friction stops counted
    alike, and nearly every step fused."""
    scene = load_scene(sid, variant)
    steps = int(round(scene.duration / settings.get("dt", scene.dt)))
    ref = engine_for(scene, settings)
    staged = _frames(ref, steps, True)
    one = engine_for(scene, settings)
    fused = _plan(one).fast
    assert fused is not None
    frames = _frames(one, steps, False)
    for x, y in zip(staged, frames):
        assert np.array_equal(x, y)
    assert _calls(one, NAME) + _calls(one, FREE_NAME) >= 0.9 * steps
    many = engine_for(scene, settings)
    looped = _looped(many, steps)
    for x, y in zip(staged, looped):
        assert np.array_equal(x, y)
    for eng in (one, many):
        assert eng.profile.counters.get("friction_stops") == ref.profile.counters.get("friction_stops")
    if variant == "uphill_5deg":  # rolls up, stops (a rolling stop: no slip), rolls back
        assert ref.profile.counters.get("friction_stops", 0) >= 1


def test_the_comparison_sees_the_rolling_stop(monkeypatch):
    """The comparison above can fail: with the fused step's stop gate
    closed (its step flags' stops_gate False) the ball rolling uphill is
    not cut at its rolling stop in a fused step, and its frames differ
    from the staged step's.  (It rolls without slipping: only the gate's
    rolling half, engine/fused/stops.py, sees the stop.)"""
    from physbench.engine.fused.steady import SteadyStep

    scene = load_scene("friction.rolling_resistance", "uphill_5deg")
    settings = {"dt": 0.016}
    steps = int(round(scene.duration / 0.016))
    staged = _frames(engine_for(scene, settings), steps, True)
    real = SteadyStep.flags

    def no_gate(self, ctx, warm_any, warm_on, store_on):
        f = real(self, ctx, warm_any, warm_on, store_on)
        return f[:3] + (False,) + f[4:]

    monkeypatch.setattr(SteadyStep, "flags", no_gate)
    eng = engine_for(scene, settings)
    off = _frames(eng, steps, False)
    assert _calls(eng, NAME) >= 0.9 * steps
    assert not all(np.array_equal(x, y) for x, y in zip(off, staged))


def test_the_fused_energy_conserving_rotation_allocates_nothing():
    """The fused step's energy-conserving rotation runs on the plan's kept
    work arrays (fused.gyro.gyro_items, gyroscopic.energy_rotation_into):
    50 calls in compiled code allocate what one does (numba's allocation
    counter), where the same kernel on work arrays made per call (what the
    stage and the flight step did before) allocates per call."""
    from numba import njit
    from numba.core.runtime import _nrt_python, rtsys

    from physbench.engine.gyroscopic import Gyro, energy_rotation_into
    from physbench.engine.integrate import EnergyConservingRotation

    @njit
    def kept(n, gy, R0, T_mean, w0, q0, h, q1, w, w_free, u_ang):
        for _ in range(n):
            energy_rotation_into(gy, R0, T_mean, w0, q0, h, 0.5, q1, w, w_free, u_ang)

    @njit
    def made(n, gy, R0, T_mean, w0, q0, h, q1, w, w_free, u_ang):
        g = gy.idx.shape[0]
        for _ in range(n):
            fresh = Gyro(gy.code, gy.idx, gy.I, gy.inv_I, gy.E, gy.yoshida, gy.ymax, np.empty((4, g, 3)),
                         np.empty((g, 4)), np.empty((g, 3, 3)), gy.J, gy.f)
            energy_rotation_into(fresh, R0, T_mean, w0, q0, h, 0.5, q1, w, w_free, u_ang)

    eng = engine_for(load_scene("friction.capsule_spins_to_rest"), {})
    fused = _plan(eng).fast
    gy = fused.gyro
    assert gy.code == ENERGY and gy.idx.size == 1 and gy.wk.shape == (4, 1, 3)
    assert any(type(s) is EnergyConservingRotation for s in eng.stages)
    n = eng.model.n
    s = eng.state
    R0 = np.zeros((n, 3, 3))
    R0[:, 0, 0] = R0[:, 1, 1] = R0[:, 2, 2] = 1.0
    args = (gy, R0, np.zeros((n, 3)), s.w.copy(), s.q.copy(), 1 / 240, np.zeros((n, 4)), np.zeros((n + 1, 3)),
            np.zeros((n, 3)), np.zeros((n, 3)))
    _nrt_python.memsys_enable_stats()

    def allocations(f, k):
        f(1, *args)  # (compiled)
        before = rtsys.get_allocation_stats().alloc
        f(k, *args)
        return rtsys.get_allocation_stats().alloc - before

    assert allocations(kept, 50) == allocations(kept, 1)
    assert allocations(made, 50) > allocations(made, 1)


@pytest.mark.parametrize("scene, settings", [
    (scene, {} if g is None else {"gyroscopic": g})
    for scene in ("friction.cylinder_rolls", "friction.capsule_spins_to_rest", "gyroscopic.dzhanibekov")
    for g in (None, "implicit", "explicit")] + [
    ("forces.spring_pair", {}), ("forces.spring_pair", {"integrator": "rk4"}), ("forces.damped_spring", {}),
    ("friction.cylinder_rolls", {"integrator": "rk4"}), ("stacking.cans", {}), ("stacking.log_pile", {})])
def test_every_gyroscopic_setting_steps_without_allocating(scene, settings):
    """Steps taken n at a time (``eng.step(n)``: one compiled loop,
    engine/fused/) allocate no array per step in compiled code (numba's
    allocation counter) for every gyroscopic treatment and with springs:
    200 steps allocate exactly as many arrays as 100 (the loop's argument
    unboxing).  Before, per step: the energy-conserving rotation's three
    work arrays in the flight step, the implicit update's matrices and
    solves (7 a step on a rolling cylinder), the explicit torque's
    normalised quaternions at the integrator's intermediate states, the
    springs' forces, the capsule's (2) and cylinder's (1) collision
    scratch, the cylinder pairs' (cans 278, log pile 165 a step)."""
    from numba.core.runtime import _nrt_python, rtsys

    _nrt_python.memsys_enable_stats()
    eng = engine_for(load_scene(scene), settings)
    eng.step(20)
    before = sum(_calls(eng, k) for k in (NAME, FREE_NAME, "flight_step"))
    counts = []
    for n in (100, 200):
        a0 = rtsys.get_allocation_stats().alloc
        eng.step(n)
        counts.append(rtsys.get_allocation_stats().alloc - a0)
    # the steps ran as fused (compiled-loop) steps
    assert sum(_calls(eng, k) for k in (NAME, FREE_NAME, "flight_step")) - before >= 0.9 * 300
    assert counts[1] == counts[0], counts
