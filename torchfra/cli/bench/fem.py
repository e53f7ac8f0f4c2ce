"""The FE core suite on Hex20 box meshes: kernels, assembly, factorization, Newton (one member and batched)."""
from __future__ import annotations

import dataclasses
import gc

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import KAPPA_T  # C10's prior: logN(1.1 kappa_t, (0.2 kappa_t)^2)
from torchfra.fem.assembly import scatter_vector
from torchfra.fem.linsolve import Factorization, available_backends, resolve_backend
from torchfra.cli.bench.common import (
    BOX_MM, Config, D1, DTYPE, KERNEL_AMPLITUDE, PILOT_DIVISIONS, P_OVER_C10, STATE_AMPLITUDE, build, clock, log,
    measure, measure_members, member_params, members, pardiso_memory_guard, pardiso_phases, release, smallest_edge
)


DEFINITIONS = {
    "timing record": "{'s': seconds, 'runs_s': every timed run, 'warmed_up': a discarded warm-up run preceded}. "
    "'s' is the median of `repeats` runs after one warm-up run; a first run longer than repeat_budget_s / repeats "
    "is itself the measurement (warmed_up false; smaller cases of the same code ran before it).",
    "member-chunked record": "a timing record over all members; members are evaluated in chunks of "
    "`chunk_size` = Model._chunk_size() (as Model.evaluate does for tangents), each chunk once, until "
    "chunk_budget_s is spent; 's' is then extrapolated linearly to all members ('extrapolated': true, "
    "'members_timed' says how many were timed).",
    "mesh": "box_mesh(16 x 16 x 60 mm, divisions); dofs = 3 * nodes; reduced_dofs = unknowns after clamping zmin "
    "and making zmax one rigid body (6 unknowns); pattern_nnz = entries of the full sparse pattern.",
    "build.mesh_s": "box_mesh(...) incl. its validity checks.",
    "build.finalize_s": "Model.finalize(): constraint map (DofMap) + sparse pattern + orphan check.",
    "build.pattern_s": "SparsePattern(3 n_nodes, dofs of every term) alone, built once per mesh.",
    "kernel": "Hex20Solid(hybrid).evaluate(u, params, load_factor, tangent) called directly on a random "
    "displacement (amplitude KERNEL_AMPLITUDE x smallest element edge), local=None (element pressures projected "
    "from u). residual_s: tangent=False (element forces + condensed pressure), unchunked for the closed form (as "
    "Model.evaluate), member-chunked for torch.func because its derived path computes the Gauss-point Hessian "
    "even for a residual. residual_tangent_s: tangent=True, member-chunked. member_elements_per_s = members x "
    "elements / s.",
    "kernel.material": "neohookean_closed_form: NeoHookean() fast path; neohookean_torch_func: "
    "NeoHookean(fast=False), stress and tangent by vmap(jacfwd(grad(psi))).",
    "assembly": "At a random small state (reduced unknowns ~ STATE_AMPLITUDE, load factor 1, element pressures "
    "model.initial_local = 0) of members_timed = min(members, chunk_size) members; all values are seconds per "
    "member. "
    "assemble: SparsePattern.assemble of all terms' element tangents into CSR data (one index_add_ per term). "
    "reduce: Model._reduced_tangents minus assemble: per member CSR build, J^T K J with the constraint "
    "Jacobian and the rigid-body geometric stiffness. model_residual / model_tangent: Model.evaluate(a, ..., "
    "tangent=False / True, local=pressures) end to end (displacement map, every term, scatter, reduction), as a "
    "Newton iteration calls it.",
    "factorization": "fem.linsolve.Factorization(K, backend) of member 0's reduced tangent K from the assembly "
    "state (1 member), for every backend in available_backends(); right-hand side b = -rhs (the condensed "
    "residual Newton solves with). auto_backend: what backend 'auto' (fem.newton's default) resolves to for K. "
    "Per backend: factorize_s: Factorization(K, backend) incl. its sparse format conversion (and for pardiso the "
    "construction of the pypardiso solver, which searches for the MKL library: constructor_s, timed alone); "
    "solve_s: one solve(b); relative_residual: |K x - b| / |b|. superlu: scipy splu, COLAMD, factor_nnz = nnz(L) "
    "+ nnz(U); skipped above superlu_max_unknowns (a 51k-unknown SuperLU factorization did not finish in 20 min). "
    "pardiso: MKL PARDISO (pypardiso, mtype 11) with mkl_threads threads; multi_rhs_solve_s: one solve of "
    "multi_rhs right-hand sides at once (B: n x multi_rhs); factor_nnz = iparm(18); factor_memory_mb = iparm(16) "
    "+ iparm(17), the MKL memory a Factorization keeps (Factorization never frees it; the benchmark frees its own "
    "after each run, fem.solve does not); phases: analysis_s (PARDISO phase 11: reordering + symbolic) and "
    "numeric_s (phase 22: numerical factorization) timed once each on a separate solver.",
    "newton.problem": "clamped base (zmin), rigid top (zmax), follower pressure P on the side face ymin (the "
    "block bends towards +y), NeoHookean hybrid, D1 near-incompressible; member 0: C10 = 1.1 kappa_t, other "
    "members C10 ~ logN(1.1 kappa_t, (0.2 kappa_t)^2); P = P_OVER_C10 x 1.1 kappa_t for all; load factor 0 -> 1 "
    "with NewtonOptions() defaults.",
    "newton.full_solve": "fem.solve(model, params, (1.0,), NewtonOptions(linear_solver=linear_solver)) wall time "
    "once; timings = Solution.timings (residual: Model.evaluate without tangent; tangent: Model.evaluate with "
    "tangent, kernels + assembly + reduction; solve: per-member Factorization + solve); other_s = wall - "
    "sum(timings): Euler predictor (one tangent and one factorization per member, two residuals) and "
    "bookkeeping. iterations/increments/cutbacks: per member (min, max, mean for a batch).",
    "newton_pilot": "full_solve of the same problem on the tiny PILOT_DIVISIONS mesh with pilot_members members, "
    "run first: its iteration counts (member 0, and the slowest member) are the assumed_iterations of the "
    "estimates below until a mesh's own 1-member solve has run (Newton iteration counts depend little on the mesh).",
    "newton.single": "the 1-member record is for linear_solver = the backend 'auto' picks (fem.newton's default); "
    "other_backends holds the same record for every other available backend. mode: full_solve, estimated, or "
    "skipped ('skipped' says why: the backend's factorization was skipped, or PARDISO's unfreed factor memory, "
    "factor_memory_mb x (assumed_iterations + 1) factorizations, would exceed half the available memory).",
    "newton.estimated": "a full solve does not fit newton_budget_s: estimated_wall_s = (assumed_iterations + 1) x "
    "per_iteration_s, with per_iteration_s = model_residual + model_tangent + factorize + solve of that backend "
    "measured above for one member (the + 1 is the Euler predictor's factorization).",
    "newton.one_iteration": "cost of one batched Newton iteration as fem.solve runs it, measured from the "
    "undeformed state (a = 0, element pressures model.initial_local) at load factor initial_increment: "
    "residual_s = Model.evaluate(all members, local=...); tangent_s = Model.evaluate(tangent=True, local=...) in "
    "member chunks (member-chunked record); solve_s = per member Factorization(K, linear_solver) + solve(-rhs), "
    "linear_solver = what 'auto' picks, timed on at most solve_members members within chunk_budget_s and "
    "extrapolated to all members, or (source 'factorization') members x (factorize + solve) of the factorization "
    "section when one factorization exceeds the budget. check: relative residual max(|r|, |rhs|) / force_scale "
    "(fem.newton's measure) of the solved members before and after the step (pressures updated by "
    "Model.local_update).",
    "newton.estimated_full_solve_s": "(assumed_iterations + 1) x per_iteration_s of the batch, assumed_iterations = "
    "the pilot's slowest member (or this mesh's 1-member count if larger): the batch iterates until its slowest "
    "member is done. A full batched solve runs only if this fits newton_budget_s.",
}



