"""Reading spec files: the TOML document (every failure a SpecError naming
the file), its variants, and :class:`LoadedSpec`, which validates the base
and any variant with overrides applied."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

from physbench.contract.spec.errors import SpecError
from physbench.contract.spec.overrides import apply_override, parse_key_path
from physbench.contract.spec.schema import SpecModel, name_error
from physbench.contract.spec.validate import validate_raw

class LoadedSpec:
    """A validated spec with its variants.  ``raw`` is the TOML document minus
    the variant tables; ``variants`` maps variant name -> overrides."""

    def __init__(self, path: Path, raw: dict[str, Any], variants: dict[str, dict[str, Any]]):
        self.path = path
        self.raw = raw
        self.variants = variants

    @property
    def label(self) -> str:
        return _display(self.path)

    def validated(self, variant: str | None = None, overrides: dict[str, Any] | None = None) -> SpecModel:
        """The spec with ``variant`` and then ``overrides`` applied, validated."""
        raw = copy.deepcopy(self.raw)
        label = self.label
        errors: list[str] = []
        if variant is not None:
            if variant not in self.variants:
                names = ", ".join(self.variants) or "none"
                raise SpecError([f"{label}: variant: unknown variant {variant!r}; this spec has: {names}"])
            for key, value in self.variants[variant].items():
                try:
                    apply_override(raw, key, value)
                except ValueError as e:
                    errors.append(f"{label}: variant[{variant}].{key}: {e}")
        for key, value in (overrides or {}).items():
            try:
                apply_override(raw, key, value)
            except ValueError as e:
                errors.append(f"{label}: --set {key}: {e}")
        if errors:
            raise SpecError(errors)
        return validate_raw(raw, label)


def _display(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def read_toml(p: Path, label: str, error: type[SpecError] = SpecError) -> tuple[dict[str, Any], bytes]:
    """The TOML document in file ``p`` and the file's bytes.  A missing file, a directory, an
    unreadable file, bytes that are not UTF-8 and invalid TOML raise
    ``error`` (a SpecError: exit 2) naming the file."""
    if p.is_dir():
        raise error([f"{label}: <file>: is a directory; expected a spec file (.toml)"])
    if not p.is_file():
        raise error([f"{label}: <file>: no such file"])
    try:
        data = p.read_bytes()
    except OSError as e:
        raise error([f"{label}: <file>: cannot read: {e.strerror or e}"]) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error([f"{label}: <file>: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); "
                     f"expected a TOML spec"]) from None
    try:
        return tomllib.loads(text), data
    except tomllib.TOMLDecodeError as e:
        raise error([f"{label}: <toml>: not valid TOML: {e}"]) from None
    except RecursionError:
        raise error([f"{label}: <toml>: not valid TOML: arrays or tables nested too deeply"]) from None


def load_spec(path: str | Path) -> LoadedSpec:
    """Read and validate a spec file (base and every variant).  Raises SpecError."""
    p = Path(path)
    label = _display(p)
    raw, _ = read_toml(p, label, SpecError)
    variants_raw = raw.pop("variant", [])
    errors: list[str] = []
    variants: dict[str, dict[str, Any]] = {}
    if not isinstance(variants_raw, list):
        errors.append(f"{label}: variant: expected an array of tables [[variant]], got {type(variants_raw).__name__}")
        variants_raw = []
    for i, v in enumerate(variants_raw):
        if not isinstance(v, dict):
            errors.append(f"{label}: variant[{i}]: expected a table")
            continue
        name = v.get("name")
        if not isinstance(name, str) or not name:
            errors.append(f"{label}: variant[{i}].name: required key is missing")
            continue
        if name_error(name):
            errors.append(f"{label}: variant[{i}].name: {name_error(name)}")
        if name in variants:
            errors.append(f"{label}: variant[{i}].name: duplicate variant name {name!r}")
        variants[name] = {k: val for k, val in v.items() if k != "name"}
    errors += _xfail_variant_errors(label, raw, variants)
    if errors:
        raise SpecError(errors)
    loaded = LoadedSpec(p, raw, variants)
    loaded.validated()
    for name in variants:
        loaded.validated(name)
    return loaded


def _xfail_variant_errors(label: str, raw: dict[str, Any], variants: dict[str, dict[str, Any]]) -> list[str]:
    """A known limitation's ``variants`` (``check[N].xfail.<engine>.variants``)
    must name the spec's variants or "base": a typo would key the xfail to
    no scene (tests/test_xfail_variants.py)."""
    from physbench.contract.xfail import BASE_VARIANT

    known = [BASE_VARIANT, *variants]
    errs: list[str] = []

    def scan(where: str, table: Any) -> None:
        if not isinstance(table, dict):
            return
        for eng, value in table.items():
            names = value.get("variants") if isinstance(value, dict) else None
            if not isinstance(names, list):
                continue  # absent, or of the wrong type: the schema reports it
            for n in names:
                if isinstance(n, str) and n not in known:
                    errs.append(f"{label}: {where}.{eng}.variants: unknown variant {n!r}; this spec has: "
                                f"{', '.join(known)}")

    checks = raw.get("check")
    for i, c in enumerate(checks if isinstance(checks, list) else []):
        if isinstance(c, dict):
            scan(f"check[{i}].xfail", c.get("xfail"))
    for name, over in variants.items():
        for key, value in over.items():
            if isinstance(key, str) and key.endswith(".xfail"):
                scan(f"variant {name!r}: {key}", value)
    return errs + _dead_check_override_errors(label, checks, variants)


def _dead_check_override_errors(label: str, checks: Any, variants: dict[str, dict[str, Any]]) -> list[str]:
    """A variant's override of ``check[N]...`` where check N holds only in
    other variants (its ``variants`` list, not overridden by that variant)
    would change nothing: refused, so no input is silently ignored
    (tests/test_xfail_variants.py::test_an_override_of_a_check_the_variant_does_not_run_is_refused)."""
    errs: list[str] = []
    if not isinstance(checks, list):
        return errs
    for name, over in variants.items():
        paths = {}
        for key in over:
            try:
                paths[key] = parse_key_path(key) if isinstance(key, str) else None
            except ValueError:
                paths[key] = None  # (apply_override reports it)
        overridden = {tuple(p) for p in paths.values() if p is not None}
        for key, path in paths.items():
            if path is None or len(path) < 3 or path[0] != "check" or not isinstance(path[1], int):
                continue
            i = path[1]
            c = checks[i] if 0 <= i < len(checks) else None
            held = c.get("variants") if isinstance(c, dict) else None
            if not isinstance(held, list) or name in held or ("check", i, "variants") in overridden:
                continue
            errs.append(f"{label}: variant {name!r}: {key!r} overrides check[{i}], which holds only in variants "
                        f"{held}: the override would change nothing (add {name!r} to the check's variants, or "
                        f"drop the override)")
    return errs
