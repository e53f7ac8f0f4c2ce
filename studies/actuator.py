"""Mesh study of the actuator at full pressure: one member (C10 = 1.1 kappa_t) per resolution.

    python studies/actuator.py --resolutions 1 2 3 --out actuator_study

writes runs/<out>/summary.json with, per resolution: elements, fiber elements, dofs, Newton
iterations, wall time, tracked-node displacement (y, z) at t = 1, tip rotation (deg), cavity
volume change, and the relative change of the tracked displacement against the finest mesh.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import KAPPA_T
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.fem.constraints import rotation_matrix


def solve_resolution(resolution: int, pressure: float, bulk_ratio: float, integration: str) -> dict:
    model, info = build_actuator_model(ActuatorGeometry(resolution=resolution), integration=integration)
    C10 = torch.tensor([1.1 * KAPPA_T])
    params = {"C10": C10, "D1": 1.0 / (bulk_ratio * C10), "E_fiber": torch.tensor([31000.0]), "P": torch.tensor([pressure])}
    t0 = time.perf_counter()
    sol = fem.solve(model, params, [0.5, 1.0], fem.NewtonOptions(stagnation_tol=1e-6), progress=True)
    wall = time.perf_counter() - t0
    u = sol.u[0, -1]
    theta = sol.a[0, -1, -3:]
    R = rotation_matrix(theta).numpy()
    cavity = next(t for t in model.terms if isinstance(t, fem.CavityPressure))
    V = cavity.cavity_volume(torch.stack([torch.zeros_like(u), u])).numpy()
    truss = next(t for t in model.terms if isinstance(t, fem.Truss))
    return {
        "resolution": resolution, "integration": integration, "elements": info["elements"], "fiber_elements": info["fiber_elements"],
        "dofs": model.n_red, "status": str(sol.status[0]), "iterations": int(sol.iterations[0]),
        "increments": int(sol.increments[0]), "cutbacks": int(sol.cutbacks[0]), "wall_s": wall,
        "timings_s": sol.timings,
        "tracked_u_yz_mm": u[info["tracked_node"], 1:].tolist(),
        "top_mean_u_mm": u[model.mesh.node_sets["top"]].mean(0).tolist(),
        "tip_rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))),
        "tip_rotation_vector_rad": theta.tolist(),
        "cavity_volume_mm3": {"reference": float(V[0]), "full_pressure": float(V[1])},
        "fiber_strain_max": float(truss.axial_strain(u[None]).abs().max()),
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolutions", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--pressure", type=float, default=0.022)
    p.add_argument("--bulk-ratio", type=float, default=1000.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--integration", choices=["full", "reduced"], default="full", help="Hex20 Gauss rule")
    p.add_argument("--out", default="actuator_study")
    p.add_argument("--runs-dir", default="runs")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    run_dir = Path(a.runs_dir) / a.out
    run_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for r in a.resolutions:
        rows.append(solve_resolution(r, a.pressure, a.bulk_ratio, a.integration))
        print(json.dumps(rows[-1]), flush=True)
        (run_dir / "summary.json").write_text(json.dumps({"rows": rows}, indent=1))
    finest = np.asarray(rows[-1]["tracked_u_yz_mm"])
    for row in rows:
        row["tracked_rel_change_vs_finest"] = float(np.linalg.norm(np.asarray(row["tracked_u_yz_mm"]) - finest)
                                                    / np.linalg.norm(finest))
    summary = {"command": "python studies/actuator.py " + " ".join(argv or sys.argv[1:]),
               "threads": a.threads, "integration": a.integration, "pressure_MPa": a.pressure, "bulk_ratio": a.bulk_ratio, "rows": rows}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
