"""Figures of a diagnosis (PNG in the run folder and TensorBoard): residual maps on the face before
and after, residual over time at the worst points, the candidate ranking, the posterior of the added
parameters, observed vs base vs extended model at the worst point, and, for a recording that comes back
down, the loading and unloading branches at the point with the largest loop (hysteresis).

Each figure is titled, its axes labelled with units, laid out by matplotlib's constrained layout (no
label outside the canvas), and built by a function of its own from the diagnosis record and arrays, so
:meth:`torchfra.api.DiagnosisResult.plot` rebuilds them from a finished run. TensorBoard also gets the
ranking and the fit before and after as scalars, a custom-scalars layout putting the candidates on one
chart, and a text summary (:func:`log_diagnosis_scalars`)."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from torchfra.report.tensorboard import log_figure, open_writer

BASE_LABEL = "base model (C10 fitted)"


def _score_level(row: dict) -> float:
    """The score statistic a candidate's row must exceed to be significant at its level (chi^2 with its
    degrees of freedom; a one-sided test's p-value is half the two-sided one's)."""
    from scipy import stats

    level = 2 * row["level"] if row.get("one_sided") else row["level"]
    return float(stats.chi2.isf(level, row["dof"]))


def _untested_lines(out: dict) -> list[str]:
    """One line per candidate the ranking holds no statistic for, with why."""
    lines = []
    for r in out["ranking"]:
        if r["dof"] == 0:
            absorbed = ", ".join(r.get("confounded_with") or []) or "the base parameters"
            lines.append(f"{r['name']}: absorbed by {absorbed} (0 degrees of freedom left)")
    for c, why in {**out.get("not_testable", {}), **out.get("not_available", {})}.items():
        lines.append(f"{c}: {why}")
    return lines


def ranking_figure(out: dict) -> Figure:
    """The candidates' score statistics (chi^2, log axis) as bars, most significant on top, each with the
    critical value its test must pass (the level ``alpha / n`` Bonferroni over the candidates) drawn
    across its bar; candidates without a statistic (absorbed by the base parameters, or that the
    recording or the model cannot test) are listed as text below, never drawn as bars.

    Parameters
    ----------
    out : dict
        The diagnosis record (``diagnosis.json``; ``ranking``, ``not_testable``, ``not_available``, ``decision``).

    Returns
    -------
    matplotlib.figure.Figure
    """
    rows = [r for r in out["ranking"] if r["dof"] > 0][::-1]  # barh draws bottom-up: most significant on top
    untested = _untested_lines(out)
    wrapped = [w for line in untested for w in textwrap.wrap(line, 95, subsequent_indent="    ")]
    fig = Figure(figsize=(7.5, 1.6 + 0.42 * max(len(rows), 1) + 0.17 * len(wrapped)), layout="constrained")
    if wrapped:
        ax, note = fig.subplots(2, 1, height_ratios=[max(len(rows), 1) * 0.42 + 0.9, 0.17 * len(wrapped) + 0.3])
    else:
        ax, note = fig.subplots(), None
    level = out["ranking"][0]["level"] if out["ranking"] else None
    if rows:
        y = np.arange(len(rows))
        scores = np.array([max(r["score"], 1e-3) for r in rows])
        crit = np.array([_score_level(r) for r in rows])
        ax.barh(y, scores, height=0.6, color=["tab:red" if r["significant"] else "tab:gray" for r in rows])
        ax.set_yticks(y, [r["name"] for r in rows])
        # the critical value of each bar's test across the bar (one line; NaN separates the bars)
        xs = np.repeat(crit, 3)
        ys = np.stack([y - 0.42, y + 0.42, np.full(len(rows), np.nan)], 1).ravel()
        xs[2::3] = np.nan
        ax.plot(xs, ys, color="black", lw=2, label=f"critical value at the test level {level:.2g} (alpha / candidates)")
        for yi, r, s in zip(y, rows, scores):
            p = r["p_value"]
            ax.annotate(f"p < 1e-300" if p <= 0 else f"p = {p:.2g}", (s, yi), xytext=(3, 0),
                        textcoords="offset points", va="center", fontsize=8)
        ax.set_xscale("log")
        lo = min(scores.min(), crit.min())
        ax.set_xlim(lo / 3, max(scores.max(), crit.max()) * 30)  # room for the p-values right of the bars
        ax.set_ylim(-0.7, len(rows) - 0.3)
        ax.legend(loc="lower right", fontsize=8)
    else:
        ax.set_yticks([])
        ax.text(0.5, 0.5, "no candidate could be tested", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("score statistic chi^2 (dimensionless, log scale); red: significant")
    ax.grid(True, axis="x", alpha=0.3)
    ax.set_title(f"Candidate physics ranked by their score tests; decision: {out['decision']}", fontsize=10)
    if note is not None:
        note.set_axis_off()
        note.text(0, 1, "Not tested:\n" + "\n".join(wrapped), va="top", ha="left", fontsize=8,
                  transform=note.transAxes)
    return fig


def _face_outline(X: np.ndarray) -> np.ndarray:
    """The observed points' outline on the face (Y, Z) in mm, closed: their convex hull."""
    from scipy.spatial import ConvexHull, QhullError

    pts = X[:, 1:3]
    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):  # fewer than 3 points, or all on one line
        return pts
    ring = pts[hull.vertices]
    return np.vstack([ring, ring[:1]])


