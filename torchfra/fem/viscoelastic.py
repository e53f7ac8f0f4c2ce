"""Finite-strain viscoelasticity with history variables: Prony series on the isochoric stress.

The body's isochoric (shear) stress relaxes with the Abaqus Prony series (``*VISCOELASTIC,
TIME=PRONY`` with k_i = 0: the bulk response stays elastic),

    g_R(t) = 1 - sum_i g_i (1 - exp(-t / tau_i)),     g_i >= 0,  sum_i g_i < 1,

in the hereditary-integral form of Simo (1987) written in second Piola-Kirchhoff stresses:

    S(t) = g_inf S0(t) + sum_i g_i Q_i(t),    Q_i(t) = int_0^t exp(-(t - s) / tau_i) dS0(s),

with ``g_inf = 1 - sum_i g_i`` and ``S0`` the *instantaneous* Neo-Hookean isochoric stress,
``S0 = 2 C10_0 J^-2/3 (I - I1/3 C^-1)``. The base model's ``C10`` is the long-term modulus, so
``C10_0 = C10 / g_inf`` and ``g_inf S0`` is exactly the base body's isochoric stress: this term adds
only the overstress ``sum_i g_i Q_i``. Over a time increment ``dt`` with ``S0`` linear in time,

    Q_i(n+1) = exp(-x_i) Q_i(n) + beta_i (S0(n+1) - S0(n)),   x_i = dt / tau_i,
    beta_i = (1 - exp(-x_i)) / x_i,

so at the end of the increment the overstress is ``k S_iso(C10) + H`` with the scalar
``k = sum_i g_i beta_i / g_inf`` and the history tensor ``H = sum_i g_i (exp(-x_i) Q_i(n) - beta_i S0(n))``,
fixed during the increment. That is the stress of the pseudo-energy

    psi_v(F) = k C10 (I1bar - 3) + H : E,      E = (F^T F - I) / 2,

so the increment is solved by the same Newton as an elastic body, with ``P_v = k P_iso(C10) + F H``
and the tangent ``k A_iso + d_ik H_JL``. ``g_i = 0`` gives ``k = 0``, ``H = 0``: the base model (the
null). Limits (tests/test_viscoelastic_fe.py): steps much shorter than every ``tau_i`` give the
elastic body with ``C10 / g_inf`` (the instantaneous response), steps much longer give the base body;
a stretch applied in one short increment and held relaxes the stress as ``g_R(t)`` times the
instantaneous one (closed form).

History variables (``Q_i`` and ``S0`` at every Gauss point, per member) live in the term and are
advanced by :func:`solve_history`, which marches the model through a time trace of load factors
(loading, holds and unloading in any order). The elastic solve path (:func:`fem.solve`) never sees
this term, so the base model's cost is unchanged when viscoelasticity is off.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from torchfra.fem.kinematics import cofactor, deformation_gradient
from torchfra.fem.materials import NeoHookean
from torchfra.fem.model import Model
from torchfra.fem.newton import CONVERGED, DIVERGED, NewtonOptions, WarmStart, _Packing, solve
from torchfra.fem.params import ParameterError, ParameterInfo, check_parameters
from torchfra.fem.solid import Hex20Solid, _material_tangent, _nodal_forces
from torchfra.fem.terms import Term, TermOutput

HISTORY_ROW = "history_row"  # bookkeeping parameter: each member's row in the history store

G_INFO = ParameterInfo("g1", "1", 0.0, 0.0, 0.95,
                       "Prony relaxation fraction (Abaqus *VISCOELASTIC, TIME=PRONY, shear g_i); the "
                       "instantaneous shear modulus is the long-term one / (1 - sum g_i)")
TAU_INFO = ParameterInfo("tau1", "s", None, 0.0, math.inf,
                         "Prony relaxation time, in the time unit of the load trace", low_inclusive=False)


def prony_parameters(terms: int = 1) -> dict[str, ParameterInfo]:
    """Registry entries ``g1, tau1[, g2, tau2]`` of a Prony series with ``terms`` terms."""
    if terms not in (1, 2):
        raise ValueError(f"a Prony series of 1 or 2 terms is supported, got {terms}")
    out = {}
    for i in range(1, terms + 1):
        out[f"g{i}"] = G_INFO.renamed(f"g{i}")
        out[f"tau{i}"] = TAU_INFO.renamed(f"tau{i}")
    return out


def _beta(x: torch.Tensor) -> torch.Tensor:
    """``(1 - exp(-x)) / x``, 1 at x = 0."""
    return torch.where(x > 1e-12, -torch.expm1(-x) / torch.clamp(x, min=1e-12), 1.0 - 0.5 * x)


class ViscousOverstress(Term):
    """The relaxing part of a Neo-Hookean body's shear stress (module docstring): add it beside the
    body's :class:`Hex20Solid` (same elements), then solve with :func:`solve_history`.

    Parameters: the body's long-term ``C10`` (shared with the solid) and ``g1, tau1`` (``g2, tau2``
    with ``terms=2``). A morphed body (per-member geometry) is not supported.
    """

    kind = "internal"
    conservative = True

    def __init__(self, solid: Hex20Solid, terms: int = 1):
        if not isinstance(solid.material, NeoHookean):
            raise ValueError("ViscousOverstress relaxes a Neo-Hookean body's shear stress; the body's material "
                             f"is {type(solid.material).__name__}")
        self.solid = solid
        self.n_terms = terms
        self.parameters = prony_parameters(terms)
        self.param_names = ("C10",) + tuple(self.parameters)
        self.dofs = solid.dofs
        self.conn = solid.conn
        self._dt = None
        self._Q = self._S0 = None  # (rows, E, G, 3, 3) per Prony term / shared

    # -- parameters ----------------------------------------------------------------------------
    def validate(self, params):
        if self.solid.morph_names:
            raise ValueError("ViscousOverstress does not support a morphed body (per-member geometry)")
        check_parameters(self.parameters, params, "viscoelasticity")
        total = sum(params[f"g{i}"] for i in range(1, self.n_terms + 1))
        if (total > 0.95).any():
            m = int(torch.nonzero(total > 0.95)[0, 0])
            raise ParameterError(f"the Prony fractions of member {m} add up to {float(total[m]):.4g}; "
                                 "sum g_i must stay <= 0.95 (a long-term modulus of at least 5 % of the "
                                 "instantaneous one)")

    def _g(self, params):
        return [params[f"g{i}"] for i in range(1, self.n_terms + 1)], \
               [params[f"tau{i}"] for i in range(1, self.n_terms + 1)]

    # -- history ---------------------------------------------------------------------------------
    def reset(self, N: int, dtype=torch.float64) -> None:
        """Every member at rest (no history), N rows."""
        self._dt = None
        E, G = self.solid.wdet.shape
        self._S0 = torch.zeros(N, E, G, 3, 3, dtype=dtype)
        self._Q = [torch.zeros(N, E, G, 3, 3, dtype=dtype) for _ in range(self.n_terms)]

    def begin_increment(self, dt: float) -> None:
        """Evaluate the end state of a time increment of ``dt`` from the last commit (until the next commit)."""
        if not dt > 0:
            raise ValueError(f"a time increment must be positive, got {dt}")
        self._dt = float(dt)

    def _rows(self, params):
        if HISTORY_ROW not in params:
            raise ValueError(f"ViscousOverstress needs the bookkeeping parameter '{HISTORY_ROW}' "
                             "(solve the model with fem.solve_history)")
        return params[HISTORY_ROW].round().long()

    def _coefficients(self, params):
        """``k`` (N,) and ``H`` (N, E, G, 3, 3) of the current increment; between a commit and the next
        increment, ``k = 0`` and ``H`` = the committed overstress (so nodal forces are the reactions)."""
        if self._S0 is None:
            raise RuntimeError("ViscousOverstress has no history: solve the model with fem.solve_history")
        rows = self._rows(params)
        g, tau = self._g(params)
        if self._dt is None:
            return torch.zeros_like(g[0]), self.overstress(params)
        g_inf = 1.0 - sum(g)
        k = torch.zeros_like(g_inf)
        H = torch.zeros_like(self._S0[rows])
        S0 = self._S0[rows]
        for gi, ti, Qi in zip(g, tau, self._Q):
            x = self._dt / ti
            b = _beta(x)
            k = k + gi * b
            H = H + gi[:, None, None, None, None] * (torch.exp(-x)[:, None, None, None, None] * Qi[rows]
                                                     - b[:, None, None, None, None] * S0)
        return k / g_inf, H

    def instantaneous_stress(self, u, params) -> torch.Tensor:
        """``S0``: the instantaneous isochoric 2nd Piola-Kirchhoff stress at the Gauss points, (N, E, G, 3, 3)."""
        F = deformation_gradient(u[:, self.conn], self.solid.dN_dX)
        g, _ = self._g(params)
        C10_0 = params["C10"] / (1.0 - sum(g))
        return _isochoric_pk2(F, C10_0)

    def commit(self, u, params) -> None:
        """Advance the history of the members in ``params[HISTORY_ROW]`` to their converged state ``u``
        at the end of the current increment."""
        rows = self._rows(params)
        S1 = self.instantaneous_stress(u, params)
        _, tau = self._g(params)
        for i, ti in enumerate(tau):
            x = self._dt / ti
            decay, b = torch.exp(-x)[:, None, None, None, None], _beta(x)[:, None, None, None, None]
            self._Q[i][rows] = decay * self._Q[i][rows] + b * (S1 - self._S0[rows])
        self._S0[rows] = S1

    def end_increment(self) -> None:
        """After the commits of an increment: evaluations see the committed state (``k = 0``)."""
        self._dt = None

    def overstress(self, params) -> torch.Tensor:
        """``sum_i g_i Q_i`` at the Gauss points of the members in ``params[HISTORY_ROW]`` (N, E, G, 3, 3)
        after the last commit: the viscous part of the 2nd Piola-Kirchhoff stress."""
        rows = self._rows(params)
        g, _ = self._g(params)
        return sum(gi[:, None, None, None, None] * Qi[rows] for gi, Qi in zip(g, self._Q))

    # -- evaluation ------------------------------------------------------------------------------
    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N = u.shape[0]
        k, H = self._coefficients(params)
        dN, w = self.solid.dN_dX, self.solid.wdet
        F = deformation_gradient(u[:, self.conn], dN)
        ok = torch.ones(N, dtype=torch.bool)
        kC = (k * params["C10"])[:, None, None]
        iso = NeoHookean(fast=True).derivatives(F, torch.zeros(F.shape[:-2], dtype=F.dtype),
                                                {"C10": kC, "D1": torch.ones_like(kC)}, with_energy=energy,
                                                tangent=tangent)
        P = iso.P + F @ H
        fe = _nodal_forces(dN, w, P)
        psi = None
        if energy:
            E_gl = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(3, dtype=F.dtype))
            psi = torch.einsum("eg,neg->n", w, iso.psi + (H * E_gl).sum((-1, -2)))
        Ke = None
        if tangent:
            Ke = _material_tangent(iso.A, w, dN)
            # d_ik H_JL: a scalar nodal matrix sum_g w dN_aJ H_JL dN_bL on the three diagonal blocks
            nodal = torch.einsum("eg,egaj,negjl,egbl->neab", w, dN, H, dN)
            Ke6 = Ke.view(N, -1, 20, 3, 20, 3)
            for i in range(3):
                Ke6[:, :, :, i, :, i] += nodal
        return TermOutput(fe, Ke, psi, ok)


def _isochoric_pk2(F: torch.Tensor, C10: torch.Tensor) -> torch.Tensor:
    """``2 C10 J^-2/3 (I - I1/3 C^-1)`` at Gauss points; C10 (N,)."""
    cof = cofactor(F)
    J = (F * cof).sum((-1, -2)) / 3.0
    Finv = cof.transpose(-1, -2) / J[..., None, None]
    Cinv = Finv @ Finv.transpose(-1, -2)
    I1 = (F * F).sum((-1, -2))
    c = 2.0 * C10[:, None, None] * J ** (-2.0 / 3.0)
    eye = torch.eye(3, dtype=F.dtype)
    return c[..., None, None] * (eye - (I1 / 3.0)[..., None, None] * Cinv)


def with_viscoelasticity(model: Model, terms: int = 1) -> ViscousOverstress:
    """Add the relaxing overstress of the model's (first) Neo-Hookean body to an unfinalized model."""
    if model.dofmap is not None:
        raise RuntimeError("the model is finalized; add viscoelasticity before the first solve")
    solids = [t for t in model.terms if isinstance(t, Hex20Solid) and isinstance(t.material, NeoHookean)]
    if not solids:
        raise ValueError("the model has no Neo-Hookean Hex20 body to make viscoelastic")
    return model.add(ViscousOverstress(solids[0], terms))


