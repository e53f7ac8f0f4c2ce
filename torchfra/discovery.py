"""Finding the physics the model left out: locate the mismatch, rank the candidates, refit, decide.

The diagnosis of a recording (DESIGN §1.4):

1. **Calibrate** the base model (C10) by Gauss-Newton on the posterior with the exact
   sensitivities (a Laplace posterior: MAP, covariance and log evidence verified against the exact
   posterior by quadrature, one and two parameters, on a nonlinear scaling-law stand-in for the
   actuator in tests/test_discovery.py).
2. **Locate.** Whitened residuals over points x frames with the noise model (i.i.d. or spatially
   correlated with a squared-exponential kernel; sigma and the correlation length are estimated
   from frame-to-frame differences when not given). Global test: the residual sum of squares
   against chi^2 with n - d degrees of freedom. Onset: per-frame chi^2 tests with
   Benjamini-Hochberg control; the onset is the first frame after which the significant frames
   are the majority. Space: per-point chi^2 tests (BH at ``alpha``) grouped into clusters of
   neighbouring points. Below the model's own noise floor (:func:`model_floor`: its
   discretization error alone would set off these tests) that error, estimated by one refinement
   at the base fit (:func:`discretization_error`), is taken out of the recording and C10 refitted
   first (``noise.model_floor.taken_out``).
   **Hysteresis** (model-free, :func:`hysteresis`): a recording that comes back down from its
   largest pressure is tested for path independence, loading against unloading at equal pressure;
   every candidate of the library is hyperelastic and quasi-static, so a loop means
   history-dependent physics (viscoelasticity, a sensor lag, damage, friction, drift) and the
   decision is ``"unexplained"`` with that class named, whatever a candidate explains besides.
   The omnibus half of the level is then shared by the chi^2 total and the hysteresis test.
3. **Rank without refitting.** For each candidate, the whitened sensitivities of the observations
   to its parameters at the calibrated point (candidates at their null values), projected off the
   span of the calibrated parameters' sensitivities; the Lagrange-multiplier (score) statistic
   ``e' U (U'U)^-1 U' e ~ chi^2_q`` under the base model, its p-value, and the fraction of the
   excess residual it can explain. A candidate whose sensitivities lie (almost) in the span of the
   base parameters' is reported ``confounded_with`` them (a pressure gain with C10: the scaling
   law); candidates whose projected sensitivities nearly coincide form a group. The smallest
   effect each candidate could show at this noise (80 % power at the test level) is reported. A
   candidate whose effect changes its shape as it grows (a fiber compliance:
   :data:`physics.FAR_SECANTS`) is tested along its derivative and the secant to a point two prior
   standard deviations off its null together (two degrees of freedom): the derivative at a nearly
   inextensible fiber carries a quarter of a compliant fiber's effect, the pair more than 98 %.
4. **Refit and decide.** Every significant candidate (in order of their score statistic; at most
   ``max_refits`` when given) is added alone, and the best pair when none passes, and the extended parameters
   refitted by Gauss-Newton, started
   where a coarse scan along the score direction stops falling (``scan_start``: a term that switches
   on far from its null, such as the bulk compliance D1, is invisible to a local fit from there); an
   extension is accepted only if its Laplace log evidence beats the base model's (a pair's: also
   each of its members' refitted alone, :func:`beats_its_members`) by more than
   ``evidence_threshold`` (5: decisive on Jeffreys' scale), every added parameter is more than 3
   posterior standard deviations from its null and inside its range, the residual returns to the
   noise level (global test passes at ``alpha``, RMS within 10 % of the noise), the held-out
   frames are predicted better, and no other candidate's score test is still significant on the
   extended model's residual (a surrogate explains only part of the mismatch; the test projects off
   the extended model's sensitivities at its MAP, one-sided for a one-sided candidate, on the residual
   less the diagnosis mesh's own discretization error, estimated by one refinement at the MAP:
   :func:`discretization_error`; a recording of a body, or of a finer model, carries it, and at the
   suite's noise it alone would fail the test on about one recording in eight). Of the extensions
   that pass, the one with the largest evidence is the decision; any other within
   ``evidence_threshold`` of it explains the recording about as well, and is named beside it
   (``"a|b"``: the data cannot tell them apart). Nothing passes: ``"unexplained"``, with where the
   mismatch sits.

Every FE solve is cached in the run folder (array-only .npz): a resumed diagnosis redoes no solve.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from scipy import linalg, stats

from torchfra.actuator.candidates import (
    CANDIDATE_PARAMETERS,
    COORDINATES,
    FAR_SECANTS,
    HISTORY_DEPENDENT_CANDIDATES,
    LOAD_MAP_ONLY,
    NUISANCE,
    RIVALS,
)
from torchfra.actuator.deck import DeckModel
from torchfra.observation.recording import Recording, RecordingError
from torchfra.physics import ActuatorPhysics, Evaluation, HistoryPhysics

ALL_CANDIDATES = tuple(sorted(set(CANDIDATE_PARAMETERS) - set(RIVALS.values())))
MAX_PRESSURE = 0.5  # MPa: beyond any pressure the soft actuator survives (a unit mistake)
# Levenberg-Marquardt: a rejected step is retried with the damping raised tenfold (from 1e-2 up to
# 1e5 x diag(H), a short gradient step). Measured on a fiber compliance, E_fiber = 60 MPa, scanned
# to a start at 209 MPa: four tries up to 1.6e-2 never shortened the overshooting step enough and
# the fit stopped at the start.
MAX_DAMPING_TRIES = 8
# The noise (mm) below which the paper's actuator model at a mesh resolution, fitted to a recording of a
# finer body, is flagged by its own discretization error alone on more than 5 % of nulls (the global
# chi^2 and the candidates' score tests, their union bounded by the sum; the suite's layout: 20 frames,
# a 2 mm grid, up to 0.022 MPa). Measured by scripts/study_noise_floor.py on a noise-free resolution-2
# null (results/study_noise_floor.json: at 0.1 mm 4.4-7.8 %, at 0.05 mm 50-88 %); other resolutions are
# not measured.
NOISE_FLOOR_MM = {1: 0.25}


class DiagnosisError(ValueError):
    """A recording that cannot be diagnosed as it is (too few frames or points, no noise level)."""


# -- noise model --------------------------------------------------------------------------------------

@dataclass
class NoiseModel:
    """Gaussian noise on (uy, uz): standard deviation ``sigma`` (mm), spatial correlation
    ``exp(-d^2 / (2 ell^2))`` between points at distance d (ell = 0: independent), components and
    frames independent. ``estimated`` says whether sigma / ell came from the data."""

    sigma: float
    ell: float = 0.0
    estimated: dict = field(default_factory=dict)
    dof: float | None = None  # effective degrees of freedom of an estimated sigma^2 (None: sigma known)

    def correlation(self, X: np.ndarray) -> np.ndarray:
        """The points' correlation matrix (P, P)."""
        d2 = ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1)
        return np.exp(-d2 / (2 * self.ell**2)) if self.ell > 0 else np.eye(len(X))

    def factor(self, X: np.ndarray) -> np.ndarray | None:
        """Lower Cholesky factor of the points' correlation matrix (None when independent)."""
        if self.ell <= 0:
            return None
        return linalg.cholesky(self.correlation(X) + 1e-8 * np.eye(len(X)), lower=True)


