"""What the commands share: the usage error (exit 2), ``--set`` splitting,
argparse value types and count bounds, output-path checks, value
formatting, and the checked RunRequest of ``run`` and ``trace``."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from physbench.contract.spec import parse_value


class UsageError(Exception):
    pass


def _split_sets(pairs: list[str], engine_settings: set[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """--set k=v items -> (engine settings, spec overrides)."""
    settings: dict[str, Any] = {}
    overrides: dict[str, Any] = {}
    for item in pairs or []:
        if "=" not in item:
            raise UsageError(f"--set {item}: expected key=value")
        key, _, text = item.partition("=")
        key = key.strip()
        value = parse_value(text.strip())
        if key in engine_settings:
            settings[key] = value
        elif "." in key or "[" in key:
            overrides[key] = value
        else:
            raise UsageError(
                f"--set {key}: not a setting of this engine ({', '.join(sorted(engine_settings))}) "
                f"and not a dotted spec key (e.g. material.default.restitution)")
    return settings, overrides


def _int_in(lo: int, hi: int):
    """argparse type: an integer in [lo, hi] (argparse reports anything else
    as a usage error, exit 2)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {v}")
        return v
    return parse


def _float_where(test: Any, expected: str):
    """argparse type: a number for which ``test(v)`` holds (nan never does)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not (math.isfinite(v) and test(v)):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text}")
        return v
    return parse


_phase_value = _float_where(lambda v: 0.0 <= v < 1.0, "a number 0 <= F < 1")
_positive_float = _float_where(lambda v: v > 0.0, "a finite number > 0")


#: bounds of the CLI's counts: runs at once, benchmark repeats, record stride
MAX_JOBS = 256
MAX_REPEATS = 1000
MAX_RECORD_EVERY = 10**8


def output_file(flag: str, value: str | None) -> Path | None:
    """The file an output flag (``--junit``, ``-o``, ``--save``, ``--out``)
    names, checked before any run: not empty, not an existing directory,
    and no existing file where a parent directory must be (missing parent
    directories are created when the file is written).  UsageError (exit 2)
    otherwise."""
    if value is None:
        return None
    if not value.strip():
        raise UsageError(f"{flag}: expected a file path, got {value!r}")
    p = Path(value)
    if p.is_dir() or value.endswith(("/", "\\")):
        raise UsageError(f"{flag} {value}: is a directory; expected a file path")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"{flag} {value}: {parent} is a file, not a directory")
            break
    return p


def output_dir(flag: str, value: str | None) -> Path | None:
    """The directory an output flag names: not empty, not an existing file."""
    if value is None:
        return None
    if not value.strip():
        raise UsageError(f"{flag}: expected a directory path, got {value!r}")
    p = Path(value)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{flag} {value}: is a file; expected a directory")
    return p


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        return f"{v:.6g}"
    if v is None:
        return "n/a"
    return str(v)


def _request(args: argparse.Namespace, engine: str, settings: dict[str, Any], overrides: dict[str, Any], **kw):
    """The RunRequest of a command line, checked in this process before it
    goes to a worker: a bad spec, setting or phase is exit 2 here."""
    from physbench.adapters import get_adapter
    from physbench.harness.execute import RunRequest, request_scene
    from physbench.contract.phase import PhaseError

    req = RunRequest(str(args.scenario), engine, args.variant, settings, overrides or {}, phase=args.phase, **kw)
    try:
        scene = request_scene(req)
    except PhaseError as e:
        raise UsageError(str(e) if str(e).startswith("--set dt") else f"--phase {args.phase:g}: {e}") from None
    from physbench.harness.runner import check_run_size

    try:
        resolved = get_adapter(engine).resolve_settings(scene, settings)
        check_run_size(scene, float(resolved["dt"]), req.record_every)
    except ValueError as e:  # bad setting value, or a recording too large to allocate
        raise UsageError(str(e)) from None
    return req



def _scheduler_needs_dask(args: argparse.Namespace) -> None:
    if args.scheduler and args.executor != "dask":
        raise UsageError(f"--scheduler {args.scheduler}: a scheduler address needs --executor dask")



def _seconds(text: str) -> float:
    """A --timeout value: a positive, finite number of seconds."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive, finite number of seconds, got {text!r}")
    return v

