"""Speckle images of the front face: painted on the material, deformed with it, seen by the camera.

The speckle pattern is a function of the material point ``(y, z)`` of the face (mm, reference
configuration): dark Gaussian dots of diameter ``size`` on a white coat, their centres on a jittered
grid that covers ``coverage`` of the face,

    I(X) = white - (white - black) * (1 - exp(-sum_i exp(-|X - c_i|^2 / (2 s^2)))),   s = size / 4,

so a deformed image needs no interpolation of grey levels: each camera sample point ``x`` (mm on
the image plane) sees the material point ``X`` with ``X + u(X) = x`` (the backward warp), found by
Newton on the displacement field of the face (:class:`FaceField`, bicubic in the material
coordinates, with its exact gradient), started from the nearest point of a coarse forward-mapped
grid. A sample point that sees no material point of the face sees the background. A pixel's grey
level is the mean over ``supersample`` x ``supersample`` sample points (its area), then grey-level
noise N(0, noise^2) is added and the image quantized to ``bits``.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.spatial import cKDTree

from torchfra.lab.camera import Camera

WHITE, BLACK, BACKGROUND = 0.85, 0.10, 0.05  # grey levels of the coat, a dot's core and what lies behind


class SpeckleError(ValueError):
    """A speckle pattern or warp that cannot be made; the message names the setting."""


@dataclass(frozen=True)
class Speckle:
    """Dots painted on the face: centres (N, 2) material (y, z) mm, ``size`` their diameter (mm);
    ``bounds`` ((ylo, yhi), (zlo, zhi)) the painted face."""

    centres: np.ndarray
    size: float
    bounds: tuple

    @cached_property
    def tree(self) -> cKDTree:
        """The dots' centres, for the nearest-dots queries of :meth:`intensity`."""
        return cKDTree(self.centres)

    def on_face(self, X, tol: float = 1e-9) -> np.ndarray:
        """(M,) True for material points (M, 2) inside the painted face."""
        (ylo, yhi), (zlo, zhi) = self.bounds
        return ((X[:, 0] >= ylo - tol) & (X[:, 0] <= yhi + tol) & (X[:, 1] >= zlo - tol) & (X[:, 1] <= zhi + tol))

    def intensity(self, X) -> np.ndarray:
        """(M,) grey level in [0, 1] of material points (M, 2) mm (the formula of the module's docstring)."""
        X = np.asarray(X, dtype=np.float64)
        s = self.size / 4.0
        dist, _ = self.tree.query(X, k=min(16, len(self.centres)), distance_upper_bound=5.0 * s)
        dist = np.atleast_2d(dist.T).T
        g = np.exp(-np.where(np.isfinite(dist), dist, np.inf) ** 2 / (2.0 * s * s)).sum(axis=1)
        return WHITE - (WHITE - BLACK) * (1.0 - np.exp(-g))


def speckle_pattern(bounds, size: float, coverage: float = 0.5, seed: int = 0) -> Speckle:
    """Dots of diameter ``size`` mm on the face ``bounds`` ((ylo, yhi), (zlo, zhi)) mm, one per cell of
    a grid whose cells hold ``coverage`` of dot area (pi size^2 / 4 per cell), each jittered uniformly
    within its cell (``seed``); the grid reaches one cell past the face so its edges are painted too."""
    if not (np.isfinite(size) and size > 0):
        raise SpeckleError(f"speckle size must be a positive diameter in mm, got {size}")
    if not 0 < coverage < 1:
        raise SpeckleError(f"speckle coverage must lie in (0, 1), got {coverage}")
    (ylo, yhi), (zlo, zhi) = sorted(bounds[0]), sorted(bounds[1])
    a = np.sqrt(np.pi * size * size / 4.0 / coverage)
    ys = np.arange(ylo - a, yhi + a, a)
    zs = np.arange(zlo - a, zhi + a, a)
    Y, Z = np.meshgrid(ys, zs, indexing="ij")
    rng = np.random.default_rng(seed)
    centres = np.stack([Y.ravel(), Z.ravel()], axis=1) + rng.uniform(0.0, a, (Y.size, 2))
    return Speckle(centres, float(size), ((ylo, yhi), (zlo, zhi)))


class FaceField:
    """The displacement (ux, uy, uz) of the front face as bicubic splines of the material (y, z).

    Parameters
    ----------
    y, z : array (ny,), (nz,)
        Increasing ticks (mm) of a grid that covers the face.
    U : array (ny, nz, 3)
        Displacements (ux, uy, uz) in mm at the grid's points (e.g. the FE solution through
        :class:`torchfra.observation.operator.ObservationOperator`).
    """

    def __init__(self, y, z, U):
        y, z, U = np.asarray(y, float), np.asarray(z, float), np.asarray(U, float)
        if U.shape != (len(y), len(z), 3):
            raise SpeckleError(f"U must be (ny, nz, 3) = ({len(y)}, {len(z)}, 3), got {U.shape}")
        k = 3 if min(len(y), len(z)) > 3 else 1
        self.splines = [RectBivariateSpline(y, z, U[..., c], kx=k, ky=k) for c in range(3)]

    @classmethod
    def affine(cls, bounds, A, b, ux=None) -> "FaceField":
        """The field ``(uy, uz) = A @ (y, z) + b`` (ux: a constant, default 0) on ``bounds``."""
        (ylo, yhi), (zlo, zhi) = bounds
        y, z = np.linspace(ylo - 1, yhi + 1, 9), np.linspace(zlo - 1, zhi + 1, 9)
        Y, Z = np.meshgrid(y, z, indexing="ij")
        A, b = np.asarray(A, float), np.asarray(b, float)
        U = np.zeros(Y.shape + (3,))
        U[..., 1] = A[0, 0] * Y + A[0, 1] * Z + b[0]
        U[..., 2] = A[1, 0] * Y + A[1, 1] * Z + b[1]
        U[..., 0] = 0.0 if ux is None else ux
        return cls(y, z, U)

    def __call__(self, X) -> np.ndarray:
        """(M, 3) displacements (ux, uy, uz) mm at material points X (M, 2) = (y, z) mm."""
        return np.stack([s.ev(X[:, 0], X[:, 1]) for s in self.splines], axis=1)

    def gradient(self, X) -> np.ndarray:
        """(M, 3, 2) d(ux, uy, uz)/d(y, z) at material points X (M, 2)."""
        return np.stack([np.stack([s.ev(X[:, 0], X[:, 1], dx=1), s.ev(X[:, 0], X[:, 1], dy=1)], axis=1)
                         for s in self.splines], axis=1)


