"""The exact posterior of one parameter by quadrature on a grid (the reference for every filter).

The FE map q = log C10 -> observations is interpolated by a cubic spline through a parameter
sweep (here the forward ensemble itself: its members are FE solves at 100 values of C10). The
leave-one-out error of that spline bounds the interpolation error; it must be far below the noise.
With Gaussian noise, the posterior on a fine grid of q is

    log p(q | z_1:k) = log p(q) + sum_j log N(z_j; y_j(q), R_j) - log p(z_1:k),

and the log evidence log p(z_1:k) is the log of the grid integral of the numerator.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.special import logsumexp, ndtr


class SweepMap:
    """Observations as a smooth function of one log-parameter, from a sweep q (S,), Y (S, K, m)."""

    def __init__(self, q, Y):
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        Y = np.asarray(Y, dtype=np.float64)
        if Y.shape[0] != q.size:
            raise ValueError(f"sweep values ({q.size}) and outputs ({Y.shape[0]}) differ in number")
        if not np.all(np.isfinite(Y)):
            bad = np.flatnonzero(~np.isfinite(Y.reshape(q.size, -1)).all(1))
            raise ValueError(f"sweep outputs of members {bad.tolist()} are not finite (diverged solves); drop them")
        order = np.argsort(q)
        q, Y = q[order], Y[order]
        keep = np.concatenate([[True], np.diff(q) > 1e-12])
        self.q, self.Y = q[keep], Y[keep]
        self.shape = self.Y.shape[1:]
        self._spline = CubicSpline(self.q, self.Y.reshape(self.q.size, -1), axis=0)

    @property
    def range(self) -> tuple[float, float]:
        return float(self.q[0]), float(self.q[-1])

    def __call__(self, q) -> np.ndarray:
        """(G,) -> (G, *shape)."""
        q = np.asarray(q, dtype=np.float64)
        return self._spline(q).reshape(q.shape + self.shape)

    def frame(self, q, k: int) -> np.ndarray:
        """(G,) -> (G, *shape[1:]): frame ``k`` alone (``self(q)[:, k]``), the piecewise cubic evaluated on
        that frame's coefficients only, so a filter's cost per frame does not grow with the frames."""
        q = np.asarray(q, dtype=np.float64).reshape(-1)
        s = self._spline
        m = int(np.prod(self.shape[1:]))
        i = np.clip(np.searchsorted(s.x, q, side="right") - 1, 0, s.x.size - 2)
        t = (q - s.x[i])[:, None]
        c = s.c[:, :, k * m:(k + 1) * m]  # (4, S - 1, m) cubic coefficients of frame k
        y = ((c[0, i] * t + c[1, i]) * t + c[2, i]) * t + c[3, i]
        return y.reshape((q.size,) + self.shape[1:])

    def forecaster(self, frames):
        """``forecast(Q, k)`` for :func:`~torchfra.assimilation.sequential_filter`: the observations
        of frame ``frames[k]`` at each member's log-parameter Q (N, 1), from the spline instead of an
        FE solve. A restart filter driven by it costs no FE solve; its agreement with the FE restart
        filter is as good as the spline's agreement with the FE map (check it on the path taken)."""
        frames = np.asarray(frames)
        return lambda Q, k: torch.as_tensor(self.frame(Q[:, 0].numpy(), int(frames[k])))

    def leave_one_out_error(self) -> float:
        """Largest |error| (units of Y) predicting each interior sweep point from all the others; the
        spacing is then twice the real one, so this over-estimates the spline's error."""
        err = 0.0
        flat = self.Y.reshape(self.q.size, -1)
        for i in range(1, self.q.size - 1):
            keep = np.arange(self.q.size) != i
            s = CubicSpline(self.q[keep], flat[keep], axis=0)
            err = max(err, float(np.abs(s(self.q[i]) - flat[i]).max()))
        return err


@dataclass
class GridPosterior:
    """Exact posterior on a grid of q = log parameter.

    q (G,); log_post (K + 1, G) normalized log densities in q before any frame and after each frame;
    log_evidence (K + 1,) cumulative; prior_mass_outside: prior probability beyond the grid.
    """

    q: np.ndarray
    log_post: np.ndarray
    log_evidence: np.ndarray
    prior_mass_outside: float

    def stats(self, step: int = -1, natural=np.exp) -> dict[str, float]:
        """Mean, std, p10, p90 of the physical parameter ``natural(q)`` (default exp(q)) after ``step``
        frames (-1: all)."""
        p = np.exp(self.log_post[step])
        x = np.asarray(natural(self.q))
        w = _trapezoid_weights(self.q) * p
        w = w / w.sum()
        mean = float(w @ x)
        std = float(math.sqrt(max(w @ (x - mean) ** 2, 0.0)))
        # CDF at the nodes by the trapezoid rule (cumsum of the node weights would be half a cell off)
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (p[:-1] + p[1:]) * np.diff(self.q))])
        cdf /= cdf[-1]
        p10, p90 = np.interp([0.1, 0.9], cdf, x)
        return {"mean": mean, "std": std, "p10": float(p10), "p90": float(p90)}

    def edge_mass(self, step: int = -1, cells: int = 10) -> float:
        """Posterior probability in the ``cells`` grid cells at either end: near 0 when the grid (the
        sweep's range) holds the posterior."""
        w = _trapezoid_weights(self.q) * np.exp(self.log_post[step])
        return float((w[:cells].sum() + w[-cells:].sum()) / w.sum())

    def density(self, step: int = -1, natural=np.exp) -> tuple[np.ndarray, np.ndarray]:
        """(x, pdf of the physical parameter x = natural(q), default exp(q))."""
        x = np.asarray(natural(self.q))
        jac = x if natural is np.exp else np.abs(np.gradient(x, self.q))  # dx/dq
        return x, np.exp(self.log_post[step]) / jac


