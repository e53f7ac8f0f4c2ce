"""Reference elements: shape functions and Gauss rules.

Node orders follow Abaqus (identical to meshio/VTK for these types):

- Hex20 (C3D20): corners 0-7 with natural coordinates (xi, eta, zeta) in
  ``HEX20_NATURAL[:8]``; mid-edge nodes 8-11 on the bottom edges (0-1, 1-2, 2-3, 3-0),
  12-15 on the top edges (4-5, 5-6, 6-7, 7-4), 16-19 on the vertical edges (0-4, 1-5, 2-6, 3-7).
- Quad8 (a Hex20 face): corners 0-3, then mid-edge nodes on edges 0-1, 1-2, 2-3, 3-0.
- Line3 (T3D3): end nodes 0, 1 at s = -1, +1 and the middle node 2 at s = 0.

Abaqus face numbering S1..S6 of a Hex20 is ``HEX20_FACES`` (0-based rows); with that node order
``x_s x x_t`` of the face points *into* the element, so the outward area vector is
``-(x_s x x_t) ds dt``.
"""
from __future__ import annotations

import numpy as np
import torch

HEX20_NATURAL = np.array(
    [
        [-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
        [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1],
        [0, -1, -1], [1, 0, -1], [0, 1, -1], [-1, 0, -1],
        [0, -1, 1], [1, 0, 1], [0, 1, 1], [-1, 0, 1],
        [-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0],
    ],
    dtype=np.float64,
)

# Corner pair of every mid-edge node 8..19 (used to check node order).
HEX20_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
)

# Abaqus faces S1..S6 as Quad8 node lists (corners, then mid-edges).
HEX20_FACES = np.array(
    [
        [0, 1, 2, 3, 8, 9, 10, 11],
        [4, 7, 6, 5, 15, 14, 13, 12],
        [0, 4, 5, 1, 16, 12, 17, 8],
        [1, 5, 6, 2, 17, 13, 18, 9],
        [2, 6, 7, 3, 18, 14, 19, 10],
        [3, 7, 4, 0, 19, 15, 16, 11],
    ]
)

QUAD8_NATURAL = np.array(
    [[-1, -1], [1, -1], [1, 1], [-1, 1], [0, -1], [1, 0], [0, 1], [-1, 0]], dtype=np.float64
)


