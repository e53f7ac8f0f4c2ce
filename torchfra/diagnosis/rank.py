"""Step 2 of the diagnosis: rank the candidates without refitting them.

For each candidate the whitened sensitivities of the observations to its parameters at the calibrated
point (candidates at their nulls), projected off the calibrated parameters' span; the score (Lagrange
multiplier) statistic ``e' U (U'U)^-1 U' e ~ chi^2_q`` under the base model, its p-value, the fraction of
the excess residual it can explain, and the smallest effect it could show at this noise."""
from __future__ import annotations

import math

import numpy as np
from scipy import stats

from torchfra.actuator.candidates import (
    CANDIDATE_PARAMETERS,
    COORDINATES,
    FAR_SECANTS,
    NUISANCE,
)
from torchfra.actuator.deck import DeckModel
from torchfra.diagnosis.model import ActuatorPhysics
from torchfra.diagnosis.noise import Whitener
from torchfra.diagnosis.progress import _Progress
from torchfra.observation.recording import Recording, RecordingError


def rank(E: np.ndarray, J: np.ndarray, names: list[str], base: list[str], candidates, frames: np.ndarray,
         alpha: float, power: float = 0.8, confound_tol: float = 0.1, group_tol: float = 0.95,
         secants: dict[str, str] | None = None) -> list[dict]:
    """Score tests of the candidates at the calibrated base point.

    E: whitened residuals (K, P, 2); J: whitened sensitivities (K, P, 2, d) for ``names`` (base
    parameters first). ``secants``: {parameter: name of a column of J} holding the secant of a
    parameter that switches on far from its null (:data:`physics.FAR_SECANTS`); its candidate is
    tested along both its derivative and that secant (a row's ``tested_directions``). Returns one
    row per candidate, most significant first."""
    secants = secants or {}
    m = np.isfinite(E[frames])
    e = E[frames][m]
    Jm = J[frames][m]
    B = Jm[:, [names.index(n) for n in base]]
    Qb, _ = np.linalg.qr(B)
    e_perp = e - Qb @ (Qb.T @ e)
    n_base = e.size - len(base)
    excess = max(float(e_perp @ e_perp) - n_base, 1e-12)
    rows, bases = [], {}
    for c in candidates:
        # a nuisance parameter (tau1) has no effect at its candidate's null: the score test is the
        # one of the others at the nuisance's prior value (valid at any fixed value)
        names_c = [p for p in CANDIDATE_PARAMETERS[c] if p not in NUISANCE]
        directions = [d for p in names_c for d in ([p, secants[p]] if p in secants else [p])]
        owner = [p for p in names_c for _ in ([p, secants[p]] if p in secants else [p])]
        S = Jm[:, [names.index(d) for d in directions]]
        U = S - Qb @ (Qb.T @ S)
        s_full = np.linalg.norm(S, axis=0)
        s_perp = np.linalg.norm(U, axis=0)
        frac = s_perp / np.maximum(s_full, 1e-300)
        # a parameter is tested unless the base parameters absorb it (less than ``confound_tol`` of its
        # sensitivity survives the projection): what survives of a twin (a pressure gain keeps 0.04 %
        # beside C10) is the twin's nonlinearity, and normalized it would pose as a direction of its
        # own. The size of what survives is not the yardstick: a candidate that switches on far from
        # its null (a fiber compliance, a finite bulk modulus) has a tiny sensitivity there, yet its
        # direction is what the score test needs. The smallest change detectable along it (80 %
        # power, one parameter, linearized) is reported beside.
        # A secant's direction counts like a derivative's: a parameter is tested if either survives.
        # The smallest detectable change along a secant ("E_fiber@5.342") is in the coordinate, the
        # effect taken as growing linearly along the secant: far more telling than the derivative's
        # for a compliant fiber
        nc1 = _noncentrality(stats.chi2.isf(alpha, 1), 1, power)
        detectable = {d: float(math.sqrt(nc1) / sp) for d, sp, f in zip(directions, s_perp, frac) if f > 1e-6}
        keep = frac >= confound_tol
        tested = [pn for pn in names_c if any(k for o, k in zip(owner, keep) if o == pn)]
        confounded = [pn for pn in names_c if pn not in tested]
        untestable = confounded
        Uk = U[:, keep]
        one_sided = False
        if Uk.shape[1]:
            Qu, Ru = np.linalg.qr(Uk)
            proj = Qu.T @ e
            lm = float(proj @ proj)
            qk = Uk.shape[1]
            p = float(stats.chi2.sf(lm, qk))
            bases[c] = Qu
            co = COORDINATES[tested[0]]
            if qk == 1 and co.transform == "linear" and co.null is not None and co.null == co.low:
                # a null on the edge of the admissible range (a density, a relaxation fraction g1 >= 0):
                # the one-sided score test, significant only when the data pull into the range
                one_sided = True
                p = 0.5 * p if float(Uk[:, 0] @ e) > 0 else 1.0 - 0.5 * p
        else:
            lm, p, qk = 0.0, 1.0, 0
        rows.append({"name": c, "parameters": list(CANDIDATE_PARAMETERS[c]), "score": lm, "dof": qk, "p_value": p,
                     "one_sided": one_sided,
                     "nuisance_parameters": [pn for pn in CANDIDATE_PARAMETERS[c] if pn in NUISANCE],
                     "explained_fraction": float(min(lm / excess, 1.0)) if lm > 0 else 0.0,
                     "confounded_with": (base if confounded else []),
                     "confounded_parameters": confounded, "untestable_parameters": untestable,
                     "tested_parameters": tested,
                     "tested_directions": [d for d, k in zip(directions, keep) if k],
                     "detectable_change": detectable,
                     "projected_fraction": {d: float(a / max(b, 1e-300)) for d, a, b in
                                            zip(directions, s_perp, s_full)}})
    # groups: candidates whose projected sensitivity spaces nearly coincide
    for r in rows:
        r["group"] = [r["name"]]
    names_c = [r["name"] for r in rows]
    for i, a in enumerate(names_c):
        for b in names_c[i + 1:]:
            if a in bases and b in bases:
                sv = np.linalg.svd(bases[a].T @ bases[b], compute_uv=False)
                if sv.size and sv.max() > group_tol:
                    rows[i]["group"].append(b)
                    rows[names_c.index(b)]["group"].append(a)
    for r in rows:
        r["group"] = sorted(set(r["group"]))
        r["significant"] = bool(r["p_value"] < alpha / max(len(rows), 1))  # Bonferroni over candidates
        r["level"] = alpha / max(len(rows), 1)
    return sorted(rows, key=lambda r: (-r["score"], r["name"]))