def seen_material(camera: Camera, x, field: FaceField | None, speckle: Speckle, iterations: int = 12,
                  tol: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
    """The material points (M, 2) mm that the image-plane points ``x`` (M, 2) mm see, and (M,) True
    where one exists on the face: the solution of ``apparent(X + u(X)) = x`` (backward warp;
    ``field`` None: the reference, ``X = x``). ``tol``: largest image-plane residual (mm) taken as seen."""
    x = np.asarray(x, dtype=np.float64)
    if field is None:
        return x.copy(), speckle.on_face(x)
    (ylo, yhi), (zlo, zhi) = speckle.bounds
    h = 2.0 * camera.pixel_size  # a coarse forward-mapped grid gives each Newton its start
    gy = np.linspace(ylo, yhi, max(3, int(np.ceil((yhi - ylo) / h)) + 1))
    gz = np.linspace(zlo, zhi, max(3, int(np.ceil((zhi - zlo) / h)) + 1))
    G = np.stack(np.meshgrid(gy, gz, indexing="ij"), axis=-1).reshape(-1, 2)
    gap, nearest = cKDTree(_forward(camera, field, G)).query(x)
    X = G[nearest]
    r = np.linalg.norm(_forward(camera, field, X) - x, axis=1)
    # Newton only where not yet converged, and not where no grid point came near (the background)
    active = np.flatnonzero((r > 1e-3 * tol) & (gap < 4.0 * h))
    for _ in range(iterations):
        if active.size == 0:
            break
        Xa = X[active]
        U, dU = field(Xa), field.gradient(Xa)
        res = _forward(camera, field, Xa, U) - x[active]
        step = np.linalg.solve(_forward_jacobian(camera, Xa, U, dU), res[..., None])[..., 0]
        X[active] = Xa - step
        r[active] = np.linalg.norm(_forward(camera, field, X[active]) - x[active], axis=1)
        active = active[r[active] > 1e-3 * tol]
    return X, (r <= tol) & speckle.on_face(X)


def _forward(camera: Camera, field: FaceField, X, U=None) -> np.ndarray:
    """Where the camera sees material points X (M, 2) after the displacement: apparent(X + u)."""
    U = field(X) if U is None else U
    return camera.apparent(X + U[:, 1:3], U[:, 0])


def _forward_jacobian(camera: Camera, X, U, dU) -> np.ndarray:
    """(M, 2, 2) d apparent(X + u(X)) / dX."""
    F = np.eye(2) + dU[:, 1:3, :]
    if camera.working_distance is None:
        return F
    D = camera.working_distance
    m = camera.magnification(U[:, 0])
    dm = (D / (D - U[:, 0]) ** 2)[:, None] * dU[:, 0, :]  # (M, 2)
    p = X + U[:, 1:3] - camera.axis
    return m[:, None, None] * F + p[:, :, None] * dm[:, None, :]


def render(camera: Camera, speckle: Speckle, field: FaceField | None = None, supersample: int = 2,
           noise: float = 0.0, bits: int | None = 8, rng: np.random.Generator | None = None) -> np.ndarray:
    """The camera's image (rows, cols) float32 in [0, 1] of the speckled face displaced by ``field``
    (None: the reference image); grey-level ``noise`` (std, in the [0, 1] range) from ``rng``,
    then quantized to ``bits`` (None: not quantized)."""
    if noise < 0:
        raise SpeckleError(f"grey-level noise must be >= 0, got {noise}")
    rows, cols = camera.shape
    s = int(supersample)
    samples = camera.pixel_centres(s).reshape(-1, 2)
    x = camera.to_model(samples)
    X, seen = seen_material(camera, x, field, speckle)
    grey = np.full(len(x), BACKGROUND)
    grey[seen] = speckle.intensity(X[seen])
    image = grey.reshape(rows, s, cols, s).mean(axis=(1, 3))
    if noise > 0:
        image = image + noise * (rng or np.random.default_rng()).standard_normal(image.shape)
    image = np.clip(image, 0.0, 1.0)
    if bits is not None:
        levels = 2 ** int(bits) - 1
        image = np.round(image * levels) / levels
    return image.astype(np.float32)


def face_mask(camera: Camera, speckle: Speckle, inset: float = 0.0) -> np.ndarray:
    """(rows, cols) bool: pixels whose centre sees the reference face, ``inset`` mm inside its edges
    (the region of interest given to a DIC engine)."""
    x = camera.to_model(camera.pixel_centres(1).reshape(-1, 2))
    (ylo, yhi), (zlo, zhi) = speckle.bounds
    inside = ((x[:, 0] >= ylo + inset) & (x[:, 0] <= yhi - inset) & (x[:, 1] >= zlo + inset)
              & (x[:, 1] <= zhi - inset))
    return inside.reshape(camera.shape)
