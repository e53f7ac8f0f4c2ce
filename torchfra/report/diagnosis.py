"""Figures of a diagnosis (PNG in the run folder and TensorBoard): residual maps on the face before
and after, residual over time at the worst points, the candidate ranking, the posterior of the added
parameters, observed vs base vs extended model at the worst point, and, for a recording that comes back
down, the loading and unloading branches at the point with the largest loop (hysteresis)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from torchfra.report.tensorboard import log_figure, open_writer


def _map(ax, rec, values, title, vmax):
    sc = ax.scatter(rec.X[:, 1], rec.X[:, 2], c=values, cmap="magma", vmin=0, vmax=vmax, s=14)
    ax.set_aspect("equal")
    ax.set_xlabel("Y (mm)")
    ax.set_ylabel("Z (mm)")
    ax.set_title(title, fontsize=9)
    return sc


def write_figures(run_dir: Path, rec, out: dict, base, extended, sigma: float, where: dict) -> None:
    run_dir = Path(run_dir)
    writer = open_writer(run_dir)
    try:
        raw_b = (rec.Z - base.evaluation.Y) / sigma
        raw_a = (rec.Z - extended.evaluation.Y) / sigma if extended is not None else None
        rms_b = np.sqrt(np.nanmean(raw_b**2, axis=(0, 2)))
        vmax = max(1.5, float(np.nanmax(rms_b)))
        fig = Figure(figsize=(8, 4.5))
        ax1, ax2 = fig.subplots(1, 2)
        sc = _map(ax1, rec, rms_b, "RMS residual, base model (noise units)", vmax)
        if raw_a is not None:
            _map(ax2, rec, np.sqrt(np.nanmean(raw_a**2, axis=(0, 2))), f"after: {out['decision']}", vmax)
        else:
            ax2.set_axis_off()
            ax2.text(0.5, 0.5, f"decision: {out['decision']}", ha="center")
        fig.colorbar(sc, ax=[ax1, ax2], shrink=0.8)
        log_figure(writer, "diagnosis/residual_map", fig, run_dir / "residual_map.png")

        worst = np.argsort(-rms_b)[:3]
        fig = Figure(figsize=(7, 4))
        ax = fig.subplots()
        for p in worst:
            ax.plot(rec.pressure, np.sqrt(np.nanmean(raw_b[:, p] ** 2, axis=1)), "o-", ms=3,
                    label=f"point {rec.point_ids[p]} base")
            if raw_a is not None:
                ax.plot(rec.pressure, np.sqrt(np.nanmean(raw_a[:, p] ** 2, axis=1)), "x--", ms=3,
                        label=f"point {rec.point_ids[p]} extended")
        if out["onset"]:
            ax.axvline(out["onset"]["pressure"], color="k", lw=0.8, ls=":", label="onset")
        ax.set_xlabel("pressure (MPa)")
        ax.set_ylabel("|residual| (noise units)")
        ax.legend(fontsize=7)
        log_figure(writer, "diagnosis/residual_over_time", fig, run_dir / "residual_over_time.png")

        fig = Figure(figsize=(7, 3.5))
        ax = fig.subplots()
        names = [r["name"] for r in out["ranking"]]
        ax.barh(names[::-1], [max(r["score"], 1e-3) for r in out["ranking"]][::-1],
                color=["C3" if r["significant"] else "C7" for r in out["ranking"]][::-1])
        ax.set_xscale("log")
        ax.set_xlabel("score statistic (chi^2); red: significant")
        log_figure(writer, "diagnosis/ranking", fig, run_dir / "ranking.png")

        p = worst[0]
        fig = Figure(figsize=(7, 4))
        axs = fig.subplots(1, 2)
        for c, ax in enumerate(axs):
            ax.plot(rec.pressure, rec.Z[:, p, c], "k.", label="observed")
            ax.plot(rec.pressure, base.evaluation.Y[:, p, c], "C0-", label="base")
            if extended is not None:
                ax.plot(rec.pressure, extended.evaluation.Y[:, p, c], "C3--", label="extended")
            ax.set_xlabel("pressure (MPa)")
            ax.set_ylabel(f"u{'yz'[c]} (mm) at point {rec.point_ids[p]}")
        axs[0].legend(fontsize=7)
        log_figure(writer, "diagnosis/observed_vs_models", fig, run_dir / "observed_vs_models.png")

        loop = out.get("hysteresis", {})
        if loop.get("applicable"):
            # the whole face on one axis: the recording projected on the base model's deflection at the
            # largest pressure (a unit vector over every point and component observed in every frame),
            # so the noise of one point (sigma) does not hide a loop spread over all of them
            up = [list(rec.frames).index(f) for f in loop["frames_loading"]]
            down = [list(rec.frames).index(f) for f in loop["frames_unloading"]]
            frames = up + down
            common = np.isfinite(rec.Z[frames]).all(axis=0)
            mode = np.where(common, base.evaluation.Y[int(np.argmax(rec.pressure))], 0.0)
            mode = mode / max(float(np.linalg.norm(mode)), 1e-300)

            def amplitude(Y):
                return np.einsum("kpc,pc->k", np.where(common[None], Y, 0.0), mode)

            fig = Figure(figsize=(5.5, 4))
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
            ax.set_title(verdict, fontsize=9)
            ax.legend(fontsize=7)
            log_figure(writer, "diagnosis/hysteresis", fig, run_dir / "hysteresis.png")

        if extended is not None:
            added = [n for n in extended.names if n != "C10"]
            fig = Figure(figsize=(3.2 * max(len(added), 1), 3))
            axs = np.atleast_1d(fig.subplots(1, max(len(added), 1)))
            for ax, n in zip(axs, added):
                m, s = extended.z[n], extended.std(n)
                x = np.linspace(m - 4 * s, m + 4 * s, 200)
                ax.plot(x, np.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi)))
                ax.set_xlabel(f"{n} ({'log ' if out['parameters']['extended'][n]['coordinate'] == 'log' else ''}coordinate)")
            log_figure(writer, "diagnosis/posterior_added", fig, run_dir / "posterior_added.png")
        writer.add_scalar("diagnosis/rms_before", out["fit_before"]["rms"], 0)
        writer.add_scalar("diagnosis/rms_after", out["fit_after"]["rms"], 0)
        writer.add_text("diagnosis/decision", out["decision"], 0)
    finally:
        writer.close()
