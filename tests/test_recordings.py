"""Recordings: the CSV/NPZ contract of DESIGN §6, masking of missing values, errors that name the
culprit, matching to the visible face, and frames tied to the model by their pressure."""
import gzip
import os
import threading
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from torchfra.actuator.geometry import ActuatorGeometry, actuator_mesh
from torchfra.calibration.frames import forecast_at_frames, load_factors, recording_operator
from torchfra.io.recordings import read_recording, write_recording
from torchfra.observation.recording import Recording, RecordingError

HEADER = "frame,time,pressure,point_id,X,Y,Z,uy,uz\n"


def _rec(K=4, P=3, seed=0):
    rng = np.random.default_rng(seed)
    Z = rng.normal(size=(K, P, 2))
    Z[1, 2, 0] = np.nan  # one missing component
    X = np.column_stack([np.full(P, 8.0), np.linspace(-6, 6, P), np.linspace(5, 55, P)])
    return Recording(np.arange(K), np.linspace(0.1, 1, K), 0.022 * np.linspace(0.1, 1, K), np.array([5, 9, 11]), X, Z)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip_keeps_values_and_missing(tmp_path, suffix):
    rec = _rec()
    back = read_recording(write_recording(tmp_path / f"r{suffix}", rec))
    assert np.array_equal(back.point_ids, rec.point_ids) and np.array_equal(back.frames, rec.frames)
    assert np.array_equal(np.isnan(back.Z), np.isnan(rec.Z))
    assert np.allclose(back.Z[np.isfinite(rec.Z)], rec.Z[np.isfinite(rec.Z)], rtol=0, atol=1e-15)
    assert np.allclose(back.X, rec.X) and np.allclose(back.pressure, rec.pressure)


