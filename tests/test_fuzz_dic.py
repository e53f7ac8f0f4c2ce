"""Fuzzing the DIC readers: whatever the bytes of an export file, ``read_frame`` and ``read_dic`` return
the export or raise ``DicError`` (never another exception), and a file they accept is read as written:
every coordinate and displacement equals the file's number for that row and column, in mm (checked
against a plain reading of the CSV text). ``read_landmarks`` likewise returns landmarks or raises."""
import csv
import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchfra.io.dic.exports import LENGTH_UNITS, read_dic, read_frame, read_landmarks
from torchfra.io.tables import DicError, name_unit

FUZZ = settings(max_examples=120, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
HEADER = "x [mm],y [mm],z [mm],u [mm],v [mm],w [mm]"
ROWS = [[8.0, -7.0, 2.0, 0.0, -0.25, 0.5], [8.0, 1.75, 6.0, 0.125, -1.5, 0.75], [8.0, 7.0, 58.0, 0.5, -3.0, 1.0]]
VALID = (HEADER + "\n" + "".join(",".join(repr(v) for v in r) + "\n" for r in ROWS)).encode()


def _read(path, **kw):
    try:
        return read_frame(path, **kw)
    except DicError:
        return None  # any other exception fails the test


def _plain(data: bytes):
    """The file as a CSV reader sees it: preamble lines, then a header naming x, y, z, u, v, w with a
    length unit each, then rows of numbers (empty: NaN). (X, U) in mm, or None if it is not that."""
    try:
        lines = re.split(r"\r\n|\r|\n", data.decode("utf-8").removeprefix("\ufeff"))  # CSV line ends only
        for h, line in enumerate(lines[:64]):
            cells = [name_unit(c) for c in next(csv.reader([line]), [])]
            names = [n for n, _ in cells]
            if sorted(names) == sorted("xyzuvw"):
                break
        else:
            return None
        factor = [LENGTH_UNITS[u.lower()] for _, u in cells]
        rows = []
        for line in lines[h + 1:]:
            if not line.strip():
                continue
            fields = next(csv.reader([line]))
            if len(fields) != 6:
                return None
            rows.append([float(f) * factor[j] if f.strip() else math.nan for j, f in enumerate(fields)])
        table = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
        col = [names.index(c) for c in "xyzuvw"]
        return table[:, col[:3]], table[:, col[3:]]
    except (UnicodeDecodeError, ValueError, KeyError, AttributeError, csv.Error):
        return None


@st.composite
def edits(draw):
    """The valid export with 1-4 random byte edits (replace, insert, delete), often of digits and separators."""
    data = bytearray(VALID)
    alphabet = st.one_of(st.sampled_from(b"0123456789.,-+eE \n\r\"';[]mx"), st.integers(0, 255))
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(data)))
        kind = draw(st.sampled_from(["replace", "insert", "delete"]))
        if kind == "insert" or i == len(data):
            data[i:i] = bytes([draw(alphabet)])
        elif kind == "replace":
            data[i] = draw(alphabet)
        else:
            del data[i]
    return bytes(data)


def test_the_valid_export_reads_as_written(tmp_path):
    (tmp_path / "f.csv").write_bytes(VALID)
    fr = read_frame(tmp_path / "f.csv")
    X, U = _plain(VALID)
    assert np.array_equal(fr.X, X) and np.array_equal(fr.U, U)


@FUZZ
@given(data=st.binary(max_size=400))
def test_random_bytes_are_read_or_refused(tmp_path, data):
    f = tmp_path / "frame_0.csv"
    f.write_bytes(data)
    _read(f, units="mm")


@settings(FUZZ, max_examples=300)  # about 1 edit in 12 leaves a file the reader accepts: ~25 checked readings
@given(data=edits())
def test_an_edited_export_is_refused_or_read_as_written(tmp_path, data):
    f = tmp_path / "frame_0.csv"
    f.write_bytes(data)
    fr = _read(f)
    if fr is None:
        return
    plain = _plain(data)
    assert plain is not None, f"accepted a file that is not plainly a table: {data!r}"
    X, U = plain
    lost = ~np.all(np.isfinite(X), axis=1) | ~np.all(np.isfinite(U), axis=1)
    assert np.array_equal(fr.lost, lost), data
    assert np.array_equal(fr.X[~lost], X[~lost]) and np.array_equal(fr.U[~lost], U[~lost]), data
    assert np.all(np.isnan(fr.U[lost])), data


@FUZZ
@given(data=edits(), where=st.integers(0, 2))
def test_an_export_folder_with_an_edited_frame_is_read_or_refused(tmp_path, data, where):
    d = tmp_path / "export"
    d.mkdir(exist_ok=True)
    for k in range(3):
        (d / f"frame_{k}.csv").write_bytes(data if k == where else VALID)
    try:
        s = read_dic(d)
    except DicError:
        return
    assert s.frames.tolist() == [0, 1, 2][: len(s.frames)] or len(s.ignored) == 1
    assert s.U.shape == (len(s.frames), len(s.point_ids), 3)


@FUZZ
@given(data=st.binary(max_size=200) | edits())
def test_landmark_files_are_read_or_refused(tmp_path, data):
    (tmp_path / "e").mkdir(exist_ok=True)
    (tmp_path / "e" / "frame_0.csv").write_bytes(VALID)
    s = read_dic(tmp_path / "e")
    f = tmp_path / "lm.csv"
    f.write_bytes(data)
    try:
        src, dst = read_landmarks(f, s)
    except DicError:
        return
    assert src.shape == dst.shape and src.shape[1] == 3
