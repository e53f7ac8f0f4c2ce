"""The viscoelastic candidate (``torchfra.actuator.history``): creep of the whole body on the frame-to-load map.

References: the creep convolution mu(t) = int J(t - s) dlambda(s), J(t) = 1 - g1 exp(-t / tau_c),
tau_c = tau1 / (1 - g1), in closed form for a step, a ramp and a triangular load-unload cycle
(integrals of exponentials); the correspondence principle's inverse pair (relaxation G(t) and
creep J(t) convolve to the unit step); central differences for the derivatives; a recording made by
the FE model at closed-form creeping loads for the diagnosis."""
import math

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from torchfra.actuator.candidates import CANDIDATE_PARAMETERS, HISTORY_DEPENDENT_CANDIDATES, LOAD_MAP_ONLY
from torchfra.actuator.history import creep_load, normalized_time
from torchfra.diagnosis.model import ActuatorPhysics
from torchfra.observation.recording import Recording

D = torch.float64


def _mu(lam, t, g1, tau1):
    return creep_load(torch.as_tensor(lam, dtype=D), t, torch.tensor(g1, dtype=D), torch.tensor(tau1, dtype=D)).numpy()


def triangle_creep(t, g1, tau1):
    """Closed form of mu for lambda = 2t up to t = 1/2, 2 - 2t after (the body at rest at t = 0)."""
    tc = tau1 / (1 - g1)
    t = np.asarray(t, dtype=np.float64)
    up = 2 * (t - g1 * tc * (1 - np.exp(-t / tc)))
    s = np.maximum(t - 0.5, 0.0)
    # int_0^1/2 J(t - s) ds - int_1/2^t J(t - s) ds, each times 2
    down = 2 * (0.5 - g1 * tc * (np.exp(-s / tc) - np.exp(-t / tc))) - 2 * (s - g1 * tc * (1 - np.exp(-s / tc)))
    return np.where(t <= 0.5, up, down)


def test_creep_of_a_step_a_ramp_and_a_cycle_matches_the_closed_forms():
    g1, tau1 = 0.35, 0.08
    tc = tau1 / (1 - g1)
    # a step held: lambda jumps to 1 between the first two frames (dt = 1e-9) and is held; the body
    # creeps from 1 - g1 to 1 with the retardation time tau_c (not tau1)
    t = np.concatenate([[0.0, 1e-9], np.linspace(0.01, 1.0, 100)])
    lam = np.concatenate([[0.0], np.ones(101)])
    ref = 1 - g1 * np.exp(-t[1:] / tc)
    assert np.abs(_mu(lam, t, g1, tau1)[1:] - ref).max() < 1e-8
    # a ramp: exact on piecewise-linear loads whatever the frame spacing
    t = np.sort(np.random.default_rng(1).uniform(0, 1, 30))
    t = np.concatenate([[0.0], t, [1.0]])
    assert np.abs(_mu(t, t, g1, tau1) - (t - g1 * tc * (1 - np.exp(-t / tc)))).max() < 1e-14
    # a cycle: loading lags below lambda, and at equal load unloading passes above loading (a
    # clockwise loop: the body always lags its load)
    t = np.linspace(0, 1, 41)
    lam = np.clip(1 - np.abs(2 * t - 1), 0, 1)
    mu = _mu(lam, t, g1, tau1)
    assert np.abs(mu - triangle_creep(t, g1, tau1)).max() < 1e-14
    assert np.all(mu[1:21] < lam[1:21]) and np.all(mu[21:][::-1] > mu[:20])  # t and 1 - t: equal loads


