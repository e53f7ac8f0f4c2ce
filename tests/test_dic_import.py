"""DIC export readers, the pressure trace, and scripts/import_dic.py end to end.

The small files below are written with the headers (names, units, quoting, preambles) the programs
write (DESIGN §8); numbers are written to full precision so round trips can be checked to 1e-6 mm.
"""
from pathlib import Path

import numpy as np
import pytest
from helpers import load_script

from torchfra.actuator.geometry import ActuatorGeometry, actuator_mesh
from torchfra.calibration.frames import recording_operator
from torchfra.io.dic.exports import DicError, frame_numbers, read_dic, read_frame, read_landmarks
from torchfra.io.pressure_trace import pressure_at_frames, read_pressure_trace
from torchfra.io.recordings import read_recording
from torchfra.observation.recording import Recording

MATCHID_2024 = ("Coordinates.Image X [Pixel],Coordinates.Image Y [Pixel],coor.X [mm],coor.Y [mm],coor.Z [mm],"
                "disp.Horizontal Displacement U [mm],disp.Vertical Displacement V [mm],disp.Out-Of-Plane: W [mm],"
                "strain.Strain-global frame: Exx [ ],strain.Strain-global frame: Eyy [ ],"
                "strain.Strain-global frame: Exy [ ]")
MATCHID_SHORT = "x_pic,y_pic,x,y,z,u,v,w,exx,eyy,exy"
VIC3D = ('"x","y","u","v","sigma","X [mm]","Y [mm]","Z [mm]","U [mm]","V [mm]","W [mm]",'
         '"exx [1] - Lagrange","eyy [1] - Lagrange","exy [1] - Lagrange"')
DICE_PREAMBLE = ("***\n*** Digital Image Correlation Engine (DICe), Copyright 2021 National Technology & Engineering "
                 "Solutions of Sandia, LLC (NTESS)\n***\n*** Reference image: ref.tif \n*** Deformed image: def.tif \n"
                 "*** DIC method : local \n*** Subset size: 21\n*** Step size: x 10 y 10 (-1 implies not regular grid)\n"
                 "*** Coordinates given with (0,0) as upper left corner of image, x positive right, y positive down\n***\n")
DICE = ("SUBSET_ID,COORDINATE_X,COORDINATE_Y,DISPLACEMENT_X,DISPLACEMENT_Y,SIGMA,GAMMA,BETA,STATUS_FLAG,UNCERTAINTY,"
        "VSG_STRAIN_XX,VSG_STRAIN_YY,VSG_STRAIN_XY")


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def num(v: float) -> str:
    """A field as written by a program that leaves lost values empty."""
    return "" if not np.isfinite(v) else repr(float(v))


def full(v: float) -> str:
    """A field as written by a program that writes NaN."""
    return repr(float(v)) if np.isfinite(v) else "NaN"


# -- single frames ---------------------------------------------------------------------------------------

def test_matchid_2024_headers(tmp_path):
    f = write(tmp_path / "spec_0001_0.tif.csv", MATCHID_2024 + "\n"
              "100,200,1.5,-2.0,30.25,0.1,-0.2,0.03,0.001,0.002,0.003\n"
              "110,200,2.5,-2.0,30.5,,,,,,\n")
    fr = read_frame(f)
    assert fr.layout.label == "MatchID (2024 headers)"
    assert np.array_equal(fr.X, [[1.5, -2.0, 30.25], [2.5, -2.0, 30.5]])
    assert np.array_equal(fr.U[0], [0.1, -0.2, 0.03])
    assert np.all(np.isnan(fr.U[1])) and fr.lost.tolist() == [False, True]
    assert np.array_equal(fr.keys, [[100, 200], [110, 200]])


def test_matchid_short_headers_need_units(tmp_path):
    f = write(tmp_path / "a_0.csv", MATCHID_SHORT + "\n10,20,0.001,0.002,0.003,1e-5,2e-5,3e-5,0,0,0\n")
    with pytest.raises(DicError, match="no unit.*give the units"):
        read_frame(f)
    fr = read_frame(f, units="m")
    assert fr.layout.label == "MatchID (short headers)"
    assert np.allclose(fr.X, [[1.0, 2.0, 3.0]], rtol=1e-15) and np.allclose(fr.U, [[0.01, 0.02, 0.03]], rtol=1e-15)


def test_vic3d_lost_points_are_masked_not_zero(tmp_path):
    f = write(tmp_path / "spec_0003_0.csv", VIC3D + "\n"
              "10,20,0.5,0.5,0.01,1.0,2.0,3.0,0.1,0.2,0.3,0,0,0\n"
              "30,20,0,0,-1,0,0,0,0,0,0,0,0,0\n"
              '50,20,0.5,0.5,"",5.0,2.0,3.0,0.1,0.2,0.3,0,0,0\n')
    fr = read_frame(f, "vic3d")
    assert fr.lost.tolist() == [False, True, True]
    assert np.array_equal(fr.U[0], [0.1, 0.2, 0.3]) and np.all(np.isnan(fr.U[1:]))


