#!/usr/bin/env python
"""Benchmarks of the finite element core on Hex20 box meshes, for one member and for an ensemble.

    python scripts/bench.py --suite fem --threads 1 --out runs/bench/fem.json
    python scripts/bench.py --suite fem --quick          # smoke test on tiny meshes, < 1 min
    python scripts/bench.py --suite forward --members 10 --threads 1 --out runs/bench/forward.json
    python scripts/bench.py --suite sensitivity --mesh 1 --load-steps 10 --out runs/bench/sensitivity.json
    python scripts/bench.py --suite ensemble --mesh 2 --members 100 --old-members 10 --out runs/bench/ensemble.json
    python scripts/bench.py --suite device --mesh 2 --members 1,10,100 --threads 2 --out runs/bench/device.json

Suite ``ensemble`` (issue "Forward ensembles in minutes"): the old path (full Newton per member) and the new
one (fem.reduced: snapshots, hyper-reduced Newton, check, fallback) side by side on one ensemble, with the
accuracy of every compared member; see ENSEMBLE_DEFINITIONS.

Suite ``forward`` (issue 3, "Performance"): the prior ensemble of torchfra.calibration.forward on the actuator mesh,
one member alone vs. M members in one batched fem.solve; see FORWARD_DEFINITIONS.

Prints one JSON document (``definitions`` in it says what every timing means) and writes it to
``--out``; progress goes to stderr. Measurements that would take long have time budgets: past a
budget a member-chunked measurement stops and is extrapolated linearly in members, and a Newton
solve that would not fit is replaced by a measured batched iteration or an estimate. The JSON
says which (``extrapolated``, ``mode``, ``skipped``). Every available sparse solver backend of
``fem.linsolve`` is measured; MKL (PARDISO) runs with ``--threads`` threads, as torch does.
Timings are only meaningful on a quiet machine: the load averages at start and end are recorded.
"""
from __future__ import annotations

import argparse
import ctypes
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
from pathlib import Path

import numpy as np
import scipy
import torch


from torchfra import fem
from torchfra.actuator.candidates import KAPPA_T  # C10's prior: logN(1.1 kappa_t, (0.2 kappa_t)^2)
from torchfra.fem.assembly import SparsePattern, scatter_vector
from torchfra.fem.linsolve import Factorization, available_backends, resolve_backend
from torchfra.fem.structured import box_mesh
from torchfra.runtime import allocator

warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
warnings.filterwarnings("ignore", message="Sparse invariant checks")

DTYPE = torch.float64
BOX_MM = (16.0, 16.0, 60.0)  # the actuator body (DESIGN §3)
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
    superlu_max_unknowns: int = 20_000  # SuperLU is skipped above this (51k unknowns: > 20 min)
    multi_rhs: int = 100  # right-hand sides of the PARDISO multi-RHS solve
    pilot_members: int = 8
    seed: int = 0


PILOT_DIVISIONS = (2, 2, 4)
FULL = Config(divisions=[(8, 8, 16), (16, 16, 16)], members=[1, 100])
# Tiny meshes; the small memory budget makes the member-chunked paths run.
QUICK = Config(divisions=[(2, 2, 4), (2, 2, 8)], members=[1, 4], repeat_budget_s=1.0, chunk_budget_s=3.0,
               newton_budget_s=12.0, memory_budget_mb=4.0, pilot_members=2)

QUICK_FORWARD_MEMBERS = 8
_START = time.perf_counter()


def log(message: str) -> None:
    print(f"[bench {time.perf_counter() - _START:7.1f} s] {message}", file=sys.stderr, flush=True)


