"""Step 3 of the diagnosis: refit the base model with a significant candidate switched on, and the checks
an extension must pass (evidence, distance from its null, residual back to the noise, held-out frames,
no other candidate left significant on its residual, the mesh's own discretization error taken out
first)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchfra.actuator.candidates import (
    CANDIDATE_PARAMETERS,
    LOAD_MAP_ONLY,
    NUISANCE,
)
from torchfra.actuator.deck import DeckModel
from torchfra.diagnosis.fit import Fit, gauss_newton, load_map_start, scan_start
from torchfra.diagnosis.locate import consistency
from torchfra.diagnosis.model import ActuatorPhysics, HistoryPhysics
from torchfra.diagnosis.noise import Whitener
from torchfra.diagnosis.progress import _Progress
from torchfra.diagnosis.rank import _remaining_scores
from torchfra.observation.recording import Recording

# The noise (mm) below which the paper's actuator model at a mesh resolution, fitted to a recording of a
# finer body, is flagged by its own discretization error alone on more than 5 % of nulls (the global
# chi^2 and the candidates' score tests, their union bounded by the sum; the suite's layout: 20 frames,
# a 2 mm grid, up to 0.022 MPa). Measured by studies/noise_floor.py on a noise-free resolution-2
# null (studies/results/study_noise_floor.json: at 0.1 mm 4.4-7.8 %, at 0.05 mm 50-88 %); other resolutions are
# not measured.
NOISE_FLOOR_MM = {1: 0.25}


HISTORY_ITERATIONS = 4  # Gauss-Newton iterations of the creeping body on the FE history model (from the


def _fit_report(fit: Fit, white: Whitener, frames_fit, frames_held, d: int) -> dict:
    g = consistency(fit.residual, frames_fit, d, white.noise.dof)
    held = fit.residual[frames_held]
    held = held[np.isfinite(held)]
    held_logpdf = float(-0.5 * held @ held - 0.5 * held.size * math.log(2 * math.pi)
                        - white.log_det(frames_held)) if held.size else None
    return {"rms": g["rms"], "nis_per_observation": g["nis_per_observation"], "chi2_p_value": g["p_value"],
            "log_evidence": fit.log_evidence, "log_likelihood": fit.log_likelihood,
            "held_out_log_density": held_logpdf,
            "held_out_rms": float(np.sqrt(np.mean(held**2))) if held.size else None,
            "parameters": fit.summary(), "solves": fit.solves, "seconds": fit.seconds}


def model_floor(sigma: float, resolution: int, deck: DeckModel | None = None, mesh_error: bool = True) -> dict:
    """Whether the noise ``sigma`` (mm) lies below the diagnosis model's own floor (:data:`NOISE_FLOOR_MM`):
    {"floor_mm", "below", "why"}. Below it the model's discretization error, not the recording's
    physics, would set off the tests and be taken up by a candidate: :func:`diagnose` then takes the
    error, estimated by one refinement at the base fit, out of the recording (``taken_out``: what
    :func:`discretization_error` said of it) and says so."""
    if deck is not None:
        return {"floor_mm": None, "below": False,
                "why": "the model is the user's deck: its own discretization error is not known"}
    if not mesh_error:
        return {"floor_mm": None, "below": False,
                "why": "the recording is taken as made by the diagnosis mesh itself (mesh_error=False): no error of its own"}
    floor = NOISE_FLOOR_MM.get(resolution)
    if floor is None:
        return {"floor_mm": None, "below": False, "why": f"the floor of the resolution-{resolution} model is not measured"}
    if sigma >= floor:
        return {"floor_mm": floor, "below": False, "why": None}
    return {"floor_mm": floor, "below": True,
            "why": (f"the noise {sigma:.3g} mm is below {floor:g} mm, where the resolution-{resolution} model's own "
                    "discretization error alone sets off the tests on more than 5 % of recordings without any "
                    "missing physics (studies/noise_floor.py): the error is estimated by one refinement at the "
                    "base fit and taken out of the recording before the tests (then 0.5-1.2 % down to 0.025 mm); if it "
                    f"cannot be, diagnose on a finer mesh (--mesh {resolution + 1}) or take the decision as provisional")}


def discretization_error(rec: Recording, combo, z: dict[str, float], resolution: int, load_steps: int,
                         cache=None, deck: DeckModel | None = None,
                         weight: str = "before_reference") -> tuple[np.ndarray | None, dict]:
    """The diagnosis model's own discretization error at the parameter point ``z`` (coordinates; the
    names it lacks at their nulls), estimated by one uniform refinement: ``(delta, info)`` with delta
    (K, P, 2) mm = Y at ``resolution + 1`` minus Y at ``resolution``, both the load-level model of the
    candidates ``combo`` with the same load steps (the difference is the mesh's alone), and info
    {"resolution", "rms_mm", "solves", "seconds", "why"}; delta is None, with the
    reason in info["why"], on a user's deck (no refinement of it is known) or when a solve fails.

    A recording is made by the body itself, or by a finer model, never by the diagnosis mesh: after
    the right refit its residual is the noise plus this error. Measured on a compressible bulk
    (k = 3) recorded at resolution 2 without noise, the right refit at resolution 1 leaves score
    statistics of 2.5 (gravity), 4.3 (base springs, 2 dof) and 2.0 (fiber pitch) in the residual:
    non-central enough to fail the surrogate test on 13 % of recordings at the noise 0.25 mm (0.3 %
    for the noise alone; README "The mesh's own error"). The refinement's estimate is exact for a recording made
    at ``resolution + 1`` and takes out the leading part of a finer one's."""
    t0 = time.perf_counter()
    info = {"resolution": resolution + 1, "solves": 0, "seconds": 0.0, "rms_mm": None, "why": None}
    if deck is not None:
        info["why"] = "the model is the user's deck: no refinement of it is known, the residual is taken as it is"
        return None, info
    coarse = ActuatorPhysics(rec, combo, resolution, load_steps, cache, weight=weight)
    fine = ActuatorPhysics(rec, combo, resolution + 1, load_steps, cache, weight=weight)
    point = {**coarse.null_point(math.exp(z["C10"])), **{n: v for n, v in z.items() if n in coarse.names}}
    Y = [phys.observe(point, values_only=True) for phys in (coarse, fine)]
    info["solves"] = sum(0 if ev.reused else 1 for ev in Y)
    info["seconds"] = time.perf_counter() - t0
    if not all(ev.ok for ev in Y):
        info["why"] = (f"the solve at resolution {resolution + (0 if not Y[0].ok else 1)} did not converge at the "
                       "refit's MAP: the residual is taken as it is")
        return None, info
    delta = Y[1].Y - Y[0].Y
    info["rms_mm"] = float(np.sqrt(np.nanmean(delta[rec.mask] ** 2)))
    return delta, info


def _acceptance(fit: Fit, rep: dict, base_rep: dict, combo, threshold: float, alpha: float, c10: float,
                free: list[str], phys: ActuatorPhysics) -> dict:
    away, inside = True, True
    for c in combo:
        for p in CANDIDATE_PARAMETERS[c]:
            if p not in free or p in NUISANCE:  # a nuisance (tau1) has no null of its own
                continue
            co = phys.coordinate(p)
            null = phys.null_coordinate(p, math.exp(fit.z["C10"]))
            dist = abs(fit.z[p] - (0.0 if p in ("c_n", "c_t") else null)) / fit.std(p)
            away &= dist > 3.0
            nat = math.exp(fit.z[p]) if co.transform == "log" else fit.z[p]
            inside &= co.low <= nat <= co.high
    held_better = (rep["held_out_log_density"] is None or base_rep["held_out_log_density"] is None
                   or rep["held_out_log_density"] > base_rep["held_out_log_density"])
    return {"evidence": rep["log_evidence"] - base_rep["log_evidence"] > threshold,
            "away_from_null": bool(away), "inside_range": bool(inside),
            "residual_at_noise": bool(rep["chi2_p_value"] > alpha and rep["rms"] < 1.1),
            "held_out_better": bool(held_better)}



def beats_its_members(rep: dict, combo, tried: list[dict], evidence_threshold: float) -> bool:
    """Whether the refit of the combination ``combo`` (report ``rep``) beats every refit in ``tried``
    of a part of it (a member alone) by more than ``evidence_threshold`` in log evidence. A part is
    the combination with the other terms at their nulls (nested models): a combination no better
    than its part names a term the data do not support, however far from its null that term's
    Laplace posterior sits (a stiff fiber's effect saturates, so its log E_fiber is free over
    decades: measured, E_fiber 388 +- 191 MPa beside a compressible bulk, 1.3 below the bulk alone)."""
    parts = [t["fit"]["log_evidence"] for t in tried if set(t["candidates"]) < set(combo)]
    return all(rep["log_evidence"] - ev > evidence_threshold for ev in parts)


@dataclass
class RefitContext:
    """What the refits of one diagnosis share: the recording (less the mesh's error where it was taken
    out), its noise model, the frames fitted and held out, the model's settings, the ranking with its
    whitened sensitivities (columns ``names_w``) at the base point, the base fit's report and C10, the
    test settings, and the refits so far (``tried``: their records, ``fits``: combo -> (Fit, report))."""

    rec: Recording
    white: Whitener
    fit_frames: np.ndarray
    held: np.ndarray
    resolution: int
    load_steps: int
    cache: Path | None
    deck: DeckModel | None
    ranking: list[dict]
    Jw: np.ndarray
    names_w: list[str]
    base_report: dict
    c10: float
    alpha: float
    evidence_threshold: float
    fe_history: bool
    mesh_error: bool
    taken_out: np.ndarray | None
    bar: _Progress
    tried: list[dict] = field(default_factory=list)
    weight: str = "before_reference"  # when the gravity candidate's weight acts (actuator.geometry.WEIGHT)
    fits: dict = field(default_factory=dict)


def refit(ctx: RefitContext, combo: tuple[str, ...], left: int) -> dict:
    """Refit the base model with the candidates ``combo`` switched on (``left``: refits still to come,
    for the progress bar's plan), check the extension and record it in ``ctx.tried``; returns the record."""
    bar, rec, white, fit_frames, held = ctx.bar, ctx.rec, ctx.white, ctx.fit_frames, ctx.held
    bar.phase(f"refitting with {' + '.join(combo)}", left * (bar.FIT_SOLVES + 2))
    phys = ActuatorPhysics(rec, combo, ctx.resolution, ctx.load_steps, ctx.cache, deck=ctx.deck, weight=ctx.weight)
    rows = [next(r for r in ctx.ranking if r["name"] == c) for c in combo]
    free = ["C10"] + [p for r in rows for p in r["tested_parameters"] + r["nuisance_parameters"]]
    added = [p for p in free if p != "C10"]
    if set(added) <= set(LOAD_MAP_ONLY):
        z0, scan_solves, scan = load_map_start(phys, white, free, added, phys.null_point(ctx.c10), fit_frames)
    else:
        z0, scan_solves, scan = scan_start(phys, white, free, added, phys.null_point(ctx.c10), fit_frames,
                                           progress=bar.tick)
    ext = gauss_newton(phys, white, free, z0, fit_frames, progress=bar.tick)
    ext.solves = (ext.solves + scan_solves) * getattr(phys, "solves_per_observation", 1)  # secants solve twice more
    load_map = None
    if combo == ("viscoelasticity",) and ctx.fe_history:
        # the load-level creep is the correspondence principle's approximation; the refit ends on
        # the FE model with history variables it stands in for (it misses 5-8 % of the effect on
        # the actuator, enough to leave a loop in the residual at SNR ~60), started at its MAP
        load_map = _fit_report(ext, white, fit_frames, held, len(free))
        bar.phase("refitting the creeping body with history variables in the element kernel (4 FE "
                  "marches a step)", HISTORY_ITERATIONS + 2)
        phys = HistoryPhysics(rec, ctx.resolution, ctx.cache, ctx.deck)
        fe = gauss_newton(phys, white, free, ext.z, fit_frames, max_iterations=HISTORY_ITERATIONS,
                          progress=bar.tick)
        fe.solves = ext.solves + getattr(phys, "marches", 0)
        ext = fe
    rep = _fit_report(ext, white, fit_frames, held, len(free))
    if load_map is not None:
        rep["load_map_fit"] = load_map
        rep["model"] = "fem.viscoelastic: one Prony term, history variables at every Gauss point"
    checks = _acceptance(ext, rep, ctx.base_report, combo, ctx.evidence_threshold, ctx.alpha, ctx.c10, free, phys)
    # a surrogate explains part of the mismatch: another candidate still significant on the
    # extended model's residual (score tests linearized at the base point) says so
    others = [r for r in ctx.ranking if r["name"] not in combo and r["dof"] > 0
              and not set(r["group"]) & set(combo)]
    ev_ext = ext.evaluation
    J_fit = white(ev_ext.J[..., [ev_ext.names.index(n) for n in free]])
    if len(combo) > 1:
        checks["beats_its_members"] = beats_its_members(rep, combo, ctx.tried, ctx.evidence_threshold)
    E_rem, mesh = ext.residual, None
    if ctx.mesh_error and all(checks.values()):
        # the last check of an extension that passed every other: its residual is at the noise,
        # and what is left in it beyond the noise is the diagnosis mesh's own discretization
        # error unless another physics is missing. The error is estimated by one refinement at
        # the MAP and taken out before the surrogate test (docs/diagnosis.md, "The mesh's own error")
        bar.phase(f"estimating the mesh's own error at the refit of {' + '.join(combo)} "
                  f"(one solve at resolution {ctx.resolution + 1})", 2)
        delta, mesh = discretization_error(rec, combo, ext.z, ctx.resolution, ctx.load_steps, ctx.cache, ctx.deck,
                                           ctx.weight)
        bar.tick(2)
        if delta is not None:
            # the base fit's estimate is out of the recording already (noise below the floor)
            E_rem = ext.residual - white(delta if ctx.taken_out is None else delta - ctx.taken_out)
    remaining = _remaining_scores(E_rem, ctx.Jw, ctx.names_w, free, others, fit_frames, J_fit)
    level = ctx.ranking[0]["level"] if ctx.ranking else ctx.alpha / 2
    checks["no_other_candidate_significant"] = all(v["p_value"] >= level for v in remaining.values())
    rep["scan"] = scan
    entry = {"candidates": list(combo), "fit": rep, "checks": checks, "accepted": all(checks.values()),
             "remaining_scores": remaining}
    if mesh is not None:
        mesh["remaining_scores_uncorrected"] = (
            _remaining_scores(ext.residual, ctx.Jw, ctx.names_w, free, others, fit_frames, J_fit)
            if E_rem is not ext.residual else remaining)
        entry["mesh_error"] = mesh
    ctx.tried.append(entry)
    ctx.fits[combo] = (ext, rep)
    return entry