def test_vic3d_semicolon_export_with_preamble_and_decimal_commas(tmp_path):
    header = VIC3D.replace(",", ";")
    f = write(tmp_path / "spec_0003_0.csv", '"spec_0003_0.tif"\n' + header + "\n"
              "10;20;0,5;0,5;0,01;1,25;-2;3;0,1;0,2;0,3;0;0;0\n")
    fr = read_frame(f)
    assert fr.layout.label == "VIC-3D"
    assert np.array_equal(fr.X, [[1.25, -2.0, 3.0]]) and np.array_equal(fr.U, [[0.1, 0.2, 0.3]])


def test_dice_pixels_need_a_scale_and_sigma_minus_one_is_lost(tmp_path):
    f = write(tmp_path / "DICe_solution_1.txt", DICE_PREAMBLE + DICE + "\n"
              "0,1.0000E+02,2.0000E+02,1.0000E+00,-2.0000E+00,5.0E-03,2.1E-02,0,4,7.6E-03,0,0,0\n"
              "1,1.1000E+02,2.0000E+02,0.0000E+00,0.0000E+00,-1.0E+00,0,0,11,0,0,0,0\n")
    with pytest.raises(DicError, match="pixels; give the scale in mm per pixel"):
        read_frame(f)
    fr = read_frame(f, scale=0.05)
    assert fr.layout.two_d and fr.ids.tolist() == [0, 1]
    assert np.allclose(fr.X, [[5.0, 10.0, 0.0], [5.5, 10.0, 0.0]])
    assert np.allclose(fr.U[0], [0.05, -0.1, 0.0]) and np.all(np.isnan(fr.U[1]))


def test_generic_cloud_in_metres(tmp_path):
    f = write(tmp_path / "p.csv", "x,y,z,u,v,w\n0.008,0.001,0.03,1e-4,NaN,0\n")
    fr = read_frame(f, units="m")
    assert fr.layout.format == "generic"
    assert np.allclose(fr.X, [[8.0, 1.0, 30.0]]) and fr.lost.tolist() == [True]
    with pytest.raises(DicError, match="is in mm but units m"):
        read_frame(write(tmp_path / "q.csv", "x [mm],y [mm],z [mm],u [mm],v [mm],w [mm]\n1,2,3,0,0,0\n"), units="m")


def test_bad_rows_are_refused_by_line(tmp_path):
    with pytest.raises(DicError, match=r"line 3: cannot read '4,5,six,0,0,0'"):
        read_frame(write(tmp_path / "a.csv", "x,y,z,u,v,w\n1,2,3,0,0,0\n4,5,six,0,0,0\n"), units="mm")
    with pytest.raises(DicError, match="line 2: fewer fields than the 6 of the header"):
        read_frame(write(tmp_path / "b.csv", "x,y,z,u,v,w\n1,2,3,0\n"), units="mm")


def test_unknown_layout_lists_columns_found_and_expected(tmp_path):
    f = write(tmp_path / "frame_1.csv", "Xc,Yc,Zc,dx,dy,dz\n1,2,3,0,0,0\n")
    with pytest.raises(DicError) as err:
        read_frame(f)
    msg = str(err.value)
    assert "columns found: Xc, Yc, Zc, dx, dy, dz" in msg
    for expected in ("MatchID (2024 headers): coor.X", "MatchID (short headers): x, y, z, u, v, w, x_pic",
                     "VIC-3D: X, Y, Z, U, V, W", "DICe: COORDINATE_X", "generic point cloud: x, y, z, u, v, w"):
        assert expected in msg


# -- series of frames --------------------------------------------------------------------------------------

def test_frame_numbers_from_names():
    assert frame_numbers(["DICe_solution_10.txt", "DICe_solution_2.txt"]) == ([10, 2], True)
    assert frame_numbers(["spec_0012_0.csv", "spec_0003_0.csv"]) == ([12, 3], True)
    assert frame_numbers(["b10.csv", "a2.csv"]) == ([1, 0], False)  # no single number differs: natural order


