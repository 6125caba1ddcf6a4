"""Rich consoles for the tables the commands print, legible in CI logs.

A terminal keeps its own width.  Without one (a CI log, a pipe, a file)
rich would fall back to 80 columns and cut names ("bounce_ratio_e...") or
wrap a failures table into fragments: :func:`console` then takes the
``COLUMNS`` environment variable, else :data:`LOG_WIDTH`.  :func:`name_column`
keeps the names a reader greps for (scenarios, test cases, metrics) whole:
never wrapped, never cut (tests/test_cli.py::test_tables_keep_names_whole_without_a_terminal).
"""

from __future__ import annotations

import os
from typing import Any, Iterable

#: width (characters) of tables printed to something that is not a terminal
LOG_WIDTH = 160


def console(stderr: bool = False, file: Any = None) -> Any:
    """A rich Console on stdout (``stderr`` or ``file``): a terminal's own
    width, else ``COLUMNS`` (when a positive integer), else :data:`LOG_WIDTH`."""
    from rich.console import Console

    con = Console(stderr=stderr, file=file)
    if not con.is_terminal:
        try:
            width = int(os.environ.get("COLUMNS", ""))
        except ValueError:
            width = 0
        con = Console(stderr=stderr, file=file, width=width if width > 0 else LOG_WIDTH)
    return con


def name_column(table: Any, header: str, names: Iterable[str], **kw: Any) -> None:
    """Add a column of names to rich ``table`` that is never wrapped nor
    cut: as wide as the longest of ``names`` (the table's other columns
    fold their text instead)."""
    width = max([len(header), *(len(str(n)) for n in names)])
    table.add_column(header, no_wrap=True, overflow="ignore", min_width=width, **kw)