def estimate_noise(rec: Recording) -> NoiseModel:
    """sigma and ell from frame-to-frame differences of the recording: a smooth response (and any
    smooth model mismatch) nearly cancels between neighbouring frames, noise independent in time
    does not (var = 2 sigma^2). The correlation length is fitted to the empirical correlation of
    neighbouring points' differences (squared-exponential kernel); below 0.1 correlation at the
    nearest spacing the noise is taken as independent."""
    Z = rec.Z
    if rec.n_frames < 3:
        raise DiagnosisError(f"{rec.source}: {rec.n_frames} frames; estimating the noise needs at least 3 "
                             "(or give --noise SIGMA)")
    D2 = np.diff(Z, n=2, axis=0)  # second differences remove a linear-in-time response too
    quiet = quiet_triples(D2)
    if not quiet.any():
        raise DiagnosisError(f"{rec.source}: no point is observed in three consecutive frames, so the noise "
                             "cannot be estimated from differences in time; give --noise SIGMA (mm) and "
                             "--correlation ELL (mm, 0 for independent noise)")
    D2 = D2[quiet]
    v = np.nanmean(D2**2) / 6.0  # var of x_{k+1} - 2 x_k + x_{k-1} for white noise: 6 sigma^2
    sigma = float(np.sqrt(v))
    X = rec.X
    d = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    near = float(np.median(d.min(axis=1)))
    A = np.nan_to_num(D2.transpose(1, 0, 2).reshape(rec.n_points, -1))
    A = A - A.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(A, axis=1)
    C = (A @ A.T) / np.maximum(np.outer(norm, norm), 1e-300)
    bins = near * np.array([0.5, 1.5, 2.5, 3.5, 5.0])
    rho, r = [], []
    for lo, hi in zip(bins[:-1], bins[1:]):
        m = (d > lo) & (d <= hi)
        if m.any():
            rho.append(float(C[m].mean()))
            r.append(float(d[m].mean()))
    ell = 0.0
    if rho and rho[0] > 0.1:
        # second differences keep the spatial kernel; fit exp(-d^2/2l^2) by least squares in log
        good = [(ri, pi) for ri, pi in zip(r, rho) if 0.02 < pi < 0.999]
        if good:
            rr, pp = np.array(good).T
            ell = float(np.sqrt(np.sum(rr**4) / np.sum(-2 * np.log(pp) * rr**2)))
    # sigma^2-hat ~ sigma^2 chi^2_nu / nu: Gaussian second differences have variance 6 sigma^2 and
    # correlations -4/6, 1/6 at lags 1, 2 in time, so var(sigma^2-hat) = (70/36) 2 sigma^4 / n; points
    # correlated in space share information (their squared correlations summed per point)
    n2 = int(np.isfinite(D2).sum())
    spatial = 1.0  # sum over points j of corr(i, j)^2, averaged over i
    if ell > 0:
        spatial += float(np.mean(np.sum(np.exp(-d**2 / (2 * ell**2)) ** 2, axis=1)))  # d_ii = inf: 0
    nu = n2 / (70.0 / 36.0 * spatial)
    return NoiseModel(sigma, ell, {"sigma": True, "ell": True, "nearest_spacing_mm": near,
                                   "neighbour_correlation": rho[0] if rho else 0.0,
                                   "frames_left_out": [int(rec.frames[k + 1]) for k in np.flatnonzero(~quiet)]}, nu)


def quiet_triples(D2: np.ndarray, width: float = 8.0) -> np.ndarray:
    """Which frame triples' second differences in time (D2: (K-2, P, 2), triple k centred on frame
    k + 1) are the noise's alone: a boolean (K-2,). A smooth response nearly cancels in them, but a
    turn of the load (the peak of a load-unload cycle, the start or end of a hold) puts a kink of the
    response into the triple centred on it: measured 0.73 mm RMS on the actuator's cycle, fifteen
    times a noise of 0.05 mm, where it alone made the noise look 3.6 times larger and spatially
    correlated over 6.5 mm (at 0.25 mm, the suite's two cycles: 1.08 and 1.15 times, over 4.0 and
    3.7 mm). Per triple the mean square; a triple more than ``width`` robust standard deviations
    (1.4826 x the median absolute deviation over triples) above the median is left out.
    A triple of noise alone goes beyond that with probability ~1e-7 even under correlated noise (its
    mean square averages tens of independent values at least; measured: no triple left out in 1000
    recordings of noise correlated over 3 mm, 20 frames, 10 x 10 points, where 5 deviations lost one
    in 3.5 % of them)."""
    ms = np.array([np.nanmean(t**2) if np.isfinite(t).any() else np.nan for t in D2])
    seen = np.isfinite(ms)
    if not seen.any():
        return seen
    med = float(np.median(ms[seen]))
    spread = 1.4826 * float(np.median(np.abs(ms[seen] - med)))
    return seen & (ms <= med + width * spread)


