"""Fuzzing the recording reader: whatever the bytes, read_recording returns a Recording or raises
RecordingError (never another exception), and a file it accepts is read as written: every value
it reports is the value the file holds for that frame and point (checked against a plain reading
of the CSV text, or against the arrays written to the NPZ)."""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchfra.io.recordings import read_recording, write_recording
from torchfra.observation.recording import COLUMNS, Recording, RecordingError

FUZZ = settings(max_examples=150, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
K, P = 3, 4  # K != P: a transposed array is told apart by its shape


def _truth() -> Recording:
    """Values exact in float16/32 (multiples of 1/4), some not observed."""
    Z = (np.arange(K * P * 2, dtype=float).reshape(K, P, 2) - 7) / 4
    Z[1, 2, 0] = Z[2, 0, :] = np.nan
    X = np.column_stack([np.full(P, 8.0), np.arange(P) - 1.5, 10.0 + 4 * np.arange(P)])
    return Recording(np.arange(K) + 2, (np.arange(K) + 1) / 4, (np.arange(K) + 1) / 64, np.array([3, 5, 11, 12]), X, Z)


@pytest.fixture(scope="module")
def valid_csv(tmp_path_factory) -> bytes:
    return write_recording(tmp_path_factory.mktemp("csv") / "r.csv", _truth()).read_bytes()


def _read(path):
    try:
        return read_recording(path)
    except RecordingError:
        return None  # any other exception fails the test


def _plain_csv(data: bytes):
    """The CSV as a person reads it: comma-separated numbers under the header; None if it is not that."""
    try:
        lines = data.decode("utf-8").removeprefix("\ufeff").split("\n")
        header = [h.strip(" \t") for h in lines[0].rstrip("\r").split(",")]
        col = [header.index(c) for c in COLUMNS]
        rows = []
        for line in lines[1:]:
            fields = line.rstrip("\r").split(",")
            if all(not f.strip(" \t") for f in fields):
                continue
            if len(fields) != len(header):
                return None
            rows.append([float(fields[j]) if fields[j].strip(" \t") else math.nan for j in col])
        return rows
    except (UnicodeDecodeError, ValueError):
        return None


def _check_as_written(rec: Recording, rows) -> None:
    """Every row of the file is where the recording says, and the recording holds nothing else."""
    assert rows is not None, "accepted a file that is not plain comma-separated numbers"
    k_of = {int(f): k for k, f in enumerate(rec.frames)}
    p_of = {int(p): i for i, p in enumerate(rec.point_ids)}
    seen = np.zeros(rec.Z.shape, dtype=bool)
    for frame, time, pressure, pid, x, y, z, uy, uz in rows:
        k, p = k_of[int(frame)], p_of[int(pid)]
        assert np.array_equal(rec.Z[k, p], [uy, uz], equal_nan=True)
        assert math.isnan(time) or rec.times[k] == time
        assert math.isnan(pressure) or rec.pressure[k] == pressure
        assert np.allclose(rec.X[p], [x, y, z], rtol=0, atol=1e-6)
        seen[k, p] = True
    assert not np.isfinite(rec.Z[~seen]).any()


_BYTES = st.one_of(st.sampled_from(list(b',;\t\n\r"._-+eE0123456789 naNIf\x00\xef\xbb\xbf\xff\xfe')), st.integers(0, 255))


@st.composite
def _edits(draw, data: bytes) -> bytes:
    """1-3 byte or line edits of ``data``: replace, insert or delete a byte; drop, repeat or swap lines; cut."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["replace", "insert", "delete", "drop_line", "repeat_line", "swap_lines", "cut"]))
        i = draw(st.integers(0, max(len(out) - 1, 0)))
        if kind == "replace" and out:
            out[i] = draw(_BYTES)
        elif kind == "insert":
            out.insert(i, draw(_BYTES))
        elif kind == "delete" and out:
            del out[i]
        elif kind == "cut":
            del out[i:]
        else:
            lines = bytes(out).split(b"\n")
            a, b = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            if kind == "drop_line":
                del lines[a]
            elif kind == "repeat_line":
                lines.insert(a, lines[b])
            else:
                lines[a], lines[b] = lines[b], lines[a]
            out = bytearray(b"\n".join(lines))
    return bytes(out)


@FUZZ
@given(st.data())
def test_edited_csv_is_refused_or_read_as_written(tmp_path, valid_csv, data):
    edited = data.draw(_edits(valid_csv))
    path = tmp_path / "edited.csv"
    path.write_bytes(edited)
    rec = _read(path)
    if rec is not None:
        _check_as_written(rec, _plain_csv(edited))


@FUZZ
@given(st.binary(max_size=300), st.sampled_from([b"", b"frame,time,pressure,point_id,X,Y,Z,uy,uz\n", b"PK\x03\x04"]),
       st.sampled_from([".csv", ".npz"]))
def test_random_bytes_are_refused_or_read_as_written(tmp_path, noise, prefix, suffix):
    path = tmp_path / f"noise{suffix}"
    path.write_bytes(prefix + noise)
    rec = _read(path)
    if rec is not None:
        assert suffix == ".csv"
        _check_as_written(rec, _plain_csv(prefix + noise))


# -- NPZ layouts -------------------------------------------------------------------------------------------

def _long(t: Recording) -> dict[str, np.ndarray]:
    fi, pi = np.repeat(np.arange(K), P), np.tile(np.arange(P), K)
    return {"frame": t.frames[fi], "time": t.times[fi], "pressure": t.pressure[fi], "point_id": t.point_ids[pi],
            "X": t.X[pi, 0], "Y": t.X[pi, 1], "Z": t.X[pi, 2], "uy": t.Z[fi, pi, 0], "uz": t.Z[fi, pi, 1]}


@st.composite
def _npz_layouts(draw):
    """Arrays of the truth in a layout of the contract, and at most one corruption that must be refused."""
    t = _truth()
    layout = draw(st.sampled_from(["long", "long_shuffled", "same_2d", "grid"]))
    if layout.startswith("long") or layout == "same_2d":
        a = _long(t)
        if layout == "long_shuffled":
            order = np.asarray(draw(st.permutations(range(K * P))))
            a = {c: v[order] for c, v in a.items()}
        if layout == "same_2d":
            shape = draw(st.sampled_from([(K, P), (K * P, 1), (1, K * P), (2, K * P // 2)]))
            a = {c: v.reshape(shape) for c, v in a.items()}
    else:
        a = {"frame": t.frames, "point_id": t.point_ids, "uy": t.Z[..., 0], "uz": t.Z[..., 1]}
        for c, v in (("time", t.times), ("pressure", t.pressure)):
            a[c] = np.repeat(v[:, None], P, 1) if draw(st.booleans()) else v
        for j, c in enumerate("XYZ"):
            a[c] = np.repeat(t.X[None, :, j], K, 0) if draw(st.booleans()) else t.X[:, j]
    for c in a:  # dtypes that hold the values exactly
        kinds = [np.int64, np.int32, np.float64] if c in ("frame", "point_id") else [np.float64, np.float32, np.float16]
        a[c] = a[c].astype(draw(st.sampled_from(kinds)))
    corruption = draw(st.sampled_from([None, None, "transpose", "3d", "object", "complex", "text", "bool", "drop",
                                       "shorter", "empty"]))
    c = draw(st.sampled_from(COLUMNS))
    v = a[c]
    if corruption == "transpose" and v.ndim == 2 and v.shape[0] != v.shape[1]:
        a[c] = v.T
    elif corruption == "3d":
        a[c] = v[..., None]
    elif corruption == "object":
        a[c] = v.astype(object)
    elif corruption in ("complex", "bool"):
        a[c] = v.astype(corruption)
    elif corruption == "text":
        a[c] = v.astype(str)
    elif corruption == "drop":
        del a[c]
    elif corruption == "shorter":
        a[c] = v.reshape(-1)[:-1] if v.ndim == 1 else v[:-1]
    elif corruption == "empty":
        a[c] = v[:0]
    else:
        corruption = None
    return a, corruption


@FUZZ
@given(_npz_layouts(), st.sampled_from([np.savez, np.savez_compressed]))
def test_npz_layouts_are_refused_or_read_as_written(tmp_path, layout, save):
    arrays, corruption = layout
    save(tmp_path / "r.npz", **arrays)
    rec = _read(tmp_path / "r.npz")
    if corruption is not None:
        assert rec is None, f"{corruption} accepted"
        return
    t = _truth()
    assert rec is not None
    assert np.array_equal(rec.frames, t.frames) and np.array_equal(rec.point_ids, t.point_ids)
    assert np.array_equal(rec.Z, t.Z, equal_nan=True)
    assert np.array_equal(rec.times, t.times) and np.array_equal(rec.pressure, t.pressure)
    assert np.array_equal(rec.X, t.X)


@FUZZ
@given(st.data())
def test_edited_npz_bytes_are_refused_or_read_as_before(tmp_path, data):
    """A valid NPZ with bytes changed: the zip checksums catch an edit of the data; whatever parses
    is the recording that was written."""
    path = tmp_path / "r.npz"
    np.savez(path, **_long(_truth()))
    path.write_bytes(data.draw(_edits(path.read_bytes())))
    rec = _read(path)
    if rec is not None:
        assert np.array_equal(rec.Z, _truth().Z, equal_nan=True)
