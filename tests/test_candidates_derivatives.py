"""Candidate physics terms: residual and tangent against central differences, null values, registry.

Reference: central differences with step h = 1e-6 mm of each term's energy (for the residual) and
residual (for the tangent), as in ``test_derivatives.py``; the bound is rel. err < 1e-6. The null
checks compare with the base model's own terms (NeoHookean, CavityPressure), an independent code
path, to 1e-12.
"""
import math

import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.fem.params import ParameterError, ParameterInfo
from torchfra.fem.structured import box_mesh

H = 1e-6
TOL = 1e-6
PARAMS = {
    "C10": torch.tensor([0.5, 0.3]),
    "C01": torch.tensor([0.2, 0.05]),
    "D1": torch.tensor([0.1, 0.02]),
    "P": torch.tensor([0.2, 0.05]),
    "density": torch.tensor([2e-8, 5e-9]),
    "c_n": torch.tensor([2.0, 0.5]),
    "c_t": torch.tensor([5.0, 0.25]),
    "pressure_gain": torch.tensor([1.3, 0.8]),
    "pressure_offset": torch.tensor([0.01, -0.02]),
}


def dense(term, u, params, lam):
    """Global residual (N, n) and tangent (N, n, n) of one term; a tangent of None is zero."""
    out = term.evaluate(u, params, lam, tangent=True)
    N, n = u.shape[0], u[0].numel()
    dofs = torch.as_tensor(term.dofs)
    r = torch.zeros(N, n).index_add_(1, dofs.ravel(), out.fe.reshape(N, -1))
    K = torch.zeros(N, n, n)
    if out.Ke is not None:
        for b in range(dofs.shape[0]):
            K[:, dofs[b][:, None], dofs[b][None, :]] += out.Ke[:, b]
    return r, K


def fd_errors(term, n_nodes, params, seed=0, amplitude=0.1):
    """Largest relative errors (tangent vs FD of residual, residual vs FD of energy) over 12 dofs."""
    torch.manual_seed(seed)
    u = amplitude * torch.randn(2, n_nodes, 3)
    lam = torch.tensor([1.0, 0.7])
    r, K = dense(term, u, params, lam)

    def energy(uu):
        return term.evaluate(uu, params, lam, tangent=False, energy=True).energy

    flat = u.reshape(2, -1)
    scale_K = max(float(K.abs().max()), float(r.abs().max()))  # zero tangents are judged on the force scale
    err_K = err_r = 0.0
    for d in np.unique(np.random.default_rng(seed).choice(np.unique(term.dofs), 12, replace=False)):
        e = torch.zeros_like(flat)
        e[:, d] = H
        up, um = (flat + e).reshape(u.shape), (flat - e).reshape(u.shape)
        col = (dense(term, up, params, lam)[0] - dense(term, um, params, lam)[0]) / (2 * H)
        err_K = max(err_K, float((col - K[:, :, d]).abs().max()) / scale_K)
        g = (energy(up) - energy(um)) / (2 * H)
        err_r = max(err_r, float((g - r[:, d]).abs().max() / r.abs().max()))
    return err_K, err_r


@pytest.mark.parametrize("formulation", ["hybrid", "displacement"])
@pytest.mark.parametrize("integration", ["reduced", "full"])
def test_mooney_rivlin_derivatives(formulation, integration):
    mesh = box_mesh((1.0, 1.2, 2.0), (1, 2, 2), distortion=0.25)
    term = fem.Hex20Solid(mesh, fem.MooneyRivlin(), formulation=formulation, integration=integration)
    err_K, err_r = fd_errors(term, mesh.n_nodes, PARAMS, amplitude=0.04)
    assert err_K < TOL and err_r < TOL, (err_K, err_r)  # measured <= 4.2e-11 / 1.6e-10


def test_mooney_rivlin_fast_pressure_terms_equal_derived():
    """The closed-form pressure terms (J - 1, -D1/2, cof F) pinned to the torch.func path."""
    g = torch.Generator().manual_seed(1)
    F = torch.eye(3) + 0.2 * torch.randn(4, 8, 3, 3, generator=g)
    p = 0.05 * torch.randn(4, 8, generator=g)
    prm = {k: PARAMS[k].repeat(2)[:, None] for k in ("C10", "C01", "D1")}
    fast, slow = fem.MooneyRivlin(fast=True), fem.MooneyRivlin(fast=False)
    for a, b in zip(fast.pressure_coefficients(F, prm), slow.pressure_coefficients(F, prm)):
        assert (a - b).abs().max() < 1e-13 * b.abs().max()
    a, b = fast.pressure_gradient(F, p, prm), slow.pressure_gradient(F, p, prm)
    assert (a - b).abs().max() < 1e-13 * b.abs().max()


