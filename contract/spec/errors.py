"""Spec errors and their wording: :class:`SpecError` (one line per problem,
``<file>: <key path>: <expected, found>``, exit 2) and the translation of
pydantic's validation errors into such lines."""

from __future__ import annotations

import re
from typing import Any

from pydantic import ValidationError

from physbench.contract.models import ReferenceError

class SpecError(ValueError):
    """A scenario spec failed to load.  ``errors`` holds one line per problem,
    each ``<file>: <key path>: <what was expected, what was found>``."""

    def __init__(self, errors: list[str]):
        self.errors = list(errors)
        super().__init__("\n".join(self.errors))


class ModelRefusal(SpecError, ReferenceError):
    """The scene's reference model refused the scene at load time: a spec
    error (file, key path, exit 2) that is also the model's
    :class:`contract.models.ReferenceError`."""

# --------------------------------------------------------------------------
# error formatting


def _loc_to_path(loc: tuple[Any, ...]) -> str:
    """pydantic loc ('body', 1, 'mass') -> 'body[1].mass'."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("function-after[_dims_and_mass(), BodySection]",):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out


_CMP = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _describe(err: dict[str, Any]) -> str:
    t = err["type"]
    ctx = err.get("ctx") or {}
    got = err.get("input")
    if t in _CMP:
        bound = next(iter(ctx.values()))
        if isinstance(bound, float) and bound.is_integer():
            bound = int(bound)
        return f"must be {_CMP[t]} {bound}, got {got!r}"
    if t == "extra_forbidden":
        return "unknown key"
    if t == "missing":
        return "required key is missing"
    if t == "finite_number":
        return f"must be a finite number, got {got!r}"
    if t in ("float_parsing", "float_type"):
        return f"expected a number, got {got!r}"
    if t in ("int_parsing", "int_type", "int_from_float"):
        return f"expected an integer, got {got!r}"
    if t in ("bool_type", "bool_parsing"):
        return f"expected true or false, got {got!r}"
    if t in ("string_type",):
        return f"expected a string, got {got!r}"
    if t in ("list_type", "tuple_type"):
        return f"expected a list, got {got!r}"
    if t in ("dict_type", "model_type", "model_attributes_type"):
        return f"expected a table, got {got!r}"
    if t == "too_short" or t == "too_long":
        exp = ctx.get("min_length") if t == "too_short" else ctx.get("max_length")
        n = ctx.get("actual_length")
        if isinstance(got, (list, tuple)):
            return f"expected {exp} values, got {n}: {list(got)}"
        return f"expected length {'>=' if t == 'too_short' else '<='} {exp}, got {got!r}"
    if t == "string_too_short":
        return "must not be empty"
    if t == "literal_error":
        return f"expected one of {ctx.get('expected')}, got {got!r}"
    if t == "value_error":
        msg = str(ctx.get("error", err["msg"]))
        return msg
    return f"{err['msg']}, got {got!r}"


_VECTOR_LEN = {"orientation": 4, "counts": 3}


def _lookup(raw: Any, loc: tuple[Any, ...]) -> Any:
    node = raw
    for part in loc:
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            return None
    return node


def _format_errors(file: str, exc: ValidationError, raw: Any = None) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and "[" in p and "(" in p))
        # Union members add their type name to loc ('float', 'tuple[...]'); drop them.
        loc = tuple(
            p for p in loc if not (isinstance(p, str) and (p in ("float", "bool", "int") or p.startswith("tuple[")))
        )
        if err["type"] in ("missing", "too_long") and loc and isinstance(loc[-1], int) or (
                err["type"] == "too_long" and isinstance(err.get("input"), (list, tuple))):
            # a fixed-length vector with too few / too many values
            if isinstance(loc[-1], int):
                loc = loc[:-1]
            want = _VECTOR_LEN.get(str(loc[-1]), 3) if loc else 3
            got = _lookup(raw, loc)
            lines.append(f"{file}: {_loc_to_path(loc)}: expected {want} numbers, got {len(got) if isinstance(got, (list, tuple)) else got!r}: {got!r}")
            continue
        path = _loc_to_path(loc)
        msg = _describe(err)
        # value errors raised about an element carry their own '[i]' prefix
        m = re.match(r"^\[(\d+)\] (.*)$", msg)
        if m:
            path, msg = f"{path}[{m.group(1)}]", m.group(2)
        lines.append(f"{file}: {path or '<top>'}: {msg}")
    # unions can report the same problem once per member: keep first of each path
    seen: dict[str, str] = {}
    for line in lines:
        key = line.rsplit(": ", 1)[0]
        seen.setdefault(key, line)
    return list(seen.values())

