"""Geometric imperfections as a smooth morph of the reference mesh.

A member's reference coordinates are ``X(s) = X0 + s * phi(X0)``: one scalar parameter ``s`` (mm)
per morph, one nodal field ``phi`` (dimensionless, the displacement of the reference geometry per
unit ``s``). Every member keeps the mesh's topology, so an ensemble whose members carry different
imperfections is still solved in one batched Newton, and the sensitivities to ``s`` come from the
same forward-mode differentiation as every other parameter (the element geometry is computed from
``X(s)`` inside the terms).

``harmonic_field`` builds ``phi`` by harmonic extension: ``phi = direction`` on the nodes that move
(e.g. a cavity's surface: the mould core sat off its nominal place), ``0`` on the nodes that stay
(outer surfaces, supports), and the solution of Laplace's equation on the mesh in between (the
finite element Laplacian on the mesh's own Hex20 elements), so the material between the two moves
smoothly and embedded nodes (fibers) follow the host material they sit in.

A model carrying a morph evaluates its morphed terms member by member (each member its own element
geometry); a model without one is untouched (no cost when the candidate is off).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from torchfra.fem.elements import gauss_hex, hex20_shape
from torchfra.fem.mesh import Mesh


class MorphError(ValueError):
    """A morph that would tear the model: it moves constrained nodes or inverts an element."""


def harmonic_field(mesh: Mesh, moving: np.ndarray, fixed: np.ndarray, direction=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Nodal field (n_nodes, 3): ``direction`` on ``moving`` nodes, zero on ``fixed`` nodes, harmonic
    (finite element Laplace, 2x2x2 Gauss on the Hex20 elements) elsewhere."""
    moving = np.unique(np.asarray(moving, dtype=np.int64))
    fixed = np.unique(np.asarray(fixed, dtype=np.int64))
    if moving.size == 0:
        raise MorphError("the morph moves no node: give the nodes of the surface that moves")
    if fixed.size == 0:
        raise MorphError("the morph fixes no node: give the nodes that stay (outer surfaces, supports)")
    both = np.intersect1d(moving, fixed)
    if both.size:
        raise MorphError(f"nodes {both[:5].tolist()} are both moving and fixed; the morph would tear the mesh there")
    d = np.asarray(direction, dtype=np.float64).reshape(-1)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise MorphError(f"the morph direction must be a finite 3-vector, got {direction!r}")
    pts, wts = gauss_hex(2)
    _, dN = hex20_shape(pts)
    X = mesh.nodes[mesh.elements]  # (E, 20, 3)
    jac = np.einsum("eai,gaj->egij", X, dN)
    det = np.linalg.det(jac)
    dN_dX = np.einsum("gaj,egji->egai", dN, np.linalg.inv(jac))
    Ke = np.einsum("g,eg,egai,egbi->eab", wts, det, dN_dX, dN_dX)  # (E, 20, 20)
    rows = np.repeat(mesh.elements, 20, axis=1).ravel()
    cols = np.tile(mesh.elements, (1, 20)).ravel()
    n = mesh.n_nodes
    K = sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))
    w = np.zeros(n)
    w[moving] = 1.0
    known = np.zeros(n, dtype=bool)
    known[moving] = known[fixed] = True
    free = np.flatnonzero(~known)
    if free.size:
        rhs = -(K[free][:, np.flatnonzero(known)] @ w[known])
        w[free] = spla.spsolve(K[free][:, free].tocsc(), rhs)
    return w[:, None] * d[None, :]


def inverted_elements(mesh: Mesh, field: np.ndarray, s: float, points: int = 3) -> np.ndarray:
    """Elements whose Jacobian determinant is not positive at some Gauss point (``points`` per
    direction) of the morphed mesh ``X0 + s field``; empty when the morph keeps every element valid."""
    pts, _ = gauss_hex(points)
    _, dN = hex20_shape(pts)
    X = (mesh.nodes + s * np.asarray(field)[: mesh.n_nodes])[mesh.elements]
    det = np.linalg.det(np.einsum("eai,gaj->egij", X, dN))
    return np.flatnonzero((det <= 0).any(axis=1))


class Morphable:
    """Mixin of terms whose element geometry follows the model's morphs.

    ``set_morph`` is called by :meth:`Model.finalize` with the model's reference coordinates and its
    morph fields (n_nodes, 3, K); the term keeps, per block, its nodes' reference coordinates
    ``_X0`` (B, A, 3) and fields ``_phi`` (B, A, 3, K) (first dimension over blocks, so a term
    restricted to some blocks keeps the matching rows)."""

    morph_names: tuple[str, ...] = ()

    def _morph_nodes(self):
        raise NotImplementedError

    def set_morph(self, names, X: np.ndarray, fields: np.ndarray, dtype) -> None:
        import torch

        nodes = np.asarray(self._morph_nodes())
        self.morph_names = tuple(names)
        self.param_names = tuple(self.param_names) + tuple(n for n in names if n not in self.param_names)
        self._X0 = torch.as_tensor(X[nodes], dtype=dtype)
        self._phi = torch.as_tensor(fields[nodes], dtype=dtype)

    def morphed_reference(self, params):
        """Reference coordinates of every member's blocks, (N, B, A, 3)."""
        import torch

        s = torch.stack([params[n] for n in self.morph_names], dim=-1)  # (N, K)
        return self._X0 + torch.einsum("baik,nk->nbai", self._phi, s)