def _face_map(ax, X: np.ndarray, values: np.ndarray, vmax: float, title: str):
    """``values`` (P,) over the face, filled between the points (Y, Z in mm, to scale), with its outline."""
    from matplotlib.tri import Triangulation

    y, z = X[:, 1], X[:, 2]
    ok = np.isfinite(values)
    art = None
    try:
        tri = Triangulation(y[ok], z[ok])
        art = ax.tripcolor(tri, values[ok], shading="gouraud", cmap="magma", vmin=0, vmax=vmax)
    except (ValueError, RuntimeError):  # too few points to triangulate: the points alone
        pass
    sc = ax.scatter(y[ok], z[ok], c=values[ok], cmap="magma", vmin=0, vmax=vmax, s=6, edgecolors="white",
                    linewidths=0.3)
    ring = _face_outline(X)
    ax.plot(ring[:, 0], ring[:, 1], color="black", lw=1)
    ax.set_aspect("equal")
    ax.set_xlabel("Y (mm)")
    ax.set_ylabel("Z (mm)")
    ax.xaxis.set_major_locator(MaxNLocator(3))
    ax.set_title(title, fontsize=9)
    return art if art is not None else sc


def residual_map_figure(rec, rms_before: np.ndarray, rms_after: np.ndarray | None, decision: str) -> Figure:
    """The RMS whitened residual of every point over the frames on the observed face, before (the base
    model) and after (the decision's model), to scale, on one colour scale.

    Parameters
    ----------
    rec : Recording
        The recording (its points' reference coordinates ``X``, mm).
    rms_before, rms_after : ndarray (P,)
        The points' RMS residuals in noise units (1 = the noise); ``rms_after`` None when no extension
        was accepted.
    decision : str
        The diagnosis's decision (the right panel's title).

    Returns
    -------
    matplotlib.figure.Figure
    """
    X = np.asarray(rec.X, dtype=np.float64)
    width = max(float(np.ptp(X[:, 1])), 1e-9)
    height = max(float(np.ptp(X[:, 2])), 1e-9)
    panel_h = 4.8
    panel_w = float(np.clip(panel_h * width / height, 1.3, 6.0)) + 0.9  # the face to scale, plus its axis labels
    fig = Figure(figsize=(2 * panel_w + 1.3, panel_h + 0.9), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, sharey=True)
    vmax = max(1.5, float(np.nanmax(rms_before)))
    art = _face_map(ax1, X, rms_before, vmax, f"before: {BASE_LABEL}")
    if rms_after is not None:
        _face_map(ax2, X, rms_after, vmax, f"after: {decision}")
    else:
        ring = _face_outline(X)
        ax2.plot(ring[:, 0], ring[:, 1], color="black", lw=1)
        ax2.set_aspect("equal")
        ax2.set_xlabel("Y (mm)")
        ax2.xaxis.set_major_locator(MaxNLocator(3))
        ax2.text(float(X[:, 1].mean()), float(X[:, 2].mean()), textwrap.fill(f"no extension accepted: {decision}", 18),
                 ha="center", va="center", fontsize=9)
        ax2.set_title("after: the base model stays", fontsize=9)
    cb = fig.colorbar(art, ax=[ax1, ax2], shrink=0.85)
    cb.set_label("RMS residual over the frames (noise units; 1 = the noise)")
    fig.suptitle("Residual on the observed face", fontsize=10)
    return fig


