"""Compliant support of a face (compliant-clamping candidate): distributed linear springs.

    W(u) = 1/2 int_A0 (k_n u_n^2 + k_t |u_t|^2) dA,   u_n = u . N,   u_t = u - u_n N,
    k_n = 1 / c_n,   k_t = 1 / c_t,

with N the unit normal of the reference face: a Winkler foundation whose springs keep their
reference directions (the base of an actuator moves little, so fixed directions suffice).
Units: stiffness per area k (N/mm^3: traction in MPa per mm of displacement), compliance
c = 1/k (mm^3/N), W in mJ.

The clamp is the limit k -> infinity, so the term is parametrized by compliances: their null
c = 0 is the clamped base and is handled by clamping the face instead of adding this term
(``support_face``); every member of one model shares that choice. A member with c > 0 converges
to the clamped answer as c -> 0 (tests/test_candidates_closed_form.py).

W is quadratic in u, so the element matrices ``K_n = d2/du2 (1/2 int u_n^2 dA)`` and
``K_t = d2/du2 (1/2 int |u_t|^2 dA)`` are derived once by torch.func; the residual is
``(k_n K_n + k_t K_t) u_e`` and the tangent ``k_n K_n + k_t K_t``.
"""
from __future__ import annotations

import math

import torch
from torch.func import hessian, vmap

from torchfra.fem.elements import as_tensor, gauss_quad, quad8_shape
from torchfra.fem.mesh import Mesh
from torchfra.fem.params import ParameterInfo, check_parameters
from torchfra.fem.terms import Term, TermOutput, node_dofs

_COMPLIANCE = "{} compliance of the support, 1/k; null 0 = clamped (clamp the face instead of adding the term)"


class ElasticSupport(Term):
    """Linear springs per unit area on a face set, normal and tangential to the reference face.

    normal / tangential: names of the compliance parameters c_n, c_t (mm^3/N); ``None`` leaves
    that part out (e.g. normal springs on a face whose tangential motion is clamped or free).
    quadrature: Gauss points per direction (3: exact for ``N_a N_b`` on flat parallelogram faces).
    """

    kind = "internal"
    parameters = {
        "c_n": ParameterInfo("c_n", "mm^3/N", 0.0, 0.0, math.inf, _COMPLIANCE.format("normal"), low_inclusive=False),
        "c_t": ParameterInfo("c_t", "mm^3/N", 0.0, 0.0, math.inf, _COMPLIANCE.format("tangential"),
                             low_inclusive=False),
    }

    def __init__(self, mesh: Mesh, face_set: str, normal: str | None = "c_n", tangential: str | None = "c_t",
                 quadrature: int = 3, dtype=torch.float64):
        if normal is None and tangential is None:
            raise ValueError("ElasticSupport needs a normal or a tangential compliance (or both)")
        self.face_set = face_set
        self.normal, self.tangential = normal, tangential
        self.param_names = tuple(n for n in (normal, tangential) if n is not None)
        self.parameters = {
            name: ElasticSupport.parameters[key].renamed(name)
            for key, name in (("c_n", normal), ("c_t", tangential)) if name is not None
        }
        nodes = mesh.face_nodes(face_set)
        if nodes.shape[0] == 0:
            raise ValueError(f"face set '{face_set}' is empty")
        self.face_conn = torch.as_tensor(nodes)
        self.dofs = node_dofs(nodes)
        X = as_tensor(mesh.nodes[nodes], dtype)  # (B, 8, 3)
        pts, wts = gauss_quad(quadrature)
        N, dN = quad8_shape(pts)
        self._N, self._w = as_tensor(N, dtype), as_tensor(wts, dtype)
        xs = torch.einsum("qa,bai->bqi", as_tensor(dN[..., 0], dtype), X)
        xt = torch.einsum("qa,bai->bqi", as_tensor(dN[..., 1], dtype), X)
        a = torch.linalg.cross(xs, xt, dim=-1)
        self.dA = self._w * torch.linalg.norm(a, dim=-1)  # (B, Q) reference area weights, mm^2
        self.unit_normal = -a / torch.linalg.norm(a, dim=-1, keepdim=True)  # (B, Q, 3) outward
        self.area = float(self.dA.sum())
        zeros = torch.zeros(nodes.shape[0], 8, 3, dtype=dtype)
        self.K_n = vmap(hessian(self._normal_energy))(zeros, self.unit_normal, self.dA).reshape(-1, 24, 24)
        self.K_t = vmap(hessian(self._tangential_energy))(zeros, self.unit_normal, self.dA).reshape(-1, 24, 24)

    def _normal_energy(self, u_f, n, dA):
        """1/2 int u_n^2 dA of one face (per unit k_n). u_f: (8, 3); n: (Q, 3); dA: (Q,)."""
        un = ((self._N @ u_f) * n).sum(-1)
        return 0.5 * (dA * un**2).sum()

    def _tangential_energy(self, u_f, n, dA):
        """1/2 int |u - u_n N|^2 dA of one face (per unit k_t)."""
        uq = self._N @ u_f
        ut = uq - (uq * n).sum(-1, keepdim=True) * n
        return 0.5 * (dA * (ut * ut).sum(-1)).sum()

    def validate(self, params):
        check_parameters(self.parameters, params, f"ElasticSupport on '{self.face_set}'")

    def stiffness(self, params) -> torch.Tensor:
        """Element matrices ``k_n K_n + k_t K_t`` of all members, (N, B, 24, 24)."""
        K = 0.0
        if self.normal is not None:
            K = K + (1.0 / params[self.normal])[:, None, None, None] * self.K_n
        if self.tangential is not None:
            K = K + (1.0 / params[self.tangential])[:, None, None, None] * self.K_t
        return K

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N = u.shape[0]
        K = self.stiffness(params)
        u_e = u[:, self.face_conn].reshape(N, -1, 24)
        fe = torch.einsum("nbij,nbj->nbi", K, u_e)
        W = 0.5 * torch.einsum("nbi,nbi->n", fe, u_e) if energy else None
        return TermOutput(fe, K if tangent else None, W, torch.ones(N, dtype=torch.bool, device=u.device))


def support_face(model, face_set: str, compliant: bool, normal: str | None = "c_n", tangential: str | None = "c_t"):
    """Support a face of an unfinalized model: clamped (the null, c = 0) or on ``ElasticSupport``
    springs (c > 0). Components without springs (``normal``/``tangential`` None) are left free.
    Returns the added term, or None when clamped."""
    if not compliant:
        model.clamp(face_set)
        return None
    return model.add(ElasticSupport(model.mesh, face_set, normal, tangential, dtype=model.dtype))
