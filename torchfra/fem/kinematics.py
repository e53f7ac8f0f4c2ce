"""Small batched tensor kinematics written out by cofactors.

``torch.linalg.det`` inside nested ``torch.func`` transforms was slow and once produced NaN
(DESIGN §5), so the 3x3 determinant and cofactor are explicit polynomials here.
"""
from __future__ import annotations

import torch


def cofactor(F: torch.Tensor) -> torch.Tensor:
    """Cofactor matrix ``cof F = dJ/dF = J F^-T``. F: (..., 3, 3) -> (..., 3, 3)."""
    a, b, c = F[..., 0, 0], F[..., 0, 1], F[..., 0, 2]
    d, e, f = F[..., 1, 0], F[..., 1, 1], F[..., 1, 2]
    g, h, i = F[..., 2, 0], F[..., 2, 1], F[..., 2, 2]
    rows = [
        torch.stack([e * i - f * h, f * g - d * i, d * h - e * g], dim=-1),
        torch.stack([c * h - b * i, a * i - c * g, b * g - a * h], dim=-1),
        torch.stack([b * f - c * e, c * d - a * f, a * e - b * d], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def det3(F: torch.Tensor) -> torch.Tensor:
    """Determinant of (..., 3, 3) by cofactor expansion along the first row."""
    return (
        F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
        - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
        + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0])
    )


def deformation_gradient(u_e: torch.Tensor, dN_dX: torch.Tensor) -> torch.Tensor:
    """F = I + grad_0 u at Gauss points.

    u_e: (N, E, A, 3) element nodal displacements; dN_dX: (E, G, A, 3).
    Returns (N, E, G, 3, 3).
    """
    grad_u = torch.einsum("neai,egaj->negij", u_e, dN_dX)
    return grad_u + torch.eye(3, dtype=u_e.dtype, device=u_e.device)
