"""The cavity-offset imperfection: the morphed mesh against a re-meshed actuator, and its SNR.

    python studies/cavity_offset.py [--offset 0.3] [--resolutions 1 2] [--sizes 0.1 0.25 0.5]

For each resolution: the paper's actuator (C10 0.0062 MPa, 0.022 MPa, 20 frames of a ramp) observed
the way the proof suite observes it (uy, uz on the face x = +8 at the shifted 2 mm DIC grid of
``scenarios.dic_grid``) three ways: the base model, the morphed model at ``delta_y = offset``
(``build_actuator_model(cavity_offset=True)``), and a re-meshed actuator whose cavity axis sits at
y = 5 + offset (``ActuatorGeometry(cavity_offset=...)``) with the fibers embedded at the morphed
model's fiber positions, so both describe the same body. Reported: the effect ||morph - base|| and
the discretization difference ||morph - re-mesh|| (norms over frames, points and components, mm;
the effect's norm is its SNR at noise 1 mm), their ratio per resolution (it should fall as the
meshes refine) beside the base model's own change from that resolution to the finest one, and
the SNR of the proof suite's tabled sizes at resolution 1.
Writes studies/results/study_cavity_offset.json (``--out``) and runs/<name>/ TensorBoard scalars.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.observation.operator import ObservationOperator, visible_faces
from torchfra.report.tensorboard import open_writer
from torchfra.scenarios import PRESSURE_MAX, dic_grid, pressure_trace


def observe(model, points, params, loads) -> tuple[np.ndarray, float]:
    """(K, P, 2) uy, uz at ``points`` of the model's front face at the load factors; wall seconds."""
    mesh = model.mesh
    op = ObservationOperator(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=points, tol=0.05)
    t0 = time.perf_counter()
    sol = fem.solve(model, {k: torch.tensor([v], dtype=torch.float64) for k, v in params.items()}, loads,
                    fem.NewtonOptions(stagnation_tol=1e-6))
    if not sol.converged.all():
        raise RuntimeError(f"solve did not converge (reached {sol.load_reached[0]:.3f} of the load)")
    return op(sol.u[0, :, : mesh.n_nodes]).numpy(), time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--offset", type=float, default=0.3, help="delta_y of the morph-vs-re-mesh comparison (mm)")
    ap.add_argument("--resolutions", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--sizes", type=float, nargs="*", default=[-0.25, -0.5, -1.0, 0.25, 0.5], help="delta_y sizes for the SNR (mm)")
    ap.add_argument("--C10", type=float, default=0.0062)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--threads", type=int, default=int(os.environ.get("TORCHFRA_THREADS", "1")))
    ap.add_argument("--name", default="study_cavity_offset")
    ap.add_argument("--out", default="studies/results/study_cavity_offset.json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    _, recorded = pressure_trace("ramp", a.frames)
    loads = recorded[recorded > 0] / PRESSURE_MAX
    base_params = {"C10": a.C10, "D1": 1.0 / (BULK_RATIO * a.C10), "E_fiber": E_FIBER, "P": PRESSURE_MAX}
    rows, base_Y = [], {}
    writer = open_writer(Path("runs") / a.name)
    for res in a.resolutions:
        geom = ActuatorGeometry(resolution=res)
        base, info = build_actuator_model(geom)
        points = dic_grid(info["mesh"], 2.0)
        Y0, t_base = observe(base, points, base_params, loads)
        base_Y[res] = Y0
        morphed, info_m = build_actuator_model(geom, cavity_offset=True)
        morphed.finalize()
        Ym, t_morph = observe(morphed, points, {**base_params, "delta_y": a.offset}, loads)
        fibers = info_m["fiber_nodes"]
        Xf = morphed.X[fibers] + a.offset * morphed.morph_fields()[fibers, :, 0]
        remeshed, _ = build_actuator_model(ActuatorGeometry(resolution=res, cavity_offset=geom.cavity_offset + a.offset),
                                           fibers=(Xf, info_m["fiber_conn"] - fibers[0]))
        Yr, t_remesh = observe(remeshed, points, base_params, loads)
        effect, diff = float(np.linalg.norm(Ym - Y0)), float(np.linalg.norm(Ym - Yr))
        row = {"resolution": res, "dofs": info["dofs"], "points": len(points), "offset_mm": a.offset,
               "effect_norm_mm": effect, "morph_minus_remesh_norm_mm": diff, "ratio": diff / effect,
               "effect_max_mm": float(np.abs(Ym - Y0).max()), "morph_minus_remesh_max_mm": float(np.abs(Ym - Yr).max()),
               "solve_s": {"base": t_base, "morph": t_morph, "remesh": t_remesh}}
        rows.append(row)
        writer.add_scalar("cavity_offset/morph_vs_remesh_ratio", row["ratio"], res)
        print(json.dumps(row), flush=True)
    finest = max(base_Y)
    for row in rows:  # the base model's own discretization error, against the finest mesh (same grid points)
        if row["resolution"] != finest and base_Y[row["resolution"]].shape == base_Y[finest].shape:
            row["base_minus_finest_base_norm_mm"] = float(np.linalg.norm(base_Y[row["resolution"]] - base_Y[finest]))
            row["base_minus_finest_base_max_mm"] = float(np.abs(base_Y[row["resolution"]] - base_Y[finest]).max())
    snr = []
    if a.sizes:
        geom = ActuatorGeometry(resolution=1)
        base, info = build_actuator_model(geom)
        points = dic_grid(info["mesh"], 2.0)
        Y0, _ = observe(base, points, base_params, loads)
        morphed, _ = build_actuator_model(geom, cavity_offset=True)
        for s in a.sizes:
            Ys, _ = observe(morphed, points, {**base_params, "delta_y": s}, loads)
            snr.append({"delta_y_mm": s, "snr_at_noise_1mm": float(np.linalg.norm(Ys - Y0))})
            writer.add_scalar("cavity_offset/snr_res1", snr[-1]["snr_at_noise_1mm"], int(round(1000 * s)))
            print(json.dumps(snr[-1]), flush=True)
    writer.close()
    out = {"command": "python studies/cavity_offset.py " + " ".join(os.sys.argv[1:]), "threads": a.threads,
           "C10": a.C10, "frames": a.frames, "comparison": rows, "snr_res1": snr}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
