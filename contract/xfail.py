"""Known limitations (a check's ``xfail``) and the engine versions they hold for.

A check's ``xfail`` maps an engine to a known limitation, in one of two forms
(docs/SCENARIO_FORMAT.md, "Known limitations and engine versions")::

    xfail = { mujoco = "soft contacts: measured 6.0 mm" }
    xfail = { mujoco = { reason = "soft contacts: measured 6.0 mm", measured_on = "4.0.0",
                         versions = ">=4.0,<4.2" } }
    xfail = { drake = { reason = "measured 4.5 mm (base), 10.7 mm (plastic)", variants = ["base", "plastic"] } }

The plain string means: measured on the version :data:`MEASURED_ON` records
for that engine (the versions the shipped xfails were measured on).  The
limitation applies to the engine versions in ``versions`` (a PEP 440
specifier set), by default the same major.minor as ``measured_on``.  Outside
that range the check runs as a plain check and its verdict says which version
the limitation was measured on (:func:`xfail_for`).  An engine without a
recorded version (a plug-in whose xfail is a plain string) has no range: the
limitation applies to every version.

The table's ``variants`` (the spec's variant names, ``"base"`` for the scene
as written) keys the limitation to those scenes of the spec: in any other
variant the check is a plain check for that engine (no note: the limitation
was not declared there).  Without ``variants`` it holds in every variant
that keeps the check's xfail table (a variant's ``"check[N].xfail"``
override replaces the table for that variant).

Tests: tests/test_xfail_versions.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from packaging.specifiers import InvalidSpecifier, SpecifierSet
from packaging.version import InvalidVersion, Version

#: the engine versions the shipped scenarios' plain-string xfails were
#: measured on (one line per engine)
MEASURED_ON: dict[str, str] = {
    "mujoco": "4.0.1",
    "pybullet": "3.2.7",
    "pymunk": "7.3.1",
    "rapier": "0.36.1",
    "box2d": "0.11.1",  # pyb2d3's version (the binding's; Box2D >= 3.1 inside)
    "drake": "1.51.1",
    "mjx": "3.17.0",  # mujoco-mjx's version
}

#: the name of the scene as written among a check's ``variants``
BASE_VARIANT = "base"


@dataclass(frozen=True)
class Xfail:
    """One engine's known limitation on one check: the ``reason`` (with the
    measured figure), the engine version it was ``measured_on`` ('' when
    unknown), the ``versions`` it applies to ('' = the default range) and
    the spec ``variants`` it applies to (None = every variant)."""

    reason: str
    measured_on: str = ""
    versions: str = ""
    variants: tuple[str, ...] | None = None

    @classmethod
    def of(cls, engine: str, value: Any) -> "Xfail":
        """The spec's value (a string, a table, or an Xfail) as an Xfail."""
        if isinstance(value, Xfail):
            return value
        if isinstance(value, Mapping):
            variants = value.get("variants")
            return cls(str(value.get("reason", "")), str(value.get("measured_on") or MEASURED_ON.get(engine, "")),
                       str(value.get("versions") or ""),
                       None if variants is None else tuple(str(v) for v in variants))
        return cls(str(value), MEASURED_ON.get(engine, ""))

    @property
    def range(self) -> str:
        """The version range it applies to: ``versions``, else the same
        major.minor as ``measured_on`` (``>=4.0,<4.1`` for 4.0.0), else ''
        (every version)."""
        if self.versions:
            return self.versions
        return default_range(self.measured_on) if self.measured_on else ""

    def holds_in(self, variant: str | None) -> bool:
        """Whether the limitation is declared for the scene ``variant``
        (None or "base": the scene as written)."""
        return self.variants is None or (variant or BASE_VARIANT) in self.variants

    def covers(self, version: str) -> bool | None:
        """True when ``version`` lies in :attr:`range` (every version when
        there is no range), False outside, None when ``version`` cannot be
        compared (empty, 'unknown', not a PEP 440 version)."""
        rng = self.range
        if not rng:
            return True
        v = parse_version(version)
        if v is None:
            return None
        return SpecifierSet(rng).contains(v, prereleases=True)


def default_range(measured_on: str) -> str:
    """``>=M.m,<M.(m+1)``: the releases of the same major.minor."""
    v = Version(measured_on)
    return f">={v.major}.{v.minor},<{v.major}.{v.minor + 1}"