def test_null_and_limits():
    t = np.linspace(0, 1, 21)
    lam = np.clip(1 - np.abs(2 * t - 1), 0, 1)
    assert np.array_equal(_mu(lam, t, 0.0, 0.1), lam)  # g1 = 0: the elastic body, bitwise
    # a very slow relaxation: the instantaneous body, stiffer by 1 / (1 - g1) (load 1 - g1 times as large)
    assert np.abs(_mu(lam, t, 0.3, 1e4) - 0.7 * lam).max() < 1e-4
    # a very fast one: the relaxed body
    assert np.abs(_mu(lam, t, 0.3, 1e-5) - lam).max() < 1e-4
    assert np.array_equal(normalized_time([2.0, 3.0, 6.0]), [0.0, 0.25, 1.0])
    for g1, tau1 in ((float("nan"), 0.1), (1.0, 0.1), (-0.1, 0.1), (0.3, 0.0)):
        with pytest.raises(ValueError, match="g1"):
            creep_load(torch.zeros(3, dtype=D), t[:3], torch.tensor(g1), torch.tensor(tau1))
    with pytest.raises(ValueError, match="strictly increasing"):
        creep_load(torch.zeros(3, dtype=D), np.array([0.0, 0.5, 0.5]), torch.tensor(0.1), torch.tensor(0.1))


def test_relaxation_and_creep_are_inverse():
    """G * dJ = 1 (the correspondence principle's pair): the stress of the body held at the creeping
    load mu of a unit step, relaxed with G(t)/G_inf = 1 + g1 / (1 - g1) exp(-t / tau1), is the step."""
    g1, tau1 = 0.4, 0.05
    t = np.linspace(0.0, 1.0, 4001)
    lam = np.ones_like(t)
    lam[0] = 0.0
    t[1] = 1e-12
    mu = _mu(lam, t, g1, tau1)
    # stress(t) = int G(t - s) dmu(s) by the exact integral of G on the piecewise-linear mu
    G_inf, G_1 = 1.0, g1 / (1 - g1)
    stress = np.zeros_like(t)
    m = np.zeros(())  # memory of the Maxwell branch
    for k in range(1, t.size):
        dt = t[k] - t[k - 1]
        rate = (mu[k] - mu[k - 1]) / dt
        m = math.exp(-dt / tau1) * m + G_1 * rate * tau1 * (-math.expm1(-dt / tau1))
        stress[k] = G_inf * mu[k] + m
    # mu creeps exponentially between the 4000 frames, the stress integral takes it as linear there:
    # O((dt / tau1)^2) = 2.5e-5 relative per step; the wrong retardation time (tau1 for tau_c) misses by ~0.1
    assert np.abs(stress[1:] - 1.0).max() < 1e-6


def test_derivatives_match_central_differences():
    t = np.linspace(0, 1, 31)
    lam = torch.tensor(np.clip(1 - np.abs(2 * t - 1), 0, 1), dtype=D)
    g1, tau1 = torch.tensor(0.3, dtype=D), torch.tensor(0.12, dtype=D)
    J = torch.autograd.functional.jacobian(lambda g, tt: creep_load(lam, t, g, tt), (g1, tau1))
    for k, (x, d) in enumerate(((g1, J[0]), (tau1, J[1]))):
        h = 1e-6
        args_p = [g1, tau1]
        args_m = [g1, tau1]
        args_p[k], args_m[k] = x + h, x - h
        fd = (creep_load(lam, t, *args_p) - creep_load(lam, t, *args_m)) / (2 * h)
        assert torch.allclose(d, fd, rtol=1e-7, atol=1e-10)


# -- the diagnosis' decisions on a cheap stand-in for the FE model -------------------------------------------

