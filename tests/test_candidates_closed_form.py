"""Candidate physics terms on small blocks against closed forms and limits.

References (each evaluated here in numpy, independently of the element code):
- Mooney-Rivlin nominal stress P = 2 C10 J^(-2/3) (F - I1/3 F^-T) + 2 C01 J^(-4/3) (I1 F - F C
  - 2/3 I2 F^-T) + K (J - 1) J F^-T, lateral stretch of uniaxial tension by brentq (sigma_11 = 0);
  incompressible uniaxial Cauchy stress sigma = 2 (lam^2 - 1/lam)(C10 + C01/lam).
- Compressibility: the same closed form across D1, and the incompressible limit approached
  linearly in D1 (Richardson: successive changes shrink 10x per decade).
- Gravity: total load rho g V (V = the box volume).
- Elastic support: a laterally confined block on normal springs under a uniform pressure P
  translates by P c_n (force balance) on top of its confined compression (brentq).
- Embedded fiber: homogeneous stretch of a bar with one straight fiber along its axis; force =
  A P33_matrix(lam) + E_f A_f lam (lam^2 - 1)/2 (Green-strain truss), and at small strain the
  rule of mixtures E_eff A = E_m A + E_f A_f with E_m = 9 K mu / (3K + mu).
- Pressure sensor: scaling invariance psi(s C10) = s psi(C10) when K and E_fiber scale with C10.
"""
import numpy as np
import torch
from helpers import block_with_cavity
from scipy.optimize import brentq

from torchfra import fem
from torchfra.fem.embedding import embedding_weights
from torchfra.fem.structured import box_mesh

TIGHT = fem.NewtonOptions(rtol=1e-10, etol=1e-18)


def mr_nominal_stress(F, C10, C01, D1):
    J = np.linalg.det(F)
    H = np.linalg.inv(F).T
    C = F.T @ F
    I1 = np.trace(C)
    I2 = 0.5 * (I1**2 - np.sum(C * C))
    return (2 * C10 * J ** (-2 / 3) * (F - I1 / 3 * H) + 2 * C01 * J ** (-4 / 3) * (I1 * F - F @ C - 2 / 3 * I2 * H)
            + (2 / D1) * (J - 1) * J * H)


def uniaxial_exact(C10, C01, D1, stretch):
    """Nominal stress P33 and lateral stretch of uniaxial tension (sigma_11 = sigma_22 = 0)."""
    def lateral(t):
        F = np.diag([t, t, stretch])
        return (mr_nominal_stress(F, C10, C01, D1) @ F.T)[0, 0]

    t = brentq(lateral, 0.3, 1.5, xtol=1e-15)
    return mr_nominal_stress(np.diag([t, t, stretch]), C10, C01, D1)[2, 2], t


def reactions(model, u, params):
    """Internal nodal forces (N, n_nodes, 3) with the forces on embedded nodes passed to their hosts."""
    lam = torch.ones(u.shape[0])
    RF = model.nodal_forces(u, params, lam, kinds=("internal", "load")).clone()
    for node, hosts, w in model.embedded_nodes:
        RF[:, hosts] += torch.as_tensor(w)[None, :, None] * RF[:, node][:, None]
        RF[:, node] = 0.0
    return RF


def uniaxial_model(material, L=2.0, fiber=None):
    """Unit-square bar of length L on rollers (x = 0, y = 0, z = 0), end z = L prescribed (set later).
    fiber: (E_modulus_name, area) of a straight fiber along the axis x = y = 0.5."""
    mesh = box_mesh((1.0, 1.0, L), (1, 1, 2))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, material))
    if fiber is not None:
        X = np.column_stack([np.full(5, 0.5), np.full(5, 0.5), np.linspace(0.0, L, 5)])
        nodes = model.add_nodes(X)
        model.add(fem.Truss(model.X, nodes[np.array([[0, 2, 1], [2, 4, 3]])], area=fiber[1], modulus=fiber[0]))
        for node, (hosts, w) in zip(nodes, embedding_weights(mesh, X)):
            model.embed(int(node), hosts, w)
    model.clamp("xmin", [0])
    model.clamp("ymin", [1])
    model.clamp("zmin", [2])
    return model


