"""Hex20 solid bodies: hybrid u-p (C3D20RH analogue) and displacement-only (C3D20R) bricks.

Both use 2x2x2 (reduced) Gauss integration. The hybrid brick carries an element-discontinuous
linear pressure ``p = p0 + p1 xi + p2 eta + p3 zeta`` (4 dofs per element). Because ``psi`` is
quadratic in ``p`` and ``p`` is element-local, ``p`` is condensed exactly: for every displacement
field it is the element's stationary point

    K_pp p = -r_p0,   K_pp = sum_g w psi_pp N_p N_p^T,   r_p0 = sum_g w dpsi/dp(F, 0) N_p,

(for Neo-Hookean: the L2 projection of K (J - 1) on the linear field), and the condensed tangent is
``K_uu - K_up K_pp^-1 K_pu``. Newton then runs on displacements only and the total potential stays
well defined (energy norms, line search). The displacement-only brick eliminates ``p`` per Gauss
point instead, which gives back ``C10 (I1bar - 3) + (J - 1)^2 / D1``.
"""
from __future__ import annotations

import numpy as np
import torch

from .elements import as_tensor, gauss_hex, hex20_shape, linear_pressure_modes
from .kinematics import deformation_gradient, det3
from .materials import GaussPointTangent, Material
from .mesh import Mesh
from .terms import Term, TermOutput, node_dofs


class Hex20Solid(Term):
    """A material body on (a subset of) the Hex20 elements of a mesh.

    formulation: ``"hybrid"`` (C3D20RH analogue) or ``"displacement"`` (C3D20R analogue).
    """

    kind = "internal"

    def __init__(self, mesh: Mesh, material: Material, formulation: str = "hybrid", elements=None, dtype=torch.float64):
        if formulation not in ("hybrid", "displacement"):
            raise ValueError(f"formulation must be 'hybrid' or 'displacement', got {formulation!r}")
        self.material, self.formulation = material, formulation
        self.param_names = material.param_names
        self.element_ids = np.arange(mesh.n_elements) if elements is None else np.asarray(elements)
        conn = mesh.elements[self.element_ids]
        self.conn = torch.as_tensor(conn)
        self.dofs = node_dofs(conn)
        pts, wts = gauss_hex(2)
        _, dN = hex20_shape(pts)
        X = mesh.nodes[conn]
        jac = np.einsum("eai,gaj->egij", X, dN)  # dX_i / dxi_j
        det = np.linalg.det(jac)
        dN_dX = np.einsum("gaj,egji->egai", dN, np.linalg.inv(jac))
        self.dN_dX = as_tensor(dN_dX, dtype)  # (E, G, 20, 3)
        self.wdet = as_tensor(wts[None] * det, dtype)  # (E, G)
        self.Np = as_tensor(linear_pressure_modes(pts), dtype)  # (G, 4)
        self.volume = float(self.wdet.sum())

    def validate(self, params):
        self.material.validate(params)

    def _pressure(self, F, prm):
        """Condensed pressure at the Gauss points and -K_pp^-1 (hybrid) or -1/psi_pp (displacement)."""
        d, h = self.material.pressure_coefficients(F, prm)
        if self.formulation == "displacement":
            return -d / h, -1.0 / h
        w = self.wdet
        Kpp = torch.einsum("eg,neg,gm,gk->nemk", w, h, self.Np, self.Np)
        rp0 = torch.einsum("eg,neg,gm->nem", w, d, self.Np)
        Kpp_inv = torch.linalg.inv(Kpp)
        p_e = -torch.einsum("nemk,nek->nem", Kpp_inv, rp0)
        return torch.einsum("gm,nem->neg", self.Np, p_e), -Kpp_inv

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        prm = {k: params[k][:, None, None] for k in self.param_names}
        F = deformation_gradient(u[:, self.conn], self.dN_dX)
        J = det3(F)
        ok = (J > 0).flatten(1).all(dim=1)
        p, cond = self._pressure(F, prm)
        d = self.material.derivatives(F, p, prm, with_energy=energy)
        w, dN = self.wdet, self.dN_dX
        N, E = F.shape[:2]
        fe = torch.einsum("eg,negij,egaj->neai", w, d.P, dN).reshape(N, E, 60)
        psi = torch.einsum("eg,neg->n", w, d.psi) if energy else None
        Ke = None
        if tangent:
            A = d.A
            if self.formulation == "displacement":
                A.add_pair(cond, d.Fp, d.Fp)
            Ke = _material_tangent(A, w, dN)
            if self.formulation == "hybrid":
                G = torch.einsum("eg,gm,negkl,egbl->nembk", w, self.Np, d.Fp, dN).reshape(N, E, 4, 60)
                Ke = Ke + torch.einsum("nema,nemk,nekb->neab", G, cond, G)
        return TermOutput(fe, Ke, psi, ok)


def _material_tangent(A: GaussPointTangent, w: torch.Tensor, dN: torch.Tensor) -> torch.Tensor:
    """Element tangent ``K[a i, b k] = sum_g w dN_aJ A_iJkL dN_bL`` -> (N, E, 60, 60)."""
    if A.dense is not None:
        N, E = A.dense.shape[:2]
        AdN = torch.einsum("negijkl,egbl->negijbk", A.dense, dN)
        return torch.einsum("eg,egaj,negijbk->neaibk", w, dN, AdN).reshape(N, E, 60, 60)
    N, E = A.c.shape[:2]
    nodal = torch.einsum("eg,neg,egaj,egbj->neab", w, A.c, dN, dN)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    Ke = torch.einsum("neab,ik->neaibk", nodal, eye).reshape(N, E, 60, 60)
    for s, X, Y in A.pairs:
        x = torch.einsum("egaj,negij->negai", dN, X).reshape(N, E, -1, 60)
        y = torch.einsum("egaj,negij->negai", dN, Y).reshape(N, E, -1, 60)
        Ke = Ke + torch.einsum("neg,negp,negq->nepq", w * s, x, y)
    if A.swap is not None:
        t, H = A.swap
        h = torch.einsum("egaj,negkj->negak", dN, H).reshape(N, E, -1, 60)
        swap = torch.einsum("neg,negp,negq->nepq", w * t, h, h).reshape(N, E, 20, 3, 20, 3)
        Ke = Ke + swap.permute(0, 1, 2, 5, 4, 3).reshape(N, E, 60, 60)
    return Ke
