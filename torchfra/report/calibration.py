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

from ..assimilation import summarize
from ..calibration import forward_config
from ..forward import lognormal_parameters
from .tensorboard import log_figure, log_hparams, open_writer

LABELS = {"hierarchical": "hierarchical (paper, linear slave)", "hierarchical_nonlinear": "hierarchical, polynomial slave",
          "restart": "restart EnKF (FE re-solves)", "exact": "exact (grid)"}
COLORS = {"prior": "tab:red", "hierarchical": "tab:blue", "hierarchical_nonlinear": "tab:green",
          "restart": "tab:orange", "exact": "black"}


def filter_summary(out: dict) -> dict:
    rows = {}
    N = out["Q0"].shape[0]
    for name, f in out["filters"].items():
        if name == "exact":
            post = f["posterior"]
            rows[name] = {"C10": post.stats(), "prior_mass_outside_grid": post.prior_mass_outside,
                          "posterior_mass_in_end_cells": post.edge_mass(), "fe_solves": 0, "newton_iterations": 0, "wall_s": f["wall_s"],
                          "log_evidence": float(post.log_evidence[-1]), "frames_assimilated": int(len(f["frames"])),
                          "note": f"grid of {len(post.q)} points; FE map: cubic spline through the {N} forward "
                                  "members (a parameter sweep); no FE solve beyond the forward ensemble"}
            continue
        res = f["result"]
        row = {"C10": summarize(torch.exp(res.Q[-1][:, 0])), "fe_solves": int(res.fe_solves),
               "newton_iterations": int(res.newton_iterations), "wall_s": float(res.wall_s),
               "log_evidence": res.log_evidence, "frames_assimilated": int(len(f["frames"]))}
        if "slave_error_tracked" in f:
            err = f["slave_error_tracked"]
            row["slave_error_tracked_max_mm"] = float(err.max())
            row["slave_error_tracked_last_mm"] = err[-1].tolist()
        rows[name] = row
    return rows


def comparisons(out: dict, rows: dict) -> dict:
    """Each filter against the exact posterior (same frames) and the truth."""
    exact_all = out["filters"]["exact"]["posterior"].stats()
    comp = {}
    for name, row in rows.items():
        ref = exact_all
        ev = out["filters"]["exact"]["posterior"].log_evidence[-1]
        if name == "restart":
            ref = out["exact_restart_frames"].stats()
            ev = out["exact_restart_frames"].log_evidence[-1]
        c = row["C10"]
        d = {"exact_mean_same_frames": ref["mean"], "exact_std_same_frames": ref["std"],
             "distance_from_exact_mean_in_exact_stds": (c["mean"] - ref["mean"]) / ref["std"],
             "spread_ratio_to_exact": c["std"] / ref["std"],
             "exact_log_evidence_same_frames": float(ev), "exact_same_frames": ref}
        if out["truth"] is not None:
            d["error_from_truth_percent"] = 100 * (c["mean"] - out["truth"]) / out["truth"]
        comp[name] = d
    return comp


