"""The recording file formats (DESIGN §6) read defensively: what is not a recording is named, not guessed.

CSV is read line by line as UTF-8 text (a UTF-8 byte-order mark is skipped) with ``,``, ``;`` or tab
as the delimiter (the one under which the header names the columns); every row must have as many
fields as the header, so a stray delimiter cannot shift values into the wrong column. Refused before
any parsing: a gzip or zip file, UTF-16 text; while reading: NUL bytes (a binary file), a line that
is not UTF-8, a line longer than ``max_line_bytes``, more than ``max_rows`` rows.

NPZ is opened as a zip archive and each array's ``.npy`` header is checked before its data is read:
numbers only (an object array would need unpickling and is refused), at most ``max_rows`` entries.
Two layouts hold the same table:

- long: every array 1-D, one entry per point per frame (or all arrays of one common shape, read
  entry by entry);
- grid: ``frame`` (K,) and ``point_id`` (P,) are the axes; ``uy``, ``uz`` are (K, P) and each other
  array is (K, P) or, by its meaning, (K,) (``time``, ``pressure``) or (P,) (``X``, ``Y``, ``Z``).
  A (P, K) array is refused as transposed rather than reshaped (when K = P no shape can tell).
"""
from __future__ import annotations

import csv
import itertools
import zipfile
import zlib
from pathlib import Path

import numpy as np

from torchfra.io.files import check_regular, open_binary
from torchfra.observation.recording import (
    COLUMNS,
    MAX_FRAME_POINTS,
    MAX_LINE_BYTES,
    MAX_ROWS,
    Recording,
    RecordingError,
    from_table,
    to_table,
)

_CHUNK = 1 << 16  # rows converted to an array at a time, so memory grows by arrays, not Python floats
_DELIMITERS = (",", ";", "\t")
_PER_FRAME, _PER_POINT = ("time", "pressure"), ("X", "Y", "Z")
_BLANK = " \t"  # str.strip() alone would also drop control characters such as \x1c around a number


def _raise_limit(where, what: str, name: str, value: int):
    raise RecordingError(f"{where}: {what} (limit {name} = {value}); if the file is right, raise the limit with "
                         f"read_recording(..., {name}=...)")


def _refuse_non_text(path: Path, head: bytes) -> None:
    if head.startswith(b"\x1f\x8b"):
        raise RecordingError(f"{path}: the file is gzip-compressed; decompress it (gunzip) and read the CSV inside")
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        raise RecordingError(f"{path}: the file is a zip archive (an NPZ or a spreadsheet?), not CSV text; "
                             "name an NPZ recording .npz, or export the sheet as CSV")
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise RecordingError(f"{path}: the file is UTF-16; save it as UTF-8")


def _text_lines(f, path: Path, max_line_bytes: int):
    """Physical lines of a binary file as str, checked one by one."""
    for number in itertools.count(1):
        raw = f.readline(max_line_bytes + 1)
        if not raw:
            return
        if len(raw) > max_line_bytes and not raw.endswith(b"\n"):
            _raise_limit(f"{path}, line {number}", f"a line longer than {max_line_bytes} bytes", "max_line_bytes",
                         max_line_bytes)
        if b"\0" in raw:
            raise RecordingError(f"{path}, line {number}: NUL bytes: the file is binary, not CSV text")
        if number == 1 and raw.startswith(b"\xef\xbb\xbf"):
            raw = raw[3:]  # UTF-8 byte-order mark, as spreadsheet programs write it
        try:
            yield raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise RecordingError(f"{path}, line {number}: byte 0x{raw[exc.start]:02x} at column {exc.start + 1} "
                                 "is not UTF-8 text; save the file as UTF-8") from exc


def _header(first: str) -> tuple[str, list[str]]:
    """The delimiter under which the first line names the most columns (ties: comma), and the names."""
    best = None
    for d in _DELIMITERS:
        names = [h.strip(_BLANK) for h in next(csv.reader([first], delimiter=d), [])]
        score = sum(c in names for c in COLUMNS)
        if best is None or score > best[0]:
            best = (score, d, names)
    return best[1], best[2]


def _csv_error(path: Path, line: int, exc: csv.Error) -> RecordingError:
    if "field larger than field limit" in str(exc):
        return RecordingError(f"{path}, line {line}: a field longer than {csv.field_size_limit()} characters; a "
                              "recording's fields are numbers: is this the right file?")
    if "new-line character" in str(exc):
        return RecordingError(f"{path}, line {line}: a carriage return inside a line; save the file with "
                              "\\n or \\r\\n line endings")
    return RecordingError(f"{path}, line {line}: not readable as CSV ({exc})")


