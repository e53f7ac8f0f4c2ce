"""Synthetic recordings of the actuator (the paper's numerical experiment) and the recording a run calibrates."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from torchfra import fem
from torchfra.calibration.config import CalibrationConfig, ForwardConfig
from torchfra.calibration.forward import truth_values, with_deck
from torchfra.calibration.frames import ActuatorSolver
from torchfra.observation.operator import ObservationOperator, frame_times
from torchfra.observation.recording import Recording, RecordingError


def synthetic_recording(c10, resolution: int = 1, points="nodes", noise: float = 1.0, seed: int = 0,
                        times=None, pressure=None, progress: bool = False, parameters=(), fixed=(), deck=None
                        ) -> tuple[Recording, np.ndarray]:
    """A recording made by the model itself at C10 = ``c10`` (or, with a parameter set ``parameters``
    / ``fixed`` as in :class:`ForwardConfig`, at the values ``c10 = {name: value}`` of its uncertain
    parameters): the FE model is solved at every frame's pressure (no interpolation in time),
    observed at ``points`` ("nodes" of the visible face, or a DIC-like grid spacing in mm), and
    perturbed with N(0, noise^2) per component. Returns the recording and its noise-free
    observations (K, P, 2). ``deck``: ``{"inp", "camera", "face"}`` of the user's own model (see
    :class:`ForwardConfig`); its ``pressure`` at load factor 1 is the deck's, ``pressure`` a trace
    up to it."""
    from torchfra.observation.operator import regular_grid

    times = frame_times(100) if times is None else np.asarray(times, dtype=np.float64)
    deck = with_deck(ForwardConfig(resolution=resolution, parameters=list(parameters), **deck)) if deck else None
    fwd = deck or ForwardConfig(resolution=resolution)
    pressure = fwd.pressure * times if pressure is None else np.asarray(pressure, dtype=np.float64)
    if deck is not None and np.max(pressure) > deck.pressure * (1 + 1e-9):
        raise ValueError(f"the pressure trace reaches {np.max(pressure):g} MPa, above the deck's {deck.pressure:g} MPa")
    solver = ActuatorSolver(resolution, fwd=ForwardConfig(resolution=resolution, pressure=float(np.max(pressure)),
                                                          parameters=list(parameters), fixed=list(fixed))
                            if deck is None else replace(deck, fixed=list(fixed)))
    mesh = solver.mesh
    faces = solver.faces
    if isinstance(points, str) and points == "nodes":
        op = ObservationOperator(mesh, faces, points="nodes")
    else:
        op = ObservationOperator(mesh, faces, points=regular_grid(mesh, faces, float(points)))
    lam = pressure / solver.fwd.pressure
    distinct = np.unique(lam[lam > 0])
    if isinstance(c10, dict):
        params = solver.params_q(solver.pset.values(c10))
        where = ", ".join(f"{k} = {v:g}" for k, v in c10.items())
    else:
        params, where = solver.params([c10]), f"C10 = {c10:g} MPa"
    sol = fem.solve(solver.model, params, distinct, solver.options(),
                    progress=f"synthetic recording: FE solve at {where}" if progress else False)
    if sol.status[0] != "converged":
        raise RuntimeError(f"the model did not converge at {where} (reached load {sol.load_reached[0]:.3f})")
    Y = op(sol.u[0, :, : mesh.n_nodes]).numpy()  # (distinct, P, 2)
    clean = np.zeros((len(times), op.n_points, 2))
    pos = lam > 0
    clean[pos] = Y[np.searchsorted(distinct, lam[pos])]
    rng = np.random.default_rng(seed)
    Z = clean + noise * rng.standard_normal(clean.shape)
    rec = Recording(np.arange(len(times)), times, pressure, np.asarray(op.point_ids), op.points, Z, "synthetic")
    return rec, clean


def _load_recording(config: CalibrationConfig, run_dir: Path, progress: bool):
    """The recording to calibrate on, and its noise-free observations and truth when synthetic."""
    from torchfra.io.recordings import read_recording, write_recording

    if config.recording is not None:
        return read_recording(config.recording), None, None
    path, clean_path = run_dir / "recording.csv", run_dir / "recording_clean.npz"
    made_by = {k: getattr(config, k) for k in ("truth_c10", "noise", "noise_seed", "points", "frames", "pressure",
                                               "resolution")}
    if config.parameters:  # recordings of the paper's prior keep their old record
        made_by.update(parameters=config.parameters, fixed=config.fixed, truth=truth_values(config))
    truth = truth_values(config)
    if path.exists() and clean_path.exists():
        saved = json.loads(str(np.load(clean_path, allow_pickle=False)["made_by"]))
        if saved != json.loads(json.dumps(made_by)):
            raise RecordingError(f"{path} was made with other settings ({saved}); choose another --name, or "
                                 "delete the run folder's recording files to make a new one")
        return read_recording(path), np.load(clean_path, allow_pickle=False)["clean"], truth
    times = frame_times(config.frames)
    deck = {"inp": config.inp, "camera": config.camera, "face": config.face} if config.inp else None
    rec, clean = synthetic_recording(truth if config.parameters else config.truth_c10, config.resolution,
                                     config.points, config.noise, config.noise_seed, times, config.pressure * times,
                                     progress=progress, parameters=config.parameters, fixed=config.fixed, deck=deck)
    write_recording(path, rec)
    np.savez(clean_path.with_suffix(".tmp.npz"), clean=clean, made_by=json.dumps(made_by))
    clean_path.with_suffix(".tmp.npz").replace(clean_path)  # written last: marks the pair complete
    return read_recording(path), clean, truth

