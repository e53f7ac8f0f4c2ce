"""Import a DIC export and its pressure trace as a recording (DESIGN §6: frame,time,pressure,
point_id,X,Y,Z,uy,uz in the model frame, mm, MPa).

    python scripts/import_dic.py exports/ --pressure pressure.csv --landmarks corners.csv --out runs/recordings/test1.csv
    python scripts/import_dic.py dice_out/ --format dice --scale 0.02 --pressure p.csv --landmarks lm.csv --out rec.csv
    python scripts/import_dic.py clouds/ --units m --camera-to-model identity --pressure p.csv --out rec.csv

Formats (``--format auto`` tells them by their headers): MatchID CSV (2024 and older headers),
VIC-3D CSV, DICe solution files (pixels: give ``--scale`` in mm per pixel), generic ``x,y,z,u,v,w``
point clouds (give ``--units``). One file per frame; the first (by the frame number in the names)
is the undeformed reference.

``--camera-to-model register`` (default) places the reference points on the actuator's front face
(x = +8 mm, y in [-8, 8], z in [0, 60]) by ICP; a flat face fixes only its normal and offset, so
the in-plane placement comes from ``--landmarks`` (a CSV of DIC point -> model point pairs, see
``torchfra.io.dic.read_landmarks``). ``identity`` takes the DIC coordinates as model coordinates
(a coordinate system set up in the DIC software). Either way, points farther than ``--tol`` mm from
the face are dropped (listed by id), the others written at their closest face point, and the
displacements turned into the model frame. Beside the recording, ``<out>.import.json`` keeps the
transform, the residuals and the dropped ids.
"""
import argparse
import json
import sys
import textwrap
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from torchfra.io.dic import FORMATS, DicError, read_dic, read_landmarks, to_recording  # noqa: E402
from torchfra.io.pressure_trace import pressure_at_frames, read_pressure_trace  # noqa: E402
from torchfra.recordings import RecordingError, write_recording  # noqa: E402
from torchfra.registration import RegistrationError, Similarity, evaluate, front_face, register  # noqa: E402


def parse(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("export", nargs="+", help="directory of per-frame export files, or the files themselves")
    p.add_argument("--pressure", required=True, help="pressure trace CSV (time and pressure with units)")
    p.add_argument("--out", required=True, help="recording to write (.csv or .npz)")
    p.add_argument("--format", default="auto", choices=FORMATS)
    p.add_argument("--scale", type=float, help="mm per pixel, for exports in pixels (DICe)")
    p.add_argument("--units", choices=("mm", "m"), help="length unit of exports whose headers give none")
    p.add_argument("--pressure-units", help="pressure unit if the trace's header gives none (kPa, MPa, Pa, bar...)")
    p.add_argument("--match", choices=("frame", "time"), default="frame",
                   help="pressure per frame by frame number / file order, or by time (needs --frame-rate)")
    p.add_argument("--frame-rate", type=float, help="camera frames per second (--match time)")
    p.add_argument("--first-frame-time", type=float, default=0.0, help="trace time of the first frame (s)")
    p.add_argument("--camera-to-model", choices=("register", "identity"), default="register")
    p.add_argument("--landmarks", help="CSV of DIC point -> model point pairs (initial guess, in-plane placement)")
    p.add_argument("--fit-scale", action="store_true", help="also fit a uniform scale (registration)")
    p.add_argument("--tol", type=float, default=0.5, help="farthest a point may lie from the face (mm)")
    return p.parse_args(argv)


def run(a) -> tuple[str, dict]:
    exclude = [a.pressure] + ([a.landmarks] if a.landmarks else [])
    series = read_dic(a.export if len(a.export) > 1 else a.export[0], a.format, scale=a.scale, units=a.units,
                      exclude=exclude)
    times, pressure = pressure_at_frames(read_pressure_trace(a.pressure, a.pressure_units), series.frames,
                                         a.match, a.frame_rate, a.first_frame_time)
    face = front_face()
    if a.camera_to_model == "identity":
        reg = evaluate(series.X, face, Similarity.identity(), a.tol, series.point_ids)
    else:
        landmarks = read_landmarks(a.landmarks, series) if a.landmarks else None
        reg = register(series.X, face, landmarks=landmarks, point_ids=series.point_ids, scale=a.fit_scale, tol=a.tol)
    rec = to_recording(series, times, pressure, reg, source=str(a.out))
    out = write_recording(a.out, rec)
    K, P = rec.n_frames, rec.n_points
    masked = int((~np.isfinite(rec.Z[..., 0])).sum())
    outliers = reg.outlier_ids.tolist()
    info = {
        "format": series.layout.label, "files": [str(f) for f in series.files], "frames": series.frames.tolist(),
        "points_reference": int(len(series.point_ids)), "points_written": P,
        "lost_in_reference": series.lost_in_reference.tolist(), "off_face_ids": outliers,
        "rows_not_in_reference": series.unmatched_rows, "ignored_files": [str(f) for f in series.ignored],
        "masked_observations": masked, "camera_to_model": a.camera_to_model, "method": reg.method,
        "iterations": reg.iterations, "converged": reg.converged,
        "R": reg.transform.R.tolist(), "t_mm": reg.transform.t.tolist(), "scale": reg.transform.s,
        "residual_rms_mm": reg.rms, "residual_max_mm": reg.max, "tol_mm": a.tol,
        "landmark_error_mm": reg.landmark_error.tolist(), "pressure_MPa": [float(pressure.min()), float(pressure.max())],
        "match": a.match, "out": str(out),
    }
    Path(out).with_suffix(".import.json").write_text(json.dumps(info, indent=1))
    how = ("DIC coordinates taken as model coordinates" if a.camera_to_model == "identity" else
           f"point-to-{reg.method} ICP from {len(reg.landmark_error) or 'no'} landmarks, {reg.iterations} iterations"
           + ("" if reg.converged else " (not converged)")
           + (f", landmarks off by up to {reg.landmark_error.max():.3g} mm" if reg.landmark_error.size else ""))
    shown = ", ".join(map(str, outliers[:10])) + (", ..." if len(outliers) > 10 else "")
    text = (
        f"Imported {K} frames ({series.frames[0]}..{series.frames[-1]}) of a {series.layout.label} export: "
        f"{len(series.point_ids)} points in the reference frame"
        + (f" ({series.lost_in_reference.size} more lost there)" if series.lost_in_reference.size else "")
        + f", {len(outliers)} farther than {a.tol:g} mm from the face and dropped" + (f" (ids {shown})" if outliers else "")
        + f"; {masked} of {K * P} point-frames masked ({100.0 * masked / (K * P):.1f} %). "
        f"Registration ({how}): residual RMS {reg.rms:.3g} mm, max {reg.max:.3g} mm. "
        f"Pressure {pressure.min():.4g}..{pressure.max():.4g} MPa matched by {a.match}. "
        f"Wrote {out} ({K} frames x {P} points)."
    )
    return text, info


def main(argv=None) -> int:
    a = parse(argv)
    try:
        text, _ = run(a)
    except (DicError, RegistrationError, RecordingError, OSError) as exc:
        print(textwrap.fill(f"import_dic: {exc}", width=100), file=sys.stderr)
        return 2
    print(textwrap.fill(text, width=100))
    return 0


if __name__ == "__main__":
    from torchfra.cli import run

    run(main)