def gauss_1d(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre points and weights on [-1, 1]."""
    return np.polynomial.legendre.leggauss(n)


def gauss_hex(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss rule on the cube: points (n^3, 3), weights (n^3,)."""
    x, w = gauss_1d(n)
    pts = np.array([[a, b, c] for c in x for b in x for a in x])
    wts = np.array([wa * wb * wc for wc in w for wb in w for wa in w])
    return pts, wts


def gauss_quad(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss rule on the square: points (n^2, 2), weights (n^2,)."""
    x, w = gauss_1d(n)
    pts = np.array([[a, b] for b in x for a in x])
    wts = np.array([wa * wb for wb in w for wa in w])
    return pts, wts


def hex20_shape(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Serendipity Hex20 shape functions at natural points.

    xi: (P, 3). Returns N: (P, 20) and dN/dxi: (P, 20, 3).
    """
    xi = np.atleast_2d(xi)
    x, y, z = (xi[:, i : i + 1] for i in range(3))
    a, b, c = (HEX20_NATURAL[None, :, i] for i in range(3))
    N = np.zeros((xi.shape[0], 20))
    dN = np.zeros((xi.shape[0], 20, 3))
    corner = np.zeros(20, dtype=bool)
    corner[:8] = True
    # corners: 1/8 (1+x a)(1+y b)(1+z c)(x a + y b + z c - 2)
    fa, fb, fc = 1 + x * a, 1 + y * b, 1 + z * c
    s = x * a + y * b + z * c - 2
    Nc = fa * fb * fc * s / 8
    dNc = np.stack(
        [
            a * fb * fc * (s + fa) / 8,
            b * fa * fc * (s + fb) / 8,
            c * fa * fb * (s + fc) / 8,
        ],
        axis=-1,
    )
    # mid-edge nodes: the zero natural coordinate carries the (1 - t^2) bubble
    ga = np.where(a == 0, 1 - x**2, 1 + x * a)
    gb = np.where(b == 0, 1 - y**2, 1 + y * b)
    gc = np.where(c == 0, 1 - z**2, 1 + z * c)
    dga = np.where(a == 0, -2 * x, a)
    dgb = np.where(b == 0, -2 * y, b)
    dgc = np.where(c == 0, -2 * z, c)
    Nm = ga * gb * gc / 4
    dNm = np.stack([dga * gb * gc / 4, ga * dgb * gc / 4, ga * gb * dgc / 4], axis=-1)
    N[:, corner] = Nc[:, corner]
    N[:, ~corner] = Nm[:, ~corner]
    dN[:, corner] = dNc[:, corner]
    dN[:, ~corner] = dNm[:, ~corner]
    return N, dN


def hex20_shape_values(xi: torch.Tensor) -> torch.Tensor:
    """N (P, 20) of the Hex20 shape functions at natural points ``xi`` (P, 3), in torch, so that it
    differentiates with respect to ``xi`` (forward and reverse mode); the functions of
    :func:`hex20_shape` (pinned by tests)."""
    nat = torch.as_tensor(HEX20_NATURAL, dtype=xi.dtype, device=xi.device)
    t = xi[:, None, :]  # (P, 1, 3) against nat (20, 3)
    f = 1 + t * nat
    corner = f.prod(-1) * ((t * nat).sum(-1) - 2) / 8  # 1/8 (1+x a)(1+y b)(1+z c)(x a + y b + z c - 2)
    mid = torch.where(nat == 0, 1 - t**2, f).prod(-1) / 4  # the zero coordinate carries 1 - t^2
    is_corner = torch.zeros(20, dtype=torch.bool, device=xi.device)
    is_corner[:8] = True
    return torch.where(is_corner, corner, mid)


def quad8_shape(st: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Serendipity Quad8 shape functions. st: (P, 2) -> N (P, 8), dN/dst (P, 8, 2)."""
    st = np.atleast_2d(st)
    s, t = st[:, 0:1], st[:, 1:2]
    a, b = QUAD8_NATURAL[None, :, 0], QUAD8_NATURAL[None, :, 1]
    N = np.zeros((st.shape[0], 8))
    dN = np.zeros((st.shape[0], 8, 2))
    fa, fb = 1 + s * a, 1 + t * b
    Nc = fa * fb * (s * a + t * b - 1) / 4
    dNc = np.stack([a * fb * (2 * s * a + t * b) / 4, b * fa * (s * a + 2 * t * b) / 4], axis=-1)
    ga = np.where(a == 0, 1 - s**2, 1 + s * a)
    gb = np.where(b == 0, 1 - t**2, 1 + t * b)
    dga = np.where(a == 0, -2 * s, a)
    dgb = np.where(b == 0, -2 * t, b)
    Nm = ga * gb / 2
    dNm = np.stack([dga * gb / 2, ga * dgb / 2], axis=-1)
    N[:, :4], N[:, 4:] = Nc[:, :4], Nm[:, 4:]
    dN[:, :4], dN[:, 4:] = dNc[:, :4], dNm[:, 4:]
    return N, dN


def line3_shape(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic line shape functions, nodes at s = -1, +1, 0. s: (P,) -> N (P, 3), dN/ds (P, 3)."""
    s = np.atleast_1d(s)[:, None]
    N = np.concatenate([s * (s - 1) / 2, s * (s + 1) / 2, 1 - s**2], axis=1)
    dN = np.concatenate([s - 0.5, s + 0.5, -2 * s], axis=1)
    return N, dN


def linear_pressure_modes(xi: np.ndarray) -> np.ndarray:
    """Element pressure interpolation of the hybrid brick: (1, xi, eta, zeta). xi: (P, 3) -> (P, 4)."""
    xi = np.atleast_2d(xi)
    return np.concatenate([np.ones((xi.shape[0], 1)), xi], axis=1)


def as_tensor(a: np.ndarray, dtype=torch.float64, device=None) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

