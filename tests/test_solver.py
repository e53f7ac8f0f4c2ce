"""Solver-level checks: pressure forms agree, batches equal separate solves, rigid faces stay rigid,
failing members are reported while the others finish."""
import numpy as np
import torch
from helpers import assemble_dense, block_with_cavity

from torchfra import fem
from torchfra.fem.structured import box_mesh


def test_cavity_volume_closed_form():
    """Volume enclosed by the cavity surface: exactly the removed 1 mm^3 element, and det(F) times
    it under an affine deformation (3x3 Gauss is exact for the Quad8 volume integrand)."""
    mesh = block_with_cavity()
    term = fem.CavityPressure(mesh, "cavity")
    F = np.array([[1.2, 0.1, 0.0], [0.05, 0.9, 0.2], [0.0, -0.1, 1.1]])
    u = torch.as_tensor(np.stack([np.zeros_like(mesh.nodes), mesh.nodes @ (F - np.eye(3)).T]))
    V = term.cavity_volume(u).numpy()
    assert np.allclose(V, [1.0, np.linalg.det(F)], rtol=1e-13)


def test_cavity_potential_equals_follower_load():
    """On a closed surface, P dV/dx (conservative form) equals the follower traction P J F^-T N
    integrated (both residuals and load stiffnesses), for an arbitrary deformed state."""
    mesh = block_with_cavity()
    params = {"P": torch.tensor([0.3, 1.1])}
    lam = torch.tensor([1.0, 0.5])
    u = 0.05 * torch.randn(2, mesh.n_nodes, 3, generator=torch.Generator().manual_seed(0))
    n = 3 * mesh.n_nodes
    r1, K1 = assemble_dense(fem.CavityPressure(mesh, "cavity"), u, params, lam, n)
    r2, K2 = assemble_dense(fem.FollowerPressure(mesh, "cavity"), u, params, lam, n)
    assert (r1 - r2).abs().max() < 1e-13 * r1.abs().max()
    assert (K1 - K2).abs().max() < 1e-13 * K1.abs().max()
    assert (K1 - K1.transpose(1, 2)).abs().max() < 1e-13 * K1.abs().max()


def _cavity_model(mesh, pressure_term):
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(pressure_term)
    model.clamp("zmin")
    return model


def test_cavity_and_follower_solutions_agree():
    mesh = block_with_cavity()
    params = {"C10": torch.tensor([0.1]), "D1": torch.tensor([0.05]), "P": torch.tensor([0.1])}
    sols = [
        fem.solve(_cavity_model(mesh, t(mesh, "cavity")), params, [0.5, 1.0])
        for t in (fem.CavityPressure, fem.FollowerPressure)
    ]
    assert all(s.status[0] == "converged" for s in sols)
    du = (sols[0].u - sols[1].u).abs().max() / sols[0].u.abs().max()
    assert du < 1e-9
    # the cavity grows monotonically with pressure
    cav = fem.CavityPressure(mesh, "cavity")
    V = cav.cavity_volume(sols[0].u[0])
    assert V[0] > 1.0 and V[1] > V[0]


def _bending_model(mesh):
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.add(fem.FollowerPressure(mesh, "ymax", pressure="P"))
    model.clamp("zmin")
    model.rigid("zmax")
    return model


def test_batch_equals_separate_solves():
    """N members in one batch equal N separate solves to 1e-10."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {
        "C10": torch.tensor([0.05, 0.08, 0.12]),
        "D1": torch.tensor([0.5, 0.2, 1.0]),
        "P": torch.tensor([0.002, 0.003, 0.005]),
    }
    batch = fem.solve(_bending_model(mesh), params, [0.5, 1.0])
    assert (batch.status == "converged").all()
    for m in range(3):
        one = fem.solve(_bending_model(mesh), {k: v[m : m + 1] for k, v in params.items()}, [0.5, 1.0])
        assert (one.u[0] - batch.u[m]).abs().max() / batch.u[m].abs().max() < 1e-10
        assert one.iterations[0] == batch.iterations[m]


def test_rigid_face_moves_rigidly():
    """The rigid top face: distances between its nodes are preserved and it stays planar."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05]), "D1": torch.tensor([0.2]), "P": torch.tensor([0.004])}
    sol = fem.solve(_bending_model(mesh), params, [1.0])
    top = mesh.node_sets["zmax"]
    x = mesh.nodes[top] + sol.u[0, -1, top].numpy()
    X = mesh.nodes[top]
    d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)  # noqa: E731
    assert np.abs(d(x) - d(X)).max() < 1e-12
    centred = x - x.mean(0)
    assert np.linalg.svd(centred, compute_uv=False)[-1] < 1e-12
    assert sol.u[0, -1, top, 1].abs().max() > 0.5  # and it really moved: the block bends


