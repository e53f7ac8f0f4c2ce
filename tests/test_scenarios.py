"""Scenario recordings of the proof suite (torchfra.scenarios): the null is the base model, an effect
shows at the SNR its metadata claims, the noise has the asked-for statistics, clean observations are
cached, bad names are refused, and the DIC grid avoids the mesh nodes.

FE work is kept to three solves at resolution 1 on a short trace (module-scoped fixtures)."""
import numpy as np
import pytest
import torch

from torchfra import fem, scenarios
from torchfra.actuator.geometry import ActuatorGeometry, actuator_mesh, build_actuator_model
from torchfra.observation.operator import ObservationOperator, visible_faces
from torchfra.scenarios import calculix, generate

FAST = dict(resolution=1, frames=3, truth_c10=0.0062)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("clean")


@pytest.fixture(scope="module")
def null(cache):
    return scenarios.make_scenario("none", 0, noise=0.5, seed=3, cache_dir=cache, **FAST)


@pytest.fixture(scope="module")
def gravity(cache, null):
    return scenarios.make_scenario("gravity", 2, noise=0.5, seed=4, cache_dir=cache, **FAST)


def test_null_is_the_base_model_at_the_same_points(null):
    rec, clean, meta = null
    model, info = build_actuator_model(ActuatorGeometry(resolution=1))
    c10 = FAST["truth_c10"]
    params = {"C10": [c10], "D1": [1 / (1000 * c10)], "E_fiber": [31000.0], "P": [0.022]}
    sol = fem.solve(model, {k: torch.tensor(v) for k, v in params.items()}, rec.pressure / 0.022,
                    fem.NewtonOptions(stagnation_tol=1e-6))
    op = ObservationOperator(info["mesh"], visible_faces(info["mesh"], (1.0, 0.0, 0.0)), points=rec.X)
    expected = op(sol.u[0, :, : info["mesh"].n_nodes]).numpy()
    assert np.abs(expected).max() > 5.0  # a real deflection (mm), not two zeros
    np.testing.assert_allclose(clean, expected, atol=1e-6 * np.abs(expected).max())
    assert meta["snr"] == 0.0 and meta["expected"] == "none" and meta["solves"] == 1
    np.testing.assert_allclose(rec.pressure, 0.022 * np.arange(1, 4) / 3)


def test_effect_differs_from_the_null_by_the_snr_meta_reports(null, gravity, cache):
    """The weight acts before the reference image: the recording's points are where the sagged body puts
    them, and its SNR is against the base model seen at those same points (one solve of its own)."""
    _, clean0, _ = null
    rec, clean, meta = gravity
    assert meta["solves"] == 2  # the effect, and the null at the recording's (sagged) points
    assert meta["parameters"]["density"] == scenarios.EFFECTS["gravity"].sizes[1] > 0
    moved = np.linalg.norm(rec.X - null[0].X, axis=1)
    assert moved.max() > 0.1  # mm: the reference image's points sit on the sagged body
    base, solves = scenarios.clean_observations("none", 0.0, FAST["truth_c10"], FAST["resolution"], 2.0,
                                                FAST["frames"], "ramp", cache_dir=cache, points=rec.X)
    assert solves == 0  # kept by make_scenario
    snr = np.linalg.norm(clean - base["clean"]) / 0.5
    assert snr > 1.0
    assert meta["snr"] == pytest.approx(snr, rel=1e-12)


def test_noise_statistics_iid(null, gravity):
    for rec, clean, meta in (null, gravity):
        e = (rec.Z - clean).ravel()
        # mean of n draws: std sigma / sqrt(n); std: relative std 1 / sqrt(2n); 5-sigma bounds
        n = e.size
        assert abs(e.mean()) < 5 * 0.5 / np.sqrt(n)
        assert abs(e.std() / 0.5 - 1) < 5 / np.sqrt(2 * n)
    assert not np.allclose(null[0].Z - null[1], gravity[0].Z - gravity[1])  # seeds differ