class Whitener:
    """Maps residuals (K, P, 2) to independent standard normal residuals under the noise model,
    honouring missing observations (NaN) frame by frame.

    Correlated noise is whitened in the eigenbasis of the points' correlation matrix, keeping the
    directions whose eigenvalue is at least ``keep`` times the largest: a squared-exponential kernel's
    small eigenvalues depend so strongly on the correlation length that whitening them with an
    estimated length (or a real camera's kernel, never exactly squared-exponential) inflates them by
    factors of ten; smooth model mismatch lives in the leading directions anyway. The whitened
    values of a frame-component fill its first r slots, NaN (unobserved) after them."""

    def __init__(self, rec: Recording, noise: NoiseModel, keep: float = 1e-2):
        self.noise, self.mask, self.keep = noise, rec.mask, keep
        self.C = None if noise.ell <= 0 else noise.correlation(rec.X)
        self._basis: dict[bytes, tuple[np.ndarray, float]] = {}

    def basis(self, m: np.ndarray) -> tuple[np.ndarray, float]:
        """(B, half log det) for the observed points m: B (m.sum(), r) maps correlated values to
        independent unit ones; half log det sums log sqrt(eigenvalue) over the kept directions."""
        key = m.tobytes()
        if key not in self._basis:
            w, V = linalg.eigh(self.C[np.ix_(m, m)])
            k = w >= self.keep * w.max()
            self._basis[key] = (V[:, k] / np.sqrt(w[k]), 0.5 * float(np.sum(np.log(w[k]))))
        return self._basis[key]

    def __call__(self, R: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """R: (K, P, 2, ...) -> whitened, NaN where not observed (``mask`` (K, P, 2): the recording's)."""
        mask = self.mask if mask is None else mask
        out = np.full(R.shape, np.nan)
        s = self.noise.sigma
        for k in range(R.shape[0]):
            for c in range(2):
                m = mask[k, :, c]
                if not m.any():
                    continue
                x = R[k, m, c] / s
                if self.C is None:
                    out[k, m, c] = x
                else:
                    B, _ = self.basis(m)
                    out[k, :B.shape[1], c] = np.tensordot(B.T, x, axes=1)
        return out

    def log_det(self, frames: np.ndarray) -> float:
        """log sqrt|noise covariance| of the whitened observations of ``frames`` (the same for every
        model of the recording)."""
        total = 0.0
        for k in frames:
            for c in range(2):
                m = self.mask[k, :, c]
                if not m.any():
                    continue
                if self.C is None:
                    total += m.sum() * math.log(self.noise.sigma)
                else:
                    B, half_logdet = self.basis(m)
                    total += B.shape[1] * math.log(self.noise.sigma) + half_logdet
        return total

    def calibrate(self, rec: Recording) -> None:
        """Rescale sigma so that the recording's second differences in time, whitened, have the
        variance 6 of independent unit noise (their noise is the residuals' noise, whatever the true
        spatial kernel), and set the degrees of freedom of that estimate. Used whenever sigma or the
        correlation length was estimated."""
        D2 = np.diff(rec.Z, n=2, axis=0)
        D2 = D2[quiet_triples(D2)]  # a turn of the load's kink is not noise
        W = self(D2, np.isfinite(D2))
        n = int(np.isfinite(W).sum())
        factor = math.sqrt(float(np.nanmean(W**2)) / 6.0)
        self.noise.sigma *= factor
        self.noise.estimated["whitened_scale"] = factor
        self.noise.dof = n / (70.0 / 36.0)


HISTORY_ITERATIONS = 4  # Gauss-Newton iterations of the creeping body on the FE history model (from the
# load-level approximation's MAP, which is close: 1.4 std at most on the suite's recordings)


# -- calibration by Gauss-Newton ------------------------------------------------------------------------

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


# -- locate -------------------------------------------------------------------------------------------

def _bh(p: np.ndarray, alpha: float) -> np.ndarray:
    """Benjamini-Hochberg: True where rejected at false discovery rate alpha."""
    p = np.asarray(p, dtype=float)
    order = np.argsort(p)
    ranked = p[order] * p.size / (np.arange(p.size) + 1)
    passed = np.flatnonzero(ranked <= alpha)
    out = np.zeros(p.size, dtype=bool)
    if passed.size:
        out[order[: passed[-1] + 1]] = True
    return out


def consistency(E: np.ndarray, frames: np.ndarray, d: int, noise_dof: float | None = None) -> dict:
    """Global test of whitened residuals E (K, P, 2) over ``frames`` (d fitted parameters): chi^2 with
    n - d degrees of freedom when sigma is known; when sigma was estimated with ``noise_dof``
    effective degrees of freedom, the residual variance over sigma-hat^2 is F(n - d, noise_dof)
    (the chi^2 band would be far too narrow: sigma-hat^2 is itself uncertain by sqrt(2 / noise_dof))."""
    e = E[frames]
    e = e[np.isfinite(e)]
    n = e.size
    ss = float(e @ e)
    dof = max(n - d, 1)
    if noise_dof is None:
        p = float(stats.chi2.sf(ss, dof))
        z = (ss - dof) / math.sqrt(2 * dof)
    else:
        m = _ratio_dof(E.shape[0], frames, n, dof, noise_dof)
        p = float(stats.chi2.sf(m * ss / dof, m))
        z = (ss / dof - 1) * math.sqrt(m / 2)
    return {"statistic": ss, "dof": dof, "noise_dof": noise_dof, "nis_per_observation": ss / n,
            "rms": float(np.sqrt(ss / n)), "p_value": p, "z": z}


def _ratio_dof(K: int, frames: np.ndarray, n: int, dof: int, noise_dof: float) -> float:
    """Degrees of freedom m of the scaled chi^2 that matches the variance of RSS / (dof sigma-hat^2)
    under the noise model, sigma-hat^2 estimated from the second differences of the same recording
    (``estimate_noise``). Delta method: var = 2/dof + 2/noise_dof - 2 cov, where the whitened residuals
    and the second differences share the noise: cov(RSS, sum D2^2) = 2 sum_{k in frames} w_k o
    (w_k: frame k's weight in the second differences, o observations per frame). Independent noise
    gives var ~ 1.9/dof (chi^2 is about right); spatially correlated noise far more (sigma-hat rests
    on fewer independent samples), which chi^2 alone would turn into false alarms."""
    D = np.zeros((K - 2, K))
    for i in range(K - 2):
        D[i, i:i + 3] = (1.0, -2.0, 1.0)
    w = (D**2).sum(axis=0)
    o = n / max(len(frames), 1)
    cov = 2.0 * float(w[frames].sum()) / (6.0 * len(frames) * (K - 2) * o)
    var = max(2.0 / dof + 2.0 / noise_dof - 2.0 * cov, 0.5 * 2.0 / dof)
    return 2.0 / var


def locate(E: np.ndarray, rec: Recording, frames: np.ndarray, d: int, alpha: float, raw: np.ndarray,
           sigma: float, noise_dof: float | None = None) -> dict:
    """Global test, onset in time and spatial clusters of the whitened residuals E (K, P, 2);
    ``raw`` residuals (mm) give the map in noise units."""
    glob = consistency(E, frames, d, noise_dof)
    # per frame
    Ek = E[frames]
    ss_k = np.nansum(Ek**2, axis=(1, 2))
    n_k = np.isfinite(Ek).sum(axis=(1, 2))
    p_k = np.where(n_k > 0, stats.chi2.sf(ss_k, np.maximum(n_k, 1)), 1.0)
    sig_k = _bh(p_k, alpha)
    onset = None
    for j in range(len(frames)):
        if sig_k[j] and sig_k[j:].mean() > 0.5:
            onset = j
            break
    # per point (marginal: standardized, not whitened, so that a point is a point)
    std = raw[frames] / sigma
    ss_p = np.nansum(std**2, axis=(0, 2))
    n_p = np.isfinite(std).sum(axis=(0, 2))
    p_p = np.where(n_p > 0, stats.chi2.sf(ss_p, np.maximum(n_p, 1)), 1.0)
    sig_p = _bh(p_p, alpha)
    rms_p = np.sqrt(ss_p / np.maximum(n_p, 1))
    clusters = _clusters(rec.X, sig_p, rms_p, rec.point_ids)
    return {
        "global": glob,
        "detected": bool(glob["p_value"] < alpha),
        "onset": None if onset is None else {"frame": int(rec.frames[frames[onset]]),
                                              "pressure": float(rec.pressure[frames[onset]]),
                                              "time": float(rec.times[frames[onset]])},
        "frames_significant": int(sig_k.sum()),
        "points_significant": int(sig_p.sum()),
        "clusters": clusters,
        "point_rms": rms_p,
        "frame_statistic": ss_k / np.maximum(n_k, 1),
    }


def _clusters(X: np.ndarray, sig: np.ndarray, rms: np.ndarray, ids: np.ndarray) -> list[dict]:
    idx = np.flatnonzero(sig)
    if idx.size == 0:
        return []
    d = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    link = 1.5 * float(np.median(d.min(axis=1)))
    label = -np.ones(len(X), dtype=int)
    out = []
    for seed in idx:
        if label[seed] >= 0:
            continue
        stack, members = [seed], []
        label[seed] = len(out)
        while stack:
            i = stack.pop()
            members.append(i)
            for j in idx[(d[i, idx] <= link) & (label[idx] < 0)]:
                label[j] = len(out)
                stack.append(j)
        members = np.array(members)
        out.append({"points": int(members.size), "centre_mm": X[members].mean(axis=0).round(3).tolist(),
                    "z_range_mm": [float(X[members, 2].min()), float(X[members, 2].max())],
                    "rms_noise_units": float(np.sqrt(np.mean(rms[members] ** 2))),
                    "worst_point": int(ids[members[np.argmax(rms[members])]])})
    return sorted(out, key=lambda c: -c["points"] * c["rms_noise_units"] ** 2)


# -- hysteresis: a model-free test of path independence ----------------------------------------------------

HISTORY_DEPENDENT = ("viscoelasticity", "a time lag of the pressure sensor", "Mullins-type damage on first loading",
                     "friction", "a drift of the camera or the specimen in time")
# the sense of the loop sorts the causes: a passive body that dissipates (creep, damage, friction)
# takes more work on loading than it returns, so at equal pressure it unloads through larger
# displacements (it lags its load); a loop the other way round would return more work than it took,
# which only a clock (a lagging pressure sensor, a camera out of step) or a drift can make. A cavity
# whose pressure lags its sensor (a pneumatic line) makes a loop of the first sense, like a creeping body
CAUSES = {"lags": ("viscoelasticity", "the cavity's pressure lagging its sensor (a pneumatic line between them)",
                   "Mullins-type damage on first loading", "friction", "a drift of the camera or the specimen in time"),
          "leads": ("a time lag of the pressure sensor, or the camera's clock out of step with it",
                    "a drift of the camera or the specimen in time")}


def _pressure_direction(phys: ActuatorPhysics, z: dict[str, float]) -> np.ndarray | None:
    """The model's dY/dlambda at every frame's load factor (K, P, 2), by linear interpolation between
    its load steps; None if its solve failed."""
    steps = phys.at_steps(z)
    if steps is None:
        return None
    s, _, dYs = steps
    zt = {k: torch.tensor([v], dtype=torch.float64) for k, v in z.items()}
    lam = np.clip(phys.frame_loads(zt).numpy(), 0.0, 1.0)
    i = np.clip(np.searchsorted(s, lam, side="right") - 1, 0, s.size - 2)
    t = ((lam - s[i]) / (s[i + 1] - s[i]))[:, None, None]
    return (1 - t) * dYs[i] + t * dYs[i + 1]


def hysteresis(rec: Recording, white: Whitener, alpha: float, direction: np.ndarray | None = None) -> dict:
    """Does the recording pass through the same state at the same pressure on loading and unloading?

    Every term of the model library is hyperelastic and quasi-static, so its observations are a
    function of the pressure alone: a recording that goes up and comes back down must show the same
    displacements at the same pressure. The loading branch (the frames up to the largest pressure,
    pressure rising) is interpolated at each unloading frame's pressure by a cubic spline (linear
    below 4 frames), which is linear in the data: ``d_k = Z_k - sum_j W_kj Z_j``. Under path
    independence ``d`` is noise only, with covariance ``(I + W W^T)`` in time times the spatial noise
    covariance (frames independent), so after spatial whitening and temporal decorrelation

    - omnibus: ``sum d^2`` is chi^2 with (unloading frames x observations per frame) dof;
    - directional: the projections of each ``d_k`` on ``direction[k]`` ((K, P, 2) for every frame;
      e.g. the calibrated model's
      ``dY/dpressure`` there: what a lagging or creeping pressure response moves) are jointly
      Gaussian with covariance ``(I + W W^T) o (cosines between the directions)``, chi^2 with one dof
      per unloading frame. Any fixed direction keeps the test valid; the model's makes it powerful.

    Each statistic takes half of ``alpha``. Points and components must be observed in every frame
    compared (others are left out). Returns a dict with ``applicable`` (False with a ``reason`` when
    the recording has no unloading frame within its loading range), ``detected``, both statistics,
    their dof and p-values, the frames compared, the loop per unloading frame (z-scores of the
    directional projections) and per point (RMS in noise units), and the largest loop in mm."""
    p = np.asarray(rec.pressure, dtype=np.float64)
    K = p.size
    top = int(np.argmax(p))
    start = top
    while start > 0 and p[start - 1] < p[start]:
        start -= 1
    load = np.arange(start, top + 1)
    after = np.arange(top + 1, K)
    if load.size < 2 or after.size == 0:
        return {"applicable": False, "detected": False,
                "reason": "the recording does not come back down from its largest pressure (no unloading frames)"
                if after.size == 0 else "fewer than 2 loading frames before the largest pressure"}
    p_l = p[load]
    unl = after[(p[after] >= p_l.min()) & (p[after] <= p_l.max())]
    if unl.size == 0:
        return {"applicable": False, "detected": False,
                "reason": "no unloading frame lies within the pressures of the loading branch"}
    if load.size >= 4:
        from scipy.interpolate import CubicSpline

        W = CubicSpline(p_l, np.eye(load.size))(p[unl])
    else:
        W = np.stack([np.interp(p[unl], p_l, e) for e in np.eye(load.size)], axis=1)
    frames = np.concatenate([load, unl])
    common = rec.mask[frames].all(axis=0)  # (P, 2)
    if not common.any():
        return {"applicable": False, "detected": False, "reason": "no point is observed in every frame compared"}
    Z = np.where(common[None], rec.Z, 0.0)
    D = Z[unl] - np.einsum("uj,jpc->upc", W, Z[load])  # (U, P, 2) mm
    mask = np.broadcast_to(common, D.shape)
    Dw = white(D, mask)
    A = np.eye(unl.size) + W @ W.T
    L = np.linalg.cholesky(A)
    flat = np.nan_to_num(Dw.reshape(unl.size, -1))
    n_obs = int(np.isfinite(Dw[0]).sum())
    X = linalg.solve_triangular(L, flat, lower=True)
    T1 = float(np.sum(X**2))
    dof1 = unl.size * n_obs
    out = {"applicable": True, "frames_loading": [int(rec.frames[k]) for k in load],
           "frames_unloading": [int(rec.frames[k]) for k in unl], "alpha": alpha,
           "omnibus": {"statistic": T1, "dof": dof1, "p_value": float(stats.chi2.sf(T1, dof1))}}
    z_frames = None
    if direction is not None:
        G = np.nan_to_num(white(np.where(mask, np.asarray(direction)[unl], 0.0), mask).reshape(unl.size, -1))
        norms = np.linalg.norm(G, axis=1)
        if np.all(norms > 0):
            Gh = G / norms[:, None]
            s_k = np.sum(Gh * flat, axis=1)
            C = A * (Gh @ Gh.T)
            T2 = float(s_k @ np.linalg.solve(C, s_k))
            out["directional"] = {"statistic": T2, "dof": int(unl.size), "p_value": float(stats.chi2.sf(T2, unl.size))}
            z_frames = s_k / np.sqrt(np.diag(C))
            # along dY/dpressure: > 0 when unloading passes through larger displacements than loading
            out["sense"] = "lags" if float(np.sum(s_k)) > 0 else "leads"
    tests = [out["omnibus"]] + ([out["directional"]] if "directional" in out else [])
    out["detected"] = bool(any(t["p_value"] < alpha / len(tests) for t in tests))
    scale = np.sqrt(np.diag(A))[:, None, None]
    loop = np.where(mask, D, np.nan) / white.noise.sigma / scale  # noise units per frame, per observation
    point_rms = np.sqrt(np.nanmean(loop**2, axis=(0, 2)))
    worst = np.argsort(-np.nan_to_num(point_rms))[:5]
    out["per_frame"] = [{"frame": int(rec.frames[k]), "pressure": float(p[k]),
                         "rms_noise_units": float(np.sqrt(np.nanmean(loop[i] ** 2))),
                         **({"directional_z": float(z_frames[i])} if z_frames is not None else {})}
                        for i, k in enumerate(unl)]
    out["worst_points"] = [{"point": int(rec.point_ids[j]), "X": rec.X[j].tolist(),
                            "rms_noise_units": float(point_rms[j])} for j in worst]
    out["largest_loop_mm"] = float(np.nanmax(np.abs(np.where(mask, D, np.nan))))
    if out["detected"]:
        sense = out.get("sense")
        out["physics"] = {"kind": "history-dependent",
                          "meaning": "the recording is not a function of the pressure alone: no hyperelastic, "
                                     "quasi-static term can explain it"
                                     + {"lags": "; the body lags its load, as a dissipating body does",
                                        "leads": "; the body leads the recorded pressure, which no passive body "
                                                 "does: a clock or a drift",
                                        None: ""}[sense],
                          "possible_causes": list(CAUSES.get(sense, HISTORY_DEPENDENT))}
    return out


def history_identifiable(rec: Recording, hold_fraction: float = 0.1) -> bool:
    """Whether a recording can show history-dependent physics apart from a load-axis warp: it comes
    back down from a pressure (a drop of more than 1 % of the largest), or holds a pressure above
    ``hold_fraction`` of the largest over two frames or more (a change below 0.1 % of it)."""
    p = np.asarray(rec.pressure, dtype=np.float64)
    top = float(np.max(np.abs(p))) if p.size else 0.0
    if top <= 0 or p.size < 3:
        return False
    drops = np.maximum.accumulate(p) - p > 0.01 * top
    hold = (np.abs(np.diff(p)) < 1e-3 * top) & (p[1:] > hold_fraction * top)
    return bool(drops.any() or hold.any())


# -- rank -----------------------------------------------------------------------------------------------

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


# -- the whole diagnosis ----------------------------------------------------------------------------------

def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(type(o))


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


def score_candidates(rec: Recording, white: Whitener, cands, c10: float, fit_frames: np.ndarray, alpha: float,
                     resolution: int = 1, load_steps: int = 10, cache=None, deck: DeckModel | None = None, bar=None):
    """Step 2 of the diagnosis: the model with every candidate of ``cands`` at its null, C10 =
    ``c10``, observed with its exact sensitivities, plus one solve per parameter of
    :data:`physics.FAR_SECANTS` for its secant; :func:`rank` on the recording's residual at ``alpha``.
    Returns (physics, ranking, whitened sensitivities, their column names, FE solves)."""
    bar = bar or _Progress(False)
    full = ActuatorPhysics(rec, cands, resolution, load_steps, cache, deck=deck)
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


def diagnose(rec: Recording, noise: float | None = None, correlation: float | None = None, candidates="all",
             run_dir=None, resolution: int = 1, load_steps: int = 10, alpha: float = 0.01,
             evidence_threshold: float = 5.0, held_out_every: int = 5, progress: bool = True,
             max_refits: int | None = None, deck: DeckModel | None = None, fe_history: bool = True,
             mesh_error: bool = True) -> dict:
    """Diagnose ``rec`` (see the module docstring); returns the diagnosis (also written to
    ``run_dir/diagnosis.json`` with figures when ``run_dir`` is given). ``deck``: the user's own
    model (an Abaqus/CalculiX deck) instead of the paper's actuator at ``resolution``; ``fe_history``:
    a creeping body's refit ends on the FE model with history variables (else its load-level
    approximation alone); ``mesh_error``: take the diagnosis mesh's own discretization error, estimated by one
    refinement (:func:`discretization_error`), out of an extension's residual before the surrogate test (a
    recording of a real body, or of a finer model); False only for a recording made by the diagnosis model
    itself on its own mesh (a test's inverse crime), where there is no such error to take out."""
    t_start = time.perf_counter()
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
    _check_recording(rec, held_out_every)
    run_dir = None if run_dir is None else Path(run_dir)
    cache = None if run_dir is None else run_dir / "solves"
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
    white = Whitener(rec, nm)
    if nm.estimated["sigma"] or (nm.estimated["ell"] and nm.ell > 0):
        white.calibrate(rec)
    K = rec.n_frames
    held = np.arange(held_out_every - 1, K, held_out_every) if held_out_every > 1 else np.zeros(0, int)
    fit_frames = np.setdiff1d(np.arange(K), held)
    bar = _Progress(progress)

    # 1. calibrate the base model
    base_phys = ActuatorPhysics(rec, (), resolution, load_steps, cache, deck=deck)
    c10_0, start_solves = _initial_c10(base_phys, white, fit_frames, bar)
    bar.phase("calibrating the base model (C10)", bar.FIT_SOLVES + 2)
    base = gauss_newton(base_phys, white, ["C10"], {"C10": math.log(c10_0)}, fit_frames, progress=bar.tick)
    floor = model_floor(nm.sigma, resolution, deck, mesh_error)
    taken_out, base_solves = None, base.solves
    if floor["below"]:
        # below the floor the mesh's own discretization error alone sets off the tests (a null flagged
        # on 50-88 % of recordings at 0.05 mm): it is estimated by one refinement at the base fit, taken
        # out of the recording, and the base refitted; every test then sees the physics alone (measured:
        # 0.5-1.2 % flagged at every noise scanned down to 0.025 mm, the level's own 1 %;
        # scripts/study_noise_floor.py)
        bar.phase(f"the noise {nm.sigma:.3g} mm is below the resolution-{resolution} model's floor: estimating "
                  f"its own error (one solve at resolution {resolution + 1})", 2)
        taken_out, floor["taken_out"] = discretization_error(rec, (), base.z, resolution, load_steps, cache, deck)
        bar.tick(2)
        if taken_out is not None:
            rec = replace(rec, Z=rec.Z - taken_out)
            base_phys = ActuatorPhysics(rec, (), resolution, load_steps, cache, deck=deck)
            bar.phase("recalibrating the base model (C10) on the recording less the mesh's error", bar.FIT_SOLVES + 2)
            base = gauss_newton(base_phys, white, ["C10"], base.z, fit_frames, progress=bar.tick)
            base_solves += base.solves
    c10 = math.exp(base.z["C10"])
    raw = rec.Z - base.evaluation.Y
    # the omnibus test takes half the level, the candidates' score tests the other half (Bonferroni):
    # a specific alternative is found by its score test long before it shows in the chi^2 total. A
    # recording that comes back down is also tested for path independence (hysteresis, model-free):
    # it then shares the omnibus half with the chi^2 total
    loop = hysteresis(rec, white, alpha / 4, _pressure_direction(base_phys, base.z))
    where = locate(base.residual, rec, fit_frames, 1, alpha / 4 if loop["applicable"] else alpha / 2, raw, nm.sigma,
                   nm.dof)
    where["detected_by_hysteresis"] = loop["detected"]
    where["detected"] = where["detected"] or loop["detected"]

    # 2. rank: sensitivities of every candidate at the calibrated point, candidates at their null
    not_testable = {}
    if set(cands) & set(HISTORY_DEPENDENT_CANDIDATES) and not history_identifiable(rec):
        # on a load that only rises, each load level is met once: creep only warps the load axis,
        # which the material's own nonlinearity can do as well (a surrogate); unloading or a hold
        # at constant pressure is what shows a history
        for c in set(cands) & set(HISTORY_DEPENDENT_CANDIDATES):
            not_testable[c] = ("the pressure only rises, without a hold: creep is a warp of the load axis there, "
                               "confounded with the material's nonlinearity; record unloading or a hold to test it")
        cands = tuple(c for c in cands if c not in not_testable)
    full, ranking, Jw, names_w, ranking_solves = score_candidates(rec, white, cands, c10, fit_frames, alpha / 2,
                                                                  resolution, load_steps, cache, deck, bar)
    where["detected_by_score"] = any(r["significant"] for r in ranking)
    where["detected"] = where["detected"] or where["detected_by_score"]

    # 3./4. refit and decide
    base_report = _fit_report(base, white, fit_frames, held, 1)
    tried, decision, accepted = [], "none", None
    rival_solves, history_verdict = 0, None
    if where["detected"]:
        decision = "unexplained"
        order = [r for r in ranking if r["significant"] and r["dof"] > 0]
        singles = [(r["name"],) for r in order[:max_refits]]  # None: every significant candidate
        pair = [(order[0]["name"], order[1]["name"])] if len(order) >= 2 else []
        fits = {}

        def refit(combo, left):
            bar.phase(f"refitting with {' + '.join(combo)}", left * (bar.FIT_SOLVES + 2))
            phys = ActuatorPhysics(rec, combo, resolution, load_steps, cache, deck=deck)
            rows = [next(r for r in ranking if r["name"] == c) for c in combo]
            free = ["C10"] + [p for r in rows for p in r["tested_parameters"] + r["nuisance_parameters"]]
            added = [p for p in free if p != "C10"]
            if set(added) <= set(LOAD_MAP_ONLY):
                z0, scan_solves, scan = load_map_start(phys, white, free, added, phys.null_point(c10), fit_frames)
            else:
                z0, scan_solves, scan = scan_start(phys, white, free, added, phys.null_point(c10), fit_frames,
                                                   progress=bar.tick)
            ext = gauss_newton(phys, white, free, z0, fit_frames, progress=bar.tick)
            ext.solves = (ext.solves + scan_solves) * getattr(phys, "solves_per_observation", 1)  # secants solve twice more
            load_map = None
            if combo == ("viscoelasticity",) and fe_history:
                # the load-level creep is the correspondence principle's approximation; the refit ends on
                # the FE model with history variables it stands in for (it misses 5-8 % of the effect on
                # the actuator, enough to leave a loop in the residual at SNR ~60), started at its MAP
                load_map = _fit_report(ext, white, fit_frames, held, len(free))
                bar.phase("refitting the creeping body with history variables in the element kernel (4 FE "
                          "marches a step)", HISTORY_ITERATIONS + 2)
                phys = HistoryPhysics(rec, resolution, cache, deck)
                fe = gauss_newton(phys, white, free, ext.z, fit_frames, max_iterations=HISTORY_ITERATIONS,
                                  progress=bar.tick)
                fe.solves = ext.solves + getattr(phys, "marches", 0)
                ext = fe
            rep = _fit_report(ext, white, fit_frames, held, len(free))
            if load_map is not None:
                rep["load_map_fit"] = load_map
                rep["model"] = "fem.viscoelastic: one Prony term, history variables at every Gauss point"
            checks = _acceptance(ext, rep, base_report, combo, evidence_threshold, alpha, c10, free, phys)
            # a surrogate explains part of the mismatch: another candidate still significant on the
            # extended model's residual (score tests linearized at the base point) says so
            others = [r for r in ranking if r["name"] not in combo and r["dof"] > 0
                      and not set(r["group"]) & set(combo)]
            ev_ext = ext.evaluation
            J_fit = white(ev_ext.J[..., [ev_ext.names.index(n) for n in free]])
            if len(combo) > 1:
                checks["beats_its_members"] = beats_its_members(rep, combo, tried, evidence_threshold)
            E_rem, mesh = ext.residual, None
            if mesh_error and all(checks.values()):
                # the last check of an extension that passed every other: its residual is at the noise,
                # and what is left in it beyond the noise is the diagnosis mesh's own discretization
                # error unless another physics is missing. The error is estimated by one refinement at
                # the MAP and taken out before the surrogate test (README "The mesh's own error")
                bar.phase(f"estimating the mesh's own error at the refit of {' + '.join(combo)} "
                          f"(one solve at resolution {resolution + 1})", 2)
                delta, mesh = discretization_error(rec, combo, ext.z, resolution, load_steps, cache, deck)
                bar.tick(2)
                if delta is not None:
                    # the base fit's estimate is out of the recording already (noise below the floor)
                    E_rem = ext.residual - white(delta if taken_out is None else delta - taken_out)
            remaining = _remaining_scores(E_rem, Jw, names_w, free, others, fit_frames, J_fit)
            level = ranking[0]["level"] if ranking else alpha / 2
            checks["no_other_candidate_significant"] = all(v["p_value"] >= level for v in remaining.values())
            rep["scan"] = scan
            entry = {"candidates": list(combo), "fit": rep, "checks": checks, "accepted": all(checks.values()),
                     "remaining_scores": remaining}
            if mesh is not None:
                mesh["remaining_scores_uncorrected"] = (
                    _remaining_scores(ext.residual, Jw, names_w, free, others, fit_frames, J_fit)
                    if E_rem is not ext.residual else remaining)
                entry["mesh_error"] = mesh
            tried.append(entry)
            fits[combo] = (ext, rep)

        # every significant single candidate is refitted, not only the first that passes: the score
        # ranks by the linearization at the null, and two terms that switch on far from it (a bulk
        # compliance, a fiber compliance) can both explain a recording once refitted (measured: a
        # fiber compliance at SNR 13 after the base fit was first explained by D1 alone). The pair
        # is tried only when no single candidate passes.
        for i, combo in enumerate(singles):
            refit(combo, len(singles) - i + len(pair))
        if not any(t["accepted"] for t in tried):
            for combo in pair:
                refit(combo, 1)
        decision, best = decide(tried, ranking, evidence_threshold)
        rival = [RIVALS[c] for c in (best["candidates"] if best is not None else ()) if c in RIVALS]
        if rival:
            # a creeping body and a cavity pressure lagging its sensor make the same loop once the lag
            # is shorter than the frame spacing: the body's physics is named only if it beats the lag
            # decisively
            bar.phase(f"fitting the rival of {' + '.join(best['candidates'])}: {rival[0]}", bar.FIT_SOLVES + 2)
            phys = ActuatorPhysics(rec, (rival[0],), resolution, load_steps, cache, deck=deck)
            free = ["C10"] + list(CANDIDATE_PARAMETERS[rival[0]])
            z0, _, _ = load_map_start(phys, white, free, free[1:], phys.null_point(c10), fit_frames)
            rfit = gauss_newton(phys, white, free, z0, fit_frames, progress=bar.tick)
            rrep = _fit_report(rfit, white, fit_frames, held, len(free))
            rival_solves += rfit.solves
            margin = best["fit"]["log_evidence"] - rrep["log_evidence"]
            best["rival"] = {"name": rival[0], "fit": rrep, "evidence_margin": margin}
            if margin <= evidence_threshold:
                best["chosen"] = False
                best["partial"] = True
                history_verdict = {
                    "kind": "history-dependent",
                    "meaning": ("a creeping body (viscoelasticity) or a cavity pressure lagging its sensor: the "
                                f"recording cannot tell them apart (log evidence {margin:+.1f} for the creep); a hold "
                                "at constant pressure would (a body creeps on, a lagging pressure settles)")
                    if margin > -evidence_threshold else
                    ("the cavity's pressure lags the recorded one (by "
                     f"{rfit.z['pressure_lag']:.3g} of the recording's duration), which explains the recording "
                     f"better than a creeping body (log evidence {-margin:+.1f})"),
                    "possible_causes": ["viscoelasticity", "a time lag between the pressure sensor and the cavity"]
                    if margin > -evidence_threshold else ["a time lag between the pressure sensor and the cavity"]}
                decision, best = "unexplained", None
        if best is not None and loop["detected"]:
            # a loop is explained only by history-dependent physics, and only if none is left in the
            # extended model's residual (the same path-independence test on recording - model)
            history = set(best["candidates"]) & set(HISTORY_DEPENDENT_CANDIDATES)
            ext = fits[tuple(best["candidates"])][0]
            left = (hysteresis(replace(rec, Z=rec.Z - ext.evaluation.Y), white, alpha / 4,
                               _pressure_direction(base_phys, base.z)) if history else None)
            best["loop_left_in_residual"] = left
            if not history or left["detected"]:
                # what the candidate explained is part of the story only
                best["chosen"] = False
                best["partial"] = True
                decision, best = "unexplained", None
        if best is not None:
            combo = tuple(best["candidates"])
            accepted = (combo, *fits[combo])
    bar.close()
    fit_after = accepted[2] if accepted else base_report
    mesh_solves = sum(t["mesh_error"]["solves"] for t in tried if "mesh_error" in t)
    mesh_solves += floor["taken_out"]["solves"] if "taken_out" in floor else 0
    fe_solves = (start_solves + base_solves + ranking_solves + sum(t["fit"]["solves"] for t in tried) + rival_solves
                 + mesh_solves)
    out = {
        "recording": rec.source,
        "frames": int(K), "points": int(rec.n_points), "observations": int(np.isfinite(rec.Z).sum()),
        "noise": {"sigma": nm.sigma, "correlation_length_mm": nm.ell, "estimated": nm.estimated,
                  "model_floor": floor},
        "mismatch_detected": {"detected": where["detected"], "alpha": alpha, "global": where["global"],
                              "by_score_test": where["detected_by_score"],
                              "by_hysteresis": where["detected_by_hysteresis"],
                              "frames_significant": where["frames_significant"],
                              "points_significant": where["points_significant"]},
        "location": {"clusters": where["clusters"]},
        "onset": where["onset"],
        "hysteresis": loop,
        "ranking": ranking,
        "not_testable": not_testable,
        "not_available": not_available,
        "model": ({"kind": "actuator", "resolution": resolution} if deck is None else
                  {"kind": "deck", "path": str(deck.path), "camera": deck.camera, "face": deck.face,
                   "digest": base_phys.deck_digest}),
        "tried": tried,
        "decision": decision,
        "missing_physics": ({"kind": "candidate", "name": decision} if decision not in ("none", "unexplained") else
                            history_verdict or (loop["physics"] if loop["detected"] else {"kind": decision})),
        "parameters": {"base": base_report["parameters"], "extended": accepted[2]["parameters"] if accepted else None},
        "fit_before": base_report,
        "fit_after": fit_after,
        "cost": {"solves": fe_solves, "seconds": time.perf_counter() - t_start,
                 "resolution": resolution if deck is None else None,
                 "load_steps": load_steps, "ranking_solves": ranking_solves, "mesh_error_solves": mesh_solves},
        "held_out_frames": [int(rec.frames[k]) for k in held],
    }
    if run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "diagnosis.json").write_text(json.dumps(out, indent=1, default=_json_default))
        np.savez(run_dir / "residuals.npz", before=raw, after=(rec.Z - accepted[1].evaluation.Y) if accepted else raw,
                 point_rms_before=where["point_rms"], X=rec.X, point_ids=rec.point_ids,
                 mesh_error_taken_out=np.zeros_like(raw) if taken_out is None else taken_out)
        try:
            from torchfra.report.diagnosis import write_figures

            write_figures(run_dir, rec, out, base, accepted[1] if accepted else None, nm.sigma, where)
        except ImportError:  # figures need matplotlib
            pass
    return out