def _trapezoid_weights(q: np.ndarray) -> np.ndarray:
    w = np.zeros_like(q)
    dq = np.diff(q)
    w[:-1] += dq / 2
    w[1:] += dq / 2
    return w


def grid_posterior(sweep: SweepMap, Z, r, prior_mu: float, prior_sigma: float, n_grid: int = 4000,
                   frames=None) -> GridPosterior:
    """Exact posterior of q given frames of Z (K, m) (NaN = not observed), noise variances r (m,) or
    (K, m), and the normal prior N(prior_mu, prior_sigma^2) of q. ``frames``: the frame indices to
    assimilate (default all); the grid spans the sweep."""
    Z = np.asarray(Z, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), Z.shape)
    frames = range(Z.shape[0]) if frames is None else frames
    lo, hi = sweep.range
    q = np.linspace(lo, hi, n_grid)
    log_w = np.log(_trapezoid_weights(q))
    log_prior = -0.5 * ((q - prior_mu) / prior_sigma) ** 2 - math.log(prior_sigma * math.sqrt(2 * math.pi))
    outside = float(ndtr((lo - prior_mu) / prior_sigma) + 1.0 - ndtr((hi - prior_mu) / prior_sigma))
    log_num = log_prior.copy()
    posts = [log_num - logsumexp(log_num + log_w)]
    evid = [float(logsumexp(log_num + log_w))]
    for k in frames:
        obs = np.isfinite(Z[k])
        if obs.any():
            Yk = sweep.frame(q, k).reshape(q.size, -1)[:, obs]
            res = (Z[k, obs] - Yk) ** 2 / r[k, obs]
            log_num = log_num - 0.5 * (res.sum(axis=1) + np.log(2 * math.pi * r[k, obs]).sum())
        ev = float(logsumexp(log_num + log_w))
        posts.append(log_num - ev)
        evid.append(ev)
    return GridPosterior(q, np.asarray(posts), np.asarray(evid), outside)


EDGE_MASS_LIMIT = 0.01  # posterior probability in the 10 end cells of the grid that flags the prior's edge
RESIDUAL_RMS_LIMIT = 2.0  # residual RMS at the MAP, in noise units, that flags a model that does not fit
UNIT_HINTS = ((1e-3, "metres instead of mm?"), (1e-1, "cm instead of mm?"), (1e3, "micrometres instead of mm?"),
              (25.4, "inches instead of mm?"))  # recorded / model displacement ratio -> the likely unit mistake


def data_fit(posterior: GridPosterior, sweep: SweepMap, Z, r, natural=math.exp) -> dict:
    """Whether the recording fits the model and the prior at all, from the exact posterior: a posterior
    piled against an end of the sweep's range (``edge_mass`` above ``EDGE_MASS_LIMIT``: the data want
    a parameter outside the forward ensemble, e.g. a stiffer silicone or a unit mistake), or a residual
    at the MAP far above the noise (RMS of (Z - Y) / sqrt(r) above ``RESIDUAL_RMS_LIMIT``: no parameter
    of the model reproduces the recording: wrong noise level, units, or missing physics). Returns
    {"ok", "edge_mass", "residual_rms_in_noise_units", "map", "range", "displacement_scale" (the best a in
    Z ~ a Y at the MAP: far from 1 at the range's end names the likely unit mistake), "reasons"};
    a run whose data do not fit must say so, never report its posterior as a result."""
    Z = np.asarray(Z, dtype=np.float64)
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), Z.shape)
    q_map = float(posterior.q[int(np.argmax(posterior.log_post[-1]))])
    e = (Z - sweep(np.array([q_map]))[0]) / np.sqrt(r)
    rms = float(np.sqrt(np.nanmean(e**2)))
    edge = posterior.edge_mass()
    lo, hi = sweep.range
    Y = sweep(np.array([q_map]))[0]
    seen = np.isfinite(Z)
    scale = float(np.sum(Z[seen] * Y[seen]) / max(float(np.sum(Y[seen] ** 2)), 1e-300))  # best a in Z ~ a Y
    reasons = []
    if edge > EDGE_MASS_LIMIT:
        side = "upper" if q_map > 0.5 * (lo + hi) else "lower"
        hint = next((h for ratio, h in UNIT_HINTS if abs(math.log10(max(abs(scale), 1e-300) / ratio)) < 0.35), None)
        units = (f"the recorded displacements are {scale:.3g} times the model's at that end: {hint}" if hint else
                 "check the units of displacements and pressures")
        reasons.append(f"{edge:.0%} of the exact posterior lies at the {side} end of the forward ensemble's range "
                       f"[{natural(lo):.4g}, {natural(hi):.4g}]: the recording wants a parameter outside the "
                       f"prior ({units}; or widen the prior)")
    if rms > RESIDUAL_RMS_LIMIT:
        reasons.append(f"at the best parameter ({natural(q_map):.4g}) the residual is {rms:.3g} times the noise: "
                       "no parameter of the model reproduces the recording (check the noise level and units, or "
                       "look for missing physics with scripts/diagnose.py)")
    return {"ok": not reasons, "edge_mass": edge, "residual_rms_in_noise_units": rms, "map": float(natural(q_map)),
            "range": [float(natural(lo)), float(natural(hi))], "displacement_scale": scale, "reasons": reasons}
