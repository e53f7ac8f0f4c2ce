#!/usr/bin/env python
"""Benchmarks of the finite element core on Hex20 box meshes, for one member and for an ensemble.

    python scripts/bench.py --suite fem --threads 1 --out runs/bench/fem.json
    python scripts/bench.py --suite fem --quick          # smoke test on tiny meshes, < 1 min

Prints one JSON document (``definitions`` in it says what every timing means) and writes it to
``--out``; progress goes to stderr. Measurements that would take long have time budgets: past a
budget a member-chunked measurement stops and is extrapolated linearly in members, and a Newton
solve that would not fit is replaced by a measured batched iteration or an estimate. The JSON
says which (``extrapolated``, ``mode``). Timings are only meaningful on a quiet machine: the
load averages at start and end are recorded.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import gc
import json
import math
import os
import platform
import statistics
import sys
import time
import warnings

import numpy as np
import scipy
import scipy.sparse.linalg as spla
import torch

from torchfra import fem
from torchfra.fem.assembly import SparsePattern, scatter_vector
from torchfra.geometry.structured import box_mesh

warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks")

DTYPE = torch.float64
BOX_MM = (16.0, 16.0, 60.0)  # the actuator body (DESIGN §3)
KAPPA_T = 0.005615  # MPa, the paper's true C10 (§5); its prior: C10 ~ logN(1.1 kappa_t, (0.2 kappa_t)^2)
D1 = 0.1  # 1/MPa: K = 2 / D1 = 20 MPa, about 1600 times mu = 2 C10: near-incompressible
P_OVER_C10 = 0.02  # follower pressure on the ymin face / nominal C10; linear beam theory: tip ~ 16 mm
KERNEL_AMPLITUDE = 0.01  # random nodal displacement / smallest element edge (strains of ~1 %)
STATE_AMPLITUDE = 1e-3  # random reduced unknowns for the assembly state (mm and rad)

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
    "displacement (amplitude KERNEL_AMPLITUDE x smallest element edge). residual_s: tangent=False (element "
    "forces + condensed pressure), unchunked for the closed form (as Model.evaluate), member-chunked for "
    "torch.func because its derived path computes the Gauss-point Hessian even for a residual. "
    "residual_tangent_s: tangent=True, member-chunked. member_elements_per_s = members x elements / s.",
    "kernel.material": "neohookean_closed_form: NeoHookean() fast path; neohookean_torch_func: "
    "NeoHookean(fast=False), stress and tangent by vmap(jacfwd(grad(psi))).",
    "assembly": "At a random small state (reduced unknowns ~ STATE_AMPLITUDE, load factor 1) of "
    "members_timed = min(members, chunk_size) members; all values are seconds per member. "
    "assemble: SparsePattern.assemble of all terms' element tangents into CSR data (one index_add_ per term). "
    "reduce: Model._reduced_tangents minus assemble: per member CSR build, J^T K J with the constraint "
    "Jacobian and the rigid-body geometric stiffness. model_residual / model_tangent: Model.evaluate(a, ..., "
    "tangent=False / True) end to end (displacement map, every term, scatter, reduction).",
    "factorization": "scipy.sparse.linalg.splu (SuperLU, default COLAMD ordering, as fem.newton) of member 0's "
    "reduced tangent from the assembly state (1 member), after tocsc (tocsc_s); solve_s: one lu.solve; "
    "factor_nnz = nnz(L) + nnz(U).",
    "newton.problem": "clamped base (zmin), rigid top (zmax), follower pressure P on the side face ymin (the "
    "block bends towards +y), NeoHookean hybrid, D1 near-incompressible; member 0: C10 = 1.1 kappa_t, other "
    "members C10 ~ logN(1.1 kappa_t, (0.2 kappa_t)^2); P = P_OVER_C10 x 1.1 kappa_t for all; load factor 0 -> 1 "
    "with NewtonOptions() defaults.",
    "newton.full_solve": "fem.solve(model, params, (1.0,)) wall time once; timings = Solution.timings (residual: "
    "Model.evaluate without tangent; tangent: Model.evaluate with tangent, kernels + assembly + reduction; "
    "solve: per-member tocsc + splu + solve); other_s = wall - sum(timings): Euler predictor (one tangent "
    "and one factorization per member, two residuals) and bookkeeping. iterations/increments/cutbacks: "
    "per member (min, max, mean for a batch).",
    "newton_pilot": "full_solve of the same problem on the tiny PILOT_DIVISIONS mesh with pilot_members members, "
    "run first: its iteration counts (member 0, and the slowest member) are the assumed_iterations of the "
    "estimates below until a mesh's own 1-member solve has run (Newton iteration counts depend little on the mesh).",
    "newton.estimated": "a full solve does not fit newton_budget_s: estimated_wall_s = (assumed_iterations + 1) x "
    "per_iteration_s, with per_iteration_s = model_residual + model_tangent + splu + solve measured above for one "
    "member (the + 1 is the Euler predictor's factorization).",
    "newton.one_iteration": "cost of one batched Newton iteration as fem.solve runs it, measured from the "
    "undeformed state a = 0 at load factor initial_increment: residual_s = Model.evaluate(all members); "
    "tangent_s = Model.evaluate(tangent=True) in member chunks (member-chunked record); solve_s = per member "
    "tocsc + splu + solve, timed on at most solve_members members within chunk_budget_s and extrapolated to all "
    "members, or (source 'factorization') members x factorization splu + solve when one factorization exceeds "
    "the budget. check: relative residual |r| / force_scale of the solved members before and after the step.",
    "newton.estimated_full_solve_s": "(assumed_iterations + 1) x per_iteration_s of the batch, assumed_iterations = "
    "the pilot's slowest member (or this mesh's 1-member count if larger): the batch iterates until its slowest "
    "member is done. A full batched solve runs only if this fits newton_budget_s.",
}


@dataclasses.dataclass
class Config:
    divisions: list[tuple[int, int, int]]
    members: list[int]
    derived_meshes: int = 1  # the torch.func path is benchmarked on the first this many meshes
    repeats: int = 3
    repeat_budget_s: float = 10.0
    chunk_budget_s: float = 60.0
    newton_budget_s: float = 300.0
    memory_budget_mb: float = 1024.0  # Model's default
    solve_members: int = 3  # most members factorized in a measured batched iteration
    pilot_members: int = 8
    seed: int = 0


PILOT_DIVISIONS = (2, 2, 4)
FULL = Config(divisions=[(8, 8, 16), (16, 16, 16)], members=[1, 100])
# Tiny meshes; the small memory budget makes the member-chunked paths run.
QUICK = Config(divisions=[(2, 2, 4), (2, 2, 8)], members=[1, 4], repeat_budget_s=1.0, chunk_budget_s=3.0,
               newton_budget_s=12.0, memory_budget_mb=4.0, pilot_members=2)

_START = time.perf_counter()


def log(message: str) -> None:
    print(f"[bench {time.perf_counter() - _START:7.1f} s] {message}", file=sys.stderr, flush=True)


# -- timing ----------------------------------------------------------------------------------------
def clock(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def measure(fn, cfg: Config):
    """Timing record of ``fn()`` and its last output (see DEFINITIONS['timing record'])."""
    first, out = clock(fn)
    if first * cfg.repeats > cfg.repeat_budget_s:
        return {"s": first, "runs_s": [first], "warmed_up": False}, out
    runs = []
    for _ in range(cfg.repeats):
        del out
        t, out = clock(fn)
        runs.append(t)
    return {"s": statistics.median(runs), "runs_s": runs, "warmed_up": True}, out


def measure_members(fn, n: int, chunk: int, cfg: Config) -> dict:
    """``fn(lo, hi)`` evaluates members lo..hi-1 (see DEFINITIONS['member-chunked record'])."""
    if n <= chunk:
        record, _ = measure(lambda: fn(0, n), cfg)
        return {**record, "chunk_size": chunk, "members_timed": n, "extrapolated": False}
    runs, done = [], 0
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        runs.append(clock(lambda: fn(lo, hi))[0])
        done = hi
        if sum(runs) > cfg.chunk_budget_s:
            break
    return {"s": sum(runs) * n / done, "runs_s": runs, "warmed_up": False, "chunk_size": chunk,
            "members_timed": done, "extrapolated": done < n}


# -- the benchmark problem ----------------------------------------------------------------------------
def build(divisions, cfg: Config):
    """Model of the bending block (DEFINITIONS['newton.problem']) and its size/build record."""
    t_mesh, mesh = clock(lambda: box_mesh(BOX_MM, divisions))
    model = fem.Model(mesh, dtype=DTYPE, memory_budget_mb=cfg.memory_budget_mb)
    solid = model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), dtype=DTYPE))
    model.clamp("zmin")
    model.rigid("zmax")
    model.add(fem.FollowerPressure(mesh, "ymin", pressure="P", dtype=DTYPE))
    t_final, _ = clock(model.finalize)
    t_pattern, _ = clock(lambda: SparsePattern(3 * model.n_nodes, [t.dofs for t in model.terms]))
    info = {
        "divisions": list(divisions), "elements": mesh.n_elements, "nodes": model.n_nodes,
        "dofs": 3 * model.n_nodes, "reduced_dofs": model.n_red, "pattern_nnz": int(model.pattern.nnz),
        "chunk_size": model._chunk_size(),
        "build": {"mesh_s": t_mesh, "finalize_s": t_final, "pattern_s": t_pattern},
    }
    return model, solid, info


def member_params(n: int, seed: int) -> dict[str, torch.Tensor]:
    """C10 (member 0 nominal, the rest from the paper's lognormal prior), D1, P: each (n,)."""
    mean, sd = 1.1 * KAPPA_T, 0.2 * KAPPA_T
    s2 = math.log1p((sd / mean) ** 2)
    g = torch.Generator().manual_seed(seed)
    C10 = torch.exp(math.log(mean) - s2 / 2 + math.sqrt(s2) * torch.randn(n, generator=g, dtype=DTYPE))
    C10[0] = mean
    return {"C10": C10, "D1": torch.full((n,), D1, dtype=DTYPE), "P": torch.full((n,), P_OVER_C10 * mean, dtype=DTYPE)}


def members(params: dict[str, torch.Tensor], idx) -> dict[str, torch.Tensor]:
    return {k: v[idx] for k, v in params.items()}


def smallest_edge(divisions) -> float:
    return min(s / d for s, d in zip(BOX_MM, divisions))


# -- sections ------------------------------------------------------------------------------------------
def bench_kernels(model, solid, info, cfg: Config, derived: bool) -> list[dict]:
    E, chunk = info["elements"], info["chunk_size"]
    terms = [("neohookean_closed_form", solid)]
    if derived:
        terms.append(("neohookean_torch_func", fem.Hex20Solid(model.mesh, fem.NeoHookean(fast=False), dtype=DTYPE)))
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
    """Per-member assembly/reduction records, and member 0's reduced tangent and residual (1 member)."""
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
        residual, _ = measure(lambda: model.evaluate(a, params, lam), cfg)
        tangent, ev = measure(lambda: model.evaluate(a, params, lam, tangent=True), cfg)
        if first is None:
            first = ev.tangents[0], ev.residual[0].numpy()
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


def bench_factorization(K, r, cfg: Config) -> dict:
    log(f"  factorization, {K.shape[0]} unknowns, nnz {K.nnz}")
    to_csc, Kc = measure(K.tocsc, cfg)
    splu, lu = measure(lambda: spla.splu(Kc), cfg)
    solve, _ = measure(lambda: lu.solve(-r), cfg)
    log(f"    splu {splu['s']:.2f} s, solve {solve['s']:.3f} s")
    return {"reduced_dofs": int(K.shape[0]), "nnz": int(K.nnz), "factor_nnz": int(lu.L.nnz + lu.U.nnz),
            "permc_spec": "COLAMD (scipy default, as fem.newton)", "tocsc_s": to_csc, "splu_s": splu,
            "solve_s": solve}


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


def bench_newton_single(model, cfg: Config, assembly_row: dict, factorization: dict, assumed: int) -> dict:
    per_iteration = (assembly_row["model_residual_per_member_s"] + assembly_row["model_tangent_per_member_s"]
                     + factorization["splu_s"]["s"] + factorization["solve_s"]["s"])
    record = {"members": 1, "per_iteration_s": per_iteration, "assumed_iterations": assumed,
              "estimated_wall_s": (assumed + 1) * per_iteration}
    if record["estimated_wall_s"] > cfg.newton_budget_s:
        log(f"  newton, 1 member: estimated {record['estimated_wall_s']:.0f} s > budget, not run")
        return {"mode": "estimated", **record}
    log(f"  newton, 1 member: full solve (estimated {record['estimated_wall_s']:.0f} s)")
    wall, sol = clock(lambda: fem.solve(model, member_params(1, cfg.seed), (1.0,), fem.NewtonOptions()))
    result = solution_record(sol, wall, model)
    log(f"    {result['iterations']['max']} iterations, {result['increments']['max']} increments, {wall:.1f} s")
    return {"mode": "full_solve", **record, **result, "residual_history_member0": sol.residual_history[0]}


def bench_newton_batch(model, n: int, cfg: Config, factorization: dict, assumed: int) -> dict:
    log(f"  newton, {n} members: one batched iteration")
    params = member_params(n, cfg.seed)
    lam = torch.full((n,), fem.NewtonOptions().initial_increment, dtype=DTYPE)
    a = torch.zeros(n, model.n_red, dtype=DTYPE)
    residual, ev = measure(lambda: model.evaluate(a, params, lam), cfg)
    chunk = model._chunk_size()
    one_factorization = factorization["splu_s"]["s"] + factorization["solve_s"]["s"]
    may_solve = one_factorization <= cfg.chunk_budget_s
    tangent_runs, solve_runs, solved, steps = [], [], [], []
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        t, evt = clock(lambda: model.evaluate(a[lo:hi], members(params, slice(lo, hi)), lam[lo:hi], tangent=True))
        tangent_runs.append(t)
        for j in range(hi - lo):
            if not may_solve or len(solved) == cfg.solve_members or sum(solve_runs) > cfg.chunk_budget_s:
                break
            t, da = clock(lambda: spla.splu(evt.tangents[j].tocsc()).solve(-evt.residual[j].numpy()))
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
    else:
        solve = {"s": one_factorization * n, "source": "factorization", "members_timed": 0, "extrapolated": True}
    per_iteration = residual["s"] + tangent["s"] + solve["s"]
    record = {
        "members": n, "mode": "one_iteration", "load_factor": float(lam[0]), "residual_s": residual,
        "tangent_s": tangent, "solve_s": solve, "per_iteration_s": per_iteration,
        "split": {k: v["s"] / per_iteration
                  for k, v in (("residual", residual), ("tangent", tangent), ("solve", solve))},
    }
    if solved:
        idx = torch.as_tensor(solved)
        after = model.evaluate(a[idx] + torch.stack(steps), members(params, idx), lam[idx])
        record["check"] = {
            "members": solved,
            "relative_residual_before": (ev.residual[idx].norm(dim=1) / ev.force_scale[idx]).tolist(),
            "relative_residual_after": (after.residual.norm(dim=1) / after.force_scale).tolist(),
        }
    log(f"    per iteration {per_iteration:.1f} s (residual {residual['s']:.2f}, tangent {tangent['s']:.1f}, "
        f"solve {solve['s']:.1f} [{solve['source']}])")
    estimate = (assumed + 1) * per_iteration
    record.update(assumed_iterations=assumed, estimated_full_solve_s=estimate)
    if estimate <= cfg.newton_budget_s:
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
            "members": cfg.pilot_members, **solution_record(sol, wall, model),
            "iterations_per_member": sol.iterations.tolist(), "increments_per_member": sol.increments.tolist(),
            "residual_history_member0": sol.residual_history[0]}