def decide(tried: list[dict], ranking: list[dict], evidence_threshold: float) -> tuple[str, dict | None]:
    """The decision from the refits ``tried`` (each with ``candidates``, ``accepted`` and
    ``fit["log_evidence"]``): "unexplained" when none was accepted; else the accepted one with the
    largest evidence (a candidate confounded with another at the null, e.g. the pressure sensor's
    group, by its group's names, less the members refitted themselves without passing within the
    margin: the data told those apart), joined by "|" with every other accepted one within ``evidence_threshold`` of it:
    the data cannot tell those apart, so none of them is the winner alone. Marks the chosen entry
    ``chosen`` and the others named ``rival``; returns (decision, chosen entry or None)."""
    passed = [t for t in tried if t["accepted"]]
    if not passed:
        return "unexplained", None
    best = max(passed, key=lambda t: t["fit"]["log_evidence"])
    best["chosen"] = True
    combo = best["candidates"]
    row = next(r for r in ranking if r["name"] == combo[0])
    # the group is confounding at the null (linearized); a member refitted itself and not within the
    # margin was told apart by the data (a compressible bulk beside a compliant fiber, whose secant
    # spans the bulk's direction at the null), so only members never refitted (or a base parameter,
    # C10 for a pressure gain) are named with the winner
    refitted = {c for t in tried for c in t["candidates"]}
    names = (["+".join(combo)] if len(row["group"]) == 1 or len(combo) > 1 else
             [g for g in row["group"] if g == combo[0] or g not in refitted])
    for t in passed:
        if t is not best and best["fit"]["log_evidence"] - t["fit"]["log_evidence"] < evidence_threshold:
            t["rival"] = True
            names.append("+".join(t["candidates"]))
    return "|".join(names), best


