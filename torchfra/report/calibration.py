"""Files of a calibration run: ``summary.json``, figures (PNG and TensorBoard), per-step scalars,
ensemble histograms and hparams."""
from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from torchfra.report.tensorboard import log_figure, log_hparams, open_writer

LABELS = {"hierarchical": "hierarchical (paper, linear slave)", "hierarchical_nonlinear": "hierarchical, polynomial slave",
          "restart": "restart EnKF (FE re-solves)", "exact": "exact (grid)"}
COLORS = {"prior": "tab:red", "hierarchical": "tab:blue", "hierarchical_nonlinear": "tab:green",
          "restart": "tab:orange", "exact": "black"}


def _pset(out: dict):
    return out["parameter_set"]


def filter_summary(out: dict) -> dict:
    """Per filter: one entry per parameter (mean, std, p10, p90; natural units), ``correlation``
    between parameters when there are several, the FE cost and the log evidence."""
    from torchfra.assimilation import innovation_flags
    from torchfra.calibration.exact import ensemble_stats

    rows = {}
    pset = _pset(out)
    for name, f in out["filters"].items():
        if name == "exact":
            post = f["posterior"]
            rows[name] = {**post.stats(), "prior_mass_outside_grid": post.prior_mass_outside,
                          "posterior_mass_in_end_cells": post.edge_mass(), "fe_solves": 0, "newton_iterations": 0,
                          "wall_s": f["wall_s"], "log_evidence": post.log_evidence,
                          "frames_assimilated": int(len(f["frames"])),
                          "note": f"FE map: {out['sweep'].kind}; no FE solve beyond the forward ensemble"}
            continue
        res = f["result"]
        row = {**ensemble_stats(pset, res.Q[-1]), "fe_solves": int(res.fe_solves),
               "newton_iterations": int(res.newton_iterations), "wall_s": float(res.wall_s),
               "log_evidence": res.log_evidence, "frames_assimilated": int(len(f["frames"]))}
        row["innovation_flags"] = innovation_flags(res, f["frames"])
        if pset.d > 1:
            X = torch.stack(list(pset.natural(res.Q[-1]).values()), 1).numpy()
            row["correlation"] = np.corrcoef(X.T).tolist()
        if "slave_error_tracked" in f:
            err = f["slave_error_tracked"]
            row["slave_error_tracked_max_mm"] = float(err.max())
            row["slave_error_tracked_last_mm"] = err[-1].tolist()
        rows[name] = row
    return rows


def comparisons(out: dict, rows: dict) -> dict:
    """Each filter against the exact posterior (same frames) and the truth, per parameter: distance
    of the means in exact stds, std ratio, error from the truth; for several parameters also the
    correlation against the exact one. One parameter: its entries at the top (the record's keys)."""
    pset = _pset(out)
    exact_all = out["filters"]["exact"]["posterior"]
    comp = {}
    for name, row in rows.items():
        post = (out["exact_restart_frames"] if name == "restart" else
                out["exact_hierarchical_frames"] if name.startswith("hierarchical") and "exact_hierarchical_frames" in out
                else exact_all)
        ref_all = post.stats()
        per = {}
        for p in pset.names:
            ref, c = ref_all[p], row[p]
            d = {"exact_mean_same_frames": ref["mean"], "exact_std_same_frames": ref["std"],
                 # None: the exact posterior collapsed onto one grid cell (a recording the model cannot fit)
                 "distance_from_exact_mean_in_exact_stds": (c["mean"] - ref["mean"]) / ref["std"] if ref["std"] > 0
                 else None,
                 "spread_ratio_to_exact": c["std"] / ref["std"] if ref["std"] > 0 else None,
                 "exact_log_evidence_same_frames": post.log_evidence, "exact_same_frames": ref}
            if out["truth"] is not None:
                d["error_from_truth_percent"] = 100 * (c["mean"] - out["truth"][p]) / out["truth"][p] \
                    if out["truth"][p] != 0 else None
                d["error_from_truth"] = c["mean"] - out["truth"][p]
            per[p] = d
        if pset.d == 1:
            comp[name] = per[pset.names[0]]
        else:
            comp[name] = {**per, "correlation": row["correlation"], "exact_correlation_same_frames": ref_all["correlation"]}
    return comp


