"""Newton-Raphson with load stepping for N members at once.

Every member has its own load path: its own increment, cutbacks and status; all members still
iterate in lockstep so element kernels run batched over (member x element). A member that fails
after its cutbacks is reported (status, load reached, last residual) while the others finish.

Convergence of an increment (both must hold):
  force:  ||r||_2 <= rtol * f_scale + atol,  f_scale = largest norm of one term's nodal forces
          (so reactions count for displacement-driven problems);
  energy: |da_k . r_k| <= etol * E_ref,  E_ref = max(|da_0 . r_0|, f_scale * ||a - a_conv||), the
          work scale of the increment (skipped when the predictor already satisfies force).
Round-off floor: the attainable relative residual grows with the bulk/shear ratio (~1e-9 at
K/mu = 2e6); an iterate whose relative residual is below ``stagnation_tol`` and no longer falls
(by 2x per iteration, where Newton would square it) is accepted as converged to that floor.
Divergence (cut the increment by ``cutback`` and retry from the last converged state): a
non-finite residual, an inadmissible state (det F <= 0) after line search, a singular tangent,
or no convergence within ``max_iterations``.

Reference state: a model with preloads (``Term.preload``: the weight in a DIC recording's reference
image) is first settled under them alone, member by member, and the load path then starts from that
state (``Solution.u_reference``), with the preloads held in full.

Cost: all members' tangents share one sparsity pattern, so one :class:`SparseSolver` serves the
whole solve (PARDISO analyses the pattern once), factorizing symmetric tangents as such; the
tangent is evaluated together with the residual for iterates that will most likely take a step
(``tangent_hint``), which saves the second evaluation without changing any iterate.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from torchfra.fem.linsolve import SingularMatrixError, SparseSolver
from torchfra.fem.model import Evaluation, Model


@dataclass
class NewtonOptions:
    rtol: float = 1e-9
    atol: float = 1e-14
    etol: float = 1e-16
    max_iterations: int = 15
    initial_increment: float = 0.1
    min_increment: float = 1e-5
    max_increment: float = 1.0
    growth: float = 1.5
    easy_iterations: int = 4
    cutback: float = 0.25
    stagnation_tol: float = 1e-7
    line_search_steps: int = 4
    linear_solver: str = "auto"  # "superlu", "pardiso" (optional extra) or "auto" (pardiso if installed)
    line_search_growth: float = 1e6  # backtrack when ||r|| grows more than this (near-incompressible
    # Newton steps legitimately raise ||r|| by orders of magnitude before converging quadratically)
    tangent_hint: float = 1e-5  # evaluate the tangent with the residual when the member's last relative
    # residual exceeds this (its next iterate will most likely need a step): one evaluation, not two
    member_budget: int = 0  # Newton iterations one member may spend in all (0: no limit); a member
    # that uses them up before the last load factor stops there, "diverged", and the others go on
    member_seconds: float = 0.0  # wall seconds of this solve a member may take (0: no limit); the
    # members of a batch advance together, so one still short of its last load factor after that long
    # stops where it is, "diverged", at the next iteration it does not converge
    reuse_factorization: bool = True  # near convergence (last relative residual below tangent_hint),
    # a member steps with its factorization from earlier in the same increment instead of a new
    # tangent (modified Newton), while each such step cuts the residual by reuse_contraction; the
    # convergence test is the same, so is the answer to its tolerance. Each member then holds its
    # own factorization: batches of more than REUSE_MAX_MEMBERS take a new tangent every step
    reuse_contraction: float = 0.1


REUSE_MAX_MEMBERS = 8


CONVERGED, DIVERGED = "converged", "diverged"


@dataclass
class Solution:
    """Results at the requested load factors.

    u: (N, T, n_nodes, 3) displacements (NaN where a member did not reach that load);
    a: (N, T, n_red) reduced unknowns; status (N,): "converged" / "diverged";
    load_reached (N,); iterations, increments, cutbacks (N,); last_residual (N,): the last finite
    relative residual (NaN marks inadmissible states in ``residual_history``);
    residual_history: per member, the relative residual of every Newton iteration;
    iterations_per_output (N, T): Newton iterations spent from the previous output load factor to
    this one (-1 where not reached). ``a`` ends with 6 unknowns per rigid body (translation, rotation
    vector): ``Model.rigid_motion`` reads them.
    """

    load_factors: np.ndarray
    u: torch.Tensor
    a: torch.Tensor
    status: np.ndarray
    load_reached: np.ndarray
    iterations: np.ndarray
    increments: np.ndarray
    cutbacks: np.ndarray
    last_residual: np.ndarray
    residual_history: list[list[float]]
    timings: dict[str, float] = field(default_factory=dict)
    x_last: torch.Tensor | None = None  # (N, size) packed state [a, element pressures] at the last load
    iterations_per_output: np.ndarray | None = None
    u_reference: torch.Tensor | None = None  # (N, n_nodes, 3) the settled reference state of a model with
    # preloads (its weight before the load path), from which the path starts; None without preloads
    a_reference: torch.Tensor | None = None  # (N, n_red) its reduced unknowns
    x_reference: torch.Tensor | None = None  # (N, size) its packed state

    @property
    def converged(self) -> np.ndarray:
        return self.status == CONVERGED


def _members(params, idx):
    return {k: v[idx] for k, v in params.items()}


class _Packing:
    """Per-member state vector ``x = [a, local unknowns of every term (flattened)]``, so that
    predictors, cutbacks and line search treat displacements and element pressures alike."""

    def __init__(self, model: Model):
        self.n = model.n_red
        self.shapes = [(t.dofs.shape[0], t.n_local) if t.n_local else None for t in model.terms]
        self.size = self.n + sum(b * l for b, l in filter(None, self.shapes))

    def split(self, x: torch.Tensor):
        local, i = [], self.n
        for shape in self.shapes:
            if shape is None:
                local.append(None)
            else:
                local.append(x[:, i : i + shape[0] * shape[1]].reshape(x.shape[0], *shape))
                i += shape[0] * shape[1]
        return x[:, : self.n], local

    def join(self, a: torch.Tensor, local) -> torch.Tensor:
        return torch.cat([a] + [l.reshape(a.shape[0], -1) for l in local if l is not None], dim=1)


@dataclass
class WarmStart:
    """Continue from equilibrium states: packed states x (N, size) (``Solution.x_last``) reached at
    load factors ``lam0`` (N,), towards ``lam1`` (N,); the solve's load factors then run along
    lam0 + mu (lam1 - lam0), mu in (0, 1]. Parameters may differ from those that made x (the restart
    filter changes them); the first increment absorbs the change. lam1 < lam0 unloads. ``predict``:
    the first increment's predictor is the Euler step ``-K^-1 dr/dlambda`` at x (an equilibrium of
    these parameters, e.g. the settled reference state) instead of x itself."""

    x: torch.Tensor
    lam0: np.ndarray
    lam1: np.ndarray
    predict: bool = False


def solve(
    model: Model,
    params: dict[str, torch.Tensor],
    load_factors=(1.0,),
    options: NewtonOptions | None = None,
    progress: bool | str = False,
    start: WarmStart | None = None,
) -> Solution:
    """Solve ``model`` for every member (params: name -> (N,)) at the given load factors in (0, 1]
    (fractions of the path from ``start``, when given, else from the reference state: the unloaded
    body, or for a model with preloads the body settled under them, ``Solution.u_reference``).

    A member whose settling fails is reported diverged (load reached 0, NaN states)."""
    model.finalize()
    if start is not None or not model.has_preload or model.is_settling:
        return _solve_path(model, params, load_factors, options, progress, start)
    params = {k: torch.as_tensor(v, dtype=model.dtype).reshape(-1) for k, v in params.items()}
    N = model.validate(params)
    with model.settling():  # no member carries a preload (e.g. a density of 0): the path from the unloaded body
        weightless = not model.evaluate(torch.zeros(N, model.n_red, dtype=model.dtype), params,
                                        torch.ones(N, dtype=model.dtype)).residual.abs().max() > 0
    if weightless:
        sol = _solve_path(model, params, load_factors, options, progress, start)
        sol.u_reference = torch.zeros(N, model.n_nodes, 3, dtype=model.dtype)
        sol.a_reference = torch.zeros(N, model.n_red, dtype=model.dtype)
        return sol
    label = False
    if progress:
        label = "settling under the preloads (weight)" if progress is True else f"{progress}: settling"
    with model.settling():
        ref = _solve_path(model, params, (1.0,), options, label)
    settled = torch.as_tensor(ref.converged)
    x0 = torch.where(settled[:, None], torch.nan_to_num(ref.x_last), torch.zeros_like(ref.x_last))
    sol = _solve_path(model, params, load_factors, options, progress,
                      WarmStart(x0, np.zeros(N), np.ones(N), predict=True))
    if not settled.all():
        bad = ~settled
        sol.u[bad], sol.a[bad] = float("nan"), float("nan")
        if sol.x_last is not None:
            sol.x_last[bad] = float("nan")
        sol.status[bad.numpy()] = DIVERGED
        sol.load_reached[bad.numpy()] = 0.0
    sol.iterations = sol.iterations + ref.iterations
    sol.timings = {k: sol.timings.get(k, 0.0) + ref.timings.get(k, 0.0) for k in set(sol.timings) | set(ref.timings)}
    sol.u_reference, sol.a_reference, sol.x_reference = ref.u[:, 0], ref.a[:, 0], ref.x_last
    return sol


def _solve_path(
    model: Model,
    params: dict[str, torch.Tensor],
    load_factors=(1.0,),
    options: NewtonOptions | None = None,
    progress: bool | str = False,
    start: WarmStart | None = None,
) -> Solution:
    """The load path of :func:`solve`, from ``start`` or from the unloaded state."""
    opt = options or NewtonOptions()
    model.finalize()
    dtype = model.dtype
    params = {k: torch.as_tensor(v, dtype=dtype).reshape(-1) for k, v in params.items()}
    N = model.validate(params)
    outs = np.unique(np.asarray(load_factors, dtype=np.float64))
    if outs.size == 0 or outs[0] <= 0 or outs[-1] > 1 + 1e-12:
        raise ValueError(f"load factors must lie in (0, 1], got {load_factors}")
    T, n = outs.size, model.n_red
    pack = _Packing(model)
    timings = {"residual": 0.0, "tangent": 0.0, "solve": 0.0}
    t_start = time.perf_counter()

    x = torch.zeros(N, pack.size, dtype=dtype)
    x_conv, x_prev = x.clone(), x.clone()
    lam_conv, lam_prev = np.zeros(N), np.zeros(N)
    lam_prev2, x_prev2 = np.full(N, np.nan), x.clone()  # a third converged state: quadratic predictor
    dlam = np.full(N, opt.initial_increment)
    nxt = np.zeros(N, dtype=np.int64)
    lam = np.minimum(dlam, outs[0])
    it = np.zeros(N, dtype=np.int64)
    E0, de = np.zeros(N), np.zeros(N)
    active = np.ones(N, dtype=bool)
    status = np.array([CONVERGED] * N, dtype=object)
    iterations, increments, cutbacks = np.zeros(N, int), np.zeros(N, int), np.zeros(N, int)
    at_output = np.full((N, T), -1, dtype=np.int64)  # cumulative iterations when each output was reached
    last_res = np.full(N, np.nan)
    history: list[list[float]] = [[] for _ in range(N)]
    a_out = torch.full((N, T, n), float("nan"), dtype=dtype)
    x_last = torch.full((N, pack.size), float("nan"), dtype=dtype)

    if start is None:
        lam0, lam1 = np.zeros(N), np.ones(N)
    else:
        lam0 = np.broadcast_to(np.asarray(start.lam0, dtype=np.float64), (N,)).copy()
        lam1 = np.broadcast_to(np.asarray(start.lam1, dtype=np.float64), (N,)).copy()
        if tuple(start.x.shape) != (N, pack.size):
            raise ValueError(f"warm start states must be ({N}, {pack.size}), got {tuple(start.x.shape)}")

    def load(idx, mu):  # model load factor along the path
        return torch.as_tensor(lam0[idx] + mu * (lam1[idx] - lam0[idx]), dtype=dtype)

    def evaluate(idx, xx, tangent=False):
        t0 = time.perf_counter()
        aa, local = pack.split(xx)
        ev = model.evaluate(aa, _members(params, idx), load(idx, lam[idx]), tangent=tangent, local=local)
        timings["tangent" if tangent else "residual"] += time.perf_counter() - t0
        return ev

    def evaluate_iterates(idx):
        """Residuals of the iterates of ``idx``, with tangents (member -> matrix) for those that will
        most likely take a Newton step: the start of an increment, or a residual still far from
        converged (quadratic convergence squares it)."""
        hint = np.array([it[m] == 0 or rel_prev[m] > opt.tangent_hint for m in idx])
        if hint.all() or not hint.any():
            ev = evaluate(idx, x[idx], tangent=bool(hint.any()))
            return ev, dict(zip(idx.tolist(), ev.tangents)) if hint.any() else {}
        with_t, without = evaluate(idx[hint], x[idx[hint]], tangent=True), evaluate(idx[~hint], x[idx[~hint]])
        merged = {}
        for name in ("residual", "force_scale", "ok", "rhs"):
            a, b = getattr(with_t, name), getattr(without, name)
            out = torch.empty((idx.size,) + tuple(a.shape[1:]), dtype=a.dtype)
            out[torch.as_tensor(hint)], out[torch.as_tensor(~hint)] = a, b
            merged[name] = out
        return Evaluation(**merged), dict(zip(idx[hint].tolist(), with_t.tangents))

    def predictor(m):
        if np.isfinite(lam_prev2[m]) and lam_prev[m] > lam_prev2[m]:  # quadratic through the last three
            l0, l1, l2, t = lam_prev2[m], lam_prev[m], lam_conv[m], lam[m]
            w0 = (t - l1) * (t - l2) / ((l0 - l1) * (l0 - l2))
            w1 = (t - l0) * (t - l2) / ((l1 - l0) * (l1 - l2))
            w2 = (t - l0) * (t - l1) / ((l2 - l0) * (l2 - l1))
            return w0 * x_prev2[m] + w1 * x_prev[m] + w2 * x_conv[m]
        return x_conv[m] + (lam[m] - lam_conv[m]) * velocity[m]

    def cut(m):
        cutbacks[m] += 1
        step = opt.cutback * (lam[m] - lam_conv[m])
        if step < opt.min_increment:
            status[m], active[m] = DIVERGED, False
            return
        dlam[m], lam[m], it[m] = step, lam_conv[m] + step, 0
        ls_pending[m] = False
        x[m] = predictor(m)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        label = progress if isinstance(progress, str) else f"Newton, {N} member{'s' if N > 1 else ''}"
        bar = tqdm(total=100, desc=label, unit="% load",
                   bar_format="{l_bar}{bar}| {n:.0f}/{total}% load [{elapsed} elapsed, ~{remaining} left]")

    if start is None:
        # Euler predictor for the first increment: dx/dlambda = -K^-1 dr/dlambda at the unloaded state.
        velocity = _euler_velocity(model, pack, params, dtype, opt.linear_solver)
        x = torch.as_tensor(lam, dtype=dtype)[:, None] * velocity
    else:  # the previous equilibrium (or its Euler step) is the first predictor
        x = start.x.to(dtype).clone()
        x_conv, x_prev = x.clone(), x.clone()
        if start.predict:
            velocity = _euler_velocity(model, pack, params, dtype, opt.linear_solver, x0=x,
                                       lam0=torch.as_tensor(lam0, dtype=dtype))
            velocity = velocity * torch.as_tensor(lam1 - lam0, dtype=dtype)[:, None]
            x = x + torch.as_tensor(lam, dtype=dtype)[:, None] * velocity
        else:
            velocity = torch.zeros(N, pack.size, dtype=dtype)
    # one solver for every member and iteration: the tangents share one sparsity pattern
    linear = SparseSolver(opt.linear_solver, model.symmetric_tangent)
    ls_base, ls_dx = torch.zeros_like(x), torch.zeros_like(x)
    ls_alpha, ls_count = np.ones(N), np.zeros(N, dtype=np.int64)
    ls_pending, r_prev, rel_prev = np.zeros(N, dtype=bool), np.zeros(N), np.full(N, np.inf)
    # modified Newton near convergence: each member's own solver, the increment its factorization
    # is from (-1: none), whether its last step reused it, and whether reusing stopped contracting
    reusing = opt.reuse_factorization and N <= REUSE_MAX_MEMBERS
    solvers = [SparseSolver(opt.linear_solver, model.symmetric_tangent) for _ in range(N)] if reusing else None
    held_increment = np.full(N, -1, dtype=np.int64)
    modified, poor = np.zeros(N, dtype=bool), np.zeros(N, dtype=bool)
    idx = np.flatnonzero(active)
    while idx.size:
        ev, tangents_at = evaluate_iterates(idx)
        rnorm = torch.maximum(torch.linalg.norm(ev.residual, dim=1), torch.linalg.norm(ev.rhs, dim=1)).numpy()
        scale = ev.force_scale.numpy()
        rel = rnorm / np.maximum(scale, 1e-300)
        ok = ev.ok.numpy() & np.isfinite(rnorm)
        force_ok = rnorm <= opt.rtol * scale + opt.atol
        need = []
        for j, m in enumerate(idx):
            if ls_pending[m]:
                # line search: back off while the trial state is inadmissible or the residual blew up
                if (not ok[j] or rnorm[j] > opt.line_search_growth * r_prev[m]) and ls_count[m] < opt.line_search_steps:
                    ls_alpha[m] *= 0.5
                    ls_count[m] += 1
                    x[m] = ls_base[m] + ls_alpha[m] * ls_dx[m]
                    continue
                ls_pending[m] = False
            history[m].append(float(rel[j]))
            if np.isfinite(rel[j]):
                last_res[m] = rel[j]
            E_ref = max(E0[m], scale[j] * float(torch.linalg.norm(x[m, :n] - x_conv[m, :n])))
            energy_ok = it[m] == 0 or de[m] <= opt.etol * E_ref
            if modified[m] and not rel[j] <= opt.reuse_contraction * rel_prev[m]:
                poor[m] = True  # the held factorization no longer contracts: a new tangent next
            # a slow modified step is no round-off floor: only full Newton steps may stagnate
            stagnated = (it[m] > 0 and not modified[m] and rel[j] < opt.stagnation_tol
                         and rel[j] > 0.5 * rel_prev[m])
            rel_prev[m] = rel[j]
            if ok[j] and ((force_ok[j] and energy_ok) or stagnated):
                increments[m] += 1
                lam_prev2[m], x_prev2[m] = lam_prev[m], x_prev[m]
                lam_prev[m], lam_conv[m] = lam_conv[m], lam[m]
                x_prev[m], x_conv[m] = x_conv[m], x[m].clone()
                velocity[m] = (x_conv[m] - x_prev[m]) / (lam_conv[m] - lam_prev[m])
                if lam[m] == outs[nxt[m]]:
                    a_out[m, nxt[m]] = x[m, :n]
                    at_output[m, nxt[m]] = iterations[m]
                    nxt[m] += 1
                    if nxt[m] == T:
                        x_last[m] = x[m]
                        active[m] = False
                        continue
                if it[m] <= opt.easy_iterations:
                    dlam[m] = min(dlam[m] * opt.growth, opt.max_increment)
                lam[m] = min(lam_conv[m] + dlam[m], outs[nxt[m]])
                it[m] = 0
                x[m] = predictor(m)
            elif ((opt.member_budget and iterations[m] >= opt.member_budget)
                  or (opt.member_seconds and time.perf_counter() - t_start >= opt.member_seconds)):
                status[m], active[m] = DIVERGED, False  # its budget is spent: the load it reached stands
            elif not ok[j] or it[m] >= opt.max_iterations:
                cut(m)
            else:
                need.append(m)
                r_prev[m] = rnorm[j]
        if need:
            need = np.asarray(need)
            rhs = ev.rhs[np.searchsorted(idx, need)]  # condensed residuals at the iterates
            reuse = {m for m in need if reusing and m not in tangents_at and held_increment[m] == increments[m]
                     and it[m] > 0 and not poor[m]}
            missing = np.array([m for m in need if m not in tangents_at and m not in reuse], dtype=np.int64)
            if missing.size:  # the hint was wrong for these: evaluate their tangents now
                tangents_at.update(zip(missing.tolist(), evaluate(missing, x[missing], tangent=True).tangents))
            t0 = time.perf_counter()
            da = torch.full((need.size, n), float("nan"), dtype=dtype)
            for j, m in enumerate(need):
                modified[m] = m in reuse
                solver = solvers[m] if reusing else linear
                try:
                    if not modified[m]:
                        held_increment[m] = -1
                        solver.factorize(tangents_at[m])
                        held_increment[m], poor[m] = increments[m], False
                    da[j] = torch.as_tensor(solver.solve(-rhs[j].numpy()))
                except SingularMatrixError:  # the member is cut back below
                    pass
            timings["solve"] += time.perf_counter() - t0
            a_need, local_need = pack.split(x[need])
            good = torch.isfinite(da).all(dim=1)
            da_safe = torch.where(good[:, None], da, torch.zeros_like(da))
            new_local = model.local_update(a_need, da_safe, _members(params, need), load(need, lam[need]), local_need)
            dx = pack.join(da_safe, [None if l is None else nl - l for nl, l in zip(new_local, local_need)])
            for j, m in enumerate(need):
                dot = abs(float(da_safe[j] @ rhs[j]))
                if it[m] == 0:
                    E0[m] = dot
                de[m] = dot
                it[m] += 1
                iterations[m] += 1
                if not good[j]:
                    cut(m)
                    continue
                ls_base[m], ls_dx[m], ls_alpha[m], ls_count[m] = x[m], dx[j], 1.0, 0
                ls_pending[m] = True
                x[m] = x[m] + dx[j]
        if bar is not None:
            act = np.flatnonzero(active)
            done = 100 * (lam_conv[act].min() if act.size else 1.0)
            bar.update(max(0.0, done - bar.n))
        idx = np.flatnonzero(active)
    if bar is not None:
        bar.close()
    linear.release()
    for solver in solvers or []:
        solver.release()

    u_out = torch.full((N, T, model.n_nodes, 3), float("nan"), dtype=dtype)
    for k in range(T):
        done = torch.as_tensor(nxt > k)
        if done.any():
            u_out[done, k] = model.displacement(a_out[done, k], load(np.flatnonzero(nxt > k), outs[k]))
    per_output = np.where(at_output >= 0, np.diff(at_output, axis=1, prepend=0), -1)
    return Solution(outs, u_out, a_out, status.astype(str), lam_conv.copy(), iterations, increments, cutbacks,
                    last_res, history, timings, x_last, per_output)


def _euler_velocity(model: Model, pack: _Packing, params, dtype, backend: str, h: float = 1e-6,
                    x0: torch.Tensor | None = None, lam0: torch.Tensor | None = None) -> torch.Tensor:
    """``dx/dlambda`` at the unloaded state, or at the equilibria ``x0`` (N, size) reached at load factors
    ``lam0`` (N,), for every member (central difference in lambda)."""
    N = next(iter(params.values())).shape[0]
    if x0 is None:
        a0 = torch.zeros(N, model.n_red, dtype=dtype)
        local0 = model.initial_local(N)
    else:
        a0, local0 = pack.split(x0)
    lam = torch.zeros(N, dtype=dtype) if lam0 is None else lam0
    ev = model.evaluate(a0, params, lam, tangent=True, local=local0)
    dr = (model.evaluate(a0, params, lam + h, local=local0).rhs - model.evaluate(a0, params, lam - h, local=local0).rhs) / (2 * h)
    v = torch.zeros_like(a0)
    linear = SparseSolver(backend, model.symmetric_tangent)
    for m in range(N):
        try:
            linear.factorize(ev.tangents[m])
            v[m] = torch.as_tensor(linear.solve(-dr[m].numpy()))
        except SingularMatrixError:  # singular initial tangent: start from zero, Newton will tell
            v[m] = 0.0
    linear.release()
    if pack.size == model.n_red:
        return v
    # dp/dlambda = -K_pp^-1 K_pu du/dlambda, du/dlambda including prescribed displacements
    du = (model.displacement(a0 + h * v, lam + h) - model.displacement(a0, lam)) / h
    u0 = model.displacement(a0, lam)
    local_v = [None if l is None else t.local_update(u0, params, l, du) for t, l in zip(model.terms, local0)]
    return pack.join(v, local_v)
