"""Text tables as DIC programs and data loggers write them: a header line (possibly after preamble
lines), cells split by ``,``, ``;`` or tab, units in the header (``coor.X [mm]``, ``pressure (kPa)``),
empty cells for missing values, decimal commas in ``;``-separated files."""
from __future__ import annotations

import csv
import re
from itertools import islice
from pathlib import Path

import numpy as np

MAX_PREAMBLE = 64  # lines searched for the header


class DicError(ValueError):
    """A DIC export or pressure trace that cannot be read as it is; the message names the file, line
    or frame and what to do."""


_UNIT = re.compile(r"^(.*?)\s*[\[(]\s*([^\])]*?)\s*[\])]\s*$")


def name_unit(cell: str) -> tuple[str, str | None]:
    """``"coor.X [mm]"`` -> ``("coor.X", "mm")``; ``"x"`` -> ``("x", None)``; ``[ ]`` -> ``""``."""
    cell = cell.strip().strip('"').strip()
    m = _UNIT.match(cell)
    return (m.group(1).strip(), m.group(2)) if m else (cell, None)


def split_line(line: str) -> tuple[list[str], str]:
    """Cells of one text line and the delimiter (``,``, ``;`` or tab: whichever gives most cells)."""
    best = ([line.strip()], ",")
    for delim in (",", ";", "\t"):
        cells = next(csv.reader([line], delimiter=delim), [])
        if len(cells) > len(best[0]):
            best = (cells, delim)
    return [c.strip() for c in best[0]], best[1]


def to_float(text: str, decimal_comma: bool) -> float:
    """A cell as a number; empty is NaN."""
    text = text.strip()
    if not text:
        return np.nan
    try:
        return float(text)
    except ValueError:
        if decimal_comma:
            return float(text.replace(",", "."))
        raise


def read_lines(path: Path, limit: int | None = None) -> list[str]:
    """The file's lines (the first ``limit`` of them if given)."""
    try:
        with open(path, newline="", encoding="utf-8-sig", errors="replace") as f:
            return [ln.rstrip("\r\n") for ln in islice(f, limit)]
    except OSError as exc:
        raise DicError(f"{path}: cannot read ({exc.strerror})") from exc
