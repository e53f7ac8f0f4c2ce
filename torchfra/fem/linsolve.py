"""Sparse direct solvers for the reduced Newton systems.

Measured on a 14,688-dof Hex20 tangent (2.2M nonzeros), one core: SciPy SuperLU factorizes in
~7 s (COLAMD, ~21M factor nonzeros; symmetric orderings do no better), MKL PARDISO (``pypardiso``,
optional extra ``torchfra[pardiso]``) in ~2.5 s, and solves 100 right-hand sides at once in
~2.5 s where SuperLU's multi-RHS path took 45 s. On the 4,218-dof actuator tangent (resolution 1)
PARDISO factorizes in 0.16 s against SuperLU's 0.76 s, and it is no slower from ~1000 unknowns up
(0.007 s vs 0.009 s), so ``"auto"`` takes it when installed and the system has at least
``PARDISO_MIN_SIZE`` unknowns.
"""
from __future__ import annotations

import functools
import os
from importlib import metadata

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class SingularMatrixError(RuntimeError):
    """The tangent is singular (e.g. an unconstrained rigid-body mode)."""


def _point_pypardiso_at_mkl() -> None:
    """pypardiso otherwise searches the whole ``sys.prefix/lib`` tree for libmkl_rt on every solver
    it builds (0.4 s warm, once 67 s with a cold file cache); the mkl wheel's file list says where."""
    if "PYPARDISO_MKL_RT" in os.environ:
        return
    try:
        files = metadata.files("mkl") or []
    except metadata.PackageNotFoundError:
        return
    for f in files:
        if f.name.startswith("libmkl_rt.so") or f.name.startswith("mkl_rt") and f.name.endswith(".dll"):
            os.environ["PYPARDISO_MKL_RT"] = str(f.locate())
            return


def available_backends() -> list[str]:
    out = ["superlu"]
    try:
        import pypardiso  # noqa: F401

        out.append("pardiso")
    except ImportError:
        pass
    return out


PARDISO_MIN_SIZE = 1000


def resolve_backend(name: str, size: int = 0) -> str:
    if name == "auto":
        return "pardiso" if size >= PARDISO_MIN_SIZE and "pardiso" in available_backends() else "superlu"
    if name not in available_backends():
        raise ValueError(f"linear solver {name!r} is not available here; available: {available_backends()}")
    return name


class Factorization:
    """LU factors of one sparse matrix; ``solve(b)`` for b (n,) or (n, k).

    ``symmetric=True`` promises K = K^T (the Hessian of a total potential: see
    ``Model.symmetric_tangent``); PARDISO then factorizes its upper triangle as real symmetric
    indefinite (Bunch-Kaufman pivoting), 0.060 s instead of 0.106 s on the 4,218-dof actuator
    tangent. SuperLU ignores the promise."""

    def __init__(self, K: sp.spmatrix, backend: str = "auto", symmetric: bool = False):
        self.backend = resolve_backend(backend, K.shape[0])
        self._solver = None
        if self.backend == "pardiso":
            _point_pypardiso_at_mkl()
            import pypardiso

            # real symmetric indefinite (-2) on the upper triangle, or real non-symmetric (11): follower loads
            self._K = sp.triu(K, format="csr") if symmetric else sp.csr_matrix(K)
            self._solver = pypardiso.PyPardisoSolver(mtype=-2 if symmetric else 11)
            self._solver.factorize(self._K)
        else:
            try:
                self._lu = spla.splu(sp.csc_matrix(K))
            except RuntimeError as exc:
                raise SingularMatrixError(str(exc)) from exc

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self.backend == "pardiso":
            return self._solver.solve(self._K, b)
        return self._lu.solve(b)

    def release(self) -> None:
        """Free the factors now. PARDISO keeps them in MKL's memory (231 MB at 14k dofs, 1.2 GB at
        51k) until told, so every factorization must be released."""
        if self._solver is not None:
            self._solver.free_memory(everything=True)
            self._solver = None

    def __del__(self):
        self.release()


class SparseSolver:
    """Factorize one matrix after another, all of the same sparsity pattern (the members of an
    ensemble, the iterations of Newton), and solve with the latest.

    With PARDISO the symbolic analysis (fill-reducing ordering, about 45 % of a factorization of
    the actuator tangent) is done once per pattern and reused: numeric factorizations only
    (phase 22) while the pattern stays the same, a new analysis when it changes. Other backends
    factorize each matrix from scratch (:class:`Factorization`).

    >>> solver = SparseSolver("auto", symmetric=True)
    >>> solver.factorize(K1); x1 = solver.solve(b1)
    >>> solver.factorize(K2); x2 = solver.solve(b2)   # same pattern: no new analysis
    >>> solver.release()
    """

    def __init__(self, backend: str = "auto", symmetric: bool = False):
        self.backend, self.symmetric = backend, symmetric
        self.analyses = 0  # symbolic analyses done (PARDISO)
        self._pardiso = None
        self._pattern = None
        self._K = None
        self._lu: Factorization | None = None

    def factorize(self, K: sp.spmatrix) -> None:
        if resolve_backend(self.backend, K.shape[0]) != "pardiso" or not _has_phases():
            self.release()
            self._lu = Factorization(K, self.backend, self.symmetric)
            return
        if self._pardiso is None:
            _point_pypardiso_at_mkl()
            import pypardiso

            self._pardiso = pypardiso.PyPardisoSolver(mtype=-2 if self.symmetric else 11)
        A = sp.triu(K, format="csr") if self.symmetric else sp.csr_matrix(K)
        A.sort_indices()
        same = (self._pattern is not None and np.array_equal(A.indptr, self._pattern[0])
                and np.array_equal(A.indices, self._pattern[1]))
        self._pardiso.set_phase(22 if same else 12)  # numeric factorization only, or analysis + factorization
        from pypardiso.pardiso_wrapper import PyPardisoError

        try:
            self._pardiso._call_pardiso(A, np.zeros((A.shape[0], 1)))
        except PyPardisoError as exc:  # PARDISO's error codes (e.g. a zero pivot)
            self._pattern = None
            raise SingularMatrixError(f"PARDISO factorization failed: {exc}") from exc
        if not same:
            self._pattern = (A.indptr.copy(), A.indices.copy())
            self.analyses += 1
        self._K = A

    def solve(self, b: np.ndarray) -> np.ndarray:
        if self._lu is not None:
            return self._lu.solve(b)
        b = np.asarray(b, dtype=np.float64)
        self._pardiso.set_phase(33)
        x = self._pardiso._call_pardiso(self._K, np.asfortranarray(b.reshape(b.shape[0], -1)))
        return x.reshape(b.shape)

    def release(self) -> None:
        if self._lu is not None:
            self._lu.release()
            self._lu = None
        if self._pardiso is not None:
            self._pardiso.free_memory(everything=True)
            self._pardiso, self._pattern, self._K = None, None, None

    def __del__(self):
        self.release()


@functools.cache
def _has_phases() -> bool:
    """pypardiso exposes PARDISO's phases only through ``set_phase`` and ``_call_pardiso`` (0.4.x);
    without them every matrix is analysed again."""
    try:
        import pypardiso
    except ImportError:
        return False
    return all(hasattr(pypardiso.PyPardisoSolver, m) for m in ("set_phase", "_call_pardiso", "free_memory"))
