"""Step 1 of the diagnosis, and every refit: Gauss-Newton (Levenberg-Marquardt) on the posterior with the
exact sensitivities, a Laplace posterior (MAP, covariance, log evidence) at its end; the starts of a refit
(a coarse scan along the score direction, a grid for the frame-to-load parameters) and the base model's
first C10."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy import stats

from torchfra.actuator.candidates import (
    COORDINATES,
)
from torchfra.diagnosis.model import ActuatorPhysics, Evaluation
from torchfra.diagnosis.noise import DiagnosisError, Whitener
from torchfra.observation.recording import Recording, RecordingError

# Levenberg-Marquardt: a rejected step is retried with the damping raised tenfold (from 1e-2 up to
# 1e5 x diag(H), a short gradient step). Measured on a fiber compliance, E_fiber = 60 MPa, scanned
# to a start at 209 MPa: four tries up to 1.6e-2 never shortened the overshooting step enough and
# the fit stopped at the start.
MAX_DAMPING_TRIES = 8


@dataclass
class Fit:
    """Laplace posterior of the free parameters of one model: MAP ``z`` (coordinates), covariance,
    log likelihood / prior / evidence, whitened residuals (K, P, 2), the evaluation at the MAP."""

    names: list[str]
    z: dict[str, float]
    cov: np.ndarray
    log_likelihood: float
    log_prior: float
    log_evidence: float
    residual: np.ndarray
    evaluation: Evaluation
    solves: int
    seconds: float
    converged: bool

    def std(self, name: str) -> float:
        return float(np.sqrt(self.cov[self.names.index(name), self.names.index(name)]))

    def summary(self) -> dict:
        out = {}
        for n in self.names:
            c = COORDINATES[n]
            z, s = self.z[n], self.std(n)
            nat = math.exp(z) if c.transform == "log" else z
            nat_std = nat * s if c.transform == "log" else s
            out[n] = {"mean": nat, "std": nat_std, "unit": c.unit, "coordinate": c.transform,
                      "coordinate_mean": z, "coordinate_std": s}
        return out


def _objective(phys, white, Z, fit_frames, z, names, prior_mu, prior_sd):
    ev = phys.observe(z)
    if not ev.ok:
        return ev, math.inf, None, None
    e = white((Z - ev.Y)[fit_frames])
    J = white(ev.J[fit_frames])
    m = np.isfinite(e)
    r = e[m]
    Jm = J[m][:, [ev.names.index(n) for n in names]]
    dz = np.array([z[n] for n in names]) - prior_mu
    phi = 0.5 * float(r @ r) + 0.5 * float(np.sum((dz / prior_sd) ** 2))
    return ev, phi, r, Jm


def gauss_newton(phys: ActuatorPhysics, white: Whitener, free: list[str], z0: dict[str, float],
                 fit_frames: np.ndarray, max_iterations: int = 8, progress=None) -> Fit:
    """MAP of the ``free`` coordinates (the others stay at ``z0``) by Levenberg-Marquardt-damped
    Gauss-Newton with the exact sensitivities, prior Gaussian in the coordinates; the Laplace
    approximation at the MAP gives the covariance and the log evidence."""
    t0 = time.perf_counter()
    coords = [phys.coordinate(n) for n in free]
    mu = np.array([c.prior_mean for c in coords])
    sd = np.array([c.prior_std for c in coords])
    Z = phys.rec.Z
    z = dict(z0)
    solves = 0
    ev, phi, r, Jm = _objective(phys, white, Z, fit_frames, z, free, mu, sd)
    solves += 1
    if not math.isfinite(phi):
        raise RecordingError(f"{phys.rec.source}: the model did not converge at the starting point {z}")
    damping, converged = 0.0, False
    for _ in range(max_iterations):
        small = False
        x = np.array([z[n] for n in free])
        H = Jm.T @ Jm + np.diag(1 / sd**2)
        g = Jm.T @ r - (x - mu) / sd**2  # r = data - model: the step solves H dx = g
        accepted = False
        for _ in range(MAX_DAMPING_TRIES):
            step = np.linalg.solve(H + damping * np.diag(np.diag(H)), g)
            trial = dict(z)
            for n, c, s in zip(free, coords, step):
                trial[n] = c.clip(z[n] + s)
            ev_t, phi_t, r_t, J_t = _objective(phys, white, Z, fit_frames, trial, free, mu, sd)
            solves += 1
            if progress is not None:
                progress(solves)
            if phi_t <= phi + 1e-9 * abs(phi):
                small = np.all(np.abs(np.array([trial[n] - z[n] for n in free])) < 0.01 / np.sqrt(np.diag(H)))
                z, ev, phi, r, Jm = trial, ev_t, phi_t, r_t, J_t
                damping = damping / 4 if damping > 1e-6 else 0.0
                accepted = True
                break
            damping = max(10 * damping, 1e-2)
        if not accepted or small:
            converged = True  # no step lowers the objective, or the last one was negligible
            break
    x = np.array([z[n] for n in free])
    H = Jm.T @ Jm + np.diag(1 / sd**2)
    cov = np.linalg.inv(H)
    n_obs = r.size
    loglik = -0.5 * float(r @ r) - 0.5 * n_obs * math.log(2 * math.pi) - white.log_det(fit_frames)
    logprior = float(np.sum(stats.norm.logpdf(x, mu, sd))) - sum(c.log_prior_normalizer() for c in coords)
    sign, logdet = np.linalg.slogdet(cov)
    logev = loglik + logprior + 0.5 * len(free) * math.log(2 * math.pi) + 0.5 * logdet
    e_all = white(Z - ev.Y)
    return Fit(list(free), {n: z[n] for n in free}, cov, loglik, logprior, logev, e_all, ev, solves,
               time.perf_counter() - t0, converged)


def scan_start(phys: ActuatorPhysics, white: Whitener, free: list[str], added: list[str], z0: dict[str, float],
               fit_frames: np.ndarray, max_points: int = 6, progress=None) -> tuple[dict[str, float], int, list]:
    """A starting point for the refit of ``free`` from ``z0`` (the added parameters at their null): a
    coarse scan along the added parameters' Gauss-Newton direction at ``z0``, in steps of that step
    (capped at one prior standard deviation of the parameter that moves most), while the misfit with
    the other free parameters profiled out keeps falling.

    Why: a term that switches on far from its null is invisible to a local fit started there. The
    bulk's compliance D1 moves the observations in proportion to D1 itself, so in log D1 the
    sensitivity at the near-incompressible null is ~1/100 of that at D1 ~ 50 1/MPa; a damped
    Gauss-Newton from the null sees a flat objective and stops there (measured: log D1 = -0.1 +- 1.8
    against a true 4.0). The score direction at the null is still right (the score test is what
    ranked the candidate), so the scan walks along it until the misfit turns up.

    The profiled misfit of a scan point is the objective after the Gauss-Newton correction of the
    other free parameters (the quadratic model's decrease, from the exact sensitivities the solve
    returns); the scan continues from the corrected point. Returns (start, solves, trace) with trace
    rows {added parameter: coordinate, "misfit": profiled objective}."""
    coords = [phys.coordinate(n) for n in free]
    mu = np.array([c.prior_mean for c in coords])
    sd = np.array([c.prior_std for c in coords])
    ia = [free.index(n) for n in added]
    ib = [i for i in range(len(free)) if i not in ia]
    Z = phys.rec.Z

    def profiled(z):
        ev, phi, r, Jm = _objective(phys, white, Z, fit_frames, z, free, mu, sd)
        if progress is not None:
            progress(1)
        if not math.isfinite(phi):
            return math.inf, None, None
        x = np.array([z[n] for n in free])
        g = Jm.T @ r - (x - mu) / sd**2
        H = Jm.T @ Jm + np.diag(1 / sd**2)
        corrected = dict(z)
        gain = 0.0
        if ib:
            db = np.linalg.solve(H[np.ix_(ib, ib)], g[ib])
            gain = 0.5 * float(g[ib] @ db)
            for i, d in zip(ib, db):
                corrected[free[i]] = coords[i].clip(z[free[i]] + d)
        return phi - gain, corrected, np.linalg.solve(H, g)

    best, start, step = profiled(z0)
    solves = 1
    trace = [{n: z0[n] for n in added} | {"misfit": best}]
    if step is None:
        return dict(z0), solves, trace
    s = step[ia]
    scale = float(np.max(np.abs(s) / sd[ia]))
    if not scale > 1e-12:
        return start, solves, trace
    s = s / max(scale, 1.0)
    origin = np.array([z0[n] for n in added])
    for k in range(1, max_points + 1):
        trial = dict(start)
        for n, i, v in zip(added, ia, origin + k * s):
            trial[n] = coords[i].clip(v)
        if all(trial[n] == trace[-1][n] for n in added):
            break  # the scan reached the end of the admissible range
        value, corrected, _ = profiled(trial)
        solves += 1
        trace.append({n: trial[n] for n in added} | {"misfit": value})
        if not value < best:
            break
        best, start = value, corrected
    return start, solves, trace


LOAD_MAP_GRIDS = {"g1": (0.02, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.9),
                  "tau1": tuple(np.logspace(-2.5, 0.5, 13)),
                  "pressure_lag": tuple(np.linspace(-0.1, 0.1, 41))}


def load_map_start(phys: ActuatorPhysics, white: Whitener, free: list[str], added: list[str], z0: dict[str, float],
                   fit_frames: np.ndarray) -> tuple[dict[str, float], int, list]:
    """A starting point for a refit whose added parameters act on the frame-to-load map only
    (viscoelasticity's g1 and tau1, a pressure lag): ``z0`` and every point of the grid of the
    added parameters (:data:`LOAD_MAP_GRIDS`, natural units) are scored by the misfit with the
    other free parameters (C10) profiled out by their Gauss-Newton correction. The FE solve at
    ``z0`` serves every grid point, so the grid costs one solve; the objective in tau1 has a
    plateau on each side of the recording's time scale, which a local fit from the prior's tau1
    could not leave. Returns (start, solves, trace) as :func:`scan_start`."""
    import itertools

    coords = [phys.coordinate(n) for n in free]
    mu = np.array([c.prior_mean for c in coords])
    sd = np.array([c.prior_std for c in coords])
    ib = [i for i, n in enumerate(free) if n not in added]
    points = [dict(z0)] + [dict(z0) | {n: phys.coordinate(n).clip(phys.coordinate(n).coordinate(v)) for n, v in zip(added, vals)}
                           for vals in itertools.product(*(LOAD_MAP_GRIDS[n] for n in added))]
    best, start, trace = math.inf, dict(z0), []
    for z in points:
        ev, phi, r, Jm = _objective(phys, white, phys.rec.Z, fit_frames, z, free, mu, sd)
        if not math.isfinite(phi):
            continue
        x = np.array([z[n] for n in free])
        g = Jm.T @ r - (x - mu) / sd**2
        H = Jm.T @ Jm + np.diag(1 / sd**2)
        corrected = dict(z)
        if ib:
            db = np.linalg.solve(H[np.ix_(ib, ib)], g[ib])
            phi -= 0.5 * float(g[ib] @ db)
            for i, d in zip(ib, db):
                corrected[free[i]] = coords[i].clip(z[free[i]] + d)
        trace.append({n: z[n] for n in added} | {"misfit": phi})
        if phi < best:
            best, start = phi, corrected
    return start, 1, trace


def _initial_c10(phys: ActuatorPhysics, white: Whitener, frames, bar) -> tuple[float, int]:
    """A starting C10 for Gauss-Newton from one solve, by the scaling law of the incompressible
    rigid-fibre actuator: u(P, C10) ~ u(P C10_lo / C10, C10_lo) (DESIGN §1.3). The solve at a soft
    C10_lo (the prior's 2.5 % quantile, or a stiffer one when that balloons before full pressure)
    covers every stiffer C10's load range; the recording's misfit is then minimized over C10 on that
    one solve (bounded Brent in log C10). Returns (C10, FE solves spent)."""
    from scipy.optimize import minimize_scalar

    c = phys.coordinate("C10")
    bar.phase("starting point of C10 (one solve, scaling law)", bar.FIT_SOLVES + 3)
    # the softest solve that reaches the largest recorded pressure: the prior's 2.5 % quantile first
    # (a very soft one balloons before full pressure), then stiffer ones
    solves = 0
    for lo in (c.prior_mean - 1.96 * c.prior_std, c.prior_mean - c.prior_std, c.prior_mean):
        steps = phys.at_steps({"C10": lo})
        solves += 1
        bar.tick(1)
        if steps is not None:
            break
    else:
        return math.exp(c.prior_mean), solves
    s, Ys, dYs = steps
    lam = phys.frame_loads({"C10": torch.tensor([lo], dtype=torch.float64)}).numpy()
    Z = phys.rec.Z

    def misfit(logc):
        scaled = np.clip(lam * math.exp(lo - logc), 0.0, 1.0)  # the frames' load factors on the soft solve
        j = np.clip(np.searchsorted(s, scaled, side="right") - 1, 0, s.size - 2)
        h = s[j + 1] - s[j]
        t = ((scaled - s[j]) / h)[:, None, None]
        hh = h[:, None, None]
        Y = ((2 * t**3 - 3 * t**2 + 1) * Ys[j] + hh * (t**3 - 2 * t**2 + t) * dYs[j]
             + (-2 * t**3 + 3 * t**2) * Ys[j + 1] + hh * (t**3 - t**2) * dYs[j + 1])
        e = white((Z - Y)[frames])
        return float(np.nansum(e**2))

    hi = c.prior_mean + 3 * c.prior_std
    res = minimize_scalar(misfit, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    _check_magnitude(phys.rec, frames, lambda logc: np.clip(lam * math.exp(lo - logc), 0.0, 1.0), s, Ys,
                     res.x, lo, hi)
    return float(math.exp(res.x)), solves


def _check_magnitude(rec: Recording, frames, loads, s, Ys, logc: float, lo: float, hi: float) -> None:
    """Refuse displacements no C10 of the prior range can produce (a unit mistake), before any fit:
    at the bounds of the range the model's displacements (interpolated on the soft solve ``Ys`` at
    load factors ``s``) are compared with the recorded ones."""
    if not (abs(logc - hi) < 1e-2 or abs(logc - lo) < 1e-2):
        return
    lam = loads(logc)[frames]
    Y = np.stack([np.interp(lam, s, Ys[:, p, c]) for p in range(Ys.shape[1]) for c in range(2)], -1)
    Z = rec.Z[frames].reshape(len(frames), -1)
    m = np.isfinite(Z)
    ratio = float(np.linalg.norm(Z[m]) / max(np.linalg.norm(Y[m]), 1e-300))
    if 0.3 < ratio < 3.0:
        return
    c10 = math.exp(logc)
    if ratio < 1:
        raise DiagnosisError(
            f"{rec.source}: the recorded displacements are {1 / ratio:.3g} times smaller than the model's for the "
            f"stiffest C10 of the prior ({c10:.3g} MPa) at the recorded pressures. Displacements in metres "
            "instead of mm, or pressures in a unit too large (the contract is mm and MPa)? Nothing was fitted.")
    raise DiagnosisError(
        f"{rec.source}: the recorded displacements are {ratio:.3g} times larger than the model's for the softest "
        f"C10 of the prior ({c10:.3g} MPa) at the recorded pressures. Displacements in a unit smaller than mm, "
        "or pressures in a unit too small (the contract is mm and MPa)? Nothing was fitted.")

