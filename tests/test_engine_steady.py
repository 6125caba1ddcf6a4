"""The contract between the staged and the fused step (engine/fused/).

The engine has two paths for a step: the staged step (engine/pipeline.py,
one stage object after the other) and the fast path behind one door
(``engine.fused.advance``: the steady, contact-free and flight steps as
compiled calls, runs of them as one compiled loop).  The contract:

1. a step on the fast path gives the staged step's bits: every recorded
   frame and the final state, bit for bit, on every kind of step either
   path meets (resting, sliding, rolling, landing, impacts, friction
   stops, every integrator and gyroscopic treatment);
2. it leaves the staged step's bookkeeping: the profile's calls and
   counters (``contact_rows``, ``solver_sweeps``), ``state.t``,
   ``state.steps``, the warm-start cache, the contacts;
3. which scenes the fast path covers is decided once, with the plan, and
   where it runs it runs for most steps of a steady scene.

This module pins the contract for the steady step (and 3.); with it,
tests/test_engine_steady_gyro.py (the gyroscopic stages, rolling friction
with stops) and tests/test_engine_loop.py (runs of steps as one loop, the
contact-free and flight steps) are the contract.  A physics change to a
stage that the fused step also runs must keep them passing: they compare
the two paths, not fixed numbers (tests/test_determinism.py pins those)."""

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene
from physbench.engine.fused import SteadyStep
from physbench.harness.bench import column_scene, spheres_scene


def _final(scene, settings, by_stage: bool, steps: int):
    eng = engine_for(scene, settings)
    eng.profile.by_stage = by_stage
    eng.step(steps)
    s = eng.state
    return eng, [a.copy() for a in (s.x, s.q, s.v, s.w)]


@pytest.mark.parametrize("sid,settings", [
    ("stacking.column_5", {}),
    ("stacking.pyramid", {}),
    ("stacking.mixed_bin", {}),
    ("friction.block_thrown_uphill", {}),
    ("friction.box_slides_to_rest", {}),
    ("billiards.newtons_cradle", {}),
    ("stacking.column_5", {"integrator": "semi_implicit_euler", "ccd": "toi", "direct_start": False}),
    ("stacking.column_5", {"ccd": "off"}),
])
def test_fused_step_is_bit_identical_to_the_staged_step(sid, settings):
    scene = load_scene(sid)
    steps = int(round(min(scene.duration, 0.5) / scene.dt))
    fused, a = _final(scene, settings, False, steps)
    staged, b = _final(scene, settings, True, steps)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    assert "steady_step" not in staged.profile.as_dict()
    # the counters the stages keep are kept by the fused step alike
    assert fused.profile.counters.get("contact_rows") == staged.profile.counters.get("contact_rows")
    assert fused.profile.counters.get("solver_sweeps") == staged.profile.counters.get("solver_sweeps")


@pytest.mark.parametrize("make,steps,share", [(lambda: column_scene(10), 240, 0.9), (lambda: spheres_scene(100), 240, 0.3)])
def test_steady_scenes_step_in_one_call(make, steps, share):
    """A resting column steps almost only through the fused call; a sphere
    cloud landing on a plane at least in part (landings are impacts and new
    contact graphs: stage by stage)."""
    eng, a = _final(make(), {}, False, steps)
    p = eng.profile.as_dict()
    assert p["steady_step"]["calls"] >= share * steps
    _, b = _final(make(), {}, True, steps)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("sid,settings,covered", [
    ("stacking.column_5", {}, True),
    ("stacking.column_5", {"position_correction": "baumgarte"}, False),
    ("stacking.column_5", {"contact_model": "penalty"}, False),
    ("gyroscopic.dzhanibekov", {}, False),  # no contact: nothing to fuse
    ("forces.drag_linear_fall", {}, False),
])
def test_plan_decides_once_what_the_fused_step_covers(sid, settings, covered):
    eng = engine_for(load_scene(sid), settings)
    eng.step(2)
    plan = eng.state.ctx.plan
    assert isinstance(plan.fast, SteadyStep) == covered