def test_series_by_subset_id_natural_order_and_reference_losses(tmp_path):
    rows = {2: "0,100,200,0,0,0.01\n1,110,200,0,0,0.01\n2,120,200,0,0,-1\n",
            10: "1,110,200,0.4,0.5,0.01\n0,100,200,0.2,0.3,0.01\n2,120,200,9,9,0.01\n",
            3: "2,120,200,9,9,0.01\n0,100,200,0.1,0.1,-1\n"}
    for n, body in rows.items():
        write(tmp_path / f"DICe_solution_{n}.txt", DICE_PREAMBLE + DICE.split(",GAMMA")[0] + "\n" + body)
    write(tmp_path / "notes.txt", "operator: A. N. Other\n")
    with pytest.raises(DicError, match=r"frames 2\.\.10 have a gap: frame\(s\) 4, 5, 6, 7, 8, 9 missing"):
        read_dic(tmp_path, scale=1.0)
    s = read_dic(tmp_path, scale=1.0, allow_gaps=True)
    assert s.frames.tolist() == [2, 3, 10] and [f.name for f in s.files][0] == "DICe_solution_2.txt"
    assert s.point_ids.tolist() == [0, 1] and s.lost_in_reference.tolist() == [2]
    assert np.array_equal(s.U[2, :, :2], [[0.2, 0.3], [0.4, 0.5]])  # matched by id, not row
    assert np.all(np.isnan(s.U[1])) and s.unmatched_rows == 2  # id 0 lost, id 1 missing; id 2 not in reference
    assert [p.name for p in s.ignored] == ["notes.txt"] and s.ignored_why == ["no DIC export header"]


def test_series_matches_missing_rows_by_image_coordinates(tmp_path):
    ref = "100,200,1,2,3,0,0,0,0,0,0\n110,200,2,2,3,0,0,0,0,0,0\n120,200,3,2,3,0,0,0,0,0,0\n"
    write(tmp_path / "spec_0000_0.tif.csv", MATCHID_2024 + "\n" + ref)
    write(tmp_path / "spec_0001_0.tif.csv", MATCHID_2024 + "\n120,200,3,2,3,0.3,0,0,0,0,0\n100,200,1,2,3,0.1,0,0,0,0,0\n")
    s = read_dic(tmp_path)
    assert np.array_equal(s.U[1, :, 0], [0.1, np.nan, 0.3], equal_nan=True)


def test_series_refuses_duplicate_frames_and_mixed_layouts(tmp_path):
    body = "SUBSET_ID,COORDINATE_X,COORDINATE_Y,DISPLACEMENT_X,DISPLACEMENT_Y\n0,1,2,0,0\n"
    write(tmp_path / "a" / "DICe_solution_0.txt", body)
    write(tmp_path / "a" / "DICe_solution_00.txt", body)
    with pytest.raises(DicError, match="are both frame 0"):
        read_dic(tmp_path / "a", scale=1.0)
    write(tmp_path / "b" / "f_1.csv", body)
    write(tmp_path / "b" / "f_2.csv", "x,y,z,u,v,w\n1,2,3,0,0,0\n")
    with pytest.raises(DicError, match="mixes layouts"):
        read_dic(tmp_path / "b", scale=1.0, units="mm")


def test_landmarks_in_export_units_or_by_point_id(tmp_path):
    write(tmp_path / "e" / "c_0.csv", "x,y,z,u,v,w\n0.001,0.002,0.003,0,0,0\n0.004,0.005,0.006,0,0,0\n")
    s = read_dic(tmp_path / "e", units="m")
    src, dst = read_landmarks(write(tmp_path / "l1.csv", "dic_x,dic_y,dic_z,model_x,model_y,model_z\n"
                                                          "0.01,0.02,0.03,8,0,30\n"), s)
    assert np.allclose(src, [[10, 20, 30]]) and np.allclose(dst, [[8, 0, 30]])
    src, _ = read_landmarks(write(tmp_path / "l2.csv", "point_id,model_x,model_y,model_z\n1,8,0,30\n"), s)
    assert np.allclose(src, [[4, 5, 6]])
    with pytest.raises(DicError, match="not points of the reference"):
        read_landmarks(write(tmp_path / "l3.csv", "point_id,model_x,model_y,model_z\n7,8,0,30\n"), s)


# -- pressure trace ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("unit, factor", [("kPa", 1e-3), ("MPa", 1.0), ("Pa", 1e-6), ("bar", 0.1)])
def test_pressure_units_are_converted_to_mpa(tmp_path, unit, factor):
    tr = read_pressure_trace(write(tmp_path / "p.csv", f"time [s],pressure [{unit}]\n0,0\n1,22\n"))
    assert np.allclose(tr.pressure, [0.0, 22 * factor], rtol=1e-15)