@pytest.mark.parametrize("formulation", ["hybrid", "displacement"])
def test_mooney_rivlin_null_is_neo_hookean(formulation):
    """C01 = 0: residual, tangent and energy of the body equal NeoHookean's (closed-form path) to 1e-12."""
    mesh = box_mesh((1.0, 1.2, 2.0), (1, 2, 2), distortion=0.25)
    torch.manual_seed(2)
    u = 0.05 * torch.randn(2, mesh.n_nodes, 3)
    lam = torch.ones(2)
    params = dict(PARAMS, C01=torch.zeros(2))
    mr = fem.Hex20Solid(mesh, fem.MooneyRivlin(), formulation).evaluate(u, params, lam, energy=True)
    nh = fem.Hex20Solid(mesh, fem.NeoHookean(), formulation).evaluate(u, params, lam, energy=True)
    assert (mr.fe - nh.fe).abs().max() < 1e-12 * nh.fe.abs().max()
    assert (mr.Ke - nh.Ke).abs().max() < 1e-12 * nh.Ke.abs().max()
    assert (mr.energy - nh.energy).abs().max() < 1e-12 * nh.energy.abs().max()


def test_mooney_rivlin_rejects_negative_c01():
    mesh = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.MooneyRivlin()))
    with pytest.raises(ParameterError, match="C01 of member 1"):
        model.validate(dict(PARAMS, C01=torch.tensor([0.1, -0.1])))


def test_gravity_derivatives_and_null():
    mesh = box_mesh((1.0, 1.2, 2.0), (1, 2, 2), distortion=0.25)
    term = fem.Gravity(mesh, direction=(0.3, -1.0, 0.2))
    err_K, err_r = fd_errors(term, mesh.n_nodes, PARAMS)
    assert err_K < TOL and err_r < TOL, (err_K, err_r)
    u = torch.randn(2, mesh.n_nodes, 3)
    out = term.evaluate(u, dict(PARAMS, density=torch.zeros(2)), torch.ones(2), energy=True)
    assert out.fe.abs().max() == 0 and out.energy.abs().max() == 0


def _rotated_distorted_box():
    """A distorted box turned about a skew axis, so no face normal lies along a coordinate axis."""
    mesh = box_mesh((1.0, 1.5, 2.0), (2, 1, 2), distortion=0.25)
    theta = torch.tensor([0.4, -0.7, 0.3], dtype=torch.float64)
    R = fem.rotation_matrix(theta).numpy()
    return fem.Mesh(mesh.nodes @ R.T, mesh.elements, mesh.node_sets, mesh.face_sets)


@pytest.mark.parametrize("parts", [("c_n", "c_t"), ("c_n", None), (None, "c_t")])
def test_elastic_support_derivatives(parts):
    mesh = _rotated_distorted_box()
    term = fem.ElasticSupport(mesh, "zmin", *parts)
    err_K, err_r = fd_errors(term, mesh.n_nodes, PARAMS)
    assert err_K < TOL and err_r < TOL, (err_K, err_r)


def test_elastic_support_energy_of_a_uniform_translation():
    """Closed form: a face of area A translated by v stores 1/2 A (k_n (v.n)^2 + k_t |v - (v.n) n|^2)."""
    mesh = _rotated_distorted_box()
    term = fem.ElasticSupport(mesh, "zmin")
    R = fem.rotation_matrix(torch.tensor([0.4, -0.7, 0.3], dtype=torch.float64))
    n = -R[:, 2]  # outward normal of the rotated zmin face
    v = torch.tensor([0.3, -0.2, 0.5])
    u = v.expand(2, mesh.n_nodes, 3).clone()
    W = term.evaluate(u, PARAMS, torch.ones(2), tangent=False, energy=True).energy
    A = 1.0 * 1.5  # box_mesh distorts interior corners only: the boundary face keeps its area
    vn = float(v @ n)
    vt2 = float(v @ v) - vn**2
    exact = 0.5 * A * (vn**2 / PARAMS["c_n"] + vt2 / PARAMS["c_t"])
    assert abs(term.area - A) < 1e-13
    assert (W - exact).abs().max() < 1e-13 * exact.abs().max()
    assert (term.unit_normal - n).abs().max() < 1e-14