# -- sections ------------------------------------------------------------------------------------------
def bench_kernels(model, solid, info, cfg: Config, derived: bool) -> list[dict]:
    E, chunk = info["elements"], info["chunk_size"]
    terms = [("neohookean_closed_form", solid)]
    if derived:
        terms.append(("neohookean_torch_func", fem.Hex20Solid(model.mesh, fem.NeoHookean(fast=False), integration="reduced", dtype=DTYPE)))
    rows = []
    for name, term in terms:
        for n in cfg.members:
            log(f"  kernel {name}, {n} members x {E} elements")
            params = member_params(n, cfg.seed)
            lam = torch.ones(n, dtype=DTYPE)
            g = torch.Generator().manual_seed(cfg.seed)
            u = KERNEL_AMPLITUDE * smallest_edge(info["divisions"]) * torch.randn(
                n, model.n_nodes, 3, generator=g, dtype=DTYPE)
            if not bool(term.evaluate(u[:1], members(params, slice(0, 1)), lam[:1], tangent=False).ok.all()):
                raise RuntimeError(f"the random kernel displacement inverted an element of mesh {info['divisions']}; "
                                   "lower KERNEL_AMPLITUDE")

            def run(tangent):
                return lambda lo, hi: term.evaluate(u[lo:hi], members(params, slice(lo, hi)), lam[lo:hi],
                                                    tangent=tangent)

            residual = measure_members(run(False), n, n if term.material.fast else chunk, cfg)
            both = measure_members(run(True), n, chunk, cfg)
            rows.append({
                "material": name, "members": n, "member_elements": n * E,
                "residual_s": residual, "residual_tangent_s": both,
                "member_elements_per_s": {"residual": n * E / residual["s"], "residual_tangent": n * E / both["s"]},
            })
            log(f"    residual {residual['s']:.3f} s, residual+tangent {both['s']:.3f} s"
                f"{' (extrapolated)' if both['extrapolated'] else ''}")
    return rows