def prior_summary(out: dict) -> dict:
    """Per parameter: the prior as given (kind, its two numbers) and the members' sample statistics."""
    from torchfra.calibration.exact import ensemble_stats

    pset = _pset(out)
    sample = ensemble_stats(pset, out["Q0"])  # the members the hierarchical filters start from
    rows = {}
    for p in pset.priors:
        given = {"low": p.a, "high": p.b} if p.kind == "uniform" else {"mean": p.a, "std": p.b}
        rows[p.name] = {"kind": p.kind, **given, "unit": p.unit, "sample": sample[p.name]}
    for n, v in pset.fixed:
        rows[n] = {"fixed": v}
    return rows


def write_calibration_outputs(out: dict, run_dir, wall_s: float) -> dict:
    run_dir = Path(run_dir)
    cfg = out["config"]
    fwd = out["forward"]
    rec = out["recording"]
    pset = _pset(out)
    rows = filter_summary(out)
    summary = {
        "members": int(cfg.members),
        "members_in_hierarchical_filters": int(out["Q0"].shape[0]),
        "frames": int(rec.n_frames),
        "observation_points": int(rec.n_points),
        "observations": int(np.isfinite(rec.Z).sum()),
        "recording_layout": (f"ragged: frames observe different points, at most {rec.Z.shape[1]} each" if rec.ragged
                             else "points followed through the frames"),
        "parameters": pset.names,
        "truth": out["truth"],
        "prior": prior_summary(out),
        "filters": rows,
        "comparison": comparisons(out, rows),
        "forward": {"resolution": cfg.resolution, "dofs": int(fwd["model"].n_red),
                    "newton_iterations_total": int(fwd["iterations"].sum()), "member_solves": int(len(fwd["status"])),
                    "solver_time_s": float(sum(fwd["timings"].values())),
                    "members_failed": [{"member": int(m), **{n: float(fwd["params"][n][m]) for n in pset.names},
                                        "load_reached": float(fwd["load_reached"][m])}
                                       for m in np.flatnonzero(fwd["status"] != "converged")],
                    "members_converged": int((fwd["status"] == "converged").sum())},
        "exact_interpolation_loo_error_mm": float(out["sweep_loo_error"]),
        "exact_map": out["sweep"].kind,
        "noise_std_mm": cfg.noise,
        "tracked_point": out["tracked_point"],
        "config": asdict(cfg),
        "wall_s": wall_s,
        "threads": torch.get_num_threads(),
    }
    if out.get("sweep_loo_error_rms") is not None:
        summary["exact_interpolation_loo_rms_mm"] = float(out["sweep_loo_error_rms"])
    if "data_fit" in out:
        summary["data_fit"] = out["data_fit"]
    if "restart_threads" in out:
        summary["restart_threads"] = out["restart_threads"]
        summary["restart_ranks"] = out.get("restart_ranks", 1)  # processes sharing its FE re-solves
    summary["direct_fe_check"] = out["direct_fe_check"]
    summary["polynomial_slave"] = {"degree": out["slave_degree"], "leave_one_out_rms_mm": out["slave_loo_rms_mm"]}
    if "restart_spline_check" in out:
        summary["restart_spline_check"] = out["restart_spline_check"]
    if "coverage" in out:
        summary["coverage"] = out["coverage"]
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))

    writer = open_writer(run_dir)
    log_figure(writer, "calibration/bands", bands_figure(out), run_dir / "bands.png")
    log_figure(writer, "calibration/pdfs", pdf_figure(out), run_dir / "pdfs.png")
    if pset.d > 1:
        log_figure(writer, "calibration/pairs", pairs_figure(out), run_dir / "pairs.png")
    _log_steps(writer, out)
    log_filter_layout(writer, pset.names, list(out["filters"]), out["truth"] is not None)
    metrics = {f"final/{n}/{p}_mean": r[p]["mean"] for n, r in rows.items() for p in pset.names}
    metrics.update({f"final/{n}/log_evidence": r["log_evidence"] for n, r in rows.items()})
    log_hparams(writer, {"members": summary["members"], "frames": summary["frames"], "resolution": cfg.resolution,
                         "noise": cfg.noise, "degree": out["slave_degree"], "restart_every": cfg.restart_every,
                         "recording": str(cfg.recording), "parameters": ",".join(pset.names)}, metrics)
    writer.close()
    return summary


def _band(ax, t, values, color, label):
    lo, hi = np.nanpercentile(values, [10, 90], axis=1)
    ax.fill_between(t, lo, hi, color=color, alpha=0.2, lw=0)
    ax.plot(t, np.nanmean(values, axis=1), color=color, label=label)


