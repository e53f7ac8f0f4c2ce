"""The noise of a recording estimated from its own frames: sigma and the spatial correlation length from
frame-to-frame second differences (a frame triple carrying a turn of the load left out, :func:`quiet_triples`).
The diagnosis (torchfra.diagnosis.noise) and the calibration (``torchfra calibrate`` without ``--noise``)
estimate it the same way."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from torchfra.observation.recording import Recording


class NoiseEstimateError(ValueError):
    """A recording whose noise cannot be estimated from its frames (too few, or no motion at all)."""


def check_motion(rec: Recording) -> None:
    """Refuse a recording whose displacements never change: every observed point has the same (uy, uz)
    in every frame, so there is neither a response to calibrate or diagnose nor noise to estimate.

    Raises
    ------
    NoiseEstimateError
        Naming the recording and what to check.
    """
    Z = rec.Z
    seen = np.isfinite(Z)
    if rec.n_frames < 2 or not seen.any():
        return
    spread = np.nanmax(Z, axis=0) - np.nanmin(Z, axis=0)  # (P, 2), NaN where a point is never seen
    if np.nanmax(spread) == 0.0:
        values = np.unique(Z[seen])
        shown = ", ".join(f"{v:g}" for v in values[:3]) + (", ..." if values.size > 3 else "")
        raise NoiseEstimateError(
            f"{rec.source}: the recording shows no motion: every point's uy and uz are the same in all "
            f"{rec.n_frames} frames (values {shown} mm). Check that the uy, uz columns hold displacements "
            "from the reference frame (not coordinates or a constant), that the frames were taken while the "
            "pressure changed, and, for a DIC export, that the displacement columns were exported")


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


def estimate_noise(rec: Recording, give: str = "give --noise SIGMA (mm)") -> NoiseModel:
    """sigma and ell from frame-to-frame differences of the recording: a smooth response (and any
    smooth model mismatch) nearly cancels between neighbouring frames, noise independent in time
    does not (var = 2 sigma^2). The correlation length is fitted to the empirical correlation of
    neighbouring points' differences (squared-exponential kernel); below 0.1 correlation at the
    nearest spacing the noise is taken as independent. ``give``: how the command that asks would be
    told the noise instead (said when it cannot be estimated).

    Raises
    ------
    NoiseEstimateError
        Fewer than 3 frames, no point seen in three consecutive frames, or a recording that shows no motion.
    """
    Z = rec.Z
    check_motion(rec)
    if rec.n_frames < 3:
        raise NoiseEstimateError(f"{rec.source}: {rec.n_frames} frames; estimating the noise needs at least 3 "
                                 f"(or {give})")
    D2 = np.diff(Z, n=2, axis=0)  # second differences remove a linear-in-time response too
    quiet = quiet_triples(D2)
    if not quiet.any():
        raise NoiseEstimateError(f"{rec.source}: no point is observed in three consecutive frames, so the noise "
                                 f"cannot be estimated from differences in time; {give}")
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
