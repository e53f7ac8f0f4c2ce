"""Reduced-order ensemble solves (torchfra.fem.reduced) against full Newton solves of every member.

Reference: ``fem.solve`` (full Newton to rtol 1e-9) of the same members. The model is the block with
a pressurized cavity carrying every candidate term at once (Mooney-Rivlin hybrid body, embedded
fiber, self-weight, base springs, pressure sensor, a rigid top that rotates), with two parameters
varying across members, so the method is checked beyond the one-parameter P/C10 scaling law.
"""
import numpy as np
import pytest
import torch
from test_sensitivity import THETA, every_candidate_model

from torchfra import fem
from torchfra.fem.reduced import ReducedBasis, build_reduced, select_snapshots, solve_ensemble, solve_reduced

LOADS = [0.25, 0.5, 0.75, 1.0]


def ensemble(N=9, seed=0):
    g = torch.Generator().manual_seed(seed)
    th = {k: torch.full((N,), v, dtype=torch.float64) for k, v in THETA.items()}
    th["C10"] = 0.1 * torch.exp(0.15 * torch.randn(N, generator=g, dtype=torch.float64))
    th["E_fiber"] = 300 * torch.exp(0.2 * torch.randn(N, generator=g, dtype=torch.float64))
    th["P"] = torch.full((N,), 0.12, dtype=torch.float64)
    return th


@pytest.fixture(scope="module")
def solved():
    model = every_candidate_model()
    params = ensemble()
    ref = fem.solve(model, params, LOADS)
    assert ref.converged.all()
    scale = float(ref.u.abs().max())  # 0.11 mm: tolerances scaled from the actuator's ~20 mm
    return model, params, ref, solve_ensemble(model, params, LOADS, tol=TOL * scale, xtol=1e-5 * scale,
                                              polish_tol=1e-7 * scale)


TOL = 2e-4  # accepted error estimate of a reduced member, relative to the largest displacement


def test_reduced_members_match_full_newton_and_their_error_estimate(solved):
    model, params, ref, es = solved
    reduced = np.flatnonzero(es.method == "reduced")
    assert reduced.size >= 3  # 5 snapshots (1 + 2 x 2 varying directions) of 9 members
    assert set(es.snapshots) == set(np.flatnonzero(es.method == "full"))
    assert (es.status == "converged").all()
    err = (es.u - ref.u).abs().amax(dim=(1, 2, 3)).numpy()
    scale = float(ref.u.abs().max())
    # every frame of every member: the reduced answer is within 2e-4 of the largest displacement
    # (the actuator's requirement, 1e-3 mm on ~18 mm, is 5.5e-5: its tests are in test_forward.py)
    assert err.max() < TOL * scale, err
    assert err[es.snapshots].max() < 1e-12 * scale  # snapshots are the full Newton solutions
    # the check (one full Newton step at the last load) measures the distance to the full solution:
    # Newton converges quadratically from there, so estimate and error agree to a few percent; at
    # the other loads a modified Newton step (the last load's factorization) estimates it within
    # the tangent's change: the estimate is the largest over the loads
    last = (es.u[reduced, -1] - ref.u[reduced, -1]).abs().amax(dim=(1, 2)).numpy()
    every = (es.u[reduced] - ref.u[reduced]).abs().amax(dim=(1, 2, 3)).numpy()
    assert np.all(es.error_estimate[reduced] >= 0.95 * last)
    assert np.all((es.error_estimate[reduced] >= 0.5 * every) & (es.error_estimate[reduced] <= 2.0 * every))
    assert np.isnan(es.error_estimate[es.snapshots]).all()
    assert es.counts["sampled_iterations"] > 0 and es.counts["polish_iterations"] > 0


def test_hyper_reduction_reproduces_the_reduced_forces_it_was_trained_on(solved):
    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, ref.a[snap], {k: v[snap] for k, v in params.items()}, LOADS, sampling_tol=1e-3)
    assert max(hyper.training_error) <= 1e-3
    assert sum(hyper.sampled_blocks) < sum(t.dofs.shape[0] for t in model.terms)
    # on a training state the sampled reduced residual equals V^T r of the full model to the tolerance
    q = ref.a[snap[:1], 2] @ hyper.basis.V
    lam = torch.tensor([LOADS[2]], dtype=torch.float64)
    sub = {k: v[snap[:1]] for k, v in params.items()}
    R, K, ok = hyper.evaluate(q, sub, lam)
    full = model.evaluate(q @ hyper.basis.V.T, sub, lam, tangent=True)
    V = hyper.basis.V.numpy()
    Kg = V.T @ (full.tangents[0] @ V)
    assert ok.all()
    assert np.abs(K[0].numpy() - Kg).max() < 0.05 * np.abs(Kg).max()


