"""Determinism: the reference engine gives bit-identical states for the same
scene and settings.  One scenario per family, final state hashed.

What is guaranteed today (engine/README.md, "Determinism"): bit-identical
results across runs, processes and worker counts on one machine and
environment.  What is not yet: the same bits across CPUs and BLAS kernels.
The engine's step still runs BLAS-dispatched numpy calls (matmul, solve),
whose rounding depends on the kernel OpenBLAS picks from the CPU or from
``OPENBLAS_CORETYPE`` (issue 20: the GRID scene's hash differed under
Haswell, Sandybridge, Prescott and SkylakeX kernels).

So a pinned hash -- the one snapshot the standards allow: it detects any
change in arithmetic, not whether the physics is right; the analytic tests do
that -- is keyed by the arithmetic it was measured under
(``harness.fingerprint.arithmetic_key``: BLAS library, version and core type,
numpy's SIMD targets, the CPU's arithmetic flags, numpy and scipy versions)
and asserted only there; elsewhere it is skipped with that reason.  The
repeat-in-one-process test holds everywhere.  If a deliberate change to the
engine changes these, re-pin every key in the same commit and say why
(``python tests/test_determinism.py`` prints this environment's entry; run it
under each OPENBLAS_CORETYPE of the table).
"""

import hashlib
import json
import sys

import numpy as np
import pytest

from harness.fingerprint import arithmetic_key
from harness.runner import run
from harness.scene import load_scene

SCENES = ("billiards.head_on", "stacking.column_5", "tunnelling.bullet_400", "friction.block_slides",
          "gyroscopic.dzhanibekov")
DURATION = 0.25  # s: enough steps for contacts, impacts and rotation to act

_SIMD = "simd=X86_V3+X86_V4+AVX512_ICL|flags=sse4_2+avx+fma+avx2+avx512f|numpy=2.4.6|scipy=1.17.1"
# Pinned 2026-11-24 on an AVX-512 x86-64 machine under four OpenBLAS core
# types (Prescott reports itself as Katmai; SkylakeX is this CPU's own pick
# with the variable unset, and gives the pins of earlier sessions).  Re-pinned
# block_slides only when every narrow-phase pair family became a compiled loop
# (box-plane corners summed left to right, not by einsum: the final state moved
# by at most 4.2e-16).  head_on, bullet_400 and
# dzhanibekov run no BLAS-dispatched call that matters and agree under all
# three; the column's and the slide's solver matmuls do not.
PINNED: dict[str, dict[str, str]] = {
    "openblas-0.3.30-Haswell,openblas-0.3.31.188.0-Haswell|" + _SIMD: {
        "billiards.head_on": "8a5a4b45b6cd0c6d", "stacking.column_5": "cd49a5ab1f798d7e",
        "tunnelling.bullet_400": "0985ae710f0e12b8", "friction.block_slides": "baee31454cddd038",
        "gyroscopic.dzhanibekov": "4755e7eae6487b47"},
    "openblas-0.3.30-Sandybridge,openblas-0.3.31.188.0-Sandybridge|" + _SIMD: {
        "billiards.head_on": "8a5a4b45b6cd0c6d", "stacking.column_5": "69106eb1b8855043",
        "tunnelling.bullet_400": "0985ae710f0e12b8", "friction.block_slides": "ef72fe787578bc8a",
        "gyroscopic.dzhanibekov": "4755e7eae6487b47"},
    "openblas-0.3.30-Katmai,openblas-0.3.31.188.0-Katmai|" + _SIMD: {
        "billiards.head_on": "8a5a4b45b6cd0c6d", "stacking.column_5": "9f86e9b528312107",
        "tunnelling.bullet_400": "0985ae710f0e12b8", "friction.block_slides": "b3ae8991fcd1fed4",
        "gyroscopic.dzhanibekov": "4755e7eae6487b47"},
    "openblas-0.3.30-SkylakeX,openblas-0.3.31.188.0-SkylakeX|" + _SIMD: {
        "billiards.head_on": "8a5a4b45b6cd0c6d", "stacking.column_5": "8b1adf47e7fa5d38",
        "tunnelling.bullet_400": "0985ae710f0e12b8", "friction.block_slides": "a3900c4108dab624",
        "gyroscopic.dzhanibekov": "4755e7eae6487b47"},
}


def final_state_hash(sid: str) -> str:
    scene = load_scene(sid, overrides={"scenario.duration": DURATION})
    r = run(scene, "reference", compute_metrics=False)
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    h = hashlib.sha256()
    for a in (tr.pos[-1], tr.quat[-1], tr.vel[-1], tr.angvel[-1]):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()[:16]


@pytest.mark.parametrize("sid", SCENES)
def test_two_runs_in_one_process_are_bit_identical(sid):
    assert final_state_hash(sid) == final_state_hash(sid)


@pytest.mark.parametrize("sid", SCENES)
def test_final_state_hash_is_pinned(sid):
    key = arithmetic_key()
    pins = PINNED.get(key)
    if pins is None:
        pytest.skip(f"no hash pinned for this arithmetic ({key}): the engine's bits depend on the BLAS "
                    f"kernel until its step is free of BLAS calls (issue 23)")
    got = final_state_hash(sid)
    assert got == pins[sid], f"{sid}: final-state hash {got}, pinned {pins[sid]} under {key}"


if __name__ == "__main__":  # print this environment's PINNED entry
    json.dump({arithmetic_key(): {s: final_state_hash(s) for s in SCENES}}, sys.stdout, indent=1)
    print()