def test_correlated_noise_has_the_requested_correlation():
    points = scenarios.dic_grid(actuator_mesh(ActuatorGeometry(resolution=1)), 2.0)
    ell, sigma, frames = 3.0, 0.7, 400
    e, _ = scenarios.observation_noise(points, frames, sigma, ell, np.random.default_rng(0))
    assert e.shape == (frames, len(points), 2)
    flat = e.transpose(0, 2, 1).reshape(-1, len(points))  # draws x points
    assert flat.std() == pytest.approx(sigma, rel=0.03)
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    corr = np.corrcoef(flat.T)
    for lag in (2.0, 4.0):  # grid neighbours and next neighbours along an axis
        pairs = np.isclose(d, lag)
        assert pairs.sum() > 100
        assert corr[pairs].mean() == pytest.approx(np.exp(-lag**2 / (2 * ell**2)), abs=0.02)
    iid, _ = scenarios.observation_noise(points, frames, sigma, 0.0, np.random.default_rng(0))
    assert abs(np.corrcoef(iid.transpose(0, 2, 1).reshape(-1, len(points)).T)[np.isclose(d, 2.0)].mean()) < 0.02


def test_clean_cache_is_reused_without_solving(null, gravity, cache, monkeypatch):
    def no_solve(*args, **kwargs):
        raise AssertionError("fem.solve called although the clean observations are cached")

    monkeypatch.setattr(fem, "solve", no_solve)
    rec, clean, meta = scenarios.make_scenario("gravity", 2, noise=0.5, seed=9, cache_dir=cache, **FAST)
    assert meta["solves"] == 0
    np.testing.assert_array_equal(clean, gravity[1])
    assert meta["snr"] == gravity[2]["snr"]
    assert not np.allclose(rec.Z, gravity[0].Z)  # another seed, other noise on the same clean part
    _, clean_null, meta_null = scenarios.make_scenario("gravity", 0, noise=0.5, cache_dir=cache, **FAST)
    np.testing.assert_array_equal(clean_null, null[1])  # size 0 is the null itself
    for path in cache.iterdir():
        with np.load(path, allow_pickle=False) as f:
            assert f["clean"].dtype == np.float64


def test_unknown_effect_or_size_is_refused_naming_it():
    with pytest.raises(ValueError, match="'gravitas'.*gravity.*sensor_lag"):
        scenarios.make_scenario("gravitas", 1)
    with pytest.raises(ValueError, match="unknown size 7 of effect 'gravity'"):
        scenarios.make_scenario("gravity", 7)
    with pytest.raises(ValueError, match="outside its admissible range"):
        scenarios.make_scenario("gravity", 1.0)


def test_grid_points_are_not_mesh_nodes():
    for resolution in (1, 2):
        mesh = actuator_mesh(ActuatorGeometry(resolution=resolution))
        points = scenarios.dic_grid(mesh, 2.0)
        assert len(points) >= 200
        assert np.allclose(points[:, 0], 8.0)
        gap = np.linalg.norm(points[:, None] - mesh.nodes[None], axis=-1).min()
        assert gap > 0.05  # mm
        ObservationOperator(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=points)  # all on the face


def test_suite_driver_selects_cases_and_tabulates_by_the_snr_after_the_base_fit():
    """scripts/scenarios.py: --sizes picks effect sizes (nulls keep their truths and traces); the table
    bands rows by the SNR left after the base model's C10 refit and averages wall time only over
    diagnoses that solved everything themselves."""
    from torchfra.scenarios import suite
    todo = suite.cases(["none", "gravity"], 2, [0.0, 4.0], False, {3})
    names = [c["case"] for c in todo]
    assert len(todo) == (4 + 1) * 2 * 2 and len(set(names)) == len(names)
    assert {c["size"] for c in todo if c["effect"] == "gravity"} == {3}
    # every case draws its own noise (the four null variants of a seed used to share one draw), the
    # same case the same noise on every run
    seeds = [suite.noise_seed(c) for c in todo]
    assert len(set(seeds)) == len(todo) and seeds == [suite.noise_seed(dict(c)) for c in todo]
    # more seeds of a suite already run (--first-seed 2): seeds 2 and 3, new names and new draws, and a
    # case of seed 0 named and drawn as before
    more = suite.cases(["gravity"], 2, [0.0], False, {3}, first_seed=2)
    assert [c["seed"] for c in more] == [2, 3] and not {c["case"] for c in more} & set(names)
    assert not {suite.noise_seed(c) for c in more} & set(seeds)
    again = suite.cases(["gravity"], 1, [0.0], False, {3}, first_seed=0)[0]
    assert again["case"] in names and suite.noise_seed(again) in seeds
    row = dict(effect="gravity", kind="library", correct=True, decision="gravity", rms_before=1.3, rms_after=1.0,
               solves=12, snr=46.0)
    rows = [row | dict(snr_after_base=30.0, band=suite.snr_band(30.0, "library"), seconds=100.0, solves_reused=0),
            row | dict(snr_after_base=28.0, band=suite.snr_band(28.0, "library"), seconds=1.0, solves_reused=12),
            row | dict(snr_after_base=8.0, band=suite.snr_band(8.0, "library"), seconds=50.0, solves_reused=0,
                       correct=False, decision="none")]
    lines = [line for line in suite.table(rows).splitlines() if line.startswith("| gravity")]
    assert len(lines) == 2
    low, high = sorted(lines, key=lambda line: line.split("|")[3])
    cells = [c.strip() for c in high.split("|")]
    assert cells[3] == ">=25" and cells[4] == "2" and cells[6] == "29" and cells[7] == "100%"
    assert cells[-2] == "100", cells  # the reused diagnosis' 1 s is not a cost
    assert [c.strip() for c in low.split("|")][7] == "0%"


