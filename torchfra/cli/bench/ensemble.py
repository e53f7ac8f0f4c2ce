"""The ensemble suite: full Newton member by member against the reduced-order path on one ensemble."""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from torchfra import fem
from torchfra.cli.bench.common import Config, clock, log


ENSEMBLE_DEFINITIONS = {
    "problem": "the forward suite's actuator and prior (torchfra.calibration.forward.member_parameters, seed 0, --members M, "
    "--mesh); --vary NAME=S also draws that parameter per member as its ForwardConfig value x lognormal(0, S) "
    "(a multi-parameter prior, beyond the one-parameter P/C10 scaling law). Load factors (1..load_steps)/load_steps.",
    "old": "the full path as run_forward(method='full') runs it: fem.solve of one member at a time (chunk = 1), "
    "for --old-members of the M members (all by default); wall_s is their sum, wall_per_member_s its mean, "
    "wall_each_s each member's; reached_full_load: whether its Newton reached the last load factor (a member "
    "that stops at a limit point spends longer and is flagged in either path).",
    "new": "fem.reduced.solve_ensemble (the algorithm of run_forward(method='reduced') without its files): "
    "snapshot members by full Newton, basis + hyper-reduction, the others by reduced Newton in batches of 4, each "
    "checked by one full Newton step at the last load, re-solved in full if its estimate exceeds tol_mm. "
    "phases_s: full (snapshots), build, reduced (sampled Newton + polish + check), fallback.",
    "counts": "newton_iterations: full Newton iterations (one tangent + one factorization each, plus one Euler "
    "predictor factorization per full solve); sampled_iterations: reduced Newton iterations on the sampled blocks "
    "(no factorization); polish_iterations: full-residual evaluations; full_tangents: Galerkin tangents the polish "
    "needed; checks: one full tangent + factorization per reduced member.",
    "accuracy": "max over the compared members, load steps, observation points and both components of |Y_new - "
    "Y_old| (mm); frames interpolate linearly between load steps, so this bounds every frame. Target 1e-3 mm.",
    "speedup": "old.wall_per_member_s x M / new.wall_s: the old path's wall for all M members (measured on "
    "--old-members, per member) over the new path's measured wall, same process, same threads: the issue's "
    "batching efficiency, 100 x (one member alone) / (100-member run), for M = 100.",
    "two_processes_estimate_s": "new.wall_s with the snapshot and reduced phases halved (two workers on one run "
    "folder split members; build runs once per worker): an ESTIMATE for 2 cores; measure with two forward_uq.py "
    "processes.",
}


def ensemble_suite(cfg: Config, args) -> dict:
    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import member_parameters
    from torchfra.fem.reduced import solve_ensemble
    from torchfra.observation.operator import ObservationOperator, visible_faces

    M = args.forward_members
    fcfg = ForwardConfig(members=M, resolution=args.mesh, load_steps=args.load_steps, threads=args.threads)
    model, info = build_actuator_model(ActuatorGeometry(resolution=fcfg.resolution))
    model.finalize()
    op = ObservationOperator(model.mesh, visible_faces(model.mesh, (1.0, 0.0, 0.0)), points="nodes")
    params = member_parameters(fcfg)
    gen = torch.Generator().manual_seed(1)
    for spec in args.vary or []:
        name, spread = spec.split("=")
        params[name] = params[name] * torch.exp(float(spread) * torch.randn(M, generator=gen, dtype=torch.float64))
    load = np.arange(1, fcfg.load_steps + 1) / fcfg.load_steps
    options = fem.NewtonOptions(**fcfg.newton)
    n_old = min(M, args.old_members or M)
    log(f"ensemble: resolution {fcfg.resolution}, {model.n_red} dofs, {fcfg.load_steps} load steps, {M} members "
        f"(varying: C10 {'+ ' + ', '.join(args.vary) if args.vary else ''}), old path on {n_old}")

    def observe(u):
        return op(u[:, :, : model.mesh.n_nodes]).numpy()

    log("  new path: fem.reduced.solve_ensemble")
    wall_new, es = clock(lambda: solve_ensemble(model, params, load, options, tol=fcfg.reduced_tol,
                                                batch=fcfg.reduced_batch))
    Y_new = observe(es.u)
    n_red = int((es.method == "reduced").sum())
    log(f"    {wall_new:.1f} s: {len(es.snapshots)} snapshots, {n_red} reduced, "
        f"{int(((es.method == 'full')).sum()) - len(es.snapshots)} re-solved in full; basis {es.basis_size} modes, "
        f"sampled blocks {es.sampled_blocks}; phases { {k: round(v, 1) for k, v in es.timings.items()} }")
    old_members = np.linspace(0, M - 1, n_old).round().astype(int)
    log(f"  old path: fem.solve member by member, {n_old} members")
    walls, iters, err, reached = [], [], [], []
    for i, m in enumerate(old_members):
        w, sol = clock(lambda: fem.solve(model, {k: v[m : m + 1] for k, v in params.items()}, load, options))
        walls.append(w)
        iters.append(int(sol.iterations[0]))
        reached.append(bool(sol.converged.all()))
        err.append(float(np.nanmax(np.abs(observe(sol.u)[0] - Y_new[m]))) if sol.converged.all() else float("nan"))
        log(f"    member {m} ({es.method[m]}): {w:.1f} s, {iters[-1]} iterations, max |dY| {err[-1]:.2e} mm "
            f"[{i + 1}/{n_old}]")
    per_member_old = float(np.mean(walls))
    compared = np.array(err)
    result = {
        "config": {**dataclasses.asdict(fcfg), "vary": args.vary or [], "old_members": old_members.tolist()},
        "mesh": {"resolution": fcfg.resolution, "bricks": info.get("elements"),
                 "fiber_elements": info.get("fiber_elements"), "reduced_dofs": int(model.n_red)},
        "old": {"members": n_old, "wall_s": float(np.sum(walls)), "wall_per_member_s": per_member_old,
                "newton_iterations_per_member": iters, "wall_each_s": walls, "reached_full_load": reached},
        "new": {"members": M, "wall_s": wall_new, "phases_s": es.timings, "counts": {**es.counts, "checks": n_red},
                "snapshots": es.snapshots.tolist(), "reduced_members": n_red,
                "resolved_in_full": int((es.method == "full").sum()) - len(es.snapshots),
                "basis_size": es.basis_size, "sampled_blocks": es.sampled_blocks,
                "error_estimate_max_mm": float(np.nanmax(es.error_estimate)) if n_red else None,
                "converged": int((es.status == "converged").sum())},
        "accuracy": {"max_abs_dY_mm": float(np.nanmax(compared)), "per_compared_member_mm": err,
                     "target_mm": 1e-3, "met": bool(np.nanmax(compared) <= 1e-3)},
        "speedup": per_member_old * M / wall_new,
    }
    halved = es.timings["full"] / 2 + es.timings["build"] + es.timings["reduced"] / 2 + es.timings["fallback"] / 2
    result["two_processes_estimate_s"] = halved
    log(f"  old {per_member_old:.1f} s per member -> {per_member_old * M:.0f} s for {M}; new {wall_new:.0f} s: "
        f"speed-up {result['speedup']:.1f}x; max |dY| {result['accuracy']['max_abs_dY_mm']:.2e} mm; "
        f"2-process estimate {halved:.0f} s")
    return result
