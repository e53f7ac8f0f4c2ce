"""The ensemble Kalman analysis step with perturbed observations (paper Eqs. 14 and 21), in ensemble
space, and the Gaussian innovation likelihood behind the log evidence.

Shapes: members on the first axis. Q (N, d) parameters (log space in this package), Y (N, m)
forecast observations, z (m,) the data, R = diag(r) (m,) the observation noise variances, E (N, m)
the perturbations, E ~ N(0, R).

    Q_a = Q + K (z - (Y + E)),   K = C_qy (C_yy + R)^-1.

With S = (Y - mean Y) / sqrt(N - 1) and Dq = (Q - mean Q) / sqrt(N - 1) the gain applied to the
innovations D (N, m) is, by the Woodbury identity,

    (C_yy + R)^-1 = R^-1 - R^-1 S^T (I_N + S R^-1 S^T)^-1 S R^-1
    K D^T = Dq^T (I_N + G)^-1 S R^-1 D^T,   G = S R^-1 S^T   (N x N),

so no m x m matrix is ever formed (m is ~10^4 per frame here, N = 100). Masked (unobserved)
entries are dropped before the update: NaN in z means "not observed".
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class AnalysisInfo:
    """Diagnostics of one analysis step (all about the forecast before the update).

    innovation (m_obs,): z - mean(Y); innovation_rms; nis: normalized innovation squared
    nu^T S^-1 nu divided by its expectation m_obs (~1 when the forecast spread and noise are right);
    log_likelihood: log N(nu; 0, C_yy + R), the step's contribution to the log evidence;
    spread: sqrt(mean diagonal of C_yy) (forecast spread of the observations).
    """

    m: int
    innovation_rms: float
    nis: float
    log_likelihood: float
    spread: float


def _anomalies(X: torch.Tensor) -> torch.Tensor:
    return (X - X.mean(dim=0, keepdim=True)) / math.sqrt(X.shape[0] - 1)


def _check(Q, Y, z, r, E):
    N = Q.shape[0]
    if Q.ndim != 2 or Y.ndim != 2 or Y.shape[0] != N:
        raise ValueError(f"Q must be (N, d) and Y (N, m) with the same N, got {tuple(Q.shape)} and {tuple(Y.shape)}")
    if N < 2:
        raise ValueError(f"an ensemble needs at least 2 members, got {N}")
    m = Y.shape[1]
    if z.shape != (m,) or r.shape != (m,):
        raise ValueError(f"z and r must be ({m},), got {tuple(z.shape)} and {tuple(r.shape)}")
    if E is not None and E.shape != (N, m):
        raise ValueError(f"E must be ({N}, {m}), got {tuple(E.shape)}")
    if not torch.all(r > 0):
        raise ValueError("observation noise variances must be positive")
    if not torch.isfinite(Y).all():
        bad = torch.nonzero(~torch.isfinite(Y))[0].tolist()
        raise ValueError(f"forecast observation of member {bad[0]} (entry {bad[1]}) is not finite; "
                         "a diverged member cannot be assimilated: drop it or fix the forward solve")


def analysis(Q: torch.Tensor, Y: torch.Tensor, z: torch.Tensor, r: torch.Tensor, E: torch.Tensor | None,
             mask: torch.Tensor | None = None) -> tuple[torch.Tensor, AnalysisInfo]:
    """One perturbed-observation EnKF update. Returns the analysed Q (N, d) and the step's diagnostics.

    ``E`` None updates without perturbations (the mean update of a square-root filter, used in tests).
    ``mask`` (m,) True where observed; by default the finite entries of z.
    """
    if z.ndim != 1 or Y.ndim != 2 or Y.shape[1] != z.shape[0] or r.shape != z.shape:
        raise ValueError(f"Y must be (N, m), z and r (m,), got {tuple(Y.shape)}, {tuple(z.shape)}, {tuple(r.shape)}")
    mask = torch.isfinite(z) if mask is None else mask & torch.isfinite(z)
    z, r, Y = z[mask], r[mask], Y[:, mask]
    E = None if E is None else E[:, mask]
    _check(Q, Y, z, r, E)
    m = int(z.shape[0])
    if m == 0:
        return Q.clone(), AnalysisInfo(0, math.nan, math.nan, 0.0, math.nan)
    N = Q.shape[0]
    S, Dq = _anomalies(Y), _anomalies(Q)
    SRinv = S / r  # (N, m) = S R^-1
    G = SRinv @ S.T
    L = torch.linalg.cholesky(torch.eye(N, dtype=Q.dtype) + G)
    D = z - Y if E is None else z - (Y + E)  # (N, m) innovations of every member
    T = torch.cholesky_solve(SRinv @ D.T, L)  # (N, N): (I + G)^-1 S R^-1 D^T
    Qa = Q + T.T @ Dq

    nu = z - Y.mean(dim=0)
    a = SRinv @ nu
    quad = float(nu @ (nu / r) - a @ torch.cholesky_solve(a[:, None], L)[:, 0])
    logdet = float(torch.log(r).sum() + 2 * torch.log(torch.diagonal(L)).sum())
    loglik = -0.5 * (quad + logdet + m * math.log(2 * math.pi))
    info = AnalysisInfo(m, float(torch.sqrt((nu ** 2).mean())), quad / m, loglik, float(torch.sqrt((S ** 2).sum(0).mean())))
    return Qa, info

