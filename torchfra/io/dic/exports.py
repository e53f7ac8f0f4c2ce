"""Readers for DIC exports as the software writes them (DESIGN §8), one file per frame.

| format | columns read (headers verbatim) | units | a lost point |
|---|---|---|---|
| ``matchid`` (2024) | ``coor.X [mm]``, ``coor.Y [mm]``, ``coor.Z [mm]``, ``disp.Horizontal Displacement U [mm]``, ``disp.Vertical Displacement V [mm]``, ``disp.Out-Of-Plane: W [mm]``; rows matched by ``Coordinates.Image X/Y [Pixel]`` | in the header | a missing row, or an empty/NaN value |
| ``matchid`` (older) | ``x, y, z, u, v, w``; rows matched by ``x_pic, y_pic`` | none written: the caller's ``units`` | as above |
| ``vic3d`` | ``"X [mm]"`` .. ``"W [mm]"``, ``"sigma"``; ``,`` or ``;`` separated, preamble rows allowed | in the header | ``sigma`` -1 or empty/NaN |
| ``dice`` (2-D) | ``SUBSET_ID, COORDINATE_X, COORDINATE_Y, DISPLACEMENT_X, DISPLACEMENT_Y, SIGMA``; ``***`` preamble | pixels: the caller's ``scale`` (mm per pixel) | ``SIGMA`` -1 |
| ``pyvale`` (2-D) | ``subset_x, subset_y, disp_u, disp_v`` (:mod:`.pyvale`) | pixels: the caller's ``scale`` | NaN displacements |
| ``generic`` | ``x, y, z, u, v, w`` | the caller's ``units`` (mm or m) | an empty/NaN value |

Other columns (strains, image coordinates, correlation data) are ignored. Coordinates are the
points' reference positions in the camera frame; displacements are relative to the reference image.
A directory's files are frames in the order of the frame number in their names (the one number that
differs between the names; natural sort otherwise); the first is the reference (frame 0,
undeformed). Points are identified across frames by ``SUBSET_ID`` (DICe), else by row order, else,
where a frame has a different number of rows, by their image (or reference) coordinates. A point
lost in a frame is NaN there, never zero; a point lost in the reference frame has no reference
position and is left out (listed in ``DicSeries.lost_in_reference``). 2-D (DICe) data lie in the
image plane z = 0 and their out-of-plane displacement is taken as 0, the 2-D DIC assumption.

Everything returned is in mm.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from torchfra.io.dic.pyvale import LAYOUT as PYVALE_LAYOUT
from torchfra.io.tables import MAX_PREAMBLE, DicError, name_unit, read_lines, split_line
from torchfra.observation.recording import Recording, from_table, to_table

ROLES = ("x", "y", "z", "u", "v", "w")
LENGTH_UNITS = {"mm": 1.0, "m": 1e3, "cm": 10.0, "um": 1e-3, "µm": 1e-3, "μm": 1e-3, "in": 25.4}
PIXEL_UNITS = ("pixel", "pixels", "px")
SUFFIXES = (".csv", ".txt", ".dat")


@dataclass(frozen=True)
class Layout:
    """One way a DIC program writes a frame: the header name of each role, without the unit."""

    format: str
    label: str
    columns: dict
    sigma: str | None = None
    ident: str | None = None
    keys: tuple | None = None
    marks: tuple = ()  # further columns that tell this layout from a look-alike
    unit: str | None = None  # assumed when the header gives none; None: the caller must say

    @property
    def two_d(self) -> bool:
        return "z" not in self.columns

    @property
    def required(self) -> tuple:
        return tuple(self.columns.values()) + self.marks


LAYOUTS = (
    Layout("matchid", "MatchID (2024 headers)",
           dict(x="coor.X", y="coor.Y", z="coor.Z", u="disp.Horizontal Displacement U",
                v="disp.Vertical Displacement V", w="disp.Out-Of-Plane: W"),
           keys=("Coordinates.Image X", "Coordinates.Image Y")),
    Layout("matchid", "MatchID (short headers)", dict(x="x", y="y", z="z", u="u", v="v", w="w"),
           keys=("x_pic", "y_pic"), marks=("x_pic", "y_pic")),
    Layout("vic3d", "VIC-3D", dict(x="X", y="Y", z="Z", u="U", v="V", w="W"), sigma="sigma", keys=("x", "y")),
    Layout("dice", "DICe", dict(x="COORDINATE_X", y="COORDINATE_Y", u="DISPLACEMENT_X", v="DISPLACEMENT_Y"),
           sigma="SIGMA", ident="SUBSET_ID", unit="pixel"),
    Layout(**PYVALE_LAYOUT),
    Layout("generic", "generic point cloud", dict(x="x", y="y", z="z", u="u", v="v", w="w")),
)
FORMATS = ("auto",) + tuple(dict.fromkeys(lay.format for lay in LAYOUTS))


def _layouts(fmt: str) -> tuple:
    if fmt not in FORMATS:
        raise DicError(f"unknown format {fmt!r}; use one of {', '.join(FORMATS)}")
    return LAYOUTS if fmt == "auto" else tuple(lay for lay in LAYOUTS if lay.format == fmt)


def expected_columns(layouts=LAYOUTS) -> str:
    """The formats and the columns each needs, for error messages."""
    extra = {lay.label: [c for c in (lay.ident, lay.sigma) if c] for lay in layouts}
    return "; ".join(f"{lay.label}: {', '.join(lay.required + tuple(extra[lay.label]))}" for lay in layouts)


# -- text --------------------------------------------------------------------------------------------------

def find_header(lines: list[str], layouts) -> tuple[int, list[str], str, Layout] | None:
    """First line (within the preamble limit) naming every column of one of ``layouts``."""
    for i, line in enumerate(lines[:MAX_PREAMBLE]):
        cells, delim = split_line(line)
        names = [name_unit(c)[0] for c in cells]
        for lay in layouts:
            if all(c in names for c in lay.required):
                return i, cells, delim, lay
    return None


def header_guess(lines: list[str]) -> list[str]:
    """The first line that looks like a header (non-numeric cells, not a ``***`` comment)."""
    for line in lines[:MAX_PREAMBLE]:
        cells, _ = split_line(line)
        if len(cells) > 1 and not line.lstrip().startswith("*"):
            try:
                [float(c) for c in cells if c]
            except ValueError:
                return cells
    return []


# -- one frame --------------------------------------------------------------------------------------------

@dataclass
class DicFrame:
    """One export file: n rows; X, U (n, 3) mm (NaN for a lost point), ids (n,) or None, keys (n, 2)."""

    path: Path
    layout: Layout
    X: np.ndarray
    U: np.ndarray
    lost: np.ndarray
    ids: np.ndarray | None
    keys: np.ndarray | None
    lines: np.ndarray
    factor: float


def length_factor(path, column: str, unit: str | None, layout: Layout, scale, units) -> float:
    """mm per unit of a coordinate or displacement column."""
    if unit is None:
        unit = layout.unit or units
        if unit is None:
            raise DicError(f"{path}: column {column!r} gives no unit ({layout.label} writes none); give the "
                           "units of the export (mm or m)")
    elif units is not None and unit.lower() != units.lower():
        raise DicError(f"{path}: column {column!r} is in {unit} but units {units} was given; leave units out "
                       "(the header says) or correct it")
    key = unit.lower()
    if key in PIXEL_UNITS:
        if scale is None:
            raise DicError(f"{path}: column {column!r} is in pixels; give the scale in mm per pixel "
                           "(the size of one pixel on the specimen)")
        if not scale > 0:
            raise DicError(f"scale must be a positive number of mm per pixel, got {scale}")
        return float(scale)
    if key not in LENGTH_UNITS:
        raise DicError(f"{path}: column {column!r} has unit {unit!r}; known length units: "
                       f"{', '.join(LENGTH_UNITS)} and pixel (with a scale)")
    return LENGTH_UNITS[key]


def _numbers(path, lines, h: int, delim: str, idx: list[int], n_header: int) -> tuple[np.ndarray, np.ndarray]:
    """Columns ``idx`` of the rows below header line ``h`` as floats (empty: NaN); and the line numbers."""
    numbers = [k for k, line in enumerate(lines[h + 1:], start=h + 2) if line.strip()]
    rows = csv.reader((lines[k - 1] for k in numbers), delimiter=delim)
    try:
        text = np.array([[r[i] for i in idx] for r in rows], dtype=str).reshape(-1, len(idx))
    except IndexError:
        k = next(k for k in numbers if len(next(csv.reader([lines[k - 1]], delimiter=delim))) <= max(idx))
        raise DicError(f"{path}, line {k}: fewer fields than the {n_header} of the header") from None
    text = np.char.strip(text)
    text[text == ""] = "nan"
    if delim != ",":  # decimal commas come with ';' or tab separated files
        text = np.char.replace(text, ",", ".")
    try:
        return text.astype(np.float64), np.asarray(numbers, dtype=np.int64)
    except ValueError:
        bad = next(i for i, row in enumerate(text) if not all(_is_number(c) for c in row))
        raise DicError(f"{path}, line {numbers[bad]}: cannot read {lines[numbers[bad] - 1].strip()!r} as "
                       "numbers") from None


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def read_frame(path, fmt: str = "auto", *, scale=None, units=None) -> DicFrame:
    """Read one export file (any supported layout, detected from its header)."""
    path = Path(path)
    layouts = _layouts(fmt)
    lines = read_lines(path, what="DIC frame")
    found = find_header(lines, layouts)
    if found is None:
        seen = header_guess(lines)
        raise DicError(f"{path}: not a {'known DIC export' if fmt == 'auto' else fmt + ' export'}; columns found: "
                       f"{', '.join(seen) if seen else '(no header line)'}. Expected one of: "
                       f"{expected_columns(layouts)}")
    h, cells, delim, lay = found
    names = [name_unit(c)[0] for c in cells]
    numeric = [c for c in names if c and _is_number(c)]
    if numeric:  # a header holding numbers: a data row joined to it (its values would be lost as column names)
        raise DicError(f"{path}, line {h + 1}: the header holds numbers ({', '.join(numeric[:4])}"
                       f"{', ...' if len(numeric) > 4 else ''}) among its column names; is a row joined to it? "
                       "Put the header on a line of its own")
    col = {n: i for i, n in reversed(list(enumerate(names)))}
    wanted = dict(lay.columns)
    extras = dict(sigma=lay.sigma, ident=lay.ident, **dict(zip(("key0", "key1"), lay.keys or ())))
    wanted.update({role: c for role, c in extras.items() if c and c in col})
    table, numbers = _numbers(path, lines, h, delim, [col[c] for c in wanted.values()], len(names))
    v = dict(zip(wanted, table.T))
    units_of = {r: name_unit(cells[col[c]])[1] for r, c in lay.columns.items()}
    factor = {r: length_factor(path, lay.columns[r], units_of[r], lay, scale, units) for r in lay.columns}
    n = len(table)
    X = np.zeros((n, 3))
    U = np.zeros((n, 3))
    for j, (rx, ru) in enumerate(zip("xyz", "uvw")):
        if rx in v:
            X[:, j] = v[rx] * factor[rx]
            U[:, j] = v[ru] * factor[ru]
    lost = ~np.all(np.isfinite(X), axis=1) | ~np.all(np.isfinite(U), axis=1)
    if "sigma" in v:
        lost |= ~np.isfinite(v["sigma"]) | (v["sigma"] == -1)
    U[lost] = np.nan
    ids = None
    if "ident" in v:
        ids = v["ident"]
        bad = np.flatnonzero(~np.isfinite(ids) | (ids != np.round(ids)))
        if bad.size:
            raise DicError(f"{path}, line {numbers[bad[0]]}: {lay.ident} must be an integer")
        ids = ids.astype(np.int64)
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            raise DicError(f"{path}: {lay.ident} {uniq[counts > 1][0]} appears {counts.max()} times; ids must be unique")
    keys = None
    if "key0" in v and "key1" in v:
        keys = np.stack([v["key0"], v["key1"]], axis=1)
    return DicFrame(path, lay, X, U, lost, ids, keys, np.asarray(numbers, dtype=np.int64), factor["x"])


# -- a series of frames -------------------------------------------------------------------------------------

@dataclass
class DicSeries:
    """K frames x P points: frames (K,) numbers, files (K,), point_ids (P,), X (P, 3) mm reference
    positions (camera frame), U (K, P, 3) mm displacements with NaN where lost; ``ignored`` the
    entries of the export folder that are not frames and ``ignored_why`` why; ``merged_duplicates``
    (kept id, merged id) of points written twice."""

    layout: Layout
    files: list
    frames: np.ndarray
    point_ids: np.ndarray
    X: np.ndarray
    U: np.ndarray
    factor: float
    frames_from_names: bool
    lost_in_reference: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    unmatched_rows: int = 0
    ignored: list = field(default_factory=list)
    ignored_why: list = field(default_factory=list)
    merged_duplicates: list = field(default_factory=list)

    @property
    def two_d(self) -> bool:
        return self.layout.two_d


def natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def frame_numbers(names: list[str]) -> tuple[list[int], bool]:
    """Frame numbers of files: the one number that differs between the names (``spec_0012_0.csv``:
    12), or the natural-sort position if no single number does. Returns (numbers, from_names)."""
    parts = [re.split(r"(\d+)", Path(n).name) for n in names]
    same_shape = len({len(p) for p in parts}) == 1 and len({tuple(p[::2]) for p in parts}) == 1
    if len(names) > 1 and same_shape:
        numbered = range(1, len(parts[0]), 2)
        varying = [j for j in numbered if len({int(p[j]) for p in parts}) > 1]
        if len(varying) == 1 or (not varying and len(numbered) == 1):  # one number: the frame's, even if repeated
            j = varying[0] if varying else numbered[0]
            return [int(p[j]) for p in parts], True
    order = sorted(range(len(names)), key=lambda i: natural_key(Path(names[i]).name))
    rank = {i: r for r, i in enumerate(order)}
    return [rank[i] for i in range(len(names))], False


def _why_not_a_frame(path: Path, layouts) -> str | None:
    """Why a file of an export folder is not a frame of it (None: it is one)."""
    try:
        head = read_lines(path, MAX_PREAMBLE)
    except DicError as exc:  # not a regular file, binary, UTF-16, too big: the reading layer says which
        return str(exc).removeprefix(f"{path}: ").split(";")[0]
    return None if find_header(head, layouts) is not None else "no DIC export header"


def export_files(source, fmt: str = "auto", exclude=()) -> tuple[list[Path], list[Path], list[str]]:
    """The frame files of ``source`` (a directory, a file, or a list of files) and, for a directory,
    the entries skipped (every one but the frames and ``exclude``) with why each was skipped: no
    supported header, not a .csv/.txt/.dat file, or not readable as text (a FIFO, a device, a binary or
    UTF-16 file, ...)."""
    layouts = _layouts(fmt)
    sources = [Path(s) for s in ([source] if isinstance(source, (str, Path)) else source)]
    if not sources:
        raise DicError("no DIC export given")
    skip = {Path(e).resolve() for e in exclude}
    if len(sources) == 1 and sources[0].is_dir():
        d = sources[0]
        entries = sorted((p for p in d.iterdir() if p.resolve() not in skip), key=lambda p: natural_key(p.name))
        files, ignored, why = [], [], []
        for p in entries:
            reason = (_why_not_a_frame(p, layouts) if p.suffix.lower() in SUFFIXES
                      else "a folder" if p.is_dir() else f"not a {'/'.join(SUFFIXES)} file")
            if reason is None:
                files.append(p)
            else:
                ignored.append(p)
                why.append(reason)
        if not files:
            candidates = [p for p in entries if p.suffix.lower() in SUFFIXES and p.is_file()]
            seen = []
            if candidates:
                try:
                    seen = header_guess(read_lines(candidates[0], MAX_PREAMBLE))
                except DicError:
                    seen = []
            raise DicError(f"{d}: no {'DIC export' if fmt == 'auto' else fmt + ' export'} among its "
                           f"{len(candidates)} .csv/.txt/.dat files"
                           + (f"; columns found: {', '.join(seen)} (in {candidates[0].name})" if seen else "")
                           + f". Expected one of: {expected_columns(layouts)}")
        return files, ignored, why
    missing = [str(p) for p in sources if not p.exists()]
    if missing:
        raise DicError(f"no such export file or directory: {', '.join(missing)}")
    return sources, [], []


def read_dic(source, fmt: str = "auto", *, scale=None, units=None, exclude=(), allow_gaps: bool = False) -> DicSeries:
    """Read a DIC export: a directory of per-frame files, one file, or a list of files (see the
    module docstring). ``scale``: mm per pixel (pixel exports); ``units``: mm or m for exports whose
    headers give none; ``exclude``: files of the directory that are not frames (the pressure trace).
    Frame numbers taken from the file names must run without a gap (a frame file lost or unreadable)
    unless ``allow_gaps``; reference points at the same position are merged when they carry the same
    data in every frame (a row written twice), and refused otherwise."""
    files, ignored, why = export_files(source, fmt, exclude)
    frames = [read_frame(p, fmt, scale=scale, units=units) for p in files]
    labels = {f.layout.label for f in frames}
    if len(labels) > 1:
        counts = {lab: sum(f.layout.label == lab for f in frames) for lab in labels}
        raise DicError(f"the export mixes layouts ({', '.join(f'{k}: {v} files' for k, v in counts.items())}); "
                       "give the files of one export, or the format")
    numbers, from_names = frame_numbers([str(p) for p in files])
    order = np.argsort(numbers, kind="stable")
    numbers = np.asarray(numbers)[order]
    frames = [frames[i] for i in order]
    dup = np.flatnonzero(np.diff(numbers) == 0)
    if dup.size:
        k = int(dup[0])
        raise DicError(f"{frames[k].path.name} and {frames[k + 1].path.name} are both frame {numbers[k]}; "
                       "keep one export per frame")
    gaps = np.flatnonzero(np.diff(numbers) > 1)
    if from_names and gaps.size and not allow_gaps:
        missing = [int(n) for g in gaps for n in range(numbers[g] + 1, numbers[g + 1])]
        shown = ", ".join(map(str, missing[:10])) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
        skipped = "; ".join(f"{p.name} ({w})" for p, w in zip(ignored, why) if w != "no DIC export header")
        raise DicError(f"the export's frames {numbers[0]}..{numbers[-1]} have a gap: frame(s) {shown} missing"
                       + (f" (skipped: {skipped})" if skipped else "")
                       + "; restore the missing files, or allow the gap (allow_gaps, --allow-gaps) if the export "
                       "skips frames on purpose")
    ref = frames[0]
    ids = ref.ids if ref.ids is not None else np.arange(len(ref.X))
    keep = ~ref.lost
    if not keep.any():
        raise DicError(f"{ref.path}: every point is lost in the reference frame")
    P = int(keep.sum())
    U = np.full((len(frames), P, 3), np.nan)
    U[0] = ref.U[keep]
    unmatched = 0
    for k, fr in enumerate(frames[1:], start=1):
        rows, target = _match_rows(ref, fr, keep)
        U[k, target] = fr.U[rows]
        unmatched += len(fr.X) - len(rows)
    X, point_ids = ref.X[keep], ids[keep]
    unique, merged = _merge_duplicates(ref, keep, X, U, point_ids)
    return DicSeries(ref.layout, [f.path for f in frames], numbers, point_ids[unique], X[unique], U[:, unique],
                     ref.factor, from_names, ids[~keep], unmatched, ignored, why, merged)


def _merge_duplicates(ref: DicFrame, keep: np.ndarray, X: np.ndarray, U: np.ndarray, ids: np.ndarray):
    """Indices of the points to keep and the (kept id, merged id) pairs of points written twice: the
    same reference position (to 1e-9 mm) and the same displacements in every frame. Two points at one
    position with different data are refused (which one is the point?)."""
    _, first, inverse = np.unique(np.round(X, 9), axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if first.size == len(X):
        return np.arange(len(X)), []
    lines = ref.lines[keep]
    merged, drop = [], np.zeros(len(X), dtype=bool)
    for i in np.flatnonzero(first[inverse] != np.arange(len(X))):
        j = first[inverse[i]]
        if not np.array_equal(U[:, i], U[:, j], equal_nan=True):
            k = int(np.flatnonzero((~np.isclose(U[:, i], U[:, j], rtol=0, atol=0, equal_nan=True)).any(axis=1))[0])
            raise DicError(f"{ref.path}, lines {lines[j]} and {lines[i]}: points {ids[j]} and {ids[i]} lie at the same "
                           f"reference position {X[i].round(6).tolist()} but differ in frame index {k}; a point must be "
                           "exported once: remove the duplicate rows (or the duplicated subset) from the export")
        merged.append((int(ids[j]), int(ids[i])))
        drop[i] = True
    return np.flatnonzero(~drop), merged


def _match_rows(ref: DicFrame, fr: DicFrame, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``fr`` and the reference point (index among kept points) each one is."""
    slot = np.cumsum(keep) - 1  # reference row -> kept point index
    if ref.ids is not None:
        if fr.ids is None:
            raise DicError(f"{fr.path}: no {ref.layout.ident} column, but the reference frame has one")
        pos = {int(i): r for r, i in enumerate(ref.ids)}
        pairs = [(r, pos[int(i)]) for r, i in enumerate(fr.ids) if int(i) in pos]
    elif len(fr.X) == len(ref.X):
        pairs = [(r, r) for r in range(len(ref.X))]
    else:
        by_keys = ref.keys is not None and fr.keys is not None
        a, b = (ref.keys, fr.keys) if by_keys else (ref.X, fr.X)
        finite_a = np.all(np.isfinite(a), axis=1)
        tree = cKDTree(a[finite_a])
        gap = tree.query(a[finite_a], k=2)[0][:, 1] if finite_a.sum() > 1 else np.ones(1)
        spacing = float(np.median(gap))
        if gap.min() <= 1e-3 * spacing:
            what = "image coordinates" if by_keys else "coordinates"
            raise DicError(f"{fr.path}: {len(fr.X)} rows against {len(ref.X)} in the reference, and reference rows "
                           f"share their {what}, so rows cannot be matched; export every point in every frame")
        ok_b = np.all(np.isfinite(b), axis=1)
        dist, nearest = tree.query(np.where(ok_b[:, None], b, 0.0))
        hit = ok_b & (dist <= 1e-3 * spacing)
        ref_rows = np.flatnonzero(finite_a)[nearest]
        pairs = [(r, int(ref_rows[r])) for r in np.flatnonzero(hit)]
        if not pairs:
            what = "image coordinates" if by_keys else "reference coordinates"
            raise DicError(f"{fr.path}: {len(fr.X)} rows against {len(ref.X)} in the reference and none matches a "
                           f"reference point by its {what}; is this file from the same export?")
    pairs = [(r, s) for r, s in pairs if keep[s]]
    rows = np.asarray([r for r, _ in pairs], dtype=np.int64)
    return rows, slot[np.asarray([s for _, s in pairs], dtype=np.int64)]