def observed_vs_models_figure(rec, Z: np.ndarray, Y_base: np.ndarray, Y_ext: np.ndarray | None, point: int,
                              decision: str) -> Figure:
    """The recorded (uy, uz) of one point against the frames' pressure, with the base model's and the
    decision's model's, one panel per component.

    Parameters
    ----------
    rec : Recording
        The recording (pressures in MPa, point ids and coordinates).
    Z, Y_base, Y_ext : ndarray (K, P, 2)
        Observed displacements and the two models' (mm); ``Y_ext`` None when no extension was accepted.
    point : int
        The point's index (the figure names its id and coordinates).
    decision : str
        The decision (the extended model's label).

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig = Figure(figsize=(8.5, 3.9), layout="constrained")
    axs = fig.subplots(1, 2)
    p = int(point)
    order = np.argsort(rec.pressure, kind="stable")
    for c, ax in enumerate(axs):
        ax.plot(rec.pressure, Z[:, p, c], "k.", ms=5, label="observed")
        ax.plot(rec.pressure[order], Y_base[order, p, c], "C0-", label=BASE_LABEL)
        if Y_ext is not None:
            ax.plot(rec.pressure[order], Y_ext[order, p, c], "C3--", label=f"extended: {decision}")
        ax.set_xlabel("recorded pressure (MPa)")
        ax.set_ylabel(f"u{'yz'[c]} (mm)")
        ax.set_title(f"u{'yz'[c]}", fontsize=9)
        ax.xaxis.set_major_locator(MaxNLocator(4))
        ax.grid(True, alpha=0.3)
    axs[0].legend(fontsize=7)
    X = rec.X[p]
    fig.suptitle(f"Observed and modelled displacement at point {int(rec.point_ids[p])} (Y = {X[1]:.1f} mm, "
                 f"Z = {X[2]:.1f} mm), the largest base residual", fontsize=10)
    return fig


def residual_over_time_figure(rec, raw_b: np.ndarray, raw_a: np.ndarray | None, worst, onset) -> Figure:
    """The whitened residual's magnitude at the worst points against the recorded pressure, before and
    after (``raw_*``: (K, P, 2) residuals in noise units), with the onset when one was found."""
    fig = Figure(figsize=(7.5, 4.2), layout="constrained")
    ax = fig.subplots()
    for i, p in enumerate(worst):
        where = f"point {int(rec.point_ids[p])} (Z = {rec.X[p, 2]:.1f} mm)"
        ax.plot(rec.pressure, np.sqrt(np.nanmean(raw_b[:, p] ** 2, axis=1)), "o-", ms=3, color=f"C{i}",
                label=f"{where}, base")
        if raw_a is not None:
            ax.plot(rec.pressure, np.sqrt(np.nanmean(raw_a[:, p] ** 2, axis=1)), "x--", ms=3, color=f"C{i}",
                    label=f"{where}, extended")
    if onset:
        ax.axvline(onset["pressure"], color="k", lw=0.8, ls=":", label="onset of the mismatch")
    ax.set_xlabel("recorded pressure (MPa)")
    ax.set_ylabel("|residual| (noise units)")
    ax.set_title("Residual at the three worst points", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    return fig


def posterior_added_figure(out: dict, extended) -> Figure:
    """The Laplace posterior of each parameter the accepted extension adds, in its fit coordinate."""
    added = [n for n in extended.names if n != "C10"]
    fig = Figure(figsize=(3.4 * max(len(added), 1), 3.2), layout="constrained")
    axs = np.atleast_1d(fig.subplots(1, max(len(added), 1)))
    for ax, n in zip(axs, added):
        m, s = extended.z[n], extended.std(n)
        x = np.linspace(m - 4 * s, m + 4 * s, 200)
        ax.plot(x, np.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi)))
        row = out["parameters"]["extended"][n]
        log = row["coordinate"] == "log"
        ax.set_xlabel(f"{'log ' if log else ''}{n}" + ("" if log else f" ({row.get('unit', '')})"))
        ax.set_ylabel("density")
        ax.xaxis.set_major_locator(MaxNLocator(4))
    fig.suptitle("Laplace posterior of the added parameters", fontsize=10)
    return fig


def hysteresis_figure(rec, out: dict, base, extended, sigma: float) -> Figure:
    """The recording's loading and unloading branches along the base model's deflection mode, with the
    models' (the whole face on one axis, so the noise of one point does not hide a loop)."""
    loop = out["hysteresis"]
    up = [list(rec.frames).index(f) for f in loop["frames_loading"]]
    down = [list(rec.frames).index(f) for f in loop["frames_unloading"]]
    frames = up + down
    common = np.isfinite(rec.Z[frames]).all(axis=0)
    mode = np.where(common, base.evaluation.Y[int(np.argmax(rec.pressure))], 0.0)
    mode = mode / max(float(np.linalg.norm(mode)), 1e-300)

    def amplitude(Y):
        return np.einsum("kpc,pc->k", np.where(common[None], Y, 0.0), mode)

    fig = Figure(figsize=(6, 4.3), layout="constrained")
    ax = fig.subplots()
    amp = amplitude(rec.Z)
    ax.plot(rec.pressure[up], amp[up], "C0o", ms=4, label="recorded, loading")
    ax.plot(rec.pressure[down], amp[down], "C3s", ms=4, label="recorded, unloading")
    models = [("base", base)] + ([(out["decision"], extended)] if extended is not None else [])
    for (name, fit), style in zip(models, ("k-", "C2--")):
        a = amplitude(fit.evaluation.Y)
        ax.plot(rec.pressure[up + down], a[up + down], style, lw=1, label=f"model: {name}")
    ax.set_xlabel("recorded pressure (MPa)")
    ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.set_ylabel(f"displacement along the deflection mode (mm, noise {sigma:g})")
    sense = {"lags": "the body lags its load", "leads": "the body leads the recorded pressure"}
    verdict = (f"hysteresis: {sense.get(loop.get('sense'), 'history-dependent physics')}"
               if loop["detected"] else "no significant loop")
    ax.set_title(f"Loading against unloading; {verdict}", fontsize=10)
    ax.legend(fontsize=7)
    return fig


