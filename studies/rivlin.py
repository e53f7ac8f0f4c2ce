"""Mesh-refinement study of the plane-strain Rivlin tube (hybrid Hex20 vs the closed form).

    python studies/rivlin.py [--meshes 1,2,1 2,4,1 ...] [--a-over-A 1.5] [--name rivlin]

Prints a JSON table (mesh, dofs, a_FE, a_exact, rel error, order, Newton iterations, wall_s) and
writes it to runs/<name>/summary.json with TensorBoard scalars (error vs refinement level) beside it.
Model, measure and D1 -> 0 extrapolation: torchfra/verification/tube.py.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

from torchfra.report.tensorboard import open_writer
from torchfra.verification import limit_pressure, pressure_for_inner_radius
from torchfra.verification.tube import refinement_study


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", nargs="+", default=["1,2,1", "2,4,1", "4,8,1", "8,16,1", "16,32,1"],
                    help="divisions n_radial,n_angular,n_axial of each mesh, uniformly refined")
    ap.add_argument("--inner-radius", type=float, default=2.0, help="A (mm)")
    ap.add_argument("--outer-radius", type=float, default=4.0, help="B (mm)")
    ap.add_argument("--C10", type=float, default=0.0048, help="MPa")
    ap.add_argument("--a-over-A", type=float, default=1.5, help="exact inflation a/A that sets the pressure")
    ap.add_argument("--K-over-mu", type=float, nargs=2, default=(1e3, 1e4),
                    help="bulk-to-shear ratios of the two members extrapolated to D1 = 0")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("TORCHFRA_THREADS", "1")))
    ap.add_argument("--name", default="rivlin", help="output folder runs/<name>")
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    A, B, C10 = args.inner_radius, args.outer_radius, args.C10
    P = pressure_for_inner_radius(args.a_over_A * A, A, B, C10)
    try:
        meshes = [tuple(int(v) for v in m.split(",")) for m in args.meshes]
    except ValueError:
        ap.error(f"--meshes takes divisions like 1,2,1 (n_radial,n_angular,n_axial), got {' '.join(args.meshes)}")
    results = refinement_study(A, B, C10, P, meshes, K_over_mu=tuple(args.K_over_mu))

    rows = [
        {
            "mesh": list(r.divisions), "dofs": r.dofs, "a_FE": r.a_fe, "a_exact": r.a_exact,
            "rel_error": r.rel_error, "max_nodal_rel_error": r.max_nodal_rel_error, "order": r.order,
            "a_FE_members": list(r.a_fe_members), "d1_sensitivity": r.d1_sensitivity,
            "newton_iterations": list(r.newton_iterations), "increments": list(r.increments),
            "wall_s": r.wall_s,
        }
        for r in results
    ]
    summary = {
        "problem": {"A_mm": A, "B_mm": B, "C10_MPa": C10, "P_MPa": P, "P_over_limit": P / limit_pressure(A, B, C10),
                    "a_over_A_exact": args.a_over_A, "K_over_mu": list(args.K_over_mu), "threads": args.threads},
        "rows": rows,
    }
    out = Path("runs") / args.name
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    with open_writer(out) as tb:
        for level, row in enumerate(rows):
            tb.add_scalar("rivlin/rel_error", abs(row["rel_error"]), level)
            tb.add_scalar("rivlin/max_nodal_rel_error", row["max_nodal_rel_error"], level)
            if row["order"] is not None:
                tb.add_scalar("rivlin/order", row["order"], level)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
