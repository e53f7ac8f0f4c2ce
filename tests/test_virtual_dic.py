"""The virtual DIC experiment (torchfra.lab) and pyvale's export (torchfra.io.dic.pyvale).

Without pyvale (the default install, CI): the camera's pixel <-> mm mapping round-trips, the
speckle warp moves the image the way a displacement moves the face (a one-pixel translation is a
one-column shift; an affine field is inverted to its closed form; warping back recovers the
reference), a pinhole's magnification matches D / (D - ux), the error budget recovers known biases
and the correlation length of squared-exponential noise, and pyvale's export, as the real engine
wrote it (tests/data/pyvale/, made by its make_export.py), is read against the affine displacement
it was made from: Lagrangian, v downwards, through the DIC importer into a recording in mm. With
pyvale installed the command runs end to end on a small experiment; without it the command says
how to install the extra and exits 2.
"""
import json
import os
import shutil
import subprocess
import sys
from argparse import Namespace
from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion, map_coordinates

from torchfra.io.dic import import_export, read_dic
from torchfra.io.dic.pyvale import read_pyvale_file
from torchfra.io.tables import DicError
from torchfra.lab.budget import error_budget
from torchfra.lab.camera import Camera, CameraError
from torchfra.lab.speckle import FaceField, render, seen_material, speckle_pattern

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "pyvale"
BOUNDS = ((-4.0, 4.0), (0.0, 6.0))
HAVE_PYVALE = find_spec("pyvale") is not None


@pytest.fixture(scope="module")
def scene():
    camera = Camera.framing(0.1, (-5.0, 5.0), (-1.0, 7.0))
    return camera, speckle_pattern(BOUNDS, 0.4, seed=1)


def test_camera_maps_pixels_and_mm_both_ways_with_y_right_and_z_up():
    cam = Camera(0.05, (300, 200), (-6.0, 64.0))
    rng = np.random.default_rng(0)
    yz = rng.uniform([-8, 0], [8, 60], (50, 2))
    assert np.allclose(cam.to_model(cam.to_pixels(yz)), yz, rtol=0, atol=1e-12)
    uv = rng.normal(size=(7, 50, 2))
    assert np.allclose(cam.displacement_to_pixels(cam.displacement_to_model(uv)), uv, rtol=0, atol=1e-12)
    # +y is one column to the right per pixel, +z one row up (image rows count downwards)
    assert np.allclose(cam.to_pixels([[-6.0 + 0.05, 64.0 - 0.05]]), [[1.0, 1.0]])
    assert np.allclose(cam.displacement_to_model([[2.0, 4.0]]), [[0.1, -0.2]])
    with pytest.raises(CameraError, match="pixel_size"):
        Camera(0.0, (300, 200), (0.0, 0.0))


def test_a_one_pixel_translation_moves_the_image_one_column_right_or_one_row_up(scene):
    camera, speckle = scene
    ref = render(camera, speckle, None, bits=None)
    right = render(camera, speckle, FaceField.affine(BOUNDS, np.zeros((2, 2)), [camera.pixel_size, 0.0]), bits=None)
    up = render(camera, speckle, FaceField.affine(BOUNDS, np.zeros((2, 2)), [0.0, camera.pixel_size]), bits=None)
    assert np.abs(right[:, 1:] - ref[:, :-1]).max() < 1e-6
    assert np.abs(up[:-1, :] - ref[1:, :]).max() < 1e-6
    assert ref.std() > 0.1  # a speckled face, not a blank image


def test_the_backward_warp_inverts_an_affine_field_and_warping_back_recovers_the_reference(scene):
    camera, speckle = scene
    A, b = np.array([[0.03, -0.05], [0.04, 0.02]]), np.array([0.37, -0.61])
    field = FaceField.affine(BOUNDS, A, b)
    x = camera.to_model(camera.pixel_centres(2).reshape(-1, 2))
    X, seen = seen_material(camera, x, field, speckle)
    exact = np.linalg.solve(np.eye(2) + A, (x - b).T).T  # closed form of X + A X + b = x
    assert seen.sum() > 0.3 * len(x)
    assert np.abs(X[seen] - exact[seen]).max() < 1e-9
    inside, outside = speckle.on_face(exact, tol=-1e-6), ~speckle.on_face(exact, tol=1e-6)
    assert seen[inside].all() and not seen[outside].any()
    ref = render(camera, speckle, None, bits=None)
    deformed = render(camera, speckle, field, bits=None)
    # sample the deformed image where each reference pixel's material point went: the reference again
    centres = camera.pixel_centres(1).reshape(-1, 2)
    went = camera.to_pixels(camera.to_model(centres) @ (np.eye(2) + A).T + b)
    back = map_coordinates(deformed.astype(float), [went[:, 1], went[:, 0]], order=3).reshape(camera.shape)
    inner = binary_erosion(speckle.on_face(camera.to_model(centres)).reshape(camera.shape), iterations=4)
    rms = np.sqrt(np.mean((back - ref)[inner] ** 2))
    assert rms < 0.03 * ref[inner].std(), rms  # bicubic resampling error only (measured 1.3 %)
    wrong = map_coordinates(deformed.astype(float), [2 * centres[:, 1] - went[:, 1], 2 * centres[:, 0] - went[:, 0]],
                            order=3).reshape(camera.shape)
    assert np.sqrt(np.mean((wrong - ref)[inner] ** 2)) > 0.5 * ref[inner].std()  # the opposite warp does not


