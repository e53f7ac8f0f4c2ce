"""The analysis step, the hierarchical and restart filters and the exact posterior on problems with
known answers: a reference library (ES-MDA), the dense Kalman formula, and the linear-Gaussian
closed form."""
import copy
import math

import numpy as np
import pytest
import torch

from torchfra.assimilation import (
    LinearSlave,
    PolynomialSlave,
    SweepMap,
    analysis,
    grid_posterior,
    hierarchical_filter,
    sequential_filter,
)


def _problem(N=50, d=2, m=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    Q = torch.randn(N, d, generator=g)
    A = torch.randn(d, m, generator=g)
    Y = Q @ A + 0.1 * torch.sin(Q[:, :1] * 3) + 0.05 * torch.randn(N, m, generator=g)
    z = torch.randn(m, generator=g)
    r = 0.5 + torch.rand(m, generator=g)
    E = torch.randn(N, m, generator=g) * r.sqrt()
    return Q, Y, z, r, E


def test_analysis_equals_esmda_reference():
    """One update equals iterative-ensemble-smoother 1.2.0 ESMDA(alpha=1), truncation=1.0, with
    observation_perturbations=-E (its D_obs = z + perturbations; ours z - (Y + E)): to 1e-12."""
    import iterative_ensemble_smoother as ies  # the test extra pins 1.2.0

    assert ies.__version__ == "1.2.0"
    Q, Y, z, r, E = _problem()
    Qa, _ = analysis(Q, Y, z, r, E)
    esmda = ies.ESMDA(r.numpy(), z.numpy(), alpha=1, seed=0)
    esmda.prepare_assimilation(Y=Y.numpy().T, truncation=1.0, observation_perturbations=-E.numpy().T)
    ref = esmda.assimilate_batch(X=Q.numpy().T).T
    assert np.abs(Qa.numpy() - ref).max() < 1e-12 * max(1.0, np.abs(ref).max())


def test_analysis_equals_dense_gain_and_masks_missing():
    """Woodbury form = the textbook K = C_qy (C_yy + R)^-1 with the m x m matrix formed; NaN entries
    of z are dropped, which equals an update on the observed entries only."""
    Q, Y, z, r, E = _problem()
    N = Q.shape[0]
    dQ, dY = Q - Q.mean(0), Y - Y.mean(0)
    K = (dQ.T @ dY / (N - 1)) @ torch.linalg.inv(dY.T @ dY / (N - 1) + torch.diag(r))
    dense = Q + (z - (Y + E)) @ K.T
    Qa, info = analysis(Q, Y, z, r, E)
    assert torch.allclose(Qa, dense, atol=1e-12, rtol=0)
    # log likelihood = log N(z - mean Y; 0, C_yy + R) with the dense covariance
    S = dY.T @ dY / (N - 1) + torch.diag(r)
    nu = z - Y.mean(0)
    ref = torch.distributions.MultivariateNormal(torch.zeros_like(nu), covariance_matrix=S).log_prob(nu)
    assert abs(info.log_likelihood - float(ref)) < 1e-9
    z2 = z.clone()
    z2[[3, 7, 11]] = float("nan")
    keep = torch.isfinite(z2)
    Qm, info_m = analysis(Q, Y, z2, r, E)
    Qk, _ = analysis(Q, Y[:, keep], z[keep], r[keep], E[:, keep])
    assert info_m.m == int(keep.sum()) and torch.equal(Qm, Qk)


def test_analysis_rejects_diverged_member():
    Q, Y, z, r, E = _problem()
    Y[7, 2] = float("nan")
    with pytest.raises(ValueError, match="member 7"):
        analysis(Q, Y, z, r, E)


def _linear_gaussian(N, seed=1, K=8, m=5):
    """q ~ N(mu0, s0^2) (1-D), y_k = a_k + b_k q, z_k = y_k(q_true) + noise."""
    g = torch.Generator().manual_seed(seed)
    mu0, s0 = 0.3, 0.4
    a = torch.randn(K, m, generator=g)
    b = torch.randn(K, m, generator=g)
    r = torch.full((m,), 0.5 ** 2)
    q_true = 0.1
    Z = a + b * q_true + torch.randn(K, m, generator=g) * r.sqrt()
    Q0 = mu0 + s0 * torch.randn(N, 1, generator=g)
    return mu0, s0, a, b, r, Z, Q0


def _kalman(mu0, s0, a, b, r, Z):
    """Closed-form posterior of q from all frames (precision-weighted)."""
    prec = 1 / s0 ** 2 + float((b ** 2 / r).sum())
    mean = (mu0 / s0 ** 2 + float((b * (Z - a) / r).sum())) / prec
    return mean, 1 / math.sqrt(prec)


def test_linear_gaussian_hierarchical_equals_restart_equals_kalman():
    """For an affine map the slave's forecast is exact, so the hierarchical filter (Eqs. 21-23) and
    the restart filter (forecast by evaluating the map) give the same ensembles to round-off; both
    match the Kalman posterior to Monte Carlo error. With N = 2000 the sample mean's error is
    ~ std / sqrt(N) = 2.2 % of the std; we allow 10 %, and 10 % on the std itself."""
    N = 2000
    mu0, s0, a, b, r, Z, Q0 = _linear_gaussian(N)
    Y_fe = (a + b * Q0[:, :, None]).reshape(N, *a.shape)  # (N, K, m)
    hier, _ = hierarchical_filter(Q0, Y_fe, Z, r, torch.Generator().manual_seed(5), slave="linear")
    restart = sequential_filter(Q0, lambda Q, k: a[k] + b[k] * Q, Z, r, torch.Generator().manual_seed(5))
    assert torch.allclose(hier.Q[-1], restart.Q[-1], atol=1e-10, rtol=0)
    mean, std = _kalman(mu0, s0, a, b, r, Z)
    q = hier.Q[-1][:, 0]
    assert abs(float(q.mean()) - mean) < 0.1 * std
    assert abs(float(q.std()) / std - 1) < 0.1
    # Log evidence of the filter ~ exact evidence log N(z; a + b mu0, b b^T s0^2 + R)
    zf = Z.reshape(-1)
    cov = torch.outer(b.reshape(-1), b.reshape(-1)) * s0 ** 2 + torch.diag(r.repeat(Z.shape[0]))
    ref = float(torch.distributions.MultivariateNormal(a.reshape(-1) + b.reshape(-1) * mu0, cov).log_prob(zf))
    assert abs(hier.log_evidence - ref) < 0.5  # Monte Carlo error of sample covariances, N = 2000


def test_grid_posterior_equals_kalman_closed_form():
    """The exact posterior by quadrature: mean and std to 1e-6 relative, log evidence to 1e-6,
    when the map is affine (the cubic spline through a sweep reproduces it exactly)."""
    mu0, s0, a, b, r, Z, _ = _linear_gaussian(10)
    q_sweep = np.linspace(mu0 - 8 * s0, mu0 + 8 * s0, 30)
    Y = a.numpy()[None] + b.numpy()[None] * q_sweep[:, None, None]
    sweep = SweepMap(q_sweep, Y)
    assert sweep.leave_one_out_error() < 1e-12
    post = grid_posterior(sweep, Z.numpy(), r.numpy(), mu0, s0, n_grid=20001)
    mean, std = _kalman(mu0, s0, a, b, r, Z)
    # stats() reports exp(q); check the q-moments directly from the grid density
    w = np.exp(post.log_post[-1]) * np.gradient(post.q)
    m_q = float(w @ post.q / w.sum())
    s_q = math.sqrt(float(w @ (post.q - m_q) ** 2 / w.sum()))
    assert abs(m_q - mean) < 1e-6 * std + 1e-9 and abs(s_q / std - 1) < 1e-6
    zf = Z.reshape(-1)
    cov = torch.outer(b.reshape(-1), b.reshape(-1)) * s0 ** 2 + torch.diag(r.repeat(Z.shape[0]))
    ref = float(torch.distributions.MultivariateNormal(a.reshape(-1) + b.reshape(-1) * mu0, cov).log_prob(zf))
    assert abs(post.log_evidence[-1] - ref) < 1e-6


def test_sweep_forecaster_reads_one_frame_exactly_as_the_whole_spline():
    """The restart filter's spline forecast of frame k evaluates that frame's coefficients only (its
    cost per frame does not grow with the frames): equal to scipy's CubicSpline at every frame, inside
    the sweep and beyond both ends (extrapolation by the end cubics), to round-off."""
    rng = np.random.default_rng(3)
    q = np.sort(rng.uniform(-1, 1, 12))
    Y = np.exp(-q)[:, None, None, None] * rng.normal(size=(1, 7, 5, 2))
    sweep = SweepMap(q, Y)
    Q = torch.tensor([[-1.3], [-0.2], [0.0], [0.7], [1.4]], dtype=torch.float64)
    full = sweep(Q[:, 0].numpy())
    forecast = sweep.forecaster(np.arange(7)[::-1])
    for k in range(7):
        assert sweep.frame(Q[:, 0].numpy(), k).shape == (5, 5, 2)
        np.testing.assert_allclose(forecast(Q, 6 - k).numpy(), full[:, k], rtol=1e-13, atol=1e-13)


def test_polynomial_slave_follows_a_curved_map_where_the_linear_slave_drifts():
    """y = 10 exp(-q) (displacement ~ 1/C10): fitted on a prior of std 0.18 in q, asked at a narrow
    ensemble 1.2 prior stds below the prior mean (the paper's truth sits there). The cubic slave's
    forecast error must be < 1 % of the linear slave's, which must be visibly biased (> 0.05)."""
    g = torch.Generator().manual_seed(0)
    N = 100
    Q0 = 0.1 + 0.18 * torch.randn(N, 1, generator=g)
    f = lambda Q: 10 * torch.exp(-Q)[:, :, None].expand(-1, 3, 4).reshape(Q.shape[0], 3, 4)  # noqa: E731
    Y_fe = f(Q0)
    Q = 0.1 - 0.22 + 0.005 * torch.randn(N, 1, generator=g)
    truth = f(Q)[:, 1]
    lin = LinearSlave(Q0, Y_fe)(Q, 1)
    poly = PolynomialSlave(Q0, Y_fe, degree=3)(Q, 1)
    e_lin = float((lin - truth).abs().max())
    e_poly = float((poly - truth).abs().max())
    assert e_lin > 0.05 and e_poly < 0.01 * e_lin
    # degree 1 is Eq. 23 with R_q = 0
    assert torch.allclose(PolynomialSlave(Q0, Y_fe, degree=1)(Q, 2), LinearSlave(Q0, Y_fe)(Q, 2), atol=1e-11)


def test_interrupted_filter_resumes_to_the_same_ensemble():
    """A run stopped after step 3 (checkpoint: result + generator state) and resumed gives exactly the
    ensembles of an uninterrupted run: no step repeated, no random draw reused or skipped."""
    mu0, s0, a, b, r, Z, Q0 = _linear_gaussian(40)
    forecast = lambda Q, k: a[k] + b[k] * Q ** 3  # noqa: E731  (any deterministic map)
    full = sequential_filter(Q0, forecast, Z, r, torch.Generator().manual_seed(3))
    saved = {}

    def checkpoint(res, g):
        saved.update(result=copy.deepcopy(res), state=g.get_state())
        if res.steps == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sequential_filter(Q0, forecast, Z, r, torch.Generator().manual_seed(3), checkpoint=checkpoint)
    g = torch.Generator()
    g.set_state(saved["state"])
    resumed = sequential_filter(Q0, forecast, Z, r, g, result=saved["result"])
    assert resumed.steps == Z.shape[0]
    assert all(torch.equal(x, y) for x, y in zip(resumed.Q, full.Q))
    assert resumed.log_evidence == pytest.approx(full.log_evidence, abs=1e-12)


def test_grid_posterior_masks_and_frame_subsets():
    """NaN entries are not observed: the posterior equals the one from data without those entries
    (built by giving them infinite noise). ``frames`` assimilates only those frames."""
    mu0, s0, a, b, r, Z, _ = _linear_gaussian(10)
    q = np.linspace(mu0 - 8 * s0, mu0 + 8 * s0, 30)
    sweep = SweepMap(q, a.numpy()[None] + b.numpy()[None] * q[:, None, None])
    Zn = Z.numpy().copy()
    Zn[2, 1] = Zn[5, 0] = np.nan
    masked = grid_posterior(sweep, Zn, r.numpy(), mu0, s0, n_grid=2001)
    rr = np.broadcast_to(r.numpy(), Zn.shape).copy()
    rr[2, 1] = rr[5, 0] = 1e30
    wide = grid_posterior(sweep, np.nan_to_num(Zn), rr, mu0, s0, n_grid=2001)
    assert np.allclose(masked.log_post[-1], wide.log_post[-1], atol=1e-9)
    sub = grid_posterior(sweep, Z.numpy(), r.numpy(), mu0, s0, n_grid=2001, frames=[1, 4])
    # same posterior and evidence as a sweep holding only those frames
    ref = SweepMap(q, sweep.Y[:, [1, 4]])
    only = grid_posterior(ref, Z.numpy()[[1, 4]], r.numpy(), mu0, s0, n_grid=2001)
    assert np.allclose(sub.log_post[-1], only.log_post[-1], atol=1e-9)
    assert sub.log_evidence[-1] == pytest.approx(only.log_evidence[-1], abs=1e-9)
    # quantiles: for this Gaussian posterior p10/p90 of q sit at mean -/+ 1.2816 std (on exp(q) here)
    st = sub.stats()
    w = np.exp(sub.log_post[-1])
    m = np.trapezoid(w * sub.q, sub.q)
    sd = np.sqrt(np.trapezoid(w * (sub.q - m) ** 2, sub.q))
    assert np.log(st["p10"]) == pytest.approx(m - 1.2815516 * sd, abs=2e-4 * sd)
    assert np.log(st["p90"]) == pytest.approx(m + 1.2815516 * sd, abs=2e-4 * sd)


def test_slave_degree_chosen_by_leave_one_out_error():
    """'auto' picks the degree with the smallest closed-form leave-one-out error (checked against
    explicit refits): 2 for a quadratic map under noise (higher degrees only fit the noise), and a
    higher degree than 3 for 10 exp(-q), whose Taylor series does not stop."""
    from torchfra.assimilation.filters import select_degree

    g = torch.Generator().manual_seed(4)
    N = 100
    Q0 = 0.18 * torch.randn(N, 1, generator=g)
    quad = (1 + Q0 + 0.5 * Q0 ** 2)[:, :, None] + 0.01 * torch.randn(N, 4, 50, generator=g)
    degree, loo = select_degree(Q0, quad)
    assert degree == 2 and loo[1] > 2 * loo[2]
    # closed form = refitting without each member (degree 2, first 5 members)
    errs = []
    for i in range(5):
        keep = torch.arange(N) != i
        s = PolynomialSlave(Q0[keep], quad[keep], 2)
        errs.append(quad[i].reshape(-1) - s.features(Q0[i:i + 1])[0] @ s.W.reshape(3, -1))
    s = PolynomialSlave(Q0, quad, 2)
    Phi = s.features(Q0)
    h = torch.diagonal(Phi @ torch.linalg.pinv(Phi))
    closed = (quad.reshape(N, -1) - s._g0.reshape(N, -1)) / (1 - h)[:, None]
    assert torch.allclose(torch.stack(errs), closed[:5], atol=1e-12)
    curved = 10 * torch.exp(-Q0)[:, :, None].expand(-1, 3, 4)
    assert PolynomialSlave(Q0, curved, "auto").degree > 3


def test_data_that_do_not_fit_the_model_or_prior_are_flagged():
    """The exact posterior's data-fit check on the actuator's map shape (y ~ A / C10 per observation,
    sweep over the prior's +- 3 std in log C10, noise 0.5): a recording made inside the range with
    the model's own noise passes; one made at a C10 three times stiffer than the range (or in metres:
    1000x smaller) piles the posterior on the range's end; one with shifts of +- 3 noise stds
    alternating across the points (no C10 makes them) leaves a residual far above the noise. Each is flagged with its reason, the good one
    with none (reference: the generating truth of each recording)."""
    from torchfra.assimilation import data_fit

    rng = np.random.default_rng(3)
    K, m, noise = 12, 40, 0.5
    A = rng.uniform(0.5, 2.0, (1, m)) * np.linspace(0.1, 1.0, K)[:, None] * 0.06  # mm at C10 = 0.006
    mu, sd = math.log(0.0062), 0.18
    q_sweep = np.linspace(mu - 3 * sd, mu + 3 * sd, 60)
    sweep = SweepMap(q_sweep, A[None] / np.exp(q_sweep)[:, None, None])

    def check(c10, shift=0.0, scale=1.0):
        Z = scale * (A / c10 + shift + noise * rng.standard_normal((K, m)))
        post = grid_posterior(sweep, Z, noise**2, mu, sd, n_grid=4000)
        return data_fit(post, sweep, Z, noise**2)

    good = check(0.0058)
    assert good["ok"] and good["reasons"] == [] and good["residual_rms_in_noise_units"] < 1.2, good
    stiff = check(0.02)
    assert not stiff["ok"] and stiff["edge_mass"] > 0.5 and "upper end" in stiff["reasons"][0], stiff
    metres = check(0.006, scale=1e-3)
    assert not metres["ok"] and "metres instead of mm?" in metres["reasons"][0], metres
    shifted = check(0.006, shift=3 * noise * (-1.0) ** np.arange(m))
    assert not shifted["ok"] and shifted["residual_rms_in_noise_units"] > 2.5, shifted
    assert any("no parameter of the model" in r for r in shifted["reasons"]), shifted


def test_innovation_flags_name_the_frames_the_model_stops_following():
    """Affine model, 60 frames of 200 entries, restart-style forecasts from the true map: with data
    made by the model no frame is flagged at alpha = 1e-4 (expected 0.006 false flags); a drift of
    2 noise stds added to half the entries from frame 40 on (a physics the model lacks switching on)
    is flagged from frame 40 on, and only there."""
    from torchfra.assimilation import innovation_flags

    g = torch.Generator().manual_seed(4)
    K, m, N = 60, 200, 100
    a, b = torch.randn(K, m, generator=g), torch.randn(K, m, generator=g)
    r = torch.full((m,), 0.25)
    Q0 = 0.3 + 0.4 * torch.randn(N, 1, generator=g)
    Z = a + b * 0.1 + torch.randn(K, m, generator=g) * r.sqrt()
    forecast = lambda Q, k: a[k] + b[k] * Q  # noqa: E731
    clean = sequential_filter(Q0, forecast, Z, r, torch.Generator().manual_seed(5))
    assert innovation_flags(clean, range(K))["frames"] == []
    drift = Z.clone()
    drift[40:, : m // 2] += 2 * r.sqrt()[: m // 2]
    res = sequential_filter(Q0, forecast, drift, r, torch.Generator().manual_seed(5))
    flags = innovation_flags(res, range(K))
    assert flags["first"] == 40 and set(flags["frames"]) == set(range(40, K))
