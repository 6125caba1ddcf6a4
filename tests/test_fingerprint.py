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


def test_blas_list_is_the_one_importing_scipy_linalg_gives():
    # the fingerprint loads scipy.linalg's BLAS without importing scipy.linalg (a sweep client's start-up);
    # the list, and every id and string made from it (machine and env ids key stored history), must be the
    # ones importing scipy.linalg gives: each way in a fresh process, with the CPU's own core type and another
    code = ("import json, sys\n"
            "if sys.argv[1] == 'import':\n"
            "    import scipy.linalg\n"
            "from physbench.harness import fingerprint as F\n"
            "if sys.argv[1] == 'import':\n"
            "    F._load_scipy_blas = lambda: None\n"
            "fp = F.fingerprint()\n"
            "print(json.dumps({'fp': fp, 'env_id': F.env_id(fp), 'machine_id': F.machine_id(fp),\n"
            "                  'key': F.arithmetic_key(fp), 'summary': F.summary(fp),\n"
            "                  'scipy.linalg': 'scipy.linalg' in sys.modules}))\n")
    import json

    for core in (None, "Sandybridge"):
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        env.pop("OPENBLAS_CORETYPE", None)
        if core:
            env["OPENBLAS_CORETYPE"] = core
        got = {}
        for way in ("import", "load"):
            out = subprocess.run([sys.executable, "-c", code, way], capture_output=True, text=True, env=env,
                                 cwd=ROOT, timeout=120)
            assert out.returncode == 0, out.stderr
            got[way] = json.loads(out.stdout)
        assert got["import"].pop("scipy.linalg") is True
        assert got["load"].pop("scipy.linalg") is False
        assert got["load"] == got["import"], core
        import scipy

        # scipy's own OpenBLAS (wheels ship one beside numpy's) is listed
        assert len(got["load"]["fp"]["blas"]) >= 1
        assert scipy.__version__ in got["load"]["key"]
