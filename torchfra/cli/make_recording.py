"""Write a synthetic DIC recording of the actuator made by the FE model itself.

    python scripts/make_recording.py --c10 0.0048 --noise 1.0 --seed 0 --out runs/recordings/paper.csv
    python scripts/make_recording.py --points 2.0 --cycles 2 --out runs/recordings/grid_cycles.npz
    python scripts/make_recording.py --value C01=0.001 --value E_fiber=25000 --out runs/recordings/mr.csv

The FE model is solved at every frame's pressure, observed (y, z displacements) at the visible face's
nodes or on a regular DIC-like grid (spacing in mm), and perturbed with independent N(0, noise^2)
noise on each component. The file holds only what a camera and a pressure sensor give
(frame,time,pressure,point_id,X,Y,Z,uy,uz): no parameter values, no hint of how it was made.
"""
from __future__ import annotations

from pathlib import Path

from torchfra.cli.flags import PEAK_PRESSURE, add_peak_pressure, add_resolution, add_threads, parser
from torchfra.cli.run import add_deck_flags, check_deck_flags

TRUTH_C10 = 0.0048  # MPa, the paper's truth (CalibrationConfig.truth_c10)


def pressure_trace(frames: int, p_max: float, cycles: int):
    """Normalized times 1/n..1 and the pressure: a linear ramp (cycles = 0, the paper's) or
    ``cycles`` loading-unloading triangles peaking at p_max.

    Returns
    -------
    times, pressure : numpy.ndarray
        Both of shape ``(frames,)``; the pressure in the units of ``p_max``.
    """
    import numpy as np

    from torchfra.observation.operator import frame_times

    t = frame_times(frames)
    if cycles <= 0:
        return t, p_max * t
    phase = (t * cycles) % 1.0
    return t, p_max * (1.0 - np.abs(2.0 * phase - 1.0))


def build_parser():
    """The flags of ``torchfra make-recording`` (no torch imported)."""
    p = parser(__doc__)
    p.add_argument("--c10", type=float, default=None, metavar="MPA",
                   help=f"C10 of the body (MPa); default the paper's truth {TRUTH_C10} (with --inp the deck's)")
    add_resolution(p)
    p.add_argument("--points", default="nodes", help="'nodes' of the visible face, or a DIC grid spacing in mm")
    p.add_argument("--noise", type=float, default=1.0, metavar="MM", help="noise std on each observed component (mm)")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--frames", type=int, default=100, help="camera frames, at t = 1/n .. 1")
    add_peak_pressure(p, None, f"peak cavity pressure (MPa; default {PEAK_PRESSURE}, with --inp the deck's)")
    p.add_argument("--cycles", type=int, default=0, help="loading-unloading cycles (0: one linear ramp)")
    p.add_argument("--value", action="append", default=[], metavar="NAME=VALUE",
                   help="another model parameter at a value (repeatable), e.g. C01=0.001 (Mooney-Rivlin), "
                        "E_fiber=25000, density=1.1e-9 (gravity), D1=0.5; the others keep the base model's")
    p.add_argument("--out", default="runs/recordings/recording.csv", help="the recording file to write: .csv or .npz")
    add_threads(p)
    add_deck_flags(p, "its values are kept unless --c10 or --value replace them")
    return p


def main(argv=None) -> Path:
    p = build_parser()
    a = p.parse_args(argv)
    check_deck_flags(a, "peak_pressure")
    if Path(a.out).suffix.lower() not in (".csv", ".npz"):
        p.error(f"--out must end in .csv or .npz, got {a.out!r}")
    if a.points != "nodes":
        try:
            float(a.points)
        except ValueError:
            p.error(f"--points must be 'nodes' or a grid spacing in mm, got {a.points!r}")
    import torch

    from torchfra.actuator.deck import deck_summary
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import with_deck
    from torchfra.calibration.priors import parse_fixed
    from torchfra.calibration.synthetic import synthetic_recording
    from torchfra.io.recordings import write_recording

    values = dict(parse_fixed(v, "--value") for v in a.value)  # each bad entry named before any work
    if "C10" in values:
        p.error("give C10 with --c10")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)  # a bad folder fails now, not after the FE solves
    torch.set_num_threads(a.threads)
    torch.set_default_dtype(torch.float64)
    if a.inp:  # the user's deck: its own values, those of --value and --c10 replaced, at its pressure
        fwd = with_deck(ForwardConfig(inp=a.inp, camera=a.camera, face=a.face or "", parameters=["C10=lognormal:1,0.1"],
                                      fixed=[f"{k}={v!r}" for k, v in values.items()]))
        c10 = a.c10 if a.c10 is not None else deck_summary(a.inp)[0]["C10"]
        times, pressure = pressure_trace(a.frames, fwd.pressure, a.cycles)
        rec, _ = synthetic_recording({"C10": c10}, a.resolution, a.points, a.noise, a.seed, times, pressure,
                                     progress=True, parameters=[f"C10=lognormal:{c10!r},{0.1 * c10!r}"],
                                     fixed=list(fwd.fixed),
                                     deck={"inp": a.inp, "camera": a.camera, "face": a.face or ""})
        path = write_recording(a.out, rec)
        print(f"{path}: {rec.n_frames} frames x {rec.n_points} points")
        return path
    a.c10 = TRUTH_C10 if a.c10 is None else a.c10
    times, pressure = pressure_trace(a.frames, PEAK_PRESSURE if a.peak_pressure is None else a.peak_pressure, a.cycles)
    if values:  # the model with the candidates these parameters need; the prior is only a carrier here
        rec, _ = synthetic_recording({"C10": a.c10}, a.resolution, a.points, a.noise, a.seed, times, pressure,
                                     progress=True, parameters=[f"C10=lognormal:{a.c10!r},{0.1 * a.c10!r}"],
                                     fixed=[f"{k}={v!r}" for k, v in values.items()])
    else:
        rec, _ = synthetic_recording(a.c10, a.resolution, a.points, a.noise, a.seed, times, pressure, progress=True)
    path = write_recording(a.out, rec)
    print(f"{path}: {rec.n_frames} frames x {rec.n_points} points")
    return path


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
