"""The fiber-pitch candidate (``fem.FiberPitch``, ``build_actuator_model(fiber_pitch=True)``).

References: the base model itself (the null), the actuator re-built with its Line3 fibers wound at
the member's pitch (the same trusses embedded where they fall: what the term claims to be), central
differences of the term's energy and residual, and central differences of full solves for the
sensitivity.
"""
import numpy as np
import pytest
import torch
from torch.func import jvp

from torchfra import fem
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model, helix_points
from torchfra.observation.operator import visible_faces

C10 = 0.0068
PARAMS = {"C10": C10, "D1": 1.0 / (1000.0 * C10), "E_fiber": 31000.0, "P": 0.022}
LOADS = [0.5, 1.0]
TIGHT = fem.NewtonOptions(rtol=1e-12, etol=1e-20, stagnation_tol=1e-11)


def tensors(values: dict) -> dict:
    return {k: torch.tensor([v], dtype=torch.float64) for k, v in values.items()}


@pytest.fixture(scope="module")
def models():
    geom = ActuatorGeometry(resolution=1)
    base, info = build_actuator_model(geom)
    pitched, _ = build_actuator_model(geom, fiber_pitch=True)
    return geom, base, info, pitched


def pitch_term(model) -> fem.FiberPitch:
    return next(t for t in model.terms if isinstance(t, fem.FiberPitch))


def smooth_state(model, scale=0.02) -> torch.Tensor:
    """A smooth displacement field (N = 1, n_nodes, 3): quadratic in the reference coordinates."""
    X = torch.as_tensor(model.X)
    x, y, z = (X[:, i] / 10.0 for i in range(3))
    return scale * torch.stack([x * z + 0.3 * y, y * z - 0.2 * x**2, 0.5 * z**2 + 0.1 * x * y], -1)[None]


