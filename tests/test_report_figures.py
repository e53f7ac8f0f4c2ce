"""The diagnosis's figures and TensorBoard events, checked at the image level on a diagnosis record of
the shape ``diagnosis.json`` has (no FE solve: the fits are stand-ins with their arrays): every text
the renderer draws lies inside the canvas, tick labels do not overlap, each figure is titled, the
ranking draws its test level and lists the untested candidates as text, not bars. The event file is
read back with TensorBoard's own EventAccumulator."""
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.lines import Line2D
from matplotlib.text import Text
from scipy import stats

from torchfra.observation.recording import Recording
from torchfra.report import diagnosis as report


def drawn_texts(fig):
    """Every text the renderer draws (tick labels outside their axis's view left out), with its extent."""
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    hidden = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if not lo - 1e-9 * abs(hi - lo) <= tick.get_loc() <= hi + 1e-9 * abs(hi - lo):
                    hidden |= {id(tick.label1), id(tick.label2)}
    out = []
    for t in fig.findobj(Text):
        if t.get_visible() and t.get_text().strip() and id(t) not in hidden:
            out.append((t, t.get_window_extent(renderer)))
    return out, renderer


def assert_nothing_clipped(fig):
    texts, _ = drawn_texts(fig)
    box = fig.bbox
    for t, e in texts:
        assert (e.x0 >= box.x0 - 1 and e.y0 >= box.y0 - 1 and e.x1 <= box.x1 + 1 and e.y1 <= box.y1 + 1), \
            f"text {t.get_text()!r} at {e} is outside the figure {box}"
    for i, (t, e) in enumerate(texts):  # no two texts collide (tick labels, axis labels of neighbouring panels)
        for u, f in texts[i + 1:]:
            assert not e.overlaps(f), f"texts {t.get_text()!r} and {u.get_text()!r} overlap: {e} and {f}"


def titled(fig) -> bool:
    sup = fig._suptitle.get_text() if fig._suptitle is not None else ""
    return bool(sup.strip()) or any(ax.get_title().strip() for ax in fig.axes)


class _Fit:
    def __init__(self, Y, names, z, std):
        self.evaluation = type("Evaluation", (), {"Y": Y})()
        self.names, self.z, self._std = names, z, std

    def std(self, name):
        return self._std[name]


def _face(ny=6, nz=20):
    y, z = np.meshgrid(np.linspace(-7.5, 7.5, ny), np.linspace(2.0, 62.0, nz))
    X = np.stack([np.full(y.size, 8.0), y.ravel(), z.ravel()], 1)
    return X


@pytest.fixture()
def case():
    K, X = 10, _face()
    P = len(X)
    p = np.linspace(0.002, 0.02, K)
    Y = (p[:, None, None] / 0.02) * np.stack([X[:, 2] / 60, 0.2 * X[:, 2] / 60], 1)[None] * 20  # (K, P, 2) mm
    rng = np.random.default_rng(0)
    Z = Y * 1.05 + 0.3 * rng.standard_normal(Y.shape)
    rec = Recording(np.arange(K), np.arange(1, K + 1) / K, p, np.arange(100, 100 + P), X, Z, "synthetic")
    level = 0.01 / 2 / 4
    ranking = [
        {"name": "pressure_sensor", "score": 5652.1, "dof": 1, "p_value": 0.0, "significant": True, "level": level,
         "one_sided": False, "confounded_with": ["C10"]},
        {"name": "gravity", "score": 149.7, "dof": 1, "p_value": 1e-34, "significant": True, "level": level,
         "one_sided": True, "confounded_with": []},
        {"name": "fiber_stiffness", "score": 3.1, "dof": 2, "p_value": 0.21, "significant": False, "level": level,
         "one_sided": False, "confounded_with": []},
        {"name": "pressure_gain_only", "score": 0.0, "dof": 0, "p_value": 1.0, "significant": False, "level": level,
         "one_sided": False, "confounded_with": ["C10"]},
    ]
    fit = {"rms": 3.2, "log_evidence": -1234.5, "nis_per_observation": 10.2, "chi2_p_value": 0.0}
    after = {"rms": 1.01, "log_evidence": -300.0, "nis_per_observation": 1.02, "chi2_p_value": 0.4}
    out = {"decision": "pressure_sensor", "ranking": ranking, "onset": {"pressure": 0.006},
           "not_testable": {"viscoelasticity": "the pressure only rises, without a hold: record unloading or a hold"},
           "not_available": {"cavity_offset": "the deck has no cavity"}, "hysteresis": {"applicable": False},
           "fit_before": fit, "fit_after": after,
           "parameters": {"extended": {"pressure_offset": {"coordinate": "linear", "unit": "MPa"}}}}
    base = _Fit(Y, ["C10"], {"C10": -5.1}, {"C10": 0.004})
    ext = _Fit(Z - 0.3 * rng.standard_normal(Y.shape), ["C10", "pressure_offset"],
               {"C10": -5.1, "pressure_offset": 0.004}, {"C10": 0.004, "pressure_offset": 6e-5})
    return rec, out, base, ext