def test_absent_rows_and_empty_fields_are_masked_not_zero(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text(HEADER + "0,0.5,0.01,1,8,0,40,-1.5,0.2\n0,0.5,0.01,2,8,1,40,,0.1\n1,1.0,0.02,1,8,0,40,-3,0.4\n")
    rec = read_recording(path)
    assert rec.Z.shape == (2, 2, 2)
    assert np.isnan(rec.Z[0, 1, 0]) and rec.Z[0, 1, 1] == 0.1  # empty field
    assert np.isnan(rec.Z[1, 1]).all()  # point 2 absent from frame 1
    assert rec.mask.sum() == 5


@pytest.mark.parametrize("text, match", [
    ("", "empty"),
    (HEADER, "no rows"),
    ("frame,time,pressure,point_id,X,Y,Z,uy\n0,0,0,1,8,0,40,0\n", "missing column.*uz"),
    (HEADER + "0,0.5,0.01,1,8,0,40,1,1\n0,0.5,0.01,1,8,0,40,1,1\n", "point 1 appears 2 times in frame 0"),
    (HEADER + "0,0.5,0.01,1,8,0,40,1,1\n1,0.4,0.01,1,8,0,40,1,1\n", "time does not increase from frame 0"),
    (HEADER + "0,0.5,0.01,1,8,0,40,1,1\n1,,0.01,1,8,0,40,1,1\n", "frame 1 has no finite time"),
    (HEADER + "0,0.5,0.01,1,8,0,40,1,1\n1,0.6,0.01,1,8,0,41,1,1\n", "point 1 changes its reference"),
    (HEADER + "0,0.5,0.01,1,8,0,40,1,1\n1,0.6,0.02,1,8,0,40,-4000,1\n", "frame 1, point 1: uy = -4000"),
    (HEADER + "0,0.5,0.01,1,8,0,40,abc,1\n", "line 2"),
])
def test_bad_recordings_name_the_culprit(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(RecordingError, match=match):
        read_recording(path)


def test_points_are_matched_to_the_visible_face_by_coordinates():
    """Nodes of the front face (x = 8) match exactly; a point inside the body is refused by id."""
    mesh = actuator_mesh(ActuatorGeometry(resolution=1))
    front = np.flatnonzero(np.abs(mesh.nodes[:, 0] - 8.0) < 1e-9)[:5]
    rec = Recording(np.arange(1), np.ones(1), np.full(1, 0.02), front, mesh.nodes[front], np.zeros((1, 5, 2)))
    op = recording_operator(mesh, rec)
    dense = op.weights.toarray()
    assert np.allclose(dense[np.arange(5), front], 1.0) and np.allclose(dense.sum(1), 1.0)
    X = mesh.nodes[front].copy()
    X[3, 0] = 7.0  # 1 mm inside the body
    with pytest.raises(RecordingError, match=f"point id {front[3]}"):
        recording_operator(mesh, Recording(rec.frames, rec.times, rec.pressure, front, X, rec.Z))


def test_frames_follow_the_pressure_trace_including_unloading():
    """A loading-unloading trace is served by the forward solution at load factor p / P_forward;
    on data affine in the load factor the interpolation is exact (1e-14). A frame above the
    forward's pressure is refused by frame number."""
    steps = np.linspace(0.25, 1.0, 4)
    base = np.random.default_rng(1).normal(size=(3, 1, 5, 2))
    Y_steps = base * steps[None, :, None, None]  # (N, S, P, 2): linear in the load factor
    p = 0.022 * np.array([0.1, 0.5, 0.9, 0.6, 0.2, 0.7])
    rec = Recording(np.arange(6), np.linspace(0.1, 1, 6), p, np.arange(5), np.zeros((5, 3)), np.zeros((6, 5, 2)))
    lam = load_factors(rec, 0.022)
    out = forecast_at_frames(Y_steps, steps, lam, sp.identity(5, format="csr"))
    assert np.abs(out - base * lam[None, :, None, None]).max() < 1e-14
    rec.pressure[4] = 0.03
    with pytest.raises(RecordingError, match="frame 4 has pressure 0.03"):
        load_factors(rec, 0.022)


# -- files that are not recordings, and limits ---------------------------------------------------------

BODY = "0,0.5,0.01,1,8,0,40,-1.5,0.2\n0,0.5,0.01,2,8,1,40,,0.1\n1,1.0,0.02,1,8,0,40,-3,0.4\n"


def _fifo(path):
    """A named pipe: opening it blocks until a writer comes, so the reader must refuse it from its
    stat alone. A writer thread comes anyway, so that a reader that opens it fails instead of hanging."""
    os.mkfifo(path)

    def writer():
        with open(path, "wb"):
            pass

    threading.Thread(target=writer, daemon=True).start()


@pytest.mark.parametrize("name, make, match", [
    ("dir.csv", lambda p: p.mkdir(), "is a folder, not a recording"),
    # a device is refused from its stat (/dev/zero would be read forever); /dev/null keeps a
    # regression from eating memory here, as it reads empty
    ("null.csv", lambda p: p.symlink_to("/dev/null"), "not a regular file"),
    ("pipe.csv", _fifo, "not a regular file"),
    ("gz.csv", lambda p: p.write_bytes(gzip.compress((HEADER + BODY).encode())), "gzip-compressed; decompress"),
    ("le.csv", lambda p: p.write_bytes((HEADER + BODY).encode("utf-16")), "the file is UTF-16; save it as UTF-8"),
    ("be.csv", lambda p: p.write_bytes(b"\xfe\xff" + (HEADER + BODY).encode("utf-16-be")), "UTF-16; save it as UTF-8"),
    ("nul.csv", lambda p: p.write_bytes((HEADER + BODY).encode() + b"\0\0\0"), "line 5: NUL bytes: the file is binary"),
    ("latin1.csv", lambda p: p.write_bytes((HEADER + "0,0.5,0.01,1,8,0,40,1µ,1\n").encode("latin-1")),
     "line 2: byte 0xb5 at column 22 is not UTF-8"),
    ("zip.csv", lambda p: p.write_bytes(b"PK\x03\x04" + bytes(40)), "a zip archive"),
    ("field.csv", lambda p: p.write_text(HEADER + "0,0.5,0.01,1,8,0,40," + "1" * 200_000 + ",1\n"),
     "line 2: a field longer than 131072 characters"),
    ("cr.csv", lambda p: p.write_bytes((HEADER + "0,0.5,0.01,1,8,0,40,1,1\r1,1,0.02,1,8,0,40,1,1\n").encode()),
     "line 2: a carriage return inside a line"),
    ("shift.csv", lambda p: p.write_text(HEADER + "0,0.5,0.01,1,8,0,40,-1.5,,0.2\n"), "line 2: 10 fields, but the header has 9"),
    ("dup.csv", lambda p: p.write_text(HEADER.replace("\n", ",uy\n") + "0,0.5,0.01,1,8,0,40,1,1,2\n"),
     "column\\(s\\) uy appear more than once in the header"),
    ("inf.csv", lambda p: p.write_text(HEADER + "0,0.5,0.01,1,8,0,40,inf,1\n"), "uy = inf; a missing value is empty or NaN"),
    ("under.csv", lambda p: p.write_text(HEADER + "0,0.5,0.01,1,8,0,40,1_5,1\n"), "line 2: .*not a decimal number: '1_5'"),
    ("decimal_comma.csv", lambda p: p.write_text((HEADER + BODY).replace(",", ";").replace("0.5", "0,5")),
     "line 2: .*a decimal comma\\? write 0.5, not 0,5"),
    ("no_obs.csv", lambda p: p.write_text(HEADER + "0,0.5,0.01,1,8,0,40,,\n1,1,0.02,1,8,0,40,nan,NaN\n"),
     "no observed displacements"),
    ("text.npz", lambda p: p.write_text(HEADER + BODY), "not an NPZ \\(zip\\) archive"),
    ("empty.npz", lambda p: p.write_bytes(b""), "not an NPZ \\(zip\\) archive \\(the file is empty\\)"),
    ("array.npz", lambda p: np.save(open(p, "wb"), np.zeros(3)), "not an NPZ \\(zip\\) archive"),
])
def test_what_is_not_a_recording_is_named(tmp_path, name, make, match):
    assert name != "null.csv" or Path("/dev/null").exists()  # the device case needs a POSIX system
    path = tmp_path / name
    make(path)
    try:
        with pytest.raises(RecordingError, match=match) as err:
            read_recording(path)
    finally:
        if name == "pipe.csv":
            os.close(os.open(path, os.O_RDONLY | os.O_NONBLOCK))  # lets the writer thread finish
    assert "allow_pickle" not in str(err.value)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("encode", [
    lambda t: b"\xef\xbb\xbf" + t.encode(),  # a UTF-8 byte-order mark, as spreadsheets write it
    lambda t: t.replace(",", ";").encode(),
    lambda t: t.replace(",", "\t").encode(),
    lambda t: t.replace("\n", "\r\n").encode(),
])
def test_bom_semicolons_tabs_and_crlf_read_like_plain_csv(tmp_path, encode):
    (tmp_path / "plain.csv").write_text(HEADER + BODY)
    (tmp_path / "other.csv").write_bytes(encode(HEADER + BODY))
    a, b = read_recording(tmp_path / "plain.csv"), read_recording(tmp_path / "other.csv")
    assert np.array_equal(a.Z, b.Z, equal_nan=True) and np.array_equal(a.X, b.X) and np.array_equal(a.times, b.times)


def test_limits_name_the_keyword_that_raises_them(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text(HEADER + BODY)
    for kw, match in (({"max_rows": 2}, r"more than 2 rows \(limit max_rows = 2\).*max_rows=\.\.\."),
                      ({"max_line_bytes": 30}, r"line 1: a line longer than 30 bytes.*max_line_bytes=\.\.\."),
                      ({"max_frame_points": 3}, r"2 frames x 2 points = 4 .*max_frame_points=\.\.\.")):
        with pytest.raises(RecordingError, match=match):
            read_recording(path, **kw)
    assert read_recording(path, max_rows=3, max_line_bytes=len(HEADER) - 1, max_frame_points=4).Z.shape == (2, 2, 2)
    write_recording(tmp_path / "r.npz", read_recording(path))
    with pytest.raises(RecordingError, match=r"array frame has 4 entries \(limit max_rows = 2\)"):
        read_recording(tmp_path / "r.npz", max_rows=2)


def test_a_ragged_layout_is_stored_per_frame_in_memory_of_its_rows(tmp_path):
    """Rows that each bring their own frame and point (ids renumbered per frame): 1e5 rows would need a
    dense frames x points array of 1e10 entries (149 GiB). They are stored per frame instead, one
    slot each: 1e5 x 1 x 2 values, every row where it was, written back row for row; reading takes
    memory of the order of the file's rows (peak measured ~25 MB, bounded here at 200 MB)."""
    import tracemalloc

    n = 100_000
    lines = [f"{k},{0.5 + k / (2 * n)},{0.01},{k},8.0,{k % 8},{k % 60},{k / n},-0.1" for k in range(n)]
    path = tmp_path / "ragged.csv"
    path.write_text(HEADER + "\n".join(lines) + "\n")
    tracemalloc.start()
    try:
        rec = read_recording(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 200e6, peak
    assert rec.ragged and rec.Z.shape == (n, 1, 2) and rec.n_points == n
    assert np.array_equal(rec.point_ids[rec.slots[:, 0]], np.arange(n)) and np.array_equal(rec.Z[:, 0, 0], np.arange(n) / n)
    write_recording(tmp_path / "again.npz", rec)
    again = read_recording(tmp_path / "again.npz")
    assert again.ragged and np.array_equal(again.Z, rec.Z) and np.array_equal(again.slots, rec.slots)
    with pytest.raises(RecordingError, match=r"100000 frames x 1 observed points in the fullest frame = 100000 .*"
                                             r"max_frame_points=\.\.\."):
        read_recording(path, max_frame_points=n - 1)


def test_ragged_frames_keep_their_own_points_and_refuse_the_diagnosis():
    """Frames that each observe their own few points: frame k's slots hold its rows in the order of
    their point ids, empty slots NaN and -1; what follows points through frames refuses by name."""
    from torchfra.diagnosis.pipeline import diagnose
    from torchfra.observation.recording import from_table

    # frame 0 sees points 3, 1; frame 1 sees 2; frame 2 sees 5, 4, 0 (6 points, at most 3 per frame)
    frame = np.array([0, 0, 1, 2, 2, 2], dtype=float)
    pid = np.array([3, 1, 2, 5, 4, 0], dtype=float)
    t = {"frame": frame, "time": frame + 1.0, "pressure": 0.01 * (frame + 1), "point_id": pid, "X": np.full(6, 8.0),
         "Y": pid, "Z": 10 * pid, "uy": pid / 10, "uz": -pid}
    rec = from_table(t)
    assert rec.ragged and rec.slots.tolist() == [[1, 3, -1], [2, -1, -1], [0, 4, 5]]
    assert np.array_equal(rec.Z[..., 0], [[0.1, 0.3, np.nan], [0.2, np.nan, np.nan], [0.0, 0.4, 0.5]], equal_nan=True)
    assert np.array_equal(rec.X[:, 2], 10 * np.arange(6))
    with pytest.raises(RecordingError, match=r"frames observe different points .* the diagnosis .* follows each point"):
        diagnose(rec, noise=1.0)


def _grid(K=3, P=2):
    return {"frame": np.arange(K), "point_id": np.array([4, 7][:P]), "time": np.linspace(0.1, 1, K),
            "pressure": np.linspace(0.01, 0.02, K), "X": np.full(P, 8.0), "Y": np.arange(P, dtype=float),
            "Z": np.full(P, 40.0), "uy": np.arange(K * P, dtype=float).reshape(K, P), "uz": -np.ones((K, P))}


def test_npz_grid_layout_reads_frames_by_points(tmp_path):
    """frame (K,) and point_id (P,) are the axes of (K, P) displacements: the same recording as
    the long layout, entry (k, p) at frame k, point p."""
    g = _grid()
    np.savez(tmp_path / "g.npz", **g)
    rec = read_recording(tmp_path / "g.npz")
    assert np.array_equal(rec.Z[..., 0], g["uy"]) and np.array_equal(rec.point_ids, [4, 7])
    assert np.array_equal(rec.times, g["time"]) and np.array_equal(rec.X[:, 1], g["Y"])


@pytest.mark.parametrize("change, match", [
    ({"uy": np.zeros((2, 3))}, r"array uy has shape \(2, 3\), points x frames; .* must be frames x points, \(3, 2\): "
                               r"store uy.T"),
    ({"time": np.zeros((2, 3))}, r"array time has shape \(2, 3\), points x frames"),
    ({"uz": np.zeros((3, 2, 1))}, r"array uz has shape \(3, 2, 1\); .* must be frames x points, \(3, 2\)"),
    ({"X": np.zeros(3)}, r"array X has shape \(3,\); .* \(3, 2\) or \(2,\)"),
    ({"uy": np.zeros(6)}, r"array uy has shape \(6,\); .* must be frames x points, \(3, 2\)"),
    ({"frame": np.zeros((3, 2)), "point_id": np.zeros((3, 2))}, r"arrays differ in shape"),
    ({"uy": np.zeros((3, 2), dtype=complex)}, r"array uy has dtype complex128; store numbers"),
    ({"pressure": np.array(["a", "b", "c"])}, r"array pressure has dtype <U1; store numbers"),
    ({"frame": np.array([0, 1, 2 ** 60])}, r"frame = .*must be an integer of magnitude below 2\^53"),
])
def test_npz_arrays_are_never_reshaped_silently(tmp_path, change, match):
    np.savez(tmp_path / "g.npz", **{**_grid(), **change})
    with pytest.raises(RecordingError, match=match):
        read_recording(tmp_path / "g.npz")


def test_damaged_npz_is_named(tmp_path):
    np.savez_compressed(tmp_path / "g.npz", **_grid())
    data = bytearray((tmp_path / "g.npz").read_bytes())
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match="cut.npz: a damaged NPZ archive"):
        read_recording(tmp_path / "cut.npz")