def test_the_unsampled_view_gives_the_full_models_galerkin_residual_and_tangent(solved):
    """hyper.galerkin(): every block at weight 1, evaluated from element arrays, against the full
    model's assembled, constraint-reduced residual and tangent projected on V (the polish's
    reference). The tangent is projected in single precision: it agrees to 1e-5, the residual to
    round-off."""
    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, ref.a[snap], {k: v[snap] for k, v in params.items()}, LOADS)
    g = hyper.galerkin()
    assert g is hyper.galerkin() and g.sampled_blocks == [t.dofs.shape[0] for t in model.terms]
    V = hyper.basis.V
    q = ref.a[:3, 1] @ V + 1e-3 * torch.randn(3, V.shape[1], generator=torch.Generator().manual_seed(0), dtype=V.dtype)
    lam = torch.full((3,), LOADS[1], dtype=torch.float64)
    sub = {k: v[:3] for k, v in params.items()}
    R, K, ok = g.evaluate(q, sub, lam)
    full = model.evaluate(q @ V.T, sub, lam, tangent=True)
    Vn = V.numpy()
    Kg = np.stack([Vn.T @ (Kr @ Vn) for Kr in full.tangents])
    assert ok.all()
    assert float((R - full.residual @ V).abs().max()) <= 1e-10 * float(R.abs().max())
    assert np.abs(K.numpy() - Kg).max() <= 1e-5 * np.abs(Kg).max()
    # the sampled model is not this: its residual differs by the sampling error
    Rs, _, _ = hyper.evaluate(q, sub, lam, tangent=False)
    assert float((Rs - R).abs().max()) > 1e-8 * float(R.abs().max())


def test_members_the_check_rejects_are_solved_in_full(solved):
    model, params, ref, _ = solved
    es = solve_ensemble(model, params, LOADS, tol=0.0)  # no reduced answer is good enough
    assert (es.method == "full").all()
    assert float((es.u - ref.u).abs().max()) < 1e-12 * float(ref.u.abs().max())


def test_reduced_newton_reports_failure_instead_of_a_wrong_answer(solved):
    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, ref.a[snap], {k: v[snap] for k, v in params.items()}, LOADS)
    far = {k: v[:1].clone() for k, v in params.items()}
    far["C10"] = far["C10"] * 1e-3  # far outside the snapshots: the basis cannot hold this member
    rs = solve_reduced(hyper, far, LOADS, max_iterations=4, max_polish=3)
    assert rs.status[0] == "failed" and torch.isnan(rs.u[0]).all() and np.isnan(rs.error_estimate[0])


def test_snapshot_selection_covers_the_parameter_range():
    c10 = torch.tensor([1.0, 1.1, 0.9, 2.0, 0.5, 1.05, 1.2])
    chosen = select_snapshots({"C10": c10, "P": torch.full((7,), 0.1)})
    assert chosen.size == 5  # one varying parameter: the centre, the two ends, then the middles
    assert chosen[0] == 5 and set(chosen[1:3]) == {3, 4}  # the median member (1.05), then the extremes
    assert select_snapshots({"C10": torch.ones(4)}).tolist() == [0]  # nothing varies: one solve serves all
    tied = select_snapshots({"C10": c10, "D1": 1e-3 / c10})  # D1 tied to C10: still one direction
    assert tied.tolist() == chosen.tolist()


def test_basis_keeps_the_modes_above_its_tolerance():
    rng = np.random.default_rng(0)
    states = rng.standard_normal((30, 3)) @ rng.standard_normal((3, 50))  # rank 3
    basis = ReducedBasis.from_states(np.vstack([states, np.full((1, 50), np.nan)]), tol=1e-9)
    assert basis.size == 3
    np.testing.assert_allclose(basis.V.T @ basis.V, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="no finite state"):
        ReducedBasis.from_states(np.full((2, 5), np.nan))


