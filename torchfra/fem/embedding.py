"""Embedded points in a Hex20 mesh: host element and natural coordinates by inverse isoparametric
Newton, and the weights of the embedded-element constraint ``u_point = sum_a N_a(xi) u_a``
(DESIGN §3: a linear constraint even at finite strain, located once in the reference configuration).
"""
from __future__ import annotations

import numpy as np

from torchfra.fem.elements import hex20_shape
from torchfra.fem.mesh import Mesh


def locate_points(mesh: Mesh, X: np.ndarray, tol: float = 1e-6, chunk: int = 4_000_000):
    """Host Hex20 element and natural coordinates of every point, by inverse isoparametric Newton.

    X: (n, 3) reference coordinates (mm). Candidates are the elements whose bounding box, padded by
    a tenth of its size, contains the point; Newton runs on all (point, candidate) pairs at once.
    A point belongs to an element if the element's image of its clipped natural coordinates
    ``clip(xi, -1, 1)`` lies within ``tol`` (mm) of it, so points on the boundary (the helix
    touching the outer face) are found. Among several hosts within ``tol`` the most interior
    ``max |xi|`` wins, then the lowest element id: a point on a face shared by two elements (a fiber
    end on a layer boundary) is placed by a fixed rule, not by round-off in the distances (the
    interpolation is continuous across the face, so either host gives the same constraint). Returns ``elements (n,)`` and ``xi (n, 3)`` (clipped).
    """
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    XE = mesh.nodes[mesh.elements]  # (E, 20, 3)
    lo, hi = XE.min(1), XE.max(1)
    pad = 0.1 * (hi - lo).max(1, keepdims=True) + tol
    lo, hi = lo - pad, hi + pad
    step = max(1, chunk // max(1, mesh.n_elements))
    p_idx, e_idx = [], []
    for i in range(0, X.shape[0], step):
        inside = ((X[i : i + step, None] >= lo) & (X[i : i + step, None] <= hi)).all(-1)
        p, e = np.nonzero(inside)
        p_idx.append(p + i)
        e_idx.append(e)
    p_idx, e_idx = np.concatenate(p_idx), np.concatenate(e_idx)

    xi = np.zeros((p_idx.size, 3))
    target = X[p_idx]
    nodes = XE[e_idx]
    active = np.arange(p_idx.size)
    for it in range(40):  # quadratic convergence: ~5 iterations for points inside an element
        N, dN = hex20_shape(xi[active])
        r = target[active] - np.einsum("ka,kai->ki", N, nodes[active])
        J = np.einsum("kai,kaj->kij", nodes[active], dN)
        J[~(np.abs(np.linalg.det(J)) > 1e-300)] = np.eye(3)
        dxi = np.linalg.solve(J, r[..., None])[..., 0]
        step = np.abs(dxi).max(1)
        dxi *= np.minimum(1.0, 0.5 / np.maximum(step, 1e-300))[:, None]  # damped in thin curved bricks
        xi[active] = np.clip(xi[active] + dxi, -3.0, 3.0)
        # converged pairs, and pairs that stay far outside their candidate (not hosts), stop
        far = (np.abs(xi[active]).max(1) > 2.5) if it >= 10 else np.zeros(active.size, dtype=bool)
        active = active[(step > 1e-13) & ~far]
        if active.size == 0:
            break
    xi_c = np.clip(xi, -1.0, 1.0)
    N, _ = hex20_shape(xi_c)
    dist = np.linalg.norm(target - np.einsum("ka,kai->ki", N, nodes), axis=1)
    interior = np.abs(xi).max(1)

    # best pair of every point: most interior (to round-off), then lowest element id
    order = np.lexsort((e_idx, np.round(interior, 9), p_idx))
    order = order[dist[order] <= tol]
    points, first = np.unique(p_idx[order], return_index=True)
    host = np.full(X.shape[0], -1, dtype=np.int64)
    xi_out = np.zeros((X.shape[0], 3))
    host[points] = e_idx[order[first]]
    xi_out[points] = xi_c[order[first]]
    missing = np.flatnonzero(host < 0)
    if missing.size:
        i = int(missing[0])
        near = dist[p_idx == i]
        where = f"the closest element point found is {near.min():.3g} mm away" if near.size else "no element is near it"
        raise ValueError(
            f"point {i} at {X[i].tolist()} lies outside the body ({where}; tol = {tol:g} mm); "
            f"{missing.size} point(s) outside in all. Check the fiber geometry or raise tol"
        )
    return host, xi_out


def embedding_weights(mesh: Mesh, X: np.ndarray, tol: float = 1e-6) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per point, the host nodes (20,) and weights N_a(xi) (20,) with X = sum_a N_a X_a
    (the embedded-element constraint u = sum_a N_a u_a, DESIGN §3)."""
    host, xi = locate_points(mesh, X, tol)
    N, _ = hex20_shape(xi)
    return [(mesh.elements[e], N[k]) for k, e in enumerate(host)]