def _kernel_allocations(settings: dict, steps: int) -> int:
    """Arrays the compiled code allocated (numba's NRT counter) in ``steps``
    steady steps of the 10-box column, after 240 steps to come to rest."""
    from numba.core.runtime import _nrt_python, rtsys

    _nrt_python.memsys_enable_stats()
    eng = engine_for(column_scene(10), settings)
    eng.step(240)
    before = rtsys.get_allocation_stats().alloc
    eng.step(steps)
    assert eng.profile.as_dict()["steady_step"]["calls"] >= 0.9 * (240 + steps)
    return rtsys.get_allocation_stats().alloc - before


@pytest.mark.parametrize("sparse", [False, True])
def test_steady_direct_start_allocates_nothing(monkeypatch, sparse):
    """The direct start runs on the solve stage's kept work arrays: 100
    steady steps of the resting column with it on allocate no more arrays
    in compiled code than with it off (it allocated 18 a step before:
    the normal matrix, the active set's and the ordering's arrays), with the
    dense start and with the sparse one (every start sparse: its band
    storage grows once, then is kept)."""
    import physbench.engine.solver as solver

    if sparse:
        monkeypatch.setattr(solver, "DIRECT_MAX_ROWS", 0)
    on = _kernel_allocations({}, 100)
    off = _kernel_allocations({"direct_start": False}, 100)
    assert on == off


@pytest.fixture(scope="module")
def _unboxed():
    """A compiled call that does nothing with its arguments: what unboxing
    them costs in compiled allocations (numba makes one NRT record per
    array argument handed in from Python)."""
    from numba import njit

    @njit
    def unboxed(*args):
        return 0

    return unboxed


def _fused_allocations(monkeypatch, unboxed, eng, steps: int) -> tuple[int, int]:
    """(fused calls that committed, compiled allocations inside them beyond
    the unboxing of their arguments) over ``steps`` steps of ``eng``."""
    import physbench.engine.fused.steady as steady
    from numba.core.runtime import _nrt_python, rtsys

    _nrt_python.memsys_enable_stats()
    kernel = steady.steady_loop  # (SteadyStep.run's one step: n = 1)
    seen = [0, 0]

    def counted(*args):
        a0 = rtsys.get_allocation_stats().alloc
        unboxed(*args)
        a1 = rtsys.get_allocation_stats().alloc
        out = kernel(*args)
        a2 = rtsys.get_allocation_stats().alloc
        seen[0] += out[0] == 1  # (one step done: the try committed)
        seen[1] += (a2 - a1) - (a1 - a0)
        return out

    monkeypatch.setattr(steady, "steady_loop", counted)
    for _ in range(steps):  # one step a call: the fused try from Python (eng.step(n) loops compiled)
        eng.step(1)
    monkeypatch.setattr(steady, "steady_loop", kernel)
    return seen[0], seen[1]


@pytest.mark.parametrize("integrator", ["explicit_euler", "semi_implicit_euler", "midpoint", "heun", "rk4",
                                        "velocity_verlet"])
@pytest.mark.parametrize("scene,settle", [("column", 240), ("spheres", 240)])
def test_steady_step_allocates_nothing(monkeypatch, _unboxed, scene, settle, integrator):
    """A steady step's whole fused call (engine/fused/steady.py::steady_kernel:
    free flight, broad and narrow phase, the solve stage, the position
    update, the end-pose check, the commit) allocates no array in compiled
    code beyond unboxing its arguments, with every integrator it covers,
    on the resting 10-box column (box-box and box-plane pairs) and on a
    settled pile of 100 spheres (sphere-sphere and sphere-plane pairs).
    It allocated 31 arrays a column step before with rk4, 25 a sphere
    pile step (the sweep's spread and numba's sort of the pair codes; the
    free flight's rotations, velocity sum and slope copies; two 3-vectors
    of the swept boxes; eleven scratch arrays of the box-box kernel; ten
    3-vectors and rows of the row preparation and classification).
    Explicit Euler's resting scenes commit one fused call in about six
    steps (the others fall back to the staged step): its failed calls
    count too."""
    make = (lambda: column_scene(10)) if scene == "column" else (lambda: spheres_scene(100))
    eng = engine_for(make(), {"integrator": integrator})
    eng.step(settle)
    steps = 60
    done, allocations = _fused_allocations(monkeypatch, _unboxed, eng, steps)
    # the fused call ran and committed (the count below is not vacuous)
    assert done >= (0.15 if integrator == "explicit_euler" else 0.9) * steps
    assert allocations == 0


