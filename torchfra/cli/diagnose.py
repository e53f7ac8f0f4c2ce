"""Find the physics the model left out: locate the mismatch between a recording and the calibrated
base model, rank the candidate physics by score tests, refit the best and decide.

    python scripts/diagnose.py my_dic.csv --noise 1.0 --name my_diag
    python scripts/diagnose.py my_dic.csv --candidates gravity,compliant_base
    python scripts/diagnose.py matchid_exports/ --pressure trace.csv --landmarks corners.csv   # a DIC export
    python scripts/diagnose.py my_dic.csv --inp my_actuator.inp --camera=-x    # your own model (a deck)

writes runs/<name>/: diagnosis.json, residual_map.png, residual_over_time.png, ranking.png,
observed_vs_models.png, posterior_added.png (when a candidate is accepted), TensorBoard events,
and solves/ (every FE solve, reused when the diagnosis is run again).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from torchfra.cli.flags import add_resolution, add_run_folder, add_threads, parser
from torchfra.cli.run import add_deck_flags, check_deck_flags
from torchfra.io.dic.importer import add_arguments

# torchfra.diagnosis.pipeline.ALL_CANDIDATES (tests/test_help.py checks they agree), here so that --help needs no torch
CANDIDATES = ("cavity_offset", "compliant_base", "compressibility", "fiber_pitch", "fiber_stiffness", "gravity",
              "mooney_rivlin", "pressure_sensor", "viscoelasticity")


def build_parser():
    """The flags of ``torchfra diagnose`` (no torch imported)."""
    p = parser(__doc__)
    p.add_argument("recording", help="CSV/NPZ recording (torchfra format), or with --pressure a DIC export (a folder "
                                     "of per-frame files or one file), converted into runs/<name>/recording.csv")
    p.add_argument("--noise", type=float, default=None, metavar="MM",
                   help="noise std (mm); default: estimated from the frames")
    p.add_argument("--correlation", type=float, default=None, metavar="MM",
                   help="spatial noise correlation length (mm); 0 = independent; default: estimated")
    p.add_argument("--candidates", default="all", help=f"all, or a comma list of: {', '.join(CANDIDATES)}")
    add_run_folder(p, None, "outputs (default: diagnose_<recording stem>)")
    add_resolution(p, what="the diagnosis model (the paper's actuator)")
    p.add_argument("--load-steps", type=int, default=10, help="load steps of each FE solve")
    p.add_argument("--alpha", type=float, default=0.01, help="test level: the false-alarm probability of each test")
    add_threads(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar and no summary lines")
    p.add_argument("--no-mesh-error", action="store_true",
                   help="leave the diagnosis mesh's own discretization error in an extension's residual (by default "
                        "one solve a mesh finer estimates it and takes it out before the surrogate test); only for a "
                        "recording made by this very model on its own mesh")
    add_arguments(p)
    add_deck_flags(p, "the diagnosis fits its C10")
    p.add_argument("--gravity", default=None, metavar="X,Y,Z",
                   help="direction of the weight in the model's frame, for the gravity candidate (default 0,-1,0: "
                        "the paper's actuator lies on its side)")
    p.add_argument("--weight", choices=("before-reference", "with-load"), default="before-reference",
                   help="when the gravity candidate's weight acts: before the recording's reference image (a real DIC "
                        "recording: the body sags first, displacements are measured from there), or ramped with the "
                        "pressure from the unloaded body (default: %(default)s)")
    return p


def main(argv=None) -> dict:
    p = build_parser()
    a = p.parse_args(argv)
    check_deck_flags(a, pressure_flag=None)  # --pressure is the DIC export's pressure trace here
    import torch

    from torchfra.actuator.candidates import GRAVITY_DIRECTION
    from torchfra.actuator.deck import DeckModel
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import observed_surface
    from torchfra.diagnosis.noise import DiagnosisError
    from torchfra.diagnosis.pipeline import ALL_CANDIDATES, diagnose
    from torchfra.io.dic.importer import recording_path
    from torchfra.io.recordings import read_recording
    from torchfra.observation.noise import NoiseEstimateError, check_motion

    torch.set_num_threads(a.threads)
    cands = "all" if a.candidates == "all" else [c.strip() for c in a.candidates.split(",") if c.strip()]
    if cands != "all":
        bad = [c for c in cands if c not in ALL_CANDIDATES]
        if bad:
            raise DiagnosisError(f"--candidates: unknown candidate {bad[0]!r}; choose from {', '.join(ALL_CANDIDATES)}")
    run_dir = Path(a.runs_dir) / (a.name or f"diagnose_{Path(a.recording).stem}")
    gravity = GRAVITY_DIRECTION
    if a.gravity is not None:
        try:
            gravity = tuple(float(v) for v in a.gravity.split(","))
        except ValueError:
            gravity = ()
        if len(gravity) != 3 or not all(map(math.isfinite, gravity)) or not any(gravity):
            raise DiagnosisError(f"--gravity {a.gravity}: give the direction of the weight as three numbers X,Y,Z, "
                                 "not all zero, e.g. 0,-1,0")
        if a.inp is None and gravity != GRAVITY_DIRECTION:
            raise DiagnosisError("--gravity: the paper's actuator lies on its side (weight along -y); another "
                                 "direction needs your own model (--inp)")
    deck = DeckModel(a.inp, a.camera, a.face.upper() if a.face else None, gravity) if a.inp else None
    if deck is not None:
        deck.values()  # a missing or unreadable deck is refused here, before any work
    face = observed_surface(ForwardConfig(inp=a.inp, camera=a.camera, face=a.face or "")) if a.inp else None
    rec = read_recording(recording_path(a.recording, a, run_dir, face))
    try:
        check_motion(rec)  # a recording without motion has nothing to diagnose (and no noise to estimate)
    except NoiseEstimateError as exc:
        raise DiagnosisError(str(exc)) from None
    reused = len(list((run_dir / "solves").glob("solve_*.npz"))) if (run_dir / "solves").exists() else 0
    if reused and not a.quiet:
        print(f"resuming {run_dir}: {reused} FE solves on disk are reused")
    out = diagnose(rec, noise=a.noise, correlation=a.correlation, candidates=cands, run_dir=run_dir,
                   resolution=a.resolution, load_steps=a.load_steps, alpha=a.alpha, progress=not a.quiet, deck=deck,
                   mesh_error=not a.no_mesh_error, weight=a.weight.replace("-", "_"))
    out["threads"] = a.threads
    (run_dir / "diagnosis.json").write_text(json.dumps(out, indent=1, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
    if not a.quiet:
        g = out["mismatch_detected"]["global"]
        print(f"mismatch: {'yes' if out['mismatch_detected']['detected'] else 'no'} (chi2 p = {g['p_value']:.3g}, "
              f"RMS {g['rms']:.3f} noise units); decision: {out['decision']}; RMS after {out['fit_after']['rms']:.3f}; "
              f"{out['cost']['solves']} FE solves, {out['cost']['seconds']:.0f} s -> {run_dir}")
        floor = out["noise"]["model_floor"]
        if floor["below"]:
            out_of_it = floor.get("taken_out", {})
            if out_of_it.get("rms_mm") is not None:
                print(f"note: the noise is below the model's own floor ({floor['floor_mm']:g} mm): its discretization "
                      f"error ({out_of_it['rms_mm']:.3g} mm RMS, one solve at resolution {out_of_it['resolution']}) was "
                      "taken out of the recording before the tests")
            else:
                print(f"caution: {floor['why']}; here it could not be: {out_of_it.get('why')}")
        h = out["hysteresis"]
        if h.get("detected"):
            print(f"hysteresis: loading and unloading differ at equal pressure (largest loop {h['largest_loop_mm']:.3g} mm "
                  f"at point {h['worst_points'][0]['point']}; the body {h.get('sense', 'lags or leads')} its load): "
                  + ("explained by the library's viscoelastic creep" if out["decision"] == "viscoelasticity" else
                     "history-dependent physics the library does not explain (" + ", ".join(h["physics"]["possible_causes"])
                     + ")"))
    return out



if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