def test_creeping_body_is_generated_with_history_variables(cache, monkeypatch):
    """The viscoelastic scenario marches the FE model with a Prony term in its element kernel
    (fem.viscoelastic), not the diagnosis' load-level approximation: on the load-unload cycle the
    body lags (more displacement coming down than going up at the same recorded pressure), and the
    recorded pressure is the cavity's."""
    calls = []
    real = fem.solve_history
    monkeypatch.setattr(fem, "solve_history", lambda *a, **k: calls.append(a[1]) or real(*a, **k))
    rec, clean, meta = scenarios.make_scenario("viscoelasticity", 3, noise=0.5, seed=1, cache_dir=cache,
                                               resolution=1, frames=8, truth_c10=0.0062)
    assert len(calls) == 1 and float(calls[0]["g1"][0]) == 0.4 and float(calls[0]["tau1"][0]) == scenarios.VISCO_TAU1
    assert meta["parameters"]["g1"] == 0.4 and meta["parameters"]["tau1"] == scenarios.VISCO_TAU1
    assert np.allclose(meta["trace"]["true"], meta["trace"]["recorded"])
    p = np.asarray(meta["trace"]["recorded"])
    up, down = 1, 5  # frames at t = 2/8 and 6/8: the same pressure on either side of the peak (t = 4/8)
    assert abs(p[up] - p[down]) < 1e-12
    assert np.abs(clean[down]).sum() > 1.05 * np.abs(clean[up]).sum()
    assert meta["snr"] > 5  # against the elastic body at the same trace (noise 0.5 mm)


def test_calculix_recordings_of_the_actuator(cache, tmp_path):
    """``generator="calculix"``: the same scenario solved by CalculiX 2.20 on the deck write_inp writes
    (C3D20R, SPRINGA fibers, the frames' pressures as one amplitude): the null's clean observations
    against torchfra's at the same points, frame for frame. The two codes differ in element
    formulation, integration and fiber element, +0.57 % at the tracked node at resolution 1
    (README "CalculiX, the actuator"); over the grid measured 0.55-0.58 % on a load-unload trace.
    Bounds 0.2-1.5 % per frame: a frame shifted by one, or a lost amplitude, would differ by a third
    or more. Effects a deck cannot carry are refused by name before any work."""
    low = dict(pressure=0.003, cache_dir=cache)  # 9 CalculiX increments (CALCULIX_DP)
    ccx, _ = scenarios.clean_observations("none", 0.0, FAST["truth_c10"], 1, 2.0, FAST["frames"], "ramp",
                                          generator="calculix", **low)
    ours, _ = scenarios.clean_observations("none", 0.0, FAST["truth_c10"], 1, 2.0, FAST["frames"], "ramp", **low)
    assert np.array_equal(ccx["points"], ours["points"]) and np.array_equal(ccx["true"], ours["true"])
    for k in range(FAST["frames"]):
        rel = np.linalg.norm(ccx["clean"][k] - ours["clean"][k]) / np.linalg.norm(ours["clean"][k])
        assert 2e-3 < rel < 1.5e-2, (k, rel)
    assert list(cache.glob("calculix/none_*/scenario.inp"))  # the deck stays beside the cache
    for effect in ("viscoelasticity", "cavity_offset", "sensor_lag", "stiff_base_region"):
        with pytest.raises(ValueError, match=f"effect '{effect}' has no CalculiX deck"):
            scenarios.make_scenario(effect, 1, generator="calculix", cache_dir=tmp_path)
    with pytest.raises(ValueError, match="unknown generator 'abaqus'"):
        scenarios.make_scenario("none", 0, generator="abaqus", cache_dir=tmp_path)