def _noncentrality(crit: float, dof: int, power: float) -> float:
    lo, hi = 0.0, 1e6
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if stats.ncx2.sf(crit, dof, mid) < power:
            lo = mid
        else:
            hi = mid
    return hi


def score_candidates(rec: Recording, white: Whitener, cands, c10: float, fit_frames: np.ndarray, alpha: float,
                     resolution: int = 1, load_steps: int = 10, cache=None, deck: DeckModel | None = None, bar=None,
                     weight: str = "before_reference"):
    """Step 2 of the diagnosis: the model with every candidate of ``cands`` at its null, C10 =
    ``c10``, observed with its exact sensitivities, plus one solve per parameter of
    :data:`physics.FAR_SECANTS` for its secant; :func:`rank` on the recording's residual at ``alpha``.
    Returns (physics, ranking, whitened sensitivities, their column names, FE solves)."""
    bar = bar or _Progress(False)
    full = ActuatorPhysics(rec, cands, resolution, load_steps, cache, deck=deck, weight=weight)
    far = [p for p in FAR_SECANTS if p in full.names]
    bar.phase("sensitivities of every candidate at the calibrated point"
              + (f", secants of {', '.join(far)}" if far else ""), 1 + len(far))
    z_null = full.null_point(c10)
    ev_full = full.observe(z_null)
    bar.tick(1)
    if not ev_full.ok:
        raise RecordingError(f"{rec.source}: the model with every candidate at its null did not converge at "
                             f"C10 = {c10:.4g} MPa")
    Ew = white(rec.Z - ev_full.Y)
    Jw = white(ev_full.J)
    names_w, secants, secant_points = list(full.names), {}, {}
    for p in far:
        co = full.coordinate(p)
        z_far = dict(z_null) | {p: co.clip(z_null[p] + FAR_SECANTS[p] * co.prior_std)}
        ev = full.observe(z_far, values_only=True)  # the secant needs the values alone: one solve
        bar.tick(1)
        if not ev.ok:  # the model does not solve there: the candidate keeps its derivative's test alone
            continue
        col = f"{p}@{z_far[p]:.4g}"
        Jw = np.concatenate([Jw, white((ev.Y - ev_full.Y) / (z_far[p] - z_null[p]))[..., None]], axis=-1)
        names_w.append(col)
        secants[p] = col
        secant_points[p] = math.exp(z_far[p]) if co.transform == "log" else z_far[p]
    ranking = rank(Ew, Jw, names_w, ["C10"], cands, fit_frames, alpha, secants=secants)
    for r in ranking:
        r["secant_points"] = {p: v for p, v in secant_points.items() if p in r["tested_parameters"]}
    return full, ranking, Jw, names_w, getattr(full, "solves_per_observation", 1) + len(far)


def _remaining_scores(E: np.ndarray, J: np.ndarray, names: list[str], fitted: list[str], rows: list[dict],
                      frames: np.ndarray, J_fit: np.ndarray | None = None) -> dict:
    """Score statistics of the candidates ``rows`` (their tested directions) on the residual E of a fit
    of ``fitted``: {name: {"score", "dof", "p_value"}}. J: whitened sensitivities at the base point
    (columns ``names``); the candidates' directions are projected off the fitted parameters'
    sensitivities, taken from ``J_fit`` (whitened, (K, P, 2, len(fitted)), at the fit's MAP) when
    given: a refit that moved a parameter far from its null (a fiber compliance) leaves a residual
    orthogonal to its sensitivities there, not at the null. A one-sided candidate (``one_sided``: a
    density, a relaxation fraction) counts only a pull into its range, as in :func:`rank`."""
    m = np.isfinite(E[frames]) & np.isfinite(J[frames][..., 0])
    e = E[frames][m]
    Jm = J[frames][m]
    F = Jm[:, [names.index(n) for n in fitted]] if J_fit is None else J_fit[frames][m]
    Qb, _ = np.linalg.qr(F)
    out = {}
    for r in rows:
        # a secant's column is named "<parameter>@<coordinate>": fitted with its parameter
        cols = [names.index(d) for d in r.get("tested_directions", r["tested_parameters"])
                if d.split("@")[0] not in fitted]
        if not cols:
            continue
        U = Jm[:, cols] - Qb @ (Qb.T @ Jm[:, cols])
        Qu, _ = np.linalg.qr(U)
        lm = float(np.sum((Qu.T @ e) ** 2))
        p = float(stats.chi2.sf(lm, len(cols)))
        if r.get("one_sided") and len(cols) == 1:
            p = 0.5 * p if float(U[:, 0] @ e) > 0 else 1.0 - 0.5 * p
        out[r["name"]] = {"score": lm, "dof": len(cols), "p_value": p}
    return out

