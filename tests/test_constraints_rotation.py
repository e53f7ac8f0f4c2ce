"""Closed-form derivatives of the rigid body's finite rotation (``fem.constraints``).

Reference: torch.func (``jacfwd`` and ``hessian``, automatic differentiation) of the Rodrigues
formula, at rotation vectors from 0 through the series/closed-form switch (|theta|^2 = 0.25) to 3 rad;
agreement to 1e-12 (absolute, entries of order 1). Below |theta| = 0.5 the reference differentiates
the power series of the Rodrigues coefficients (``rotation_series``, a polynomial, so its automatic
derivatives carry no cancellation), since ``sin(s)/s`` differentiated twice near s = 1e-4 loses
half its digits (1e-8) in the reference itself.
"""
import math

import numpy as np
import torch
from torch.func import hessian, jacfwd, vmap

from torchfra.fem.constraints import rotation_jacobian, rotation_matrix, rotation_work_hessian


def rotation_series(theta):
    """``I + A W + B W^2`` with A, B summed from their power series in a = |theta|^2 (20 terms)."""
    a = (theta * theta).sum()
    A = sum((-1) ** n * a**n / float(math.factorial(2 * n + 1)) for n in range(20))
    B = sum((-1) ** n * a**n / float(math.factorial(2 * n + 2)) for n in range(20))
    z = torch.zeros((), dtype=theta.dtype)
    W = torch.stack([torch.stack([z, -theta[2], theta[1]]), torch.stack([theta[2], z, -theta[0]]),
                     torch.stack([-theta[1], theta[0], z])])
    return torch.eye(3, dtype=theta.dtype) + A * W + B * (W @ W)


def reference(fn, th, *args):
    small = torch.linalg.norm(th, dim=1) < 0.5
    out = fn(rotation_matrix)(th, *args)
    out[small] = fn(rotation_series)(th[small], *[x[small] for x in args])
    return out


def thetas():
    gen = torch.Generator().manual_seed(0)
    d = torch.randn(9, 3, generator=gen, dtype=torch.float64)
    d = d / torch.linalg.norm(d, dim=1, keepdim=True)
    size = torch.tensor([0.0, 1e-9, 1e-4, 0.1, 0.4999, 0.5001, 0.9, 2.0, 3.0], dtype=torch.float64)
    return d * size[:, None]


def test_rotation_jacobian_matches_automatic_differentiation():
    th = thetas()
    ref = reference(lambda R: vmap(jacfwd(R)), th)
    assert float((rotation_jacobian(th) - ref).abs().max()) < 1e-12


def test_rotation_work_hessian_matches_automatic_differentiation():
    th = thetas()
    M = torch.randn(th.shape[0], 3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref = reference(lambda R: vmap(hessian(lambda t, m: (R(t) * m).sum())), th, M)
    got = rotation_work_hessian(th, M)
    assert float((got - ref).abs().max()) < 1e-12 * max(1.0, float(ref.abs().max()))
    assert np.allclose(got.numpy(), got.transpose(1, 2).numpy())
