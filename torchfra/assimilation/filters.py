"""Sequential ensemble Kalman filters for constant parameters (paper §3.4).

One loop serves every filter; they differ only in how the forecast observations ``Y_k`` of the
current parameter ensemble are obtained:

- hierarchical (paper Eqs. 21-23): a *slave* predicts ``Y_k`` from the offline forward ensemble
  ``Y_fe`` (Eq. 15) and the current parameters, with no FE solve;
  :class:`LinearSlave` is Eq. 23, :class:`PolynomialSlave` its nonlinear extension;
- restart: ``Y_k`` comes from FE solves of the current ensemble (see :mod:`.restart`).

Parameters are filtered in log space (Q = log kappa) so they stay positive. Randomness comes only
from the ``torch.Generator`` passed in.
"""
from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np
import torch

from torchfra.assimilation.analysis import AnalysisInfo, analysis


class LinearSlave:
    """Eq. 23: ``Y_{k,ae} = Y_{k,fe} + B_k (Q - (Q_0f + E_q))``, ``B_k = C_{y q0} (C_{q0 q0} + R_q)^-1``.

    Q0 (N, d) the prior ensemble that made Y_fe (N, K, m). ``R_q`` (d,) the state perturbation
    variances (0 in the paper's experiment); E_q ~ N(0, R_q) is drawn from the filter's generator.
    With R_q = 0 the map is the least-squares affine fit of Y_fe on Q0, each member keeping its own
    residual: exact for affine maps, biased for curved ones once Q leaves the prior's spread.
    """

    name = "linear"

    def __init__(self, Q0: torch.Tensor, Y_fe: torch.Tensor, R_q=None):
        self.Q0, self.Y_fe = Q0, Y_fe
        N, d = Q0.shape
        self.R_q = torch.zeros(d, dtype=Q0.dtype) if R_q is None else torch.as_tensor(R_q, dtype=Q0.dtype).reshape(d)
        dQ = Q0 - Q0.mean(0)
        self._Cqq = dQ.T @ dQ / (N - 1) + torch.diag(self.R_q)
        self._dQ = dQ

    def __call__(self, Q: torch.Tensor, k: int, generator: torch.Generator | None = None) -> torch.Tensor:
        Yk = self.Y_fe[:, k]
        N = Yk.shape[0]
        Cyq = (Yk - Yk.mean(0)).T @ self._dQ / (N - 1)  # (m, d)
        B = torch.linalg.solve(self._Cqq, Cyq.T).T  # (m, d) = C_yq (C_qq + R_q)^-1
        shift = Q - self.Q0
        if torch.any(self.R_q > 0):
            shift = shift - torch.randn(Q.shape, generator=generator, dtype=Q.dtype) * self.R_q.sqrt()
        return Yk + shift @ B.T


def select_degree(Q0: torch.Tensor, Y_fe: torch.Tensor, max_degree: int = 8) -> tuple[int, dict[int, float]]:
    """The polynomial degree with the smallest leave-one-out RMS error of the map Q0 -> Y_fe, over
    degree 1 and the higher degrees (up to max_degree) whose coefficients number at most half the
    members (the leave-one-out error, not a members-per-coefficient rule, guards against
    over-fitting: with d = 2 parameters and 100 members a cubic has 10 coefficients and a quintic
    21, and the map's curvature may need the quintic). Leave-one-out residuals of least squares come
    in closed form, e_i / (1 - h_ii) with h the hat matrix: no refits."""
    N, d = Q0.shape
    loo: dict[int, float] = {}
    for p in range(1, max_degree + 1):
        if p > 1 and 2 * len(_monomials(d, p)) > N:
            break
        s = PolynomialSlave(Q0, Y_fe, p)
        Phi = s.features(Q0)
        h = torch.diagonal(Phi @ torch.linalg.pinv(Phi))
        e = Y_fe.reshape(N, -1) - s._g0.reshape(N, -1)
        loo[p] = float(torch.sqrt(((e / (1 - h)[:, None]) ** 2).mean()))
    return min(loo, key=loo.get), loo


def _monomials(d: int, degree: int) -> list[tuple[int, ...]]:
    return [c for p in range(degree + 1) for c in itertools.combinations_with_replacement(range(d), p)]


