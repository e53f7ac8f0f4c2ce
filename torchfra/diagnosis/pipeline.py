"""Steps 1-4 of the diagnosis in order (:func:`diagnose`); the steps themselves live in the modules of
:mod:`torchfra.diagnosis` named after them."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from torchfra.actuator.candidates import DIAGNOSIS_CANDIDATES, HISTORY_DEPENDENT_CANDIDATES
from torchfra.actuator.deck import DeckModel
from torchfra.actuator.geometry import WEIGHT
from torchfra.diagnosis.decide import refit_and_decide
from torchfra.diagnosis.fit import Fit, _initial_c10, gauss_newton
from torchfra.diagnosis.locate import _pressure_direction, history_identifiable, hysteresis, locate
from torchfra.diagnosis.model import ActuatorPhysics
from torchfra.diagnosis.noise import DiagnosisError, NoiseModel, Whitener, estimate_noise
from torchfra.diagnosis.progress import _Progress
from torchfra.diagnosis.rank import score_candidates
from torchfra.diagnosis.refit import RefitContext, _fit_report, discretization_error, model_floor
from torchfra.diagnosis.result import Diagnosis, write_outputs
from torchfra.observation.recording import Recording

ALL_CANDIDATES = DIAGNOSIS_CANDIDATES  # every candidate a diagnosis can name (a rival is fitted, never named)
MAX_PRESSURE = 0.5  # MPa: beyond any pressure the soft actuator survives (a unit mistake)


def diagnose(rec: Recording, noise: float | None = None, correlation: float | None = None, candidates="all",
             run_dir=None, resolution: int = 1, load_steps: int = 10, alpha: float = 0.01,
             evidence_threshold: float = 5.0, held_out_every: int = 5, progress: bool = True,
             max_refits: int | None = None, deck: DeckModel | None = None, fe_history: bool = True,
             mesh_error: bool = True, weight: str = "before_reference") -> dict:
    """Diagnose ``rec``: locate its mismatch with the calibrated base model, rank the candidate physics,
    refit and decide (:mod:`torchfra.diagnosis`).

    Parameters
    ----------
    rec : Recording
        The recording (frames x points of (uy, uz) in mm, pressures in MPa).
    noise, correlation : float, optional
        The noise's standard deviation and spatial correlation length (mm); estimated from the
        frames when not given.
    candidates : "all" or list of str
        The candidate physics to test (:data:`ALL_CANDIDATES`).
    run_dir : path, optional
        Where ``diagnosis.json``, ``residuals.npz``, the figures and every FE solve (``solves/``) are
        written; a resumed diagnosis reuses the solves.
    resolution, load_steps : int
        The paper's actuator's mesh resolution and the load steps of each solve.
    alpha, evidence_threshold : float
        The tests' level, and the log-evidence margin an extension must win by (5: decisive).
    held_out_every : int
        Every n-th frame is held out of the fits to check their predictions.
    max_refits : int, optional
        Refit at most this many significant candidates (None: every one).
    deck : DeckModel, optional
        The user's own model (an Abaqus/CalculiX deck) instead of the paper's actuator.
    fe_history : bool
        A creeping body's refit ends on the FE model with history variables.
    mesh_error : bool
        Take the diagnosis mesh's own discretization error, estimated by one refinement, out of an
        extension's residual before the surrogate test; False only for a recording made by the
        diagnosis model itself on its own mesh (a test's inverse crime).
    weight : {"before_reference", "with_load"}
        When the ``gravity`` candidate's weight acts: before the recording's reference image (a real DIC
        recording: the body settles under it first, the recording's points are positions on the sagged
        body and its displacements are measured from there), or ramped with the pressure from the
        unloaded body (an explicit option for recordings made that way). Recorded in ``diagnosis.json``.

    Returns
    -------
    dict
        The diagnosis (:class:`torchfra.diagnosis.result.Diagnosis`: its fields and their meaning).
    """
    t_start = time.perf_counter()
    if weight not in WEIGHT:
        raise ValueError(f"weight must be one of {sorted(WEIGHT)}, got {weight!r}")
    cands, not_available = _candidates(candidates, deck)
    _check_recording(rec, held_out_every)
    run_dir = None if run_dir is None else Path(run_dir)
    cache = None if run_dir is None else run_dir / "solves"
    nm = noise_model(rec, noise, correlation)
    white = Whitener(rec, nm)
    if nm.estimated["sigma"] or (nm.estimated["ell"] and nm.ell > 0):
        white.calibrate(rec)
    K = rec.n_frames
    held = np.arange(held_out_every - 1, K, held_out_every) if held_out_every > 1 else np.zeros(0, int)
    fit_frames = np.setdiff1d(np.arange(K), held)
    bar = _Progress(progress)

    # 1. calibrate the base model (below the model's own noise floor: on the recording less its mesh's error)
    base = calibrate_base(rec, white, fit_frames, resolution, load_steps, cache, deck, mesh_error, bar)
    rec = base.rec
    c10 = math.exp(base.fit.z["C10"])
    raw = rec.Z - base.fit.evaluation.Y
    # the omnibus test takes half the level, the candidates' score tests the other half (Bonferroni):
    # a specific alternative is found by its score test long before it shows in the chi^2 total. A
    # recording that comes back down is also tested for path independence (hysteresis, model-free):
    # it then shares the omnibus half with the chi^2 total
    loop = hysteresis(rec, white, alpha / 4, _pressure_direction(base.phys, base.fit.z))
    where = locate(base.fit.residual, rec, fit_frames, 1, alpha / 4 if loop["applicable"] else alpha / 2, raw, nm.sigma,
                   nm.dof)
    where["detected_by_hysteresis"] = loop["detected"]
    where["detected"] = where["detected"] or loop["detected"]

    # 2. rank: sensitivities of every candidate at the calibrated point, candidates at their null
    cands, not_testable = _testable(rec, cands)
    _, ranking, Jw, names_w, ranking_solves = score_candidates(rec, white, cands, c10, fit_frames, alpha / 2,
                                                               resolution, load_steps, cache, deck, bar, weight)
    where["detected_by_score"] = any(r["significant"] for r in ranking)
    where["detected"] = where["detected"] or where["detected_by_score"]

    # 3./4. refit and decide
    base_report = _fit_report(base.fit, white, fit_frames, held, 1)
    ctx = RefitContext(rec, white, fit_frames, held, resolution, load_steps, cache, deck, ranking, Jw, names_w,
                       base_report, c10, alpha, evidence_threshold, fe_history, mesh_error, base.taken_out, bar,
                       weight=weight)
    verdict = refit_and_decide(ctx, where["detected"], loop, max_refits, base.phys, base.fit.z)
    bar.close()

    out = Diagnosis.of(rec, nm, base, where, loop, ranking, not_testable, not_available, deck, resolution, load_steps,
                       ctx.tried, verdict, base_report, ranking_solves, time.perf_counter() - t_start, held,
                       alpha, weight).to_json()
    if run_dir is not None:
        accepted = verdict.accepted[1] if verdict.accepted else None
        write_outputs(run_dir, out, rec, raw, where, base.fit, accepted, nm.sigma, base.taken_out)
    return out


@dataclass
class BaseFit:
    """Step 1's outcome: the base model ``phys`` and its fit, the recording it was fitted to (less the
    mesh's own error ``taken_out`` below the noise floor), the floor's report, and the FE solves spent
    (``start_solves`` on the first C10, ``solves`` on the fits)."""

    phys: ActuatorPhysics
    fit: Fit
    rec: Recording
    floor: dict
    taken_out: np.ndarray | None
    start_solves: int
    solves: int


def calibrate_base(rec: Recording, white: Whitener, fit_frames: np.ndarray, resolution: int, load_steps: int,
                   cache, deck: DeckModel | None, mesh_error: bool, bar: _Progress) -> BaseFit:
    """Step 1: C10 of the base model by Gauss-Newton from a first guess; below the model's own noise
    floor (:func:`model_floor`) its discretization error, estimated by one refinement at the fit, is
    taken out of the recording and C10 refitted."""
    sigma = white.noise.sigma
    phys = ActuatorPhysics(rec, (), resolution, load_steps, cache, deck=deck)
    c10_0, start_solves = _initial_c10(phys, white, fit_frames, bar)
    bar.phase("calibrating the base model (C10)", bar.FIT_SOLVES + 2)
    fit = gauss_newton(phys, white, ["C10"], {"C10": math.log(c10_0)}, fit_frames, progress=bar.tick)
    floor = model_floor(sigma, resolution, deck, mesh_error)
    taken_out, solves = None, fit.solves
    if floor["below"]:
        # below the floor the mesh's own discretization error alone sets off the tests (a null flagged
        # on 50-88 % of recordings at 0.05 mm): it is estimated by one refinement at the base fit, taken
        # out of the recording, and the base refitted; every test then sees the physics alone (measured:
        # 0.5-1.2 % flagged at every noise scanned down to 0.025 mm, the level's own 1 %;
        # studies/noise_floor.py)
        bar.phase(f"the noise {sigma:.3g} mm is below the resolution-{resolution} model's floor: estimating "
                  f"its own error (one solve at resolution {resolution + 1})", 2)
        taken_out, floor["taken_out"] = discretization_error(rec, (), fit.z, resolution, load_steps, cache, deck)
        bar.tick(2)
        if taken_out is not None:
            rec = replace(rec, Z=rec.Z - taken_out)
            phys = ActuatorPhysics(rec, (), resolution, load_steps, cache, deck=deck)
            bar.phase("recalibrating the base model (C10) on the recording less the mesh's error", bar.FIT_SOLVES + 2)
            fit = gauss_newton(phys, white, ["C10"], fit.z, fit_frames, progress=bar.tick)
            solves += fit.solves
    return BaseFit(phys, fit, rec, floor, taken_out, start_solves, solves)


def noise_model(rec: Recording, noise: float | None, correlation: float | None) -> NoiseModel:
    """The noise model: sigma and the correlation length as given, each estimated from the frames when
    not (:func:`estimate_noise`)."""
    if noise is None or correlation is None:
        est = estimate_noise(rec)
    nm = NoiseModel(float(noise) if noise is not None else est.sigma,
                    float(correlation) if correlation is not None else est.ell,
                    {"sigma": noise is None, "ell": correlation is None,
                     **({"frames_left_out": est.estimated["frames_left_out"]} if noise is None or correlation is None
                        else {})},
                    est.dof if noise is None else None)
    if not (nm.sigma > 0 and math.isfinite(nm.sigma)):
        raise DiagnosisError(f"noise sigma must be positive, got {nm.sigma}")
    return nm


def _candidates(candidates, deck: DeckModel | None) -> tuple[tuple[str, ...], dict[str, str]]:
    """The candidates to test, and those the deck cannot carry (with why)."""
    cands = ALL_CANDIDATES if candidates in ("all", None) else tuple(candidates)
    unknown = sorted(set(cands) - set(ALL_CANDIDATES))
    if unknown:
        raise DiagnosisError(f"unknown candidate {unknown[0]!r}; candidates: {', '.join(ALL_CANDIDATES)}")
    not_available = {}
    if deck is not None:
        not_available = deck.available(cands)
        if not_available and candidates not in ("all", None):
            c, why = next(iter(not_available.items()))
            raise DiagnosisError(f"candidate {c!r} on the deck {deck.path}: {why}; leave it out of --candidates")
        cands = tuple(c for c in cands if c not in not_available)
    return cands, not_available


def _testable(rec: Recording, cands) -> tuple[tuple[str, ...], dict[str, str]]:
    """The candidates the recording can test, and those it cannot (with why)."""
    not_testable = {}
    if set(cands) & set(HISTORY_DEPENDENT_CANDIDATES) and not history_identifiable(rec):
        # on a load that only rises, each load level is met once: creep only warps the load axis,
        # which the material's own nonlinearity can do as well (a surrogate); unloading or a hold
        # at constant pressure is what shows a history
        for c in set(cands) & set(HISTORY_DEPENDENT_CANDIDATES):
            not_testable[c] = ("the pressure only rises, without a hold: creep is a warp of the load axis there, "
                               "confounded with the material's nonlinearity; record unloading or a hold to test it")
        cands = tuple(c for c in cands if c not in not_testable)
    return cands, not_testable


def _check_recording(rec: Recording, held_out_every: int) -> None:
    rec.require_followed_points("the diagnosis (its residual maps, onset test and spatial clusters)")
    if rec.n_frames < 4:
        raise DiagnosisError(f"{rec.source}: {rec.n_frames} frames; a diagnosis needs at least 4 frames (some are "
                             "held out to check predictions, and the onset test needs a time series)")
    if rec.n_points < 5:
        raise DiagnosisError(f"{rec.source}: {rec.n_points} points; a diagnosis needs at least 5 points on the face "
                             "to locate a mismatch")
    if not (rec.pressure > 0).any():
        raise DiagnosisError(f"{rec.source}: no frame has a positive pressure; nothing loads the actuator")
    if np.nanmax(rec.pressure) > MAX_PRESSURE:
        k = int(np.nanargmax(rec.pressure))
        raise DiagnosisError(f"{rec.source}: frame {int(rec.frames[k])} records a pressure of {rec.pressure[k]:.4g} MPa; "
                             f"the silicone actuator (C10 ~ 0.006 MPa) balloons far below {MAX_PRESSURE:g} MPa (the "
                             "paper's largest is 0.022 MPa). Pressures in kPa or Pa instead of MPa?")