def test_a_pinhole_sees_out_of_plane_motion_as_a_magnification_about_its_axis(scene):
    camera, speckle = scene
    D, ux = 250.0, 0.8
    pin = Camera(camera.pixel_size, camera.shape, camera.origin, working_distance=D)
    field = FaceField.affine(BOUNDS, np.zeros((2, 2)), [0.0, 0.0], ux=ux)
    x = pin.to_model(pin.pixel_centres(1).reshape(-1, 2))
    X, seen = seen_material(pin, x, field, speckle)
    c = pin.axis
    assert np.abs(X[seen] - (c + (x[seen] - c) * (D - ux) / D)).max() < 1e-9  # similar triangles: D / (D - ux)
    assert np.allclose(camera.magnification(np.array([ux])), 1.0)  # telecentric: none


def test_the_error_budget_finds_known_biases_and_the_correlation_length_of_squared_exponential_noise():
    from torchfra.scenarios.generate import observation_noise

    y, z = np.meshgrid(np.arange(-7.5, 8.0, 1.0), np.arange(0.5, 60.0, 1.0), indexing="ij")
    yz = np.stack([y.ravel(), z.ravel()], 1)
    X = np.column_stack([np.full(len(yz), 8.0), yz])
    K = 6
    noise, _ = observation_noise(X, K, 1e-3, 3.0, np.random.default_rng(5))  # squared-exponential, l = 3 mm
    truth = np.zeros((K, len(yz), 2))
    engine = truth + noise
    edge = np.minimum.reduce([yz[:, 0] + 8, 8 - yz[:, 0], yz[:, 1], 60 - yz[:, 1]]) < 2.1
    engine[1:, edge, 0] += 0.01  # a bias of 10 um in uy along the edges
    engine[1:, ~edge, 1] -= 0.004
    engine[0] = 0.0
    b = error_budget(yz, engine, truth, ((-8, 8), (0, 60)), band=2.1, spacing=1.0)
    assert b["points"]["edge"] == int(edge.sum())
    assert b["regions"]["edge"]["bias_mm"][0] == pytest.approx(0.01, abs=3e-4)
    assert b["regions"]["interior"]["bias_mm"][0] == pytest.approx(0.0, abs=3e-4)
    assert b["regions"]["interior"]["bias_mm"][1] == pytest.approx(-0.004, abs=3e-4)
    assert b["frame0"]["rms_mm"] == [0.0, 0.0]
    # the fitted length is the generating kernel's, 3 mm (the biases are per-frame constants per
    # region, so they add a step that the per-frame mean does not remove: fit on the noise alone)
    pure = error_budget(yz, noise, truth, ((-8, 8), (0, 60)), band=2.1, spacing=1.0)
    assert pure["correlation_length_mm"] == pytest.approx(3.0, rel=0.15)
    white = error_budget(yz, np.random.default_rng(6).normal(0, 1e-3, truth.shape), truth, ((-8, 8), (0, 60)),
                         band=2.1, spacing=1.0)
    assert white["correlation_length_mm"] == 0.0


def _truth():
    t = json.loads((DATA / "truth.json").read_text())
    cam = Camera(t["pixel_size_mm"], tuple(t["shape"]), tuple(t["origin_mm"]))
    return t, cam, np.asarray(t["A"]), np.asarray(t["b_mm"])


def test_pyvale_export_written_by_the_engine_is_lagrangian_with_v_downwards():
    t, cam, A, b = _truth()
    zero = read_pyvale_file(DATA / t["files"][0])
    frame = read_pyvale_file(DATA / t["files"][1])
    assert len(frame.xy) == len(zero.xy) >= 20 and frame.converged.all()
    assert np.array_equal(frame.xy, zero.xy)
    assert np.abs(zero.uv).max() < 1e-6  # the reference against itself
    X = cam.to_model(frame.xy)  # the subset centres in the reference image
    lagrangian = cam.displacement_to_pixels(X @ A.T + b)
    err = frame.uv - lagrangian
    assert np.sqrt(np.mean(err ** 2)) < 0.02, err  # measured 0.004 px
    # had the engine reported at the deformed centres (Eulerian), or v upwards, it would be far off
    eulerian = cam.displacement_to_pixels(np.linalg.solve(np.eye(2) + A, (X - b).T).T @ A.T + b)
    assert np.sqrt(np.mean((frame.uv - eulerian) ** 2)) > 5 * np.sqrt(np.mean(err ** 2))
    assert np.sqrt(np.mean((frame.uv * [1, -1] - lagrangian) ** 2)) > 1.0
    assert np.all(frame.cost > 0.99)


