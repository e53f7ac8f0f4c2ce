"""The virtual DIC experiment measured: pyvale's error against the FE truth, C10 calibrated from its
recording, and the diagnosis of that recording (a null: nothing but DIC between the model and the data).

    python studies/virtual_dic.py [--pixel-size 0.1] [--frames 10] [--members 16] [--diagnose] [--effect pressure_offset]

Needs the ``virtual-dic`` extra (pyvale). Steps:

1. ``torchfra.lab.run_virtual_dic``: the paper's actuator (C10 0.0048 MPa, no gravity, resolution 1)
   along a ramp to 0.022 MPa, filmed at ``--pixel-size`` mm per pixel (speckles 0.4 mm, grey noise
   1 %, 8 bits), correlated by pyvale (subset 21 px, step 10 px), imported as a recording; its error
   against the FE truth by region and its correlation length.
2. ``torchfra.calibration.run_calibration`` on that recording (``--members`` forward members,
   resolution 1, noise sigma = the engine's measured RMS, no restart filter): the posteriors of C10
   and their offsets from the truth in posterior standard deviations; and the same calibration on
   the FE truth at the same points (a perfect camera), so that the shift DIC causes is told from
   the calibration's own error. A recording made earlier with the same settings is reused.
3. With ``--diagnose``: ``torchfra.diagnosis.diagnose`` on it, at resolution 1 with the noise model
   the experiment measured (sigma, correlation length) and ``mesh_error=False`` (the recording is
   the diagnosis mesh's own, so DIC is all that differs). A null: no candidate should be named.
   ``--effect pressure_offset`` adds the same recording with its pressure trace read 0.002 MPa low
   (a sensor's offset, a library effect; the unloaded frame left out): the diagnosis should name it.

Writes studies/results/virtual_dic.json (``--out``) with the command; runs in runs/virtual_dic/.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch


def calibrate(recording: Path, sigma: float, members: int, run_dir: Path, truth: float) -> dict:
    """C10 from the recording: each filter's final mean and std, and its offset from ``truth`` in stds."""
    from torchfra.calibration import CalibrationConfig, run_calibration

    config = CalibrationConfig(members=members, resolution=1, recording=str(recording), noise=sigma,
                               restart=False, coverage_seeds=0)
    t0 = time.perf_counter()
    out = run_calibration(config, run_dir, progress=False)
    res = {"config": {"members": members, "resolution": 1, "noise_mm": sigma, "restart": False},
           "seconds": time.perf_counter() - t0, "filters": {}}
    post = out["filters"]["exact"]["posterior"]
    res["filters"]["exact"] = post.stats()["C10"]
    q = post.raw.q  # the exact posterior's grid in log C10: a posterior narrower than a cell is not resolved
    res["exact_grid_cell_C10"] = float(np.exp(q).mean() * (q[1] - q[0]))
    res["exact_edge_mass"] = post.edge_mass()
    for name in ("hierarchical", "hierarchical_nonlinear"):
        c = torch.exp(out["filters"][name]["result"].Q[-1][:, 0]).numpy()
        res["filters"][name] = {"mean": float(c.mean()), "std": float(c.std(ddof=1))}
    for name, s in res["filters"].items():
        s["offset_stds"] = (s["mean"] - truth) / s["std"]
        s["offset_relative"] = s["mean"] / truth - 1.0
    res["exact_spline_loo_error_mm"] = float(out["sweep_loo_error"])
    res["data_fit"] = {k: (float(v) if np.isscalar(v) else None) for k, v in out["data_fit"].items()}
    return res


def truth_recording(rec, truth: np.ndarray, path: Path) -> Path:
    """The engine's recording with the FE truth in place of the engine's displacements (same points, frames
    and pressures): what a perfect camera would record."""
    from dataclasses import replace

    from torchfra.io.recordings import write_recording

    return write_recording(path, replace(rec, Z=truth, source=str(path)))


def diagnosis(rec, sigma: float, ell: float, run_dir: Path) -> dict:
    """The diagnosis' decision on ``rec`` with the measured noise model, and what it calibrated."""
    from torchfra.diagnosis import diagnose

    t0 = time.perf_counter()
    d = diagnose(rec, noise=sigma, correlation=ell, run_dir=run_dir, resolution=1, progress=False, mesh_error=False)
    keep = {k: d[k] for k in ("decision", "missing_physics", "mismatch_detected", "parameters", "fit_before", "noise",
                              "ranking") if k in d}
    return {"seconds": time.perf_counter() - t0, "decision": d.get("decision"), "summary": _short(keep)}


