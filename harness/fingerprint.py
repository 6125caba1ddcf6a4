"""The environment a run's numbers come from.

Two runs' timings compare only on the same hardware and library stack, and
their bits only where the arithmetic is the same.  ``fingerprint()`` gathers
what decides both:

- the CPU: model name, vendor, family/model/stepping numbers, the flags that
  change arithmetic (``fma``, ``avx``, ``avx2``, ``avx512f``), logical cores;
- the BLAS libraries loaded (via threadpoolctl): library, version, the core
  type whose kernels it picked (``OPENBLAS_CORETYPE`` or the CPU's own);
- numpy's runtime SIMD dispatch targets (its ufunc loops differ by target);
- numpy, scipy, numba, Python and physbench engine versions.

Three ids are derived from it:

- ``machine_id()``: the hardware alone (``<cpu-slug>-<8 hex>``).  Host names
  are left out on purpose: CI machines are new each night, and two CPUs of one
  model string ("AMD EPYC") with and without AVX-512 are different machines.
- ``env_id()``: hardware plus the library stack; a history across a numpy or
  BLAS upgrade starts a new series (tests/test_fingerprint.py).
- ``arithmetic_key()``: only what decides the bits of a numpy computation;
  a pinned state hash holds where this key is the one it was pinned under.

Only the standard library, numpy and threadpoolctl are imported here.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import re
from typing import Any

ARITHMETIC_FLAGS = ("sse4_2", "avx", "fma", "avx2", "avx512f")


def _cpuinfo() -> dict[str, str]:
    """The first processor block of /proc/cpuinfo (empty off Linux)."""
    out: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if not line.strip():
                    if out:
                        break
                    continue
                k, _, v = line.partition(":")
                out.setdefault(k.strip().lower(), v.strip())
    except OSError:
        pass
    return out


def cpu_info() -> dict[str, Any]:
    """CPU model, vendor, family/model/stepping, arithmetic flags, cores."""
    info = _cpuinfo()
    flags = set(info.get("flags", "").split())
    return {
        "model": info.get("model name") or platform.processor() or platform.machine(),
        "vendor": info.get("vendor_id", ""),
        "family": info.get("cpu family", ""),
        "model_number": info.get("model", ""),
        "stepping": info.get("stepping", ""),
        "flags": [f for f in ARITHMETIC_FLAGS if f in flags] if flags else [],
        "cores": os.cpu_count() or 0,
        "arch": platform.machine(),
    }


def _load_scipy_blas() -> None:
    """Load the BLAS library scipy.linalg uses (scipy's own OpenBLAS, if it
    ships one) as importing scipy.linalg would, without running scipy's
    Python modules (about 0.14 s of a client's start-up): the dynamic
    loader opens scipy.linalg's BLAS extension file, which loads the
    libraries it links and runs no module code.  Where that file is not
    found or does not load, scipy.linalg is imported.  The BLAS list is
    the same either way
    (tests/test_fingerprint.py::test_blas_list_is_the_one_importing_scipy_linalg_gives)."""
    import ctypes
    import importlib.machinery
    import importlib.util

    try:
        spec = importlib.util.find_spec("scipy")  # finds the package, imports nothing
    except (ImportError, ValueError):  # pragma: no cover - scipy is a dependency
        spec = None
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover
        return
    for base in spec.submodule_search_locations:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = os.path.join(base, "linalg", f"_fblas{suffix}")
            if os.path.isfile(path):
                try:
                    ctypes.CDLL(path)
                    return
                except OSError:  # pragma: no cover - then the import below
                    break
    try:  # pragma: no cover - a layout without the extension file
        import scipy.linalg  # noqa: F401
    except ImportError:
        pass


def blas_info() -> list[dict[str, str]]:
    """Each BLAS library loaded by numpy and scipy: library, version, the
    core type it runs kernels for, threading layer.  Loads scipy.linalg's
    BLAS (:func:`_load_scipy_blas`) so that scipy's own OpenBLAS, if it
    ships one, is listed too."""
    import numpy  # noqa: F401  (loads numpy's BLAS)

    _load_scipy_blas()
    from threadpoolctl import threadpool_info

    libs = []
    for lib in threadpool_info():
        if lib.get("user_api") != "blas":
            continue
        libs.append({
            "library": str(lib.get("internal_api", "")),
            "version": str(lib.get("version", "")),
            "core_type": str(lib.get("architecture") or ""),
            "threading": str(lib.get("threading_layer") or ""),
            "prefix": str(lib.get("prefix", "")),
        })
    return sorted(libs, key=lambda d: (d["prefix"], d["library"], d["version"]))


def numpy_simd() -> list[str]:
    """numpy's runtime-dispatched SIMD targets that this CPU enables."""
    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # pragma: no cover - numpy < 2
        try:
            from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
        except ImportError:
            return []
    return [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]


def package_version(mod: str) -> str:
    try:
        from importlib.metadata import version

        return version(mod)
    except Exception:
        return ""


@functools.lru_cache(maxsize=1)
def fingerprint() -> dict[str, Any]:
    """The environment fingerprint (a JSON-able dict; cached per process)."""
    from physbench.engine import version as engine_version  # the engine (numba) only once a fingerprint is taken

    return {
        "cpu": cpu_info(),
        "blas": blas_info(),
        "numpy_simd": numpy_simd(),
        "versions": {
            "python": platform.python_version(),
            "numpy": package_version("numpy"),
            "scipy": package_version("scipy"),
            "numba": package_version("numba"),
            "physbench_engine": engine_version(),
        },
        "os": platform.system(),
    }


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:8]


