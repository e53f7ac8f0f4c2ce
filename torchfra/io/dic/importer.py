"""A DIC export and its pressure trace as a recording (DESIGN §6), shared by ``scripts/import_dic.py``
and by every script that takes a recording (``calibrate.py``, ``diagnose.py``): given ``--pressure``,
their recording argument is read as a DIC export and converted first.

Formats (``--format auto`` tells them by their headers): MatchID CSV (2024 and older headers),
VIC-3D CSV, DICe solution files (pixels: give ``--scale`` in mm per pixel), generic ``x,y,z,u,v,w``
point clouds (give ``--units``). One file per frame; the first (by the frame number in the names)
is the undeformed reference. Registration: ``--camera-to-model register`` (ICP on the actuator's
front face, in-plane placement from ``--landmarks``) or ``identity``; points farther than ``--tol``
mm from the face are dropped (listed by id). Beside the recording, ``<out>.import.json`` keeps the
transform, the residuals and the dropped ids.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from torchfra.io.dic.exports import FORMATS, read_dic, read_landmarks, to_recording
from torchfra.io.pressure_trace import pressure_at_frames, read_pressure_trace
from torchfra.io.tables import DicError

MIN_KEPT = 0.5  # default least fraction of the reference points a registration must keep on the face
MIN_POINTS = 5  # fewest points a recording is written with: what a diagnosis needs (torchfra.diagnosis.pipeline)


def add_arguments(p: argparse.ArgumentParser, pressure_required: bool = False) -> None:
    """The import options (a group of ``p``)."""
    g = p.add_argument_group("DIC export (read as an export when --pressure is given)")
    g.add_argument("--pressure", required=pressure_required,
                   help="pressure trace CSV (time and pressure with units) of a DIC export")
    g.add_argument("--format", default="auto", choices=FORMATS,
                   help="the DIC software that wrote the export (auto: told by its headers)")
    g.add_argument("--scale", type=float, help="mm per pixel, for exports in pixels (DICe)")
    g.add_argument("--units", choices=("mm", "m"), help="length unit of exports whose headers give none")
    g.add_argument("--pressure-units", help="pressure unit if the trace's header gives none (kPa, MPa, Pa, bar...)")
    g.add_argument("--match", choices=("frame", "time"), default="frame",
                   help="pressure per frame by frame number / file order, or by time (needs --frame-rate)")
    g.add_argument("--frame-rate", type=float, help="camera frames per second (--match time)")
    g.add_argument("--first-frame-time", type=float, default=0.0, help="trace time of the first frame (s)")
    g.add_argument("--camera-to-model", choices=("register", "identity"), default="register",
                   help="register: place the points on the model's face by ICP (in-plane placement from "
                        "--landmarks); identity: the export's coordinates are the model's")
    g.add_argument("--landmarks", help="CSV of DIC point -> model point pairs (initial guess, in-plane placement)")
    g.add_argument("--fit-scale", action="store_true", help="also fit a uniform scale (registration)")
    g.add_argument("--tol", type=float, default=0.5, help="farthest a point may lie from the face (mm)")
    g.add_argument("--min-kept", type=float, default=MIN_KEPT,
                   help="refuse a registration that keeps less than this fraction of the points on the face")
    g.add_argument("--allow-gaps", action="store_true",
                   help="accept frame numbers with gaps (frames left out of the export on purpose)")
    g.add_argument("--left-handed", action="store_true", help="the export's coordinate frame is left-handed")
    g.add_argument("--dic-camera", choices=("auto", "origin", "+z", "-z", "unknown"), default="auto",
                   help="where the camera is in the DIC frame: at its origin (camera coordinates), along +z or -z "
                        "of it; auto: -z for 2-D (image) data, the origin when it lies far off the points' plane")


def import_export(export, a: argparse.Namespace, out, face=None) -> tuple[str, dict]:
    """Convert the export (a directory, a file, or a list of files) with the options ``a`` (see
    :func:`add_arguments`) into the recording ``out``; returns a one-paragraph report and the
    ``<out>.import.json`` content. ``face``: the model face the points are registered on (a
    :mod:`torchfra.observation.registration` face; default the actuator's front face)."""
    from torchfra.io.recordings import write_recording
    from torchfra.observation.registration import Similarity, check_orientation, evaluate, front_face, register

    exclude = [a.pressure] + ([a.landmarks] if a.landmarks else [])
    if isinstance(export, (list, tuple)) and len(export) == 1:
        export = export[0]
    series = read_dic(export, a.format, scale=a.scale, units=a.units, exclude=exclude,
                      allow_gaps=getattr(a, "allow_gaps", False))
    times, pressure = pressure_at_frames(read_pressure_trace(a.pressure, a.pressure_units), series.frames,
                                         a.match, a.frame_rate, a.first_frame_time)
    face = front_face() if face is None else face
    camera, camera_note = _dic_camera(series, getattr(a, "dic_camera", "auto"))
    view = np.array([1.0 if getattr(a, "camera", "+x") != "-x" else -1.0, 0.0, 0.0])
    if a.camera_to_model == "identity":
        reg = evaluate(series.X, face, Similarity.identity(), a.tol, series.point_ids)
        _check_kept(reg, getattr(a, "min_kept", MIN_KEPT))
        orient = None
    else:
        landmarks = read_landmarks(a.landmarks, series) if a.landmarks else None
        reg = register(series.X, face, landmarks=landmarks, point_ids=series.point_ids, scale=a.fit_scale, tol=a.tol,
                       left_handed=getattr(a, "left_handed", False))
        _check_kept(reg, getattr(a, "min_kept", MIN_KEPT))
        orient = check_orientation(reg, series.X, face, camera=camera, view=view, displacement=series.U,
                                   camera_note=camera_note)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    rec = to_recording(series, times, pressure, reg, source=str(out))
    out = write_recording(out, rec)
    K, P = rec.n_frames, rec.n_points
    masked = int((~np.isfinite(rec.Z[..., 0])).sum())
    outliers = reg.outlier_ids.tolist()
    info = {
        "format": series.layout.label, "files": [str(f) for f in series.files], "frames": series.frames.tolist(),
        "points_reference": int(len(series.point_ids)), "points_written": P,
        "lost_in_reference": series.lost_in_reference.tolist(), "off_face_ids": outliers,
        "rows_not_in_reference": series.unmatched_rows, "ignored_files": [str(f) for f in series.ignored],
        "ignored_why": list(series.ignored_why), "merged_duplicates": series.merged_duplicates,
        "orientation": None if orient is None else orient.text, "left_handed": bool(getattr(a, "left_handed", False)),
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
    ignored = [f"{f.name} ({why})" for f, why in zip(series.ignored, series.ignored_why)]
    merged = series.merged_duplicates
    text = (
        f"Imported {K} frames ({series.frames[0]}..{series.frames[-1]}) of a {series.layout.label} export: "
        f"{len(series.point_ids)} points in the reference frame"
        + (f" ({series.lost_in_reference.size} more lost there)" if series.lost_in_reference.size else "")
        + f", {len(outliers)} farther than {a.tol:g} mm from the face and dropped" + (f" (ids {shown})" if outliers else "")
        + f"; {masked} of {K * P} point-frames masked ({100.0 * masked / (K * P):.1f} %)."
        + (f" {len(merged)} point(s) written twice merged (kept id, merged id: "
           + ", ".join(f"{i} {j}" for i, j in merged[:10]) + (", ..." if len(merged) > 10 else "") + ")." if merged else "")
        + (f" Ignored {len(ignored)} file(s) of the export folder: " + "; ".join(ignored) + "." if ignored else "")
        + f" Registration ({how}): residual RMS {reg.rms:.3g} mm, max {reg.max:.3g} mm"
        + (f"; {orient.text}" if orient is not None else "") + ". "
        f"Pressure {pressure.min():.4g}..{pressure.max():.4g} MPa matched by {a.match}. "
        f"Wrote {out} ({K} frames x {P} points)."
    )
    return text, info


def _dic_camera(series, where: str):
    """The camera in the DIC frame for the orientation check, and a note when it cannot be placed."""
    if where == "unknown":
        return None, "camera side not checked (--dic-camera unknown)"
    if where in ("+z", "-z"):
        return ("direction", np.array([0.0, 0.0, 1.0 if where == "+z" else -1.0])), ""
    if where == "origin":
        return ("point", np.zeros(3)), ""
    if series.two_d:  # image coordinates, x right and y down: the camera looks along +z
        return ("direction", np.array([0.0, 0.0, -1.0])), ""
    X = series.X
    centre = X.mean(axis=0)
    _, sv, Vt = np.linalg.svd(X - centre, full_matrices=False)
    extent = float(np.sqrt((sv ** 2).sum() / len(X)))
    if abs(float(centre @ Vt[-1])) > 2.0 * extent:  # camera coordinates: the origin is at the camera
        return ("point", np.zeros(3)), ""
    return None, ("camera side not checked (the DIC frame's origin lies near the points, as in a plane-fitted frame; "
                  "--dic-camera says where the camera is)")


def _check_kept(reg, min_kept: float) -> None:
    """Refuse a registration that keeps too few points on the face."""
    if not 0.0 <= min_kept <= 1.0:
        raise DicError(f"--min-kept must be a fraction between 0 and 1, got {min_kept}")
    kept, total = int(reg.inlier.sum()), len(reg.inlier)
    if kept < max(MIN_POINTS, min_kept * total):
        raise DicError(
            f"the registration keeps {kept} of {total} points ({100.0 * kept / total:.1f} %) within {reg.tol:g} mm of "
            f"the face, fewer than {'the ' + str(MIN_POINTS) + ' a calibration or diagnosis needs' if kept < MIN_POINTS else f'{100.0 * min_kept:g} % (--min-kept)'}; "
            "the points do not lie on the face as registered: check the landmarks, the units or scale, "
            "--camera-to-model, and --tol (the farthest a point may lie from the face)")


def recording_path(path, a: argparse.Namespace, run_dir, face=None) -> Path:
    """The recording a script should read: ``path`` itself (the recording contract), or, when
    ``--pressure`` was given, the export at ``path`` converted into ``run_dir/recording.csv`` (the
    report printed), registered on ``face`` (see :func:`import_export`)."""
    if getattr(a, "pressure", None) is None:
        return Path(path)
    import textwrap

    out = Path(run_dir) / "recording.csv"
    text, _ = import_export(path, a, out, face)
    print(textwrap.fill(text, width=100))
    return out