def bench_assembly(model, info, cfg: Config):
    """Per-member assembly/reduction records, and member 0's reduced tangent and condensed residual (1 member)."""
    rows, first = [], None
    for n in cfg.members:
        m = min(n, info["chunk_size"])
        log(f"  assembly, {n} members (timed on {m})")
        params = members(member_params(n, cfg.seed), slice(0, m))
        lam = torch.ones(m, dtype=DTYPE)
        g = torch.Generator().manual_seed(cfg.seed + 1)
        a = STATE_AMPLITUDE * torch.randn(m, model.n_red, generator=g, dtype=DTYPE)
        u = model.displacement(a, lam)
        outs = [t.evaluate(u, params, lam, tangent=True) for t in model.terms]
        blocks = [o.Ke for o in outs]
        r_full = scatter_vector(3 * model.n_nodes, [t.dofs for t in model.terms], [o.fe for o in outs])
        assemble, _ = measure(lambda: model.pattern.assemble(blocks), cfg)
        with_reduce, _ = measure(lambda: model._reduced_tangents(a, r_full, blocks), cfg)
        del outs, blocks, r_full
        local = model.initial_local(m)
        residual, _ = measure(lambda: model.evaluate(a, params, lam, local=local), cfg)
        tangent, ev = measure(lambda: model.evaluate(a, params, lam, tangent=True, local=local), cfg)
        if first is None:
            first = ev.tangents[0], ev.rhs[0].numpy()
        del ev
        rows.append({
            "members": n, "members_timed": m,
            "assemble_per_member_s": assemble["s"] / m,
            "reduce_per_member_s": (with_reduce["s"] - assemble["s"]) / m,
            "model_residual_per_member_s": residual["s"] / m,
            "model_tangent_per_member_s": tangent["s"] / m,
            "records": {"assemble": assemble, "assemble_and_reduce": with_reduce, "model_residual": residual,
                        "model_tangent": tangent},
        })
    return rows, first


