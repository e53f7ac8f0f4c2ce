"""Every energy term's residual and tangent against central finite differences (rel. err < 1e-6).

Reference: central differences with step h = 1e-6 mm; their truncation + round-off error is
~1e-9 relative here, far below the 1e-6 bound, so a wrong sign or missing term cannot pass.
"""
import numpy as np
import pytest
import torch
from helpers import assemble_dense, block_with_cavity

from torchfra import fem
from torchfra.fem.structured import box_mesh

H = 1e-6
TOL = 1e-6


def _fd_check(fun_r, fun_K, u, n_dofs, dofs_to_check, energy=None):
    """Compare K columns with FD of r, and r with FD of the energy (if any)."""
    r, K = fun_K(u)
    N = u.shape[0]
    flat = u.reshape(N, -1)
    scale_K = K.abs().max()
    scale_r = r.abs().max()
    for d in dofs_to_check:
        e = torch.zeros_like(flat)
        e[:, d] = H
        up, um = (flat + e).reshape(u.shape), (flat - e).reshape(u.shape)
        col = (fun_r(up) - fun_r(um)) / (2 * H)
        assert (col - K[:, :, d]).abs().max() / scale_K < TOL, f"tangent column {d}"
        if energy is not None:
            g = (energy(up) - energy(um)) / (2 * H)
            assert (g - r[:, d]).abs().max() / scale_r < TOL, f"residual entry {d}"


def _term_check(term, n_nodes, params, seed=0, amplitude=0.1, conservative=True):
    torch.manual_seed(seed)
    N = 2
    u = amplitude * torch.randn(N, n_nodes, 3)
    lam = torch.tensor([1.0, 0.7])
    n = 3 * n_nodes

    def fun_K(uu):
        return assemble_dense(term, uu, params, lam, n)

    def fun_r(uu):
        return fun_K(uu)[0]

    energy = (lambda uu: term.evaluate(uu, params, lam, tangent=False, energy=True).energy) if conservative else None
    dofs = np.unique(np.random.default_rng(seed).choice(np.unique(term.dofs), 12, replace=False))
    _fd_check(fun_r, fun_K, u, n, dofs, energy)


PARAMS = {
    "C10": torch.tensor([0.5, 0.3]),
    "D1": torch.tensor([0.1, 0.02]),
    "P": torch.tensor([0.2, 0.05]),
    "E_fiber": torch.tensor([100.0, 40.0]),
}


@pytest.mark.parametrize("formulation", ["hybrid", "displacement"])
@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("integration", ["reduced", "full"])
def test_solid_derivatives(formulation, fast, integration):
    mesh = box_mesh((1.0, 1.2, 2.0), (1, 2, 2), distortion=0.25)
    term = fem.Hex20Solid(mesh, fem.NeoHookean(fast=fast), formulation=formulation, integration=integration)
    _term_check(term, mesh.n_nodes, PARAMS, amplitude=0.04)


def test_follower_pressure_derivatives():
    mesh = box_mesh((1.0, 1.0, 2.0), (2, 1, 2), distortion=0.2)
    term = fem.FollowerPressure(mesh, "ymax", pressure="P")
    _term_check(term, mesh.n_nodes, PARAMS, conservative=False)


def test_cavity_pressure_derivatives():
    mesh = block_with_cavity()
    term = fem.CavityPressure(mesh, "cavity", pressure="P")
    _term_check(term, mesh.n_nodes, PARAMS)


def test_truss_derivatives():
    X = np.array([[0.0, 0, 0], [1.0, 0.2, 0.1], [0.5, 0.15, 0.0], [2.0, 0.0, 0.3], [1.5, 0.1, 0.2]])
    term = fem.Truss(X, np.array([[0, 1, 2], [1, 3, 4]]), area=0.01)
    _term_check(term, X.shape[0], PARAMS, amplitude=0.05)


