"""Exact sensitivities of converged states to parameters, by implicit differentiation.

At equilibrium the reduced residual vanishes, ``r(a(theta), theta) = 0``, so

    da/dtheta = -K^-1 dr/dtheta      (K = dr/da, the tangent Newton factorizes)

with ``dr/dtheta`` at fixed ``a`` by forward-mode automatic differentiation of the element kernels
(dual numbers through every term; the constraint map is linear in the residual for fixed ``a``).
Hybrid (mixed u/p) terms are differentiated at their stationary element pressures: the condensed
residual's derivative is then the full system's, because the pressure equations hold at
equilibrium. One factorization per load step serves all ``d`` parameters (``d`` back-solves), and
``du/dtheta = J(a) da/dtheta`` with ``J = du/da`` (rigid bodies rotate: ``J`` depends on ``a``).

The load factor is differentiated the same way (``du/dlambda``): it gives cubic Hermite
interpolation between load steps and the sensitivity to a pressure gain.

Verified against central finite differences of full solves in tests/test_sensitivity.py.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.autograd.forward_ad as fwAD
from torch.func import jvp

from torchfra.fem.linsolve import SparseSolver
from torchfra.fem.model import Model
from torchfra.fem.newton import Solution


@dataclass
class Sensitivities:
    """Derivatives of the displacements at every output load step of one solve.

    names: the d parameters; du: (N, T, n_nodes, 3, d) = du/dtheta; du_dlambda: (N, T, n_nodes, 3),
    the derivative along the load factor (the pressure ramp); timings: seconds spent in tangents,
    factorizations + back-solves, and parameter derivatives of the residual."""

    load_factors: np.ndarray
    names: list[str]
    du: torch.Tensor
    du_dlambda: torch.Tensor
    timings: dict[str, float] = field(default_factory=dict)


def residual_derivative(model: Model, a: torch.Tensor, params: dict[str, torch.Tensor],
                        load_factor: torch.Tensor, dparams: dict[str, torch.Tensor] | None = None,
                        dload: torch.Tensor | None = None) -> torch.Tensor:
    """Directional derivative of the reduced residual at fixed ``a`` (N, n_red) along the parameter
    direction ``dparams`` (name -> (N,); parameters not named do not move) and load-factor direction
    ``dload`` (N,). Returns (N, n_red). Forward-mode AD through the terms."""
    model.finalize()
    dtype = model.dtype
    a = torch.as_tensor(a, dtype=dtype)
    N, n = a.shape[0], 3 * model.n_nodes
    params = {k: torch.as_tensor(v, dtype=dtype) for k, v in params.items()}
    lam = torch.as_tensor(load_factor, dtype=dtype)
    dparams = {k: torch.as_tensor(dparams[k], dtype=dtype).expand_as(v).contiguous() if dparams and k in dparams
               else torch.zeros_like(v) for k, v in params.items()}
    dlam = torch.zeros_like(lam) if dload is None else torch.as_tensor(dload, dtype=dtype).expand_as(lam).contiguous()
    u = model.displacement(a, lam)  # the constraint map stays outside the transform (sparse matrices)
    # prescribed displacements ramp with lambda (and are off while the model settles its preloads)
    du = (model.prescribed_factor(dlam)[:, None] * model.dofmap.u_presc).reshape(u.shape)

    def full_residual(p, lf, uu):
        r = torch.zeros(N, n, dtype=dtype)
        for t, dofs in zip(model.terms, model._dofs):
            r = r.index_add(1, dofs, t.evaluate(uu, p, model.term_load_factor(t, lf), tangent=False).fe.reshape(N, -1))
        return r

    # torch.func.jvp nests with the materials' own vmap/jacfwd kernels (autograd's forward mode does not)
    _, tangent = jvp(full_residual, (params, lam, u), (dparams, dlam, du))
    return model.dofmap.reduce(tangent, a)


def _jvp(fn: Callable, theta: dict[str, torch.Tensor], name: str) -> dict[str, torch.Tensor]:
    """Derivative of every output of ``fn(theta)`` (name -> (N,)) along ``theta[name]``."""
    with fwAD.dual_level():
        th = {k: fwAD.make_dual(v, torch.ones_like(v)) if k == name else v for k, v in theta.items()}
        out = fn(th)
        res = {}
        for k, v in out.items():
            t = fwAD.unpack_dual(v).tangent
            res[k] = torch.zeros_like(fwAD.unpack_dual(v).primal) if t is None else t.clone()
    return res


def sensitivities(model: Model, params_of: Callable[[dict], dict], theta: dict[str, torch.Tensor],
                  solution: Solution, names: list[str] | None = None, linear_solver: str = "auto") -> Sensitivities:
    """du/dtheta at every converged output load step of ``solution``.

    params_of: maps the parameters ``theta`` (name -> (N,)) to the model's parameters (fixed ones,
    tied ones such as D1 = 1/(K/mu C10), transformed ones); it is differentiated by forward AD, so
    ``theta`` may be in any coordinates (log C10, ...). names: the parameters to differentiate
    (default: all of theta). Members or load steps that did not converge get NaN."""
    model.finalize()
    dtype = model.dtype
    theta = {k: torch.as_tensor(v, dtype=dtype).reshape(-1) for k, v in theta.items()}
    names = list(theta) if names is None else list(names)
    params = params_of(theta)
    dparams = {k: _jvp(params_of, theta, k) for k in names}
    N, T = solution.a.shape[:2]
    d = len(names)
    du = torch.full((N, T, model.n_nodes, 3, d), float("nan"), dtype=dtype)
    du_dlam = torch.full((N, T, model.n_nodes, 3), float("nan"), dtype=dtype)
    timings = {"tangent": 0.0, "solve": 0.0, "derivatives": 0.0}
    linear = SparseSolver(linear_solver, model.symmetric_tangent)
    try:
        for m in range(N):
            pm = {k: v[m : m + 1] for k, v in params.items()}
            for k in range(T):
                a = solution.a[m : m + 1, k]
                if not torch.isfinite(a).all():
                    continue
                lam = torch.as_tensor([solution.load_factors[k]], dtype=dtype)
                t0 = time.perf_counter()
                K = model.evaluate(a, pm, lam, tangent=True).tangents[0]
                t1 = time.perf_counter()
                rhs = [residual_derivative(model, a, pm, lam, {p: v[m : m + 1] for p, v in dparams[nm].items()})[0]
                       for nm in names]
                rhs.append(residual_derivative(model, a, pm, lam, dload=torch.ones(1, dtype=dtype))[0])
                t2 = time.perf_counter()
                linear.factorize(K)
                B = -torch.stack(rhs, dim=1).numpy()
                da = torch.as_tensor(np.column_stack([linear.solve(B[:, j]) for j in range(B.shape[1])]), dtype=dtype)
                t3 = time.perf_counter()
                J = model.dofmap.jacobian(a)[0]
                dU = torch.as_tensor(J @ da.numpy(), dtype=dtype)  # (n_full, d + 1)
                if not model.is_settling:  # prescribed displacements ramp with the load factor
                    dU[:, -1] += model.dofmap.u_presc
                du[m, k] = dU[:, :d].reshape(model.n_nodes, 3, d)
                du_dlam[m, k] = dU[:, d].reshape(model.n_nodes, 3)
                timings["tangent"] += t1 - t0
                timings["derivatives"] += t2 - t1
                timings["solve"] += t3 - t2
    finally:
        linear.release()
    return Sensitivities(np.asarray(solution.load_factors), names, du, du_dlam, timings)
