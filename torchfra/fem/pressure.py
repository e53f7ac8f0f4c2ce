"""Pressure loads on Quad8 face sets, scaled by the load factor.

With the Abaqus face node order, ``a = x_s x x_t`` (current configuration) points into the body,
so ``n da = -a ds dt`` is the body's outward area element (Nanson: ``J F^-T N dA``).

- ``FollowerPressure``: traction ``t = -P n`` (pressure pushes on the face, Abaqus ``*DLOAD P``);
  residual ``r_a = -P int N_a (x_s x x_t) ds dt`` and its exact load stiffness (torch.func).
- ``CavityPressure``: for a closed face set bounding a cavity, the conservative potential
  ``-P (V(x) - V(X))`` with ``V = 1/3 sum_faces int x . (x_s x x_t) ds dt`` (divergence theorem).
  Its gradient equals the follower residual on a closed surface; 3x3 Gauss (the default
  ``quadrature``) integrates both integrands (degree <= 5 per direction) exactly, so they agree to
  round-off. ``quadrature=2`` reproduces CalculiX's C3D20R face rule for cross-checks.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.func import grad, jacfwd, vmap

from .elements import as_tensor, gauss_quad, quad8_shape
from .mesh import Mesh
from .morph import Morphable
from .terms import Term, TermOutput, node_dofs


class _FaceLoad(Morphable, Term):
    kind = "load"

    def __init__(self, mesh: Mesh, face_set: str, pressure: str = "P", quadrature: int = 3, dtype=torch.float64):
        self.face_set = face_set
        self.param_names = (pressure,)
        self.pressure = pressure
        nodes = mesh.face_nodes(face_set)
        if nodes.shape[0] == 0:
            raise ValueError(f"face set '{face_set}' is empty")
        self.face_conn = torch.as_tensor(nodes)
        self.dofs = node_dofs(nodes)
        self.X = as_tensor(mesh.nodes[nodes], dtype)  # (B, 8, 3)
        pts, wts = gauss_quad(quadrature)
        N, dN = quad8_shape(pts)
        self.N, self.dN, self.w = as_tensor(N, dtype), as_tensor(dN, dtype), as_tensor(wts, dtype)

    def _morph_nodes(self):
        return self.face_conn.numpy()

    def _reference(self, params, N: int) -> torch.Tensor:
        """Reference face nodes of every member, (N, B, 8, 3) (broadcast (B, 8, 3) without a morph)."""
        return self.morphed_reference(params) if self.morph_names else self.X

    def area_vectors(self, x: torch.Tensor) -> torch.Tensor:
        """``x_s x x_t`` at the face Gauss points. x: (..., 8, 3) -> (..., Q, 3)."""
        xs = torch.einsum("qa,...ai->...qi", self.dN[..., 0], x)
        xt = torch.einsum("qa,...ai->...qi", self.dN[..., 1], x)
        return torch.linalg.cross(xs, xt, dim=-1)

    def _face_force(self, x: torch.Tensor) -> torch.Tensor:
        """int N_a (x_s x x_t) ds dt for one face. x: (8, 3) -> (8, 3)."""
        return torch.einsum("q,qa,qi->ai", self.w, self.N, self.area_vectors(x))

    def _scale(self, params, load_factor):
        return load_factor * params[self.pressure]  # (N,)


class FollowerPressure(_FaceLoad):
    """Follower pressure ``P`` (MPa) on a face set, times the load factor (not conservative in
    general: no energy)."""

    conservative = False

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N = u.shape[0]
        x = self._reference(params, N) + u[:, self.face_conn]  # (N, B, 8, 3)
        scale = self._scale(params, load_factor)
        flat = x.reshape(-1, 8, 3)
        fe = -scale[:, None, None] * vmap(self._face_force)(flat).reshape(N, -1, 24)
        Ke = None
        if tangent:
            K = vmap(jacfwd(self._face_force))(flat).reshape(N, -1, 24, 24)
            Ke = -scale[:, None, None, None] * K
        ok = torch.ones(N, dtype=torch.bool, device=u.device)
        return TermOutput(fe, Ke, None, ok)


class CavityPressure(_FaceLoad):
    """Pressure ``P`` (MPa) in a closed cavity bounded by a face set, as the conservative
    potential ``-lambda P (V - V0)``; ``cavity_volume`` reports V (mm^3)."""

    def __init__(self, mesh: Mesh, face_set: str, pressure: str = "P", quadrature: int = 3, dtype=torch.float64):
        check_closed(mesh, face_set)
        super().__init__(mesh, face_set, pressure, quadrature, dtype)

    def _face_volume(self, x: torch.Tensor) -> torch.Tensor:
        return torch.einsum("q,qi,qi->", self.w, torch.einsum("qa,ai->qi", self.N, x), self.area_vectors(x)) / 3.0

    def cavity_volume(self, u: torch.Tensor, params: dict | None = None) -> torch.Tensor:
        """u: (N, n_nodes, 3) -> V (N,) (``params`` carry the morphs, if any)."""
        x = self._reference(params, u.shape[0]) + u[:, self.face_conn]
        return vmap(self._face_volume)(x.reshape(-1, 8, 3)).reshape(u.shape[0], -1).sum(1)

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N = u.shape[0]
        X = self._reference(params, N)
        x = (X + u[:, self.face_conn]).reshape(-1, 8, 3)
        scale = self._scale(params, load_factor)
        fe = -scale[:, None, None] * vmap(grad(self._face_volume))(x).reshape(N, -1, 24)
        Ke = None
        if tangent:
            H = vmap(jacfwd(grad(self._face_volume)))(x).reshape(N, -1, 24, 24)
            Ke = -scale[:, None, None, None] * H
        W = None
        if energy:
            V0 = vmap(self._face_volume)(X.expand(N, -1, -1, -1).reshape(-1, 8, 3)).reshape(N, -1).sum(1)
            W = -scale * (self.cavity_volume(u, params) - V0)
        ok = torch.ones(N, dtype=torch.bool, device=u.device)
        return TermOutput(fe, Ke, W, ok)


def check_closed(mesh: Mesh, face_set: str) -> None:
    """Raise if a face set is not a closed surface (every face edge must be shared by two faces)."""
    quads = mesh.face_nodes(face_set)[:, :4]
    edges = np.sort(np.stack([quads, np.roll(quads, -1, axis=1)], axis=-1).reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if np.any(counts != 2):
        raise ValueError(
            f"face set '{face_set}' is not closed ({int(np.sum(counts == 1))} free edges): "
            "CavityPressure needs a closed cavity surface; use FollowerPressure for open surfaces"
        )