def test_failing_member_reported_others_finish():
    """A member loaded far beyond what the body can take is flagged 'diverged' with the load it
    reached and its last residual; the other members converge to their own answers."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05, 0.05]), "D1": torch.tensor([0.2, 0.2]), "P": torch.tensor([0.003, 0.5])}
    opts = fem.NewtonOptions(min_increment=1e-4, max_iterations=10)
    sol = fem.solve(_bending_model(mesh), params, [0.5, 1.0], opts)
    assert sol.status.tolist() == ["converged", "diverged"]
    assert 0 < sol.load_reached[1] < 1.0 and np.isfinite(sol.last_residual[1])
    assert torch.isnan(sol.u[1, -1]).all()
    alone = fem.solve(_bending_model(mesh), {k: v[:1] for k, v in params.items()}, [0.5, 1.0], opts)
    assert (alone.u[0] - sol.u[0]).abs().max() < 1e-10 * sol.u[0].abs().max()


def test_a_member_stops_when_its_newton_budget_is_spent():
    """``member_budget``: a hopeless member stops after that many Newton iterations, flagged
    'diverged' at the load it reached, instead of cutting back to the minimum increment; the other
    member's answer is unchanged (1e-10) and its own iterations are far below the budget."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05, 0.05]), "D1": torch.tensor([0.2, 0.2]), "P": torch.tensor([0.003, 0.5])}
    free = fem.solve(_bending_model(mesh), params, [0.5, 1.0], fem.NewtonOptions(min_increment=1e-4, max_iterations=10))
    budget = fem.NewtonOptions(min_increment=1e-4, max_iterations=10, member_budget=30)
    sol = fem.solve(_bending_model(mesh), params, [0.5, 1.0], budget)
    assert free.iterations[1] > 60 and free.iterations[0] < 30  # the budget binds the hopeless member only
    assert sol.status.tolist() == ["converged", "diverged"] and sol.iterations[1] == 30
    assert 0 < sol.load_reached[1] < 1.0 and torch.isnan(sol.u[1, -1]).all()
    assert (free.u[0] - sol.u[0]).abs().max() < 1e-10 * sol.u[0].abs().max()


def test_a_member_stops_when_its_time_budget_is_spent():
    """``member_seconds``: once the solve has taken that long, a member that has not reached its last
    load factor stops at its next unconverged iteration, flagged 'diverged' at the load it reached
    (NaN beyond it). A budget no member reaches changes nothing (bitwise); a vanishing one stops
    every member short of the load (no timing in the assertion: the clock is past it at once)."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05, 0.05]), "D1": torch.tensor([0.2, 0.2]), "P": torch.tensor([0.003, 0.5])}
    opts = dict(min_increment=1e-4, max_iterations=10, member_budget=40)
    free = fem.solve(_bending_model(mesh), params, [0.5, 1.0], fem.NewtonOptions(**opts))
    ample = fem.solve(_bending_model(mesh), params, [0.5, 1.0], fem.NewtonOptions(**opts, member_seconds=1e9))
    assert torch.equal(torch.nan_to_num(free.u), torch.nan_to_num(ample.u)) and free.status.tolist() == ample.status.tolist()
    spent = fem.solve(_bending_model(mesh), params, [0.5, 1.0], fem.NewtonOptions(**opts, member_seconds=1e-12))
    assert spent.status.tolist() == ["diverged", "diverged"]
    assert (spent.load_reached < 0.5).all() and torch.isnan(spent.u[:, -1]).all()
    assert (spent.iterations <= 2).all()


def test_hybrid_newton_takes_a_full_load_step():
    """Near-incompressible bending (K/mu = 100) under a follower pressure with a rigid top, solved in
    ONE load increment: the element pressures are Newton unknowns (u-p Newton, as Abaqus hybrid
    elements), so a mispredicted volume change is not amplified by K into the tangent. Before this
    design the same step stalled at a relative residual ~1 and needed cutbacks."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05]), "D1": torch.tensor([0.2]), "P": torch.tensor([0.003])}
    opts = fem.NewtonOptions(initial_increment=1.0, min_increment=0.5, max_iterations=15)
    sol = fem.solve(_bending_model(mesh), params, [1.0], opts)
    assert sol.status[0] == "converged" and sol.cutbacks[0] == 0 and sol.iterations[0] <= 12
    ref = fem.solve(_bending_model(mesh), params, [1.0])  # default load stepping, same answer
    assert (ref.u - sol.u).abs().max() < 1e-8 * ref.u.abs().max()