def write_calibration_outputs(out: dict, run_dir, wall_s: float) -> dict:
    run_dir = Path(run_dir)
    cfg = out["config"]
    fwd = out["forward"]
    rec = out["recording"]
    rows = filter_summary(out)
    c10_prior = torch.exp(out["Q0"][:, 0])
    fc = forward_config(cfg)
    mu, sigma = lognormal_parameters(fc.c10_mean, fc.c10_std)
    summary = {
        "members": int(cfg.members),
        "members_in_hierarchical_filters": int(out["Q0"].shape[0]),
        "frames": int(rec.n_frames),
        "observation_points": int(rec.n_points),
        "observations": int(np.isfinite(rec.Z).sum()),
        "truth": None if out["truth"] is None else {"C10": out["truth"]},
        "prior": {"C10": {"mean": fc.c10_mean, "std": fc.c10_std, "sample": summarize(c10_prior)}},
        "filters": rows,
        "comparison": comparisons(out, rows),
        "forward": {"resolution": cfg.resolution, "dofs": int(fwd["model"].n_red),
                    "newton_iterations_total": int(fwd["iterations"].sum()), "member_solves": int(len(fwd["status"])),
                    "solver_time_s": float(sum(fwd["timings"].values())),
                    "members_failed": [{"member": int(m), "C10": float(fwd["params"]["C10"][m]),
                                        "load_reached": float(fwd["load_reached"][m])}
                                       for m in np.flatnonzero(fwd["status"] != "converged")],
                    "members_converged": int((fwd["status"] == "converged").sum())},
        "exact_interpolation_loo_error_mm": float(out["sweep_loo_error"]),
        "noise_std_mm": cfg.noise,
        "tracked_point": out["tracked_point"],
        "config": asdict(cfg),
        "wall_s": wall_s,
        "threads": torch.get_num_threads(),
    }
    if "data_fit" in out:
        summary["data_fit"] = out["data_fit"]
    if "restart_threads" in out:
        summary["restart_threads"] = out["restart_threads"]
    summary["direct_fe_check"] = out["direct_fe_check"]
    summary["polynomial_slave"] = {"degree": out["slave_degree"], "leave_one_out_rms_mm": out["slave_loo_rms_mm"]}
    if "restart_spline_check" in out:
        summary["restart_spline_check"] = out["restart_spline_check"]
    if "coverage" in out:
        summary["coverage"] = out["coverage"]
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))

    writer = open_writer(run_dir)
    log_figure(writer, "calibration/bands", bands_figure(out), run_dir / "bands.png")
    log_figure(writer, "calibration/pdfs", pdf_figure(out, mu, sigma), run_dir / "pdfs.png")
    _log_steps(writer, out)
    metrics = {f"final/{n}/C10_mean": r["C10"]["mean"] for n, r in rows.items()}
    metrics.update({f"final/{n}/log_evidence": r["log_evidence"] for n, r in rows.items()})
    log_hparams(writer, {"members": summary["members"], "frames": summary["frames"], "resolution": cfg.resolution,
                         "noise": cfg.noise, "degree": out["slave_degree"], "restart_every": cfg.restart_every,
                         "recording": str(cfg.recording)}, metrics)
    writer.close()
    return summary


def _band(ax, t, values, color, label):
    lo, hi = np.nanpercentile(values, [10, 90], axis=1)
    ax.fill_between(t, lo, hi, color=color, alpha=0.2, lw=0)
    ax.plot(t, np.nanmean(values, axis=1), color=color, label=label)