def bench_factorization(K, rhs: np.ndarray, cfg: Config) -> dict:
    n = K.shape[0]
    b = -rhs
    record = {"reduced_dofs": int(n), "nnz": int(K.nnz), "auto_backend": resolve_backend("auto", n), "backends": {}}
    for backend in available_backends():
        log(f"  factorization, {backend}, {n} unknowns, nnz {K.nnz}")
        if backend == "superlu" and n > cfg.superlu_max_unknowns:
            reason = f"{n} unknowns > superlu_max_unknowns = {cfg.superlu_max_unknowns}"
            log(f"    skipped: {reason}")
            record["backends"][backend] = {"skipped": reason}
            continue
        factorize, fac = measure(lambda: Factorization(K, backend), cfg, cleanup=release)
        solve, x = measure(lambda: fac.solve(b), cfg)
        row = {"factorize_s": factorize, "solve_s": solve,
               "relative_residual": float(np.linalg.norm(K @ x - b) / np.linalg.norm(b))}
        if backend == "superlu":
            row.update(permc_spec="COLAMD (scipy default, as fem.linsolve)",
                       factor_nnz=int(fac._lu.L.nnz + fac._lu.U.nnz))
        else:
            import pypardiso

            B = np.random.default_rng(cfg.seed).standard_normal((n, cfg.multi_rhs))
            multi, _ = measure(lambda: fac.solve(B), cfg)
            iparm = fac._solver.get_iparm
            row.update(multi_rhs=cfg.multi_rhs, multi_rhs_solve_s=multi, factor_nnz=int(iparm(18)),
                       factor_memory_mb=(int(iparm(16)) + int(iparm(17))) / 1024,
                       constructor_s=measure(pypardiso.PyPardisoSolver, cfg)[0], phases=pardiso_phases(K))
        release(fac)
        del fac
        record["backends"][backend] = row
        extra = (f", {cfg.multi_rhs} right-hand sides {row['multi_rhs_solve_s']['s']:.2f} s"
                 if "multi_rhs" in row else "")
        log(f"    factorize {factorize['s']:.2f} s, solve {solve['s']:.3f} s{extra}, "
            f"|Kx - b| / |b| = {row['relative_residual']:.1e}")
    return record


def solution_record(sol, wall: float, model) -> dict:
    top = model.mesh.node_sets["zmax"]
    converged = sol.converged
    stats = {k: {"min": int(v.min()), "max": int(v.max()), "mean": float(v.mean())}
             for k, v in (("iterations", sol.iterations), ("increments", sol.increments), ("cutbacks", sol.cutbacks))}
    return {
        "wall_s": wall, "timings": dict(sol.timings), "other_s": wall - sum(sol.timings.values()),
        "converged_members": int(converged.sum()), "load_reached_min": float(sol.load_reached.min()),
        **stats,
        "tip_uy_mm_member0": float(sol.u[0, -1, top, 1].mean()) if converged[0] else None,
        "max_displacement_mm_member0": float(sol.u[0, -1].norm(dim=1).max()) if converged[0] else None,
    }


def newton_single(model, cfg: Config, backend: str, assembly_row: dict, factorization: dict, assumed: int) -> dict:
    row = factorization["backends"][backend]
    if "skipped" in row:
        return {"mode": "skipped", "linear_solver": backend, "skipped": f"factorization skipped: {row['skipped']}"}
    per_iteration = (assembly_row["model_residual_per_member_s"] + assembly_row["model_tangent_per_member_s"]
                     + row["factorize_s"]["s"] + row["solve_s"]["s"])
    record = {"members": 1, "linear_solver": backend, "per_iteration_s": per_iteration, "assumed_iterations": assumed,
              "estimated_wall_s": (assumed + 1) * per_iteration}
    reason = pardiso_memory_guard(row, assumed + 1) if backend == "pardiso" else None
    if reason:
        log(f"  newton, 1 member, {backend}: skipped: {reason}")
        return {"mode": "skipped", **record, "skipped": reason}
    if record["estimated_wall_s"] > cfg.newton_budget_s:
        log(f"  newton, 1 member, {backend}: estimated {record['estimated_wall_s']:.0f} s > budget, not run")
        return {"mode": "estimated", **record}
    log(f"  newton, 1 member, {backend}: full solve (estimated {record['estimated_wall_s']:.0f} s)")
    options = fem.NewtonOptions(linear_solver=backend)
    wall, sol = clock(lambda: fem.solve(model, member_params(1, cfg.seed), (1.0,), options))
    result = solution_record(sol, wall, model)
    log(f"    {result['iterations']['max']} iterations, {result['increments']['max']} increments, {wall:.1f} s")
    return {"mode": "full_solve", **record, **result, "residual_history_member0": sol.residual_history[0]}