def test_pressure_trace_errors_and_frame_matching(tmp_path):
    with pytest.raises(DicError, match="gives no unit"):
        read_pressure_trace(write(tmp_path / "a.csv", "time,pressure\n0,1\n"))
    tr = read_pressure_trace(write(tmp_path / "b.csv", "frame,time [ms],pressure [kPa]\n0,0,0\n1,500,5\n2,1000,10\n"))
    t, p = pressure_at_frames(tr, [0, 2])
    assert np.allclose(t, [0.0, 1.0]) and np.allclose(p, [0.0, 0.01])
    with pytest.raises(DicError, match=r"no row for DIC frame\(s\) \[3\]"):
        pressure_at_frames(tr, [0, 3])
    tr = read_pressure_trace(write(tmp_path / "c.csv", "time [s],pressure [kPa]\n0,0\n1,10\n"))
    with pytest.raises(DicError, match="2 samples for 3 DIC frames"):
        pressure_at_frames(tr, [0, 1, 2])
    t, p = pressure_at_frames(tr, [4, 5, 6], "time", frame_rate=4.0, first_frame_time=0.25)
    assert np.allclose(t, [0.25, 0.5, 0.75]) and np.allclose(p, [0.0025, 0.005, 0.0075])
    with pytest.raises(DicError, match="DIC frame 6 is at t = 1.25 s"):
        pressure_at_frames(tr, [4, 5, 6], "time", frame_rate=2.0, first_frame_time=0.25)


# -- end to end: scripts/import_dic.py --------------------------------------------------------------------

import_dic = load_script("import_dic")
NORMAL = np.array([1.0, 0.0, 0.0])
CORNERS = np.array([[8.0, -8.0, 0.0], [8.0, 8.0, 0.0], [8.0, 8.0, 60.0], [8.0, -8.0, 60.0]])


def face_recording(seed: int = 0):
    """A contract recording of a DIC-like grid on the front face x = 8 (4 frames, frame 0 the
    undeformed reference), smooth made-up displacements, ~6 % of later point-frames lost; also the
    out-of-plane displacement ux a 3-D camera would see. Returns (recording, U (K, P, 3) mm, lost)."""
    rng = np.random.default_rng(seed)
    y, z = np.meshgrid(np.arange(-7.0, 7.01, 1.75), np.arange(2.0, 58.1, 4.0))
    X = np.stack([np.full(y.size, 8.0), y.ravel(), z.ravel()], axis=1)
    lam = np.arange(4) / 3
    U = lam[:, None, None] * np.stack([0.4 * np.sin(X[:, 2] / 15), -12.0 * (X[:, 2] / 60) ** 2,
                                       0.8 * X[:, 2] / 60 + 0.1 * X[:, 1] / 8], axis=1)[None]
    lost = np.zeros(U.shape[:2], dtype=bool)
    lost[1:] = rng.random((3, len(X))) < 0.06
    Z = np.where(lost[..., None], np.nan, U[..., 1:])
    rec = Recording(np.arange(4), 0.5 * np.arange(4), 0.022 * lam, np.arange(len(X)), X, Z, "truth")
    return rec, U, lost


def camera_3d(rng):
    """A camera frame at a random orientation whose origin (the camera, as in VIC-3D's camera
    coordinates) lies 100-300 mm in front of the face x = 8: model = R p + t."""
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    return (Q if np.linalg.det(Q) > 0 else -Q), np.array([rng.uniform(100.0, 300.0), *rng.uniform(-300.0, 300.0, 2)])


def export_3d(fmt, out, rec, U, lost, rng, corners=CORNERS, frame=np.eye(3), origin=None):
    """Write the recording as a 3-D export seen by a camera at a random pose (model = R p + t), with one
    extra speckle 3 mm in front of the face; landmarks: the face corners picked with depth errors,
    paired with the model points ``corners`` (the true ones by default). ``frame``: a further change of
    the camera coordinates (``diag(1, 1, -1)``: a left-handed frame); ``origin``: the model point the
    frame's origin sits at (default: the camera, 100-300 mm in front of the face)."""
    R, t = camera_3d(rng)
    t = t if origin is None else np.asarray(origin, dtype=np.float64)
    R = R @ frame
    X = np.vstack([rec.X, [11.0, 0.5, 31.0]])
    P, Ucam = (X - t) @ R, np.concatenate([U, np.zeros((len(U), 1, 3))], axis=1) @ R
    lost = np.concatenate([lost, np.zeros((len(U), 1), dtype=bool)], axis=1)
    pix = np.stack([500 + 40 * X[:, 1], 2600 - 40 * X[:, 2]], axis=1)
    depth = rng.uniform(-1.0, 1.0, (4, 1)) * (NORMAL @ R)
    landmarks = (CORNERS - t) @ R + depth
    f = 1e-3 if fmt == "generic" else 1.0
    for k in range(len(U)):
        rows = []
        for i in range(len(X)):
            if fmt == "matchid2024":
                if lost[k, i]:
                    continue  # MatchID leaves lost points out
                rows.append(",".join(map(num, [*pix[i], *P[i], *Ucam[k, i], 0.001, 0.002, 0.0])))
            elif fmt == "matchid":
                u = np.full(3, np.nan) if lost[k, i] else Ucam[k, i]
                rows.append(",".join(map(num, [*pix[i], *P[i], *u, 0.0, 0.0, 0.0])))
            elif fmt in ("vic3d", "vic3d;"):
                if lost[k, i]:
                    cells = [*pix[i], 0, 0, -1 if i % 2 else np.nan, 0, 0, 0, 0, 0, 0, 0, 0, 0]
                else:
                    cells = [*pix[i], 0.5, 0.5, 0.01, *P[i], *Ucam[k, i], 0, 0, 0]
                rows.append(",".join(map(num, cells)))
            else:
                u = np.full(3, np.nan) if lost[k, i] else Ucam[k, i]
                if k == 3 and lost[k, i]:
                    continue  # the last frame leaves lost points out: matched by coordinates
                rows.append(",".join(f"{full(v)}" for v in [*(P[i] * f), *(u * f)]))
        if fmt == "matchid2024":
            write(out / f"specimen_{k:04d}_0.tif.csv", MATCHID_2024 + "\n" + "\n".join(rows) + "\n")
        elif fmt == "matchid":
            write(out / f"specimen_{k:04d}_0.tif.csv", MATCHID_SHORT + "\n" + "\n".join(rows) + "\n")
        elif fmt == "vic3d":
            write(out / f"spec_{k:04d}_0.csv", VIC3D + "\n" + "\n".join(rows) + "\n")
        elif fmt == "vic3d;":
            text = VIC3D + "\n" + "\n".join(rows) + "\n"
            write(out / f"spec_{k:04d}_0.csv", f'"spec_{k:04d}_0.tif"\n' + text.replace(",", ";"))
        else:
            write(out / f"cloud-{k:03d}.csv", "x,y,z,u,v,w\n" + "\n".join(rows) + "\n")
    lm = "dic_x,dic_y,dic_z,model_x,model_y,model_z\n" + "".join(
        ",".join(f"{full(v)}" for v in [*(a * f), *b]) + "\n" for a, b in zip(landmarks, corners))
    return write(out.parent / "landmarks.csv", lm)