class PolynomialSlave:
    """The nonlinear slave: ``Y_{k,ae} = Y_{k,fe} + g_k(Q) - g_k(Q_0f)``, ``g_k`` the least-squares
    polynomial (total degree ``degree``, in the standardized parameters) fitted to (Q0, Y_fe[:, k]).

    Each member keeps its own regression residual, as in Eq. 23, to which this reduces for degree 1
    and R_q = 0. A degree high enough to follow the map (displacement ~ 1/C10 here) keeps the
    forecast right when the posterior is far narrower than the prior; still no FE solve.
    """

    name = "polynomial"

    def __init__(self, Q0: torch.Tensor, Y_fe: torch.Tensor, degree: int | str = 3, max_degree: int = 8):
        N, d = Q0.shape
        self.loo_rms: dict[int, float] = {}
        if degree == "auto":
            degree, self.loo_rms = select_degree(Q0, Y_fe, max_degree)
        self.degree = int(degree)
        self.terms = _monomials(d, self.degree)
        if len(self.terms) >= N:
            raise ValueError(f"a degree-{degree} polynomial in {d} parameters has {len(self.terms)} coefficients, "
                             f"too many for {N} members; lower the degree")
        self.center, self.scale = Q0.mean(0), Q0.std(0)
        if not torch.all(self.scale > 0):
            raise ValueError("every parameter needs spread in the prior ensemble to fit the slave's map")
        self.Y_fe = Y_fe
        Phi0 = self.features(Q0)
        K = Y_fe.shape[1]
        W = torch.linalg.lstsq(Phi0, Y_fe.reshape(N, -1)).solution
        self.W = W.reshape(len(self.terms), K, -1)
        self._g0 = (Phi0 @ W).reshape(N, K, -1)
        self.residual_rms = float(torch.sqrt(((Y_fe - self._g0) ** 2).mean()))

    def features(self, Q: torch.Tensor) -> torch.Tensor:
        s = (Q - self.center) / self.scale
        cols = [torch.prod(s[:, list(t)], dim=1) if t else torch.ones(Q.shape[0], dtype=Q.dtype) for t in self.terms]
        return torch.stack(cols, dim=1)

    def map(self, Q: torch.Tensor, k: int) -> torch.Tensor:
        """The fitted map g_k(Q) alone (N, m)."""
        return self.features(Q) @ self.W[:, k]

    def __call__(self, Q: torch.Tensor, k: int, generator: torch.Generator | None = None) -> torch.Tensor:
        return self.Y_fe[:, k] + self.map(Q, k) - self._g0[:, k]


@dataclass
class FilterResult:
    """Ensembles and diagnostics of a sequential filter.

    Q: (K + 1, N, d) the parameter ensemble before the first step and after every step (log space);
    info: per step the :class:`AnalysisInfo`; Y_forecast_tracked: (K, N, c) forecast of the tracked
    observation entries (for figures); log_evidence: sum of the steps' log likelihoods.
    """

    Q: list[torch.Tensor] = field(default_factory=list)
    info: list[AnalysisInfo] = field(default_factory=list)
    Y_tracked: list[torch.Tensor] = field(default_factory=list)
    fe_solves: int = 0
    newton_iterations: int = 0
    wall_s: float = 0.0

    @property
    def log_evidence(self) -> float:
        return float(sum(i.log_likelihood for i in self.info))

    @property
    def steps(self) -> int:
        return len(self.info)

    def to_dict(self) -> dict:
        """Tensors, numbers and lists only: a checkpoint that ``torch.load(weights_only=True)`` reads
        without unpickling any class."""
        return {"Q": list(self.Q), "info": [asdict(i) for i in self.info], "Y_tracked": list(self.Y_tracked),
                "fe_solves": self.fe_solves, "newton_iterations": self.newton_iterations, "wall_s": self.wall_s}

    @classmethod
    def from_dict(cls, d: dict) -> "FilterResult":
        return cls(Q=list(d["Q"]), info=[AnalysisInfo(**i) for i in d["info"]], Y_tracked=list(d["Y_tracked"]),
                   fe_solves=int(d["fe_solves"]), newton_iterations=int(d["newton_iterations"]),
                   wall_s=float(d["wall_s"]))