# -- timing ----------------------------------------------------------------------------------------
def clock(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def measure(fn, cfg: Config, cleanup=None):
    """Timing record of ``fn()`` and its last output (see DEFINITIONS['timing record']); ``cleanup(out)``
    runs untimed on every output but the last."""
    first, out = clock(fn)
    if first * cfg.repeats > cfg.repeat_budget_s:
        return {"s": first, "runs_s": [first], "warmed_up": False}, out
    runs = []
    for _ in range(cfg.repeats):
        if cleanup is not None:
            cleanup(out)
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


# -- sparse solvers ---------------------------------------------------------------------------------------
def mkl_library():
    """The MKL runtime that pypardiso calls, or None without the pardiso extra."""
    if "pardiso" not in available_backends():
        return None
    import pypardiso

    return pypardiso.PyPardisoSolver().libmkl


def set_mkl_threads(n: int) -> int | None:
    """Threads of PARDISO (MKL's own setting; torch.set_num_threads does not reach it)."""
    lib = mkl_library()
    if lib is None:
        return None
    lib.MKL_Set_Num_Threads(ctypes.c_int(n))
    return int(lib.mkl_get_max_threads())


def release(factorization: Factorization) -> None:
    """Free a PARDISO factorization's MKL memory, which Factorization leaves allocated (pypardiso frees
    it only on request), so that the benchmark's own repeated factorizations do not accumulate it."""
    if factorization.backend == "pardiso":
        factorization._solver.free_memory(everything=True)


def pardiso_phases(K) -> dict:
    """PARDISO reordering + symbolic analysis (phase 11) and numerical factorization (phase 22), timed once."""
    import pypardiso
    import scipy.sparse as sp

    solver = pypardiso.PyPardisoSolver(mtype=11)
    A = sp.csr_matrix(K)
    solver._check_A(A)  # the input preparation pypardiso's factorize does
    b = np.zeros((A.shape[0], 1))
    out = {}
    for name, phase in (("analysis_s", 11), ("numeric_s", 22)):
        solver.set_phase(phase)
        out[name] = clock(lambda: solver._call_pardiso(A, b))[0]
    solver.free_memory(everything=True)
    return out


def available_memory_mb() -> float:
    with open("/proc/meminfo") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith("MemAvailable"))


def pardiso_memory_guard(row: dict, factorizations: int) -> str | None:
    """Why a run of ``factorizations`` PARDISO factorizations through fem.linsolve must not run (their
    factor memory is never freed), or None."""
    need, have = row["factor_memory_mb"] * factorizations, available_memory_mb()
    if need <= 0.5 * have:
        return None
    return (f"Factorization does not free PARDISO's factor memory: {factorizations} factorizations x "
            f"{row['factor_memory_mb']:.0f} MB = {need:.0f} MB > half the available {have:.0f} MB")


# -- the benchmark problem ----------------------------------------------------------------------------
def build(divisions, cfg: Config):
    """Model of the bending block (DEFINITIONS['newton.problem']) and its size/build record."""
    t_mesh, mesh = clock(lambda: box_mesh(BOX_MM, divisions))
    model = fem.Model(mesh, dtype=DTYPE, memory_budget_mb=cfg.memory_budget_mb)
    solid = model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), integration="reduced", dtype=DTYPE))
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


# -- driver ---------------------------------------------------------------------------------------------
def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        return platform.processor()


def environment(mkl_threads: int | None) -> dict:
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "torch": torch.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
        "python": platform.python_version(), "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(), "mkl_threads": mkl_threads,
        "linear_solver_backends": available_backends(),
        "allocator_keeps_freed_memory": allocator.state["tuned"], "allocator": allocator.state["reason"],
        "platform": platform.platform(), "machine": platform.machine(), "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(), "load_average_start": list(os.getloadavg()),
        "memory_available_mb_start": available_memory_mb(),
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


FORWARD_TARGET_MEMBERS = 100
FORWARD_TARGET_S = 600.0  # issue 3: 100-member forward ensemble <= 10 min on this 2-core machine
FORWARD_TARGET_EFFICIENCY = 5.0  # issue 3: batching efficiency >= 5x