class _ScalingActuator(ActuatorPhysics):
    """ActuatorPhysics whose FE solve is replaced by a closed form with the actuator's structure: every
    point moves by a_p h(lambda C10_0 / C10), h(x) = x / (1 + 0.4 x) (the scaling law with a
    softening response). Everything else (frame loads, creep, lag, Hermite reading of the frames,
    sensitivities' assembly) is ActuatorPhysics' own."""

    A = None  # (P, 2) amplitudes, set by the test

    def __init__(self, rec, candidates=(), resolution=1, load_steps=10, cache_dir=None, newton=None, deck=None, weight="before_reference"):
        assert deck is None, "the stand-in is the paper's actuator"
        self.deck, self.deck_values, self.deck_digest = None, None, None
        self.rec, self.candidates = rec, tuple(sorted(candidates))
        self.resolution, self.load_steps, self.newton = resolution, int(load_steps), {}
        self.names = ["C10"] + [p for c in self.candidates for p in CANDIDATE_PARAMETERS[c]]
        self.fe_names = [n for n in self.names if n not in LOAD_MAP_ONLY]
        self.fe_candidates = tuple(c for c in self.candidates if c not in HISTORY_DEPENDENT_CANDIDATES)
        assert self.fe_names == ["C10"], "the stand-in knows C10 and load-map parameters only"
        self.steps = np.arange(1, self.load_steps + 1) / self.load_steps
        self.W = sp.identity(rec.n_points, format="csr")
        self.cache_dir, self._memo = None, {}

    def _solve_nodal(self, z, values_only=False):  # the same closed form on every mesh: no discretization error
        c = math.exp(z["C10"]) / 0.006
        lam = np.concatenate([[0.0], self.steps])
        x = lam / c
        h, dh = x / (1 + 0.4 * x), 1 / (1 + 0.4 * x) ** 2
        field = np.zeros((1, self.rec.n_points, 3))
        field[0, :, 1:] = self.A
        u = h[:, None, None] * field
        du_dlam = (dh / c)[:, None, None] * field
        du = (-x * dh)[:, None, None, None] * field[..., None]
        return u, du_dlam, du, True, 1, False


@pytest.fixture
def stand_in(monkeypatch):
    for step in ("pipeline", "rank", "refit", "decide"):  # every step of the diagnosis that builds a model
        monkeypatch.setattr(f"torchfra.diagnosis.{step}.ActuatorPhysics", _ScalingActuator)
    # the stand-in's creep is exact on its own terms: the FE history refit is the same model again
    monkeypatch.setattr("torchfra.diagnosis.refit.HistoryPhysics",
                        lambda rec, resolution, cache, deck: _ScalingActuator(rec, ("viscoelasticity",)))

    def recording(felt, recorded, seed, frames=21, sigma=0.3):
        t = np.arange(frames) / (frames - 1)
        y, z = np.meshgrid(np.arange(6) * 3.0, np.arange(8) * 5.0)
        X = np.column_stack([np.full(y.size, 8.0), y.ravel(), z.ravel()])
        _ScalingActuator.A = np.stack([0.5 + X[:, 2] / 4, 0.2 + X[:, 1] / 10], axis=1)  # up to ~9 mm
        rec = Recording(np.arange(frames), t, 0.02 * recorded(t), np.arange(len(X)), X, np.zeros((frames, len(X), 2)))
        phys = _ScalingActuator(rec, ())
        x = felt(t) / 1.0  # C10 = 0.006: x = lambda
        rec.Z = (x / (1 + 0.4 * x))[:, None, None] * _ScalingActuator.A[None]
        rec.Z = rec.Z + sigma * np.random.default_rng(seed).standard_normal(rec.Z.shape)
        assert phys.names == ["C10"]
        return rec

    return recording


def triangle(t):
    return np.clip(1 - np.abs(2 * np.asarray(t) - 1), 0, 1)