def parse_version(text: str) -> Version | None:
    """An engine's version string as a PEP 440 version (a ``name-1.2.3``
    form gives 1.2.3), or None."""
    text = (text or "").strip()
    for cand in (text, text.rpartition("-")[2]):
        try:
            return Version(cand)
        except InvalidVersion:
            continue
    return None


def spec_error(engine: str, value: Any) -> str | None:
    """Why the spec value of ``xfail.<engine>`` is not valid, or None."""
    if isinstance(value, str):
        return None if value.strip() else "expected a non-empty reason"
    reason = value.get("reason")
    if not isinstance(reason, str) or not reason.strip():
        return "expected reason = \"...\" (the limitation and its measured figure)"
    measured = value.get("measured_on")
    if measured is not None:
        try:
            Version(measured)
        except (InvalidVersion, TypeError):
            return f"measured_on: expected an engine version such as \"4.0.0\", got {measured!r}"
    versions = value.get("versions")
    if versions is not None:
        try:
            if not str(versions).strip():
                raise InvalidSpecifier(versions)
            SpecifierSet(versions)
        except (InvalidSpecifier, TypeError):
            return f"versions: expected a version range such as \">=4.0,<4.2\", got {versions!r}"
    variants = value.get("variants")
    if variants is not None:
        if (not isinstance(variants, (list, tuple)) or not variants
                or not all(isinstance(v, str) and v.strip() for v in variants)):
            return f"variants: expected a non-empty list of variant names such as [\"base\", \"elastic\"], got {variants!r}"
        if len(set(variants)) != len(variants):
            return f"variants: a variant is named twice in {list(variants)}"
    return None


def xfail_for(xfails: Mapping[str, Any], engine: str, version: str,
              variant: str | None = None) -> tuple[str | None, str]:
    """(reason, note) of ``engine`` at ``version`` in the scene ``variant``
    (None: the scene as written) for a check's ``xfails``: the reason when a
    known limitation applies, else None; the note says why one was set
    aside (the version lies outside the range it was measured for) or could
    not be compared, '' otherwise.  A limitation keyed to other variants
    does not apply, without a note (tests/test_xfail_variants.py)."""
    value = xfails.get(engine)
    if value is None:
        return None, ""
    xf = Xfail.of(engine, value)
    if not xf.holds_in(variant):
        return None, ""
    inside = xf.covers(version)
    if inside is None:
        if not version or version == "unknown":
            return xf.reason, ""
        return xf.reason, (f"{engine} version {version!r} cannot be compared with the known limitation's range "
                           f"{xf.range}; it is applied")
    if inside:
        return xf.reason, ""
    return None, (f"known limitation measured on {engine} {xf.measured_on or '?'} (applies to {xf.range}) "
                  f"set aside for {engine} {version}, checked as a plain check; it said: {xf.reason}")


def shipped_xfails(root: Any = None) -> dict[str, dict[tuple[str, str], int]]:
    """The known limitations of the shipped scenarios (or of the spec files
    under ``root``), read from the TOML as written (checks and variants'
    ``check[N].xfail`` overrides): engine -> {(measured_on, range): count}.
    ``physbench engines`` tells from it whether each installed engine's
    version lies inside the ranges they were measured for."""
    import tomllib
    from pathlib import Path

    from physbench.contract.data import SHIPPED_SCENARIOS

    out: dict[str, dict[tuple[str, str], int]] = {}

    def add(table: Any) -> None:
        if not isinstance(table, Mapping):
            return
        for engine, value in table.items():
            try:
                xf = Xfail.of(engine, value)
                key = (xf.measured_on, xf.range)
            except Exception:  # an invalid entry: the spec's own validation reports it
                continue
            per = out.setdefault(engine, {})
            per[key] = per.get(key, 0) + 1

    for p in sorted(Path(root or SHIPPED_SCENARIOS).rglob("*.toml")):
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        for check in doc.get("check", []) if isinstance(doc.get("check"), list) else []:
            if isinstance(check, Mapping):
                add(check.get("xfail"))
        for variant in doc.get("variant", []) if isinstance(doc.get("variant"), list) else []:
            if isinstance(variant, Mapping):
                for key, value in variant.items():
                    if key.endswith(".xfail"):
                        add(value)
    return out


__all__ = ["BASE_VARIANT", "MEASURED_ON", "Xfail", "default_range", "parse_version", "shipped_xfails", "spec_error", "xfail_for"]