FORWARD_DEFINITIONS = {
    "problem": "build_actuator_model(ActuatorGeometry(resolution=--mesh)) (hybrid Hex20 body + embedded fiber "
    "trusses, clamped base, rigid top, cavity pressure P); parameters = torchfra.calibration.forward.member_parameters("
    "ForwardConfig(members=M, resolution=--mesh)) (prior C10 draws, seed 0, D1 = 1/(bulk_ratio C10), E_fiber, "
    "P = full pressure); load factors (1..load_steps)/load_steps as run_forward; NewtonOptions(**ForwardConfig().newton).",
    "single": "wall time of fem.solve(model, params[0:1], load, options): member 0 of the ensemble solved alone.",
    "batch": "wall time of ONE fem.solve(model, params[0:M], load, options) call (all M members in lockstep: "
    "every Newton pass evaluates all active members batched, then factorizes + solves each member's system).",
    "batching_efficiency": "(M x single.wall_s) / batch.wall_s; > 1 means batching beats M separate solves. "
    "Member 0 stands for every member; batch.iterations shows how the members differ.",
    "timings": "Solution.timings: residual = Model.evaluate without tangent (all Newton passes incl. line search "
    "trials); tangent = Model.evaluate with tangent (kernels + assembly + reduction); solve = per-member "
    "Factorization + solve + release of the Newton steps. other_s = wall - sum(timings): the Euler predictor "
    "(_euler_velocity: one tangent + one factorization per member, not in timings), local_update (element "
    "pressure update), the per-member Python bookkeeping, and output displacements. split = fraction of wall.",
    "iterations": "per member: Newton iterations (tangent + linear solve each) summed over all increments; "
    "total = sum over members, max = the slowest member (the batch runs until its slowest member is done, so "
    "the number of batched passes is >= max). increments/cutbacks per member likewise.",
    "extrapolation_100": "present only if M < 100, and labelled an extrapolation, not a measurement. "
    "one_batch_linear_s: one 100-member fem.solve with every phase (residual, tangent, solve, and other, which "
    "is also per member) scaled by 100/M, assuming the same lockstep iteration count as the M batch (a larger "
    "ensemble's slowest member may need more); one_batch_other_fixed_s: the same with other_s held fixed (a "
    "lower bound). run_forward_chunks_s: run_forward as it runs (chunk = ForwardConfig.chunk members per "
    "fem.solve call): ceil(100/chunk) calls of a chunk-member batch, each taken as batch.wall_s x chunk / M. "
    "target_s: the issue's 600 s.",
    "load_average": "os.getloadavg() (1, 5, 15 min) at start and end: other jobs on this 2-core machine slow "
    "every timing.",
}


def forward_solution_record(sol, wall: float) -> dict:
    timings = dict(sol.timings)
    other = wall - sum(timings.values())
    return {
        "wall_s": wall, "timings": timings, "other_s": other,
        "split": {**{k: v / wall for k, v in timings.items()}, "other": other / wall},
        "converged_members": int(sol.converged.sum()), "status": sol.status.tolist(),
        "load_reached": sol.load_reached.tolist(),
        "iterations": {"per_member": sol.iterations.tolist(), "total": int(sol.iterations.sum()),
                       "max": int(sol.iterations.max()), "mean": float(sol.iterations.mean())},
        "increments": {"per_member": sol.increments.tolist(), "max": int(sol.increments.max())},
        "cutbacks": {"per_member": sol.cutbacks.tolist(), "max": int(sol.cutbacks.max())},
    }


