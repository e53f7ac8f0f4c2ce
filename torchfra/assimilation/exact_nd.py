"""The exact posterior of several parameters (d = 2, 3) by quadrature on a tensor grid.

The FE map q -> observations is interpolated through the forward members (prior draws, scattered
in q) by least squares in a tensor-product Legendre basis of the member box (degree p in every
coordinate, p chosen by the closed-form leave-one-out error, reported against the noise). The map
is linear in its coefficients, Y_k(q) = phi(q) W_k, so with Gaussian noise the log likelihood of
all frames is a quadratic form in phi(q),

    sum_k log N(z_k; phi W_k, R_k) = -1/2 (c - 2 phi . b + phi^T A phi),
    A = sum_k W_k R_k^-1 W_k^T,  b = sum_k W_k R_k^-1 z_k,  c = sum_k z_k^T R_k^-1 z_k + log det(2 pi R_k),

accumulated once over the observations (memory and time linear in the recording, none per grid
point). The posterior is evaluated on a coarse grid over the member box (which also measures the
mass at its edges), then on a fine grid around the mass; moments, marginal quantiles, correlations
and the log evidence come from the fine grid. The prior is independent normal in each coordinate
(:class:`torchfra.priors.ParameterSet`).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre
from scipy.special import logsumexp, ndtr


def _legendre(t: np.ndarray, degree: int) -> np.ndarray:
    """(G,) in [-1, 1] -> (G, degree + 1) Legendre polynomials P_0..P_degree."""
    return np.stack([legendre.legval(t, np.eye(degree + 1)[i]) for i in range(degree + 1)], axis=1)


class TensorMap:
    """Observations as a smooth function of d coordinates, fitted to scattered members Q (N, d),
    Y (N, K, m) (NaN-free). ``degree``: per coordinate, or "auto" (smallest leave-one-out RMS among
    degrees whose (degree + 1)^d coefficients stay within half the members)."""

    def __init__(self, Q, Y, degree: int | str = "auto", max_degree: int = 10):
        Q = np.asarray(Q, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if Q.ndim != 2 or Y.shape[0] != Q.shape[0]:
            raise ValueError(f"members ({Q.shape}) and outputs ({Y.shape}) do not match")
        if not np.isfinite(Y).all():
            bad = np.flatnonzero(~np.isfinite(Y.reshape(len(Y), -1)).all(1))
            raise ValueError(f"outputs of members {bad.tolist()} are not finite (diverged solves); drop them")
        self.N, self.d = Q.shape
        self.shape = Y.shape[1:]
        self.lo, self.hi = Q.min(0), Q.max(0)
        if not np.all(self.hi > self.lo):
            raise ValueError("every parameter needs spread among the members to fit the map")
        flat = Y.reshape(self.N, -1)
        self.loo_rms: dict[int, float] = {}
        self.loo_max: dict[int, float] = {}
        degrees = [degree] if degree != "auto" else [
            p for p in range(1, max_degree + 1) if (p + 1) ** self.d <= self.N // 2]
        if not degrees:
            raise ValueError(f"{self.N} members are too few for a map in {self.d} parameters")
        best = None
        for p in degrees:
            self.degree = int(p)
            Phi = self.features(Q)
            pinv = np.linalg.pinv(Phi)
            C = pinv @ flat
            h = np.einsum("ij,ji->i", Phi, pinv)
            e = (flat - Phi @ C) / (1 - h)[:, None]
            self.loo_rms[p], self.loo_max[p] = float(np.sqrt((e**2).mean())), float(np.abs(e).max())
            if best is None or self.loo_rms[p] < self.loo_rms[best[0]]:
                best = (p, C)
        self.degree, C = best
        self.W = C.reshape((-1,) + self.shape)  # (T, K, m)
        # largest and RMS leave-one-out error (units of Y); the largest sits at the members on the
        # box's hull, where leaving one out extrapolates; inside, the map is far closer
        self.loo_error, self.loo_error_rms = self.loo_max[self.degree], self.loo_rms[self.degree]

    def features(self, Q) -> np.ndarray:
        Q = np.asarray(Q, dtype=np.float64).reshape(-1, self.d)
        t = 2 * (Q - self.lo) / (self.hi - self.lo) - 1
        P = [_legendre(t[:, j], self.degree) for j in range(self.d)]
        cols = [np.prod([P[j][:, i[j]] for j in range(self.d)], axis=0)
                for i in itertools.product(range(self.degree + 1), repeat=self.d)]
        return np.stack(cols, axis=1)

    def __call__(self, Q) -> np.ndarray:
        """(G, d) -> (G, K, m)."""
        Phi = self.features(Q)
        return (Phi @ self.W.reshape(len(self.W), -1)).reshape((len(Phi),) + self.shape)

    def frame(self, Q, k: int) -> np.ndarray:
        return self.features(Q) @ self.W[:, k].reshape(len(self.W), -1)

    def forecaster(self, frames):
        """``forecast(Q, k)`` for :func:`~torchfra.assimilation.sequential_filter` from the map (no FE
        solve): the observations of frame ``frames[k]`` at each member's coordinates Q (N, d)."""
        import torch

        frames = np.asarray(frames)
        return lambda Q, k: torch.as_tensor(self.frame(Q.numpy(), int(frames[k])))

    @property
    def range(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo.copy(), self.hi.copy()


@dataclass
class Likelihood:
    """The quadratic form of the log likelihood in the map's features (see the module docstring)."""

    A: np.ndarray
    b: np.ndarray
    c: float
    observations: int

    def __call__(self, Phi: np.ndarray) -> np.ndarray:
        return -0.5 * (self.c - 2 * Phi @ self.b + np.einsum("gi,ij,gj->g", Phi, self.A, Phi))


def likelihood(tmap: TensorMap, Z, r, frames=None) -> Likelihood:
    """Accumulate the quadratic form over ``frames`` (default all) of Z (K, m) (NaN = not observed),
    noise variances r (m,) or (K, m)."""
    Z = np.asarray(Z, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), Z.shape)
    T = len(tmap.W)
    A, b, c, n = np.zeros((T, T)), np.zeros(T), 0.0, 0
    for k in (range(Z.shape[0]) if frames is None else frames):
        obs = np.isfinite(Z[k])
        if not obs.any():
            continue
        Wk = tmap.W[:, k].reshape(T, -1)[:, obs]
        w = 1.0 / r[k, obs]
        A += (Wk * w) @ Wk.T
        b += Wk @ (w * Z[k, obs])
        c += float(np.sum(w * Z[k, obs] ** 2) + np.sum(np.log(2 * math.pi * r[k, obs])))
        n += int(obs.sum())
    return Likelihood(A, b, c, n)