def _islands_matrix(rng, k: int, size: int) -> np.ndarray:
    """A symmetric positive definite (k, k) matrix of islands of about
    ``size`` rows in shuffled order, each island's rows coupled in a chain
    (a contact graph's normal matrix: zeros but on the shared bodies)."""
    A = np.zeros((k, k))
    perm = rng.permutation(k)
    for s in range(0, k, size):
        rows = perm[s:s + size]
        for t, i in enumerate(rows):
            A[i, i] = rng.uniform(1.0, 3.0)
            if t:
                j = rows[t - 1]
                A[i, j] = A[j, i] = rng.uniform(-0.9, 0.9)
    return A


@pytest.mark.parametrize("seed", range(6))
def test_lu_skip_is_lu_bit_for_bit(seed):
    """linalg.lu_skip_inplace (the dense direct start's LU without its
    no-ops on zeros) gives lu_inplace's solution and determinant bit for
    bit: on islands of rows in shuffled order, with exact ties between
    pivot candidates, a right-hand side with signed zeros, on a dense
    matrix, and it hands back NaN (the caller's fall-back to lu_inplace) on
    a singular or non-finite matrix."""
    from physbench.engine.contact import linalg

    rng = np.random.default_rng(seed)
    cases = []
    for k, size in ((40, 8), (100, 4), (30, 30), (12, 3)):
        A = _islands_matrix(rng, k, size)
        r = rng.normal(size=k)
        r[rng.random(k) < 0.2] = -0.0
        r[rng.random(k) < 0.2] = 0.0
        cases.append((A, r))
    T = _islands_matrix(rng, 20, 5)
    T[np.abs(T) > 0] = np.round(T[np.abs(T) > 0] * 4) / 4 + 1e-3  # exact ties
    cases.append((T, np.zeros(20)))
    cases.append((rng.normal(size=(15, 15)), rng.normal(size=15)))  # dense, not symmetric
    for A, r in cases:
        x0, x1 = r.copy(), r.copy()
        d0 = linalg.lu_inplace(A.copy(), x0)
        d1 = linalg.lu_skip_inplace(A.copy(), x1, np.empty(A.shape[0], np.int64))
        assert np.array_equal(np.array([d0]).view(np.int64), np.array([d1]).view(np.int64))
        assert np.array_equal(x0.view(np.int64), x1.view(np.int64))
    S = _islands_matrix(rng, 10, 5)
    S[3, :] = S[:, 3] = 0.0  # singular
    N = _islands_matrix(rng, 10, 5)
    N[2, 7] = np.inf
    for A in (S, N):
        assert np.isnan(linalg.lu_skip_inplace(A, np.ones(10), np.empty(10, np.int64)))


@pytest.mark.parametrize("scene", ["column", "spheres"])
def test_steps_run_as_a_loop_allocate_nothing_per_step(scene):
    """``eng.step(n)`` runs consecutive steady steps inside one compiled
    loop (engine/fused/steady.py): what it allocates in compiled code (the loop's
    argument unboxing, the odd step one by one) does not grow with the
    number of steps: 400 steps allocate exactly as many arrays as 100."""
    from numba.core.runtime import _nrt_python, rtsys

    _nrt_python.memsys_enable_stats()
    counts = []
    for steps in (100, 400):
        make = (lambda: column_scene(10)) if scene == "column" else (lambda: spheres_scene(100))
        eng = engine_for(make(), {})
        eng.step(240)
        a0 = rtsys.get_allocation_stats().alloc
        eng.step(steps)
        counts.append(rtsys.get_allocation_stats().alloc - a0)
        assert eng.profile.calls.get("steady_step", 0) > 0  # the fused steps ran
    assert counts[1] == counts[0], counts
