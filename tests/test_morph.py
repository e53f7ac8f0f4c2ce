"""Geometric imperfections as a morph of the reference mesh (``fem.morph``, ``Model.morph``).

References: (1) an affine morph maps a mesh exactly onto the re-meshed body (same nodes), so a
morphed model and the model built on the re-meshed body must give the same solution to the
solver's tolerance — for every member of one batched solve, each with its own morph; (2) central
differences of the residual and of full solves for the derivatives (the issue's bounds: residual
< 1e-6, solves < 1e-5); (3) at a zero morph the model is the base model (round-off).
The actuator's cavity offset morphed vs re-meshed (discretization error) is measured by
``studies/cavity_offset.py`` (README).
"""
import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.actuator.geometry import CAVITY_OFFSET, ActuatorGeometry, build_actuator_model, cavity_offset_field
from torchfra.fem.embedding import embedding_weights
from torchfra.fem.morph import MorphError, harmonic_field, inverted_elements
from torchfra.fem.params import ParameterError, ParameterInfo
from torchfra.fem.sensitivity import residual_derivative, sensitivities
from torchfra.io.vtu import element_fields

TIGHT = fem.NewtonOptions(rtol=1e-12, etol=1e-20, stagnation_tol=1e-11)
HEIGHT = 3.0
STRETCH = ParameterInfo("s", "mm", 0.0, -1.0, 1.0)


def block_model(height: float = HEIGHT, morph: bool = False):
    """Block with a pressurized cavity, an embedded Line3 fiber, a follower pressure on one side,
    self-weight, clamped base; with ``morph`` its height grows by the parameter ``s`` (mm) through
    the affine field ``(0, 0, z / height)``."""
    mesh = block_with_cavity(size=(3.0, 3.0, height))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    Xf = np.column_stack([np.full(5, 2.6), np.full(5, 0.4), np.linspace(0.2, 0.9, 5) * height])
    nodes = model.add_nodes(Xf)
    model.add(fem.Truss(model.X, nodes[np.array([[0, 2, 1], [2, 4, 3]])], area=0.01))
    for node, (hosts, w) in zip(nodes, embedding_weights(mesh, Xf)):
        model.embed(int(node), hosts, w)
    model.add(fem.CavityPressure(mesh, "cavity"))
    model.add(fem.FollowerPressure(mesh, "xmax", pressure="Pside"))
    model.add(fem.Gravity(mesh, direction=(0.0, -1.0, 0.0)))
    model.clamp("zmin")
    if morph:
        model.morph("s", np.column_stack([np.zeros((mesh.n_nodes, 2)), mesh.nodes[:, 2] / height]), STRETCH)
    return model


def params(N: int = 1, **extra):
    p = {"C10": 0.1, "D1": 0.05, "E_fiber": 300.0, "P": 0.1, "Pside": 0.02, "density": 2e-8}
    out = {k: torch.full((N,), v, dtype=torch.float64) for k, v in p.items()}
    out.update({k: torch.as_tensor(v, dtype=torch.float64).reshape(-1) for k, v in extra.items()})
    return out


def test_affine_morph_equals_the_remeshed_body_member_by_member():
    """Three members of one batched solve, heights 3 - 0.4, 3 and 3 + 0.3 by the morph, against three
    solves on the re-meshed blocks (same node numbering): equal to the solver's tolerance."""
    s = [-0.4, 0.0, 0.3]
    model = block_model(morph=True)
    morphed = fem.solve(model, params(3, s=s), [0.5, 1.0], TIGHT)
    assert morphed.converged.all()
    scale = float(morphed.u.abs().max())
    assert scale > 0.1  # a real deformation
    stress = element_fields(model.terms[0], morphed.u[:, -1], params(3, s=s))["S"]  # ParaView's S, per member
    for m, sm in enumerate(s):
        ref_model = block_model(HEIGHT + sm)
        ref = fem.solve(ref_model, params(), [0.5, 1.0], TIGHT)
        assert ref.converged.all()
        err = float((morphed.u[m] - ref.u[0]).abs().max())
        assert err < 1e-9 * scale, (sm, err)
        ref_stress = element_fields(ref_model.terms[0], ref.u[:, -1], params())["S"][0]
        assert float((stress[m] - ref_stress).abs().max()) < 1e-9 * float(ref_stress.abs().max())
    # the morph matters: the members differ by far more than that
    assert float((morphed.u[0] - morphed.u[2]).abs().max()) > 0.05 * scale