def bands_figure(out: dict) -> Figure:
    """Tracked node y, z and C10 over time: 10-90 % bands and means, prior vs each filter."""
    rec = out["recording"]
    t = rec.times
    row = out["tracked_row"]
    fig = Figure(figsize=(15, 4.2), layout="constrained")
    axes = fig.subplots(1, 3)
    prior_Y = out["Y_fe"][:, :, row, :]  # (N, K, 2)
    for c, ax in enumerate(axes[:2]):
        _band(ax, t, prior_Y[:, :, c].T, COLORS["prior"], "prior (forward ensemble)")
        for name, f in out["filters"].items():
            if name == "exact":
                continue
            res = f["result"]
            Ytr = torch.stack(res.Y_tracked).numpy()[:, :, c]  # (steps, N)
            _band(ax, t[f["frames"]], Ytr, COLORS[name], LABELS[name] + " forecast")
        ax.plot(t, rec.Z[:, row, c], ".", ms=3, color="0.4", label="observations")
        ax.set(xlabel="normalized time t", ylabel=f"u{'yz'[c]} of the tracked point (mm)")
        ax.grid(True, alpha=0.3)
    ax = axes[2]
    prior = np.exp(out["Q0"][:, 0].numpy())
    ax.fill_between(t, *np.percentile(prior, [10, 90]), color=COLORS["prior"], alpha=0.15, lw=0)
    ax.plot(t, np.full_like(t, prior.mean()), color=COLORS["prior"], label="prior")
    for name, f in out["filters"].items():
        if name == "exact":
            post = f["posterior"]
            st = [post.stats(k + 1) for k in range(len(t))]
            ax.plot(t, [s["mean"] for s in st], color="k", label=LABELS[name])
            ax.plot(t, [s["p10"] for s in st], "k:", lw=0.8)
            ax.plot(t, [s["p90"] for s in st], "k:", lw=0.8)
            continue
        C = torch.exp(torch.stack(f["result"].Q[1:])[:, :, 0]).numpy()  # (steps, N)
        _band(ax, t[f["frames"]], C, COLORS[name], LABELS[name])
    if out["truth"] is not None:
        ax.axhline(out["truth"], color="k", ls="--", lw=1, label="truth")
    ax.set(xlabel="normalized time t", ylabel="C10 (MPa)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="x-small")
    axes[0].legend(fontsize="x-small")
    fig.suptitle(f"10-90 % bands and means; tracked point (y, z) = ({out['tracked_point'][1]:.1f}, "
                 f"{out['tracked_point'][2]:.1f}) mm")
    return fig


def pdf_figure(out: dict, mu: float, sigma: float) -> Figure:
    """Prior and posterior densities of C10 with the truth as a vertical line."""
    from scipy.stats import gaussian_kde

    fig = Figure(figsize=(11, 4.2), layout="constrained")
    ax_all, ax_zoom = fig.subplots(1, 2)
    x = np.linspace(0.002, 0.011, 800)
    prior_pdf = np.exp(-0.5 * ((np.log(x) - mu) / sigma) ** 2) / (x * sigma * math.sqrt(2 * math.pi))
    ax_all.plot(x, prior_pdf, color=COLORS["prior"], label="prior")
    post = out["filters"]["exact"]["posterior"]
    xe, pe = post.density()
    st = post.stats()
    lo, hi = st["mean"] - 8 * st["std"], st["mean"] + 8 * st["std"]
    for name, f in out["filters"].items():
        if name == "exact":
            continue
        c = torch.exp(f["result"].Q[-1][:, 0]).numpy()
        lo, hi = min(lo, c.min()), max(hi, c.max())
    xz = np.linspace(lo, hi, 600)
    for ax in (ax_all, ax_zoom):
        ax.plot(xe, pe, color="k", label=LABELS["exact"])
        if "exact_restart_frames" in out:
            xr, pr = out["exact_restart_frames"].density()
            ax.plot(xr, pr, "k:", label="exact, on the restart filter's frames")
        for name, f in out["filters"].items():
            if name == "exact":
                continue
            c = torch.exp(f["result"].Q[-1][:, 0]).numpy()
            xs = np.union1d(x, xz) if ax is ax_all else xz  # resolve the narrow posteriors on the wide axis
            note = f", {len(f['frames'])} frames" if len(f["frames"]) != len(out["recording"].times) else ""
            ax.plot(xs, gaussian_kde(c)(xs), color=COLORS[name], ls="--", label=f"{LABELS[name]} (KDE{note})")
        if out["truth"] is not None:
            ax.axvline(out["truth"], color="k", lw=1)
        ax.set(xlabel="C10 (MPa)", ylabel="density")
        ax.grid(True, alpha=0.3)
    ax_all.set_xlim(x[0], x[-1])
    ax_all.set_yscale("log")  # the prior is ~100x lower than the posteriors
    ax_all.set_ylim(prior_pdf.max() * 1e-2, pe.max() * 3)
    ax_all.set_title("prior and posteriors (log scale)")
    ax_zoom.set_xlim(lo, hi)
    ax_zoom.set_title("zoom on the posteriors")
    ax_all.legend(fontsize="x-small")
    return fig


def _log_steps(writer, out: dict) -> None:
    t = out["recording"].times
    truth = out["truth"]
    for name, f in out["filters"].items():
        if name == "exact":
            post = f["posterior"]
            for k in range(len(t)):
                s = post.stats(k + 1)
                writer.add_scalar("C10_mean/exact", s["mean"], k)
                writer.add_scalar("C10_std/exact", s["std"], k)
            continue
        res = f["result"]
        for j, k in enumerate(f["frames"]):
            c = torch.exp(res.Q[j + 1][:, 0])
            writer.add_scalar(f"C10_mean/{name}", float(c.mean()), int(k))
            writer.add_scalar(f"C10_std/{name}", float(c.std()), int(k))
            info = res.info[j]
            writer.add_scalar(f"innovation_rms/{name}", info.innovation_rms, int(k))
            writer.add_scalar(f"nis_over_expectation/{name}", info.nis, int(k))
            writer.add_scalar(f"forecast_spread/{name}", info.spread, int(k))
            if truth is not None:
                writer.add_scalar(f"C10_abs_error/{name}", abs(float(c.mean()) - truth), int(k))
            if "slave_error_tracked" in f:
                writer.add_scalar(f"slave_error_tracked_uy/{name}", float(f["slave_error_tracked"][j, 0]), int(k))
            if j % 10 == 9 or j == len(f["frames"]) - 1:
                writer.add_histogram(f"C10_ensemble/{name}", c.numpy(), int(k))