def export_dice(out, rec, U, lost, rng, scale=0.025):
    """Write the recording as DICe 2-D solutions: image plane parallel to the face, image y down,
    pixels; one extra subset beside the actuator (y = 12 mm); later frames list subsets shuffled."""
    a = rng.uniform(0, 2 * np.pi)
    ex, ey = np.array([0.0, np.cos(a), np.sin(a)]), np.array([0.0, np.sin(a), -np.cos(a)])
    R = np.stack([ex, ey, np.cross(ex, ey)], axis=1)  # model = scale R p + t, p = (x_px, y_px, 0)
    t = np.array([8.0, -40.0, 80.0])
    X = np.vstack([rec.X, [8.0, 12.0, 30.0]])
    P, Upx = (X - t) @ R / scale, np.concatenate([U, np.zeros((len(U), 1, 3))], axis=1) @ R / scale
    assert np.abs(P[:, 2]).max() < 1e-9
    lost = np.concatenate([lost, np.zeros((len(U), 1), dtype=bool)], axis=1)
    for k in range(len(U)):
        order = rng.permutation(len(X)) if k else np.arange(len(X))
        rows = []
        for i in order:
            sigma, u = (-1.0, (0.0, 0.0)) if lost[k, i] else (0.005, Upx[k, i, :2])
            rows.append(",".join(f"{v:.16E}" for v in [P[i, 0], P[i, 1], *u, sigma, 0.02, 0.0, 4.0, 0.007, 0, 0, 0]))
            rows[-1] = f"{i}," + rows[-1]
        write(out / f"DICe_solution_{k}.txt", DICE_PREAMBLE + DICE + "\n" + "\n".join(rows) + "\n")
    lm = "dic_x,dic_y,model_x,model_y,model_z\n" + "".join(
        f"{full(p[0])},{full(p[1])},{full(c[0])},{full(c[1])},{full(c[2])}\n" for p, c in zip((CORNERS - t) @ R / scale, CORNERS))
    return write(out.parent / "landmarks.csv", lm)


def assert_same(rec, truth):
    assert rec.frames.tolist() == truth.frames.tolist()
    assert rec.point_ids.tolist() == truth.point_ids.tolist()
    assert np.allclose(rec.times, truth.times, rtol=0, atol=1e-12)
    assert np.allclose(rec.pressure, truth.pressure, rtol=0, atol=1e-12)
    assert np.abs(rec.X - truth.X).max() < 1e-6
    assert np.array_equal(rec.mask, truth.mask)
    assert np.nanmax(np.abs(rec.Z - truth.Z)) < 1e-6