def forward_suite(cfg: Config, args) -> dict:
    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import member_parameters

    M = args.forward_members
    fcfg = ForwardConfig(members=M, resolution=args.mesh, load_steps=args.load_steps, threads=args.threads)
    t_build, (model, info) = clock(lambda: build_actuator_model(ActuatorGeometry(resolution=fcfg.resolution)))
    t_finalize = clock(model.finalize)[0]
    mesh_info = {"resolution": fcfg.resolution, "bricks": info.get("elements"), "fiber_elements": info.get("fiber_elements"),
                 "nodes": info.get("nodes"), "reduced_dofs": int(model.n_red), "build_s": t_build,
                 "finalize_s": t_finalize}
    params = member_parameters(fcfg)
    load = np.arange(1, fcfg.load_steps + 1) / fcfg.load_steps
    options = fem.NewtonOptions(**fcfg.newton)
    log(f"forward: resolution {fcfg.resolution}, {mesh_info['bricks']} bricks, {mesh_info['fiber_elements']} fibers, "
        f"{model.n_red} dofs, {fcfg.load_steps} load steps, {M} members, "
        f"linear solver {resolve_backend(options.linear_solver, model.n_red)}")

    log("  1 member alone")
    wall1, sol1 = clock(lambda: fem.solve(model, {k: v[:1] for k, v in params.items()}, load, options))
    single = forward_solution_record(sol1, wall1)
    log(f"    {wall1:.1f} s, {single['iterations']['total']} iterations, timings "
        f"{ {k: round(v, 1) for k, v in single['timings'].items()} }, other {single['other_s']:.1f} s")
    del sol1
    gc.collect()

    log(f"  {M} members in one fem.solve")
    wallM, solM = clock(lambda: fem.solve(model, params, load, options))
    batch = forward_solution_record(solM, wallM)
    log(f"    {wallM:.1f} s, iterations per member {batch['iterations']['per_member']}, timings "
        f"{ {k: round(v, 1) for k, v in batch['timings'].items()} }, other {batch['other_s']:.1f} s")
    del solM

    efficiency = M * wall1 / wallM
    result = {
        "config": {**dataclasses.asdict(fcfg), "newton_options": dataclasses.asdict(options),
                   "load_factors": load.tolist(), "linear_solver": resolve_backend(options.linear_solver, model.n_red)},
        "mesh": mesh_info,
        "parameters": {k: v.tolist() for k, v in params.items() if k == "C10"},
        "single": single, "batch": {"members": M, **batch},
        "batching_efficiency": efficiency,
        "per_member_in_batch_s": wallM / M,
        "phase_per_member_s": {"single": {**single["timings"], "other": single["other_s"]},
                               "batch": {**{k: v / M for k, v in batch["timings"].items()}, "other": batch["other_s"] / M}},
        "targets": {"members": FORWARD_TARGET_MEMBERS, "wall_s": FORWARD_TARGET_S,
                    "batching_efficiency": FORWARD_TARGET_EFFICIENCY,
                    "efficiency_met": efficiency >= FORWARD_TARGET_EFFICIENCY},
    }
    if M == FORWARD_TARGET_MEMBERS:
        result["targets"]["wall_met"] = wallM <= FORWARD_TARGET_S
    else:
        scale = FORWARD_TARGET_MEMBERS / M
        per_member = sum(batch["timings"].values())
        linear = scale * wallM
        fixed = scale * per_member + batch["other_s"]
        chunk_calls = math.ceil(FORWARD_TARGET_MEMBERS / fcfg.chunk)
        chunks = chunk_calls * wallM * fcfg.chunk / M
        result["extrapolation_100"] = {
            "label": f"EXTRAPOLATION from the measured {M}-member batch, not a measurement",
            "from_members": M, "one_batch_linear_s": linear, "one_batch_other_fixed_s": fixed,
            "run_forward_chunks_s": chunks, "chunk": fcfg.chunk,
            "target_s": FORWARD_TARGET_S, "within_target": max(linear, chunks) <= FORWARD_TARGET_S,
            "ratio_to_target": linear / FORWARD_TARGET_S,
        }
        log(f"  EXTRAPOLATED 100 members: {linear:.0f} s (other fixed: {fixed:.0f} s, run_forward chunks: "
            f"{chunks:.0f} s) vs target {FORWARD_TARGET_S:.0f} s")
    phases = {**batch["timings"], "other": batch["other_s"]}
    result["dominant_phase"] = max(phases, key=phases.get)
    log(f"  batching efficiency {efficiency:.2f}x (target {FORWARD_TARGET_EFFICIENCY}x); dominant phase "
        f"{result['dominant_phase']} ({phases[result['dominant_phase']] / wallM:.0%} of the batch)")
    return result


def sensitivity_suite(cfg: Config, args) -> dict:
    """One actuator solve and the exact sensitivities of its states to d parameters (C10, D1,
    E_fiber, C01, density, c_n, c_t: every candidate term switched on at its null), measured side by
    side; the fraction is what the sensitivities cost relative to the solve they come from."""
    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
    from torchfra.fem.sensitivity import sensitivities

    model, info = build_actuator_model(ActuatorGeometry(resolution=args.mesh), material=fem.MooneyRivlin(),
                                       base="compliant", gravity=(0.0, -1.0, 0.0))
    model.finalize()
    load = np.arange(1, args.load_steps + 1) / args.load_steps
    theta = {"C10": torch.tensor([0.0062], dtype=torch.float64), "C01": torch.zeros(1, dtype=torch.float64),
             "D1": torch.tensor([1 / 6.2], dtype=torch.float64), "E_fiber": torch.tensor([31000.0], dtype=torch.float64),
             "density": torch.zeros(1, dtype=torch.float64), "c_n": torch.tensor([1e-4], dtype=torch.float64),
             "c_t": torch.tensor([1e-4], dtype=torch.float64)}

    def params_of(th):
        return {**th, "P": torch.full((1,), 0.022, dtype=torch.float64)}

    options = fem.NewtonOptions(stagnation_tol=1e-6)
    log(f"sensitivity: resolution {args.mesh}, {model.n_red} dofs, {args.load_steps} load steps, d = {len(theta)}")
    wall_solve, sol = clock(lambda: fem.solve(model, params_of(theta), load, options))
    wall_sens, S = clock(lambda: sensitivities(model, params_of, theta, sol))
    log(f"  solve {wall_solve:.1f} s ({int(sol.iterations[0])} iterations); sensitivities of {len(theta)} parameters "
        f"at {len(load)} load steps {wall_sens:.1f} s = {wall_sens / wall_solve:.0%} of the solve")
    return {"resolution": args.mesh, "dofs": int(model.n_red), "load_steps": args.load_steps, "parameters": list(theta),
            "solve_s": wall_solve, "newton_iterations": int(sol.iterations[0]), "sensitivities_s": wall_sens,
            "fraction_of_solve": wall_sens / wall_solve, "sensitivity_phases_s": S.timings}


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