def _number(s: str) -> float:
    """A field as a float: empty or NaN = missing; ASCII decimal only (Python's float() would also
    take '1_000' and non-ASCII digits, which no camera software writes); blanks are spaces and tabs."""
    s = s.strip(_BLANK)
    if not s:
        return np.nan
    if not s.isascii() or "_" in s:
        raise ValueError(f"not a decimal number: {s!r}")
    return float(s)


def table_from_csv(path: Path, max_line_bytes: int = MAX_LINE_BYTES, max_rows: int = MAX_ROWS) -> dict[str, np.ndarray]:
    with open_binary(path, "recording", error=RecordingError) as f:
        _refuse_non_text(path, f.read(4))
        f.seek(0)
        lines = _text_lines(f, path, max_line_bytes)
        first = next(lines, None)
        if first is None:
            raise RecordingError(f"{path}: the file is empty; a recording needs the header "
                                 f"{','.join(COLUMNS)} and one row per point per frame")
        reader = None
        try:
            delimiter, header = _header(first)
            missing = [c for c in COLUMNS if c not in header]
            if missing:
                raise RecordingError(f"{path}: missing column(s) {', '.join(missing)}; the header must name "
                                     f"{','.join(COLUMNS)} (got {','.join(header)})")
            twice = sorted({h for h in header if h in COLUMNS and header.count(h) > 1})
            if twice:
                raise RecordingError(f"{path}: column(s) {', '.join(twice)} appear more than once in the header")
            col = [header.index(c) for c in COLUMNS]
            reader = csv.reader(lines, delimiter=delimiter)
            chunks, rows, n_rows = [], [], 0
            for row in reader:
                if not row or all(not v.strip(_BLANK) for v in row):
                    continue
                line = reader.line_num + 1  # the header was read apart
                if len(row) != len(header):
                    raise RecordingError(f"{path}, line {line}: {len(row)} fields, but the header has "
                                         f"{len(header)}; every row needs one field per column (empty = missing)")
                try:
                    rows.append([_number(row[j]) for j in col])
                except ValueError as exc:
                    hint = " (a decimal comma? write 0.5, not 0,5)" if delimiter != "," and "," in "".join(row) else ""
                    raise RecordingError(f"{path}, line {line}: cannot read {row!r} as numbers ({exc}){hint}") from exc
                n_rows += 1
                if n_rows > max_rows:
                    _raise_limit(path, f"more than {max_rows} rows", "max_rows", max_rows)
                if len(rows) == _CHUNK:
                    chunks.append(np.asarray(rows, dtype=np.float64))
                    rows = []
        except csv.Error as exc:
            raise _csv_error(path, 1 if reader is None else reader.line_num + 1, exc) from exc
    if rows:
        chunks.append(np.asarray(rows, dtype=np.float64))
    if not chunks:
        raise RecordingError(f"{path}: the file has a header but no rows")
    table = np.concatenate(chunks)
    return {c: table[:, i] for i, c in enumerate(COLUMNS)}


# -- NPZ -----------------------------------------------------------------------------------------------

def _npz_array(z: zipfile.ZipFile, name: str, path: Path, max_rows: int) -> np.ndarray:
    with z.open(name + ".npy") as fp:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise RecordingError(f"{path}: array {name} is in .npy format version {version}; write it with numpy.savez")
    if dtype.hasobject:
        raise RecordingError(f"{path}: array {name} holds Python objects (an object array, which would need "
                             "unpickling to read); store numbers")
    if dtype.kind not in "iuf":
        raise RecordingError(f"{path}: array {name} has dtype {dtype}; store numbers (integers or floats)")
    if int(np.prod(shape)) > max_rows:
        _raise_limit(path, f"array {name} has {int(np.prod(shape))} entries", "max_rows", max_rows)
    with z.open(name + ".npy") as fp:
        return np.lib.format.read_array(fp, allow_pickle=False)