def solve_uniaxial(model, params, stretch, L=2.0):
    model.prescribe("zmax", 2, (stretch - 1) * L)
    params = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in params.items()}
    sol = fem.solve(model, params, [1.0], TIGHT)
    assert sol.converged.all(), sol.status
    u = sol.u[:, -1]
    force = reactions(model, u, params)[:, model.mesh.node_sets["zmax"], 2].sum(1).numpy()  # N, area 1 mm^2
    lateral = 1 + u[:, model.mesh.node_sets["xmax"], 0].mean(1).numpy()
    return force, lateral


# -- 1. Mooney-Rivlin ---------------------------------------------------------------------------------
def test_mooney_rivlin_uniaxial_tension_compressible():
    C10, C01, D1 = np.array([0.5, 0.2, 0.3]), np.array([0.1, 0.3, 0.0]), np.array([0.4, 0.05, 0.1])
    force, lateral = solve_uniaxial(uniaxial_model(fem.MooneyRivlin()), {"C10": C10, "C01": C01, "D1": D1}, 1.6)
    for m in range(3):
        P33, t = uniaxial_exact(C10[m], C01[m], D1[m], 1.6)
        assert abs(force[m] - P33) < 1e-9 * abs(P33)  # measured 1.0e-14
        assert abs(lateral[m] - t) < 1e-10


def test_mooney_rivlin_uniaxial_tension_incompressible():
    """D1 -> 0: Cauchy stress 2 (lam^2 - 1/lam)(C10 + C01/lam) to 1e-5 (error ~ D1; measured 3.3e-7 at
    D1 = 1e-6 /MPa, lateral stretch lam^-1/2 to 1.5e-7)."""
    C10, C01, lam = 0.3, 0.15, np.array([0.7, 1.5, 2.0])
    D1 = 1e-6
    rows = []
    for s in lam:  # prescribed values are per model, so one model per stretch
        model = uniaxial_model(fem.MooneyRivlin())
        rows.append(solve_uniaxial(model, {"C10": [C10], "C01": [C01], "D1": [D1]}, s))
    force = np.array([r[0][0] for r in rows])
    sigma = force * lam  # current area 1/lam
    exact = 2 * (lam**2 - 1 / lam) * (C10 + C01 / lam)
    assert np.abs(sigma - exact).max() / np.abs(exact).max() < 1e-5
    assert np.abs(np.array([r[1][0] for r in rows]) - lam**-0.5).max() < 1e-6


# -- 2. Finite compressibility --------------------------------------------------------------------------
def test_compressibility_uniaxial_response_across_d1():
    """D1 free: the compressible closed form holds over three decades of K/mu (1 to 1000)."""
    C10 = 0.2
    K_over_mu = np.array([1.0, 10.0, 100.0, 1000.0])
    D1 = 2.0 / (K_over_mu * 2 * C10)
    n = D1.size
    force, lateral = solve_uniaxial(uniaxial_model(fem.MooneyRivlin()),
                                    {"C10": np.full(n, C10), "C01": np.full(n, 0.05), "D1": D1}, 1.4)
    for m in range(n):
        P33, t = uniaxial_exact(C10, 0.05, D1[m], 1.4)
        assert abs(force[m] - P33) < 1e-9 * abs(P33)
        assert abs(lateral[m] - t) < 1e-10
    assert np.all(np.diff(lateral) < 0)  # less compressible, more lateral contraction


