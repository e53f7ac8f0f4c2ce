"""DIC export readers and the pressure trace.

The small files below are written with the headers (names, units, quoting, preambles) the programs
write (DESIGN §8); numbers are written to full precision so round trips can be checked to 1e-6 mm.
"""
from pathlib import Path

import numpy as np
import pytest

from torchfra.io.dic import DicError, frame_numbers, read_dic, read_frame, read_landmarks
from torchfra.io.pressure_trace import pressure_at_frames, read_pressure_trace

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
    s = read_dic(tmp_path, scale=1.0)
    assert s.frames.tolist() == [2, 3, 10] and [f.name for f in s.files][0] == "DICe_solution_2.txt"
    assert s.point_ids.tolist() == [0, 1] and s.lost_in_reference.tolist() == [2]
    assert np.array_equal(s.U[2, :, :2], [[0.2, 0.3], [0.4, 0.5]])  # matched by id, not row
    assert np.all(np.isnan(s.U[1])) and s.unmatched_rows == 2  # id 0 lost, id 1 missing; id 2 not in reference
    assert [p.name for p in s.ignored] == ["notes.txt"]


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