@dataclass
class TensorPosterior:
    """The exact posterior on a fine tensor grid: ``axes`` (d arrays of q), ``log_post`` normalized
    log density on the grid (shape of the axes), ``log_evidence``, ``edge_mass`` (posterior mass in
    the outer cells of the coarse grid over the member box), ``prior_mass_outside`` (prior mass
    beyond the box)."""

    names: list[str]
    axes: list[np.ndarray]
    log_post: np.ndarray
    log_evidence: float
    edge_mass: float
    prior_mass_outside: float
    naturals: list = field(default_factory=list)  # q -> parameter value, per coordinate

    def _weights(self) -> np.ndarray:
        w = np.exp(self.log_post)
        for j, ax in enumerate(self.axes):
            shape = [1] * len(self.axes)
            shape[j] = -1
            w = w * _trapezoid(ax).reshape(shape)
        return w / w.sum()

    def marginal(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(q grid, normalized density of coordinate j)."""
        w = self._weights()
        m = w.sum(axis=tuple(i for i in range(len(self.axes)) if i != j))
        return self.axes[j], m / _trapezoid(self.axes[j])

    def map_point(self) -> np.ndarray:
        idx = np.unravel_index(int(np.argmax(self.log_post)), self.log_post.shape)
        return np.array([ax[i] for ax, i in zip(self.axes, idx)])

    def stats(self) -> dict[str, dict[str, float]]:
        """Per parameter (natural units): mean, std, p10, p90; and ``correlation`` between parameters."""
        w = self._weights()
        grids = np.meshgrid(*self.axes, indexing="ij")
        xs = [np.asarray(f(g)) for f, g in zip(self.naturals, grids)]
        out = {}
        for j, (name, x) in enumerate(zip(self.names, xs)):
            mean = float((w * x).sum())
            std = float(math.sqrt(max(float((w * (x - mean) ** 2).sum()), 0.0)))
            q, dens = self.marginal(j)
            cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[:-1] + dens[1:]) * np.diff(q))])
            cdf /= cdf[-1]
            p10, p90 = np.interp([0.1, 0.9], cdf, np.asarray(self.naturals[j](q)))
            out[name] = {"mean": mean, "std": std, "p10": float(p10), "p90": float(p90)}
        corr = np.eye(len(xs))
        for i, j in itertools.combinations(range(len(xs)), 2):
            mi, mj = out[self.names[i]]["mean"], out[self.names[j]]["mean"]
            cov = float((w * (xs[i] - mi) * (xs[j] - mj)).sum())
            corr[i, j] = corr[j, i] = cov / (out[self.names[i]]["std"] * out[self.names[j]]["std"])
        out["correlation"] = corr.tolist()
        return out


def _trapezoid(q: np.ndarray) -> np.ndarray:
    w = np.zeros_like(q)
    dq = np.diff(q)
    w[:-1] += dq / 2
    w[1:] += dq / 2
    return w


GRID_POINTS = {1: 4001, 2: 161, 3: 45}  # per coordinate of the fine grid
COARSE_POINTS = {1: 801, 2: 121, 3: 41}


def tensor_posterior(tmap: TensorMap, Z, r, prior_mean, prior_std, names=None, naturals=None, frames=None,
                     points: int | None = None, span: float = 8.0) -> TensorPosterior:
    """Exact posterior of the d coordinates given frames of Z: independent normal priors
    N(prior_mean, prior_std^2) per coordinate, Gaussian noise of variances r, the map ``tmap``."""
    d = tmap.d
    if d > 3:
        raise ValueError(f"a tensor grid in {d} parameters is too large; the grid reference covers d <= 3")
    mean0, std0 = np.asarray(prior_mean, dtype=np.float64), np.asarray(prior_std, dtype=np.float64)
    names = names or [f"q{j}" for j in range(d)]
    naturals = naturals or [np.exp] * d
    like = likelihood(tmap, Z, r, frames)

    def log_num(axes):
        G = np.stack([g.reshape(-1) for g in np.meshgrid(*axes, indexing="ij")], axis=1)
        lp = (-0.5 * ((G - mean0) / std0) ** 2 - np.log(std0 * math.sqrt(2 * math.pi))).sum(1)
        return (like(tmap.features(G)) + lp).reshape([len(a) for a in axes])

    def log_w(axes):
        out = np.zeros([len(a) for a in axes])
        for j, ax in enumerate(axes):
            shape = [1] * d
            shape[j] = -1
            out = out + np.log(_trapezoid(ax)).reshape(shape)
        return out

    lo, hi = tmap.range
    coarse = [np.linspace(lo[j], hi[j], COARSE_POINTS[d]) for j in range(d)]
    ln = log_num(coarse)
    w = np.exp(ln + log_w(coarse) - logsumexp(ln + log_w(coarse)))
    inner = tuple(slice(5, -5) for _ in range(d))
    edge = float(1.0 - w[inner].sum())
    # the fine grid: around the coarse posterior's mass (mean +- span stds per coordinate, within the box)
    grids = np.meshgrid(*coarse, indexing="ij")
    axes = []
    for j in range(d):
        m = float((w * grids[j]).sum())
        s = math.sqrt(max(float((w * (grids[j] - m) ** 2).sum()), 0.0))
        step = (hi[j] - lo[j]) / (COARSE_POINTS[d] - 1)
        s = max(s, step)  # a posterior narrower than the coarse cell: at least a cell wide
        axes.append(np.linspace(max(lo[j], m - span * s), min(hi[j], m + span * s), points or GRID_POINTS[d]))
    ln = log_num(axes)
    ev = float(logsumexp(ln + log_w(axes)))
    outside = 1.0 - float(np.prod([ndtr((hi[j] - mean0[j]) / std0[j]) - ndtr((lo[j] - mean0[j]) / std0[j])
                                   for j in range(d)]))
    return TensorPosterior(list(names), axes, ln - ev, ev, edge, outside, list(naturals))