@pytest.mark.parametrize("fmt", ["matchid2024", "matchid", "vic3d", "vic3d;", "generic", "dice"])
def test_import_dic_round_trip(tmp_path, capsys, fmt):
    truth, U, lost = face_recording()
    rng = np.random.default_rng(["matchid2024", "matchid", "vic3d", "vic3d;", "generic", "dice"].index(fmt))
    export = tmp_path / "export"
    out = tmp_path / "rec.csv"
    args = [str(export), "--out", str(out), "--format", "auto"]
    if fmt == "dice":
        landmarks = export_dice(export, truth, U, lost, rng)
        # a dense trace in ms and Pa, the frames taken by time at 2 frames per second
        t = np.linspace(0.0, 2.0, 21)
        trace = write(tmp_path / "trace.csv", "Time [ms];Pressure [Pa]\n"
                      + "".join(f"{full(1e3 * ti)};{full(1e6 * 0.022 * ti / 1.5)}\n" for ti in t))
        args += ["--scale", "0.025", "--match", "time", "--frame-rate", "2"]
    else:
        landmarks = export_3d(fmt, export, truth, U, lost, rng)
        if fmt.startswith("vic3d"):  # a frame column and more samples than exported frames
            trace = write(tmp_path / "trace.csv", "frame,time [s],pressure [bar]\n" + "".join(
                f"{k},{full(0.5 * k)},{full(0.22 * k / 3)}\n" for k in range(8)))
        else:  # one row per frame in file order, placed in the export directory itself
            trace = write(export / "pressure.csv", "time [s],pressure [kPa]\n" + "".join(
                f"{full(ti)},{full(1e3 * p)}\n" for ti, p in zip(truth.times, truth.pressure)))
        if fmt in ("matchid", "generic"):
            args += ["--units", "m" if fmt == "generic" else "mm"]
    assert import_dic.main(args + ["--pressure", str(trace), "--landmarks", str(landmarks)]) == 0
    rec = read_recording(out)
    assert_same(rec, truth)
    if fmt == "vic3d":  # the calibration takes it: every point on the actuator's visible face
        assert recording_operator(actuator_mesh(ActuatorGeometry(resolution=1)), rec).n_points == len(truth.X)
    said = " ".join(capsys.readouterr().out.split())
    assert "Imported 4 frames (0..3)" in said and "1 farther than 0.5 mm from the face and dropped" in said
    assert f"(ids {len(truth.X)})" in said and "residual RMS" in said


def test_import_dic_identity_for_exports_already_in_the_model_frame(tmp_path):
    truth, export, trace = _identity_export(tmp_path)
    out = tmp_path / "rec.npz"
    assert import_dic.main([str(export), "--pressure", str(trace), "--out", str(out),
                            "--camera-to-model", "identity"]) == 0
    assert_same(read_recording(out), truth)
    assert (tmp_path / "rec.import.json").exists()


@pytest.mark.parametrize("case, message", [
    ("dice_no_scale", "in pixels; give the scale in mm per pixel"),
    ("unknown", "columns found: a, b, c"),
    ("no_landmarks", "3 of the 6 degrees of freedom undetermined"),
    ("trace_units", "gives no unit"),
])
def test_import_dic_errors_are_one_paragraph_and_exit_code_2(tmp_path, capsys, case, message):
    truth, U, lost = face_recording()
    export = tmp_path / "export"
    if case == "dice_no_scale":
        export_dice(export, truth, U, lost, np.random.default_rng(0))
    elif case == "unknown":
        write(export / "f_1.csv", "a,b,c\n1,2,3\n")
    else:
        export_3d("vic3d", export, truth, U, lost, np.random.default_rng(0))
    trace = write(tmp_path / "p.csv", "time,pressure" + ("" if case == "trace_units" else " [kPa]") + "\n"
                  + "".join(f"{k},{k}\n" for k in range(4)))
    assert import_dic.main([str(export), "--pressure", str(trace), "--out", str(tmp_path / "r.csv")]) == 2
    err = capsys.readouterr().err
    assert message in " ".join(err.split()) and "Traceback" not in err and "\n\n" not in err.strip()
    assert not (tmp_path / "r.csv").exists()


def _identity_export(tmp_path):
    truth, U, lost = face_recording(1)
    rows = lambda k: "".join(",".join(f"{full(v)}" for v in [*truth.X[i], *(np.nan * U[k, i] if lost[k, i] else U[k, i])])
                             + "\n" for i in range(len(truth.X)))
    for k in range(4):
        write(tmp_path / "e" / f"frame{k}.csv", "x [mm],y [mm],z [mm],u [mm],v [mm],w [mm]\n" + rows(k))
    trace = write(tmp_path / "p.csv", "time,pressure [MPa]\n" + "".join(
        f"{full(ti)},{full(p)}\n" for ti, p in zip(truth.times, truth.pressure)))
    return truth, tmp_path / "e", trace