def test_the_importer_reads_pyvale_exports_into_a_recording_in_mm(tmp_path):
    t, cam, A, b = _truth()
    series = read_dic(DATA, scale=t["pixel_size_mm"])
    assert series.layout.format == "pyvale" and list(series.frames) == [0, 1]
    (tmp_path / "p.csv").write_text("frame,time,pressure [kPa]\n0,0,0\n1,1,10\n")
    corners = np.array([[-4.0, 0.0], [4.0, 0.0], [4.0, 6.0], [-4.0, 6.0]])
    px = cam.to_pixels(corners)
    (tmp_path / "lm.csv").write_text("dic_x,dic_y,model_x,model_y,model_z\n" + "".join(
        f"{c},{r},8,{y},{z}\n" for (c, r), (y, z) in zip(px, corners)))
    a = Namespace(pressure=str(tmp_path / "p.csv"), format="auto", scale=t["pixel_size_mm"], units=None,
                  pressure_units=None, match="frame", frame_rate=None, first_frame_time=0.0,
                  camera_to_model="register", landmarks=str(tmp_path / "lm.csv"), fit_scale=False, tol=0.5)
    files = [DATA / f for f in t["files"]]
    _, info = import_export(files, a, tmp_path / "rec.csv")
    from torchfra.io.recordings import read_recording

    rec = read_recording(tmp_path / "rec.csv")
    assert info["format"] == "pyvale 2-D DIC" and info["residual_max_mm"] < 1e-9
    assert np.allclose(rec.X[:, 0], 8.0) and rec.pressure.tolist() == [0.0, 0.01]
    expected = rec.X[:, 1:3] @ A.T + b  # (uy, uz) mm at the reference points
    assert np.abs(rec.Z[1] - expected).max() < 3e-3  # 0.03 px
    assert np.sqrt(np.mean((rec.Z[1] - expected) ** 2)) < 1e-3


def test_a_file_that_is_not_a_pyvale_export_is_refused_by_name(tmp_path):
    bad = tmp_path / "dic_results_0.csv"
    bad.write_text("subset_x,subset_y,disp_u\n1,2,3\n")
    with pytest.raises(DicError, match=r"dic_results_0.csv: not a pyvale 2-D DIC export: columns disp_v"):
        read_pyvale_file(bad)
    lines = (DATA / "dic_results_def_img_0001.csv").read_text().splitlines()
    broken = tmp_path / "broken.csv"
    broken.write_text("\n".join(lines[:3] + ["40.0,50.0,oops,1,1,1,1,1,1,1"] + lines[3:]) + "\n")
    with pytest.raises(DicError, match=r"broken.csv, line 4: cannot read"):
        read_pyvale_file(broken)


def _command(args, tmp_path, env_extra=None):
    exe = shutil.which("torchfra", path=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    cmd = [exe] if exe else [sys.executable, "-m", "torchfra"]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", **(env_extra or {}))
    return subprocess.run(cmd + args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.skipif(HAVE_PYVALE, reason="pyvale is installed here")
def test_without_pyvale_the_command_says_how_to_install_the_extra_and_exits_2(tmp_path):
    out = _command(["virtual-dic", "--out", "runs/virtual_dic/recording.csv"], tmp_path)
    assert out.returncode == 2, out.stderr
    assert "pyvale is not installed" in out.stderr and '.[virtual-dic]' in out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "runs").exists()


@pytest.mark.skipif(not HAVE_PYVALE, reason="needs the virtual-dic extra (pyvale)")
def test_the_documented_small_command_writes_a_recording_and_its_error_budget(tmp_path):
    out = _command(["virtual-dic", "--pixel-size", "0.2", "--speckle-size", "0.8", "--frames", "4", "--pressure",
                    "0.011", "--out", "rec.csv"], tmp_path)
    assert out.returncode == 0, out.stderr
    summary = json.loads((tmp_path / "rec.virtual_dic.json").read_text())
    interior = summary["budget"]["regions"]["interior"]
    assert max(interior["rms_mm"]) < 0.5 * summary["settings"]["pixel_size"]  # under half a pixel (measured 0.04)
    assert "interior" in out.stdout and "correlation length" in out.stdout
    assert not (tmp_path / "plotter_log.log").exists()  # pyvale's import-time log file is not left behind