def test_zero_morph_is_the_base_model():
    base, morphed = block_model().finalize(), block_model(morph=True).finalize()
    a = 0.01 * torch.randn(2, base.n_red, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    lam = torch.tensor([0.7, 1.0], dtype=torch.float64)
    r0 = base.evaluate(a, params(2), lam).residual
    r1 = morphed.evaluate(a, params(2, s=[0.0, 0.0]), lam).residual
    assert float((r0 - r1).abs().max()) < 1e-13 * float(r0.abs().max())


def test_residual_derivative_and_tangent_under_a_morph():
    """d r / d s by forward AD against central differences of the residual (h = 1e-5: error
    O(h^2) ~ 1e-10 relative); the tangent of the morphed model against central differences in a."""
    model = block_model(morph=True).finalize()
    sol = fem.solve(model, params(s=0.25), [1.0], TIGHT)
    a, lam = sol.a[:, 0], torch.tensor([1.0], dtype=torch.float64)
    exact = residual_derivative(model, a, params(s=0.25), lam, {"s": torch.ones(1)})
    h = 1e-5
    fd = (model.evaluate(a, params(s=0.25 + h), lam).residual - model.evaluate(a, params(s=0.25 - h), lam).residual) / (2 * h)
    assert float(exact.abs().max()) > 1e-3
    assert float((exact - fd).abs().max()) < 1e-6 * float(exact.abs().max())
    K = model.evaluate(a, params(s=0.25), lam, tangent=True).tangents[0]
    v = torch.randn(model.n_red, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    hv = 1e-6
    fd_K = (model.evaluate(a + hv * v, params(s=0.25), lam).residual - model.evaluate(a - hv * v, params(s=0.25), lam).residual)[0] / (2 * hv)
    Kv = torch.as_tensor(K @ v.numpy())
    assert float((Kv - fd_K).abs().max()) < 1e-6 * float(Kv.abs().max())


def test_sensitivity_to_the_morph_matches_finite_differences_of_solves():
    """du/ds by implicit differentiation against the 4th-order central difference of four solves
    (h = 0.01 mm), relative < 1e-5 (the bound of tests/test_sensitivity.py)."""
    model = block_model(morph=True)

    def params_of(th):
        return {**params(), "s": th["s"]}

    th = {"s": torch.tensor([0.1], dtype=torch.float64)}
    sol = fem.solve(model, params_of(th), [0.5, 1.0], TIGHT)
    S = sensitivities(model, params_of, th, sol)
    h = 0.01
    us = [fem.solve(model, params(s=0.1 + k * h), [0.5, 1.0], TIGHT).u for k in (2, 1, -1, -2)]
    fd = (-us[0] + 8 * us[1] - 8 * us[2] + us[3]) / (12 * h)
    exact = S.du[..., 0]
    assert float(exact.abs().max()) > 0.01
    assert float((fd - exact).abs().max()) < 1e-5 * float(exact.abs().max())


def test_morph_errors_name_the_culprit():
    model = block_model()
    with pytest.raises(MorphError, match=r"shape"):
        model.morph("s", np.zeros((3, 3)))
    clamped = block_model()
    clamped.morph("s", np.tile([0.0, 0.0, 1.0], (clamped.mesh.n_nodes, 1)), STRETCH)  # moves the base too
    with pytest.raises(MorphError, match="clamped nodes"):
        clamped.finalize()
    springs = fem.Model(block_with_cavity())
    springs.add(fem.Hex20Solid(springs.mesh, fem.NeoHookean()))
    fem.support_face(springs, "zmin", compliant=True)
    springs.morph("s", np.tile([0.0, 1.0, 0.0], (springs.mesh.n_nodes, 1)))
    with pytest.raises(MorphError, match="ElasticSupport"):
        springs.finalize()
    morphed = block_model(morph=True)
    with pytest.raises(ParameterError, match=r"parameter s of member 1 is 2\.0"):
        fem.solve(morphed, params(2, s=[0.0, 2.0]), [1.0])
    mesh = block_with_cavity()
    with pytest.raises(MorphError, match="both moving and fixed"):
        harmonic_field(mesh, [0, 1], [1, 2])


def test_actuator_cavity_offset_field_and_its_range():
    """The cavity-offset morph: 1 on the cavity, 0 on every outer face (so the base's clamp, the rigid
    top and the observed face stay put), no element inverted anywhere in the admissible range, and a
    larger offset than the wall allows does invert elements (the check can fail)."""
    model, info = build_actuator_model(ActuatorGeometry(resolution=1), cavity_offset=True)
    mesh = model.mesh
    f = cavity_offset_field(mesh)
    assert np.allclose(f[mesh.node_set("cavity")], [0.0, 1.0, 0.0])
    assert np.abs(f[mesh.face_set_nodes("exterior")]).max() == 0.0
    assert np.abs(f[:, [0, 2]]).max() == 0.0
    for s in (CAVITY_OFFSET.low, CAVITY_OFFSET.high):
        assert inverted_elements(mesh, f, s).size == 0, s
    assert inverted_elements(mesh, f, 1.0).size > 0  # the 1 mm wall closes
    model.finalize()
    fiber = model.morph_fields()[info["fiber_nodes"], 1, 0]
    assert 0.0 < fiber.max() < 1.0  # the fibers follow the material between cavity and wall
    assert model.param_names().count("delta_y") == 1
    base, _ = build_actuator_model(ActuatorGeometry(resolution=1))
    base.finalize()
    a = 0.01 * torch.randn(1, base.n_red, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    p = {"C10": torch.tensor([0.005]), "D1": torch.tensor([0.2]), "E_fiber": torch.tensor([31000.0]),
         "P": torch.tensor([0.02])}
    p = {k: v.double() for k, v in p.items()}
    lam = torch.tensor([1.0], dtype=torch.float64)
    r0 = base.evaluate(a, p, lam).residual
    r1 = model.evaluate(a, {**p, "delta_y": torch.zeros(1, dtype=torch.float64)}, lam).residual
    assert float((r0 - r1).abs().max()) < 1e-12 * float(r0.abs().max())