def _short(obj, depth: int = 0):
    """The diagnosis' record without its long arrays (JSON-able)."""
    if isinstance(obj, dict):
        return {k: _short(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_short(v, depth + 1) for v in obj[:20]]
    if isinstance(obj, np.ndarray):
        return obj.tolist() if obj.size <= 20 else f"array {obj.shape}"
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return obj


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixel-size", type=float, default=0.1)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--members", type=int, default=16)
    ap.add_argument("--diagnose", action="store_true", help="also diagnose the recording (10-20 min)")
    ap.add_argument("--effect", choices=["pressure_offset"], default=None,
                    help="also diagnose the recording with this library effect (with --diagnose)")
    ap.add_argument("--runs", default="runs/virtual_dic")
    ap.add_argument("--out", default="studies/results/virtual_dic.json")
    a = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    from torchfra.io.recordings import read_recording
    from torchfra.lab.experiment import VirtualDicSettings, run_virtual_dic

    runs = Path(a.runs)
    settings = VirtualDicSettings(pixel_size=a.pixel_size, frames=a.frames)
    t0 = time.perf_counter()
    done = runs / "recording.virtual_dic.json"
    summary = json.loads(done.read_text()) if done.exists() else None
    if summary is None or summary["settings"] != json.loads(json.dumps(asdict(settings))):
        summary = run_virtual_dic(settings, runs / "recording.csv")
    else:
        print(f"virtual DIC: {done} was made with these settings; reusing it")
    b = summary["budget"]
    all_rms = np.asarray(b["regions"]["all"]["rms_mm"])
    sigma = float(np.sqrt(np.mean(all_rms ** 2)))
    ell = float(b["correlation_length_mm"])
    result = {
        "command": "python " + " ".join(sys.argv),
        "experiment": {k: v for k, v in summary.items() if k != "budget"},
        "budget": b, "noise_model": {"sigma_mm": sigma, "correlation_length_mm": ell,
                                     "how": "sigma: RMS of the engine's error over the loaded frames, both components"},
    }
    print(json.dumps(b["regions"], indent=1))
    result["calibration"] = calibrate(runs / "recording.csv", sigma, a.members, runs / "calibration", settings.c10)
    print(json.dumps(result["calibration"]["filters"], indent=1))
    # the same calibration on a perfect camera's recording: what the calibration itself is off by
    rec = read_recording(runs / "recording.csv")
    truth = np.load(runs / "recording_lab" / "truth.npz")["truth"]
    perfect = truth_recording(rec, truth, runs / "recording_fe_truth.csv")
    result["calibration_fe_truth"] = calibrate(perfect, sigma, a.members, runs / "calibration_fe_truth", settings.c10)
    result["calibration_dic_shift"] = {
        name: {"mean_difference": s["mean"] - result["calibration_fe_truth"]["filters"][name]["mean"],
               "in_stds": (s["mean"] - result["calibration_fe_truth"]["filters"][name]["mean"]) / s["std"]}
        for name, s in result["calibration"]["filters"].items()}
    print(json.dumps(result["calibration_dic_shift"], indent=1))
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1))
    if a.diagnose:
        result["diagnosis_null"] = diagnosis(rec, sigma, ell, runs / "diagnosis_null")
        print("null:", result["diagnosis_null"]["decision"])
        Path(a.out).write_text(json.dumps(result, indent=1))
        if a.effect == "pressure_offset":
            from torchfra.observation.recording import Recording

            offset = 0.002  # MPa: the sensor reads this much low (true = recorded + offset); the unloaded frame,
            # which would read below zero, is left out
            shifted = Recording(rec.frames[1:], rec.times[1:], rec.pressure[1:] - offset, rec.point_ids, rec.X,
                                rec.Z[1:], "virtual DIC recording")
            result["diagnosis_pressure_offset"] = {"offset_MPa": offset,
                                                   **diagnosis(shifted, sigma, ell, runs / "diagnosis_pressure_offset")}
            print("pressure offset:", result["diagnosis_pressure_offset"]["decision"])
    result["seconds"] = time.perf_counter() - t0
    Path(a.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