def _members(pset, Q: torch.Tensor, j: int) -> np.ndarray:
    return pset.natural(Q)[pset.names[j]].numpy()


def bands_figure(out: dict) -> Figure:
    """Tracked node y, z and every parameter over time: 10-90 % bands and means, prior vs each filter."""
    rec = out["recording"]
    pset = _pset(out)
    t = rec.times
    row = out["tracked_row"]
    fig = Figure(figsize=(5 * (2 + pset.d), 4.2), layout="constrained")
    axes = fig.subplots(1, 2 + pset.d)
    prior_Y = out["Y_fe"][:, :, row, :]  # (N, K, 2)
    for c, ax in enumerate(axes[:2]):
        _band(ax, t, prior_Y[:, :, c].T, COLORS["prior"], "prior (forward ensemble)")
        for name, f in out["filters"].items():
            if name == "exact":
                continue
            res = f["result"]
            Ytr = torch.stack(res.Y_tracked).numpy()[:, :, c]  # (steps, N)
            _band(ax, t[f["frames"]], Ytr, COLORS[name], LABELS[name] + " forecast")
        ax.plot(t, out["observed"][:, row, c], ".", ms=3, color="0.4", label="observations")
        ax.set(xlabel="normalized time t", ylabel=f"u{'yz'[c]} of the tracked point (mm)")
        ax.grid(True, alpha=0.3)
    for j, (ax, name_p) in enumerate(zip(axes[2:], pset.names)):
        prior = _members(pset, out["Q0"], j)
        ax.fill_between(t, *np.percentile(prior, [10, 90]), color=COLORS["prior"], alpha=0.15, lw=0)
        ax.plot(t, np.full_like(t, prior.mean()), color=COLORS["prior"], label="prior")
        for name, f in out["filters"].items():
            if name == "exact":
                post = f["posterior"]
                if pset.d == 1:  # the one-parameter grid keeps every frame's posterior
                    st = [post.stats(k + 1)[name_p] for k in range(len(t))]
                    ax.plot(t, [s["mean"] for s in st], color="k", label=LABELS[name])
                    ax.plot(t, [s["p10"] for s in st], "k:", lw=0.8)
                    ax.plot(t, [s["p90"] for s in st], "k:", lw=0.8)
                else:
                    st = post.stats()[name_p]
                    ax.errorbar([t[-1]], [st["mean"]], yerr=[[st["mean"] - st["p10"]], [st["p90"] - st["mean"]]],
                                fmt="o", color="k", ms=4, label=LABELS[name] + ", all frames (10-90 %)")
                continue
            C = np.stack([_members(pset, Q, j) for Q in f["result"].Q[1:]])  # (steps, N)
            _band(ax, t[f["frames"]], C, COLORS[name], LABELS[name])
        if out["truth"] is not None:
            ax.axhline(out["truth"][name_p], color="k", ls="--", lw=1, label="truth")
        ax.set(xlabel="normalized time t", ylabel=f"{name_p} ({pset.priors[j].unit})")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="x-small")
    axes[0].legend(fontsize="x-small")
    fig.suptitle(f"10-90 % bands and means; tracked point (y, z) = ({out['tracked_point'][1]:.1f}, "
                 f"{out['tracked_point'][2]:.1f}) mm")
    return fig


def _prior_pdf(prior, x: np.ndarray) -> np.ndarray:
    m, s = prior.gaussian
    if prior.kind == "lognormal":
        return np.exp(-0.5 * ((np.log(x) - m) / s) ** 2) / (x * s * math.sqrt(2 * math.pi))
    if prior.kind == "normal":
        return np.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))
    return np.where((x >= prior.a) & (x <= prior.b), 1.0 / (prior.b - prior.a), 0.0)