def test_diagnose_and_calibrate_take_a_dic_export_directly(tmp_path, monkeypatch, capsys):
    """With --pressure, the scripts' recording argument is a DIC export: converted into
    runs/<name>/recording.csv (the import report printed) and that recording is what they use."""
    truth, export, trace = _identity_export(tmp_path)
    diagnose_script = load_script("diagnose")
    seen = {}

    def fake_diagnose(rec, **kw):
        seen["diagnose"] = rec
        raise SystemExit(0)

    monkeypatch.setattr("torchfra.diagnosis.pipeline.diagnose", fake_diagnose)  # the command imports it when run
    with pytest.raises(SystemExit):
        diagnose_script.main([str(export), "--pressure", str(trace), "--camera-to-model", "identity",
                              "--runs-dir", str(tmp_path / "runs"), "--name", "d"])
    assert_same(seen["diagnose"], truth)
    assert (tmp_path / "runs" / "d" / "recording.csv").exists()
    assert "Imported 4 frames" in " ".join(capsys.readouterr().out.split())

    calibrate_script = load_script("calibrate")

    def fake_calibration(config, run_dir, **kw):
        seen["calibrate"] = read_recording(config.recording)
        raise SystemExit(0)

    monkeypatch.setattr("torchfra.calibration.experiment.run_calibration", fake_calibration)
    with pytest.raises(SystemExit):
        calibrate_script.main(["--recording", str(export), "--pressure", str(trace), "--camera-to-model", "identity",
                               "--runs-dir", str(tmp_path / "runs"), "--name", "c", "--workers", "1"])
    assert_same(seen["calibrate"], truth)
    with pytest.raises(ValueError, match="give the export with --recording"):
        calibrate_script.main(["--pressure", str(trace), "--runs-dir", str(tmp_path / "runs"), "--workers", "1"])


# -- the commands as processes ---------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]


def run_command(argv, cwd):
    """A documented command as a process (``python scripts/...`` or ``torchfra ...``, here as ``python -m
    torchfra``, the same entry point): (exit code, stdout, stderr)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    argv = [sys.executable, str(ROOT / argv[1])] + argv[2:] if argv[0] == "python" else \
        [sys.executable, "-m", "torchfra"] + argv[1:]
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    return done.returncode, " ".join(done.stdout.split()), done.stderr


def vic3d_export(tmp_path, rng=0, **kw):
    """A VIC-3D export of the face recording in tmp_path/export, its trace (one row per frame) and landmarks."""
    truth, U, lost = face_recording()
    landmarks = export_3d("vic3d", tmp_path / "export", truth, U, lost, np.random.default_rng(rng), **kw)
    trace = write(tmp_path / "trace.csv", "time [s],pressure [kPa]\n" + "".join(
        f"{full(ti)},{full(1e3 * p)}\n" for ti, p in zip(truth.times, truth.pressure)))
    return truth, landmarks, trace


@pytest.mark.parametrize("command", [["python", "scripts/import_dic.py"], ["torchfra", "import-dic"]])
def test_import_dic_as_a_process(tmp_path, command):
    truth, _, _ = vic3d_export(tmp_path)
    rc, out, err = run_command(command + ["export", "--pressure", "trace.csv", "--landmarks", "landmarks.csv",
                                          "--out", "rec.csv"], tmp_path)
    assert rc == 0 and "Traceback" not in err, err
    assert_same(read_recording(tmp_path / "rec.csv"), truth)
    assert "Imported 4 frames (0..3) of a VIC-3D export" in out and "confirmed by the response" in out
    # without landmarks a flat face leaves the in-plane placement open: refused in one paragraph, exit 2
    rc, out, err = run_command(command + ["export", "--pressure", "trace.csv", "--out", "rec2.csv"], tmp_path)
    assert rc == 2 and "Traceback" not in err and "3 of the 6 degrees of freedom undetermined" in " ".join(err.split())
    assert not (tmp_path / "rec2.csv").exists()


def import_args(tmp_path, *extra):
    return [str(tmp_path / "export"), "--pressure", str(tmp_path / "trace.csv"), "--out", str(tmp_path / "rec.csv"),
            *extra]


# -- registration that cannot be fooled ------------------------------------------------------------------

def test_landmarks_on_the_diagonally_opposite_corners_are_refused(tmp_path, capsys):
    """The face is symmetric under a half turn, so landmarks paired with the opposite corners fit to
    1e-14 mm with every point at its mirror position; the clamped base decides: the measured
    displacement vanishes at z = 0 (the test's field grows with z, as the clamped actuator's does)."""
    vic3d_export(tmp_path, corners=CORNERS[[2, 3, 0, 1]])
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(tmp_path / "landmarks.csv"))) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "turned by a half turn about the face normal" in err and "diagonally opposite" in err
    assert not (tmp_path / "rec.csv").exists()


def test_mirrored_landmarks_put_the_camera_behind_the_face_and_are_refused(tmp_path, capsys):
    vic3d_export(tmp_path, corners=CORNERS[[1, 0, 3, 2]])  # left and right swapped
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(tmp_path / "landmarks.csv"))) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "the registered camera is" in err and "behind the face" in err and "landmarks are mirrored" in err
    assert "--left-handed" in err


def test_a_left_handed_camera_frame_registers_correctly(tmp_path, capsys):
    """Camera coordinates with z turned over: said with --left-handed, the registration is the
    reflection (det R = -1) and the recording equals the truth; unsaid, the camera lands behind the
    face and the import is refused, naming --left-handed. A left-handed plane-fitted frame (origin on
    the face, the camera's place unknown) registers as before, the camera side not checked."""
    truth, landmarks, _ = vic3d_export(tmp_path, frame=np.diag([1.0, 1.0, -1.0]))
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 2
    assert "--left-handed" in " ".join(capsys.readouterr().err.split())
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks), "--left-handed")) == 0
    assert_same(read_recording(tmp_path / "rec.csv"), truth)
    info = __import__("json").loads((tmp_path / "rec.import.json").read_text())
    assert np.linalg.det(np.asarray(info["R"])) == pytest.approx(-1.0, abs=1e-12) and info["left_handed"]
    assert "camera registered" in " ".join(capsys.readouterr().out.split())
    other = tmp_path / "plane_fitted"
    truth, landmarks, _ = vic3d_export(other, frame=np.diag([1.0, 1.0, -1.0]), origin=(8.0, 0.0, 30.0))
    assert import_dic.main(import_args(other, "--landmarks", str(landmarks))) == 0
    assert_same(read_recording(other / "rec.csv"), truth)
    assert "camera side not checked" in " ".join(capsys.readouterr().out.split())


