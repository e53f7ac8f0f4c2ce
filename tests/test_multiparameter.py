"""Any parameter set: priors as data, the exact posterior of two and three parameters on a tensor
grid (against the linear-Gaussian closed form and a brute-force grid of the true map), and the
hierarchical filters in two parameters against that exact posterior."""
import math

import numpy as np
import pytest
import torch

from torchfra.assimilation import hierarchical_filter
from torchfra.assimilation.exact_nd import TensorMap, tensor_posterior
from torchfra.calibration.priors import ParameterSet, PriorError, lognormal_parameters, parse_prior


def test_priors_map_their_coordinates_and_sample_the_stated_moments():
    """Lognormal, normal and uniform priors given for the parameter itself: 4e5 draws reproduce the
    stated mean and std (lognormal, normal) or bounds and mean (uniform) to Monte Carlo error, and
    coordinate() inverts natural() (to 1e-12; the probit to 1e-6: a value within 1e-7 of a bound
    keeps fewer digits of its coordinate)."""
    ps = ParameterSet.parse(["C10=lognormal:0.0062,0.0011", "C01=normal:0.001,0.0005", "density=uniform:0,1e-8"],
                            ["E_fiber=31000"])
    Q = ps.sample(400_000, torch.Generator().manual_seed(0))
    x = ps.natural(Q)
    n = math.sqrt(4e5)
    assert abs(float(x["C10"].mean()) - 0.0062) < 4 * 0.0011 / n
    assert float(x["C10"].std()) == pytest.approx(0.0011, rel=0.01)
    assert abs(float(x["C01"].mean()) - 0.001) < 4 * 0.0005 / n
    assert float(x["C01"].std()) == pytest.approx(0.0005, rel=0.01)
    assert 0 <= float(x["density"].min()) and float(x["density"].max()) <= 1e-8
    assert abs(float(x["density"].mean()) - 5e-9) < 4 * 1e-8 / math.sqrt(12) / n
    back = ps.coordinates(x)
    assert torch.allclose(back[:, :2], Q[:, :2], atol=1e-12, rtol=0)
    assert torch.allclose(back[:, 2], Q[:, 2], atol=1e-6, rtol=0)
    p = ps.model_parameters(Q[:3], pressure=0.022)
    assert set(p) == {"C10", "D1", "E_fiber", "P", "C01", "density"}
    assert torch.allclose(p["D1"], 1 / (1000 * p["C10"])) and torch.all(p["E_fiber"] == 31000)
    assert ps.candidates() == ("gravity", "mooney_rivlin")
    # the paper's prior: the same draws as the one-parameter code always made
    mu, s = lognormal_parameters(0.0062, 0.0011)
    one = ParameterSet.parse(["C10=lognormal:0.0062,0.0011"]).sample(5, torch.Generator().manual_seed(3))
    ref = mu + s * torch.randn(5, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.equal(one[:, 0], ref)


@pytest.mark.parametrize("spec, words", [
    ("C11=lognormal:1,0.1", "unknown parameter 'C11'"),
    ("C10=gamma:1,0.1", "unknown prior kind 'gamma'"),
    ("C10=lognormal:0.0062", "takes two numbers"),
    ("C10=lognormal:-0.0062,0.001", "mean > 0"),
    ("C10=normal:0.0062,0.003", "C10 must lie in"),
    ("C01=uniform:0.002,0.001", "lower < upper"),
    ("density=normal:0,1e-9", "density must lie in"),
    ("C01=uniform:0,nan", "not a finite number"),
    ("pressure_gain=normal:1,0.1", "diagnose.py"),
    ("C10 lognormal 0.006 0.001", "write NAME=KIND:A,B"),
])
def test_bad_priors_are_refused_by_name(spec, words):
    with pytest.raises(PriorError, match=words):
        parse_prior(spec)


def test_bad_parameter_sets_are_refused_by_name(tmp_path):
    with pytest.raises(PriorError, match="more than once"):
        ParameterSet.parse(["C10=lognormal:0.0062,0.0011"], ["C10=0.005"])
    with pytest.raises(PriorError, match="C10 needs a prior"):
        ParameterSet.parse(["C01=uniform:0,0.001"])
    with pytest.raises(PriorError, match="c_n and c_t"):
        ParameterSet.parse(["C10=lognormal:0.0062,0.0011", "c_n=uniform:0.001,1"])
    with pytest.raises(PriorError, match="E_fiber must lie in"):
        ParameterSet.parse(["C10=lognormal:0.0062,0.0011"], ["E_fiber=-5"])
    f = tmp_path / "prior.toml"
    f.write_text('[parameters]\nC10 = "lognormal:0.0062,0.0011"\nE_fiber = "lognormal:31000,6000"\n[fixed]\nC01 = 0.0\n')
    ps = ParameterSet.from_file(f)
    assert ps.names == ["C10", "E_fiber"] and ps.fixed == (("C01", 0.0),)
    f.write_text('[parameters]\nC10 = "lognormal:0.0062"\n')
    with pytest.raises(PriorError, match=r"prior.toml: --param 'C10=lognormal:0.0062': a lognormal prior takes two"):
        ParameterSet.from_file(f)
    f.write_text('[priors]\nC10 = 1\n')
    with pytest.raises(PriorError, match=r"unknown tables \['priors'\]"):
        ParameterSet.from_file(f)


def _linear_gaussian_2d(N=60, K=6, m=8, seed=0, ridge=0.0):
    rng = np.random.default_rng(seed)
    mu0, s0 = np.array([0.3, -1.0]), np.array([0.2, 0.5])
    a = rng.normal(size=(K, m))
    B = rng.normal(size=(K, m, 2)) * np.array([4.0, 1.5])
    if ridge:  # the second column nearly a multiple of the first: only a combination is identified
        B[..., 1] = -2.0 * B[..., 0] + ridge * B[..., 1]
    r = 0.5 + rng.random((K, m))
    q_true = mu0 + s0 * np.array([0.7, -0.4])
    Z = a + B @ q_true + np.sqrt(r) * rng.normal(size=(K, m))
    Q0 = mu0 + s0 * rng.normal(size=(N, 2))
    Y = a[None] + np.einsum("kmd,nd->nkm", B, Q0)
    return mu0, s0, a, B, r, Z, Q0, Y


@pytest.mark.parametrize("ridge", [0.0, 0.002])
def test_tensor_posterior_equals_the_linear_gaussian_closed_form(ridge):
    """Affine map, normal prior: the grid posterior's mean, std, correlation and log evidence equal
    the Kalman closed form (posterior precision diag(1/s0^2) + sum_k B_k^T R_k^-1 B_k) to 1e-4 of a
    std, 1e-4 relative and 1e-4 nats (the fine grid's quadrature error), also for a ridge (two
    parameters of which the data fix one combination: correlation 0.983 here)."""
    mu0, s0, a, B, r, Z, Q0, Y = _linear_gaussian_2d(ridge=ridge)
    tmap = TensorMap(Q0, Y)
    assert tmap.loo_error < 1e-10
    post = tensor_posterior(tmap, Z, r, mu0, s0, names=["x", "y"], naturals=[lambda q: q] * 2)
    P = np.diag(1 / s0**2) + sum(B[k].T @ np.diag(1 / r[k]) @ B[k] for k in range(len(Z)))
    rhs = mu0 / s0**2 + sum(B[k].T @ ((Z[k] - a[k]) / r[k]) for k in range(len(Z)))
    cov = np.linalg.inv(P)
    mean = cov @ rhs
    st = post.stats()
    for j, n in enumerate(("x", "y")):
        sd = math.sqrt(cov[j, j])
        assert abs(st[n]["mean"] - mean[j]) < 1e-4 * sd
        assert st[n]["std"] == pytest.approx(sd, rel=1e-4)
    assert st["correlation"][0][1] == pytest.approx(cov[0, 1] / math.sqrt(cov[0, 0] * cov[1, 1]), abs=1e-4)
    zf, Bf = Z.reshape(-1), B.reshape(-1, 2)
    C = Bf @ np.diag(s0**2) @ Bf.T + np.diag(r.reshape(-1))
    e = zf - a.reshape(-1) - Bf @ mu0
    ref = -0.5 * (e @ np.linalg.solve(C, e) + np.linalg.slogdet(2 * math.pi * C)[1])
    assert abs(post.log_evidence - ref) < 1e-4
    # along a ridge the prior alone bounds the posterior: some of it reaches the members' outer cells
    assert post.edge_mass < (1e-2 if ridge else 1e-6)
    if ridge:
        assert abs(st["correlation"][0][1]) > 0.98


def _curved(Q):
    """A curved map of two log-parameters: displacement ~ 1/C10 and a second, weaker stiffness."""
    Q = np.atleast_2d(Q)
    t = np.linspace(0.1, 1.0, 5)[None, :, None]
    w = np.linspace(-1, 1, 6)[None, None, :]
    return 10 * np.exp(-Q[:, 0])[:, None, None] * t * (1 + 0.3 * w) + 3 * np.exp(-0.5 * Q[:, 1])[:, None, None] * t * w**2


def test_two_parameter_posterior_and_filters_on_a_curved_map():
    """Curved map, 100 prior members: the tensor map's leave-one-out RMS error is far below the noise;
    its grid posterior equals a brute-force grid of the true map (means to 0.02 posterior stds, stds to
    2 %); the hierarchical filter with the polynomial slave lands within 0.3 exact stds of the exact
    mean in both parameters with a std ratio in [0.7, 1.3] (ensemble of 100 after 5 frames)."""
    rng = np.random.default_rng(1)
    mu0, s0 = np.array([0.0, 0.0]), np.array([0.2, 0.4])
    Q0 = mu0 + s0 * rng.normal(size=(100, 2))
    Y = _curved(Q0)
    truth = np.array([-0.15, 0.3])
    noise = 0.05
    Z = (_curved(truth)[0] + noise * rng.normal(size=(5, 6))).reshape(5, -1)
    r = np.full(Z.shape[1], noise**2)
    tmap = TensorMap(Q0, Y.reshape(100, 5, -1))
    assert tmap.loo_error_rms < 0.05 * noise
    post = tensor_posterior(tmap, Z, r, mu0, s0, names=["a", "b"])
    # brute force: the true map on a fine grid around the mass
    st = post.stats()
    axes = [np.log(np.linspace(st[n]["mean"] - 8 * st[n]["std"], st[n]["mean"] + 8 * st[n]["std"], 401))
            for n in ("a", "b")]
    G = np.stack([g.reshape(-1) for g in np.meshgrid(*axes, indexing="ij")], 1)
    ll = -0.5 * (((Z[None] - _curved(G).reshape(len(G), 5, -1)) ** 2) / r).sum((1, 2))
    lp = -0.5 * (((G - mu0) / s0) ** 2).sum(1)
    w = np.exp(ll + lp - (ll + lp).max()) / np.exp(G.sum(1))  # density in the natural values' grid
    w /= w.sum()
    X = np.exp(G)
    for j, n in enumerate(("a", "b")):
        m = float(w @ X[:, j])
        sd = math.sqrt(float(w @ (X[:, j] - m) ** 2))
        assert abs(st[n]["mean"] - m) < 0.02 * sd and st[n]["std"] == pytest.approx(sd, rel=0.02)
    res, slave = hierarchical_filter(torch.as_tensor(Q0), torch.as_tensor(Y.reshape(100, 5, -1)), torch.as_tensor(Z),
                                     torch.as_tensor(r), torch.Generator().manual_seed(0), slave="polynomial",
                                     degree="auto")
    X = torch.exp(res.Q[-1]).numpy()
    for j, n in enumerate(("a", "b")):
        assert abs(X[:, j].mean() - st[n]["mean"]) < 0.3 * st[n]["std"]
        assert 0.7 < X[:, j].std(ddof=1) / st[n]["std"] < 1.3


def test_three_parameters_on_the_tensor_grid():
    """d = 3, affine map: means within 1e-3 posterior stds and stds within 1e-3 of the closed form."""
    rng = np.random.default_rng(2)
    K, m = 4, 9
    mu0, s0 = np.zeros(3), np.array([0.3, 0.5, 0.8])
    a, B = rng.normal(size=(K, m)), rng.normal(size=(K, m, 3)) * 2
    r = np.ones((K, m))
    Z = a + B @ np.array([0.1, -0.2, 0.3]) + rng.normal(size=(K, m))
    Q0 = mu0 + s0 * rng.normal(size=(80, 3))
    tmap = TensorMap(Q0, a[None] + np.einsum("kmd,nd->nkm", B, Q0), degree=1)
    post = tensor_posterior(tmap, Z, r, mu0, s0, names=list("xyz"), naturals=[lambda q: q] * 3)
    P = np.diag(1 / s0**2) + sum(B[k].T @ B[k] for k in range(K))
    cov = np.linalg.inv(P)
    mean = cov @ (mu0 / s0**2 + sum(B[k].T @ (Z[k] - a[k]) for k in range(K)))
    st = post.stats()
    for j, n in enumerate("xyz"):
        assert abs(st[n]["mean"] - mean[j]) < 1e-3 * math.sqrt(cov[j, j])
        assert st[n]["std"] == pytest.approx(math.sqrt(cov[j, j]), rel=1e-3)


def test_five_parameters_by_importance_sampling():
    """d = 5, affine map, normal prior: the importance-sampling reference (t proposal at the Laplace
    point) against the closed form: means within 0.05 posterior stds, stds within 3 %, log evidence
    within 0.05 (Monte Carlo error ~ 1/sqrt(ESS); ESS above 10,000 of 40,000 draws here)."""
    from torchfra.assimilation.exact_nd import sampled_posterior

    rng = np.random.default_rng(3)
    d, K, m = 5, 4, 12
    mu0, s0 = np.zeros(d), np.linspace(0.3, 0.9, d)
    a, B = rng.normal(size=(K, m)), rng.normal(size=(K, m, d)) * 2
    r = np.ones((K, m))
    Z = a + B @ (0.3 * s0) + rng.normal(size=(K, m))
    Q0 = mu0 + s0 * rng.normal(size=(100, d))
    tmap = TensorMap(Q0, a[None] + np.einsum("kmd,nd->nkm", B, Q0))
    assert tmap.basis == "total" and tmap.loo_error < 1e-9
    post = sampled_posterior(tmap, Z, r, mu0, s0, names=list("abcde"), naturals=[lambda q: q] * d)
    P = np.diag(1 / s0**2) + sum(B[k].T @ B[k] for k in range(K))
    cov = np.linalg.inv(P)
    mean = cov @ (mu0 / s0**2 + sum(B[k].T @ (Z[k] - a[k]) for k in range(K)))
    st = post.stats()
    assert post.ess > 10_000
    for j, n in enumerate("abcde"):
        assert abs(st[n]["mean"] - mean[j]) < 0.05 * math.sqrt(cov[j, j])
        assert st[n]["std"] == pytest.approx(math.sqrt(cov[j, j]), rel=0.03)
    zf, Bf = Z.reshape(-1), B.reshape(-1, d)
    C = Bf @ np.diag(s0**2) @ Bf.T + np.eye(K * m)
    e = zf - a.reshape(-1) - Bf @ mu0
    ref = -0.5 * (e @ np.linalg.solve(C, e) + np.linalg.slogdet(2 * math.pi * C)[1])
    assert abs(post.log_evidence - ref) < 0.05
