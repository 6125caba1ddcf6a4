"""The environment fingerprint: what decides timings and bits, and the ids
derived from it (harness/fingerprint.py)."""

import copy
import os
import subprocess
import sys
from pathlib import Path

from physbench.harness import fingerprint as F

ROOT = Path(__file__).resolve().parent.parent


def test_fingerprint_names_cpu_blas_and_versions():
    fp = F.fingerprint()
    assert fp["cpu"]["cores"] == os.cpu_count()
    assert set(fp["cpu"]["flags"]) <= set(F.ARITHMETIC_FLAGS)
    assert fp["blas"] and all(b["library"] and b["version"] for b in fp["blas"])
    import numpy
    import scipy

    assert fp["versions"]["numpy"] == numpy.__version__
    assert fp["versions"]["scipy"] == scipy.__version__
    s = F.summary(fp)
    assert s["id"] == F.machine_id(fp) and s["numpy"] == numpy.__version__


def test_same_cpu_string_with_and_without_avx512_are_two_machines():
    fp = copy.deepcopy(F.fingerprint())
    a, b = copy.deepcopy(fp), copy.deepcopy(fp)
    a["cpu"].update(model="AMD EPYC", flags=["sse4_2", "avx", "fma", "avx2", "avx512f"])
    b["cpu"].update(model="AMD EPYC", flags=["sse4_2", "avx", "fma", "avx2"])
    assert F.machine_id(a) != F.machine_id(b)
    assert F.machine_id(a).startswith("amd-epyc-")


def test_host_name_is_not_part_of_the_machine_id(monkeypatch):
    fp = F.fingerprint()
    mid = F.machine_id(fp)
    monkeypatch.setattr("platform.node", lambda: "another-host")
    assert F.machine_id(fp) == mid


def test_a_library_upgrade_is_another_environment_on_the_same_machine():
    fp = F.fingerprint()
    up = copy.deepcopy(fp)
    up["versions"]["numpy"] = "99.0.0"
    assert F.machine_id(up) == F.machine_id(fp)
    assert F.env_id(up) != F.env_id(fp)
    assert F.arithmetic_key(up) != F.arithmetic_key(fp)


def test_blas_core_type_enters_the_arithmetic_key():
    code = "from physbench.harness.fingerprint import arithmetic_key; print(arithmetic_key())"
    keys = {}
    for core in ("Prescott", "Sandybridge"):
        env = dict(os.environ, OPENBLAS_CORETYPE=core, PYTHONPATH=str(ROOT))
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                             timeout=120)
        assert out.returncode == 0, out.stderr
        keys[core] = out.stdout.strip()
    assert keys["Prescott"] != keys["Sandybridge"]
    assert "Sandybridge" in keys["Sandybridge"]
