"""The exact reference posterior of a calibration (quadrature on a grid in the filters' coordinates, or
importance sampling for 4-6 parameters) and ensemble statistics in the parameters' own units."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


def _stats(c10) -> dict[str, float]:
    from torchfra.assimilation import summarize

    return summarize(np.asarray(c10).reshape(-1))


def ensemble_stats(pset, Q: torch.Tensor) -> dict[str, dict[str, float]]:
    """Per parameter: mean, std, p10, p90 of an ensemble of coordinates Q (N, d)."""
    if pset.d == 1 and pset.priors[0].kind == "lognormal":
        return {pset.names[0]: _stats(torch.exp(Q[:, 0]))}  # the paper's path, to the last digit
    return {n: _stats(v) for n, v in pset.natural(Q).items()}


def natural_of(prior):
    """q -> parameter value on numpy arrays (exp for a lognormal prior)."""
    if prior.kind == "lognormal":
        return np.exp
    return lambda q: prior.natural(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


@dataclass
class ExactPosterior:
    """The exact posterior of a parameter set: ``raw`` the grid (1-D :class:`GridPosterior` or
    :class:`TensorPosterior`), per-parameter ``stats()`` in natural units."""

    raw: object
    names: list
    naturals: list

    @property
    def d(self) -> int:
        return len(self.names)

    def stats(self, step: int = -1) -> dict:
        if self.d == 1:
            return {self.names[0]: self.raw.stats(step, natural=self.naturals[0])}
        if step != -1:
            raise ValueError("the tensor-grid posterior is kept after the last frame only")
        return self.raw.stats()

    @property
    def log_evidence(self) -> float:
        return float(self.raw.log_evidence[-1]) if self.d == 1 else float(self.raw.log_evidence)

    def edge_mass(self) -> float:
        return self.raw.edge_mass() if self.d == 1 else float(self.raw.edge_mass)

    @property
    def prior_mass_outside(self) -> float:
        return float(self.raw.prior_mass_outside)

    def density(self, j: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(x, marginal pdf of parameter j)."""
        if self.d == 1:
            return self.raw.density(natural=self.naturals[0])
        q, dens = self.raw.marginal(j)
        x = np.asarray(self.naturals[j](q))
        jac = x if self.naturals[j] is np.exp else np.abs(np.gradient(x, q))  # dx/dq
        return x, dens / jac


class ExactReference:
    """The exact posterior's map through the forward members: for one parameter the cubic spline
    through them (a sweep, :class:`SweepMap`), for two or three the tensor-product Legendre map
    (:class:`~torchfra.assimilation.exact_nd.TensorMap`); each with its leave-one-out error."""

    def __init__(self, pset, Q0: torch.Tensor, Y: np.ndarray, grid: int = 4000):
        from torchfra.assimilation import SweepMap
        from torchfra.assimilation.exact_nd import TensorMap

        if pset.d > 6:
            raise ValueError(f"{pset.d} uncertain parameters: calibrate at most 6 at once")
        self.pset, self.d, self.grid = pset, pset.d, grid
        self.names = pset.names
        self.naturals = [natural_of(p) for p in pset.priors]
        m, sd = pset.gaussian()
        self.prior_mean, self.prior_std = m.numpy(), sd.numpy()
        if self.d == 1:
            self.map = SweepMap(Q0[:, 0].numpy(), Y)
            self.loo_error_rms = None
            self.kind = f"cubic spline through the {len(Q0)} forward members (a parameter sweep)"
        else:
            self.map = TensorMap(Q0.numpy(), Y)
            self.loo_error_rms = self.map.loo_error_rms
            basis = "per parameter" if self.map.basis == "tensor" else "in total"
            self.kind = (f"Legendre polynomial map of degree {self.map.degree} {basis}, least squares through the "
                         f"{len(Q0)} forward members; posterior "
                         + ("on a tensor grid along its principal axes" if self.d <= 3 else
                            "by importance sampling (t proposal at the Laplace point)"))

    @property
    def loo_error(self) -> float:
        """Largest leave-one-out error of the map through the members (units of Y)."""
        if self.d == 1:
            if not hasattr(self, "_loo"):
                self._loo = self.map.leave_one_out_error()
            return self._loo
        return self.map.loo_error

    def predict(self, Q) -> np.ndarray:
        """(N, d) coordinates -> (N, K, m) observations."""
        Q = np.asarray(Q, dtype=np.float64)
        return self.map(Q[:, 0]) if self.d == 1 else self.map(Q)

    def forecaster(self, frames):
        return self.map.forecaster(frames)

    def posterior(self, Z, r, frames=None) -> ExactPosterior:
        from torchfra.assimilation import grid_posterior
        from torchfra.assimilation.exact_nd import sampled_posterior, tensor_posterior

        if self.d > 3:
            raw = sampled_posterior(self.map, Z, r, self.prior_mean, self.prior_std, self.names, self.naturals,
                                    frames=frames)
        elif self.d == 1:
            raw = grid_posterior(self.map, Z, r, float(self.prior_mean[0]), float(self.prior_std[0]), self.grid,
                                 frames=frames)
        else:
            raw = tensor_posterior(self.map, Z, r, self.prior_mean, self.prior_std, self.names, self.naturals,
                                   frames=frames)
        return ExactPosterior(raw, list(self.names), self.naturals)

    def data_fit(self, post: ExactPosterior, Z, r) -> dict:
        from torchfra.assimilation import data_fit
        from torchfra.assimilation.exact_nd import data_fit_nd

        if self.d == 1:
            f = self.naturals[0]
            return data_fit(post.raw, self.map, Z, r, natural=math.exp if f is np.exp else lambda q: float(f(q)))
        return data_fit_nd(post.raw, self.map, Z, r)