def test_saved_reduction_rebuilds_the_same_reduced_model(solved, tmp_path):
    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, ref.a[snap], {k: v[snap] for k, v in params.items()}, LOADS)
    np.savez(tmp_path / "r.npz", **hyper.arrays())
    with np.load(tmp_path / "r.npz", allow_pickle=False) as f:
        again = type(hyper).from_arrays(model, {k: f[k] for k in f.files})
    q = ref.a[:2, 1] @ hyper.basis.V
    lam = torch.full((2,), LOADS[1], dtype=torch.float64)
    sub = {k: v[:2] for k, v in params.items()}
    R1, K1, _ = hyper.evaluate(q, sub, lam)
    R2, K2, _ = again.evaluate(q, sub, lam)
    assert torch.equal(R1, R2) and torch.equal(K1, K2)
    with pytest.raises(ValueError, match="unknowns"):
        type(hyper).from_arrays(model, {**hyper.arrays(), "V": hyper.basis.V.numpy()[1:]})


def test_a_snapshot_that_stopped_early_keeps_the_load_steps_it_reached(solved):
    """A snapshot member that does not reach full load (a soft draw that balloons) still holds
    equilibrium states up to where it stopped; the basis must span them (on the actuator, leaving
    them out sent the neighbours of the softest draw to full Newton, with estimates of 0.03 mm).
    Reference: the full Newton states themselves (projection error to the basis tolerance)."""
    model, params, ref, es = solved
    a, b = (int(m) for m in es.snapshots[:2])
    states = ref.a[[a, b]].clone()
    states[1, 2:] = float("nan")  # member b stopped after the second load step
    sub = {k: v[[a, b]] for k, v in params.items()}
    with_partial = build_reduced(model, states, sub, LOADS).basis.V
    without = build_reduced(model, states[:1], {k: v[:1] for k, v in sub.items()}, LOADS).basis.V
    reached = ref.a[b, :2]
    norm = float(reached.norm())

    def gap(V):
        return float((reached - (reached @ V) @ V.T).norm()) / norm

    assert gap(with_partial) < 1e-6, gap(with_partial)
    assert gap(without) > 1e-4, gap(without)  # the test would see them missing


def test_a_reduced_solve_resumes_from_any_load_step_exactly(solved):
    """``on_step`` hands out the solve's whole state after every load factor; ``resume=`` that state
    continues as if never stopped: every output bit-identical (the forward ensemble's per-load-step
    checkpoints of a reduced batch rely on it)."""
    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, es.a[snap], {k: v[snap] for k, v in params.items()}, LOADS)
    rest = np.setdiff1d(np.arange(len(es.method)), snap)[:3]
    sub = {k: v[rest] for k, v in params.items()}
    scale = float(ref.u.abs().max())
    opts = dict(xtol=1e-5 * scale, polish_tol=1e-7 * scale)
    states = []
    whole = solve_reduced(hyper, sub, LOADS, on_step=lambda s: states.append({k: np.copy(v) for k, v in s.items()}),
                          **opts)
    assert [int(s["step"]) for s in states] == list(range(len(LOADS)))
    for s in states[:-1]:
        again = solve_reduced(hyper, sub, LOADS, resume=s, **opts)
        assert torch.equal(again.u, whole.u) and torch.equal(again.a, whole.a)
        np.testing.assert_array_equal(again.error_estimate, whole.error_estimate)
        np.testing.assert_array_equal(again.iterations, whole.iterations)
        np.testing.assert_array_equal(again.polish, whole.polish)


def test_refresh_zero_is_newton_on_the_galerkin_system(solved):
    """refresh = 0 (the reference the conditioning study solves with): every polish iteration takes
    a fresh Galerkin tangent, without a warning, and the answer is the Galerkin system's root."""
    import warnings

    model, params, ref, es = solved
    snap = es.snapshots
    hyper = build_reduced(model, ref.a[snap], {k: v[snap] for k, v in params.items()}, LOADS)
    sub = {k: v[:2] for k, v in params.items()}
    scale = float(ref.u.abs().max())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rs = solve_reduced(hyper, sub, LOADS, refresh=0.0, polish_tol=1e-10 * scale, check=False)
    assert (rs.status == "converged").all()
    assert (rs.full_tangents == rs.polish).all() and (rs.polish >= len(LOADS)).all()
    V = hyper.basis.V
    for t, lam in enumerate(LOADS):
        R, _, _ = hyper.galerkin().evaluate(rs.a[:, t] @ V, sub, torch.full((2,), lam, dtype=torch.float64),
                                            tangent=False)
        force = model.evaluate(rs.a[:, t], sub, torch.full((2,), lam, dtype=torch.float64), tangent=False)
        # Newton converged quadratically below 1e-10 of the displacements: the Galerkin residual is at
        # round-off of the forces it balances
        assert float(R.abs().max()) < 1e-8 * float(force.force_scale.max())