def test_warm_start_continues_changes_parameters_and_unloads():
    """A warm start from equilibrium states (as the restart filter uses them) reaches the same
    equilibrium as a solve from scratch, to 1e-8 relative: continuing the load 0.5 -> 1, with new
    parameters (C10 +10 %), and unloading 1 -> 0.5 (hyperelastic: path independent)."""
    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    model = _bending_model(mesh)
    p = {"C10": torch.tensor([0.05, 0.08]), "D1": torch.tensor([0.5, 0.2]), "P": torch.tensor([0.003, 0.004])}
    q = dict(p, C10=p["C10"] * 1.1)
    half = fem.solve(model, p, [0.5])
    full_q = fem.solve(model, q, [0.5, 1.0])
    cont = fem.solve(model, q, [1.0], start=fem.WarmStart(half.x_last, 0.5, 1.0))
    assert (cont.status == "converged").all()
    rel = lambda a, b: float((a - b).abs().max() / b.abs().max())  # noqa: E731
    assert rel(cont.u[:, -1], full_q.u[:, -1]) < 1e-8
    back = fem.solve(model, q, [1.0], start=fem.WarmStart(cont.x_last, 1.0, 0.5))
    assert rel(back.u[:, -1], full_q.u[:, 0]) < 1e-8
    assert back.iterations.max() > 0


def test_reused_factorizations_give_the_same_answer_with_fewer_factorizations(monkeypatch):
    """Modified Newton near convergence (``reuse_factorization``): the converged states equal full
    Newton's to the Newton tolerance (1e-9 relative residual: 1e-7 in u here), with fewer sparse
    factorizations; a batch still equals its members solved one by one, step for step."""
    from torchfra.fem import linsolve

    mesh = box_mesh((2.0, 2.0, 6.0), (2, 2, 3))
    params = {"C10": torch.tensor([0.05, 0.08]), "D1": torch.tensor([0.5, 0.2]), "P": torch.tensor([0.004, 0.005])}
    loads = np.arange(1, 11) / 10
    count = {"n": 0}
    factorize = linsolve.SparseSolver.factorize

    def counted(self, K):
        count["n"] += 1
        return factorize(self, K)

    monkeypatch.setattr(linsolve.SparseSolver, "factorize", counted)
    runs = {}
    for reuse in (False, True):
        count["n"] = 0
        sol = fem.solve(_bending_model(mesh), params, loads, fem.NewtonOptions(reuse_factorization=reuse))
        assert (sol.status == "converged").all()
        runs[reuse] = (sol, count["n"])
    (full, n_full), (mod, n_mod) = runs[False], runs[True]
    assert n_mod < n_full, (n_mod, n_full)
    assert float((mod.u - full.u).abs().max() / full.u.abs().max()) < 1e-7
    for m in range(2):
        one = fem.solve(_bending_model(mesh), {k: v[m : m + 1] for k, v in params.items()}, loads)
        assert one.iterations[0] == mod.iterations[m]
        assert float((one.u[0] - mod.u[m]).abs().max() / mod.u[m].abs().max()) < 1e-10