def test_ranking_is_titled_draws_the_level_and_lists_the_untested_as_text(case):
    rec, out, base, ext = case
    fig = report.ranking_figure(out)
    assert_nothing_clipped(fig)
    assert titled(fig)
    ax = fig.axes[0]
    bars = [t.get_text() for t in ax.get_yticklabels()]
    assert bars == ["fiber_stiffness", "gravity", "pressure_sensor"]  # the 0-dof candidate is not a bar
    assert len(ax.patches) == 3
    notes = " ".join(t.get_text() for t in fig.findobj(Text))
    for c in ("pressure_gain_only", "viscoelasticity", "cavity_offset"):
        assert c in notes
    level = [line for line in ax.get_lines() if line.get_label().startswith("critical value")]
    assert len(level) == 1
    # the critical values drawn are chi^2's at each row's level (reference: scipy.stats.chi2; a one-sided
    # test's p-value halves the two-sided one, so its critical value is at twice the level)
    x = level[0].get_xdata()
    want = [stats.chi2.isf(out["ranking"][2]["level"], 2), stats.chi2.isf(2 * out["ranking"][1]["level"], 1),
            stats.chi2.isf(out["ranking"][0]["level"], 1)]
    np.testing.assert_allclose(x[0::3], want, rtol=1e-12)
    assert "chi^2" in ax.get_xlabel() and "pressure_sensor" in ax.get_title()


def test_residual_map_is_the_face_to_scale_with_its_outline(case):
    rec, out, base, ext = case
    rms_b = np.sqrt(np.nanmean((rec.Z - base.evaluation.Y) ** 2, axis=(0, 2))) / 0.3
    rms_a = np.sqrt(np.nanmean((rec.Z - ext.evaluation.Y) ** 2, axis=(0, 2))) / 0.3
    for after in (rms_a, None):
        fig = report.residual_map_figure(rec, rms_b, after, out["decision"])
        assert_nothing_clipped(fig)
        assert titled(fig)
        face_axes = fig.axes[:2]
        for ax in face_axes:
            assert ax.get_aspect() == 1.0 and ax.get_xlabel() == "Y (mm)"
            outline = [line for line in ax.get_lines() if len(line.get_xdata()) > 3]
            assert outline, "the face's outline is drawn"
            # the outline is closed and encloses every point: the convex hull of the face's points
            xy = np.stack([outline[0].get_xdata(), outline[0].get_ydata()], 1)
            np.testing.assert_allclose(xy[0], xy[-1])
            assert xy[:, 0].min() == rec.X[:, 1].min() and xy[:, 1].max() == rec.X[:, 2].max()
        # the face's width on screen over its height is its width over its height in mm (to scale)
        _, renderer = drawn_texts(fig)
        pos = face_axes[0].get_window_extent(renderer)
        (x0, x1), (y0, y1) = face_axes[0].get_xlim(), face_axes[0].get_ylim()
        np.testing.assert_allclose((pos.width / (x1 - x0)) / (pos.height / (y1 - y0)), 1.0, rtol=0.02)
        # the face fills its panel rather than floating in white space: at least 8 % of the canvas
        assert pos.width * pos.height > 0.08 * fig.bbox.width * fig.bbox.height
        assert "noise units" in fig.axes[-1].get_ylabel()  # the colour bar says its unit


def test_observed_vs_models_names_the_point_by_id_and_place(case):
    rec, out, base, ext = case
    fig = report.observed_vs_models_figure(rec, rec.Z, base.evaluation.Y, ext.evaluation.Y, 7, out["decision"])
    assert_nothing_clipped(fig)
    title = fig._suptitle.get_text()
    assert f"point {rec.point_ids[7]}" in title and f"Z = {rec.X[7, 2]:.1f} mm" in title
    assert [ax.get_ylabel() for ax in fig.axes] == ["uy (mm)", "uz (mm)"]
    assert all(ax.get_xlabel() == "recorded pressure (MPa)" for ax in fig.axes)


def test_write_figures_writes_titled_pngs_and_the_events_read_back(case, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.custom_scalar import layout_pb2

    rec, out, base, ext = case
    report.write_figures(tmp_path, rec, out, base, ext, 0.3, {})
    for name in ("residual_map", "residual_over_time", "ranking", "observed_vs_models", "posterior_added"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000
    acc = EventAccumulator(str(tmp_path), size_guidance={"tensors": 0, "scalars": 0}).Reload()
    tags = acc.Tags()
    for r in out["ranking"]:
        assert acc.Scalars(f"diagnosis/score/{r['name']}")[0].value == pytest.approx(r["score"], rel=1e-6)
    fit = acc.Scalars("diagnosis/fit/rms")
    assert [(e.step, round(e.value, 4)) for e in fit] == [(0, 3.2), (1, 1.01)]
    assert "diagnosis/summary/text_summary" in tags["tensors"]
    text = acc.Tensors("diagnosis/summary/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "decision: pressure_sensor" in text and "| gravity |" in text and "viscoelasticity" in text
    layout = layout_pb2.Layout()
    layout.ParseFromString(acc.Tensors("custom_scalars__config__")[0].tensor_proto.string_val[0])
    charts = {c.title: list(c.multiline.tag) for cat in layout.category for c in cat.chart}
    assert charts["score statistic per candidate"] == [f"diagnosis/score/{r['name']}" for r in out["ranking"]]
