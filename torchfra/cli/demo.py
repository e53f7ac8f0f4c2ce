"""FEM demo: an ensemble of soft blocks bent by a pressure, all members solved in one batched call.

The block has the actuator body's size (16 x 16 x 60 mm, z along the length), a coarse hybrid Hex20
mesh, an incompressible-like Neo-Hookean body, the base z = 0 clamped and the top z = 60 rigid (flat
and undeformed, free to move and turn). A follower pressure on the long side y = 0 bends the block
towards +y, in the y-z plane the camera of the paper sees. Members differ in C10, drawn lognormal
around the nominal 0.0056 MPa; D1 is one value for all members, set from the ratio K / mu at the
nominal C10 (K = 2 / D1, mu = 2 C10, so K / mu = 1 / (D1 C10)).

    python scripts/fem_demo.py --name fem_demo

writes ``runs/<name>/``: ``summary.json``, TensorBoard events (``tensorboard --logdir runs``),
``deformed.vtu`` (the member whose log C10 is nearest the ensemble mean, with the ensemble mean and
standard deviation of U and element stresses; open in ParaView, Warp By Vector ``U``) and
``tip_displacement.png``. A member that fails keeps its row in the summary with its status.
"""
from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

from torchfra.cli.flags import add_peak_pressure, add_run_folder, add_threads, parser

BODY_SIZE_MM = (16.0, 16.0, 60.0)


def parse_args(argv=None) -> argparse.Namespace:
    p = parser(__doc__.split("\n\n")[0])
    add_run_folder(p, "fem_demo", "outputs")
    p.add_argument("--members", type=int, default=8, help="ensemble members (C10 samples)")
    p.add_argument("--divisions", default="2,2,6",
                   help="Hex20 elements along x,y,z of the block (a box mesh: the actuator's --resolution does not "
                        "apply here)")
    add_peak_pressure(p, 2e-4, "follower pressure on y = 0 at load factor 1 (MPa)")
    p.add_argument("--c10", type=float, default=0.0056, help="median C10 of the ensemble (MPa)")
    p.add_argument("--c10-sigma", type=float, default=0.2, help="standard deviation of log C10")
    p.add_argument("--bulk-ratio", type=float, default=1000.0, help="K / mu at the median C10: D1 = 1 / (ratio C10)")
    p.add_argument("--load-steps", type=int, default=10, help="output load factors 1/n, 2/n, ..., 1")
    p.add_argument("--seed", type=int, default=0, help="seed of the C10 draws")
    add_threads(p)
    args = p.parse_args(argv)
    try:
        args.divisions = tuple(int(d) for d in args.divisions.split(","))
    except ValueError:
        p.error(f"--divisions must be three integers like 2,2,6, got {args.divisions!r}")
    if len(args.divisions) != 3 or min(args.divisions) < 1:
        p.error(f"--divisions must be three positive integers like 2,2,6, got {args.divisions}")
    for name in ("members", "load_steps", "threads"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be at least 1")
    if not (args.peak_pressure > 0 and args.c10 > 0 and args.c10_sigma >= 0 and args.bulk_ratio > 0):
        p.error("--pressure, --c10 and --bulk-ratio must be positive and --c10-sigma non-negative")
    return args


def build_model(divisions):
    from torchfra import fem
    from torchfra.fem.structured import box_mesh

    mesh = box_mesh(BODY_SIZE_MM, divisions)
    model = fem.Model(mesh)
    solid = model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), integration="reduced"))  # C3D20RH, the paper's
    model.add(fem.FollowerPressure(mesh, "ymin", pressure="P"))
    model.clamp("zmin")
    model.rigid("zmax")
    return mesh, model, solid


