"""The estimators a Python user calls, ``torchfra.calibrate`` and ``torchfra.diagnose``, on a small case
(resolution 1, 4 members, 6 frames at low pressure, as tests/test_calibration.py): their results hold
what the run folder holds, the headline reads as text, the figures are titled and unclipped, and the
calibration's TensorBoard events put the filters on one chart beside the exact posterior (read back
with TensorBoard's EventAccumulator)."""
import json

import numpy as np
import pytest
from matplotlib.figure import Figure
from test_report_figures import assert_nothing_clipped, titled

import torchfra
from torchfra.calibration.priors import PriorError

pytestmark = pytest.mark.slow  # minutes of FE work each: python -m pytest -m slow runs them

SMALL = dict(members=4, frames=6, pressure=0.004, load_steps=2, restart=False, coverage_seeds=0, degree=2, grid=400)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    run = tmp_path_factory.mktemp("api") / "runs" / "cal"
    return torchfra.calibrate(None, noise=0.05, run_dir=run, truth=0.0048, progress=False, **SMALL), run


def test_calibrate_returns_the_run_folders_posteriors(calibrated):
    cal, run = calibrated
    saved = json.loads((run / "summary.json").read_text())
    post = cal.posterior["C10"]
    assert post.unit == "MPa" and post.source == "exact"
    assert set(post.filters) == {"hierarchical", "hierarchical_nonlinear", "exact"}
    assert post.mean == saved["filters"]["exact"]["C10"]["mean"] and post.exact["std"] == post.std
    for name, f in post.filters.items():
        assert f["mean"] == saved["filters"][name]["C10"]["mean"]
        comp = saved["comparison"][name]
        assert f["distance_from_exact_in_exact_stds"] == comp["distance_from_exact_mean_in_exact_stds"]
    # the recording was made at C10 = 0.0048 with 0.05 mm of noise: the exact posterior holds it
    # within 3 of its stds (reference: the truth that made the synthetic data)
    assert abs(post.mean - 0.0048) < 3 * post.std
    record = cal.to_json()
    assert json.loads(json.dumps(record)) == record and record["noise_source"] == "given"
    assert {k: v for k, v in record.items() if k not in ("noise_source", "wall_s")} == \
        {k: v for k, v in saved.items() if k != "wall_s"}
    text = cal.summary()
    assert any(line.startswith("C10 = ") and line.endswith("MPa (exact posterior; truth 0.0048 MPa)")
               for line in text.splitlines())
    assert "hierarchical: " in text and "exact stds from the exact mean" in text and str(run) in text


def test_calibration_figures_are_titled_and_unclipped(calibrated):
    cal, run = calibrated
    figs = cal.plot()
    assert set(figs) == {"bands", "pdfs"}
    for fig in figs.values():
        assert isinstance(fig, Figure) and titled(fig)
        assert_nothing_clipped(fig)
    for f in ("bands.png", "pdfs.png"):
        assert (run / f).stat().st_size > 10_000


def test_calibration_events_chart_the_filters_beside_the_exact_posterior(calibrated):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.custom_scalar import layout_pb2

    cal, run = calibrated
    acc = EventAccumulator(str(run), size_guidance={"tensors": 0, "scalars": 0}).Reload()
    layout = layout_pb2.Layout()
    layout.ParseFromString(acc.Tensors("custom_scalars__config__")[0].tensor_proto.string_val[0])
    charts = {c.title: list(c.multiline.tag) for cat in layout.category for c in cat.chart}
    tags = charts["C10 mean: the filters and the exact posterior"]
    assert tags == ["C10_mean/hierarchical", "C10_mean/hierarchical_nonlinear", "C10_mean/exact"]
    scalars = set(acc.Tags()["scalars"])
    for chart in charts.values():
        assert set(chart) <= scalars, set(chart) - scalars  # every charted curve was logged
    # the curve's last point is the posterior the result reports
    assert acc.Scalars("C10_mean/exact")[-1].value == pytest.approx(cal.posterior["C10"].mean, rel=1e-6)
    assert acc.Scalars("C10_mean/hierarchical")[-1].value == \
        pytest.approx(cal.posterior["C10"].filters["hierarchical"]["mean"], rel=1e-6)


def test_diagnose_on_the_models_own_recording_finds_nothing(calibrated, tmp_path):
    cal, run = calibrated
    diag = torchfra.diagnose(run / "recording.csv", noise=0.05, run_dir=tmp_path / "diag", candidates=["gravity"],
                             correlation=0.0, load_steps=2, mesh_error=False, held_out_every=3, progress=False)
    saved = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert diag.to_json() == saved
    # the model's own recording (C10 = 0.0048, noise 0.05 mm): no mismatch, and the Laplace
    # posterior holds the truth (reference: the truth that made the synthetic data)
    assert diag.decision == "none"
    c10 = diag.posterior["C10"]
    assert c10.source == "laplace (base model)" and abs(c10.mean - 0.0048) < 4 * c10.std
    assert c10.mean == saved["parameters"]["base"]["C10"]["mean"]
    text = diag.summary()
    assert text.startswith("decision: none (no mismatch with the base model)") and "C10 = " in text
    figs = diag.plot()
    assert set(figs) == {"ranking", "residual_map", "observed_vs_models"}
    for fig in figs.values():
        assert titled(fig)
        assert_nothing_clipped(fig)
    for f in ("ranking.png", "residual_map.png", "observed_vs_models.png"):
        assert (tmp_path / "diag" / f).exists()


def test_bad_calls_are_refused_by_name_before_any_work(tmp_path):
    with pytest.raises(TypeError, match="unknown keyword 'member'"):
        torchfra.calibrate(None, member=4)
    with pytest.raises(PriorError, match="C10"):
        torchfra.calibrate(None, params=["C10=lognormal:-1,0.001"], run_dir=tmp_path / "x")
    with pytest.raises(ValueError, match="fixed: name the uncertain parameters"):
        torchfra.calibrate(None, fixed={"E_fiber": 31000})
    with pytest.raises(TypeError, match="recording: give a path"):
        torchfra.calibrate(np.zeros(3), run_dir=tmp_path / "y")
    with pytest.raises(TypeError, match="unknown keyword 'nosie'"):
        torchfra.diagnose(tmp_path / "none.csv", nosie=1.0)
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_a_diagnosis_result_reads_the_stored_pressure_offset_diagnosis():
    from pathlib import Path

    from torchfra.api import DiagnosisResult

    stored = json.loads((Path(__file__).parent / "data" / "diagnosis_pressure_offset.json").read_text())
    diag = DiagnosisResult(stored, None, {}, None)
    assert diag.decision == "pressure_sensor" and diag.to_json() == stored
    off = diag.posterior["pressure_offset"]
    assert (off.mean, off.std) == (stored["parameters"]["extended"]["pressure_offset"]["mean"],
                                   stored["parameters"]["extended"]["pressure_offset"]["std"])
    assert set(diag.posterior["C10"].filters) == {"base", "extended"} and "base" not in off.filters
    lines = diag.summary().splitlines()
    assert lines[0] == "decision: pressure_sensor (missing physics: pressure_sensor)"
    assert "  pressure_offset = 0.004004 +- 5.8e-05 MPa (laplace (extended model))" in lines
    assert lines[-1] == "8 frames, 80 points, 19 FE solves"
    assert any(line.startswith("significant candidates: pressure_sensor (score 5.65e+03, p = 0), gravity") for line in lines)