def sequential_filter(
    Q0: torch.Tensor,
    forecast: Callable[[torch.Tensor, int], torch.Tensor],
    Z: torch.Tensor,
    r: torch.Tensor,
    generator: torch.Generator,
    tracked=None,
    result: FilterResult | None = None,
    checkpoint: Callable[[FilterResult, torch.Generator], None] | None = None,
    progress: str | None = None,
) -> FilterResult:
    """Assimilate the frames of ``Z`` (K, m) one by one (NaN = not observed).

    forecast(Q, k) -> (N, m) forecast observations of frame k for the current ensemble Q (N, d).
    r (m,) or (K, m) noise variances. tracked: indices into m recorded per step for figures.
    ``result`` continues an interrupted run (its steps are skipped; the generator must be the one
    saved with it); ``checkpoint`` is called after every step.
    """
    import time

    res = result or FilterResult(Q=[Q0.clone()])
    r = r if r.ndim == 2 else r.expand(Z.shape[0], -1)
    steps = range(res.steps, Z.shape[0])
    if progress:
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc=progress, unit="frame", initial=res.steps, total=Z.shape[0])
    for k in steps:
        t0 = time.perf_counter()
        Q = res.Q[-1]
        Y = forecast(Q, k)
        E = torch.randn(Y.shape, generator=generator, dtype=Y.dtype) * r[k].sqrt()
        Qa, info = analysis(Q, Y, Z[k], r[k], E)
        res.Q.append(Qa)
        res.info.append(info)
        if tracked is not None:
            res.Y_tracked.append(Y[:, tracked].clone())
        res.wall_s += time.perf_counter() - t0
        if checkpoint is not None:
            checkpoint(res, generator)
    return res


def hierarchical_filter(Q0, Y_fe, Z, r, generator, slave: str = "linear", degree: int | str = 3, R_q=None,
                        tracked=None) -> tuple[FilterResult, object]:
    """The paper's filter (``slave="linear"``, Eqs. 21-23) or its nonlinear-slave variant
    (``slave="polynomial"``). Y_fe (N, K, m) from the forward ensemble of Q0; no FE solve."""
    import time

    t0 = time.perf_counter()
    if slave == "linear":
        s = LinearSlave(Q0, Y_fe, R_q)
    elif slave == "polynomial":
        s = PolynomialSlave(Q0, Y_fe, degree)
    else:
        raise ValueError(f"slave must be 'linear' or 'polynomial', got {slave!r}")
    res = sequential_filter(Q0, lambda Q, k: s(Q, k, generator), Z, r, generator, tracked=tracked)
    res.wall_s = time.perf_counter() - t0
    return res, s


def innovation_flags(result: FilterResult, frames, alpha: float = 1e-4) -> dict:
    """Frames whose normalized innovation squared lies above its (1 - alpha) chi-square quantile with
    as many degrees of freedom as observed entries: there the forecast, with its spread and the
    noise, does not explain the recording (a model that stops fitting from some pressure on, a
    jump in the data, a noise level set too low). With a right model each frame is flagged with
    probability ~alpha. Returns {"alpha", "frames" (flagged frame indices), "first", "largest"
    NIS over its expectation)}."""
    from scipy.stats import chi2

    frames = np.asarray(frames)
    flagged, largest = [], 0.0
    for info, k in zip(result.info, frames):
        if info.m > 0:
            limit = chi2.isf(alpha, info.m) / info.m
            largest = max(largest, info.nis)
            if info.nis > limit:
                flagged.append(int(k))
    return {"alpha": alpha, "frames": flagged, "first": flagged[0] if flagged else None,
            "largest_nis_over_expectation": largest}


def summarize(q: torch.Tensor) -> dict[str, float]:
    """Mean, std and 10/90 % quantiles of physical parameter samples (N,)."""
    q = np.asarray(q, dtype=np.float64)
    return {"mean": float(q.mean()), "std": float(q.std(ddof=1)), "p10": float(np.quantile(q, 0.1)),
            "p90": float(np.quantile(q, 0.9))}

