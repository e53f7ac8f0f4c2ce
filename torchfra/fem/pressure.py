"""Pressure loads on Quad8 face sets, scaled by the load factor.

With the Abaqus face node order, ``a = x_s x x_t`` (current configuration) points into the body,
so ``n da = -a ds dt`` is the body's outward area element (Nanson: ``J F^-T N dA``).

- ``FollowerPressure``: traction ``t = -P n`` (pressure pushes on the face, Abaqus ``*DLOAD P``);
  residual ``r_a = -P int N_a (x_s x x_t) ds dt`` and its exact load stiffness (closed form: the
  face force is bilinear in the nodes; pinned to torch.func by tests).
- ``CavityPressure``: for a closed face set bounding a cavity, the conservative potential
  ``-P (V(x) - V(X))`` with ``V = 1/3 sum_faces int x . (x_s x x_t) ds dt`` (divergence theorem).
  Its gradient equals the follower residual on a closed surface; 3x3 Gauss (the default
  ``quadrature``) integrates both integrands (degree <= 5 per direction) exactly, so they agree to
  round-off. ``quadrature=2`` reproduces CalculiX's C3D20R face rule for cross-checks.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.func import vmap

from torchfra.fem.elements import as_tensor, gauss_quad, quad8_shape
from torchfra.fem.mesh import Mesh
from torchfra.fem.morph import Morphable
from torchfra.fem.terms import Term, TermOutput, node_dofs


@dataclass(frozen=True)
class _FaceRule:
    """The Quad8 Gauss rule of a face and the forms every face shares: N (Q, 8), dN (Q, 8, 2), w (Q,);
    D (8, 8, 8) with ``int N_a (x_s x x_t) ds dt = sum_bc D_abc (x_b x x_c)``, its alternating part
    D_alt, and the Levi-Civita symbol eps (3, 3, 3)."""

    N: torch.Tensor
    dN: torch.Tensor
    w: torch.Tensor
    D: torch.Tensor
    D_alt: torch.Tensor
    eps: torch.Tensor

    @classmethod
    def of(cls, quadrature: int, dtype) -> "_FaceRule":
        pts, wts = gauss_quad(quadrature)
        N, dN = quad8_shape(pts)
        N, dN, w = as_tensor(N, dtype), as_tensor(dN, dtype), as_tensor(wts, dtype)
        # the face force is bilinear in the face's nodes: int N_a (x_s x x_t) = sum_bc D_abc (x_b x x_c),
        # D_abc = sum_q w N_a dN_b/ds dN_c/dt (the same Gauss rule); the cavity volume is the cubic
        # 1/3 sum_a x_a . f_a = sum_abc (D_abc / 3) det[x_a, x_b, x_c], of which only the alternating
        # part of D counts. Residuals and tangents in closed form from these (tested against torch.func)
        D = torch.einsum("q,qa,qb,qc->abc", w, N, dN[..., 0], dN[..., 1])
        D_alt = (D + D.permute(1, 2, 0) + D.permute(2, 0, 1) - D.permute(1, 0, 2) - D.permute(0, 2, 1)
                 - D.permute(2, 1, 0)) / 6.0
        eps = torch.zeros(3, 3, 3, dtype=dtype)
        for (i, j, k), sign in (((0, 1, 2), 1), ((1, 2, 0), 1), ((2, 0, 1), 1), ((1, 0, 2), -1), ((0, 2, 1), -1),
                                ((2, 1, 0), -1)):
            eps[i, j, k] = sign
        return cls(N, dN, w, D, D_alt, eps)


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
        self.rule = _FaceRule.of(quadrature, dtype)

    # The face rule is shared by every face: kept in one container (not as array attributes, which a
    # term restricted to some of its faces would slice wherever their first length equals the number
    # of faces, e.g. D (8, 8, 8) on a set of 8 faces).
    N = property(lambda self: self.rule.N)
    dN = property(lambda self: self.rule.dN)
    w = property(lambda self: self.rule.w)
    _D = property(lambda self: self.rule.D)
    _D_alt = property(lambda self: self.rule.D_alt)
    _eps = property(lambda self: self.rule.eps)

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

    def _bilinear(self, C: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``sum_bc C_abc (x_b x x_c)``: x (..., 8, 3) -> (..., 8, 3)."""
        Y = torch.einsum("abc,...bj->...acj", C, x)
        return torch.einsum("ijk,...acj,...ck->...ai", self._eps, Y, x)

    def _bilinear_jacobian(self, C: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """d/dx_dl of ``sum_bc C_abc (x_b x x_c)_i``: x (..., 8, 3) -> (..., 24, 24)."""
        M1 = torch.einsum("adc,...ck->...adk", C, x)
        M2 = torch.einsum("abd,...bj->...adj", C, x)
        J = torch.einsum("ilk,...adk->...aidl", self._eps, M1) + torch.einsum("ijl,...adj->...aidl", self._eps, M2)
        return J.reshape(*x.shape[:-2], 24, 24)


class FollowerPressure(_FaceLoad):
    """Follower pressure ``P`` (MPa) on a face set, times the load factor (not conservative in
    general: no energy)."""

    conservative = False

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N = u.shape[0]
        x = self._reference(params, N) + u[:, self.face_conn]  # (N, B, 8, 3)
        scale = self._scale(params, load_factor)
        fe = -scale[:, None, None] * self._bilinear(self._D, x).reshape(N, -1, 24)
        Ke = None
        if tangent:
            Ke = -scale[:, None, None, None] * self._bilinear_jacobian(self._D, x)
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
        x = X + u[:, self.face_conn]  # (N, B, 8, 3)
        scale = self._scale(params, load_factor)
        # dV/dx_a = sum_bc D~_abc (x_b x x_c) with D~ the alternating part of D, d2V = 2 x that form's
        # Jacobian (an alternating form's two halves are equal)
        fe = -scale[:, None, None] * self._bilinear(self._D_alt, x).reshape(N, -1, 24)
        Ke = None
        if tangent:
            Ke = -scale[:, None, None, None] * self._bilinear_jacobian(self._D_alt, x)
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
