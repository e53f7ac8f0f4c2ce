"""Why a reduced member still costs what it costs: the conditioning of the actuator's reduced
problem, and what the hyper-reduction does to its softest mode.

    python studies/reduced_conditioning.py [--members 2] [--mesh 1] [--threads 1]

The forward ensemble's reduced members (``fem.reduced``) spend their time in the sampled Newton
iterations (~2.9 per load step, each one sampled tangent) and in the polish on the full residual
(~2.3 full residuals per load step, plus Galerkin tangents where the sampled one stops
contracting). This study measures the reason, on the C10 prior of ``scripts/forward_uq.py`` (its
snapshots, basis and hyper-reduction, exactly as ``solve_ensemble`` builds them) for ``--members``
members that are not snapshots, at every load step:

- ``eigenvalues``: the smallest three and the largest eigenvalue (magnitudes) of the Galerkin tangent
  ``V^T K V`` at the member's Galerkin equilibrium (solved with the Galerkin tangent to 1e-9 mm), and
  their ratio (the condition number);
- ``soft_mode``: where the softest eigenvector moves the actuator (the largest nodal displacement of
  ``V phi`` and its components at that node);
- ``sampled_rayleigh_ratio``: ``phi^T K_s phi / phi^T K_g phi``, the sampled tangent's stiffness
  along the softest mode relative to the Galerkin one (1 would be exact);
- ``sampled_to_galerkin_mm``: the largest nodal distance between the hyper-reduced equilibrium (the
  root of the sampled residual, Newton from the Galerkin one to 1e-9 mm) and the Galerkin
  equilibrium, and the part of it along the softest mode: the error the sampled phase leaves for the
  polish to remove.

Writes studies/results/study_reduced_conditioning.json (``--out``) and TensorBoard scalars under runs/<name>/.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchfra import fem
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.forward import member_parameters
from torchfra.fem.reduced import build_reduced, select_snapshots, solve_reduced
from torchfra.report.tensorboard import open_writer


def sampled_root(hyper, q0, params, lam, where: str, tol=1e-9, iterations=40):
    """Root of the hyper-reduced residual by Newton from q0 (its own, sampled tangent)."""
    V, q = hyper.basis.V, q0.clone()
    for _ in range(iterations):
        R, K, ok = hyper.evaluate(q[None], params, lam)
        dq = -torch.linalg.solve(K[0], R[0])
        q = q + dq
        if float((dq @ V.T).abs().max()) < tol:
            return q
    raise RuntimeError(f"{where}: the sampled residual's Newton did not converge in {iterations} iterations")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--members", type=int, default=2, help="non-snapshot members studied")
    ap.add_argument("--mesh", type=int, default=1, help="mesh resolution")
    ap.add_argument("--ensemble", type=int, default=100, help="ensemble the snapshots are chosen from")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="studies/results/study_reduced_conditioning.json")
    ap.add_argument("--name", default="study_reduced_conditioning", help="TensorBoard run under runs/")
    args = ap.parse_args(argv)
    if args.members < 1:
        ap.error(f"--members {args.members}: study at least one member")
    if args.ensemble < 7:
        ap.error(f"--ensemble {args.ensemble}: the snapshots take 5 members; choose at least 7 so that some are left")
    if args.threads < 1:
        ap.error(f"--threads {args.threads}: at least 1")
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()

    cfg = ForwardConfig(members=args.ensemble, resolution=args.mesh, threads=args.threads)
    model, _ = build_actuator_model(ActuatorGeometry(resolution=cfg.resolution))
    model.finalize()
    params = member_parameters(cfg)
    load = np.arange(1, cfg.load_steps + 1) / cfg.load_steps
    options = fem.NewtonOptions(**cfg.newton)
    snap = select_snapshots(params)
    states = torch.full((len(snap), load.size, model.n_red), float("nan"), dtype=torch.float64)
    for i, m in enumerate(tqdm(snap, desc="snapshots (full Newton)", unit="member")):
        states[i] = fem.solve(model, {k: v[m:m + 1] for k, v in params.items()}, load, options).a[0]
    reached = np.flatnonzero(torch.isfinite(states.reshape(len(snap), -1)).any(dim=1).numpy())
    hyper = build_reduced(model, states[reached], {k: v[snap[reached]] for k, v in params.items()}, load)
    galerkin, V = hyper.galerkin(), hyper.basis.V
    studied = [m for m in range(args.ensemble) if m not in set(snap.tolist())][: args.members]

    rows = []
    writer = open_writer(Path("runs") / args.name)
    bar = tqdm(total=len(studied) * load.size, desc="load steps studied", unit="step")
    for m in studied:
        sub = {k: v[m:m + 1] for k, v in params.items()}
        ref = solve_reduced(hyper, sub, load, refresh=0.0, polish_tol=1e-9, max_polish=40, check=False)
        if ref.status[0] != "converged":
            raise RuntimeError(f"member {m}: the Galerkin solve did not converge")
        for t, lam in enumerate(load):
            lam_t = torch.tensor([lam], dtype=torch.float64)
            q_g = ref.a[0, t] @ V
            _, K_g, _ = galerkin.evaluate(q_g[None], sub, lam_t)
            _, K_s, _ = hyper.evaluate(q_g[None], sub, lam_t)
            w, vec = torch.linalg.eigh(0.5 * (K_g[0] + K_g[0].T))
            order = torch.argsort(w.abs())
            phi = vec[:, order[0]]
            mode = model.displacement((phi @ V.T)[None], lam_t)[0]
            node = int(mode.norm(dim=1).argmax())
            q_s = sampled_root(hyper, q_g, sub, lam_t, f"member {m}, load factor {lam:.3f}")
            dq = q_s - q_g
            along = float(((dq @ phi) * phi @ V.T).abs().max())
            row = {
                "member": int(m), "C10": float(params["C10"][m]), "load_factor": float(lam),
                "eigenvalues_smallest": [float(x) for x in w.abs()[order[:3]]],
                "eigenvalue_largest": float(w.abs().max()),
                "condition": float(w.abs().max() / w.abs()[order[0]]),
                "soft_mode": {"node": node, "max_displacement": float(mode[node].norm()),
                              "components": [float(x) for x in mode[node]]},
                "sampled_rayleigh_ratio": float((phi @ K_s[0] @ phi) / (phi @ K_g[0] @ phi)),
                "sampled_to_galerkin_mm": float((dq @ V.T).abs().max()),
                "sampled_to_galerkin_along_soft_mode_mm": along,
            }
            rows.append(row)
            writer.add_scalar(f"member_{m}/smallest_eigenvalue", row["eigenvalues_smallest"][0], t)
            writer.add_scalar(f"member_{m}/condition", row["condition"], t)
            writer.add_scalar(f"member_{m}/sampled_to_galerkin_mm", row["sampled_to_galerkin_mm"], t)
            bar.update()
    bar.close()
    writer.close()
    summary = {
        "condition_min": min(r["condition"] for r in rows),
        "condition_max": max(r["condition"] for r in rows),
        "second_over_first_min": min(r["eigenvalues_smallest"][1] / r["eigenvalues_smallest"][0] for r in rows),
        "sampled_rayleigh_ratio_range": [min(r["sampled_rayleigh_ratio"] for r in rows),
                                         max(r["sampled_rayleigh_ratio"] for r in rows)],
        "sampled_to_galerkin_mm_max": max(r["sampled_to_galerkin_mm"] for r in rows),
        "along_soft_mode_fraction_min": min(r["sampled_to_galerkin_along_soft_mode_mm"]
                                            / max(r["sampled_to_galerkin_mm"], 1e-300) for r in rows),
    }
    result = {
        "settings": {"mesh": args.mesh, "ensemble": args.ensemble, "members": studied,
                     "snapshots": snap.tolist(), "basis_size": hyper.basis.size,
                     "sampled_blocks": hyper.sampled_blocks, "threads": args.threads,
                     "torch_threads": torch.get_num_threads(), "wall_s": time.perf_counter() - t_start,
                     "date": time.strftime("%Y-%m-%dT%H:%M:%S%z")},
        "summary": summary,
        "rows": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.out} ({result['settings']['wall_s']:.0f} s)")
    return result


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