def beats_its_members(rep: dict, combo, tried: list[dict], evidence_threshold: float) -> bool:
    """Whether the refit of the combination ``combo`` (report ``rep``) beats every refit in ``tried``
    of a part of it (a member alone) by more than ``evidence_threshold`` in log evidence. A part is
    the combination with the other terms at their nulls (nested models): a combination no better
    than its part names a term the data do not support, however far from its null that term's
    Laplace posterior sits (a stiff fiber's effect saturates, so its log E_fiber is free over
    decades: measured, E_fiber 388 +- 191 MPa beside a compressible bulk, 1.3 below the bulk alone)."""
    parts = [t["fit"]["log_evidence"] for t in tried if set(t["candidates"]) < set(combo)]
    return all(rep["log_evidence"] - ev > evidence_threshold for ev in parts)


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
                    "missing physics (scripts/study_noise_floor.py): the error is estimated by one refinement at the "
                    "base fit and taken out of the recording before the tests (then 0.5-1.2 % down to 0.025 mm); if it "
                    f"cannot be, diagnose on a finer mesh (--mesh {resolution + 1}) or take the decision as provisional")}


def discretization_error(rec: Recording, combo, z: dict[str, float], resolution: int, load_steps: int,
                         cache=None, deck: DeckModel | None = None) -> tuple[np.ndarray | None, dict]:
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
    coarse = ActuatorPhysics(rec, combo, resolution, load_steps, cache)
    fine = ActuatorPhysics(rec, combo, resolution + 1, load_steps, cache)
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


