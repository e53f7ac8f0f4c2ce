"""The closed-form residuals and tangents of the pressure and truss terms against torch.func's
derivatives of the same functions (the face force ``int N_a (x_s x x_t)``, the cavity volume, the
truss energy), at random states of the actuator's faces and fibers: equal to round-off. Central
differences of the whole model are in ``test_derivatives.py``."""
import torch
from torch.func import grad, jacfwd, vmap

from torchfra import fem
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model


def model():
    m, _ = build_actuator_model(ActuatorGeometry(resolution=1))
    return m.finalize()


def test_pressure_forces_and_tangents_equal_torch_func():
    m = model()
    cav = next(t for t in m.terms if isinstance(t, fem.CavityPressure))
    fol = fem.FollowerPressure(m.mesh, cav.face_set)
    g = torch.Generator().manual_seed(0)
    u = 0.3 * torch.randn(2, m.n_nodes, 3, generator=g, dtype=torch.float64)
    p = {"P": torch.tensor([0.02, 0.01], dtype=torch.float64)}
    lam = torch.tensor([1.0, 0.5], dtype=torch.float64)
    x = (cav.X + u[:, cav.face_conn]).reshape(-1, 8, 3)
    scale = (lam * p["P"])[:, None, None]
    for term, f in ((cav, grad(cav._face_volume)), (fol, fol._face_force)):
        out = term.evaluate(u, p, lam)
        r = -scale * vmap(f)(x).reshape(2, -1, 24)
        K = -scale[..., None] * vmap(jacfwd(f))(x).reshape(2, -1, 24, 24)
        assert float((out.fe - r).abs().max()) < 1e-13 * float(r.abs().max())
        assert float((out.Ke - K).abs().max()) < 1e-13 * float(K.abs().max())


def test_truss_forces_and_tangents_equal_torch_func():
    m = model()
    tr = next(t for t in m.terms if isinstance(t, fem.Truss))
    g = torch.Generator().manual_seed(1)
    u = 0.05 * torch.randn(2, m.n_nodes, 3, generator=g, dtype=torch.float64)
    p = {"E_fiber": torch.tensor([31000.0, 20000.0], dtype=torch.float64)}
    out = tr.evaluate(u, p, torch.ones(2, dtype=torch.float64), energy=True)
    B = tr.conn.shape[0]
    X, jac0 = tr._reference(p, 2)
    x, jac0 = (X + u[:, tr.conn]).reshape(2 * B, 3, 3), jac0.reshape(2 * B, -1)
    EA = (p["E_fiber"] * tr.area).repeat_interleave(B)
    r = vmap(grad(tr._element_energy))(x, jac0, EA).reshape(2, B, 9)
    K = vmap(jacfwd(grad(tr._element_energy)))(x, jac0, EA).reshape(2, B, 9, 9)
    assert float((out.fe - r).abs().max()) < 1e-13 * float(r.abs().max())
    assert float((out.Ke - K).abs().max()) < 1e-13 * float(K.abs().max())
