"""What the commands share: the usage error (exit 2), ``--set`` splitting,
argparse value types and count bounds, output-path checks, value
formatting, and the checked RunRequest of ``run`` and ``trace``."""

from __future__ import annotations

import argparse
import math
import re
from fractions import Fraction
from pathlib import Path
from typing import Any

from physbench.adapters import get_adapter
from physbench.contract.phase import PhaseError
from physbench.contract.spec import SpecError, parse_value
from physbench.harness.conformance.plan import engine_names_in_checks
from physbench.harness.execute import RunRequest, request_scene
from physbench.harness.runner import check_run_size


class UsageError(Exception):
    pass


_FRACTION = re.compile(r"^\s*[+-]?\d+(\.\d*)?\s*/\s*\d+(\.\d*)?\s*$")


def set_value(text: str) -> Any:
    """A --set value: TOML (``1e-3``, ``true``, ``[1,2,3]``, ``"rk4"``), a
    fraction ``1/240`` as its float (as ``@dt=1/30`` in a check's metric),
    else a bare word as a string (tests/test_cli.py::test_set_takes_fractions_and_engine_settings)."""
    if _FRACTION.match(text):
        try:
            return float(Fraction(text.replace(" ", "")))
        except ZeroDivisionError:
            raise UsageError(f"--set: {text!r} divides by zero") from None
    return parse_value(text)


def engine_sets(pairs: list[str], engines: list[str]) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """Split ``--set`` items of ``check`` and ``trace``: ``ENGINE:KEY=VALUE``
    sets one engine's setting, ``KEY=VALUE`` where KEY is a setting of every
    engine in ``engines`` sets it for all.  Returns (per engine settings, the
    remaining items: dotted spec keys).  Every engine setting is validated
    here (engine among ``engines``, key one of its settings, value of its
    kind): a UsageError (exit 2) otherwise."""
    per: dict[str, dict[str, Any]] = {e: {} for e in engines}
    rest: list[str] = []
    caps = {}

    def settings_of(e: str) -> dict[str, Any]:
        if e not in caps:
            caps[e] = get_adapter(e).capabilities().settings
        return caps[e]

    for item in pairs or []:
        key, sep, text = item.partition("=")
        if not sep:
            raise UsageError(f"--set {item}: expected key=value or engine:key=value")
        key = key.strip()
        head, colon, tail = key.partition(":")
        if colon:
            eng, name = head.strip(), tail.strip()
            if eng not in per:
                raise UsageError(f"--set {key}: engine {eng!r} is not among the engines of this command "
                                 f"({', '.join(engines)})")
            targets = [eng]
        elif "." in key or "[" in key:
            rest.append(item)
            continue
        else:
            name = key
            lacking = [e for e in engines if name not in settings_of(e)]
            if lacking:
                raise UsageError(f"--set {name}: not a setting of {', '.join(lacking)}; give it per engine as "
                                 f"ENGINE:{name}=VALUE, or a dotted spec key (e.g. material.default.restitution)")
            targets = list(engines)
        value = set_value(text.strip())
        for e in targets:
            known = settings_of(e)
            if name not in known:
                raise UsageError(f"--set {key}: not a setting of {e} ({', '.join(sorted(known))})")
            try:
                per[e][name] = known[name].coerce(value)
            except ValueError as err:
                raise UsageError(f"--set {key}: {err}") from None
    return per, rest


def split_sets(pairs: list[str], engine_settings: set[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """--set k=v items -> (engine settings, spec overrides)."""
    settings: dict[str, Any] = {}
    overrides: dict[str, Any] = {}
    for item in pairs or []:
        if "=" not in item:
            raise UsageError(f"--set {item}: expected key=value")
        key, _, text = item.partition("=")
        key = key.strip()
        value = set_value(text.strip())
        if key in engine_settings:
            settings[key] = value
        elif "." in key or "[" in key:
            overrides[key] = value
        else:
            raise UsageError(
                f"--set {key}: not a setting of this engine ({', '.join(sorted(engine_settings))}) "
                f"and not a dotted spec key (e.g. material.default.restitution)")
    return settings, overrides


def int_in(lo: int, hi: int):
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


phase_value = _float_where(lambda v: 0.0 <= v < 1.0, "a number 0 <= F < 1")
positive_float = _float_where(lambda v: v > 0.0, "a finite number > 0")


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


def fmt_value(v: Any) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        return f"{v:.6g}"
    if v is None:
        return "n/a"
    return str(v)


def fmt_prediction(v: Any) -> str:
    """A prediction value: a number as the metrics are printed, a list or a
    table of them (per body) element by element."""
    if isinstance(v, dict):
        return ", ".join(f"{k} {fmt_prediction(x)}" for k, x in v.items())
    if isinstance(v, list):
        return "[" + ", ".join(fmt_prediction(x) for x in v) + "]"
    return fmt_value(v)


def checked_request(args: argparse.Namespace, engine: str, settings: dict[str, Any], overrides: dict[str, Any], **kw):
    """The RunRequest of a command line, checked in this process before it
    goes to a worker: a bad spec, setting or phase is exit 2 here."""
    req = RunRequest(str(args.scenario), engine, args.variant, settings, overrides or {}, phase=args.phase, **kw)
    try:
        scene = request_scene(req)
    except PhaseError as e:
        raise UsageError(str(e) if str(e).startswith("--set dt") else f"--phase {args.phase:g}: {e}") from None

    bad, _ = engine_names_in_checks(scene, scene.source or str(args.scenario))
    if bad:  # a misspelt engine in a check is a spec error for every command
        raise SpecError(bad)
    try:
        resolved = get_adapter(engine).resolve_settings(scene, settings)
        check_run_size(scene, float(resolved["dt"]), req.record_every)
    except ValueError as e:  # bad setting value, or a recording too large to allocate
        raise UsageError(str(e)) from None
    return req


def scheduler_needs_dask(args: argparse.Namespace) -> None:
    if args.scheduler and args.executor != "dask":
        raise UsageError(f"--scheduler {args.scheduler}: a scheduler address needs --executor dask")


def timeout_seconds(text: str) -> float:
    """A --timeout value: a positive, finite number of seconds."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive, finite number of seconds, got {text!r}")
    return v

