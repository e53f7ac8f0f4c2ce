"""The virtual camera: pixels of its image and millimetres on the actuator's front face, both ways.

The camera looks at the front face x = +8 mm along -x with the model's z axis up in the image, so
an image column runs along +y and an image row (downwards, as image rows count) along -z::

    col = (y - y0) / pixel_size        row = (z0 - z) / pixel_size

with ``(y0, z0)`` the face point seen at the centre of pixel (row 0, col 0). A DIC engine's
displacement ``(u, v)`` in pixels (``v`` positive downwards) is ``(uy, uz) = pixel_size * (u, -v)``
in mm. The camera is telecentric (orthographic) unless it has a ``working_distance``: then it is a
pinhole at that distance (mm) in front of the face, on the axis through the image centre, and a
point that moves out of the plane by ``ux`` (towards the camera) is seen magnified by
``D / (D - ux)`` about that axis, the false in-plane motion that 2-D DIC reads from out-of-plane
motion.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class CameraError(ValueError):
    """A camera that cannot be used; the message names the setting."""


@dataclass(frozen=True)
class Camera:
    """An image of ``shape`` = (rows, cols) pixels of ``pixel_size`` mm on the face.

    Parameters
    ----------
    pixel_size : float
        mm per pixel on the specimen (the camera's calibration).
    shape : tuple of int
        (rows, cols) of the image.
    origin : tuple of float
        model (y, z) in mm seen at the centre of pixel (row 0, col 0).
    working_distance : float, optional
        mm from the pinhole to the face; None for a telecentric lens (no magnification change).
    """

    pixel_size: float
    shape: tuple
    origin: tuple
    working_distance: float | None = None

    def __post_init__(self):
        if not (np.isfinite(self.pixel_size) and self.pixel_size > 0):
            raise CameraError(f"pixel_size must be a positive number of mm per pixel, got {self.pixel_size}")
        if len(self.shape) != 2 or min(self.shape) < 8:
            raise CameraError(f"image shape must be (rows, cols) of at least 8 pixels each, got {self.shape}")
        if self.working_distance is not None and not self.working_distance > 0:
            raise CameraError(f"working_distance must be a positive distance in mm (or None: telecentric), "
                              f"got {self.working_distance}")

    @classmethod
    def framing(cls, pixel_size: float, y_range, z_range, margin: int = 12,
                working_distance: float | None = None) -> "Camera":
        """The smallest image that sees ``y_range`` x ``z_range`` (mm, e.g. the face and every position
        it reaches) with ``margin`` pixels around it."""
        (ylo, yhi), (zlo, zhi) = sorted(y_range), sorted(z_range)
        cols = int(np.ceil((yhi - ylo) / pixel_size)) + 1 + 2 * margin
        rows = int(np.ceil((zhi - zlo) / pixel_size)) + 1 + 2 * margin
        return cls(float(pixel_size), (rows, cols), (ylo - margin * pixel_size, zhi + margin * pixel_size),
                   working_distance)

    @property
    def axis(self) -> np.ndarray:
        """(2,) model (y, z) mm on the optical axis: the image centre."""
        rows, cols = self.shape
        return self.to_model(np.array([[(cols - 1) / 2.0, (rows - 1) / 2.0]]))[0]

    def to_pixels(self, yz) -> np.ndarray:
        """(M, 2) model (y, z) mm -> (M, 2) image (col, row) in pixels (fractional)."""
        yz = np.asarray(yz, dtype=np.float64)
        return np.stack([(yz[:, 0] - self.origin[0]) / self.pixel_size,
                         (self.origin[1] - yz[:, 1]) / self.pixel_size], axis=1)

    def to_model(self, colrow) -> np.ndarray:
        """(M, 2) image (col, row) pixels -> (M, 2) model (y, z) mm on the face."""
        colrow = np.asarray(colrow, dtype=np.float64)
        return np.stack([self.origin[0] + colrow[:, 0] * self.pixel_size,
                         self.origin[1] - colrow[:, 1] * self.pixel_size], axis=1)

    def displacement_to_model(self, uv) -> np.ndarray:
        """(..., 2) engine displacements (u, v) in pixels, v positive downwards -> (..., 2) (uy, uz) mm."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([uv[..., 0], -uv[..., 1]], axis=-1) * self.pixel_size

    def displacement_to_pixels(self, uyz) -> np.ndarray:
        """(..., 2) (uy, uz) mm -> (..., 2) (u, v) pixels, v positive downwards (inverse of
        :meth:`displacement_to_model`)."""
        uyz = np.asarray(uyz, dtype=np.float64)
        return np.stack([uyz[..., 0], -uyz[..., 1]], axis=-1) / self.pixel_size

    def magnification(self, ux) -> np.ndarray:
        """Apparent magnification ``D / (D - ux)`` of points moved ``ux`` mm towards the camera (1 when
        telecentric)."""
        ux = np.asarray(ux, dtype=np.float64)
        if self.working_distance is None:
            return np.ones_like(ux)
        if np.any(ux >= self.working_distance):
            raise CameraError(f"a point moves {float(np.max(ux)):.3g} mm towards the camera, past its working "
                              f"distance of {self.working_distance:g} mm")
        return self.working_distance / (self.working_distance - ux)

    def apparent(self, yz, ux) -> np.ndarray:
        """(M, 2) where the camera sees points at model (y, z) mm that sit ``ux`` (M,) mm off the face
        plane, as if in the plane: magnified about the optical axis."""
        c = self.axis
        return c + (np.asarray(yz, dtype=np.float64) - c) * self.magnification(ux)[:, None]

    def pixel_centres(self, supersample: int = 1) -> np.ndarray:
        """(rows * s, cols * s, 2) image (col, row) of the s x s sample points inside every pixel
        (their centres for s = 1), the pixel (r, c) covering rows r-1/2..r+1/2 and cols c-1/2..c+1/2."""
        s = int(supersample)
        if s < 1:
            raise CameraError(f"supersample must be a positive integer, got {supersample}")
        rows, cols = self.shape
        sub = (np.arange(s) + 0.5) / s - 0.5
        c = (np.arange(cols)[:, None] + sub[None, :]).ravel()
        r = (np.arange(rows)[:, None] + sub[None, :]).ravel()
        C, R = np.meshgrid(c, r, indexing="xy")
        return np.stack([C, R], axis=-1)
