"""The noise model of a recording and its whitening.

Gaussian noise on (uy, uz): i.i.d. or spatially correlated with a squared-exponential kernel; sigma and the
correlation length are estimated from frame-to-frame second differences when not given
(:mod:`torchfra.observation.noise`, shared with the calibration). :class:`Whitener` makes residuals and
sensitivities standard under the noise model."""
from __future__ import annotations

import math

import numpy as np
from scipy import linalg

from torchfra.observation.noise import NoiseEstimateError, NoiseModel, quiet_triples
from torchfra.observation.noise import estimate_noise as estimate_from_frames
from torchfra.observation.recording import Recording

__all__ = ["DiagnosisError", "NoiseModel", "Whitener", "estimate_noise", "quiet_triples"]


class DiagnosisError(ValueError):
    """A recording that cannot be diagnosed as it is (too few frames or points, no noise level)."""


def estimate_noise(rec: Recording) -> NoiseModel:
    """The recording's noise from its frames (:func:`torchfra.observation.noise.estimate_noise`).

    Raises
    ------
    DiagnosisError
        When it cannot be estimated, saying how to give it instead.
    """
    try:
        return estimate_from_frames(rec, give="give --noise SIGMA (mm) and --correlation ELL (mm, 0 for "
                                              "independent noise)")
    except NoiseEstimateError as exc:
        raise DiagnosisError(str(exc)) from None


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