def bench_newton_single(model, cfg: Config, assembly_row: dict, factorization: dict, assumed: int) -> dict:
    """The 1-member solve with the backend 'auto' picks; other_backends: the same with every other backend."""
    auto = factorization["auto_backend"]
    record = newton_single(model, cfg, auto, assembly_row, factorization, assumed)
    if record["mode"] == "full_solve":
        assumed = record["iterations"]["max"]
    record["other_backends"] = {b: newton_single(model, cfg, b, assembly_row, factorization, assumed)
                                for b in available_backends() if b != auto}
    return record


def relative_residual(ev) -> torch.Tensor:
    """fem.newton's convergence measure: max(|r|, |condensed r|) / force_scale, (N,)."""
    return torch.maximum(ev.residual.norm(dim=1), ev.rhs.norm(dim=1)) / ev.force_scale


def bench_newton_batch(model, n: int, cfg: Config, factorization: dict, assumed: int) -> dict:
    log(f"  newton, {n} members: one batched iteration")
    params = member_params(n, cfg.seed)
    lam = torch.full((n,), fem.NewtonOptions().initial_increment, dtype=DTYPE)
    a = torch.zeros(n, model.n_red, dtype=DTYPE)
    local = model.initial_local(n)
    residual, ev = measure(lambda: model.evaluate(a, params, lam, local=local), cfg)
    chunk = model._chunk_size()
    backend = factorization["auto_backend"]
    row = factorization["backends"][backend]
    one_factorization = None if "skipped" in row else row["factorize_s"]["s"] + row["solve_s"]["s"]
    may_solve = one_factorization is not None and one_factorization <= cfg.chunk_budget_s
    tangent_runs, solve_runs, solved, steps = [], [], [], []

    def factorize_and_solve(evt, j):
        fac = Factorization(evt.tangents[j], backend)
        return fac, fac.solve(-evt.rhs[j].numpy())

    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        t, evt = clock(lambda: model.evaluate(a[lo:hi], members(params, slice(lo, hi)), lam[lo:hi], tangent=True,
                                              local=[None if l is None else l[lo:hi] for l in local]))
        tangent_runs.append(t)
        for j in range(hi - lo):
            if not may_solve or len(solved) == cfg.solve_members or sum(solve_runs) > cfg.chunk_budget_s:
                break
            t, (fac, da) = clock(lambda: factorize_and_solve(evt, j))
            release(fac)
            solve_runs.append(t)
            solved.append(lo + j)
            steps.append(torch.as_tensor(da))
        del evt
        if sum(tangent_runs) > cfg.chunk_budget_s:
            break
    done = min(n, len(tangent_runs) * chunk)
    tangent = {"s": sum(tangent_runs) * n / done, "runs_s": tangent_runs, "warmed_up": False, "chunk_size": chunk,
               "members_timed": done, "extrapolated": done < n}
    if solved:
        solve = {"s": sum(solve_runs) * n / len(solved), "runs_s": solve_runs, "source": "measured",
                 "members_timed": len(solved), "extrapolated": len(solved) < n}
    elif one_factorization is not None:
        solve = {"s": one_factorization * n, "source": "factorization", "members_timed": 0, "extrapolated": True}
    else:
        solve = {"s": None, "source": "none", "members_timed": 0, "skipped": row["skipped"]}
    record = {"members": n, "mode": "one_iteration", "load_factor": float(lam[0]), "linear_solver": backend,
              "residual_s": residual, "tangent_s": tangent, "solve_s": solve}
    if solve["s"] is None:
        log(f"    residual {residual['s']:.2f} s, tangent {tangent['s']:.1f} s, solve skipped: {row['skipped']}")
        return record
    per_iteration = residual["s"] + tangent["s"] + solve["s"]
    record.update(per_iteration_s=per_iteration, split={
        k: v["s"] / per_iteration for k, v in (("residual", residual), ("tangent", tangent), ("solve", solve))})
    if solved:
        idx = torch.as_tensor(solved)
        da, prm, loc = torch.stack(steps), members(params, idx), [None if l is None else l[idx] for l in local]
        after = model.evaluate(a[idx] + da, prm, lam[idx], local=model.local_update(a[idx], da, prm, lam[idx], loc))
        record["check"] = {
            "members": solved,
            "relative_residual_before": relative_residual(ev)[idx].tolist(),
            "relative_residual_after": relative_residual(after).tolist(),
        }
    log(f"    per iteration {per_iteration:.1f} s (residual {residual['s']:.2f}, tangent {tangent['s']:.1f}, "
        f"solve {solve['s']:.1f} [{solve['source']}, {backend}])")
    estimate = (assumed + 1) * per_iteration
    record.update(assumed_iterations=assumed, estimated_full_solve_s=estimate)
    reason = pardiso_memory_guard(row, n * (assumed + 1)) if backend == "pardiso" else None
    if reason:
        log(f"  newton, {n} members: full solve skipped: {reason}")
        record["full_solve_skipped"] = reason
    elif estimate <= cfg.newton_budget_s:
        log(f"  newton, {n} members: full solve (estimated {estimate:.0f} s)")
        wall, sol = clock(lambda: fem.solve(model, params, (1.0,), fem.NewtonOptions()))
        record["full_solve"] = solution_record(sol, wall, model)
        log(f"    {wall:.1f} s, {record['full_solve']['converged_members']}/{n} converged")
    else:
        log(f"  newton, {n} members: full solve estimated {estimate:.0f} s > budget, not run")
    return record