def test_a_calculix_deck_that_does_not_solve_is_named(tmp_path, monkeypatch):
    """A CalculiX run that stops early ends in a CalculixError (which the scripts print in one
    paragraph) naming the deck and the way out, a lower pressure."""
    from torchfra.io.abaqus import write as abaqus

    def stopped(*args, **kwargs):
        raise abaqus.CalculixError("CalculiX stopped at time 0.4, before load factor 1\noutput tail")

    monkeypatch.setattr(abaqus, "run_calculix", stopped)
    model, _ = build_actuator_model(ActuatorGeometry(resolution=1), formulation="displacement", integration="reduced")
    values = {"C10": 0.0062, "D1": 1.0 / 6.2, "E_fiber": 31000.0, "P": 0.01}
    with pytest.raises(abaqus.CalculixError, match=r"scenario.inp \(CalculiX stopped at time 0.4.*lower --pressure"):
        calculix._calculix_displacements(model, values, np.array([0.5, 1.0]), 10, tmp_path, "deck")


def test_a_calculix_scenario_without_a_cache_leaves_no_deck_behind(tmp_path, monkeypatch):
    """Without a cache folder the deck is written to a temporary folder, removed once solved (a failed
    run keeps it: its CalculixError names it). CalculiX itself is stubbed: this is about the files."""
    made = []

    def mkdtemp(prefix=""):
        made.append(tmp_path / f"{prefix}{len(made)}")
        made[-1].mkdir()
        return str(made[-1])

    def solved(model, values, lam, n_nodes, deck_dir, title):
        deck_dir.mkdir(parents=True)
        (deck_dir / "scenario.inp").write_text("*HEADING\n")
        return np.zeros((lam.size, n_nodes, 3)), None

    monkeypatch.setattr(generate.tempfile, "mkdtemp", mkdtemp)
    monkeypatch.setattr(generate, "_calculix_displacements", solved)
    arrays, _ = scenarios.clean_observations("none", 0.0, FAST["truth_c10"], 1, 2.0, FAST["frames"], "ramp",
                                             pressure=0.003, generator="calculix")
    assert made and not made[0].exists() and np.all(arrays["clean"] == 0.0)


def test_pooled_table_counts_each_recording_once_and_bounds_every_rate_exactly(tmp_path):
    """scripts/scenarios.py --pool: rows of several runs in one table; a recording listed in two
    files counts once, from the later; the bounds are exact one-sided Clopper-Pearson (closed forms:
    n of n gives a lower bound alpha^(1/n), 0 of n an upper bound 1 - alpha^(1/n); and
    scipy.stats.binomtest's interval in between); a file that is no suite's results is named."""
    import json

    from scipy.stats import binomtest

    from torchfra.scenarios import suite
    assert suite.rate_bound(6, 6, "lower") == pytest.approx(0.05 ** (1 / 6), rel=1e-9)  # 60.7 %
    assert suite.rate_bound(0, 60, "upper") == pytest.approx(1 - 0.05 ** (1 / 60), rel=1e-9)  # 4.9 %
    ci = binomtest(7, 9).proportion_ci(confidence_level=0.90, method="exact")  # two-sided 90 % = one-sided 95 %
    assert suite.rate_bound(7, 9, "lower") == pytest.approx(ci.low, rel=1e-9)
    assert suite.rate_bound(7, 9, "upper") == pytest.approx(ci.high, rel=1e-9)

    def row(case, effect, kind, decision, snr_after, noise=0.25, seed=1):
        return dict(case=case, effect=effect, kind=kind, noise=noise, noise_seed=seed, snr=3 * snr_after,
                    snr_after_base=snr_after, decision=decision, rms_before=1.05, rms_after=1.0, solves=10)

    first = [row("fiber_stiffness_s2_seed0_iid", "fiber_stiffness", "library", "none", 30.0),
             row("none_s0_c0.0062_ramp_seed0_iid", "none", "null", "none", 2.0),
             row("none_s0_c0.0062_ramp_seed0_iid", "none", "null", "gravity", 2.0, noise=1.0),
             row("fiber_debond_s3_seed0_iid", "fiber_debond", "outside", "unexplained", 40.0)]
    # the same fiber recording re-decided: replaces the first row, not a second recording
    second = [row("fiber_stiffness_s2_seed0_iid", "fiber_stiffness", "library", "fiber_stiffness", 30.0),
              row("gravity_s3_seed0_iid", "gravity", "library", "gravity", 45.0)]
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"rows": first}))
    b.write_text(json.dumps({"rows": second}))
    text, summary = suite.pooled([a, b])
    assert summary["recordings"] == 5 and summary["duplicates_dropped"] == 1
    t = summary["targets"]
    top1 = t["top-1 correct, library effects, SNR >= 25 after the base fit"]
    assert (top1["k"], top1["n"]) == (2, 2) and top1["bound"] == pytest.approx(0.05 ** 0.5)
    assert top1["met"].startswith("not shown")  # 2 of 2 bound the rate only above 22 %
    nulls = t["attributed to a candidate, nulls"]
    assert (nulls["k"], nulls["n"]) == (1, 2) and nulls["met"].startswith("no")  # one null named gravity
    line = next(x for x in text.splitlines() if x.startswith("| fiber_stiffness"))
    assert "| 1 of 1 |" in line
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"rows": [{k: v for k, v in first[0].items() if k != "noise"}]}))
    with pytest.raises(ValueError, match=r"bad\.json.*fiber_stiffness_s2_seed0_iid.*noise"):
        suite.pooled([a, bad])
    bad.write_text(json.dumps({"rows": [first[0] | {"snr_after_base": float("nan")}]}))
    with pytest.raises(ValueError, match=r"bad\.json.*fiber_stiffness_s2_seed0_iid.*snr_after_base = nan"):
        suite.pooled([bad])
    bad.write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"bad\.json.*no 'rows'"):
        suite.pooled([bad])


