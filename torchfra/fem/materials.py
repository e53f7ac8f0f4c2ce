"""Solid materials as pure strain-energy functions of one Gauss point.

A material is ``psi(F, p, prm)`` in the perturbed-Lagrangian mixed form: ``F`` the deformation
gradient (3, 3), ``p`` the independent pressure-like variable (scalar), ``prm`` a dict of scalar
parameters. ``psi`` must be quadratic in ``p``; the hybrid element projects ``p`` onto its linear
element field and the displacement element eliminates it per Gauss point.

Stress and tangent are derived by ``torch.func`` (``Material.derivatives``). A material may add
a closed-form fast path; ``tests/test_materials.py`` pins every fast path to the derived one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch.func import grad, jacfwd, jvp, vmap

from torchfra.fem.kinematics import cofactor, det3
from torchfra.fem.params import ParameterError, ParameterInfo, check_parameters

__all__ = ["GaussPointTangent", "Material", "MooneyRivlin", "NeoHookean", "ParameterError", "PointDerivatives"]


@dataclass
class GaussPointTangent:
    """4th-order tangent ``A_iJkL = dP_iJ / dF_kL`` at Gauss points, dense or structured.

    Structured form: ``A = c d_ik d_JL + sum_r s_r X_r(iJ) Y_r(kL) + t H_kJ H_iL``,
    all coefficients (...,) and tensors (..., 3, 3); lets elements skip the 81-entry tensor.
    """

    dense: torch.Tensor | None = None
    c: torch.Tensor | None = None
    pairs: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = field(default_factory=list)
    swap: tuple[torch.Tensor, torch.Tensor] | None = None

    def add_pair(self, s: torch.Tensor, X: torch.Tensor, Y: torch.Tensor) -> None:
        if self.dense is not None:
            self.dense = self.dense + s[..., None, None, None, None] * torch.einsum("...ij,...kl->...ijkl", X, Y)
        else:
            self.pairs.append((s, X, Y))

    def to_dense(self) -> torch.Tensor:
        if self.dense is not None:
            return self.dense
        eye = torch.eye(3, dtype=self.c.dtype, device=self.c.device)
        A = self.c[..., None, None, None, None] * torch.einsum("ik,jl->ijkl", eye, eye)
        for s, X, Y in self.pairs:
            A = A + s[..., None, None, None, None] * torch.einsum("...ij,...kl->...ijkl", X, Y)
        if self.swap is not None:
            t, H = self.swap
            A = A + t[..., None, None, None, None] * torch.einsum("...kj,...il->...ijkl", H, H)
        return A


@dataclass
class PointDerivatives:
    """Derivatives of psi at Gauss points: P = dpsi/dF, A = d2psi/dF2, Fp = d2psi/dFdp."""

    psi: torch.Tensor | None
    P: torch.Tensor
    A: GaussPointTangent | None  # None when only a residual was asked for
    Fp: torch.Tensor


class Material:
    """Base class: subclasses define ``param_names`` and ``psi``; derivatives come from torch.func."""

    param_names: tuple[str, ...] = ()

    def psi(self, F: torch.Tensor, p: torch.Tensor, prm: dict[str, torch.Tensor]) -> torch.Tensor:
        raise NotImplementedError

    def validate(self, params: dict[str, torch.Tensor]) -> None:
        """Raise ParameterError naming the parameter and member if a value is not finite and positive."""
        for name in self.param_names:
            if name not in params:
                raise ParameterError(f"material {type(self).__name__} needs parameter '{name}'; got {sorted(params)}")
            v = params[name]
            bad = ~(torch.isfinite(v) & (v > 0))
            if bad.any():
                m = int(torch.nonzero(bad)[0, 0])
                raise ParameterError(
                    f"parameter {name} of member {m} is {float(v[m])!r}; {name} must be a finite positive number"
                )

    # -- derived path (torch.func) -------------------------------------------------------------
    def _flat_psi(self, x: torch.Tensor, prm_vec: torch.Tensor) -> torch.Tensor:
        prm = dict(zip(self.param_names, prm_vec.unbind(-1)))
        return self.psi(x[:9].reshape(3, 3), x[9], prm)

    def _stack(self, F: torch.Tensor, p: torch.Tensor, prm: dict[str, torch.Tensor]):
        shape = F.shape[:-2]
        x = torch.cat([F.reshape(*shape, 9), p.reshape(*shape, 1)], dim=-1).reshape(-1, 10)
        pv = torch.stack([prm[k].expand(shape) for k in self.param_names], dim=-1).reshape(-1, len(self.param_names))
        return shape, x, pv

    def pressure_coefficients(self, F, prm):
        """``(dpsi/dp at p = 0, d2psi/dp2)`` at Gauss points, each (...,)."""
        shape, x, pv = self._stack(F, torch.zeros(F.shape[:-2], dtype=F.dtype, device=F.device), prm)

        def dpsi_dp(xx, pp):
            g = grad(self._flat_psi)(xx, pp)
            return g[9], g[9]

        h, g = vmap(jacfwd(dpsi_dp, has_aux=True))(x, pv)
        return g.reshape(shape), h[:, 9].reshape(shape)

    def pressure_gradient(self, F, p, prm) -> torch.Tensor:
        """``d2psi/dFdp`` at Gauss points (..., 3, 3)."""
        return self.derivatives(F, p, prm, tangent=False).Fp

    def derivatives(self, F, p, prm, with_energy: bool = False, tangent: bool = True) -> PointDerivatives:
        """Derived path: gradient and hessian of psi at each Gauss point by ``vmap(jacfwd(grad))``.
        ``tangent=False`` (a residual) skips the hessian: the stress by ``grad`` and ``d2psi/dFdp``
        by one forward-mode derivative of it along p (``A`` is then None)."""
        shape, x, pv = self._stack(F, p, prm)
        psi = vmap(self._flat_psi)(x, pv).reshape(shape) if with_energy else None
        if not tangent:
            e_p = torch.zeros_like(x)
            e_p[:, 9] = 1.0

            def g_and_gp(xx, pp, ee):
                return jvp(lambda y: grad(self._flat_psi)(y, pp), (xx,), (ee,))

            g, gp = vmap(g_and_gp)(x, pv, e_p)
            return PointDerivatives(psi, g[:, :9].reshape(*shape, 3, 3), None, gp[:, :9].reshape(*shape, 3, 3))

        def g2(xx, pp):
            g = grad(self._flat_psi)(xx, pp)
            return g, g

        H, g = vmap(jacfwd(g2, has_aux=True))(x, pv)
        P = g[:, :9].reshape(*shape, 3, 3)
        A = H[:, :9, :9].reshape(*shape, 3, 3, 3, 3)
        Fp = H[:, :9, 9].reshape(*shape, 3, 3)
        return PointDerivatives(psi, P, GaussPointTangent(dense=A), Fp)


class _PerturbedLagrangeVolume(Material):
    """The volumetric part ``p (J - 1) - p^2 / (2K)``, ``K = 2 / D1``, shared by the hyperelastic
    bodies: its pressure coefficients and gradient in closed form (``fast``), else derived."""

    fast: bool = True

    def pressure_coefficients(self, F, prm):
        if not self.fast:
            return super().pressure_coefficients(F, prm)
        J = det3(F)
        return J - 1.0, (-0.5 * prm["D1"]).expand_as(J)

    def pressure_gradient(self, F, p, prm):
        return cofactor(F) if self.fast else super().pressure_gradient(F, p, prm)


class NeoHookean(_PerturbedLagrangeVolume):
    r"""Abaqus Neo-Hookean in the perturbed-Lagrangian mixed form (paper Eq. 1).

    .. math::
        \psi(F, p) = C_{10} (\bar I_1 - 3) + p (J - 1) - \frac{p^2}{2K}, \qquad K = 2 / D_1,

    with :math:`\bar I_1 = J^{-2/3} \operatorname{tr}(F^T F)`. Eliminating ``p`` gives the Abaqus
    energy :math:`C_{10}(\bar I_1 - 3) + (J - 1)^2 / D_1`; initial shear modulus
    :math:`\mu = 2 C_{10}`. Units: C10 in MPa, D1 in 1/MPa, psi in MPa (= mJ/mm^3).

    ``fast=True`` (default) evaluates stress and tangent in closed form (with ``H = F^{-T}``,
    ``c = 2 C10 J^{-2/3}``):

    - ``P = c (F - I1/3 H) + p J H``
    - ``A = c d_ik d_JL - 2c/3 (F x H + H x F) + (2c I1/9 + pJ) H x H + (c I1/3 - pJ) H_kJ H_iL``.
    """

    param_names = ("C10", "D1")
    parameters = {
        "C10": ParameterInfo("C10", "MPa", None, 0.0, math.inf, "shear modulus mu = 2 C10", low_inclusive=False),
        "D1": ParameterInfo(
            "D1", "1/MPa", 0.0, 0.0, math.inf,
            "compressibility, K = 2/D1; null 0 is the incompressible limit, which the hybrid element reaches "
            "as D1 -> 0 (the actuator model stands in with D1 = 1/(1000 C10)); nu >= 0 needs D1 <= 3/(2 C10)",
            low_inclusive=False,
        ),
    }

    def __init__(self, fast: bool = True):
        self.fast = fast

    def psi(self, F, p, prm):
        J = det3(F)
        I1bar = J ** (-2.0 / 3.0) * (F * F).sum((-1, -2))
        K = 2.0 / prm["D1"]
        return prm["C10"] * (I1bar - 3.0) + p * (J - 1.0) - p**2 / (2.0 * K)


    def derivatives(self, F, p, prm, with_energy: bool = False, tangent: bool = True) -> PointDerivatives:
        if not self.fast:
            return super().derivatives(F, p, prm, with_energy, tangent)
        cof = cofactor(F)
        J = (F * cof).sum((-1, -2)) / 3.0
        H = cof / J[..., None, None]
        I1 = (F * F).sum((-1, -2))
        C10 = prm["C10"]
        c = 2.0 * C10 * J ** (-2.0 / 3.0)
        P = c[..., None, None] * (F - (I1 / 3.0)[..., None, None] * H) + p[..., None, None] * cof
        pJ = p * J
        A = GaussPointTangent(c=c)
        A.add_pair(-2.0 / 3.0 * c, F, H)
        A.add_pair(-2.0 / 3.0 * c, H, F)
        A.add_pair(2.0 / 9.0 * c * I1 + pJ, H, H)
        A.swap = (c * I1 / 3.0 - pJ, H)
        psi = None
        if with_energy:
            K = 2.0 / prm["D1"]
            psi = C10 * (J ** (-2.0 / 3.0) * I1 - 3.0) + p * (J - 1.0) - p**2 / (2.0 * K)
        return PointDerivatives(psi, P, A, cof)


class MooneyRivlin(_PerturbedLagrangeVolume):
    r"""Abaqus Mooney-Rivlin in the perturbed-Lagrangian mixed form (second invariant candidate).

    .. math::
        \psi(F, p) = C_{10} (\bar I_1 - 3) + C_{01} (\bar I_2 - 3) + p (J - 1) - \frac{p^2}{2K},
        \qquad K = 2 / D_1,

    with :math:`\bar I_1 = J^{-2/3} I_1`, :math:`\bar I_2 = J^{-4/3} I_2`,
    :math:`I_1 = \operatorname{tr} C`, :math:`I_2 = \tfrac12 (I_1^2 - \operatorname{tr} C^2)`,
    :math:`C = F^T F`. Eliminating ``p`` gives the Abaqus/CalculiX energy
    :math:`C_{10}(\bar I_1 - 3) + C_{01}(\bar I_2 - 3) + (J - 1)^2 / D_1`; initial shear modulus
    :math:`\mu = 2 (C_{10} + C_{01})`. Incompressible uniaxial tension at stretch ``lam``:
    Cauchy stress :math:`\sigma = 2 (\lambda^2 - 1/\lambda)(C_{10} + C_{01}/\lambda)`.
    Units: C10, C01 in MPa, D1 in 1/MPa, psi in MPa (= mJ/mm^3).

    Null: ``C01 = 0`` is exactly :class:`NeoHookean` (same energy, same stress and tangent).
    Admissible: ``C10 > 0``, ``C01 >= 0`` (polyconvex, stable in every deformation).

    ``fast=True`` (default) evaluates stress and tangent in closed form (``derivatives``; pinned to
    the torch.func-derived path of ``fast=False`` in tests/test_materials.py); the pressure terms are
    those of Neo-Hookean: ``dpsi/dp = J - 1``, ``d2psi/dp2 = -D1/2``, ``d2psi/dFdp = cof F``.
    """

    param_names = ("C10", "C01", "D1")
    parameters = {
        "C10": NeoHookean.parameters["C10"],
        "C01": ParameterInfo("C01", "MPa", 0.0, 0.0, math.inf,
                             "second-invariant modulus; mu = 2 (C10 + C01); C01 >= 0 keeps psi polyconvex"),
        "D1": NeoHookean.parameters["D1"],
    }

    def __init__(self, fast: bool = True):
        self.fast = fast

    def validate(self, params):
        check_parameters(self.parameters, params, f"material {type(self).__name__}")

    def psi(self, F, p, prm):
        J = det3(F)
        C = F.transpose(-1, -2) @ F
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        I2 = 0.5 * (I1**2 - (C * C).sum((-1, -2)))
        K = 2.0 / prm["D1"]
        return (prm["C10"] * (J ** (-2.0 / 3.0) * I1 - 3.0) + prm["C01"] * (J ** (-4.0 / 3.0) * I2 - 3.0)
                + p * (J - 1.0) - p**2 / (2.0 * K))

    def derivatives(self, F, p, prm, with_energy: bool = False, tangent: bool = True) -> PointDerivatives:
        """``fast``: closed form. With ``H = F^{-T}``, ``B = F F^T``, ``C = F^T F``, ``G = 2 (I1 F - F C)``
        (= dI2/dF), ``c = 2 C10 J^{-2/3}``, ``d = C01 J^{-4/3}``, ``Q = G - 4/3 I2 H``:

        - ``P = c (F - I1/3 H) + d Q + p J H``
        - ``A = A_NeoHookean + d [-4/3 Q x H - 4/3 H x G + 4 F x F + 2 I1 d_ik d_JL - 2 d_ik C_LJ
          - 2 F_iL F_kJ - 2 B_ik d_JL + 4/3 I2 H_iL H_kJ]`` (dense: the last terms have no rank-one form).
        """
        if not self.fast:
            return super().derivatives(F, p, prm, with_energy, tangent)
        nh = NeoHookean(fast=True).derivatives(F, p, {"C10": prm["C10"], "D1": prm["D1"]}, with_energy, tangent)
        cof = nh.Fp
        J = (F * cof).sum((-1, -2)) / 3.0
        H = cof / J[..., None, None]
        C = F.transpose(-1, -2) @ F
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        I2 = 0.5 * (I1**2 - (C * C).sum((-1, -2)))
        G = 2.0 * (I1[..., None, None] * F - F @ C)
        Q = G - (4.0 / 3.0 * I2)[..., None, None] * H
        d = prm["C01"] * J ** (-4.0 / 3.0)
        P = nh.P + d[..., None, None] * Q
        psi = None if nh.psi is None else nh.psi + prm["C01"] * (J ** (-4.0 / 3.0) * I2 - 3.0)
        if not tangent:
            return PointDerivatives(psi, P, None, cof)
        eye = torch.eye(3, dtype=F.dtype, device=F.device)
        B = F @ F.transpose(-1, -2)
        outer = lambda X, Y: torch.einsum("...ij,...kl->...ijkl", X, Y)  # noqa: E731
        A01 = (-4.0 / 3.0 * (outer(Q, H) + outer(H, G)) + 4.0 * outer(F, F)
               + (2.0 * I1)[..., None, None, None, None] * torch.einsum("ik,jl->ijkl", eye, eye)
               - 2.0 * torch.einsum("ik,...lj->...ijkl", eye, C) - 2.0 * torch.einsum("...il,...kj->...ijkl", F, F)
               - 2.0 * torch.einsum("...ik,jl->...ijkl", B, eye)
               + (4.0 / 3.0 * I2)[..., None, None, None, None] * torch.einsum("...il,...kj->...ijkl", H, H))
        A = nh.A.to_dense() + d[..., None, None, None, None] * A01
        return PointDerivatives(psi, P, GaussPointTangent(dense=A), cof)