def _grid_to_long(a: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    K, P = a["frame"].size, a["point_id"].size
    out = {"frame": np.repeat(a["frame"], P), "point_id": np.tile(a["point_id"], K)}
    for c in COLUMNS:
        if c in out:
            continue
        v = a[c]
        if v.shape == (K, P):
            out[c] = v.reshape(-1)
        elif c in _PER_FRAME and v.shape == (K,):
            out[c] = np.repeat(v, P)
        elif c in _PER_POINT and v.shape == (P,):
            out[c] = np.tile(v, K)
        elif v.shape == (P, K):
            raise RecordingError(f"{path}: array {c} has shape {v.shape}, points x frames; with the axes frame "
                                 f"({K},) and point_id ({P},) it must be frames x points, ({K}, {P}): store {c}.T")
        else:
            also = f" or ({K},)" if c in _PER_FRAME else f" or ({P},)" if c in _PER_POINT else ""
            raise RecordingError(f"{path}: array {c} has shape {v.shape}; with the axes frame ({K},) and point_id "
                                 f"({P},) it must be frames x points, ({K}, {P}){also}")
    return out


def table_from_npz(path: Path, max_rows: int = MAX_ROWS) -> dict[str, np.ndarray]:
    with open_binary(path, "recording", error=RecordingError) as f:
        head = f.read(4)
        if head not in (b"PK\x03\x04", b"PK\x05\x06"):
            raise RecordingError(f"{path}: not an NPZ (zip) archive{' (the file is empty)' if not head else ''}; an "
                                 f"NPZ recording is written by numpy.savez with the arrays {', '.join(COLUMNS)}")
        f.seek(0)
        try:
            with zipfile.ZipFile(f) as z:
                names = set(z.namelist())
                missing = [c for c in COLUMNS if c + ".npy" not in names]
                if missing:
                    raise RecordingError(f"{path}: missing array(s) {', '.join(missing)}; an NPZ recording holds "
                                         f"the arrays {', '.join(COLUMNS)}, one entry per point per frame")
                a = {c: _npz_array(z, c, path, max_rows) for c in COLUMNS}
        except RecordingError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError, OSError,
                ValueError) as exc:
            raise RecordingError(f"{path}: a damaged NPZ archive ({' '.join(str(exc).split())})") from exc
    shapes = {c: v.shape for c, v in a.items()}
    if all(v.ndim == 1 for v in a.values()):
        if len({v.size for v in a.values()}) != 1:
            raise RecordingError(f"{path}: arrays differ in length {({c: v.size for c, v in a.items()})}")
    elif a["frame"].ndim == 1 and a["point_id"].ndim == 1:
        a = _grid_to_long(a, path)
    elif len(set(shapes.values())) != 1:
        raise RecordingError(f"{path}: arrays differ in shape {shapes}; store all arrays 1-D (one entry per point "
                             "per frame), or frame (K,) and point_id (P,) with (K, P) displacements")
    table = {c: np.asarray(v, dtype=np.float64).reshape(-1) for c, v in a.items()}
    if table["frame"].size == 0:
        raise RecordingError(f"{path}: the recording is empty")
    return table


def read_recording(path, max_displacement: float = 1000.0, *, max_line_bytes: int = MAX_LINE_BYTES,
                   max_rows: int = MAX_ROWS, max_frame_points: int = MAX_FRAME_POINTS) -> Recording:
    """Read and validate a recording (``.csv`` or ``.npz``).

    Limits, refused with a message naming the keyword that raises them: ``max_line_bytes`` of a CSV
    line, ``max_rows`` data rows (CSV) or entries of an array (NPZ), ``max_frame_points`` frames x
    points."""
    path = check_regular(path, "recording", error=RecordingError)  # a FIFO would block, a device never end
    if path.suffix.lower() == ".npz":
        table = table_from_npz(path, max_rows)
    elif path.suffix.lower() == ".csv":
        table = table_from_csv(path, max_line_bytes, max_rows)
    else:
        raise RecordingError(f"{path}: unknown recording format {path.suffix!r}; use .csv or .npz")
    return from_table(table, str(path), max_displacement, max_frame_points)


def write_recording(path, rec: Recording) -> Path:
    """Write ``rec`` as CSV or NPZ (by suffix); NaN (not observed) is written as an empty CSV field.
    The file appears whole or not at all (written aside, then renamed): a killed run leaves no
    half-written recording behind."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = to_table(rec)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    if path.suffix.lower() == ".npz":
        np.savez(tmp, **table)
        tmp.replace(path)
        return path
    if path.suffix.lower() != ".csv":
        raise RecordingError(f"{path}: unknown recording format {path.suffix!r}; use .csv or .npz")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        ints = {"frame", "point_id"}
        for i in range(len(table["frame"])):
            w.writerow([int(table[c][i]) if c in ints else ("" if not np.isfinite(table[c][i]) else repr(float(table[c][i])))
                        for c in COLUMNS])
    tmp.replace(path)
    return path