def test_compressibility_continuity_to_incompressible_limit():
    """A pressurized cavity block (inhomogeneous) as D1 -> 0: the displacements converge linearly in
    D1 (changes shrink ~10x per decade of K/mu), so the null D1 = 0 is the limit the base model's
    stand-in D1 = 1/(1000 C10) approximates. Measured: changes 2.6e-2, 2.7e-3, 2.8e-4, 2.8e-5 of
    max |u| per decade; the stand-in differs from the limit (Richardson from K/mu = 1e5, 1e6) by
    3.0e-3 of max |u|."""
    mesh = block_with_cavity()
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(fem.CavityPressure(mesh, "cavity"))
    model.clamp("zmin")
    C10 = 0.1
    K_over_mu = np.array([1e2, 1e3, 1e4, 1e5, 1e6])
    n = K_over_mu.size
    params = {"C10": torch.full((n,), C10), "D1": torch.as_tensor(1.0 / (K_over_mu * C10)), "P": torch.full((n,), 0.15)}
    sol = fem.solve(model, params, [1.0], TIGHT)
    assert sol.converged.all(), sol.status
    u = sol.u[:, -1].reshape(n, -1)
    scale = u.abs().max()
    assert scale > 0.1  # a 3 mm block inflating visibly
    change = (u[1:] - u[:-1]).abs().max(1).values / scale
    ratio = change[:-1] / change[1:]
    assert torch.all((ratio > 8) & (ratio < 12)), ratio  # linear in D1
    limit = u[-1] + (u[-1] - u[-2]) / 9.0  # Richardson, error O(D1^2)
    standin = float((u[1] - limit).abs().max() / scale)
    assert 1e-4 < standin < 1e-2, standin


# -- 3. Gravity -----------------------------------------------------------------------------------------
def test_gravity_total_load_and_reactions():
    """Consistent nodal loads sum to rho g V d exactly on a distorted mesh; after a finite-strain solve of
    a sagging cantilever, the support reactions carry exactly that load."""
    mesh = box_mesh((1.0, 1.2, 6.0), (1, 2, 4), distortion=0.3)
    V = 1.0 * 1.2 * 6.0  # distortion moves interior nodes only
    d = np.array([0.0, 1.0, -1.0]) / np.sqrt(2.0)
    term = fem.Gravity(mesh, direction=d)
    rho = torch.tensor([1.1e-9, 2e-8])
    out = term.evaluate(torch.zeros(2, mesh.n_nodes, 3), {"density": rho}, torch.ones(2))
    total = -out.fe.reshape(2, -1, 20, 3).sum((1, 2))  # external force = -residual
    exact = (rho * 9.81e3 * V)[:, None] * torch.as_tensor(d)
    assert (total - exact).abs().max() < 1e-14 * exact.abs().max()  # measured 6.5e-16
    assert abs(term.volume - V) < 1e-13 * V

    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(term)
    model.clamp("zmin")
    params = {"C10": torch.tensor([0.002, 0.002]), "D1": torch.tensor([5.0, 5.0]), "density": rho}
    sol = fem.solve(model, params, [1.0], TIGHT)
    assert sol.converged.all(), sol.status
    u = sol.u[:, -1]
    assert u[1].abs().max() > 1.0  # the heavy member sags by more than its width: finite strain
    r = model.nodal_forces(u, params, torch.ones(2), kinds=("internal", "load"))
    support = r[:, mesh.node_sets["zmin"]].sum(1)  # force the clamp applies = residual there
    assert (support + exact).abs().max() < 1e-9 * exact.abs().max()  # measured 4.8e-14


# -- 4. Compliant base ----------------------------------------------------------------------------------
def test_elastic_support_confined_block_translates_by_p_cn():
    """Laterally confined block (rollers on all sides), base on springs, pressure P on top: the base
    moves by exactly P c_n, the top by P c_n plus the closed-form confined compression."""
    L = 2.0
    mesh = box_mesh((1.0, 1.0, L), (2, 2, 2))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(fem.ElasticSupport(mesh, "zmin"))
    model.add(fem.FollowerPressure(mesh, "zmax"))
    for side, c in (("xmin", 0), ("xmax", 0), ("ymin", 1), ("ymax", 1)):
        model.clamp(side, [c])
    C10, D1, P = 0.2, 0.5, 0.1
    c_n = torch.tensor([1.0, 10.0, 0.01])
    params = {"C10": torch.full((3,), C10), "D1": torch.full((3,), D1), "P": torch.full((3,), P), "c_n": c_n,
              "c_t": torch.tensor([1.0, 0.1, 100.0])}
    sol = fem.solve(model, params, [1.0], TIGHT)
    assert sol.converged.all(), sol.status
    u = sol.u[:, -1]
    base = u[:, mesh.node_sets["zmin"], 2]
    assert (base + P * c_n[:, None]).abs().max() < 1e-10 * P * c_n.max()  # measured 4.8e-15 relative
    s = brentq(lambda s: mr_nominal_stress(np.diag([1.0, 1.0, s]), C10, 0.0, D1)[2, 2] + P, 0.5, 1.0, xtol=1e-15)
    top = u[:, mesh.node_sets["zmax"], 2]
    assert (top - (-P * c_n[:, None] + (s - 1) * L)).abs().max() < 1e-10 * L
    assert u[:, :, :2].abs().max() < 1e-12  # confined: no lateral motion, tangential springs idle