def test_a_cloud_off_the_face_is_refused_not_written_with_one_point(tmp_path, capsys):
    """Points scattered +-20 mm off any plane: the registration keeps 1 of 136 within 0.5 mm."""
    rng = np.random.default_rng(3)
    truth, U, lost = face_recording()
    X = truth.X + np.outer(rng.uniform(-20.0, 20.0, len(truth.X)), NORMAL)
    scattered = Recording(truth.frames, truth.times, truth.pressure, truth.point_ids, X, truth.Z, "scattered")
    landmarks = export_3d("vic3d", tmp_path / "export", scattered, U, lost, rng)
    write(tmp_path / "trace.csv", "time [s],pressure [kPa]\n0,0\n0.5,7\n1,14\n1.5,22\n")
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "the registration keeps" in err and "of 136 points" in err and "do not lie on the face" in err
    assert not (tmp_path / "rec.csv").exists()


def test_a_row_written_twice_is_merged_and_a_clash_refused(tmp_path, capsys):
    truth, landmarks, _ = vic3d_export(tmp_path)
    for f in sorted((tmp_path / "export").glob("*.csv")):  # the fifth speckle row repeated in every frame
        lines = f.read_text().splitlines()
        f.write_text("\n".join(lines + [lines[5]]) + "\n")
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 0
    assert_same(read_recording(tmp_path / "rec.csv"), truth)
    assert "1 point(s) written twice merged (kept id, merged id: 4 136)" in " ".join(capsys.readouterr().out.split())
    last = sorted((tmp_path / "export").glob("*.csv"))[-1]
    cells = last.read_text().splitlines()
    row = cells[-1].split(",")
    row[8] = repr(float(row[8]) + 0.25)  # the copy's U differs in the last frame
    last.write_text("\n".join(cells[:-1] + [",".join(row)]) + "\n")
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "lines 6 and 138: points 4 and 136 lie at the same reference position" in err


def test_files_that_are_no_frames_are_named_and_a_gap_is_an_error(tmp_path, capsys):
    import os

    truth, landmarks, _ = vic3d_export(tmp_path)
    export = tmp_path / "export"
    os.mkfifo(export / "pipe.csv")
    (export / "notes.csv").write_bytes("x,y\n".encode("utf-16"))
    (export / "image.tif").write_bytes(b"II*\x00" + bytes(64))
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 0
    said = " ".join(capsys.readouterr().out.split())
    assert "Ignored 3 file(s) of the export folder: image.tif (not a .csv/.txt/.dat file); notes.csv (" in said
    assert "UTF-16" in said and "pipe.csv (is a FIFO (named pipe)" in said
    # a frame file that cannot be read (here: binary) leaves a gap: an error naming the file, unless allowed
    (export / "spec_0002_0.csv").write_bytes(b"\x00\x01binary")
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks))) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "frame(s) 2 missing" in err and "spec_0002_0.csv (" in err and "--allow-gaps" in err
    write(tmp_path / "trace.csv", "frame,time [s],pressure [kPa]\n" + "".join(
        f"{k},{full(ti)},{full(1e3 * p)}\n" for k, (ti, p) in enumerate(zip(truth.times, truth.pressure))))
    assert import_dic.main(import_args(tmp_path, "--landmarks", str(landmarks), "--allow-gaps")) == 0
    assert read_recording(tmp_path / "rec.csv").frames.tolist() == [0, 1, 3]