def test_stand_in_diagnosis_names_a_creeping_body(stand_in, tmp_path):
    """g1 = 0.3, tau1 = 0.1: viscoelasticity named, beating the lagging-pressure rival decisively, no
    loop left, g1 and tau1 within 3 std of the generating values."""
    from torchfra.diagnosis.pipeline import diagnose

    rec = stand_in(lambda t: triangle_creep(t, 0.3, 0.1), triangle, seed=1)
    out = diagnose(rec, noise=0.3, correlation=0.0, candidates=["viscoelasticity"], progress=False, load_steps=10,
                   run_dir=tmp_path)
    assert (tmp_path / "hysteresis.png").exists() and (tmp_path / "diagnosis.json").exists()
    assert out["hysteresis"]["detected"] and out["hysteresis"]["sense"] == "lags"
    visco = out["ranking"][0]
    assert visco["one_sided"] and visco["significant"] and visco["nuisance_parameters"] == ["tau1"]
    assert out["decision"] == "viscoelasticity", (out["decision"], out["tried"])
    assert out["missing_physics"] == {"kind": "candidate", "name": "viscoelasticity"}
    chosen = next(t for t in out["tried"] if t.get("chosen"))
    assert not chosen["loop_left_in_residual"]["detected"]
    assert chosen["rival"]["name"] == "pressure_lag" and chosen["rival"]["evidence_margin"] > 5
    ext = out["parameters"]["extended"]
    assert abs(ext["g1"]["mean"] - 0.3) < 3 * ext["g1"]["std"], ext["g1"]
    assert abs(math.log(ext["tau1"]["mean"] / 0.1)) < 3 * ext["tau1"]["coordinate_std"], ext["tau1"]
    assert out["fit_after"]["rms"] < 1.1 < out["fit_before"]["rms"]


def test_stand_in_lagging_cavity_pressure_is_not_named_a_creeping_body(stand_in):
    """The cavity's pressure lags its sensor by 0.02 of the recording (a pneumatic line; frames every
    0.05): the loop has a creeping body's sense, and creep fits it as well as the lag does (a delay
    shorter than the frame spacing is short-time creep), so nothing is named; both causes are."""
    from torchfra.diagnosis.pipeline import diagnose

    rec = stand_in(lambda t: triangle(np.maximum(t - 0.02, 0.0)), triangle, seed=2)
    out = diagnose(rec, noise=0.3, correlation=0.0, candidates=["viscoelasticity"], progress=False, load_steps=10)
    assert out["hysteresis"]["detected"] and out["hysteresis"]["sense"] == "lags"
    assert out["decision"] == "unexplained", (out["decision"], out["tried"])
    assert out["missing_physics"]["kind"] == "history-dependent"
    assert any("sensor" in c for c in out["missing_physics"]["possible_causes"])
    assert out["tried"][0]["rival"]["evidence_margin"] <= 5


def test_stand_in_body_leading_its_recorded_pressure_is_not_a_creeping_body(stand_in):
    """The sensor lags the cavity by 0.04 (the body leads the recorded pressure): a loop no passive
    body makes. The one-sided score test of g1 >= 0 stays quiet, nothing is refitted, the decision
    is "unexplained" with a clock among the causes."""
    from torchfra.diagnosis.pipeline import diagnose

    rec = stand_in(triangle, lambda t: triangle(np.maximum(t - 0.04, 0.0)), seed=3)
    out = diagnose(rec, noise=0.3, correlation=0.0, candidates=["viscoelasticity"], progress=False, load_steps=10)
    assert out["hysteresis"]["detected"] and out["hysteresis"]["sense"] == "leads"
    visco = out["ranking"][0]
    assert visco["one_sided"] and not visco["significant"]
    assert out["decision"] == "unexplained" and not out["tried"], (out["decision"], out["tried"])
    assert any("sensor" in c for c in out["missing_physics"]["possible_causes"])


def test_stand_in_null_cycle_is_not_flagged(stand_in):
    """No effect on a load-unload cycle: no loop, no candidate, decision "none"."""
    from torchfra.diagnosis.pipeline import diagnose

    rec = stand_in(triangle, triangle, seed=4)
    out = diagnose(rec, noise=0.3, correlation=0.0, candidates=["viscoelasticity"], progress=False, load_steps=10)
    assert out["hysteresis"]["applicable"] and not out["hysteresis"]["detected"]
    assert out["decision"] == "none", out["ranking"]


# -- the candidate in the FE model -------------------------------------------------------------------------