def test_sensor_pressure_derivatives_and_null():
    mesh = block_with_cavity()
    term = fem.SensorCavityPressure(mesh, "cavity")
    err_K, err_r = fd_errors(term, mesh.n_nodes, PARAMS)
    assert err_K < TOL and err_r < TOL, (err_K, err_r)
    torch.manual_seed(3)
    u = 0.1 * torch.randn(2, mesh.n_nodes, 3)
    lam = torch.tensor([1.0, 0.4])
    null = dict(PARAMS, pressure_gain=torch.ones(2), pressure_offset=torch.zeros(2))
    a = term.evaluate(u, null, lam, energy=True)
    b = fem.CavityPressure(mesh, "cavity").evaluate(u, null, lam, energy=True)
    assert torch.equal(a.fe, b.fe) and torch.equal(a.Ke, b.Ke) and torch.equal(a.energy, b.energy)
    # the true pressure at lambda = 1 is gain P + offset; a recorded P_rec sits at its load factor
    c = term.evaluate(u, PARAMS, torch.ones(2), energy=True)
    true = PARAMS["pressure_gain"] * PARAMS["P"] + PARAMS["pressure_offset"]
    d = fem.CavityPressure(mesh, "cavity").evaluate(u, dict(PARAMS, P=true), torch.ones(2), energy=True)
    assert (c.fe - d.fe).abs().max() < 1e-15 * d.fe.abs().max()
    recorded = torch.stack([PARAMS["P"], -PARAMS["pressure_offset"] / PARAMS["pressure_gain"]])
    assert torch.allclose(term.load_factor_of(recorded, PARAMS), torch.tensor([[1.0, 1.0], [0.0, 0.0]]),
                          rtol=0, atol=1e-15)


CANDIDATES = [
    (fem.MooneyRivlin, "C01"), (fem.NeoHookean, "D1"), (fem.Gravity, "density"), (fem.ElasticSupport, "c_n"),
    (fem.ElasticSupport, "c_t"), (fem.SensorCavityPressure, "pressure_gain"),
    (fem.SensorCavityPressure, "pressure_offset"),
]


@pytest.mark.parametrize("cls,name", CANDIDATES)
def test_registry_entries(cls, name):
    """Every candidate parameter has a unit, a null at or inside its admissible range, a description."""
    info = cls.parameters[name]
    assert isinstance(info, ParameterInfo) and info.name == name and info.unit and info.description
    assert info.null is not None and math.isfinite(info.null)
    assert info.low <= info.null <= info.high


def test_catalogue_names_and_nulls():
    from torchfra.actuator.candidates import CANDIDATES, fe_null_values

    nulls = {name: fe_null_values(name) for name in CANDIDATES}
    assert nulls == {
        "mooney_rivlin": {"C01": 0.0}, "compressibility": {"D1": 0.0}, "gravity": {"density": 0.0},
        "compliant_base": {"c_n": 0.0, "c_t": 0.0}, "fiber_stiffness": {},
        "pressure_sensor": {"pressure_gain": 1.0, "pressure_offset": 0.0}, "cavity_offset": {"delta_y": 0.0},
        "fiber_pitch": {"fiber_pitch": 2.0},
    }
    for terms in CANDIDATES.values():
        for p in terms:
            assert p.unit and p.description and p.low < p.high


def test_the_registry_names_each_fe_terms_parameters_with_their_units_and_ranges():
    """One registry: the diagnosis's and the filters' parameters of a candidate (actuator.candidates.REGISTRY)
    are exactly the FE terms' parameters (fem ParameterInfo), in the same units."""
    from torchfra.actuator.candidates import CANDIDATES, COORDINATES, REGISTRY

    for name, terms in CANDIDATES.items():
        assert REGISTRY[name].parameter_names == tuple(p.name for p in terms), name
        for p in terms:
            c = COORDINATES[p.name]
            assert c.unit == p.unit, (p.name, c.unit, p.unit)
