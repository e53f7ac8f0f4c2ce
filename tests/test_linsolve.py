"""Both sparse direct solver backends give the same Newton steps (when PARDISO is installed)."""
import numpy as np
import scipy.sparse as sp

from torchfra.fem.linsolve import Factorization, SingularMatrixError, SparseSolver, available_backends


def test_backends_solve_a_nonsymmetric_system():
    rng = np.random.default_rng(0)
    A = sp.random(200, 200, density=0.05, random_state=1) + sp.eye(200) * 5
    b = rng.standard_normal((200, 3))
    for backend in available_backends():
        x = Factorization(A, backend).solve(b)
        assert np.abs(A @ x - b).max() < 1e-10


def test_symmetric_indefinite_system():
    """``symmetric=True`` (PARDISO: upper triangle, Bunch-Kaufman) solves a symmetric indefinite
    system as accurately as the general LU does."""
    rng = np.random.default_rng(2)
    B = sp.random(300, 300, density=0.03, random_state=3)
    A = (B + B.T + sp.diags(rng.choice([-4.0, 4.0], 300))).tocsr()  # eigenvalues of both signs
    b = rng.standard_normal((300, 2))
    for backend in available_backends():
        x = Factorization(A, backend, symmetric=True).solve(b)
        assert np.abs(A @ x - b).max() < 1e-10
        assert np.abs(x - Factorization(A, backend).solve(b)).max() < 1e-10


def test_sparse_solver_reuses_the_analysis_of_a_pattern():
    """A sequence of matrices (symmetric and not): every solve is that of its own matrix; PARDISO
    analyses a pattern once and again only when the pattern changes."""
    rng = np.random.default_rng(4)
    B = sp.random(1200, 1200, density=0.004, random_state=5)
    pattern = (B + B.T + sp.eye(1200)).tocsr()
    other = (pattern + sp.eye(1200, k=7) + sp.eye(1200, k=-7)).tocsr()
    b = rng.standard_normal(1200)
    for backend in available_backends():
        for symmetric in (True, False):
            solver = SparseSolver(backend, symmetric)
            for P in (pattern, pattern, other, other):
                A = P.copy()
                A.data = rng.standard_normal(A.nnz)
                A = A + A.T + sp.diags(np.full(1200, 8.0)) if symmetric else A + sp.diags(np.full(1200, 8.0))
                solver.factorize(A)
                x = solver.solve(b)
                assert np.abs(A @ x - b).max() < 1e-9
            assert solver.analyses == (2 if backend == "pardiso" else 0)
            solver.release()


def test_singular_matrix_is_reported():
    A = sp.csr_matrix(np.array([[1.0, 2.0], [2.0, 4.0]]))
    try:
        x = Factorization(A, "superlu").solve(np.ones(2))
    except SingularMatrixError:
        return
    assert not np.all(np.isfinite(x))
