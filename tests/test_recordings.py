"""Recordings: the CSV/NPZ contract of DESIGN §6, masking of missing values, errors that name the
culprit, matching to the visible face, and frames tied to the model by their pressure."""
import numpy as np
import pytest
import scipy.sparse as sp

from torchfra.calibration import forecast_at_frames, load_factors, recording_operator
from torchfra.geometry.actuator import ActuatorGeometry, actuator_mesh
from torchfra.recordings import Recording, RecordingError, read_recording, write_recording

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
