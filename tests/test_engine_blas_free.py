"""The reference engine's step runs no BLAS or LAPACK (issue 23): its bits
do not depend on the kernel OpenBLAS picks (``OPENBLAS_CORETYPE``).

A column of boxes (the direct start's dense solve, friction patches), a
block sliding on a slope (friction stop), a gyroscopic body (energy-
conserving rotation) and a billiards impact (time of impact, impact solve)
run in fresh processes under three core types; their final states hash
the same.  A source scan keeps BLAS-dispatched calls out of the dynamics
modules (compiled loops with a fixed summation order replace them:
engine/contact/linalg.py, engine/contact/gauss_seidel.py)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SCENES = ("stacking.column_5", "friction.block_slides", "gyroscopic.dzhanibekov", "billiards.head_on",
          "joints.four_bar")
CORE_TYPES = ("Prescott", "Sandybridge", "Haswell")

_CODE = """
import hashlib, sys
import numpy as np
from physbench.harness.runner import run
from physbench.contract.scene import load_scene
for sid in sys.argv[1:]:
    r = run(load_scene(sid, overrides={"scenario.duration": 0.25}), "reference", compute_metrics=False)
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    h = hashlib.sha256()
    for a in (tr.pos[-1], tr.quat[-1], tr.vel[-1], tr.angvel[-1]):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    print(sid, h.hexdigest())
"""


def _hashes(core: str) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OPENBLAS", "PYTHON"))}
    env.update(PYTHONPATH=str(REPO), OPENBLAS_CORETYPE=core, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CODE, *SCENES], capture_output=True, text=True, cwd=REPO,
                         env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_final_states_are_the_same_under_every_blas_core_type():
    from concurrent.futures import ThreadPoolExecutor

    # the three processes are independent: two at a time, not one after another
    with ThreadPoolExecutor(max_workers=2) as pool:
        got = dict(zip(CORE_TYPES, pool.map(_hashes, CORE_TYPES)))
    assert len(got["Haswell"].splitlines()) == len(SCENES)
    assert got["Prescott"] == got["Sandybridge"] == got["Haswell"], got


#: the dynamics modules of the step (the collision modules are scanned by
#: their own tests)
DYNAMICS = ("solver.py", "integrate.py", "forces.py", "flight.py", "gyroscopic.py", "ccd.py", "pipeline.py", "state.py",
            "penalty.py", "contact", "joints")
_BLAS = re.compile(r"(\s@\s|\s@=|np\.dot\b|\.dot\(|matmul|np\.linalg\.(solve|inv|det|lstsq|pinv|eig|cholesky|qr|svd)|"
                   r"scipy|tensordot|optimize=True)")


def _blas(code: str) -> bool:
    """A BLAS-dispatched call in ``code``: the patterns above, or a 1-D
    ``np.linalg.norm`` (no ``axis``: it is ``sqrt(ddot(a, a))``)."""
    return bool(_BLAS.search(code)) or ("np.linalg.norm(" in code and "axis" not in code)


def test_the_dynamics_modules_call_no_blas():
    bad = []
    for name in DYNAMICS:
        p = REPO / "engine" / name
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            for k, line in enumerate(f.read_text().splitlines(), 1):
                code = line.split("#", 1)[0]
                if code.strip().startswith(("@njit", "@staticmethod", "@property", "@classmethod", "@dataclass")):
                    continue
                if _blas(code) and not code.lstrip().startswith(('"', "'")):
                    bad.append(f"{f.relative_to(REPO)}:{k}: {line.strip()}")
    assert not bad, "\n".join(bad)


#: the contract modules that build a scene's numbers (poses, joint frames,
#: plane offsets, a phase-shifted start) before any engine sees them
SCENE_BUILDING = ("scene.py", "scene_model.py", "rotation.py", "shapes.py", "phase.py")


def test_building_a_scene_calls_no_blas():
    """A 1-D ``@`` or ``np.linalg.norm`` in the scene's construction made
    joints.four_bar's joint frames differ in their last bits under
    Prescott; contract.rotation.dot and norm sum in a fixed order."""
    bad = []
    for name in SCENE_BUILDING:
        f = REPO / "contract" / name
        for k, line in enumerate(f.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if _blas(code) and not code.lstrip().startswith(('"', "'", "1-D")):
                bad.append(f"{f.relative_to(REPO)}:{k}: {line.strip()}")
    # the joint reach check measures, it builds nothing: allowed
    bad = [b for b in bad if "near = [" not in b]
    assert not bad, "\n".join(bad)


_SHIFT_CODE = """
import hashlib, sys
import numpy as np
from physbench.contract.phase import shift_scene
from physbench.contract.scene import load_scene
for sid in sys.argv[1:]:
    h = hashlib.sha256()
    for f in (0.3, 0.85):
        for b in shift_scene(load_scene(sid), f).bodies:
            for a in (b.position, b.orientation, b.velocity, b.angular_velocity):
                h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    print(sid, h.hexdigest())
"""


def test_a_phase_shifted_start_is_the_same_under_every_blas_core_type():
    """A phase sweep's starts (contract/phase.py: the backward free flight,
    a tumbling body's torque-free rotation, the clearance checks) are the
    same to the bit whatever kernel OpenBLAS picks; with scipy's adaptive
    solver (its error norms are BLAS dot products) they were not
    guaranteed."""
    sids = ("gyroscopic.dzhanibekov", "tunnelling.spinning_long_box", "tunnelling.bullet_400")
    outs = []
    for core in CORE_TYPES:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("OPENBLAS", "PYTHON"))}
        env.update(PYTHONPATH=str(REPO), OPENBLAS_CORETYPE=core, OPENBLAS_NUM_THREADS="1")
        out = subprocess.run([sys.executable, "-c", _SHIFT_CODE, *sids], capture_output=True, text=True, cwd=REPO,
                             env=env, timeout=300)
        assert out.returncode == 0, out.stderr
        outs.append(out.stdout)
    assert len(outs[0].splitlines()) == len(sids)
    assert outs[0] == outs[1] == outs[2], outs
