"""TensorBoard logging of runs: Newton solutions, deformed meshes, hyperparameters, figures.

Everything goes through one ``torch.utils.tensorboard.SummaryWriter`` writing into the run folder
(``runs/<name>/``), so ``tensorboard --logdir runs`` shows every run side by side. Tags:

- ``newton/residual/member_<m>``: relative residual of every Newton iteration of member m
  (step = iteration count of that member; switch the y-axis to log scale);
- ``newton/iterations``, ``increments``, ``cutbacks``, ``load_reached``, ``last_residual``:
  one point per member (step = member index); ``newton/members_converged``;
- ``newton/timing_s/<phase>``: seconds spent in residuals, tangents and linear solves;
- ``newton/status`` (text): a table with one row per member; failed members are listed, never dropped.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot state, no display needed).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib.figure import Figure
from torch.utils.tensorboard import SummaryWriter
from torch.utils.tensorboard.summary import hparams as hparams_summary

from torchfra.fem.elements import HEX20_FACES
from torchfra.fem.mesh import Mesh
from torchfra.fem.newton import Solution

# A Quad8 face (corners 0-3, mid-edge nodes 4-7) as 6 triangles with the face's own orientation:
# four corner triangles and the inner quad of mid-edge nodes, so curved edges show.
_QUAD8_TRIANGLES = np.array([[0, 4, 7], [1, 5, 4], [2, 6, 5], [3, 7, 6], [4, 5, 6], [4, 6, 7]])


def open_writer(run_dir: str | Path) -> SummaryWriter:
    """A SummaryWriter writing event files directly into ``run_dir``."""
    return SummaryWriter(log_dir=str(run_dir))


def log_solution(writer: SummaryWriter, solution: Solution, tag: str = "newton") -> None:
    """Log the Newton record of every member of ``solution`` (see the module docstring for tags)."""
    log_newton_records(writer, vars(solution), tag)


_RECORDS = ("iterations", "increments", "cutbacks", "load_reached", "last_residual")


def log_newton_records(writer: SummaryWriter, records: dict, tag: str = "newton") -> None:
    """The same from per-member arrays: ``status``, ``residual_history``, ``timings`` and the
    ``_RECORDS`` (a ``Solution``'s fields, or a forward run's records gathered over its chunks)."""
    status = np.asarray(records["status"])
    width = len(str(max(len(status) - 1, 0)))
    for m, history in enumerate(records["residual_history"]):
        for k, value in enumerate(np.asarray(history, dtype=np.float64)):
            writer.add_scalar(f"{tag}/residual/member_{m:0{width}d}", value, k)
    for name in _RECORDS:
        for m, value in enumerate(np.asarray(records[name], dtype=np.float64)):
            writer.add_scalar(f"{tag}/{name}", value, m)
    writer.add_scalar(f"{tag}/members_converged", int(np.sum(status == "converged")), 0)
    for phase, seconds in records["timings"].items():
        writer.add_scalar(f"{tag}/timing_s/{phase}", seconds, 0)
    writer.add_text(f"{tag}/status", status_table(records), 0)


def status_table(records) -> str:
    """Markdown table, one row per member: status, load reached, iterations, increments, cutbacks,
    last relative residual. ``records``: a ``Solution`` or a dict of its per-member fields."""
    r = records if isinstance(records, dict) else vars(records)
    rows = [
        "| member | status | load reached | iterations | increments | cutbacks | last residual |",
        "|---|---|---|---|---|---|---|",
    ]
    for m, status in enumerate(r["status"]):
        rows.append(
            f"| {m} | {status} | {r['load_reached'][m]:.4g} | {r['iterations'][m]} | "
            f"{r['increments'][m]} | {r['cutbacks'][m]} | {r['last_residual'][m]:.2e} |"
        )
    return "\n".join(rows)


def boundary_triangles(mesh: Mesh) -> np.ndarray:
    """Outer surface of a Hex20 mesh as triangles (F, 3) of node indices, outward normals.

    A brick face is on the boundary when no other brick shares its four corners; each such Quad8
    is split into 6 triangles using its corner and mid-edge nodes.
    """
    faces = mesh.elements[:, HEX20_FACES].reshape(-1, 8)  # (6E, 8), node order of HEX20_FACES
    keys = np.sort(faces[:, :4], axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    outer = faces[counts[inverse.ravel()] == 1]
    # The HEX20_FACES order gives x_s x x_t pointing into the brick: reverse for outward normals.
    return outer[:, _QUAD8_TRIANGLES][..., ::-1].reshape(-1, 3)


def log_mesh(
    writer: SummaryWriter,
    tag: str,
    mesh: Mesh,
    u=None,
    values=None,
    step: int = 0,
    colormap: str = "viridis",
) -> None:
    """Log the (deformed) outer surface of a Hex20 mesh for TensorBoard's mesh dashboard.

    u: (n, 3) displacements in mm, n >= mesh.n_nodes (extra model nodes such as fiber nodes come
    after the mesh nodes and are ignored); values: (n,) nodal scalars for the colors (default: the
    displacement magnitude), mapped with a matplotlib colormap.
    """
    from matplotlib import colormaps

    tri = boundary_triangles(mesh)
    used, local = np.unique(tri, return_inverse=True)
    x = mesh.nodes[used]
    disp = np.zeros_like(x) if u is None else _numpy(u)[: mesh.n_nodes][used]
    x = x + disp
    v = np.linalg.norm(disp, axis=1) if values is None else _numpy(values)[: mesh.n_nodes][used]
    span = np.nanmax(v) - np.nanmin(v) if v.size else 0.0
    t = (v - np.nanmin(v)) / span if span > 0 else np.zeros_like(v)
    colors = (255 * colormaps[colormap](np.nan_to_num(t))[:, :3]).astype(np.uint8)
    writer.add_mesh(
        tag,
        vertices=torch.as_tensor(x, dtype=torch.float32)[None],
        faces=torch.as_tensor(local.reshape(-1, 3), dtype=torch.int32)[None],
        colors=torch.as_tensor(colors)[None],
        global_step=step,
    )


def log_hparams(writer: SummaryWriter, hparams: dict, metrics: dict) -> None:
    """Record the run's settings and headline numbers for TensorBoard's HParams dashboard.

    Written into the writer's own event file (``add_hparams`` would open a sub-folder); values that
    are not numbers, strings or booleans are stored as their ``str``.
    """
    clean = {k: v if isinstance(v, (bool, int, float, str)) else str(v) for k, v in hparams.items()}
    metrics = {k: float(v) for k, v in metrics.items()}
    for summary in hparams_summary(clean, metrics):
        writer.file_writer.add_summary(summary)
    for k, v in metrics.items():
        writer.add_scalar(k, v, 0)


def curves_figure(
    x,
    panels: dict,
    labels=None,
    xlabel: str = "",
    title: str = "",
    failed=None,
) -> Figure:
    """Side-by-side panels of curves against ``x``: ``panels`` maps a y-axis label to an array
    (k, len(x)) with one row per curve (e.g. per member); NaN ends a line (a member that stopped).
    Rows flagged in ``failed`` (k,) bool are dashed and marked with x where they stopped."""
    x = _numpy(x)
    fig = Figure(figsize=(5.0 * len(panels), 4.0), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (ylabel, curves) in zip(axes, panels.items()):
        curves = np.atleast_2d(_numpy(curves))
        bad = np.zeros(curves.shape[0], dtype=bool) if failed is None else np.asarray(failed, dtype=bool)
        for i, y in enumerate(curves):
            label = None if labels is None else labels[i]
            line, = ax.plot(x, y, ls="--" if bad[i] else "-", marker=".", label=label)
            if bad[i] and np.isfinite(y).any():
                last = np.flatnonzero(np.isfinite(y))[-1]
                ax.plot(x[last], y[last], "x", color=line.get_color(), ms=9)
        ax.set(xlabel=xlabel, ylabel=ylabel)
        ax.grid(True, alpha=0.3)
    if labels is not None and len(labels) <= 12:
        axes[0].legend(fontsize="small")
    fig.suptitle(title)
    return fig


def log_figure(writer: SummaryWriter, tag: str, fig: Figure, path: str | Path | None = None, step: int = 0) -> None:
    """Save ``fig`` as an image at ``path`` (if given, e.g. a PNG in the run folder) and log it."""
    if path is not None:
        fig.savefig(path, dpi=120)
    writer.add_figure(tag, fig, step, close=False)


def _numpy(values) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)
