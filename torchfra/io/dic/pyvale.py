"""pyvale's 2-D DIC export (``pyvale.dic.calculate_2d``, CSV text output), as its engine writes it.

One file per deformed image, ``<output_prefix><image name>.csv`` (default
``dic_results_def_img_0000.csv``, ``..._0001.csv``, ...), a header line and one row per subset::

    "subset_x","subset_y","disp_u","disp_v","disp_mag","converged","cost_zncc","ftol","xtol","num_iter",

(the header ends with a delimiter; rows do not). ``subset_x, subset_y`` are the subset's centre in
the *reference* image in pixels (column, row: y runs down the image), ``disp_u, disp_v`` its
displacement in pixels to the deformed image, ``disp_v`` positive downwards, at that reference centre
(Lagrangian); a subset that did not converge or fell below the correlation threshold is a row of
NaN displacements with ``converged`` 0. Every file lists the same subsets in the same order.
These conventions were checked against images warped by known displacements
(tests/test_virtual_dic.py, on a file the engine wrote: tests/data/pyvale/).

:data:`LAYOUT` is the layout the DIC importer (:mod:`torchfra.io.dic.exports`) detects as format
``pyvale`` (lengths in pixels: the caller's ``scale`` in mm per pixel, image y down); the
importer reads it like any export. :func:`read_pyvale_file` reads one file as the engine's own
quantities, the correlation's quality columns included.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfra.io.tables import DicError, name_unit, read_lines, split_line

# role -> header name, as the importer's layouts write them (x, y: reference subset centre; u, v: its displacement)
COLUMNS = {"x": "subset_x", "y": "subset_y", "u": "disp_u", "v": "disp_v"}
MARKS = ("converged", "cost_zncc")  # the columns that tell pyvale's export from another 2-D layout
# the importer's layout (torchfra.io.dic.exports.Layout's fields): a subset is known across frames by its
# reference centre; lengths in pixels
LAYOUT = dict(format="pyvale", label="pyvale 2-D DIC", columns=COLUMNS, keys=("subset_x", "subset_y"), marks=MARKS,
              unit="pixel")


@dataclass(frozen=True)
class PyvaleFrame:
    """One pyvale result file, S subsets: ``xy`` (S, 2) reference centres (col, row) pixels, ``uv``
    (S, 2) displacements (u right, v down) pixels, NaN where lost, ``converged`` (S,) bool,
    ``cost`` (S,) the ZNCC correlation coefficient (NaN where lost)."""

    path: Path
    xy: np.ndarray
    uv: np.ndarray
    converged: np.ndarray
    cost: np.ndarray


def read_pyvale_file(path) -> PyvaleFrame:
    """Read one pyvale 2-D result file (CSV text output; see the module's docstring).

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    PyvaleFrame
        Its subsets in pixels, lost ones NaN.

    Raises
    ------
    DicError
        A file that is not a pyvale export (naming the columns found and those needed) or a row
        that cannot be read (naming its line).
    """
    path = Path(path)
    lines = [ln for ln in read_lines(path)]
    if not lines:
        raise DicError(f"{path}: empty file; a pyvale export has a header line and one row per subset")
    cells, delim = split_line(lines[0])
    names = [name_unit(c)[0] for c in cells]
    need = list(COLUMNS.values()) + list(MARKS)
    missing = [c for c in need if c not in names]
    if missing:
        raise DicError(f"{path}: not a pyvale 2-D DIC export: columns {', '.join(missing)} missing (found "
                       f"{', '.join(n for n in names if n) or 'none'}); pyvale.dic.calculate_2d writes "
                       f"{', '.join(need)} in its CSV output (output_binary=False)")
    idx = [names.index(c) for c in need]
    rows = []
    for k, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(delim)
        try:
            rows.append([float(parts[i]) for i in idx])
        except (ValueError, IndexError):
            raise DicError(f"{path}, line {k}: cannot read {line.strip()!r} as the numbers of a subset "
                           f"({', '.join(need)})") from None
    if not rows:
        raise DicError(f"{path}: a header but no subset rows; did the correlation find no subset in the ROI?")
    t = np.asarray(rows, dtype=np.float64)
    converged = t[:, 4] == 1
    uv = t[:, 2:4].copy()
    uv[~converged | ~np.all(np.isfinite(uv), axis=1)] = np.nan
    return PyvaleFrame(path, t[:, 0:2], uv, converged & np.all(np.isfinite(uv), axis=1), t[:, 5])
