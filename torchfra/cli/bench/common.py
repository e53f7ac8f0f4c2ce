"""What every benchmark suite shares: the timing records, the sparse solvers' memory, the bending-block problem,
the environment record."""
from __future__ import annotations

import ctypes
import dataclasses
import datetime
import math
import os
import platform
import statistics
import sys
import time

import numpy as np
import scipy
import torch

from torchfra import fem
from torchfra.actuator.candidates import KAPPA_T  # C10's prior: logN(1.1 kappa_t, (0.2 kappa_t)^2)
from torchfra.fem.assembly import SparsePattern
from torchfra.fem.linsolve import Factorization, available_backends
from torchfra.fem.structured import box_mesh
from torchfra.runtime import allocator


DTYPE = torch.float64
BOX_MM = (16.0, 16.0, 60.0)  # the actuator body (DESIGN §3)
D1 = 0.1  # 1/MPa: K = 2 / D1 = 20 MPa, about 1600 times mu = 2 C10: near-incompressible
P_OVER_C10 = 0.02  # follower pressure on the ymin face / nominal C10; linear beam theory: tip ~ 16 mm
KERNEL_AMPLITUDE = 0.01  # random nodal displacement / smallest element edge (strains of ~1 %)
STATE_AMPLITUDE = 1e-3  # random reduced unknowns for the assembly state (mm and rad)


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



def rounded(x):
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, dict):
        return {k: rounded(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [rounded(v) for v in x]
    return x