def test_at_its_null_the_model_is_the_base_model(models):
    """At the drawn pitch the term adds exactly nothing: residual and tangent of the model with the
    candidate equal the base model's (reference: the base model) at a state off equilibrium."""
    _, base, _, pitched = models
    a = 0.05 * torch.randn(1, base.n_red, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    p = tensors(PARAMS)
    e0 = base.evaluate(a, p, torch.ones(1), tangent=True)
    e1 = pitched.evaluate(a, {**p, "fiber_pitch": torch.tensor([2.0], dtype=torch.float64)}, torch.ones(1),
                          tangent=True)
    assert torch.equal(e0.residual, e1.residual)
    assert abs(e0.tangents[0] - e1.tangents[0]).max() == 0.0


def test_a_pitch_is_the_actuator_rebuilt_with_its_fibers_wound_there(models):
    """Pitch 2.6 deg: the model with the candidate equals the actuator built with its Line3 fibers at
    2.6 deg (same count per helix, embedded by ``build_actuator_model(fibers=...)``), to 1e-9 mm at
    every node and load, for an effect of the pitch far above that (reference: the re-built model)."""
    geom, base, info, pitched = models
    n_el = info["fiber_elements"] // 2
    wound = ActuatorGeometry(resolution=1, pitch_deg=2.6)
    X = helix_points(wound, np.linspace(0.0, 1.0, 2 * n_el + 1)).reshape(-1, 3)
    k = np.arange(n_el)
    one = np.stack([2 * k, 2 * k + 2, 2 * k + 1], 1)
    rebuilt, _ = build_actuator_model(geom, fibers=(X, np.concatenate([one, one + 2 * n_el + 1])))
    n = info["mesh"].n_nodes
    ref = fem.solve(rebuilt, tensors(PARAMS), LOADS, TIGHT)
    got = fem.solve(pitched, tensors({**PARAMS, "fiber_pitch": 2.6}), LOADS, TIGHT)
    drawn = fem.solve(base, tensors(PARAMS), LOADS, fem.NewtonOptions(stagnation_tol=1e-6))
    assert ref.converged.all() and got.converged.all() and drawn.converged.all()
    diff = float((got.u[0, :, :n] - ref.u[0, :, :n]).abs().max())
    effect = float((got.u[0, :, :n] - drawn.u[0, :, :n]).abs().max())
    assert diff < 1e-9, diff  # measured 4e-12 mm
    assert effect > 1e-2, effect  # measured ~0.1 mm: the comparison is not trivial


def test_residual_and_tangent_against_central_differences(models):
    """The term's residual is the gradient of its energy and its tangent the Jacobian of its residual
    (central differences, h = 1e-6 mm, relative error < 1e-6), at pitch 2.6 deg and a smooth state."""
    _, _, _, pitched = models
    term = pitch_term(pitched)
    p = {"fiber_pitch": torch.tensor([2.6], dtype=torch.float64), "E_fiber": torch.tensor([31000.0], dtype=torch.float64)}
    u = smooth_state(pitched)
    out = term.evaluate(u, p, torch.ones(1), tangent=True, energy=True)
    K = out.K_global[0]
    f = out.fe[0]
    dofs = np.flatnonzero(np.abs(f.numpy()) > 1e-3 * float(f.abs().max()))[::97][:6]
    assert dofs.size >= 4
    h = 1e-6
    for d in dofs.tolist():
        step = torch.zeros_like(u).reshape(1, -1)
        step[0, d] = h
        step = step.reshape(u.shape)
        up = term.evaluate(u + step, p, torch.ones(1), tangent=False, energy=True)
        um = term.evaluate(u - step, p, torch.ones(1), tangent=False, energy=True)
        dW = float(up.energy[0] - um.energy[0]) / (2 * h)
        assert abs(dW - float(f[d])) < 1e-6 * float(f.abs().max()), (d, dW, float(f[d]))
        col = (up.fe[0] - um.fe[0]).numpy() / (2 * h)
        exact = K[:, [d]].toarray().ravel()
        assert np.abs(col - exact).max() < 1e-6 * np.abs(exact).max(), d


def test_closed_forms_are_the_derived_ones(models):
    """The hand-written residual and tangent (fem.Truss's closed forms through the embedding) against
    torch.func's derivatives of the term's energy: the gradient, and the tangent along a random
    direction as the forward derivative of the residual (1e-12 relative)."""
    from torch.func import grad

    _, _, _, pitched = models
    term = pitch_term(pitched)
    p = {"fiber_pitch": torch.tensor([2.6], dtype=torch.float64), "E_fiber": torch.tensor([31000.0], dtype=torch.float64)}
    u = smooth_state(pitched)
    out = term.evaluate(u, p, torch.ones(1), tangent=True)
    g = grad(lambda uu: term.evaluate(uu, p, torch.ones(1), tangent=False, energy=True).energy.sum())(u)
    assert float((g.reshape(1, -1) - out.fe).abs().max()) < 1e-12 * float(out.fe.abs().max())
    v = torch.randn(u.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    _, dfe = jvp(lambda uu: term.evaluate(uu, p, torch.ones(1), tangent=False).fe, (u,), (v,))
    Kv = out.K_global[0] @ v.reshape(-1).numpy()
    assert np.abs(dfe[0].numpy() - Kv).max() < 1e-12 * np.abs(Kv).max()


def test_the_pitch_derivative_of_the_residual_is_exact(models):
    """d(residual)/d(pitch) by torch.func.jvp (what the sensitivities use) against a central
    difference in the pitch (h = 1e-6 deg: fiber nodes cross brick faces, where the derivative has
    kinks, so the step stays below the next crossing); relative error < 1e-5."""
    _, _, _, pitched = models
    term = pitch_term(pitched)
    u = smooth_state(pitched)
    E = torch.tensor([31000.0], dtype=torch.float64)

    def residual(alpha):
        return term.evaluate(u, {"fiber_pitch": alpha, "E_fiber": E}, torch.ones(1), tangent=False).fe

    a0 = torch.tensor([2.6], dtype=torch.float64)
    _, exact = jvp(residual, (a0,), (torch.ones(1, dtype=torch.float64),))
    h = 1e-6
    fd = (residual(a0 + h) - residual(a0 - h)) / (2 * h)
    assert float((exact - fd).abs().max() / fd.abs().max()) < 1e-5
    assert float(fd.abs().max()) > 1.0  # the pitch moves the fibers' forces (N per deg)


def test_the_pitch_moves_with_a_morph_only_one_at_a_time():
    """With the cavity offset (a morph) and the pitch both switched on, a member that moves both is
    refused by name; moving either alone is allowed (at the other's null the model is exact)."""
    model, _ = build_actuator_model(ActuatorGeometry(resolution=1), fiber_pitch=True, cavity_offset=True)
    model.finalize()
    p = {**tensors(PARAMS), "fiber_pitch": torch.tensor([2.0, 2.5, 2.5]), "delta_y": torch.tensor([0.3, 0.0, 0.3])}
    p = {k: v.expand(3).clone() if v.numel() == 1 else v for k, v in p.items()}
    with pytest.raises(ValueError, match="member 2 moves both fiber_pitch"):
        model.validate(p)
    model.validate({k: v[:2] for k, v in p.items()})


def test_no_hyper_reduction_and_the_forward_ensemble_goes_full(tmp_path, capsys):
    """A model with the pitch cannot be hyper-reduced (each member its own couplings): refused by
    name; a forward ensemble over a pitch prior says so and solves every member by full Newton."""
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import run_forward
    from torchfra.fem.reduced import HyperReducedModel, ReducedBasis

    model, _ = build_actuator_model(ActuatorGeometry(resolution=1), fiber_pitch=True)
    model.finalize()
    basis = ReducedBasis(torch.eye(model.n_red, 2, dtype=torch.float64), np.ones(2))
    with pytest.raises(ValueError, match="FiberPitch term .* cannot be hyper-reduced"):
        HyperReducedModel(model, basis, torch.zeros(1, model.n_red), tensors(PARAMS), [1.0])
    config = ForwardConfig(members=2, resolution=1, load_steps=2, frames=3, pressure=0.004,
                           parameters=["C10=lognormal:0.0068,0.0005", "fiber_pitch=uniform:1.8,2.4"])
    out = run_forward(config, tmp_path / "fwd", progress=True)
    assert "every member is solved by full Newton" in capsys.readouterr().out
    assert (out["status"] == "converged").all() and set(out["method"]) == {"full"}
    assert not np.allclose(out["params"]["fiber_pitch"].numpy(), 2.0)


def test_sensitivity_to_the_pitch_against_full_solves(models):
    """du/d(pitch) by implicit differentiation (fem.sensitivity) against a central difference of full
    solves at 2.6 +- 1e-6 deg (reference; measured 1.7e-6 relative, 1.5e-5 at 3e-6 and 1.7e-4 at 1e-5:
    the response carries a ripple as fiber nodes slide through the bricks, so the step must stay
    below the ripple's scale); relative error < 1e-5 at every node."""
    from torchfra.fem.sensitivity import sensitivities

    _, _, info, pitched = models
    n = info["mesh"].n_nodes
    options = fem.NewtonOptions(rtol=1e-12, stagnation_tol=1e-10)

    def params_of(th):
        return {**{k: torch.full_like(th["fiber_pitch"], v) for k, v in PARAMS.items()}, **th}

    def solve(a):
        sol = fem.solve(pitched, params_of({"fiber_pitch": torch.tensor([a], dtype=torch.float64)}), [1.0], options)
        assert sol.converged.all()
        return sol

    sol = solve(2.6)
    du = sensitivities(pitched, params_of, {"fiber_pitch": torch.tensor([2.6], dtype=torch.float64)}, sol).du[0, -1, :n, :, 0]
    h = 1e-6
    fd = (solve(2.6 + h).u[0, -1, :n] - solve(2.6 - h).u[0, -1, :n]) / (2 * h)
    assert float((fd - du).abs().max() / du.abs().max()) < 1e-5


def test_the_diagnosis_sees_the_pitch_through_a_secant():
    """ActuatorPhysics with the fiber_pitch candidate: at the drawn pitch its observations are the base
    model's; its sensitivity column is the central secant over +-0.25 deg (physics.SECANT_STEPS) of the
    observations themselves (reference: two observations), not the ripple's exact slope, which is
    hundreds of times larger."""
    import math

    from torchfra.actuator.candidates import SECANT_STEPS
    from torchfra.actuator.geometry import actuator_mesh
    from torchfra.diagnosis.model import ActuatorPhysics
    from torchfra.observation.operator import regular_grid
    from torchfra.observation.recording import Recording

    mesh = actuator_mesh(ActuatorGeometry(resolution=1))
    X = regular_grid(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), 4.0)
    times = np.arange(1, 4) / 3
    rec = Recording(np.arange(3), times, 0.02 * times, np.arange(len(X)), X, np.zeros((3, len(X), 2)))
    base, phys = ActuatorPhysics(rec, (), 1, 2), ActuatorPhysics(rec, ("fiber_pitch",), 1, 2)
    z = {"C10": math.log(0.006), "fiber_pitch": 2.0}
    ev = phys.observe(z)
    assert np.abs(ev.Y - base.observe({"C10": z["C10"]}).Y).max() < 1e-9
    h = SECANT_STEPS["fiber_pitch"]
    up = phys.observe({**z, "fiber_pitch": 2.0 + h}, values_only=True).Y
    dn = phys.observe({**z, "fiber_pitch": 2.0 - h}, values_only=True).Y
    col = ev.J[..., phys.names.index("fiber_pitch")]
    assert np.array_equal(col, (up - dn) / (2 * h))
    assert 0 < np.linalg.norm(col) < 50  # a secant of the physics: ~1-10 per deg here, not the ripple's ~1e3
