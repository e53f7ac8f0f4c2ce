"""What a calibration says about how sure it is: the headline of summary.json (the exact posterior, the filter
to report and its distance from it, the reasons not to trust it), the noise it assumed (estimated from a
recording's frames as the diagnosis does when --noise is left out), the settings that applied, a refusal
that exits non-zero; and a recording without motion named as such by calibrate and diagnose.

The deck is the two-brick cantilever of test_read_inp.py seen from +x (8 points); reference for the posterior
is the run's own exact grid posterior (verified on closed forms in test_assimilation.py), for the noise the
estimator of torchfra.observation.noise (its statistics are tested in test_discovery.py)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_read_inp import HAND_DECK

from torchfra.calibration.experiment import headline, rounded
from torchfra.io.recordings import read_recording, write_recording

pytestmark = pytest.mark.slow  # minutes of FE work each: python -m pytest -m slow runs them

ROOT = Path(__file__).resolve().parents[1]
PRIOR = "C10=lognormal:0.1,0.03"


def _torchfra(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "torchfra", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def test_rounded_keeps_two_digits_of_the_std():
    assert rounded(0.00480012, 1.234e-5) == "0.004800 +- 0.000012"
    assert rounded(0.10016554882467081, 0.00019442972509498918) == "0.10017 +- 0.00019"
    assert rounded(31012.7, 812.0) == "31013 +- 812"


def _summary(members, distances, outside=0.0, ok=True):
    comp = {n: {"distance_from_exact_mean_in_exact_stds": d} for n, d in distances.items()}
    return {"parameters": ["C10"], "members": members, "members_in_hierarchical_filters": members,
            "prior": {"C10": {"unit": "MPa"}}, "data_fit": {"ok": ok, "reasons": [] if ok else ["chi2 too large"]},
            "filters": {"exact": {"C10": {"mean": 0.0048001, "std": 1.2e-5}, "prior_mass_outside_grid": outside},
                        **{n: {"C10": {"mean": 0.0048, "std": 1e-5}} for n in distances}},
            "comparison": comp}


def test_headline_names_the_filter_to_report_and_why_not_to_trust_a_run():
    # the paper's experiment: the polynomial slave 0.12 exact stds off, the linear slave 4.0 (docs/calibration.md)
    h = headline(_summary(100, {"hierarchical": 4.0, "hierarchical_nonlinear": 0.12, "restart": -0.5}))
    assert h["trusted"] and h["report"] == "hierarchical_nonlinear"
    assert h["text"].startswith("C10 = 0.004800 +- 0.000012 MPa (exact posterior); filter to report: "
                                "hierarchical_nonlinear, 0.12 exact stds from it; hierarchical 4.0 exact stds off")
    # 5 members, both hierarchical filters 5 exact stds off
    h = headline(_summary(5, {"hierarchical": 5.1, "hierarchical_nonlinear": -5.0}))
    assert not h["trusted"] and "NOT TRUSTED: 5 members are too few" in h["text"]
    assert any("every filter is more than 3 exact stds" in w for w in h["warnings"])
    # 6 members, 7.6 % of the prior outside the grid, a filter 3.9 exact stds off
    h = headline(_summary(6, {"hierarchical": 3.9, "hierarchical_nonlinear": 1.0}, outside=0.076))
    assert not h["trusted"] and any("7.6 % of the prior lies outside" in w for w in h["warnings"])
    assert "hierarchical 3.9 exact stds off" in h["text"]
    assert "no calibration result" in headline(_summary(100, {"hierarchical": 0.1}, ok=False))["text"]


@pytest.fixture(scope="module")
def deck_run(tmp_path_factory):
    """One recording of the deck (noise 0.01 mm), calibrated from its file without --noise, 6 members."""
    root = tmp_path_factory.mktemp("headline")
    (root / "cantilever.inp").write_text(HAND_DECK.replace("type=C3D20RH", "type=C3D20H"))
    made = _torchfra(["make-recording", "--inp", "cantilever.inp", "--noise", "0.01", "--seed", "3", "--frames", "20",
                      "--out", "rec.csv"], root)
    assert made.returncode == 0, made.stderr
    out = _torchfra(["calibrate", "--inp", "cantilever.inp", "--param", PRIOR, "--recording", "rec.csv", "--members",
                     "6", "--no-restart", "--workers", "1", "--name", "cal"], root)
    return root, out


def test_a_recording_file_without_noise_gets_the_diagnosis_estimate_and_says_so(deck_run):
    from torchfra.diagnosis.noise import estimate_noise

    root, out = deck_run
    assert out.returncode == 0, out.stderr
    summary = json.loads((root / "runs" / "cal" / "summary.json").read_text())
    sigma = estimate_noise(read_recording(root / "rec.csv")).sigma  # the diagnosis's own estimate
    assert summary["noise"]["sigma_mm"] == sigma == summary["config"]["noise"]
    assert "estimated from the recording's frames" in summary["noise"]["source"]
    # 320 second differences: the estimate's relative std is sqrt(70/36 / 2 / 320) = 5.5 %
    assert abs(sigma - 0.01) < 4 * 0.055 * 0.01
    assert f"noise: {sigma:.3g} mm per component, estimated from the recording's frames" in out.stdout


def test_summary_headline_config_and_stdout_of_a_small_run(deck_run):
    root, out = deck_run
    summary = json.loads((root / "runs" / "cal" / "summary.json").read_text())
    h = summary["headline"]
    exact = summary["filters"]["exact"]["C10"]
    assert h["exact"]["C10"]["mean"] == exact["mean"] and h["exact"]["C10"]["unit"] == "MPa"
    assert h["text"].startswith(f"C10 = {rounded(exact['mean'], exact['std'])} MPa (exact posterior)")
    assert not h["trusted"] and "6 members are too few for the filters to be trusted" in h["text"]
    assert abs(exact["mean"] - 0.1) < 4 * exact["std"]  # the deck's own C10, the recording's truth
    for k in ("truth_c10", "truth", "noise_seed", "points", "frames", "coverage_seeds"):  # synthetic-only settings
        assert k not in summary["config"], k
    assert "--method auto: 6 members against 5 snapshot members" in out.stdout and summary["config"]["method"] == "full"
    assert "C10 (MPa):" in out.stdout and f"headline: {h['text']}" in out.stdout
    assert "0.1" in out.stdout.split("exact (grid)")[1].splitlines()[0]


def test_a_recording_30_times_too_large_is_refused_with_a_nonzero_status(deck_run):
    root, _ = deck_run
    rec = read_recording(root / "rec.csv")
    rec.Z[...] *= 30.0
    write_recording(root / "rec30.csv", rec)
    out = _torchfra(["calibrate", "--inp", "cantilever.inp", "--param", PRIOR, "--recording", "rec30.csv",
                     "--noise", "0.01", "--members", "6", "--no-restart", "--workers", "1", "--name", "cal30"], root)
    assert out.returncode == 3 and "no calibration result" in out.stderr and "Traceback" not in out.stderr
    summary = json.loads((root / "runs" / "cal30" / "summary.json").read_text())
    assert not summary["data_fit"]["ok"] and "no calibration result" in summary["headline"]["text"]


def test_a_recording_without_motion_is_named_by_diagnose_and_calibrate(deck_run):
    root, _ = deck_run
    rec = read_recording(root / "rec.csv")
    rec.Z[...] = np.where(np.isfinite(rec.Z), 0.0, np.nan)
    write_recording(root / "still.csv", rec)
    for args in (["diagnose", "still.csv", "--inp", "cantilever.inp"],
                 ["calibrate", "--inp", "cantilever.inp", "--param", PRIOR, "--recording", "still.csv", "--workers",
                  "1", "--members", "6"]):
        out = _torchfra(args, root)
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert "still.csv: the recording shows no motion" in out.stderr and "Check that the uy, uz" in out.stderr
        assert "sigma must be positive" not in out.stderr