def bench_newton_pilot(cfg: Config) -> dict:
    log(f"newton pilot: mesh {PILOT_DIVISIONS}, {cfg.pilot_members} members")
    model, _, info = build(PILOT_DIVISIONS, cfg)
    wall, sol = clock(lambda: fem.solve(model, member_params(cfg.pilot_members, cfg.seed), (1.0,), fem.NewtonOptions()))
    log(f"    iterations per member {sol.iterations.tolist()}, {wall:.1f} s")
    return {"divisions": list(PILOT_DIVISIONS), "elements": info["elements"], "reduced_dofs": info["reduced_dofs"],
            "members": cfg.pilot_members, "linear_solver": resolve_backend("auto", info["reduced_dofs"]),
            **solution_record(sol, wall, model),
            "iterations_per_member": sol.iterations.tolist(), "increments_per_member": sol.increments.tolist(),
            "residual_history_member0": sol.residual_history[0]}



def fem_suite(cfg: Config) -> dict:
    pilot = bench_newton_pilot(cfg)
    result = {"config": {**dataclasses.asdict(cfg), "box_mm": BOX_MM, "kappa_t_MPa": KAPPA_T, "D1_per_MPa": D1,
                         "P_over_C10": P_OVER_C10, "kernel_amplitude": KERNEL_AMPLITUDE,
                         "state_amplitude": STATE_AMPLITUDE, "pilot_divisions": PILOT_DIVISIONS,
                         "newton_options": dataclasses.asdict(fem.NewtonOptions())},
              "newton_pilot": pilot, "meshes": []}
    single_iterations, batch_iterations = pilot["iterations_per_member"][0], pilot["iterations"]["max"]
    for k, divisions in enumerate(cfg.divisions):
        log(f"mesh {divisions}")
        model, solid, info = build(divisions, cfg)
        log(f"  {info['elements']} elements, {info['nodes']} nodes, {info['reduced_dofs']} reduced dofs, "
            f"chunk {info['chunk_size']} members")
        info["kernel"] = bench_kernels(model, solid, info, cfg, derived=k < cfg.derived_meshes)
        info["assembly"], (K, r) = bench_assembly(model, info, cfg)
        info["factorization"] = bench_factorization(K, r, cfg)
        del K
        single = bench_newton_single(model, cfg, info["assembly"][0], info["factorization"], single_iterations)
        solved = [s for s in (single, *single["other_backends"].values()) if s["mode"] == "full_solve"]
        if solved:
            single_iterations = solved[0]["iterations"]["max"]
            batch_iterations = max(batch_iterations, single_iterations)
        info["newton"] = [single] + [bench_newton_batch(model, n, cfg, info["factorization"], batch_iterations)
                                     for n in cfg.members if n > 1]
        result["meshes"].append(info)
        del model, solid
        gc.collect()
    return result