def test_constrained_model_derivatives():
    """Reduced residual J^T r and tangent J^T K J + (rigid-rotation geometric term) of a model with
    clamp, prescribed displacement, a rigid face with finite rotation, embedded fiber nodes."""
    mesh = box_mesh((1.0, 1.0, 3.0), (1, 1, 3), distortion=0.2)
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(fem.FollowerPressure(mesh, "ymax", pressure="P"))
    fiber_nodes = model.add_nodes(np.array([[0.5, 0.5, 1.2], [0.5, 0.5, 1.8], [0.5, 0.5, 1.5]]))
    model.add(fem.Truss(model.X, fiber_nodes[None, :], area=0.01))
    host = mesh.elements[1]
    for node in fiber_nodes:
        w = np.random.default_rng(int(node)).dirichlet(np.ones(20))
        model.embed(node, host, w)
    model.clamp("zmin")
    side = np.setdiff1d(mesh.node_sets["xmin"], np.union1d(mesh.node_sets["zmin"], mesh.node_sets["zmax"]))
    model.prescribe(side, 0, 0.05)
    model.rigid("zmax")
    model.finalize()
    torch.manual_seed(3)
    N = 2
    a = 0.05 * torch.randn(N, model.n_red)
    a[:, -3:] = torch.tensor([[0.3, -0.2, 0.1], [0.0, 0.0, 0.0]])  # finite rotation, and exactly zero
    lam = torch.tensor([1.0, 0.6])
    ev = model.evaluate(a, PARAMS, lam, tangent=True)
    for m in range(N):
        K = torch.as_tensor(ev.tangents[m].toarray())
        for d in list(range(0, model.n_red, 7)) + list(range(model.n_red - 6, model.n_red)):
            e = torch.zeros(N, model.n_red)
            e[:, d] = H
            col = (model.evaluate(a + e, PARAMS, lam).residual - model.evaluate(a - e, PARAMS, lam).residual) / (2 * H)
            assert (col[m] - K[:, d]).abs().max() / K.abs().max() < TOL, f"member {m}, reduced dof {d}"


@pytest.mark.parametrize("follower", [False, True])
def test_tangent_is_symmetric_exactly_when_every_term_is_conservative(follower):
    """The reduced tangent of a model of conservative terms is the Hessian of its total potential
    (through the clamp, a rigid face at a finite rotation and embedded fiber nodes), so it must be
    symmetric to round-off: Newton then factorizes it as symmetric (``Model.symmetric_tangent``).
    A follower pressure on an open face has no potential; its tangent is not symmetric, and the
    model must say so. Hybrid pressures are carried as Newton does (not at their projection)."""
    mesh = block_with_cavity()
    model = fem.Model(mesh)
    # 2x2x2 points: the random state below inverts an element at one of the 3x3x3 points
    solid = fem.Hex20Solid(mesh, fem.NeoHookean(), integration="reduced")
    model.add(solid)
    model.add(fem.CavityPressure(mesh, "cavity", pressure="P"))
    if follower:
        model.add(fem.FollowerPressure(mesh, "ymax", pressure="P"))
    fiber_nodes = model.add_nodes(np.array([[0.4, 0.5, 1.2], [0.4, 0.5, 1.8], [0.4, 0.5, 1.5]]))
    model.add(fem.Truss(model.X, fiber_nodes[None, :], area=0.01))
    for node in fiber_nodes:
        model.embed(node, mesh.elements[0], np.random.default_rng(int(node)).dirichlet(np.ones(20)))
    model.clamp("zmin")
    model.rigid("zmax")
    model.finalize()
    assert model.symmetric_tangent == (not follower)
    torch.manual_seed(5)
    N = 2
    a = 0.03 * torch.randn(N, model.n_red, dtype=torch.float64)
    a[:, -3:] = torch.tensor([[0.2, -0.1, 0.15], [0.0, 0.0, 0.0]])
    local = [0.01 * torch.randn(N, t.dofs.shape[0], t.n_local, dtype=torch.float64) if t.n_local else None
             for t in model.terms]
    ev = model.evaluate(a, PARAMS, torch.tensor([1.0, 0.6]), tangent=True, local=local)
    for K in ev.tangents:
        asym = abs(K - K.T).max() / abs(K).max()
        if follower:
            assert asym > 1e-6
        else:
            assert asym < 1e-13