def test_elastic_support_converges_to_the_clamp():
    """c = c_n = c_t -> 0: a bending block on springs converges to the clamped block linearly in c
    (the null c = 0 is the clamp, handled by clamping)."""
    mesh = box_mesh((1.0, 1.0, 3.0), (1, 1, 3))

    def build(compliant):
        model = fem.Model(mesh)
        model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), integration="full"))  # one brick across: no spurious modes
        model.add(fem.FollowerPressure(mesh, "ymin"))
        fem.support_face(model, "zmin", compliant)
        return model

    base = {"C10": torch.tensor([0.1]), "D1": torch.tensor([1.0]), "P": torch.tensor([0.01])}
    clamped = fem.solve(build(False), base, [1.0], TIGHT)
    c = torch.tensor([1e-1, 1e-2, 1e-3, 1e-4])
    n = c.numel()
    params = {k: v.expand(n) for k, v in base.items()} | {"c_n": c, "c_t": c}
    springs = fem.solve(build(True), params, [1.0], TIGHT)
    assert clamped.converged.all() and springs.converged.all()
    u0 = clamped.u[0, -1]
    err = (springs.u[:, -1] - u0).abs().flatten(1).max(1).values / u0.abs().max()
    assert err[-1] < 1e-3  # measured 7.4e-2, 7.4e-3, 7.5e-4, 7.5e-5 of max |u| (2.39 mm)
    ratio = err[:-1] / err[1:]
    assert torch.all((ratio > 8) & (ratio < 12)), ratio


# -- 5. Embedded fiber ----------------------------------------------------------------------------------
def test_embedded_fiber_bar_in_tension():
    """A bar with one straight embedded fiber along its axis, stretched homogeneously: the reaction is the
    matrix's closed-form stress times A plus the truss force, at finite strain (to 1e-9) and, at small
    strain, the rule of mixtures E_m A + E_f A_f (to 1e-5; the difference is O(strain) = 1e-6)."""
    C10, D1, E_f, A_f = 0.1, 0.1, 3100.0, 0.01
    params = {"C10": [C10, C10], "D1": [D1, D1], "E_fiber": [E_f, 0.5 * E_f]}
    force, lateral = solve_uniaxial(uniaxial_model(fem.NeoHookean(), fiber=("E_fiber", A_f)), params, 1.05)
    for m, E in enumerate(params["E_fiber"]):
        P33, t = uniaxial_exact(C10, 0.0, D1, 1.05)
        exact = P33 + E * A_f * 1.05 * (1.05**2 - 1) / 2
        assert abs(force[m] - exact) < 1e-9 * exact  # measured 4.2e-15
        assert abs(lateral[m] - t) < 1e-10  # a truss adds no lateral stiffness
    eps = 1e-6
    force, _ = solve_uniaxial(uniaxial_model(fem.NeoHookean(), fiber=("E_fiber", A_f)),
                              {k: v[:1] for k, v in params.items()}, 1 + eps)
    mu, K = 2 * C10, 2 / D1
    E_m = 9 * K * mu / (3 * K + mu)
    mixture = E_m * 1.0 + E_f * A_f
    assert abs(force[0] / eps - mixture) < 1e-5 * mixture  # measured 1.5e-6
    assert E_f * A_f > 30 * E_m  # the fiber dominates, as in the actuator


