"""Files of a forward-ensemble run: ``forward.npz``, ``summary.json``, TensorBoard, VTU, figures."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure

from torchfra.io.vtu import element_fields, write_vtu
from torchfra.report.tensorboard import log_figure, log_hparams, log_mesh, log_newton_records, open_writer

TRACKED_YZ = (0.0, 40.0)  # mm: the node the paper plots (front face, top centre of the cavity span)


def band_figure(times, trajectories, labels, title: str, truth=None) -> Figure:
    """10-90 % bands and means over time. trajectories: list of (N, T) arrays, one panel each."""
    fig = Figure(figsize=(5.0 * len(trajectories), 3.8), layout="constrained")
    axes = fig.subplots(1, len(trajectories), squeeze=False)[0]
    for ax, values, label in zip(axes, trajectories, labels):
        values = np.asarray(values)
        lo, hi = np.nanpercentile(values, [10, 90], axis=0)
        ax.fill_between(times, lo, hi, alpha=0.3, label="10-90 %")
        ax.plot(times, np.nanmean(values, axis=0), label="mean")
        ax.set(xlabel="normalized time t", ylabel=label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize="small")
    fig.suptitle(title)
    return fig


def write_forward_outputs(result: dict, config, run_dir: str | Path) -> dict:
    """Write every file of the run and return the summary dict."""
    run_dir = Path(run_dir)
    model, op, mesh = result["model"], result["operator"], result["model"].mesh
    params = {k: v.numpy() for k, v in result["params"].items()}
    names = list(params)
    converged = result["status"] == "converged"
    if getattr(config, "inp", ""):  # a deck: the observed point that moves most on average
        final = np.linalg.norm(result["Y_fe"][converged, -1], axis=-1)
        tracked = int(np.nanargmax(np.nanmean(final, axis=0))) if converged.any() else 0
    else:
        tracked = op.nearest_point(*TRACKED_YZ)
    at = np.round(op.points[tracked, 1:], 3).tolist()
    np.savez(
        run_dir / "forward.npz",
        times=result["times"], pressure=result["pressure"], param_names=np.array(names),
        params=np.stack([params[k] for k in names], axis=1), points=op.points, point_ids=op.point_ids,
        Y=result["Y_fe"], status=result["status"], tracked_point_index=tracked,
    )
    Y_tr = result["Y_fe"][:, :, tracked]  # (N, T, 2)
    summary = {
        "members": int(config.members),
        "members_converged": int(converged.sum()),
        "members_failed": [int(m) for m in np.flatnonzero(~converged)],
        "elements": int(mesh.n_elements),
        "fiber_elements": int(result["info"]["fiber_elements"]),
        "nodes": int(model.n_nodes),
        "dofs": int(model.n_red),
        "observation_points": int(op.n_points),
        "frames": int(len(result["times"])),
        "load_steps": int(config.load_steps),
        "newton_iterations_total": int(result["iterations"].sum()),
        "newton_iterations_max": int(result["iterations"].max()),
        "cutbacks_total": int(result["cutbacks"].sum()),
        "wall_s": float(result["wall_s"]),
        "method": config.method,
        "members_reduced": int((result["method"] == "reduced").sum()),
        "members_full": [int(m) for m in np.flatnonzero(result["method"] == "full")],
        "reduced_error_estimate_max_mm": (float(np.nanmax(result["error_estimate"][result["method"] == "reduced"]))
                                          if (result["method"] == "reduced").any() else None),
        "solver_timings_s": result["timings"],
        "threads": int(torch.get_num_threads()),
        "tracked_point": {"id": int(op.point_ids[tracked]), "X": op.points[tracked].tolist()},
        "tracked_displacement_mean": np.nanmean(Y_tr[converged, -1], axis=0).tolist(),
        "tracked_displacement_p10_p90": np.nanpercentile(Y_tr[converged, -1], [10, 90], axis=0).tolist(),
        "C10": {"mean": float(params["C10"].mean()), "std": float(params["C10"].std(ddof=1))},
        "parameters": {k: {"mean": float(np.mean(v)), "std": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0,
                           "min": float(np.min(v)), "max": float(np.max(v))} for k, v in params.items()},
        "config": asdict(config),
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))

    writer = open_writer(run_dir)
    log_newton_records(writer, {**result, "residual_history": result["history"]})
    fig = band_figure(result["times"], [Y_tr[converged, :, 0], Y_tr[converged, :, 1]],
                      ["tracked u_y (mm)", "tracked u_z (mm)"],
                      f"prior ensemble, {int(converged.sum())} members, node at (y, z) = {at} mm")
    log_figure(writer, "forward/tracked_node", fig, run_dir / "tracked_node.png")
    u_mean = result["u_last"][converged].mean(axis=0)
    log_mesh(writer, "forward/mean_deformed", mesh, u_mean)
    log_hparams(writer, {k: (" ".join(v) if isinstance(v, list) else v) for k, v in asdict(config).items()
                         if k != "newton"},
                {"summary/members_converged": summary["members_converged"], "summary/wall_s": summary["wall_s"]})
    writer.close()

    solid = model.terms[0]
    mean_params = {k: torch.tensor([float(np.mean(v))]) for k, v in params.items()}
    fields = element_fields(solid, torch.as_tensor(u_mean)[None], mean_params)
    write_vtu(run_dir / "mean_deformed.vtu", model, u_mean,
              cell_data={k: v[0].numpy() for k, v in fields.items()})
    return summary