DEVICE_DEFINITIONS = {
    "kernel": "fem.Hex20Solid.evaluate of the actuator's bricks (hybrid, 3x3x3 Gauss points, Neo-Hookean): "
    "residual and element tangents of every brick for M members at a random displacement of strain ~1 % "
    "(KERNEL_AMPLITUDE), what a Newton iteration's tangent costs before assembly. CPU: member-chunked as "
    "Model.evaluate does (chunk_size members at a time), torch threads = --threads. CUDA: all M members at "
    "once, the term's tensors moved to the GPU, timed between torch.cuda.synchronize() calls.",
    "member_elements_per_s": "M x bricks / s",
    "deviation": "max |CUDA - CPU| / max |CPU| over the first member's residual and tangents (float64 both)",
    "scope": "the element kernel only: a measurement towards an optional CUDA path; assembly, the constraint "
    "reduction and the sparse factorization stay on the CPU in torchfra",
}


def _term_to(term, device):
    """A copy of ``term`` with every tensor attribute (its material's too) on ``device``."""
    import copy

    out = copy.copy(term)
    for k, v in vars(term).items():
        if torch.is_tensor(v):
            setattr(out, k, v.to(device))
    mat = copy.copy(term.material)
    for k, v in vars(term.material).items():
        if torch.is_tensor(v):
            setattr(mat, k, v.to(device))
    out.material = mat
    return out