class _Progress:
    """A labelled bar counting FE solves (each ~10-20 s at resolution 1) with elapsed time and an
    estimate of the time left: the plan (solves still expected) is set as each phase starts, from the
    typical counts (a Gauss-Newton fit takes about ``FIT_SOLVES`` solves); tqdm's rate turns it into
    time."""

    FIT_SOLVES = 4

    def __init__(self, enabled: bool):
        self.enabled, self.bar = enabled, None

    def phase(self, label: str, expected: int | None = None):
        """Start a phase; ``expected``: solves still expected in the whole diagnosis from here on."""
        if not self.enabled:
            return
        from tqdm.auto import tqdm

        if self.bar is None:
            self.bar = tqdm(desc=label, unit="solve", total=expected,
                            bar_format="{desc}{n}/~{total} FE solves [{elapsed} elapsed, ~{remaining} left]")
        self.bar.set_description(label)
        if expected is not None:
            self.bar.total = self.bar.n + expected
            self.bar.refresh()

    def tick(self, n=1):
        if self.bar is not None:
            self.bar.update(1)
            if self.bar.total is not None and self.bar.n >= self.bar.total:
                self.bar.total = self.bar.n + 1  # a fit that takes longer than typical

    def close(self):
        if self.bar is not None:
            self.bar.close()