def _slug(text: str) -> str:
    s = re.sub(r"\(r\)|\(tm\)|cpu|processor|@.*$", "", text.lower())
    s = re.sub(r"[^a-z0-9]+", "-", s).strip("-")
    return s[:24] or "cpu"


def machine_id(fp: dict[str, Any] | None = None) -> str:
    """``<cpu-slug>-<8 hex>``: hash of the CPU fields (model, vendor,
    family/model/stepping, arithmetic flags, cores, arch) and the OS."""
    fp = fp or fingerprint()
    return f"{_slug(fp['cpu']['model'])}-{_digest([fp['cpu'], fp['os']])}"


def env_id(fp: dict[str, Any] | None = None) -> str:
    """Hash of the whole fingerprint: hardware and library stack."""
    return _digest(fp or fingerprint())


def arithmetic_key(fp: dict[str, Any] | None = None) -> str:
    """What decides a numpy computation's bits, as one readable string:
    BLAS library, version and core type, numpy's SIMD targets, the CPU's
    arithmetic flags, numpy and scipy versions."""
    fp = fp or fingerprint()
    blas = ",".join(f"{b['library']}-{b['version']}-{b['core_type']}" for b in fp["blas"]) or "noblas"
    return "|".join([
        blas,
        "simd=" + "+".join(fp["numpy_simd"]),
        "flags=" + "+".join(fp["cpu"]["flags"]),
        f"numpy={fp['versions']['numpy']}",
        f"scipy={fp['versions']['scipy']}",
    ])


def summary(fp: dict[str, Any] | None = None) -> dict[str, str]:
    """Flat string fields for a result row's ``machine.*`` columns."""
    fp = fp or fingerprint()
    cpu = fp["cpu"]
    return {
        "id": machine_id(fp),
        "env_id": env_id(fp),
        "cpu": cpu["model"],
        "cpu_family_model": f"{cpu['family']}/{cpu['model_number']}/{cpu['stepping']}",
        "cpu_flags": " ".join(cpu["flags"]),
        "cores": str(cpu["cores"]),
        "blas": "; ".join(f"{b['library']} {b['version']} {b['core_type']}".strip() for b in fp["blas"]),
        "numpy": fp["versions"]["numpy"],
        "scipy": fp["versions"]["scipy"],
        "numba": fp["versions"]["numba"],
        "python": fp["versions"]["python"],
        "host": platform.node(),
        "platform": platform.platform(),
    }