def device_suite(cfg: Config, args) -> dict:
    """The brick kernel on the CPU and, when present, on CUDA, side by side (DEVICE_DEFINITIONS)."""
    import traceback

    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model

    model, info = build_actuator_model(ActuatorGeometry(resolution=args.mesh))
    model.finalize()
    solid = next(t for t in model.terms if isinstance(t, fem.Hex20Solid))
    E = solid.conn.shape[0]
    counts = [int(v) for v in args.members.split(",")] if args.members else ([1, 4] if args.quick else [1, 10, 100])
    edge = float(np.min(np.linalg.norm(np.diff(model.mesh.nodes[model.mesh.elements[:, :2]], axis=1), axis=-1)))
    chunk = model._chunk_size()
    log(f"device: resolution {args.mesh}, {E} bricks, members {counts}, CPU chunk {chunk}, "
        f"CUDA {'available: ' + torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'not available'}")
    rows, reference = [], {}
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        term = solid if device == "cpu" else _term_to(solid, device)
        for n in counts:
            row = {"device": device, "members": n, "bricks": E}
            try:
                params = {k: v.to(device) for k, v in member_params(n, cfg.seed).items()}
                g = torch.Generator().manual_seed(cfg.seed)
                u = (KERNEL_AMPLITUDE * edge * torch.randn(n, model.n_nodes, 3, generator=g, dtype=DTYPE)).to(device)
                lam = torch.ones(n, dtype=DTYPE, device=device)

                def run(lo, hi):
                    out = term.evaluate(u[lo:hi], members(params, slice(lo, hi)), lam[lo:hi], tangent=True)
                    if device == "cuda":
                        torch.cuda.synchronize()
                    return out

                if device == "cpu":
                    rec = measure_members(run, n, chunk, cfg)
                else:
                    run(0, n)  # warm-up: kernels compiled, memory pooled
                    rec, _ = measure(lambda: run(0, n), cfg)
                row.update(rec)
                row["member_elements_per_s"] = n * E / rec["s"]
                first = run(0, 1)
                fe, Ke = first.fe.double().cpu(), first.Ke.double().cpu()
                if device == "cpu" and n == counts[0]:
                    reference = {"fe": fe, "Ke": Ke}
                elif device != "cpu":
                    row["deviation"] = max(float((fe - reference["fe"]).abs().max() / reference["fe"].abs().max()),
                                           float((Ke - reference["Ke"]).abs().max() / reference["Ke"].abs().max()))
                if device == "cuda":
                    row["peak_memory_mb"] = torch.cuda.max_memory_allocated() / 2**20
                log(f"  {device}, {n} members: {rec['s']:.4f} s, {row['member_elements_per_s']:.4g} member-elements/s"
                    + (f", deviation {row['deviation']:.2e}" if "deviation" in row else ""))
            except Exception as exc:  # a device that cannot run the kernel is reported, not fatal
                row["error"] = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                row["traceback"] = traceback.format_exc()
                log(f"  {device}, {n} members: {row['error']}")
            rows.append(row)
    speedups = {}
    for n in counts:
        cpu = next((r for r in rows if r["device"] == "cpu" and r["members"] == n and "s" in r), None)
        gpu = next((r for r in rows if r["device"] == "cuda" and r["members"] == n and "s" in r), None)
        if cpu and gpu:
            speedups[str(n)] = cpu["s"] / gpu["s"]
    return {"mesh": {"resolution": args.mesh, "bricks": E, "nodes": int(model.n_nodes)},
            "threads": torch.get_num_threads(), "rows": rows, "cuda_over_cpu": speedups,
            "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


SUITES = {"fem": lambda cfg, args: fem_suite(cfg), "forward": forward_suite, "sensitivity": sensitivity_suite,
          "ensemble": ensemble_suite, "device": device_suite}


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
    parser.add_argument("--threads", type=int, default=1, help="torch and MKL (PARDISO) threads (default 1)")
    parser.add_argument("--quick", action="store_true", help="tiny meshes and ensembles: a smoke test, < 1 min")
    parser.add_argument("--meshes", help="divisions to run instead of the suite's, e.g. 8x8x16,16x16x16")
    parser.add_argument("--members", help="fem: member counts instead of the suite's, e.g. 1,100 (1 must come "
                        "first); forward: the ensemble size M (default 100)")
    parser.add_argument("--mesh", type=int, default=1, help="forward: actuator mesh resolution (default 1)")
    parser.add_argument("--load-steps", type=int, default=None,
                        help="forward: output load factors (default 20; 5 with --quick)")
    parser.add_argument("--old-members", type=int, help="ensemble: members solved by the old path too (default all)")
    parser.add_argument("--vary", action="append", metavar="NAME=S", help="ensemble: also draw NAME per member as "
                        "its value x lognormal(0, S), e.g. E_fiber=0.3 (repeatable)")
    parser.add_argument("--newton-budget-s", type=float, help="run a full Newton solve only if estimated below this")
    parser.add_argument("--chunk-budget-s", type=float, help="time budget of one member-chunked measurement")
    parser.add_argument("--superlu-max-unknowns", type=int, help="skip SuperLU on larger systems")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    cfg = dataclasses.replace(QUICK if args.quick else FULL)
    if args.meshes:
        cfg.divisions = [tuple(int(v) for v in m.split("x")) for m in args.meshes.split(",")]
    # --quick: a smoke run of the forward suites too (8 members at 5 load steps, 2 by the old path)
    quick_forward = args.quick and args.suite in ("forward", "ensemble")
    args.forward_members = int(args.members.split(",")[-1]) if args.members else \
        (QUICK_FORWARD_MEMBERS if quick_forward else FORWARD_TARGET_MEMBERS)
    if args.load_steps is None:
        args.load_steps = 5 if quick_forward else 20
    if quick_forward and args.old_members is None:
        args.old_members = 2
    if args.suite in ("forward", "ensemble") and args.forward_members < 1:
        parser.error("--members must be >= 1")
    if args.members and args.suite == "fem":
        cfg.members = [int(v) for v in args.members.split(",")]
    if args.suite == "fem" and cfg.members[0] != 1:
        parser.error("--members must start with 1 (the single-member runs feed the estimates)")
    if args.newton_budget_s is not None:
        cfg.newton_budget_s = args.newton_budget_s
    if args.chunk_budget_s is not None:
        cfg.chunk_budget_s = args.chunk_budget_s
    if args.superlu_max_unknowns is not None:
        cfg.superlu_max_unknowns = args.superlu_max_unknowns

    env = environment(set_mkl_threads(args.threads))
    log(f"suite {args.suite}, {'quick' if args.quick else 'full'}, {torch.get_num_threads()} torch threads, "
        f"{env['mkl_threads']} MKL threads, load average {env['load_average_start']}")
    result = {"suite": args.suite, "quick": args.quick, "environment": env, **SUITES[args.suite](cfg, args),
              "definitions": {"forward": FORWARD_DEFINITIONS, "ensemble": ENSEMBLE_DEFINITIONS,
                               "device": DEVICE_DEFINITIONS}.get(args.suite, DEFINITIONS)}
    env["load_average_end"] = list(os.getloadavg())
    env["memory_available_mb_end"] = available_memory_mb()
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
    from torchfra.cli.run import run

    run(main)
