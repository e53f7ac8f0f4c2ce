"""Reduced-order solves of an ensemble: a Galerkin projection on the solved states of a few
members, with hyper-reduction, polished on the full residual and checked by a full Newton step.

Members of an ensemble differ only in their parameters, and their solutions lie on a manifold of
few dimensions (with C10 alone, the P/C10 scaling law makes it nearly one-dimensional). Given the
equilibrium states of a few members solved in full (*snapshots*, all load steps):

1. **Basis** ``V`` (n_red x k): the leading left singular vectors of the snapshot states (POD),
   kept until the discarded singular values fall below ``tol`` of the largest.
2. **Hyper-reduction** (energy-conserving sampling and weighting, ECSW: Farhat, Avery, Chapman,
   Cortial, IJNME 98 (2014) 625): for every term, non-negative weights ``xi`` on a few of its
   blocks such that ``sum_b xi_b W_b^T f_b`` reproduces the term's reduced force ``W^T f`` on every
   snapshot state to ``sampling_tol``, found by a Lawson-Hanson active-set NNLS stopped at that
   tolerance (``W = J(a) V``, ``J = du/da`` through the constraints). A reduced Newton iteration then
   evaluates those blocks only.
3. **Reduced Newton** per output load factor from a quadratic predictor in the load factor, on
   ``q`` with ``a = V q``: ``(V^T K V) dq = -V^T r`` with the sampled residual and tangent, until
   ``|V dq| < xtol`` (1e-3 mm: the polish does the rest).
4. **Polish**: the full residual replaces the sampled one, with the last sampled tangent (or, where
   that contracts by less than ``refresh`` per step, the Galerkin tangent ``V^T K V`` of the full
   model), until ``|V dq| < polish_tol`` (1e-4 mm): the answer is the Galerkin solution on ``V``, the
   sampling error removed.
5. **Check**: at the last output, one full Newton step with the member's own tangent; its largest
   nodal displacement is the distance to the full solution, to first order (Newton converges
   quadratically from there; tested: estimate and error agree to 5 %). The same at the other output
   whose full residual is largest relative to its forces. The larger of the two is the member's
   ``error_estimate`` (mm). :func:`solve_ensemble` and ``torchfra.calibration.forward`` solve a member in full
   again when its estimate exceeds their tolerance, or when its reduced Newton fails.

Why the polish is needed on the actuator (``studies/reduced_conditioning.py``, results in
``studies/results/study_reduced_conditioning.json``): its Galerkin tangent has one mode at least 1,400
times softer than the next (the free end swaying along y, the camera's horizontal; condition number
1.6e6 to 1.3e7 over the load). The sampled tangent's stiffness along that mode is off by up to 10 %,
so the hyper-reduced equilibrium lies up to 0.07 mm from the Galerkin one, all of it along that
mode, and only full residuals bring it back.

Where it pays: a sampled iteration costs what the sampled blocks cost, while a full Newton iteration
costs a full tangent and a sparse factorization; measured by ``scripts/bench.py --suite ensemble``
(README, "Reduced-order forward ensembles").

Nothing here is specific to the actuator: any :class:`Model` whose terms keep their per-block data
as arrays over blocks (every term of this package) can be reduced.
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import torch

from torchfra.fem.linsolve import SingularMatrixError, SparseSolver
from torchfra.fem.model import Model
from torchfra.fem.terms import Term


@dataclass
class ReducedBasis:
    """POD basis ``V`` (n_red, k) of solved states, with the singular values of the states."""

    V: torch.Tensor
    singular_values: np.ndarray

    @classmethod
    def from_states(cls, states, tol: float = 1e-9, max_size: int = 80) -> "ReducedBasis":
        """states: (M, n_red) equilibrium states (any members, load steps)."""
        A = np.asarray(states, dtype=np.float64).reshape(-1, np.shape(states)[-1])
        A = A[np.isfinite(A).all(axis=1)]
        if A.shape[0] == 0:
            raise ValueError("no finite state to build a reduced basis from")
        U, s, _ = np.linalg.svd(A.T, full_matrices=False)
        k = int(np.sum(s > tol * s[0]))
        k = max(1, min(k, max_size))
        return cls(torch.as_tensor(U[:, :k].copy()), s)

    @property
    def size(self) -> int:
        return self.V.shape[1]


def _restrict(term: Term, blocks: np.ndarray) -> Term:
    """A shallow copy of ``term`` on a subset of its blocks: every array attribute whose first
    dimension runs over the blocks is sliced (element geometry, connectivity, dofs)."""
    B = term.dofs.shape[0]
    out = copy.copy(term)
    idx = torch.as_tensor(blocks)
    for name, v in vars(term).items():
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == B:
            setattr(out, name, v[blocks])
        elif isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == B:
            setattr(out, name, v[idx])
    return out


class _ActiveCholesky:
    """Cholesky factor ``L`` of ``gram[A, A]`` for an ordered active set ``A``, grown one block at a
    time in O(|A|^2) (a fresh factorization per Lawson-Hanson step cost O(|A|^3), 1,300 of them per
    build) and refactored only when blocks leave the set."""

    def __init__(self, gram: np.ndarray):
        self.gram, self.active, self.L = gram, [], np.zeros((0, 0))

    def append(self, j: int) -> bool:
        """Add block ``j``; False (the set unchanged) if its column is dependent on the active ones."""
        from scipy.linalg import solve_triangular

        w = solve_triangular(self.L, self.gram[self.active, j], lower=True, check_finite=False)
        d2 = self.gram[j, j] - float(w @ w)
        if not d2 > 1e-12 * self.gram[j, j]:
            return False
        n = len(self.active)
        L = np.zeros((n + 1, n + 1))
        L[:n, :n], L[n, :n], L[n, n] = self.L, w, np.sqrt(d2)
        self.L = L
        self.active.append(j)
        return True

    def keep(self, kept: list[int]) -> None:
        self.active = list(kept)
        A = np.asarray(self.active, dtype=np.int64)
        self.L = np.linalg.cholesky(self.gram[np.ix_(A, A)]) if A.size else np.zeros((0, 0))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        from scipy.linalg import solve_triangular

        y = solve_triangular(self.L, rhs, lower=True, check_finite=False)
        return solve_triangular(self.L.T, y, lower=False, check_finite=False)


def _nnls(G: np.ndarray, b: np.ndarray, tol: float, max_blocks: int) -> np.ndarray:
    """Sparse non-negative least squares: Lawson-Hanson active set, stopped as soon as
    ``||G x - b|| <= tol ||b||`` (the ECSW training problem). Works on the Gram matrix ``G^T G``
    with a Cholesky factor of its active block updated as blocks enter, so each step costs
    (active blocks)^2, not rows x (active blocks)^2. A block whose column depends on the active
    ones is never taken (it cannot lower the residual further)."""
    n = G.shape[1]
    gram, c = G.T @ G, G.T @ b
    bb = float(b @ b)
    x = np.zeros(n)
    chol = _ActiveCholesky(gram)
    skipped: list[int] = []

    def residual2():
        A = chol.active
        xa = x[A]
        return max(bb - 2 * float(xa @ c[A]) + float(xa @ gram[np.ix_(A, A)] @ xa), 0.0) if A else bb

    while residual2() > tol**2 * bb and len(chol.active) < max_blocks:
        A = chol.active
        g = c - gram[:, A] @ x[A]  # G^T (b - G x)
        g[A] = -np.inf
        g[skipped] = -np.inf
        j = int(np.argmax(g))
        if g[j] <= 0:
            break
        if not chol.append(j):
            skipped.append(j)
            continue
        while True:
            A = np.asarray(chol.active)
            z = chol.solve(c[A])
            if (z > 0).all():
                x[:] = 0.0
                x[A] = z
                break
            xa = x[A]
            neg = z <= 0
            alpha = np.min(xa[neg] / (xa[neg] - z[neg]))
            x[A] = xa + alpha * (z - xa)
            kept = [a for a in chol.active if x[a] > 0]
            x[[a for a in chol.active if a not in kept]] = 0.0
            chol.keep(kept)
            if not kept:
                break
    return x


# ECSW tolerance. The polish removes the sampling error, so the tolerance trades sampled blocks
# against polish iterations. Measured on 8 members of the actuator's C10 prior at resolution 1 (5
# snapshots, 20 load steps, 1 thread): 1e-5 sampled 219 bricks, 499 fibers, 72 cavity faces and
# solved in 27.8 s; 1e-4 sampled 160, 359, 72 in 17.5 s (estimates below 1.5e-6 mm either way);
# 1e-3 sampled 105, 222, 68, but its tangent no longer contracted the polish: 32 s, one member failed.
SAMPLING_TOL = 1e-4


def _reducible(model: Model) -> None:
    """Refuse a model with a global term (its couplings are each member's own: no blocks to sample)."""
    glob = [type(t).__name__ for t in model.terms if t.global_dofs]
    if glob:
        raise ValueError(f"the model's {', '.join(glob)} term couples each member's dofs its own way (no blocks to "
                         "sample): it cannot be hyper-reduced; solve its members by full Newton (method='full')")


class HyperReducedModel:
    """The reduced residual ``V^T r(V q)`` and tangent ``V^T K(V q) V`` of ``model`` from sampled,
    weighted blocks of every term (ECSW), trained on equilibrium ``states`` (M, n_red) with their
    parameters (name -> (M,)) and load factors (M,)."""

    def __init__(self, model: Model, basis: ReducedBasis, states, params, load_factors,
                 sampling_tol: float = SAMPLING_TOL, max_blocks: int | None = None):
        self.model, self.basis = model.finalize(), basis
        _reducible(model)
        dtype = model.dtype
        states = torch.as_tensor(states, dtype=dtype)
        params = {k: torch.as_tensor(v, dtype=dtype) for k, v in params.items()}
        lam = torch.as_tensor(load_factors, dtype=dtype)
        V = basis.V.numpy()
        u = model.displacement(states, lam)
        W = model.dofmap.jacobian_times(states, basis.V)  # (M, n_full, k)
        self.terms: list[tuple[Term, torch.Tensor, torch.Tensor]] = []
        self.blocks: list[np.ndarray] = []
        self.sampled_blocks: list[int] = []
        self.training_error: list[float] = []
        for t in model.terms:
            fe = t.evaluate(u, params, model.term_load_factor(t, lam), tangent=False).fe  # (M, B, D)
            dofs = torch.as_tensor(t.dofs)
            G = torch.stack([torch.einsum("bd,bdk->kb", fe[m], W[m][dofs]) for m in range(fe.shape[0])])
            scale = torch.linalg.norm(G.sum(2), dim=1).clamp_min(1e-300)  # every state counts alike
            G = (G / scale[:, None, None]).reshape(-1, G.shape[-1]).numpy()
            if G.shape[0] > G.shape[1]:  # b = G 1 lies in G's range: ||G x - b|| = ||R x - R 1|| with G = Q R
                G = np.linalg.qr(G, mode="r")
            b = G.sum(axis=1)
            xi = _nnls(G, b, sampling_tol, max_blocks or t.dofs.shape[0])
            keep = np.flatnonzero(xi > 0)
            self._sample(t, keep, xi[keep])
            self.training_error.append(float(np.linalg.norm(G @ xi - b) / max(np.linalg.norm(b), 1e-300)))

    def _sample(self, term: Term, blocks: np.ndarray, weights: np.ndarray) -> None:
        self.blocks.append(np.asarray(blocks, dtype=np.int64))
        self.terms.append((_restrict(term, blocks), torch.as_tensor(weights, dtype=self.model.dtype),
                           torch.as_tensor(term.dofs)[torch.as_tensor(blocks)]))
        self.sampled_blocks.append(int(len(blocks)))

    def galerkin(self) -> "HyperReducedModel":
        """This reduction without sampling: every block of every term at weight 1, so
        :meth:`evaluate` gives the exact Galerkin residual ``V^T J^T r(a)`` and tangent ``V^T K V``
        of the full model, from the element arrays alone (no sparse assembly, constraint reduction or
        sparse product; built once, cached)."""
        if getattr(self, "_galerkin", None) is None:
            g = copy.copy(self)
            g.terms, g.blocks, g.sampled_blocks = [], [], []
            for t in self.model.terms:
                n = t.dofs.shape[0]
                g._sample(t, np.arange(n), np.ones(n))
            g._galerkin = g
            self._galerkin = g
        return self._galerkin

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything needed to rebuild this reduction for the same model, as plain arrays (for an
        ``np.savez`` file read back with ``allow_pickle=False``)."""
        out = {"V": self.basis.V.numpy(), "singular_values": self.basis.singular_values,
               "training_error": np.asarray(self.training_error)}
        for i, (blocks, (_, xi, _)) in enumerate(zip(self.blocks, self.terms)):
            out[f"blocks_{i}"], out[f"weights_{i}"] = blocks, xi.numpy()
        return out

    @classmethod
    def from_arrays(cls, model: Model, arrays) -> "HyperReducedModel":
        """The reduction :meth:`arrays` saved, for ``model`` (the same model it was trained on)."""
        model.finalize()
        V = np.asarray(arrays["V"], dtype=np.float64)
        if V.ndim != 2 or V.shape[0] != model.n_red:
            raise ValueError(f"the saved reduced basis has shape {V.shape}; this model has {model.n_red} unknowns")
        _reducible(model)
        self = cls.__new__(cls)
        self.model = model
        self.basis = ReducedBasis(torch.as_tensor(V), np.asarray(arrays["singular_values"]))
        self.terms, self.blocks, self.sampled_blocks = [], [], []
        self.training_error = [float(x) for x in np.asarray(arrays["training_error"])]
        for i, t in enumerate(model.terms):
            blocks = np.asarray(arrays[f"blocks_{i}"], dtype=np.int64)
            if blocks.size and (blocks.min() < 0 or blocks.max() >= t.dofs.shape[0]):
                raise ValueError(f"the saved sampled blocks of term {i} ({type(t).__name__}) do not fit this model")
            self._sample(t, blocks, np.asarray(arrays[f"weights_{i}"], dtype=np.float64))
        return self

    def evaluate(self, q: torch.Tensor, params: dict, load_factor: torch.Tensor, tangent: bool = True):
        """q: (N, k) -> reduced residual (N, k), reduced tangent (N, k, k) or None, admissible (N,)."""
        model, V = self.model, self.basis.V
        a = q @ V.T
        u = model.displacement(a, load_factor)
        N, n = a.shape[0], model.dofmap.n_full
        W = model.dofmap.jacobian_times(a, V)  # (N, n_full, k)
        R = torch.zeros(N, V.shape[1], dtype=a.dtype)
        K = torch.zeros(N, V.shape[1], V.shape[1], dtype=a.dtype) if tangent else None
        r_full = torch.zeros(N, n, dtype=a.dtype)
        ok = torch.ones(N, dtype=torch.bool)
        for term, xi, dofs in self.terms:
            out = term.evaluate(u, params, model.term_load_factor(term, load_factor), tangent=tangent)
            ok &= out.ok
            fe = out.fe * xi[None, :, None]
            r_full.index_add_(1, dofs.reshape(-1), fe.reshape(N, -1))
            Wb = W[:, dofs]  # (N, B, D, k)
            R += torch.einsum("nbd,nbdk->nk", fe, Wb)
            if tangent and out.Ke is not None:
                # projected in single precision: the reduced tangent only steers Newton (the answer is
                # the float64 residual's root, checked by a float64 full Newton step); measured on the
                # actuator at resolution 1, 8 members: the sampled phase 10 % faster, iteration counts
                # and check estimates unchanged to the digits that matter. One member at a time, so a
                # member's tangent does not depend on which members share its batch (the products'
                # single-precision rounding does: members would differ by up to 4e-5 mm between one
                # process and two ranks, instead of round-off)
                Ke = (out.Ke * xi[None, :, None, None]).float()
                W32 = Wb.float()
                for j in range(N):
                    K[j] += torch.einsum("bdk,bdl->kl", W32[j], torch.matmul(Ke[j], W32[j])).double()
        if tangent:
            for cols, H in model.dofmap.geometric_stiffness(a, r_full):
                Vc = V[torch.as_tensor(cols)]
                K += torch.einsum("ik,nij,jl->nkl", Vc, torch.as_tensor(H), Vc)
        return R, K, ok


def _predict(history, lam, kind):
    """Starting iterate at load factor ``lam`` from the converged (load factor, q) history:
    ``"quadratic"`` (through the last three) or ``"secant"``. An Euler predictor (reduced tangent
    and load derivative) was measured too: no fewer iterations than these."""
    lam1, q1 = history[-1]
    if len(history) == 1:
        return q1.clone()
    lam0, q0 = history[-2]
    if kind == "quadratic" and len(history) >= 3:
        lm, qm = history[-3]
        l = [(lam - b) * (lam - c) / ((a - b) * (a - c)) for a, b, c in ((lm, lam0, lam1), (lam0, lm, lam1), (lam1, lm, lam0))]
        return l[0] * qm + l[1] * q0 + l[2] * q1
    return q1 + (lam - lam1) * (q1 - q0) / (lam1 - lam0)


@dataclass
class ReducedSolution:
    """Like :class:`~torchfra.fem.Solution` for reduced solves: ``a`` (N, T, n_red), ``u`` (N, T,
    n_nodes, 3); ``status`` "converged" or "failed" (the reduced Newton did not converge: solve the
    member in full); ``error_estimate`` (N,) mm, the largest nodal displacement of one full Newton
    step at the last output (NaN if failed); ``iterations`` (sampled) and ``polish`` (full-residual)
    iterations per member; ``timings`` in seconds."""

    load_factors: np.ndarray
    a: torch.Tensor
    u: torch.Tensor
    status: np.ndarray
    error_estimate: np.ndarray
    iterations: np.ndarray
    tangents: np.ndarray
    polish: np.ndarray
    full_tangents: np.ndarray
    timings: dict


def solve_reduced(hyper: HyperReducedModel, params: dict, load_factors, xtol: float = 1e-3, polish_tol: float = 1e-4,
                  max_iterations: int = 25, max_polish: int = 10, check: bool = True,
                  refresh: float = 0.25, predictor: str = "quadratic", start=None, resume: dict | None = None,
                  on_step=None) -> ReducedSolution:
    """Solve every member (params: name -> (N,)) at the load factors (increasing, in (0, 1]) on the
    reduced basis of ``hyper``; see the module docstring for the steps. ``start``: ``(q0 (N, k),
    lam0)``, equilibria reached at load factor ``lam0`` (e.g. with other parameters: the restart
    filter), to continue from instead of the unloaded state.

    ``on_step(state)`` is called after every load factor with the solve's whole state (a dict of
    arrays: a checkpoint); ``resume=state`` continues from it exactly as the solve would have gone
    on (same members, load factors and basis). ``refresh <= 0``: every polish iteration takes a
    fresh Galerkin tangent (Newton on the Galerkin system, for reference solutions)."""
    model, V = hyper.model, hyper.basis.V
    dtype = model.dtype
    params = {k: torch.as_tensor(v, dtype=dtype).reshape(-1) for k, v in params.items()}
    N = model.validate(params)
    outs = np.asarray(load_factors, dtype=np.float64)
    T, k = outs.size, V.shape[1]
    timings = {"sampled": 0.0, "polish": 0.0, "check": 0.0}
    q_out = torch.full((N, T, k), float("nan"), dtype=dtype)
    status = np.array(["converged"] * N, dtype=object)
    iterations, polish = np.zeros(N, dtype=np.int64), np.zeros(N, dtype=np.int64)
    history = [(0.0, torch.zeros(N, k, dtype=dtype))] if start is None else \
        [(float(start[1]), torch.as_tensor(start[0], dtype=dtype).reshape(N, k).clone())]
    alive = np.ones(N, dtype=bool)
    K_last = torch.zeros(N, k, k, dtype=dtype)
    have_tangent = np.zeros(N, dtype=bool)
    tangents = np.zeros(N, dtype=np.int64)
    full_tangents = np.zeros(N, dtype=np.int64)
    first = 0
    if resume is not None:
        first = int(resume["step"]) + 1
        q_out[:, :first] = torch.as_tensor(resume["q_out"])
        history = [(float(lam_h), torch.as_tensor(q_h).clone()) for lam_h, q_h in
                   zip(resume["history_lam"], resume["history_q"])]
        K_last = torch.as_tensor(resume["K_last"]).clone()
        status = np.asarray(resume["status"]).astype(object)
        alive, have_tangent = np.asarray(resume["alive"]).copy(), np.asarray(resume["have_tangent"]).copy()
        iterations, polish = np.asarray(resume["iterations"]).copy(), np.asarray(resume["polish"]).copy()
        tangents, full_tangents = np.asarray(resume["tangents"]).copy(), np.asarray(resume["full_tangents"]).copy()
        timings.update(zip(("sampled", "polish", "check"), np.asarray(resume["timings"]).tolist()))
    for t, lam in enumerate(outs):
        if t < first:
            continue
        q = _predict(history, lam, predictor)
        for phase in ("sampled", "polish"):
            active = alive.copy()
            need_tangent = np.full(N, phase == "sampled" or refresh <= 0)
            last_step = np.full(N, np.inf)
            limit = max_iterations if phase == "sampled" else max_polish
            for _ in range(limit):
                idx_all = np.flatnonzero(active)
                if idx_all.size == 0:
                    break
                groups = [(idx_all[need_tangent[idx_all]], True), (idx_all[~need_tangent[idx_all]], False)]
                for idx, with_tangent in groups:
                    if idx.size == 0:
                        continue
                    t0 = time.perf_counter()
                    sub = {name: v[idx] for name, v in params.items()}
                    lam_t = torch.full((idx.size,), lam, dtype=dtype)
                    if phase == "sampled":
                        R, K, ok = hyper.evaluate(q[idx], sub, lam_t, tangent=with_tangent)
                        if with_tangent:
                            K_last[idx] = K
                            have_tangent[idx] = True
                            tangents[idx] += 1
                        iterations[idx] += 1
                    else:
                        # the full residual; where the sampled tangent does not contract, with the
                        # Galerkin tangent, both from the element arrays of every block
                        # (hyper.galerkin: half the time of assembling K and forming V^T K V)
                        if with_tangent:
                            R, K_last[idx], ok = hyper.galerkin().evaluate(q[idx], sub, lam_t, tangent=True)
                            have_tangent[idx] = True
                            full_tangents[idx] += 1
                        else:
                            ev = model.evaluate(q[idx] @ V.T, sub, lam_t, tangent=False)
                            R, ok = ev.residual @ V, ev.ok
                        polish[idx] += 1
                    try:
                        dq = -torch.linalg.solve(K_last[idx], R.unsqueeze(-1)).squeeze(-1)
                    except RuntimeError:
                        dq = torch.full_like(R, float("nan"))
                    timings[phase] += time.perf_counter() - t0
                    bad = ~(ok & torch.isfinite(dq).all(dim=1))
                    q[idx] = q[idx] + torch.where(bad[:, None], torch.zeros_like(dq), dq)
                    step = (dq @ V.T).abs().amax(dim=1).numpy()
                    for j, m in enumerate(idx):
                        if bool(bad[j]) or (not with_tangent and step[j] > last_step[m]):
                            if with_tangent:
                                alive[m] = active[m] = False
                                status[m] = "failed"
                            else:  # a stale tangent made things worse: undo (a rejected step was
                                # never applied), refresh the tangent
                                if not bool(bad[j]):
                                    q[m] = q[m] - dq[j]
                                need_tangent[m] = True
                            continue
                        if step[j] < (xtol if phase == "sampled" else polish_tol):
                            active[m] = False
                        # sampled phase: Newton; polish: keep the tangent while it contracts fast enough
                        # (refresh = 0: a fresh tangent every iteration, exact Newton on the Galerkin system)
                        need_tangent[m] = phase == "sampled" or refresh <= 0 or step[j] > refresh * last_step[m]
                        last_step[m] = step[j]
            for m in np.flatnonzero(active):  # ran out of iterations
                alive[m] = False
                status[m] = "failed"
        history.append((lam, q.clone()))
        q_out[:, t] = torch.where(torch.as_tensor(alive)[:, None], q, torch.full_like(q, float("nan")))
        if on_step is not None:
            kept = history[-3:]  # all the predictor looks back on
            on_step({"step": np.int64(t), "load_factors": outs, "q_out": q_out[:, : t + 1].numpy(),
                     "history_lam": np.array([h[0] for h in kept]), "history_q": torch.stack([h[1] for h in kept]).numpy(),
                     "K_last": K_last.numpy(), "status": status.astype(str), "alive": alive, "have_tangent": have_tangent,
                     "iterations": iterations, "polish": polish, "tangents": tangents, "full_tangents": full_tangents,
                     "timings": np.array([timings["sampled"], timings["polish"], timings["check"]])})
    a = q_out @ V.T
    u = torch.full((N, T, model.n_nodes, 3), float("nan"), dtype=dtype)
    for t, lam in enumerate(outs):
        u[:, t] = model.displacement(a[:, t], torch.full((N,), lam, dtype=dtype))
    error = np.full(N, np.nan)
    if check and alive.any():
        t0 = time.perf_counter()
        idx = np.flatnonzero(alive)
        lam_t = torch.full((idx.size,), outs[-1], dtype=dtype)
        ev = model.evaluate(a[idx, -1], {name: v[idx] for name, v in params.items()}, lam_t, tangent=True)
        solver = SparseSolver("auto", model.symmetric_tangent)
        lam_all = torch.as_tensor(outs, dtype=dtype)
        for j, m in enumerate(idx):
            try:
                solver.factorize(ev.tangents[j])
                da = torch.as_tensor(solver.solve(-ev.rhs[j].numpy()))
            except SingularMatrixError:
                continue
            du = model.displacement((a[m, -1] + da)[None], lam_t[:1]) - u[m, -1][None]
            error[m] = float(du.abs().max())
            if T > 1:
                # the other outputs (measured: a soft member within 1.4e-4 mm at full load was 2.6e-3 mm
                # off at 95 % load, where the softest snapshot had stopped, so the basis held no state
                # of that load near it): the one whose full residual is largest relative to its forces
                # gets a full Newton step of its own (the full load's factorization would not do: the
                # loaded actuator's soft modes amplify a low load's residual 100-fold)
                sub = {name: v[m].expand(T - 1) for name, v in params.items()}
                ev_k = model.evaluate(a[m, :-1], sub, lam_all[:-1])
                rel = (torch.linalg.norm(ev_k.rhs, dim=1) / ev_k.force_scale.clamp_min(1e-300)).numpy()
                k = int(np.argmax(rel))
                ev_w = model.evaluate(a[m, k : k + 1], {name: v[m : m + 1] for name, v in params.items()},
                                      lam_all[k : k + 1], tangent=True)
                try:
                    solver.factorize(ev_w.tangents[0])
                    da_k = torch.as_tensor(solver.solve(-ev_w.rhs[0].numpy()))
                except SingularMatrixError:
                    error[m] = np.nan
                    continue
                du_k = model.displacement((a[m, k] + da_k)[None], lam_all[k : k + 1]) - u[m, k][None]
                error[m] = max(error[m], float(du_k.abs().max()))
        solver.release()
        timings["check"] = time.perf_counter() - t0
    u[~torch.as_tensor(alive)] = float("nan")
    return ReducedSolution(outs, a, u, status.astype(str), error, iterations, tangents, polish, full_tangents, timings)


def select_snapshots(params: dict, n: int | None = None) -> np.ndarray:
    """Members to solve in full and build the basis from: farthest-point sampling in the
    standardized (log, for positive parameters) coordinates of the parameters that vary across
    members, starting from the member nearest the median. ``n`` defaults to ``1 + 2 d`` (d independent
    directions among the varying parameters, e.g. 1 for C10 with D1 tied to it: the centre and two
    far members per direction), at least 5 when any varies (with 3 along the actuator's C10 prior,
    members halfway between had check estimates up to 8.8e-4 mm; with 5, below 2e-5 mm)."""
    cols = []
    for v in params.values():
        x = np.asarray(torch.as_tensor(v).reshape(-1), dtype=np.float64)
        x = np.log(x) if (x > 0).all() else x
        if np.ptp(x) > 1e-12 * max(1.0, float(np.abs(x).max())):
            cols.append((x - x.mean()) / x.std())
    M = len(next(iter(params.values())))
    if not cols:
        return np.array([0])
    # parameters tied to each other (D1 = 1 / (K/mu C10)) are one direction: keep the principal ones
    Z = np.column_stack(cols)
    _, sv, Vt = np.linalg.svd(Z - Z.mean(axis=0), full_matrices=False)
    rank = int(np.sum(sv > 1e-8 * sv[0]))
    Z = Z @ Vt[:rank].T
    n = min(M, n or max(5, 1 + 2 * rank))
    chosen = [int(np.argmin(np.linalg.norm(Z - np.median(Z, axis=0), axis=1)))]
    dist = np.linalg.norm(Z - Z[chosen[0]], axis=1)
    while len(chosen) < n:
        j = int(np.argmax(dist))
        chosen.append(j)
        dist = np.minimum(dist, np.linalg.norm(Z - Z[j], axis=1))
    return np.array(chosen)


def build_reduced(model: Model, states, params: dict, load_factors, basis_tol: float = 1e-9,
                  sampling_tol: float = SAMPLING_TOL) -> HyperReducedModel:
    """Basis and hyper-reduction from solved members: ``states`` (S, T, n_red) at ``load_factors``
    (T,), ``params`` name -> (S,)."""
    states = torch.as_tensor(states, dtype=model.dtype)
    S, T = states.shape[:2]
    keep = torch.isfinite(states.reshape(S * T, -1)).all(dim=1)
    flat = states.reshape(S * T, -1)[keep]
    basis = ReducedBasis.from_states(flat.numpy(), tol=basis_tol)
    prm = {k: torch.as_tensor(v, dtype=model.dtype).reshape(-1).repeat_interleave(T)[keep] for k, v in params.items()}
    lam = torch.as_tensor(np.tile(np.asarray(load_factors, dtype=np.float64), S))[keep]
    return HyperReducedModel(model, basis, flat, prm, lam, sampling_tol=sampling_tol)


@dataclass
class EnsembleSolution:
    """Every member at the load factors: ``u`` (N, T, n_nodes, 3), ``a`` (N, T, n_red); ``status``
    "converged"/"diverged"; ``method`` per member: "full" (Newton, a snapshot or a fallback) or
    "reduced"; ``error_estimate`` (N,) mm for reduced members (NaN for full ones); ``snapshots``
    (member indices solved first), ``basis_size``, ``sampled_blocks`` (per term); ``counts``
    (Newton iterations of full solves, sampled and polish iterations, full tangents) and
    ``timings`` (s) per phase."""

    load_factors: np.ndarray
    u: torch.Tensor
    a: torch.Tensor
    status: np.ndarray
    method: np.ndarray
    error_estimate: np.ndarray
    snapshots: np.ndarray
    basis_size: int
    sampled_blocks: list
    counts: dict
    timings: dict


def solve_ensemble(model: Model, params: dict, load_factors, options=None, snapshots: int | None = None,
                   tol: float = 5e-4, batch: int = 4, progress: bool = False, **reduced) -> EnsembleSolution:
    """Solve an ensemble (params: name -> (N,)) at the load factors: a few members in full, the
    rest on their reduced basis, checked, and in full again where the check's estimate exceeds
    ``tol`` mm or the reduced Newton fails. ``reduced``: options of :func:`solve_reduced` (``xtol``,
    ``polish_tol``: mm, sized for the actuator)."""
    from torchfra.fem.newton import solve

    model.finalize()
    dtype = model.dtype
    params = {k: torch.as_tensor(v, dtype=dtype).reshape(-1) for k, v in params.items()}
    N = model.validate(params)
    outs = np.asarray(load_factors, dtype=np.float64)
    T = outs.size
    timings = {"full": 0.0, "build": 0.0, "reduced": 0.0, "fallback": 0.0}
    counts = {"newton_iterations": 0, "sampled_iterations": 0, "polish_iterations": 0, "full_tangents": 0}
    u = torch.full((N, T, model.n_nodes, 3), float("nan"), dtype=dtype)
    a = torch.full((N, T, model.n_red), float("nan"), dtype=dtype)
    status = np.array(["diverged"] * N, dtype=object)
    method = np.array(["full"] * N, dtype=object)
    error = np.full(N, np.nan)

    def full(idx, phase):
        t0 = time.perf_counter()
        for m in idx:
            sol = solve(model, {k: v[m : m + 1] for k, v in params.items()}, outs, options,
                        progress=f"member {m}, full Newton" if progress else False)
            u[m], a[m], status[m], method[m] = sol.u[0], sol.a[0], sol.status[0], "full"
            counts["newton_iterations"] += int(sol.iterations[0])
        timings[phase] += time.perf_counter() - t0

    # a model with preloads starts its path from a settled reference state that differs from member to
    # member; the reduced Newton starts from the unloaded body: every member is solved in full
    snap = np.arange(N) if model.has_preload else select_snapshots(params, snapshots)
    full(snap, "full")
    # a snapshot that stopped short of full load still brings the load steps it reached (the
    # softest draw of the actuator's prior stops at 95 %: without its states, its neighbours' checks fail)
    good = snap[torch.isfinite(a[snap].reshape(len(snap), -1)).any(dim=1).numpy()]
    rest = np.setdiff1d(np.arange(N), snap)
    if rest.size and good.size:
        t0 = time.perf_counter()
        hyper = build_reduced(model, a[good], {k: v[good] for k, v in params.items()}, outs)
        timings["build"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        for i in range(0, rest.size, batch):
            idx = rest[i : i + batch]
            rs = solve_reduced(hyper, {k: v[idx] for k, v in params.items()}, outs, **reduced)
            u[idx], a[idx] = rs.u, rs.a
            status[idx] = np.where(rs.status == "converged", "converged", "diverged")
            method[idx] = "reduced"
            error[idx] = rs.error_estimate
            counts["sampled_iterations"] += int(rs.iterations.sum())
            counts["polish_iterations"] += int(rs.polish.sum())
            counts["full_tangents"] += int(rs.full_tangents.sum())
        timings["reduced"] = time.perf_counter() - t0
        basis_size, blocks = hyper.basis.size, hyper.sampled_blocks
    else:
        basis_size, blocks = 0, []
    redo = rest[(method[rest] == "reduced") & ~(error[rest] <= tol)]
    full(redo, "fallback")
    return EnsembleSolution(outs, u, a, status.astype(str), method.astype(str), error, snap, basis_size, blocks,
                            counts, timings)