# -- landmarks ------------------------------------------------------------------------------------------------

def read_landmarks(path, series: DicSeries) -> tuple[np.ndarray, np.ndarray]:
    """Landmark pairs (DIC point -> model point) from a CSV with columns ``dic_x,dic_y,dic_z,model_x,
    model_y,model_z`` (DIC side in the export's own units, e.g. pixels or m; ``dic_z`` may be left out
    for 2-D data) or ``point_id,model_x,model_y,model_z`` (a DIC point by its id). Model side in mm.
    Returns (src (L, 3) mm camera frame, dst (L, 3) mm model frame)."""
    path = Path(path)
    lines = [ln for ln in read_lines(path, what="landmark") if ln.strip()]
    if not lines:
        raise DicError(f"{path}: the landmark file is empty")
    header, delim = split_line(lines[0])
    header = [name_unit(c)[0].lower() for c in header]
    need = ["model_x", "model_y", "model_z"]
    by_id = "point_id" in header
    need_dic = ["point_id"] if by_id else ["dic_x", "dic_y"] + (["dic_z"] if "dic_z" in header or not series.two_d else [])
    missing = [c for c in need_dic + need if c not in header]
    if missing:
        raise DicError(f"{path}: landmark columns {', '.join(missing)} missing (got {', '.join(header)}); write "
                       "dic_x,dic_y,dic_z,model_x,model_y,model_z or point_id,model_x,model_y,model_z")
    rows = []
    for k, line in enumerate(lines[1:], start=2):
        cells = next(csv.reader([line], delimiter=delim))
        try:
            rows.append([float(cells[header.index(c)]) for c in need_dic + need])
        except (ValueError, IndexError):
            raise DicError(f"{path}, line {k}: cannot read {line.strip()!r} as a landmark") from None
    table = np.asarray(rows, dtype=np.float64).reshape(-1, len(need_dic) + 3)
    dst = table[:, -3:]
    if by_id:
        pos = {int(i): r for r, i in enumerate(series.point_ids)}
        bad = [int(i) for i in table[:, 0] if int(i) not in pos]
        if bad:
            raise DicError(f"{path}: landmark point id(s) {bad} are not points of the reference frame")
        src = series.X[[pos[int(i)] for i in table[:, 0]]]
    else:
        src = np.zeros((len(table), 3))
        src[:, : len(need_dic)] = table[:, : len(need_dic)] * series.factor
    return src, dst


# -- to the recording contract -------------------------------------------------------------------------------

def to_recording(series: DicSeries, times, pressure, registration, source: str = "dic") -> Recording:
    """The recording (DESIGN §6) of the points the registration kept on the face: reference
    coordinates are their closest face points (mm, model frame), displacements the DIC ones turned
    into the model frame (``registration.transform.vectors``), observed components y and z."""
    keep = registration.inlier
    if not keep.any():
        raise DicError(f"no DIC point lies within {registration.tol:g} mm of the face; nothing to record")
    U = registration.transform.vectors(series.U[:, keep])
    rec = Recording(np.asarray(series.frames), np.asarray(times, dtype=np.float64),
                    np.asarray(pressure, dtype=np.float64), series.point_ids[keep],
                    registration.on_face[keep], U[..., 1:3], source)
    return from_table(to_table(rec), source)
