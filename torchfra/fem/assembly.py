"""Sparse pattern and scatter, built once per model.

Every term lists the global dofs of its blocks; the union of all block couplings is one CSR
pattern, and each block-matrix entry gets its position in the CSR data array once. An assembly is
then a single ``index_add_`` per term for all members at once.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch


class SparsePattern:
    """CSR pattern of an ``n x n`` matrix assembled from block dof lists ``blocks[t]: (B_t, D_t)``."""

    def __init__(self, n: int, blocks: list[np.ndarray]):
        self.n = n
        keys = [
            (b[:, :, None].astype(np.int64) * n + b[:, None, :]).ravel() for b in blocks
        ]
        unique, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        self.nnz = unique.size
        rows, self.indices = np.divmod(unique, n)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])
        splits = np.cumsum([k.size for k in keys])[:-1]
        self.positions = [torch.as_tensor(p) for p in np.split(inverse, splits)]

    def assemble(self, block_matrices: list[torch.Tensor | None]) -> torch.Tensor:
        """block_matrices[t]: (N, B_t, D_t, D_t) or None -> CSR data (N, nnz)."""
        first = next(K for K in block_matrices if K is not None)
        data = torch.zeros(first.shape[0], self.nnz, dtype=first.dtype, device=first.device)
        for pos, K in zip(self.positions, block_matrices):
            if K is not None:
                data.index_add_(1, pos, K.reshape(K.shape[0], -1))
        return data

    def to_scipy(self, data: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))


def scatter_vector(n: int, dofs: list[np.ndarray], blocks: list[torch.Tensor]) -> torch.Tensor:
    """Sum block vectors ``blocks[t]: (N, B_t, D_t)`` into (N, n)."""
    out = torch.zeros(blocks[0].shape[0], n, dtype=blocks[0].dtype, device=blocks[0].device)
    for d, f in zip(dofs, blocks):
        out.index_add_(1, torch.as_tensor(d).ravel(), f.reshape(f.shape[0], -1))
    return out
