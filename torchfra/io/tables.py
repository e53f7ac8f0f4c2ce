"""Text tables as DIC programs and data loggers write them: a header line (possibly after preamble
lines), cells split by ``,``, ``;`` or tab, units in the header (``coor.X [mm]``, ``pressure (kPa)``),
empty cells for missing values, decimal commas in ``;``-separated files."""
from __future__ import annotations

import csv
import re
from itertools import islice
from pathlib import Path

import numpy as np

from torchfra.io.files import decode_text, open_binary

MAX_PREAMBLE = 64  # lines searched for the header
MAX_TABLE_BYTES = 1 << 30  # a DIC frame or pressure trace; a bigger one is most likely the wrong file


class DicError(ValueError):
    """A DIC export or pressure trace that cannot be read as it is; the message names the file, line
    or frame and what to do."""


_LINE_END = re.compile(r"\r\n|\r|\n")  # as Python's text files with newline="" split lines
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


def read_lines(path: Path, limit: int | None = None, *, what: str = "DIC export",
               max_bytes: int = MAX_TABLE_BYTES) -> list[str]:
    """The file's lines (the first ``limit`` of them if given), read through :mod:`torchfra.io.files`:
    a missing file, a folder, FIFO or device, a file over ``max_bytes``, UTF-16 or binary (NUL bytes)
    content are refused as :class:`DicError` naming the file; other bytes that are not UTF-8 are read
    as U+FFFD (a header or number holding one is named where it is read)."""
    with open_binary(path, what, max_bytes=max_bytes, error=DicError) as f:
        try:
            raw = b"".join(islice(f, limit)) if limit is not None else f.read(max_bytes + 1)
        except OSError as exc:
            raise DicError(f"{path}: cannot read the {what} file ({exc.strerror})") from exc
    if len(raw) > max_bytes:
        raise DicError(f"{path}: more than {max_bytes} bytes, over the limit for a {what} file; is this the right "
                       "file? If it is, raise the limit (max_bytes=...)")
    text = decode_text(raw, path, what, error=DicError, errors="replace")
    lines = _LINE_END.split(text)
    if lines and lines[-1] == "":
        lines.pop()  # the end of the last line, not a line
    return lines[:limit] if limit is not None else lines