def test_a_suite_row_counts_the_creep_refits_fe_marches_with_its_solves(tmp_path, monkeypatch):
    """scripts/scenarios.py: a row's FE cost is every FE computation the diagnosis kept, its elastic
    solves and its marches of the FE model with history variables (the creep refit's, one file each in
    the run's solves folder; the rows used to count the solves only: 26 for a sensor lag whose
    diagnosis counted 55); a write cut short (.tmp) is no solve; what an earlier run left is reported
    as reused."""
    from types import SimpleNamespace

    from torchfra.scenarios import suite
    Z = np.zeros((3, 4, 3))
    meta = dict(kind="outside", value=0.5, trace={"kind": "cycle"}, snr=40.0, expected="unexplained",
                generation={"resolution": 2, "frames": 3}, solves=2, seconds=1.0)
    monkeypatch.setattr(suite.scenarios, "make_scenario",
                        lambda effect, size, **kw: (SimpleNamespace(Z=Z + 1.0), Z.copy(), meta))
    case = dict(case="sensor_lag_s3_seed0_iid", effect="sensor_lag", size=3, truth_c10=0.0062, trace="cycle",
                seed=0, correlation=0.0)
    run_dir = tmp_path / "diag" / case["case"]
    (run_dir / "solves").mkdir(parents=True)
    (run_dir / "solves" / "solve_old.npz").write_bytes(b"")  # left by an interrupted run

    def diagnose(rec, noise, correlation, run_dir, progress, mesh_error):
        # a recording made at resolution 2 carries the diagnosis mesh's discretization error: taken out
        assert mesh_error
        for name in ("solve_a.npz", "solve_b_values.npz", "history_c.npz", "history_d.npz", "solve_e.tmp.npz"):
            (run_dir / "solves" / name).write_bytes(b"")
        np.savez(run_dir / "residuals.npz", before=np.full_like(Z, 2.0))
        return {"decision": "unexplained", "mismatch_detected": {"detected": True},
                "noise": {"sigma": 0.25, "correlation_length_mm": 0.0}, "fit_before": {"rms": 4.0},
                "fit_after": {"rms": 4.0}, "cost": {"solves": 5, "seconds": 3.0}}

    a = SimpleNamespace(noise=0.25, generator="torchfra", pressure=0.022, resolution=2, quick=False,
                        estimate_noise=False, verbose=False)
    row = suite.run_case(case, a, tmp_path, diagnose)
    assert row["solves"] == 5 and row["history_marches"] == 2 and row["solves_reused"] == 1
    assert row["correct"] and row["snr_after_base"] == pytest.approx(np.sqrt(Z.size) / 0.25)
