"""Kinematic constraints as a map from independent unknowns ``a`` to nodal displacements ``u``.

    u = T a + lambda u_presc + sum_bodies (R(theta) - I) (X - X_ref)   on the rigid nodes

- clamped dofs: zero; prescribed dofs: ``lambda * value`` (the load factor scales them);
- embedded nodes (fibers): ``u_f = sum_h N_h(xi_f) u_h`` with host shape functions, a linear
  constraint even at finite strain (rows of ``T``);
- rigid node sets (a face that stays flat and undeformed): 6 unknowns per body, a translation
  ``u_ref`` (rows of ``T``) and a rotation vector ``theta`` with the exact finite rotation
  ``R = exp([theta]x)`` (Rodrigues), with its first and second derivatives in closed form
  (``rotation_jacobian``, ``rotation_work_hessian``; pinned to torch.func in the tests).

Reduced residual ``r_a = J^T r_u`` and tangent ``K_a = J^T K_u J + sum_i r_i . d2u_i/da2`` with
``J = du/da``.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from torch.func import vmap


def _csr(M: sp.csr_matrix, dtype) -> torch.Tensor:
    """A SciPy CSR matrix as a torch sparse CSR tensor (torch's beta warning silenced)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.as_tensor(M.indptr), torch.as_tensor(M.indices), torch.as_tensor(M.data, dtype=dtype),
            size=M.shape, check_invariants=False,
        )