# -- 6. Pressure sensor ---------------------------------------------------------------------------------
def _sensor_model():
    mesh = block_with_cavity()
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    X = np.column_stack([np.full(5, 1.5), np.full(5, 0.5), np.linspace(0.2, 2.8, 5)])  # in the cavity wall
    nodes = model.add_nodes(X)
    model.add(fem.Truss(model.X, nodes[np.array([[0, 2, 1], [2, 4, 3]])], area=0.01))
    for node, (hosts, w) in zip(nodes, embedding_weights(mesh, X)):
        model.embed(int(node), hosts, w)
    model.add(fem.SensorCavityPressure(mesh, "cavity"))
    model.clamp("zmin")
    return model


def test_sensor_gain_is_confounded_with_c10():
    """u(gain, C10) = u(1, C10 / gain) when K = 2/D1 and E_fiber scale with C10 (the incompressible,
    rigid-fiber statement), to solver tolerance; with E_fiber held fixed the pair differs."""
    gain, C10, P, bulk, fiber = 1.6, 0.1, 0.08, 1000.0, 1e4
    c10 = torch.tensor([C10, C10 / gain, C10, C10 / gain])
    E = torch.tensor([fiber * C10, fiber * C10 / gain, fiber * C10, fiber * C10])  # last pair: fixed E
    params = {"C10": c10, "D1": 1.0 / (bulk * c10), "E_fiber": E, "P": torch.full((4,), P),
              "pressure_gain": torch.tensor([gain, 1.0, gain, 1.0]), "pressure_offset": torch.zeros(4)}
    sol = fem.solve(_sensor_model(), params, [1.0], TIGHT)
    assert sol.converged.all(), sol.status
    u = sol.u[:, -1]
    scale = u.abs().max()
    assert scale > 0.05
    confounded = float((u[0] - u[1]).abs().max() / scale)
    assert confounded < 1e-8, confounded  # measured 5.5e-15 of max |u| = 0.109 mm
    assert float((u[2] - u[3]).abs().max() / scale) > 1e-4  # fixed E_fiber breaks the scaling: 1.2e-2


# -- all candidates at their nulls ----------------------------------------------------------------------
def test_candidates_at_null_reproduce_the_base_model():
    """The sensor-test block with Mooney-Rivlin (with_material), the pressure sensor
    (with_pressure_sensor) and gravity added, all at the catalogue's null values, solves to the base
    model's displacements (Neo-Hookean closed-form path vs Mooney-Rivlin derived path: round-off)."""
    from torchfra.actuator.candidates import fe_null_values
    from torchfra.fem.transforms import with_material, with_pressure_sensor

    def build():
        model = _sensor_model()
        model.terms = [fem.CavityPressure(model.mesh, "cavity") if isinstance(t, fem.CavityPressure) else t
                       for t in model.terms]
        return model

    base_params = {"C10": torch.tensor([0.1]), "D1": torch.tensor([0.01]), "E_fiber": torch.tensor([1000.0]),
                   "P": torch.tensor([0.08])}
    base = fem.solve(build(), base_params, [1.0], TIGHT)
    model = with_pressure_sensor(with_material(build(), fem.MooneyRivlin()))
    model.add(fem.Gravity(model.mesh, direction=(0.0, 1.0, 0.0)))
    nulls = {k: torch.tensor([v]) for name in ("mooney_rivlin", "gravity", "pressure_sensor")
             for k, v in fe_null_values(name).items()}
    assert set(nulls) == {"C01", "density", "pressure_gain", "pressure_offset"}
    assert set(model.param_names()) == set(base_params) | set(nulls)
    cand = fem.solve(model, base_params | nulls, [1.0], TIGHT)
    assert base.converged.all() and cand.converged.all()
    u0 = base.u[0, -1]
    assert float((cand.u[0, -1] - u0).abs().max() / u0.abs().max()) < 1e-10  # measured 7.1e-15
