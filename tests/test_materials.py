"""The closed-form Neo-Hookean fast path equals the torch.func-derived path to round-off.

Reference: ``NeoHookean(fast=False)`` differentiates the energy ``psi(F, p)`` with
``vmap(jacfwd(grad))``; the fast path writes P, A and d2psi/dFdp out by hand (STYLE: a hand-written
fast path exists only beside a test that pins it to the derived one).
"""
import torch

from torchfra.fem.materials import NeoHookean


def test_fast_path_equals_derived_path():
    g = torch.Generator().manual_seed(0)
    F = torch.eye(3) + 0.25 * torch.randn(3, 5, 8, 3, 3, generator=g, dtype=torch.float64)
    F = F[torch.linalg.det(F).reshape(-1).gt(0).reshape(3, 5, 8).all(-1).all(-1)]  # admissible members
    N = F.shape[0]
    assert N >= 1
    p = 0.05 * torch.randn(N, 5, 8, generator=g, dtype=torch.float64)
    prm = {"C10": torch.linspace(0.003, 0.5, N)[:, None, None], "D1": torch.linspace(0.01, 20.0, N)[:, None, None]}
    fast = NeoHookean(fast=True).derivatives(F, p, prm, with_energy=True)
    slow = NeoHookean(fast=False).derivatives(F, p, prm, with_energy=True)
    scale = slow.A.to_dense().abs().max()
    assert (fast.P - slow.P).abs().max() < 1e-13 * slow.P.abs().max()
    assert (fast.A.to_dense() - slow.A.to_dense()).abs().max() < 1e-13 * scale
    assert (fast.Fp - slow.Fp).abs().max() < 1e-13 * slow.Fp.abs().max()
    assert (fast.psi - slow.psi).abs().max() < 1e-13 * slow.psi.abs().max()
    for a, b in zip(NeoHookean(fast=True).pressure_coefficients(F, prm), NeoHookean(fast=False).pressure_coefficients(F, prm)):
        assert (a - b).abs().max() < 1e-13 * b.abs().max()


def test_residual_only_path_equals_the_full_derived_path():
    """A residual (tangent=False) skips the hessian: its stress and d2psi/dFdp equal those of the
    full vmap(jacfwd(grad)) path to round-off (Mooney-Rivlin: the derived material of the library)."""
    from torchfra.fem.materials import MooneyRivlin

    g = torch.Generator().manual_seed(1)
    F = torch.eye(3) + 0.2 * torch.randn(2, 4, 8, 3, 3, generator=g, dtype=torch.float64)
    p = 0.05 * torch.randn(2, 4, 8, generator=g, dtype=torch.float64)
    prm = {"C10": torch.tensor([0.006, 0.02])[:, None, None], "C01": torch.tensor([0.001, 0.0])[:, None, None],
           "D1": torch.tensor([0.1, 5.0])[:, None, None]}
    for mat in (MooneyRivlin(), NeoHookean(fast=False)):
        full = mat.derivatives(F, p, prm, with_energy=True)
        res = mat.derivatives(F, p, prm, with_energy=True, tangent=False)
        assert res.A is None
        assert (res.P - full.P).abs().max() < 1e-13 * full.P.abs().max()
        assert (res.Fp - full.Fp).abs().max() < 1e-13 * full.Fp.abs().max()
        assert (res.psi - full.psi).abs().max() == 0


def test_mooney_rivlin_closed_form_equals_derived_path():
    """MooneyRivlin(fast=True) writes P and A out by hand; MooneyRivlin(fast=False) derives them from
    psi by vmap(jacfwd(grad)): equal to round-off, with and without C01, at large random strains."""
    from torchfra.fem.materials import MooneyRivlin

    g = torch.Generator().manual_seed(2)
    F = torch.eye(3) + 0.25 * torch.randn(3, 5, 8, 3, 3, generator=g, dtype=torch.float64)
    F = F[torch.linalg.det(F).reshape(-1).gt(0).reshape(3, 5, 8).all(-1).all(-1)]
    N = F.shape[0]
    assert N >= 2
    p = 0.05 * torch.randn(N, 5, 8, generator=g, dtype=torch.float64)
    prm = {"C10": torch.linspace(0.003, 0.5, N)[:, None, None], "C01": torch.linspace(0.0, 0.2, N)[:, None, None],
           "D1": torch.linspace(0.01, 20.0, N)[:, None, None]}
    fast = MooneyRivlin(fast=True).derivatives(F, p, prm, with_energy=True)
    slow = MooneyRivlin(fast=False).derivatives(F, p, prm, with_energy=True)
    scale = slow.A.to_dense().abs().max()
    assert (fast.P - slow.P).abs().max() < 1e-13 * slow.P.abs().max()
    assert (fast.A.to_dense() - slow.A.to_dense()).abs().max() < 1e-13 * scale
    assert (fast.Fp - slow.Fp).abs().max() < 1e-13 * slow.Fp.abs().max()
    assert (fast.psi - slow.psi).abs().max() < 1e-13 * slow.psi.abs().max()
    res = MooneyRivlin(fast=True).derivatives(F, p, prm, tangent=False)
    assert res.A is None and (res.P - fast.P).abs().max() == 0