def pdf_figure(out: dict) -> Figure:
    """Prior and posterior densities of every parameter with the truth as a vertical line: for each,
    the prior's range (log scale) and a zoom on the posteriors."""
    from scipy.stats import gaussian_kde

    pset = _pset(out)
    fig = Figure(figsize=(11, 4.2 * pset.d), layout="constrained")
    grid = np.atleast_2d(fig.subplots(pset.d, 2))
    post = out["filters"]["exact"]["posterior"]
    for j, (prior, name_p) in enumerate(zip(pset.priors, pset.names)):
        ax_all, ax_zoom = grid[j]
        draws = _members(pset, out["Q0_all"], j)
        lo_p, hi_p = np.percentile(draws, [0.5, 99.5])
        pad = 0.3 * (hi_p - lo_p)
        x = np.linspace(lo_p - pad if prior.kind == "normal" else max(lo_p - pad, draws.min() * 0.8), hi_p + pad, 800)
        prior_pdf = _prior_pdf(prior, x)
        ax_all.plot(x, prior_pdf, color=COLORS["prior"], label="prior")
        xe, pe = post.density(j)
        st = post.stats()[name_p]
        lo, hi = st["mean"] - 8 * st["std"], st["mean"] + 8 * st["std"]
        for name, f in out["filters"].items():
            if name != "exact":
                c = _members(pset, f["result"].Q[-1], j)
                lo, hi = min(lo, c.min()), max(hi, c.max())
        xz = np.linspace(lo, hi, 600)
        for ax in (ax_all, ax_zoom):
            ax.plot(xe, pe, color="k", label=LABELS["exact"])
            if "exact_restart_frames" in out:
                xr, pr = out["exact_restart_frames"].density(j)
                ax.plot(xr, pr, "k:", label="exact, on the restart filter's frames")
            for name, f in out["filters"].items():
                if name == "exact":
                    continue
                c = _members(pset, f["result"].Q[-1], j)
                xs = np.union1d(x, xz) if ax is ax_all else xz  # resolve the narrow posteriors on the wide axis
                note = f", {len(f['frames'])} frames" if len(f["frames"]) != len(out["recording"].times) else ""
                ax.plot(xs, gaussian_kde(c)(xs), color=COLORS[name], ls="--", label=f"{LABELS[name]} (KDE{note})")
            if out["truth"] is not None:
                ax.axvline(out["truth"][name_p], color="k", lw=1)
            ax.set(xlabel=f"{name_p} ({prior.unit})", ylabel="density")
            ax.grid(True, alpha=0.3)
        ax_all.set_xlim(x[0], x[-1])
        ax_all.set_yscale("log")  # the prior is far lower than the posteriors
        ax_all.set_ylim(max(prior_pdf.max(), 1e-300) * 1e-2, pe.max() * 3)
        ax_all.set_title(f"{name_p}: prior and posteriors (log scale)")
        ax_zoom.set_xlim(lo, hi)
        ax_zoom.set_title(f"{name_p}: zoom on the posteriors")
        ax_all.legend(fontsize="x-small")
    return fig


def pairs_figure(out: dict) -> Figure:
    """Every pair of parameters: the exact posterior's contours (the grid's 1, 2 and 3 sigma levels)
    and each filter's final ensemble as points, the truth as a cross."""
    import itertools

    pset = _pset(out)
    pairs = list(itertools.combinations(range(pset.d), 2))
    fig = Figure(figsize=(5.5 * len(pairs), 5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(pairs)))
    raw = out["filters"]["exact"]["posterior"].raw
    X, w = raw.natural_points(), raw.weights()
    for ax, (i, j) in zip(axes, pairs):
        if pset.d == 2:  # the grid itself (aligned with the posterior's axes): contour it as it is
            n = int(round(math.sqrt(len(w))))
            xi, xj, W = X[:, i].reshape(n, n), X[:, j].reshape(n, n), w.reshape(n, n)
        else:  # a weighted 2-D histogram of the grid marginalizes the other parameters
            H, ei, ej = np.histogram2d(X[:, i], X[:, j], bins=80, weights=w)
            xi, xj, W = 0.5 * (ei[1:] + ei[:-1]), 0.5 * (ej[1:] + ej[:-1]), H.T
        # density levels holding 68 %, 95 % and 99.7 % of the grid mass
        flat = np.sort(W.reshape(-1))[::-1]
        cum = np.cumsum(flat) / flat.sum()
        levels = sorted({float(flat[min(np.searchsorted(cum, c), flat.size - 1)]) for c in (0.997, 0.95, 0.68)})
        if len(levels) > 1:
            ax.contour(xi, xj, W, levels=levels, colors="k", linewidths=1)
        ax.plot([], [], "k-", label="exact: 68/95/99.7 % regions")
        for name, f in out["filters"].items():
            if name == "exact":
                continue
            Q = f["result"].Q[-1]
            ax.plot(_members(pset, Q, i), _members(pset, Q, j), ".", ms=3, alpha=0.6, color=COLORS[name],
                    label=LABELS[name])
        if out["truth"] is not None:
            ax.plot(out["truth"][pset.names[i]], out["truth"][pset.names[j]], "x", color="k", ms=10, mew=2,
                    label="truth")
        lims = []
        for k in (i, j):  # the exact posterior's 0.05-99.95 % range and every filter's members
            order = np.argsort(X[:, k])
            cdf = np.cumsum(w[order])
            lo, hi = np.interp([0.0005, 0.9995], cdf, X[order, k])
            for name, f in out["filters"].items():
                if name != "exact":
                    v = _members(pset, f["result"].Q[-1], k)
                    lo, hi = min(lo, v.min()), max(hi, v.max())
            pad = 0.05 * (hi - lo)
            lims.append((lo - pad, hi + pad))
        ax.set(xlim=lims[0], ylim=lims[1], xlabel=f"{pset.names[i]} ({pset.priors[i].unit})",
               ylabel=f"{pset.names[j]} ({pset.priors[j].unit})")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="x-small")
    fig.suptitle("exact posterior regions and the filters' final ensembles", fontsize="medium")
    return fig


