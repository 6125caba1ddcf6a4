"""Dotted-key overrides of a raw spec document: variants and ``--set``
(``body[1].mass``, ``material.default.restitution``)."""

from __future__ import annotations

import re
import tomllib
from typing import Any

from physbench.contract.spec.errors import _loc_to_path

_TOKEN = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def parse_key_path(path: str) -> list[str | int]:
    """'body[1].mass' or 'body.1.mass' -> ['body', 1, 'mass'].  Quoted table
    names are not needed: material names cannot contain dots."""
    parts: list[str | int] = []
    pos = 0
    for m in _TOKEN.finditer(path):
        if m.start() != pos and path[pos:m.start()] != ".":
            raise ValueError(f"malformed key path {path!r}")
        pos = m.end()
        if m.group(2) is not None:
            parts.append(int(m.group(2)))
        else:
            tok = m.group(1)
            parts.append(int(tok) if tok.isdigit() else tok)
    if pos != len(path) or not parts:
        raise ValueError(f"malformed key path {path!r}")
    return parts


def apply_override(raw: dict[str, Any], path: str, value: Any) -> None:
    """Set ``value`` at dotted ``path`` inside ``raw`` (in place).  The parent
    table must exist; list indices must be in range.  Raises ValueError with a
    message naming the path."""
    parts = parse_key_path(path)
    node: Any = raw
    for i, part in enumerate(parts[:-1]):
        where = _loc_to_path(tuple(parts[: i + 1]))
        if isinstance(part, int):
            if not isinstance(node, list) or not -len(node) <= part < len(node):
                n = len(node) if isinstance(node, list) else 0
                raise ValueError(f"{where}: no such entry (there are {n})")
            node = node[part]
        else:
            if not isinstance(node, dict):
                raise ValueError(f"{where}: parent is not a table")
            if part not in node:
                if part in ("material", "reference") or (i >= 1 and parts[0] in ("material",)):
                    node[part] = {}
                else:
                    raise ValueError(f"{where}: no such table")
            node = node[part]
    last = parts[-1]
    if isinstance(last, int):
        if not isinstance(node, list) or not -len(node) <= last < len(node):
            raise ValueError(f"{_loc_to_path(tuple(parts))}: no such entry")
        node[last] = value
    else:
        if not isinstance(node, dict):
            raise ValueError(f"{_loc_to_path(tuple(parts))}: parent is not a table")
        node[last] = value


def parse_value(text: str) -> Any:
    """Parse a --set value as a TOML value ('1e-3', 'true', '[1,2,3]', '"rk4"');
    bare words are taken as strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        return text