def main(argv=None) -> dict:
    t_start = time.perf_counter()
    args = parse_args(argv)
    import numpy as np
    import torch

    from torchfra import fem
    from torchfra.io.vtu import element_fields, write_vtu
    from torchfra.report import tensorboard as tb

    torch.set_num_threads(args.threads)
    run_dir = Path(args.runs_dir) / args.name
    run_dir.mkdir(parents=True, exist_ok=True)

    mesh, model, solid = build_model(args.divisions)
    N = args.members
    gen = torch.Generator().manual_seed(args.seed)
    C10 = args.c10 * torch.exp(args.c10_sigma * torch.randn(N, generator=gen, dtype=torch.float64))
    D1 = 1.0 / (args.bulk_ratio * args.c10)
    params = {"C10": C10, "D1": torch.full((N,), D1), "P": torch.full((N,), args.peak_pressure)}
    load_factors = np.arange(1, args.load_steps + 1) / args.load_steps

    t0 = time.perf_counter()
    sol = fem.solve(model, params, load_factors, fem.NewtonOptions(), progress=True)
    solve_wall = time.perf_counter() - t0

    top = mesh.node_set("zmax")
    tip = sol.u[:, :, top].mean(dim=2)  # (N, T, 3): the rigid top moves as one, its centroid is the tip
    final_ok = torch.isfinite(tip[:, -1]).all(dim=1)

    writer = tb.open_writer(run_dir)
    tb.log_solution(writer, sol)
    for m in range(N):
        for k in range(len(load_factors)):  # step = output load step 1..T; a member's line ends where it stopped
            if torch.isfinite(tip[m, k]).all():
                for comp, axis in ((1, "uy"), (2, "uz")):
                    writer.add_scalar(f"tip_{axis}_mm/member_{m:0{len(str(N - 1))}d}", float(tip[m, k, comp]), k + 1)

    rep, vtu_path = None, None
    if final_ok.any():
        logc = torch.log(C10)
        distance = torch.where(final_ok, (logc - logc[final_ok].mean()).abs(), torch.inf)
        rep = int(torch.argmin(distance))
        u_ok = sol.u[final_ok, -1]
        fields = element_fields(solid, sol.u[rep : rep + 1, -1], {k: v[rep : rep + 1] for k, v in params.items()})
        vtu_path = write_vtu(
            run_dir / "deformed.vtu", model, sol.u[rep, -1],
            point_data={"U_ensemble_mean": u_ok.mean(0), "U_ensemble_std": u_ok.std(0, correction=0)},
            cell_data={k: v[0] for k, v in fields.items()},
        )
        for k in range(len(load_factors)):
            tb.log_mesh(writer, "deformed_surface", mesh, sol.u[rep, k], step=k + 1)

    # the undeformed state opens every curve, so the curvature of the load path shows from zero
    lf0 = np.concatenate([[0.0], load_factors])
    tip0 = torch.cat([torch.zeros(N, 1, 3, dtype=tip.dtype), tip], dim=1)
    fig = tb.curves_figure(
        lf0, {"tip displacement u_y (mm)": tip0[:, :, 1], "tip displacement u_z (mm)": tip0[:, :, 2]},
        labels=[f"C10 = {float(c):.4f} MPa" for c in C10], xlabel="load factor",
        title=f"{N} members, follower pressure {args.peak_pressure:g} MPa on y = 0", failed=~sol.converged,
    )
    if rep is not None:  # u_y is first order in the load: show how far it bends away from linear
        ax = fig.axes[0]
        ax.plot([0, 1], [0, float(tip[rep, 0, 1]) / load_factors[0]], ":", color="gray",
                label=f"member {rep}, linear from the first step")
        ax.legend(fontsize="small")
    png_path = run_dir / "tip_displacement.png"
    tb.log_figure(writer, "tip_displacement", fig, path=png_path)

    tip_final = tip[final_ok, -1]
    wall = time.perf_counter() - t_start
    summary = {
        "name": args.name,
        "command": shlex.join(["python", "scripts/fem_demo.py", *(sys.argv[1:] if argv is None else argv)]),
        "members": N,
        "members_converged": int(sol.converged.sum()),
        "elements": mesh.n_elements,
        "nodes": mesh.n_nodes,
        "dofs": model.n_red,
        "load_steps": len(load_factors),
        "load_factors": load_factors.tolist(),
        "pressure_MPa": args.peak_pressure,
        "C10_median_MPa": args.c10,
        "C10_log_sigma": args.c10_sigma,
        "D1_per_MPa": D1,
        "K_over_mu": {
            "at_median_C10": args.bulk_ratio, "min": float(1 / (D1 * C10.max())), "max": float(1 / (D1 * C10.min()))
        },
        "seed": args.seed,
        "threads": torch.get_num_threads(),
        "newton_iterations_total": int(sol.iterations.sum()),
        "newton_iterations_max": int(sol.iterations.max()),  # members iterate in lockstep: this sets the cost
        "increments_total": int(sol.increments.sum()),
        "cutbacks_total": int(sol.cutbacks.sum()),
        "solve_wall_s": solve_wall,
        "solver_timings_s": {k: float(v) for k, v in sol.timings.items()},
        "tip_displacement_mean_mm": _clean(tip_final.mean(0)) if tip_final.numel() else None,
        "tip_displacement_std_mm": _clean(tip_final.std(0, correction=0)) if tip_final.numel() else None,
        "vtu_member": rep,
        "files": {"vtu": vtu_path.name if vtu_path else None, "figure": png_path.name},
        "member_results": [
            {
                "member": m,
                "C10_MPa": float(C10[m]),
                "status": str(sol.status[m]),
                "load_reached": float(sol.load_reached[m]),
                "iterations": int(sol.iterations[m]),
                "increments": int(sol.increments[m]),
                "cutbacks": int(sol.cutbacks[m]),
                "last_residual": _clean(sol.last_residual[m]),
                "tip_displacement_mm": _clean(tip[m, -1]),
                "tip_uy_path_mm": _clean(tip[m, :, 1]),
                "tip_uz_path_mm": _clean(tip[m, :, 2]),
            }
            for m in range(N)
        ],
        "wall_s": wall,
    }
    tb.log_hparams(
        writer,
        {"members": N, "divisions": args.divisions, "pressure_MPa": args.peak_pressure, "C10_median_MPa": args.c10,
         "C10_log_sigma": args.c10_sigma, "bulk_ratio": args.bulk_ratio, "seed": args.seed,
         "threads": summary["threads"]},
        {"hparam/members_converged": summary["members_converged"], "hparam/wall_s": wall,
         "hparam/newton_iterations_total": summary["newton_iterations_total"],
         "hparam/tip_uy_mean_mm": summary["tip_displacement_mean_mm"][1] if tip_final.numel() else math.nan},
    )
    writer.close()
    summary["wall_s"] = time.perf_counter() - t_start
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{summary['members_converged']}/{N} members converged, {summary['newton_iterations_total']} Newton "
          f"iterations, solve {solve_wall:.1f} s, total {wall:.1f} s -> {run_dir}")
    return summary


def _clean(x):
    """Tensor/array/number -> JSON value; NaN (a load not reached) becomes null."""
    import numpy as np
    import torch

    a = np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float64)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_clean(v) for v in a]



if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
