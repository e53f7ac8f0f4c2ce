"""The noise model of a recording and its whitening.

Gaussian noise on (uy, uz): i.i.d. or spatially correlated with a squared-exponential kernel; sigma and the
correlation length are estimated from frame-to-frame second differences when not given (a frame triple
carrying a turn of the load is left out, :func:`quiet_triples`). :class:`Whitener` makes residuals and
sensitivities standard under the noise model."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from torchfra.observation.recording import Recording


class DiagnosisError(ValueError):
    """A recording that cannot be diagnosed as it is (too few frames or points, no noise level)."""


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