def _skew(t: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(t[..., 0])
    return torch.stack(
        [
            torch.stack([z, -t[..., 2], t[..., 1]], -1),
            torch.stack([t[..., 2], z, -t[..., 0]], -1),
            torch.stack([-t[..., 1], t[..., 0], z], -1),
        ],
        -2,
    )


def rotation_matrix(theta: torch.Tensor) -> torch.Tensor:
    """Rodrigues ``exp([theta]x)`` for theta (3,), smooth (to all orders used here) at theta = 0."""
    a = (theta * theta).sum()
    small = a < 1e-8
    a_safe = torch.where(small, torch.ones_like(a), a)
    s = torch.sqrt(a_safe)
    A = torch.where(small, 1 - a / 6 + a * a / 120, torch.sin(s) / s)
    B = torch.where(small, 0.5 - a / 24 + a * a / 720, (1 - torch.cos(s)) / a_safe)
    W = _skew(theta)
    return torch.eye(3, dtype=theta.dtype, device=theta.device) + A * W + B * (W @ W)


def _rodrigues_coefficients(a: torch.Tensor):
    """``A = sin s / s``, ``B = (1 - cos s) / s^2`` (s^2 = a) and their first and second derivatives
    with respect to ``a``: six tensors of a's shape. Power series below a = 0.25 (where the closed
    forms lose digits to cancellation), closed forms above."""
    small = a < 0.25
    s2 = torch.where(small, torch.full_like(a, 1.0), a)
    s = torch.sqrt(s2)
    sin, cos = torch.sin(s), torch.cos(s)
    exact = (sin / s, (s * cos - sin) / (2 * s**3), (3 * sin - 3 * s * cos - s2 * sin) / (4 * s**5),
             (1 - cos) / s2, (s * sin - 2 + 2 * cos) / (2 * s2**2),
             (s2 * cos - 5 * s * sin + 8 - 8 * cos) / (4 * s2**3))
    # A = sum (-1)^n a^n / (2n+1)!, B = sum (-1)^n a^n / (2n+2)!, n < 12 (remainder < 1e-30 at a = 0.25)
    series = [torch.zeros_like(a) for _ in range(6)]
    for n in range(12):
        for off, f in ((0, math.factorial(2 * n + 1)), (3, math.factorial(2 * n + 2))):
            c = (-1) ** n / f
            series[off] = series[off] + c * a**n
            if n >= 1:
                series[off + 1] = series[off + 1] + c * n * a ** (n - 1)
            if n >= 2:
                series[off + 2] = series[off + 2] + c * n * (n - 1) * a ** (n - 2)
    return tuple(torch.where(small, sr, ex) for sr, ex in zip(series, exact))


def _levi_civita(dtype) -> torch.Tensor:
    e = torch.zeros(3, 3, 3, dtype=dtype)
    for i, j, k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        e[i, j, k], e[j, i, k] = 1.0, -1.0
    return e


def rotation_jacobian(theta: torch.Tensor) -> torch.Tensor:
    """``dR_ij / dtheta_t`` of ``rotation_matrix`` in closed form for theta (N, 3): (N, 3, 3, 3) [n, i, j, t].

    With ``R = I + A W + B W^2``, ``W = [theta]x``, ``a = |theta|^2``:
    ``dR/dtheta_t = 2 A' theta_t W + A E_t + 2 B' theta_t W^2 + B (E_t W + W E_t)``, ``E_t = [e_t]x``.
    Pinned to torch.func's ``jacfwd`` in tests/test_constraints_rotation.py."""
    a = (theta * theta).sum(-1)
    A, A1, _, B, B1, _ = _rodrigues_coefficients(a)
    W = _skew(theta)
    E = _skew(torch.eye(3, dtype=theta.dtype))  # (3 [t], 3, 3)
    W2 = W @ W
    EW = torch.einsum("tij,njk->nikt", E, W) + torch.einsum("nij,tjk->nikt", W, E)
    th = theta[:, None, None, :]
    return (2 * A1[:, None, None, None] * th * W[..., None] + A[:, None, None, None] * E.permute(1, 2, 0)[None]
            + 2 * B1[:, None, None, None] * th * W2[..., None] + B[:, None, None, None] * EW)


def rotation_work_hessian(theta: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Hessian in theta of ``f = sum_ij M_ij R_ij(theta)`` for theta (N, 3), M (N, 3, 3): (N, 3, 3).

    ``f = tr M + A (w . theta) + B q``, with ``w_k = -eps_ijk M_ij`` (so that ``sum M_ij W_ij = w . theta``),
    ``q = theta^T S theta - a tr M`` (``W^2 = theta theta^T - a I``), S = sym(M); hence
    ``H = 4 A'' (w.theta) tt^T + 2 A' ((w.theta) I + t w^T + w t^T) + 4 B'' q tt^T
    + 2 B' (q I + t g^T + g t^T) + B (2 S - 2 tr M I)`` with ``g = 2 S theta - 2 tr M theta``.
    Pinned to torch.func's ``hessian`` in tests/test_constraints_rotation.py."""
    a = (theta * theta).sum(-1)
    A, A1, A2, B, B1, B2 = _rodrigues_coefficients(a)
    w = -torch.einsum("ijk,nij->nk", _levi_civita(theta.dtype), M)
    S = 0.5 * (M + M.transpose(-1, -2))
    trM = M.diagonal(dim1=-2, dim2=-1).sum(-1)
    wt = (w * theta).sum(-1)
    q = torch.einsum("ni,nij,nj->n", theta, S, theta) - a * trM
    g = 2 * torch.einsum("nij,nj->ni", S, theta) - 2 * trM[:, None] * theta
    I = torch.eye(3, dtype=theta.dtype).expand(theta.shape[0], 3, 3)
    tt = theta[:, :, None] * theta[:, None, :]
    sc = lambda c: c[:, None, None]  # noqa: E731
    return (4 * sc(A2 * wt) * tt + 2 * sc(A1) * (sc(wt) * I + theta[:, :, None] * w[:, None, :] + w[:, :, None] * theta[:, None, :])
            + 4 * sc(B2 * q) * tt + 2 * sc(B1) * (sc(q) * I + theta[:, :, None] * g[:, None, :] + g[:, :, None] * theta[:, None, :])
            + sc(B) * (2 * S - 2 * sc(trM) * I))


@dataclass
class RigidBody:
    nodes: np.ndarray  # (k,) node indices
    X_ref: np.ndarray  # (3,)
    columns: np.ndarray  # (6,) reduced indices: 3 translations, 3 rotations
    dX: torch.Tensor  # (k, 3) node positions relative to X_ref


class DofMap:
    """Built by ``Model.finalize``; see the module docstring for the map."""

    def __init__(self, n_nodes: int, clamped: np.ndarray, prescribed: dict[int, float],
                 rigid_sets: list[np.ndarray], embedded: list[tuple[int, np.ndarray, np.ndarray]],
                 X: np.ndarray, dtype=torch.float64):
        n_full = 3 * n_nodes
        self.n_full = n_full
        role = np.zeros(n_full, dtype=np.int64)  # 0 free, 1 fixed, 2 rigid, 3 embedded
        role[clamped] = 1
        role[list(prescribed)] = 1
        for nodes in rigid_sets:
            d = (3 * nodes[:, None] + np.arange(3)).ravel()
            if np.any(role[d]):
                node = int(d[np.argmax(role[d] > 0)] // 3)
                raise ValueError(
                    f"node {node} of a rigid node set is also clamped, prescribed or in another rigid set; "
                    "a node can carry only one kind of constraint (remove it from one of the sets)"
                )
            role[d] = 2
        for node, _, _ in embedded:
            if np.any(role[3 * node : 3 * node + 3]):
                raise ValueError(f"embedded node {node} is also clamped, prescribed or rigid")
            role[3 * node : 3 * node + 3] = 3
        free = np.flatnonzero(role == 0)
        u_presc = np.zeros(n_full)
        for d, v in prescribed.items():
            u_presc[d] = v
        col_of = -np.ones(n_full, dtype=np.int64)
        col_of[free] = np.arange(free.size)
        n_red = free.size
        rows, cols, vals = [free], [col_of[free]], [np.ones(free.size)]
        self.bodies: list[RigidBody] = []
        for nodes in rigid_sets:
            columns = np.arange(n_red, n_red + 6)
            n_red += 6
            X_ref = X[nodes].mean(axis=0)
            self.bodies.append(RigidBody(nodes, X_ref, columns, torch.as_tensor(X[nodes] - X_ref, dtype=dtype)))
            for c in range(3):
                rows.append(3 * nodes + c)
                cols.append(np.full(nodes.size, columns[c]))
                vals.append(np.ones(nodes.size))
        for node, hosts, weights in embedded:
            host_dofs = 3 * hosts[:, None] + np.arange(3)
            if np.any(role[host_dofs] >= 2):
                raise ValueError(f"embedded node {node}: its host nodes must be free or clamped, not rigid or embedded")
            for c in range(3):
                hd = host_dofs[:, c]
                keep = role[hd] == 0
                rows.append(np.full(int(keep.sum()), 3 * node + c))
                cols.append(col_of[hd[keep]])
                vals.append(weights[keep])
                u_presc[3 * node + c] = weights @ u_presc[hd]
        self.n_red = n_red
        self.T = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_full, n_red)
        )
        self._T_torch = _csr(self.T, dtype)
        self._TT_torch = None
        self._T_csr_t = None
        self.u_presc = torch.as_tensor(u_presc, dtype=dtype)
        self.dtype = dtype

    # -- maps --------------------------------------------------------------------------------------
    def expand(self, a: torch.Tensor, load_factor: torch.Tensor) -> torch.Tensor:
        """a: (N, n_red), load_factor: (N,) -> u: (N, n_full)."""
        u = (self._T_torch @ a.T).T + load_factor[:, None] * self.u_presc
        for b in self.bodies:
            R = vmap(rotation_matrix)(a[:, b.columns[3:]])
            rot = torch.einsum("nij,kj->nki", R - torch.eye(3, dtype=a.dtype), b.dX)
            idx = torch.as_tensor(3 * b.nodes[:, None] + np.arange(3)).ravel()
            u = u.index_add(1, idx, rot.reshape(a.shape[0], -1))
        return u

    def reduce(self, r_full: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """J^T r: (N, n_full) -> (N, n_red)."""
        if self._TT_torch is None:
            self._TT_torch = _csr(self.T.T.tocsr(), self.dtype)
        r = (self._TT_torch @ r_full.T).T.clone()
        for b, dRdt in zip(self.bodies, self._rotation_jacobians(a)):
            r_nodes = r_full[:, torch.as_tensor(3 * b.nodes[:, None] + np.arange(3))]  # (N, k, 3)
            r[:, b.columns[3:]] += torch.einsum("nijt,kj,nki->nt", dRdt, b.dX, r_nodes)
        return r

    def _rotation_jacobians(self, a):
        return [rotation_jacobian(a[:, b.columns[3:]]) for b in self.bodies]

    def jacobian_times(self, a: torch.Tensor, V: torch.Tensor) -> torch.Tensor:
        """``J(a) V`` for every member: (N, n_full, k), with ``T V`` computed once per ``V``."""
        if getattr(self, "_TV_key", None) is not V:
            self._TV_key, self._TV = V, torch.as_tensor(self.T @ V.numpy())
        W = self._TV.expand(a.shape[0], -1, -1).clone()
        for b, dRdt in zip(self.bodies, self._rotation_jacobians(a)):
            d = torch.einsum("nijt,kj->nkit", dRdt, b.dX)  # (N, k, 3, 3): du_(node k, i) / dtheta_t
            rows = torch.as_tensor(3 * b.nodes[:, None] + np.arange(3)).ravel()
            W[:, rows] += torch.einsum("nkit,tc->nkic", d, V[torch.as_tensor(b.columns[3:])]).reshape(a.shape[0], -1, V.shape[1])
        return W

    def jacobian(self, a: torch.Tensor, transposed: bool = False) -> list[sp.csr_matrix]:
        """J = du/da per member (scipy CSR), or J^T (built as CSR directly: no format conversion
        in the products J^T K J)."""
        if self._T_csr_t is None:
            self._T_csr_t = self.T.T.tocsr()
        T = self._T_csr_t if transposed else self.T
        if not self.bodies:
            return [T] * a.shape[0]
        rows, cols, vals = [], [], []
        for b, dRdt in zip(self.bodies, self._rotation_jacobians(a)):
            d = np.einsum("nijt,kj->nkit", dRdt.numpy(), b.dX.numpy())  # (N, k, 3, 3)
            rows.append(np.repeat((3 * b.nodes[:, None] + np.arange(3)).ravel(), 3))
            cols.append(np.tile(b.columns[3:], 3 * b.nodes.size))
            vals.append(d.reshape(a.shape[0], -1))
        r, c = np.concatenate(rows), np.concatenate(cols)
        if transposed:
            r, c = c, r
        v = np.concatenate(vals, axis=1)
        return [T + sp.csr_matrix((v[n], (r, c)), shape=T.shape) for n in range(a.shape[0])]

    def geometric_stiffness(self, a: torch.Tensor, r_full: torch.Tensor) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per body, ``(columns, H)`` with H (N, 3, 3) = d2/dtheta2 of sum_i r_i . R(theta) dX_i."""
        out = []
        for b in self.bodies:
            r_nodes = r_full[:, torch.as_tensor(3 * b.nodes[:, None] + np.arange(3))]
            M = torch.einsum("nki,kj->nij", r_nodes, b.dX)
            out.append((b.columns[3:], rotation_work_hessian(a[:, b.columns[3:]], M).numpy()))
        return out
