"""Exact sensitivities du/dtheta (implicit differentiation) against finite differences of full solves.

Reference: a fourth-order central difference of converged Newton solutions,
``(-u(2h) + 8 u(h) - 8 u(-h) + u(-2h)) / 12h`` with h = 1 % of each parameter (truncation
O(h^4) ~ 1e-8; the solves' own tolerance, rtol 1e-12, contributes ~1e-7 / h). The bound is the issue's:
relative error < 1e-5 (max over every node, component and load step, relative to the largest
sensitivity of that parameter).
"""
import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.fem.embedding import embedding_weights
from torchfra.fem.sensitivity import residual_derivative, sensitivities

TIGHT = fem.NewtonOptions(rtol=1e-12, etol=1e-20, stagnation_tol=1e-11)
LOADS = [0.5, 1.0]


def every_candidate_model():
    """Block with a pressurized cavity carrying every candidate term at once: Mooney-Rivlin hybrid
    body (C10, C01, D1), an embedded Line3 fiber (E_fiber), self-weight (density), springs under
    the base (c_n, c_t), a pressure sensor (gain, offset) and a rigid top that rotates."""
    mesh = block_with_cavity()
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.MooneyRivlin()))
    X = np.column_stack([np.full(5, 1.5), np.full(5, 0.5), np.linspace(0.2, 1.9, 5)])  # below the rigid top layer
    nodes = model.add_nodes(X)
    model.add(fem.Truss(model.X, nodes[np.array([[0, 2, 1], [2, 4, 3]])], area=0.01))
    for node, (hosts, w) in zip(nodes, embedding_weights(mesh, X)):
        model.embed(int(node), hosts, w)
    model.add(fem.SensorCavityPressure(mesh, "cavity"))
    model.add(fem.Gravity(mesh, direction=(0.0, -1.0, 0.0)))
    model.add(fem.ElasticSupport(mesh, "zmin"))
    model.clamp(mesh.node_sets["xmin"][mesh.nodes[mesh.node_sets["xmin"], 2] < 1e-9])  # no rigid-body mode
    model.rigid("zmax")
    return model


THETA = {"C10": 0.1, "C01": 0.03, "D1": 0.05, "E_fiber": 300.0, "density": 2e-8, "c_n": 0.5, "c_t": 2.0,
         "pressure_gain": 1.2, "pressure_offset": 0.01}


def params_of(th):
    N = th["C10"].shape[0]
    return {**th, "P": torch.full((N,), 0.12, dtype=torch.float64)}


def theta(**change):
    return {k: torch.tensor([change.get(k, v)], dtype=torch.float64) for k, v in THETA.items()}


@pytest.fixture(scope="module")
def model_and_sens():
    model = every_candidate_model()
    sol = fem.solve(model, params_of(theta()), LOADS, TIGHT)
    assert sol.converged.all()
    return model, sol, sensitivities(model, params_of, theta(), sol)


@pytest.mark.parametrize("name", sorted(THETA))
def test_sensitivity_matches_finite_differences_of_solves(model_and_sens, name):
    model, sol, S = model_and_sens
    h = 0.01 * THETA[name]
    us = []
    for k in (2, 1, -1, -2):
        s = fem.solve(model, params_of(theta(**{name: THETA[name] + k * h})), LOADS, TIGHT)
        assert s.converged.all()
        us.append(s.u)
    fd = (-us[0] + 8 * us[1] - 8 * us[2] + us[3]) / (12 * h)
    exact = S.du[..., S.names.index(name)]
    scale = float(exact.abs().max())
    assert scale > 0
    err = float((fd - exact).abs().max()) / scale
    assert err < 1e-5, (name, err)


def test_load_factor_derivative_matches_finite_differences(model_and_sens):
    model, sol, S = model_and_sens
    h = 1e-3
    up = fem.solve(model, params_of(theta()), [0.5 + h, 1.0], TIGHT).u[:, 0]
    um = fem.solve(model, params_of(theta()), [0.5 - h, 1.0], TIGHT).u[:, 0]
    fd = (up - um) / (2 * h)  # O(h^2) = 1e-6 relative
    err = float((fd - S.du_dlambda[:, 0]).abs().max() / S.du_dlambda[:, 0].abs().max())
    assert err < 1e-5, err


def test_tied_and_transformed_parameters_follow_the_chain_rule(model_and_sens):
    """theta in log coordinates with D1 tied to C10 (K/mu fixed): d u/d log C10 equals
    C10 (du/dC10 + dD1/dC10 du/dD1) assembled from the independent sensitivities."""
    model, sol, S = model_and_sens

    def tied(th):
        c10 = torch.exp(th["logC10"])
        p = params_of(theta())
        return {**p, "C10": c10, "D1": 1.0 / (200.0 * c10)}

    c10 = THETA["C10"]
    th = {"logC10": torch.tensor([np.log(c10)], dtype=torch.float64)}
    base = tied(th)
    s = fem.solve(model, base, LOADS, TIGHT)
    S_tied = sensitivities(model, tied, th, s)
    S_ind = sensitivities(model, lambda t: {**base, **t}, {"C10": base["C10"], "D1": base["D1"]}, s)
    chain = c10 * (S_ind.du[..., 0] + (-1.0 / (200.0 * c10**2)) * S_ind.du[..., 1])
    err = float((S_tied.du[..., 0] - chain).abs().max() / chain.abs().max())
    assert err < 1e-10, err


def test_residual_derivative_is_zero_for_parameters_the_model_does_not_use(model_and_sens):
    model, sol, S = model_and_sens
    p = params_of(theta())
    p["unused"] = torch.tensor([1.0], dtype=torch.float64)
    dr = residual_derivative(model, sol.a[:, 0], p, torch.tensor([0.5], dtype=torch.float64), {"unused": torch.ones(1)})
    assert float(dr.abs().max()) == 0.0


def test_rigid_motion_reads_the_rigid_top_from_the_solution(model_and_sens):
    """Model.rigid_motion: translation and rotation vector of the rigid top from Solution.a; every
    rigid node then sits at translation + (R - I)(X - centroid) (the constraint's own definition)."""
    model, sol, _ = model_and_sens
    t, theta = model.rigid_motion(sol.a[0, -1])
    assert float(torch.linalg.norm(theta)) > 1e-4  # the top does rotate in this test
    top = np.unique(model.mesh.node_sets["zmax"])
    dX = torch.as_tensor(model.X[top] - model.X[top].mean(axis=0))
    expected = t + dX @ (fem.rotation_matrix(theta) - torch.eye(3, dtype=dX.dtype)).T
    assert torch.allclose(sol.u[0, -1, top], expected, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="rigid body 1 does not exist"):
        model.rigid_motion(sol.a[0, -1], body=1)
    # Newton's work per output load level adds up to its total
    assert sol.iterations_per_output.shape == (1, len(LOADS)) and (sol.iterations_per_output > 0).all()
    assert sol.iterations_per_output.sum() == sol.iterations[0]