# -- driver ---------------------------------------------------------------------------------------------
def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        return platform.processor()


def environment() -> dict:
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "torch": torch.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
        "python": platform.python_version(), "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "platform": platform.platform(), "machine": platform.machine(), "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(), "load_average_start": list(os.getloadavg()),
    }


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
        if single["mode"] == "full_solve":
            single_iterations = single["iterations"]["max"]
            batch_iterations = max(batch_iterations, single_iterations)
        info["newton"] = [single] + [bench_newton_batch(model, n, cfg, info["factorization"], batch_iterations)
                                     for n in cfg.members if n > 1]
        result["meshes"].append(info)
        del model, solid
        gc.collect()
    return result


SUITES = {"fem": fem_suite}


def rounded(x):
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, dict):
        return {k: rounded(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [rounded(v) for v in x]
    return x


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--suite", choices=sorted(SUITES), required=True)
    parser.add_argument("--out", help="also write the JSON to this file")
    parser.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    parser.add_argument("--quick", action="store_true", help="tiny meshes and ensembles: a smoke test, < 1 min")
    parser.add_argument("--meshes", help="divisions to run instead of the suite's, e.g. 8x8x16,16x16x16")
    parser.add_argument("--members", help="member counts instead of the suite's, e.g. 1,100 (1 must come first)")
    parser.add_argument("--newton-budget-s", type=float, help="run a full Newton solve only if estimated below this")
    parser.add_argument("--chunk-budget-s", type=float, help="time budget of one member-chunked measurement")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    cfg = dataclasses.replace(QUICK if args.quick else FULL)
    if args.meshes:
        cfg.divisions = [tuple(int(v) for v in m.split("x")) for m in args.meshes.split(",")]
    if args.members:
        cfg.members = [int(v) for v in args.members.split(",")]
    if cfg.members[0] != 1:
        parser.error("--members must start with 1 (the single-member runs feed the estimates)")
    if args.newton_budget_s is not None:
        cfg.newton_budget_s = args.newton_budget_s
    if args.chunk_budget_s is not None:
        cfg.chunk_budget_s = args.chunk_budget_s

    env = environment()
    log(f"suite {args.suite}, {'quick' if args.quick else 'full'}, {torch.get_num_threads()} threads")
    result = {"suite": args.suite, "quick": args.quick, "environment": env, **SUITES[args.suite](cfg),
              "definitions": DEFINITIONS}
    env["load_average_end"] = list(os.getloadavg())
    result["total_wall_s"] = time.perf_counter() - _START
    text = json.dumps(rounded(result), indent=1)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            f.write(text + "\n")
    print(text)
    log(f"done in {result['total_wall_s']:.1f} s")
    return result


if __name__ == "__main__":
    main()