def summary_text(out: dict) -> str:
    """The diagnosis as Markdown for TensorBoard's text dashboard: the decision, the fits before and
    after, the ranking with each test's statistic, and what was not tested."""
    b, a = out["fit_before"], out["fit_after"]
    lines = [f"**decision: {out['decision']}**", "",
             "| fit | RMS (noise units) | log evidence | chi^2 p-value |", "|---|---|---|---|",
             f"| before (base) | {b['rms']:.3g} | {b['log_evidence']:.6g} | {b['chi2_p_value']:.3g} |",
             f"| after | {a['rms']:.3g} | {a['log_evidence']:.6g} | {a['chi2_p_value']:.3g} |", "",
             "| candidate | score chi^2 | dof | p-value | significant |", "|---|---|---|---|---|"]
    lines += [f"| {r['name']} | {r['score']:.4g} | {r['dof']} | {r['p_value']:.3g} | {r['significant']} |"
              for r in out["ranking"]]
    untested = _untested_lines(out)
    if untested:
        lines += ["", "Not tested:", *[f"- {u}" for u in untested]]
    return "\n".join(lines)


def log_diagnosis_scalars(writer, out: dict) -> None:
    """The ranking (``diagnosis/score/<candidate>``, ``diagnosis/minus_log10_p/<candidate>``), the fits
    before and after (``diagnosis/fit/<quantity>`` at step 0 before, step 1 after, and the earlier
    ``diagnosis/rms_before``, ``rms_after``), a custom-scalars layout putting every candidate on one
    chart and the fit on another, and the text summary (``diagnosis/summary``) and decision."""
    names = [r["name"] for r in out["ranking"]]
    for r in out["ranking"]:
        writer.add_scalar(f"diagnosis/score/{r['name']}", float(r["score"]), 0)
        writer.add_scalar(f"diagnosis/minus_log10_p/{r['name']}", -math.log10(max(float(r["p_value"]), 1e-300)), 0)
    quantities = ("rms", "log_evidence", "nis_per_observation")
    for step, fit in enumerate((out["fit_before"], out["fit_after"])):
        for q in quantities:
            if fit.get(q) is not None:
                writer.add_scalar(f"diagnosis/fit/{q}", float(fit[q]), step)
    writer.add_scalar("diagnosis/rms_before", out["fit_before"]["rms"], 0)
    writer.add_scalar("diagnosis/rms_after", out["fit_after"]["rms"], 0)
    writer.add_custom_scalars({"diagnosis": {
        "score statistic per candidate": ["Multiline", [f"diagnosis/score/{n}" for n in names]],
        "-log10 p per candidate": ["Multiline", [f"diagnosis/minus_log10_p/{n}" for n in names]],
        "fit before (step 0) and after (step 1)": ["Multiline", [f"diagnosis/fit/{q}" for q in quantities]],
    }})
    writer.add_text("diagnosis/summary", summary_text(out), 0)
    writer.add_text("diagnosis/decision", out["decision"], 0)