def log_filter_layout(writer, parameters: list[str], filters: list[str], truth: bool) -> None:
    """A custom-scalars layout (TensorBoard's CUSTOM SCALARS dashboard) putting every filter's curve of a
    parameter on one chart beside the exact posterior's: per parameter its mean, std (and error from the
    truth for a synthetic recording) over the frames, and the filters' innovation checks on two more.

    Parameters
    ----------
    writer : SummaryWriter
        The run's writer.
    parameters : list of str
        The uncertain parameters (the tags' ``<p>_mean/<filter>``).
    filters : list of str
        The filters run, ``exact`` among them.
    truth : bool
        The recording is synthetic (``<p>_abs_error/<filter>`` was logged).
    """
    ensembles = [f for f in filters if f != "exact"]
    per_frame = filters if len(parameters) == 1 else ensembles  # the exact one is logged per frame for one parameter
    charts = {}
    for p in parameters:
        charts[f"{p} mean: the filters and the exact posterior"] = ["Multiline", [f"{p}_mean/{f}" for f in per_frame]]
        charts[f"{p} std: the filters and the exact posterior"] = ["Multiline", [f"{p}_std/{f}" for f in per_frame]]
        if truth:
            charts[f"{p} |mean - truth|"] = ["Multiline", [f"{p}_abs_error/{f}" for f in ensembles]]
    charts["innovation RMS"] = ["Multiline", [f"innovation_rms/{f}" for f in ensembles]]
    charts["NIS over its expectation"] = ["Multiline", [f"nis_over_expectation/{f}" for f in ensembles]]
    writer.add_custom_scalars({"calibration": charts})


def _log_steps(writer, out: dict) -> None:
    t = out["recording"].times
    truth = out["truth"]
    pset = _pset(out)
    for name, f in out["filters"].items():
        if name == "exact":
            post = f["posterior"]
            if pset.d == 1:
                p = pset.names[0]
                for k in range(len(t)):
                    s = post.stats(k + 1)[p]
                    writer.add_scalar(f"{p}_mean/exact", s["mean"], k)
                    writer.add_scalar(f"{p}_std/exact", s["std"], k)
            continue
        res = f["result"]
        for j, k in enumerate(f["frames"]):
            values = pset.natural(res.Q[j + 1])
            for p, c in values.items():
                writer.add_scalar(f"{p}_mean/{name}", float(c.mean()), int(k))
                writer.add_scalar(f"{p}_std/{name}", float(c.std()), int(k))
                if truth is not None:
                    writer.add_scalar(f"{p}_abs_error/{name}", abs(float(c.mean()) - truth[p]), int(k))
                if j % 10 == 9 or j == len(f["frames"]) - 1:
                    writer.add_histogram(f"{p}_ensemble/{name}", c.numpy(), int(k))
            info = res.info[j]
            writer.add_scalar(f"innovation_rms/{name}", info.innovation_rms, int(k))
            writer.add_scalar(f"nis_over_expectation/{name}", info.nis, int(k))
            writer.add_scalar(f"forecast_spread/{name}", info.spread, int(k))
            if "slave_error_tracked" in f:
                writer.add_scalar(f"slave_error_tracked_uy/{name}", float(f["slave_error_tracked"][j, 0]), int(k))
