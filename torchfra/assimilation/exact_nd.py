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
(:class:`torchfra.calibration.priors.ParameterSet`).
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
    degrees whose coefficients stay within half the members). ``basis``: "tensor" (every product of
    Legendre polynomials up to ``degree`` in each coordinate) or "total" (products of total degree
    up to ``degree``; default for d >= 4, where the tensor product outgrows any ensemble)."""

    def __init__(self, Q, Y, degree: int | str = "auto", max_degree: int = 10, basis: str | None = None):
        Q = np.asarray(Q, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if Q.ndim != 2 or Y.shape[0] != Q.shape[0]:
            raise ValueError(f"members ({Q.shape}) and outputs ({Y.shape}) do not match")
        if not np.isfinite(Y).all():
            bad = np.flatnonzero(~np.isfinite(Y.reshape(len(Y), -1)).all(1))
            raise ValueError(f"outputs of members {bad.tolist()} are not finite (diverged solves); drop them")
        self.N, self.d = Q.shape
        self.basis = basis or ("tensor" if self.d <= 3 else "total")
        self.shape = Y.shape[1:]
        self.lo, self.hi = Q.min(0), Q.max(0)
        if not np.all(self.hi > self.lo):
            raise ValueError("every parameter needs spread among the members to fit the map")
        flat = Y.reshape(self.N, -1)
        self.loo_rms: dict[int, float] = {}
        self.loo_max: dict[int, float] = {}
        degrees = [degree] if degree != "auto" else [
            p for p in range(1, max_degree + 1) if len(self._multi_indices(p)) <= self.N // 2]
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

    def _multi_indices(self, p: int) -> list[tuple[int, ...]]:
        idx = itertools.product(range(p + 1), repeat=self.d)
        return [i for i in idx if self.basis == "tensor" or sum(i) <= p]

    def features(self, Q) -> np.ndarray:
        Q = np.asarray(Q, dtype=np.float64).reshape(-1, self.d)
        t = 2 * (Q - self.lo) / (self.hi - self.lo) - 1
        P = [_legendre(t[:, j], self.degree) for j in range(self.d)]
        cols = [np.prod([P[j][:, i[j]] for j in range(self.d)], axis=0) for i in self._multi_indices(self.degree)]
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
    """The exact posterior on a fine grid aligned with the posterior's principal axes (a ridge of
    strongly correlated parameters is resolved across its width): ``points`` (n^d, d) coordinates,
    ``log_post`` their normalized log density (per unit volume of q), ``cell`` the volume of a cell,
    ``log_evidence``, ``edge_mass`` (posterior mass in the outer cells of the coarse grid over the
    member box), ``prior_mass_outside`` (prior mass beyond the box)."""

    names: list[str]
    points: np.ndarray
    log_post: np.ndarray
    cell: float
    log_evidence: float
    edge_mass: float
    prior_mass_outside: float
    naturals: list = field(default_factory=list)  # q -> parameter value, per coordinate

    def weights(self) -> np.ndarray:
        w = np.exp(self.log_post - self.log_post.max())
        return w / w.sum()

    def marginal(self, j: int, bins: int = 120) -> tuple[np.ndarray, np.ndarray]:
        """(q bin centres, normalized density of coordinate j): a weighted histogram of the grid."""
        h, edges = np.histogram(self.points[:, j], bins=bins, weights=self.weights(), density=True)
        return 0.5 * (edges[1:] + edges[:-1]), h

    def map_point(self) -> np.ndarray:
        return self.points[int(np.argmax(self.log_post))].copy()

    def natural_points(self) -> np.ndarray:
        return np.stack([np.asarray(f(self.points[:, j])) for j, f in enumerate(self.naturals)], axis=1)

    def stats(self) -> dict[str, dict[str, float]]:
        """Per parameter (natural units): mean, std, p10, p90; and ``correlation`` between parameters."""
        w = self.weights()
        X = self.natural_points()
        mean = w @ X
        C = (X - mean).T @ ((X - mean) * w[:, None])
        out = {}
        for j, name in enumerate(self.names):
            order = np.argsort(X[:, j])
            cdf = np.cumsum(w[order]) - 0.5 * w[order]
            p10, p90 = np.interp([0.1, 0.9], cdf, X[order, j])
            out[name] = {"mean": float(mean[j]), "std": float(math.sqrt(max(C[j, j], 0.0))), "p10": float(p10),
                         "p90": float(p90)}
        sd = np.sqrt(np.clip(np.diag(C), 1e-300, None))
        out["correlation"] = (C / np.outer(sd, sd)).tolist()
        return out


GRID_POINTS = {2: 321, 3: 61}  # per axis of the fine grid (2 parameters: 161, 321 and 641 agreed to 1e-3 stds)
COARSE_POINTS = {2: 121, 3: 41}


def tensor_posterior(tmap: TensorMap, Z, r, prior_mean, prior_std, names=None, naturals=None, frames=None,
                     points: int | None = None, span: float = 7.0) -> TensorPosterior:
    """Exact posterior of the d coordinates given frames of Z: independent normal priors
    N(prior_mean, prior_std^2) per coordinate, Gaussian noise of variances r, the map ``tmap``.

    A coarse grid over the member box finds the mass (and the mass at the box's edges); two fine
    grids follow, each spanning ``span`` stds along the principal axes of the previous grid's
    posterior covariance, so the last one resolves the posterior whatever its correlation."""
    d = tmap.d
    if d not in GRID_POINTS:
        raise ValueError(f"a tensor grid in {d} parameters: the grid reference covers d = 2 and 3")
    mean0, std0 = np.asarray(prior_mean, dtype=np.float64), np.asarray(prior_std, dtype=np.float64)
    names = names or [f"q{j}" for j in range(d)]
    naturals = naturals or [np.exp] * d
    like = likelihood(tmap, Z, r, frames)

    def log_num(G):
        lp = (-0.5 * ((G - mean0) / std0) ** 2 - np.log(std0 * math.sqrt(2 * math.pi))).sum(1)
        return like(tmap.features(G)) + lp

    def moments(G, ln):
        w = np.exp(ln - ln.max())
        w /= w.sum()
        m = w @ G
        return m, (G - m).T @ ((G - m) * w[:, None])

    lo, hi = tmap.range
    n0 = COARSE_POINTS[d]
    coarse = [np.linspace(lo[j], hi[j], n0) for j in range(d)]
    G = np.stack([g.reshape(-1) for g in np.meshgrid(*coarse, indexing="ij")], axis=1)
    ln = log_num(G)
    w = np.exp(ln - ln.max()).reshape([n0] * d)
    w /= w.sum()
    edge = float(1.0 - w[tuple(slice(5, -5) for _ in range(d))].sum())
    m, C = moments(G, ln)
    C = C + np.diag(((hi - lo) / (n0 - 1)) ** 2 / 12)  # at least the coarse cell's own spread
    n = points or GRID_POINTS[d]
    u = np.linspace(-1.0, 1.0, n)
    U = np.stack([g.reshape(-1) for g in np.meshgrid(*[u] * d, indexing="ij")], axis=1)
    for _ in range(2):
        lam, V = np.linalg.eigh(C)
        A = V * (span * np.sqrt(np.clip(lam, 1e-300, None)))  # columns: the principal half-widths
        G = m + U @ A.T
        ln = log_num(G)
        m, C = moments(G, ln)
    cell = float(abs(np.linalg.det(A)) * (2.0 / (n - 1)) ** d)
    ev = float(logsumexp(ln) + math.log(cell))
    outside = 1.0 - float(np.prod([ndtr((hi[j] - mean0[j]) / std0[j]) - ndtr((lo[j] - mean0[j]) / std0[j])
                                   for j in range(d)]))
    return TensorPosterior(list(names), G, ln - ev, cell, ev, edge, outside, list(naturals))


@dataclass
class SampledPosterior(TensorPosterior):
    """The posterior of d >= 4 coordinates by importance sampling on the map (a multivariate t
    proposal at the MAP with the Laplace covariance): ``points`` the draws, ``log_post`` their log
    importance weights (normalized), ``ess`` the effective sample size."""

    ess: float = 0.0
    map_q: np.ndarray | None = None

    def map_point(self) -> np.ndarray:
        return np.array(self.map_q, copy=True)


def sampled_posterior(tmap: TensorMap, Z, r, prior_mean, prior_std, names=None, naturals=None, frames=None,
                      samples: int = 40_000, seed: int = 0, dof: float = 5.0) -> SampledPosterior:
    """Posterior of the d coordinates by self-normalized importance sampling: the MAP by BFGS from
    the best member, the Laplace covariance from a finite-difference Hessian, a multivariate t
    proposal (``dof``) with 1.5x that spread. Its Monte Carlo error is ~ 1/sqrt(ESS) posterior stds
    for the means; the ESS is reported, and the log evidence is the log mean importance weight."""
    from scipy.optimize import minimize
    from scipy.special import gammaln

    d = tmap.d
    mean0, std0 = np.asarray(prior_mean, dtype=np.float64), np.asarray(prior_std, dtype=np.float64)
    names = names or [f"q{j}" for j in range(d)]
    naturals = naturals or [np.exp] * d
    like = likelihood(tmap, Z, r, frames)

    def log_num(G):
        G = np.atleast_2d(G)
        lp = (-0.5 * ((G - mean0) / std0) ** 2 - np.log(std0 * math.sqrt(2 * math.pi))).sum(1)
        return like(tmap.features(G)) + lp

    lo, hi = tmap.range
    scale = hi - lo
    starts = mean0 + std0 * np.random.default_rng(seed).standard_normal((2000, d))
    x0 = starts[int(np.argmax(log_num(starts)))]
    f0 = float(log_num(x0)[0])
    res = minimize(lambda u: -(log_num(x0 + u * scale)[0] - f0), np.zeros(d), method="BFGS",
                   options={"gtol": 1e-8, "maxiter": 2000})
    m = x0 + res.x * scale
    # Hessian of the log posterior by central differences, steps a small fraction of the box
    h = 1e-3 * scale
    H = np.zeros((d, d))
    fm = float(log_num(m)[0])
    for i in range(d):
        for j in range(i, d):
            ei, ej = np.eye(d)[i] * h[i], np.eye(d)[j] * h[j]
            if i == j:
                H[i, i] = (log_num(m + ei)[0] - 2 * fm + log_num(m - ei)[0]) / h[i] ** 2
            else:
                H[i, j] = H[j, i] = (log_num(m + ei + ej)[0] - log_num(m + ei - ej)[0] - log_num(m - ei + ej)[0]
                                     + log_num(m - ei - ej)[0]) / (4 * h[i] * h[j])
    C = np.linalg.inv(-H)
    C = 0.5 * (C + C.T) * 1.5**2
    L = np.linalg.cholesky(C)
    rng = np.random.default_rng(seed + 1)
    z = rng.standard_normal((samples, d))
    g = rng.chisquare(dof, samples) / dof
    G = m + (z / np.sqrt(g)[:, None]) @ L.T
    # log density of the multivariate t proposal
    dev = np.linalg.solve(L, (G - m).T).T
    log_q = (gammaln((dof + d) / 2) - gammaln(dof / 2) - 0.5 * d * math.log(dof * math.pi)
             - np.log(np.diag(L)).sum() - 0.5 * (dof + d) * np.log1p((dev**2).sum(1) / dof))
    lw = log_num(G) - log_q
    ev = float(logsumexp(lw) - math.log(samples))
    w = np.exp(lw - lw.max())
    ess = float(w.sum() ** 2 / (w**2).sum())
    inside = np.all((G >= lo) & (G <= hi), axis=1)
    edge = float(1.0 - (w * inside).sum() / w.sum())  # posterior mass beyond the members' box
    outside = 1.0 - float(np.prod([ndtr((hi[j] - mean0[j]) / std0[j]) - ndtr((lo[j] - mean0[j]) / std0[j])
                                   for j in range(d)]))
    return SampledPosterior(list(names), G, lw - logsumexp(lw), 0.0, ev, edge, outside, list(naturals), ess, m)


def data_fit_nd(post: TensorPosterior, tmap: TensorMap, Z, r) -> dict:
    """:func:`torchfra.assimilation.exact.data_fit` for several parameters: the posterior's mass at
    the edges of the member box, and the residual at the grid's MAP in noise units."""
    from torchfra.assimilation.exact import EDGE_MASS_LIMIT, RESIDUAL_RMS_LIMIT, UNIT_HINTS

    Z = np.asarray(Z, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), Z.shape)
    q_map = post.map_point()
    Y = tmap(q_map[None])[0].reshape(Z.shape)
    rms = float(np.sqrt(np.nanmean((Z - Y) ** 2 / r)))
    seen = np.isfinite(Z)
    scale = float(np.sum(Z[seen] * Y[seen]) / max(float(np.sum(Y[seen] ** 2)), 1e-300))
    lo, hi = tmap.range
    at = {n: float(f(q)) for n, f, q in zip(post.names, post.naturals, q_map)}
    ranges = {n: [float(f(a)), float(f(b))] for n, f, a, b in zip(post.names, post.naturals, lo, hi)}
    reasons = []
    if post.edge_mass > EDGE_MASS_LIMIT:
        ends = [n for j, n in enumerate(post.names) if min(q_map[j] - lo[j], hi[j] - q_map[j]) < 0.05 * (hi[j] - lo[j])]
        hint = next((h for ratio, h in UNIT_HINTS if abs(math.log10(max(abs(scale), 1e-300) / ratio)) < 0.35), None)
        units = (f"the recorded displacements are {scale:.3g} times the model's there: {hint}" if hint else
                 "check the units of displacements and pressures")
        reasons.append(f"{post.edge_mass:.0%} of the exact posterior lies at the edge of the forward ensemble's range"
                       + (f" in {', '.join(ends)}" if ends else "") + f" ({ranges}): the recording wants parameters "
                       f"outside the prior ({units}; or widen the prior)")
    if rms > RESIDUAL_RMS_LIMIT:
        reasons.append(f"at the best parameters ({at}) the residual is {rms:.3g} times the noise: no parameters of the "
                       "model reproduce the recording (check the noise level and units, or look for missing physics "
                       "with scripts/diagnose.py)")
    return {"ok": not reasons, "edge_mass": post.edge_mass, "residual_rms_in_noise_units": rms, "map": at,
            "range": ranges, "displacement_scale": scale, "reasons": reasons}