def write_figures(run_dir: Path, rec, out: dict, base, extended, sigma: float, where: dict) -> None:
    """Every figure of a diagnosis into ``run_dir`` (PNG) and its TensorBoard events, with the scalars
    and the text summary (:func:`log_diagnosis_scalars`).

    Parameters
    ----------
    run_dir : Path
        The run folder.
    rec : Recording
        The recording the base model was fitted to.
    out : dict
        The diagnosis record.
    base, extended : Fit
        The base fit and the accepted extension's (None: none accepted).
    sigma : float
        The noise's standard deviation (mm).
    where : dict
        The location step's outcome (unused beyond the record; kept for the caller's signature).
    """
    run_dir = Path(run_dir)
    writer = open_writer(run_dir)
    try:
        raw_b = (rec.Z - base.evaluation.Y) / sigma
        raw_a = (rec.Z - extended.evaluation.Y) / sigma if extended is not None else None
        rms_b = np.sqrt(np.nanmean(raw_b**2, axis=(0, 2)))
        rms_a = np.sqrt(np.nanmean(raw_a**2, axis=(0, 2))) if raw_a is not None else None
        log_figure(writer, "diagnosis/residual_map", residual_map_figure(rec, rms_b, rms_a, out["decision"]),
                   run_dir / "residual_map.png")
        worst = np.argsort(-rms_b)[:3]
        log_figure(writer, "diagnosis/residual_over_time",
                   residual_over_time_figure(rec, raw_b, raw_a, worst, out["onset"]),
                   run_dir / "residual_over_time.png")
        log_figure(writer, "diagnosis/ranking", ranking_figure(out), run_dir / "ranking.png")
        log_figure(writer, "diagnosis/observed_vs_models",
                   observed_vs_models_figure(rec, rec.Z, base.evaluation.Y,
                                             extended.evaluation.Y if extended is not None else None, int(worst[0]),
                                             out["decision"]), run_dir / "observed_vs_models.png")
        if out.get("hysteresis", {}).get("applicable"):
            log_figure(writer, "diagnosis/hysteresis", hysteresis_figure(rec, out, base, extended, sigma),
                       run_dir / "hysteresis.png")
        if extended is not None:
            log_figure(writer, "diagnosis/posterior_added", posterior_added_figure(out, extended),
                       run_dir / "posterior_added.png")
        log_diagnosis_scalars(writer, out)
    finally:
        writer.close()