def test_actuator_physics_creep_shares_the_base_solve_and_its_sensitivities_are_exact():
    """ActuatorPhysics with viscoelasticity on a load-unload cycle (resolution 1): g1 = 0 reproduces the
    base model bitwise; changing g1 or tau1 solves nothing (they act on the frames' load factors only);
    dY/dg1 and dY/dlog tau1 match central differences of the observations (reference)."""
    from torchfra.actuator.geometry import ActuatorGeometry, actuator_mesh
    from torchfra.diagnosis.model import ActuatorPhysics as Real
    from torchfra.observation.operator import regular_grid, visible_faces

    mesh = actuator_mesh(ActuatorGeometry(resolution=1))
    X = regular_grid(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), 4.0)
    times = np.arange(9) / 8
    rec = Recording(np.arange(9), times, 0.02 * triangle(times), np.arange(len(X)), X, np.zeros((9, len(X), 2)))
    base = Real(rec, (), 1, 4)
    visco = Real(rec, ("viscoelasticity",), 1, 4)
    c10 = math.log(0.006)
    b = base.observe({"C10": c10})
    visco._memo = base._memo  # one FE model: the creeping body's observations come off the base solve
    null = visco.observe({"C10": c10, "g1": 0.0, "tau1": math.log(0.1)})
    assert null.reused and np.array_equal(null.Y, b.Y) and np.array_equal(null.J[..., 0], b.J[..., 0])
    z = {"C10": c10, "g1": 0.3, "tau1": math.log(0.15)}
    ev = visco.observe(z)
    assert ev.reused and np.abs(ev.Y - b.Y).max() > 0.5  # the loop: ~1 mm at resolution 1
    for k, n in enumerate(visco.names[1:], start=1):
        h = 1e-5
        up, dn = visco.observe(z | {n: z[n] + h}), visco.observe(z | {n: z[n] - h})
        fd = (up.Y - dn.Y) / (2 * h)
        assert np.abs(ev.J[..., k] - fd).max() < 1e-5 * np.abs(fd).max(), n


@pytest.mark.parametrize("text", ["g1=uniform:0,0.5", "tau1=lognormal:0.1,0.05", "pressure_lag=normal:0,0.01"])
def test_forward_ensembles_refuse_load_map_parameters(text):
    """A forward ensemble solves the FE model only: a prior on a creep or lag parameter would be
    ignored by every member, so it is refused by name, pointing to the diagnosis."""
    from torchfra.calibration.priors import PriorError, parse_fixed, parse_prior

    with pytest.raises(PriorError, match="scripts/diagnose.py"):
        parse_prior(text)
    with pytest.raises(PriorError, match="not on the FE solve"):
        parse_fixed(text.split("=")[0] + "=0.05")


def test_stand_in_ramp_does_not_test_creep(stand_in):
    """On a load that only rises, creep is a warp of the load axis (confounded with the material's own
    nonlinearity): the candidate is reported not testable, never ranked or refitted, even when the
    recording does creep (g1 = 0.3)."""
    from torchfra.diagnosis.locate import history_identifiable
    from torchfra.diagnosis.pipeline import diagnose

    rec = stand_in(lambda t: t - 0.3 * (0.1 / 0.7) * (1 - np.exp(-t * 7)), lambda t: np.asarray(t), seed=5)
    out = diagnose(rec, noise=0.3, correlation=0.0, candidates=["viscoelasticity"], progress=False, load_steps=10)
    assert "viscoelasticity" in out["not_testable"] and not out["ranking"] and not out["tried"]
    assert out["decision"] in ("none", "unexplained")
    t = np.linspace(0, 1, 11)
    hold = np.minimum(t, 0.5)  # rises, then holds at half the largest pressure
    assert history_identifiable(Recording(np.arange(11), t, hold, np.arange(1), np.zeros((1, 3)), np.zeros((11, 1, 2))))
    assert not history_identifiable(Recording(np.arange(11), t, t, np.arange(1), np.zeros((1, 3)), np.zeros((11, 1, 2))))