@dataclass
class HistorySolution:
    """Results of a time-stepped solve at the trace's points.

    times, load_factors (T,); u (N, T, n_nodes, 3) (NaN where a member did not get there); status (N,);
    time_reached (N,); increments, iterations (N,); timings; u_start (N, n_nodes, 3).
    """

    times: np.ndarray
    load_factors: np.ndarray
    u: torch.Tensor
    status: np.ndarray
    time_reached: np.ndarray
    increments: np.ndarray
    iterations: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    u_start: torch.Tensor | None = None  # (N, n_nodes, 3): the relaxed state the march starts from

    @property
    def converged(self) -> np.ndarray:
        return self.status == CONVERGED


def time_increments(times, load_factors, max_dt: float | None = None, max_dlam: float = 0.1, t0: float = 0.0,
                    lam0: float = 0.0, dt_free_dlam: float | None = None):
    """The increments of a trace starting at rest at ``t0``, ``lam0`` (default 0, 0): every interval
    between trace points split evenly so that no step is longer than ``max_dt`` nor changes the load
    factor by more than ``max_dlam``. With ``dt_free_dlam``, an interval split into steps that change
    the load factor by at most ``dt_free_dlam`` each needs no more for ``max_dt``: the history's
    exponential recurrence is exact for a stress linear in time over a step of any length, so a long
    step errs only by the stress's curvature over its load increment (a hold, whose stress is
    constant, is one exact step). Returns (times, load factors, index of the trace point each step
    ends at or -1)."""
    if np.asarray(times).size == 0:
        raise ValueError("a load trace needs at least one (time, load factor) point after its start")
    t = np.concatenate([[float(t0)], np.asarray(times, dtype=np.float64)])
    lam = np.concatenate([[float(lam0)], np.asarray(load_factors, dtype=np.float64)])
    if t.ndim != 1 or lam.shape != t.shape:
        raise ValueError("times and load_factors must be 1-D and of the same length")
    if not (np.isfinite(t).all() and np.isfinite(lam).all()):
        raise ValueError("times and load factors must be finite")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise ValueError(f"trace point {k} is at time {t[k + 1]!r}, not after the previous one ({t[k]!r}); times "
                         f"must increase strictly from {t[0]:g} (the body at rest)")
    if np.any(np.abs(lam) > 1 + 1e-12):
        raise ValueError("load factors must lie in [-1, 1]")
    ts, ls, ends = [], [], []
    for k in range(t.size - 1):
        dt, dl = t[k + 1] - t[k], lam[k + 1] - lam[k]
        n = max(1, int(math.ceil(abs(dl) / max_dlam - 1e-9)))
        if max_dt is not None:
            by_time = int(math.ceil(dt / max_dt - 1e-9))
            if dt_free_dlam is not None:
                by_time = min(by_time, max(1, int(math.ceil(abs(dl) / dt_free_dlam - 1e-9))))
            n = max(n, by_time)
        for j in range(1, n + 1):
            ts.append(t[k] + dt * j / n)
            ls.append(lam[k] + dl * j / n)
            ends.append(k if j == n else -1)
    return np.array(ts), np.array(ls), np.array(ends)


