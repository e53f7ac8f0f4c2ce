"""The model-free hysteresis test of the diagnosis (``diagnosis.locate.hysteresis``).

Reference: under path independence (every hyperelastic, quasi-static model) the loading/unloading
differences are noise only, so each statistic rejects at its nominal level; measured here over
seeds against the binomial 99.9 % band, for i.i.d. and spatially correlated noise. A pressure
sensor's time lag (the response follows the pressure a moment late) must be found; a ramp has
nothing to compare and says so.
"""
import numpy as np
import pytest
from scipy import stats

from torchfra.diagnosis.locate import hysteresis
from torchfra.diagnosis.noise import NoiseModel, Whitener
from torchfra.observation.recording import Recording

K, PMAX = 20, 0.022


def cycle_recording(rng, sigma=0.5, ell=0.0, lag=0.0, n=6, spacing=2.0):
    """A load-unload cycle whose response is a nonlinear function of the pressure the body feels:
    the recorded pressure delayed by ``lag`` (normalized time); noise i.i.d. or correlated."""
    y, z = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    X = np.column_stack([np.zeros(n * n), y.ravel(), z.ravel()])
    t = np.arange(1, K + 1) / K
    shape = lambda tt: np.clip(1.0 - np.abs(2.0 * tt - 1.0), 0.0, 1.0)  # noqa: E731
    p_rec = PMAX * shape(t)
    felt = shape(np.maximum(t - lag, 0.0))
    a = np.stack([1 + X[:, 2] / 5, 0.3 * np.sin(X[:, 1])], axis=1)  # (P, 2) a smooth spatial pattern
    clean = 8.0 * np.expm1(2.0 * felt)[:, None, None] * a[None]  # strongly nonlinear in the pressure
    if ell > 0:
        Lc = NoiseModel(sigma, ell).factor(X)
        noise = sigma * np.einsum("ij,kjc->kic", Lc, rng.standard_normal(clean.shape))
    else:
        noise = sigma * rng.standard_normal(clean.shape)
    direction = (16.0 * np.exp(2.0 * shape(t)))[:, None, None] * a[None]  # d clean / d(p / PMAX)
    rec = Recording(np.arange(K), t, p_rec, np.arange(len(X)), X, clean + noise, "test")
    return rec, direction


@pytest.mark.parametrize("ell", [0.0, 3.0])
def test_false_alarm_rate_matches_the_level(ell):
    rng = np.random.default_rng(4)
    alpha, trials = 0.1, 300
    hits = {"omnibus": 0, "directional": 0}
    for _ in range(trials):
        rec, direction = cycle_recording(rng, ell=ell)
        h = hysteresis(rec, Whitener(rec, NoiseModel(0.5, ell)), alpha, direction)
        for k in hits:
            hits[k] += h[k]["p_value"] < alpha / 2
    lo, hi = stats.binom.ppf([0.0005, 0.9995], trials, alpha / 2)
    for k, v in hits.items():
        assert lo <= v <= hi, (k, v, lo, hi)


def test_smooth_nonlinear_response_is_not_a_loop():
    """The spline interpolation of the loading branch is exact enough: a strongly nonlinear response
    with noise 0.005 mm (amplitude ~50 mm) is not flagged."""
    rec, direction = cycle_recording(np.random.default_rng(5), sigma=0.005)
    h = hysteresis(rec, Whitener(rec, NoiseModel(0.005)), 0.01, direction)
    assert h["applicable"] and not h["detected"], h["omnibus"]


def test_a_sensor_lag_is_found_and_located():
    rec, direction = cycle_recording(np.random.default_rng(6), lag=0.01)
    h = hysteresis(rec, Whitener(rec, NoiseModel(0.5)), 0.01, direction)
    assert h["detected"] and h["physics"]["kind"] == "history-dependent"
    assert h["directional"]["p_value"] < 1e-6
    assert h["frames_unloading"] == list(range(10, 19))  # the last frame (p = 0) lies below the loading branch
    # the lag shows where the response is largest: the far end of the grid (a grows with z)
    assert h["worst_points"][0]["X"][2] >= 8.0
    assert h["largest_loop_mm"] > 1.0


def test_a_ramp_has_nothing_to_compare():
    rec, _ = cycle_recording(np.random.default_rng(7))
    ramp = Recording(rec.frames[:10], rec.times[:10], rec.pressure[:10], rec.point_ids, rec.X, rec.Z[:10], "ramp")
    h = hysteresis(ramp, Whitener(ramp, NoiseModel(0.5)), 0.01)
    assert not h["applicable"] and not h["detected"] and "unloading" in h["reason"]