def solve_history(model: Model, params: dict[str, torch.Tensor], times, load_factors,
                  max_dt: float | None = None, max_dlam: float = 0.1, options: NewtonOptions | None = None,
                  progress: bool | str = False, t0: float = 0.0, relaxed_at: float = 0.0,
                  dt_free_dlam: float | None = None) -> HistorySolution:
    """March ``model`` through the load trace ``(times, load_factors)`` for every member (params: name
    -> (N,)), advancing the history of every :class:`ViscousOverstress` after each converged
    increment. The body starts at time ``t0`` fully relaxed under the load factor ``relaxed_at``
    (default: unloaded at t = 0): the long-term elastic equilibrium there, no overstress
    (``HistorySolution.u_start``). ``max_dt`` defaults to a quarter of the smallest relaxation time;
    ``dt_free_dlam`` exempts load steps that small from it (:func:`time_increments`).

    Each increment is one Newton solve warm-started from the previous state (cutbacks inside it only
    continue the load; the history of the increment is that of its full time step). A member that
    fails an increment stops there (status "diverged"); the others go on."""
    model.finalize()
    dtype = model.dtype
    params = {k: torch.as_tensor(v, dtype=dtype).reshape(-1) for k, v in params.items()}
    N = model.validate({**params, HISTORY_ROW: torch.zeros(len(next(iter(params.values()))), dtype=dtype)})
    visc = [t for t in model.terms if isinstance(t, ViscousOverstress)]
    if max_dt is None and visc:
        max_dt = 0.25 * min(float(params[f"tau{i}"].min()) for v in visc for i in range(1, v.n_terms + 1))
    if not 0.0 <= relaxed_at <= 1.0:
        raise ValueError(f"relaxed_at is a load factor in [0, 1], got {relaxed_at!r}")
    if dt_free_dlam is not None and not 0.0 < dt_free_dlam <= max_dlam:
        raise ValueError(f"dt_free_dlam must lie in (0, max_dlam = {max_dlam:g}], got {dt_free_dlam!r}")
    ts, ls, ends = time_increments(times, load_factors, max_dt, max_dlam, t0, relaxed_at, dt_free_dlam)
    T = int((ends >= 0).sum())
    out_index = np.cumsum(ends >= 0) - 1
    for v in visc:
        v.reset(N, dtype)
    opt = options or NewtonOptions()
    x = torch.zeros(N, _Packing(model).size, dtype=dtype)
    u_start = torch.zeros(N, model.n_nodes, 3, dtype=dtype)
    status = np.array([CONVERGED] * N, dtype=object)
    if relaxed_at > 0:  # the long-term body (no overstress before the first commit) at the starting load
        first = solve(model, {**params, HISTORY_ROW: torch.arange(N, dtype=dtype)}, [relaxed_at], opt)
        status[~first.converged] = DIVERGED
        x = torch.nan_to_num(first.x_last)
        u_start = first.u[:, 0]
        for v in visc:
            v._S0 = torch.nan_to_num(v.instantaneous_stress(torch.nan_to_num(u_start), params))
    opt = NewtonOptions(**{**opt.__dict__, "initial_increment": 1.0})
    u_out = torch.full((N, T, model.n_nodes, 3), float("nan"), dtype=dtype)
    t_reached, iterations = np.full(N, float(t0)), np.zeros(N, dtype=np.int64)
    increments = np.zeros(N, dtype=np.int64)
    timings = {"newton": 0.0, "history": 0.0}
    t_prev, l_prev = float(t0), float(relaxed_at)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        label = progress if isinstance(progress, str) else f"viscoelastic trace, {N} member{'s' if N > 1 else ''}"
        bar = tqdm(total=len(ts), desc=label, unit="step",
                   bar_format="{l_bar}{bar}| {n}/{total} steps [{elapsed} elapsed, ~{remaining} left]")
    for t1, l1, end, out in zip(ts, ls, ends, out_index):
        live = np.flatnonzero(status == CONVERGED)
        if live.size == 0:
            break
        for v in visc:
            v.begin_increment(t1 - t_prev)
        sub = {k: v[live] for k, v in params.items()}
        sub[HISTORY_ROW] = torch.as_tensor(live, dtype=dtype)
        t0 = time.perf_counter()
        sol = solve(model, sub, [1.0], opt, start=WarmStart(x[live], np.full(live.size, l_prev),
                                                                np.full(live.size, l1)))
        timings["newton"] += time.perf_counter() - t0
        iterations[live] += sol.iterations
        ok = sol.converged
        status[live[~ok]] = DIVERGED
        good = live[ok]
        if good.size:
            t0 = time.perf_counter()
            x[good] = sol.x_last[ok]
            u1 = sol.u[ok, 0]
            for v in visc:
                v.commit(u1, {**{k: val[good] for k, val in params.items()},
                              HISTORY_ROW: torch.as_tensor(good, dtype=dtype)})
            timings["history"] += time.perf_counter() - t0
            t_reached[good], increments[good] = t1, increments[good] + 1
            if end >= 0:
                u_out[good, out] = u1
        for v in visc:
            v.end_increment()
        t_prev, l_prev = t1, l1
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return HistorySolution(np.asarray(times, dtype=np.float64), np.asarray(load_factors, dtype=np.float64), u_out,
                           status.astype(str), t_reached, increments, iterations, timings, u_start)
