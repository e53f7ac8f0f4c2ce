"""The user's own model: an Abaqus/CalculiX deck read as the base model, and the side it is seen from.

:func:`read_deck` reads a deck (:func:`torchfra.io.abaqus.read_inp`) with a digest of what it holds (a
changed deck, or a changed ``*INCLUDE``d file, is another model); :func:`deck_summary` keeps it per
file version in a process; :func:`observed_faces` are the faces a camera on the x axis sees (or the
deck's named ``*SURFACE``); :class:`DeckModel` is a deck as the diagnosis's base model.
"""
from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfra import fem
from torchfra.actuator.candidates import ACTUATOR_ONLY, GRAVITY_DIRECTION
from torchfra.io.abaqus.read import read_inp
from torchfra.io.files import check_regular
from torchfra.observation.operator import visible_faces

CAMERAS = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0)}


def read_deck(path) -> tuple[fem.Model, dict[str, float], str]:
    """A deck's model, its parameter values and a digest of what it holds (nodes, elements, terms,
    constraints, values: an ``*INCLUDE``d file that changed changes it)."""
    path = _deck_path(path)
    model, values = read_inp(path)
    model.finalize()
    h = hashlib.sha256()
    T = model.dofmap.T
    for arr in (model.X, model.mesh.elements, model.clamped_dofs, T.indptr, T.indices, T.data):
        h.update(np.ascontiguousarray(arr).tobytes())
    for t in model.terms:
        h.update(type(t).__name__.encode())
        h.update(np.ascontiguousarray(t.dofs).tobytes())
    h.update(json.dumps(values, sort_keys=True).encode())
    return model, values, h.hexdigest()[:16]


def _deck_path(path) -> Path:
    return check_regular(Path(path), "deck", error=lambda message: ValueError(f"--inp {message}"))


@functools.lru_cache(maxsize=8)
def _deck_summary(path: str, mtime_ns: int, size: int) -> tuple[dict[str, float], str]:
    _, values, digest = read_deck(path)
    return values, digest


def deck_summary(path) -> tuple[dict[str, float], str]:
    """``read_deck``'s values and digest, read once per version of the file in a process (the
    scripts ask for them at several steps)."""
    path = _deck_path(path)
    st = path.stat()
    values, digest = _deck_summary(str(path.resolve()), st.st_mtime_ns, st.st_size)
    return dict(values), digest

def observed_faces(mesh, camera: str = "+x", face: str | None = None) -> np.ndarray | str:
    """The faces a camera looking from ``camera`` ("+x" or "-x") sees, or the deck's named surface ``face``."""
    if face:
        if face.upper() not in mesh.face_sets:
            raise ValueError(f"--face {face}: the deck has no such surface (its surfaces: "
                             f"{', '.join(sorted(mesh.face_sets)) or 'none'})")
        return face.upper()
    return visible_faces(mesh, CAMERAS[camera])


@dataclass(frozen=True)
class DeckModel:
    """The user's own model, an Abaqus/CalculiX deck (``torchfra.io.read_inp``), as the diagnosis'
    base model: ``camera`` the side it is observed from (:data:`CAMERAS`), ``face`` the deck's
    *SURFACE the camera observes (None: every face it sees), ``gravity`` the direction of the weight
    for the gravity candidate. Its parameter values (C10, D1, E_fiber) are the base model's: the
    prior of C10 is centred on the deck's, compressibility keeps the deck's K/mu at its null, and
    the fibers' null is the deck's E_fiber."""

    path: str
    camera: str = "+x"
    face: str | None = None
    gravity: tuple[float, float, float] = GRAVITY_DIRECTION

    def values(self) -> tuple[dict[str, float], str]:
        return deck_summary(self.path)

    def available(self, candidates) -> dict[str, str]:
        """The candidates this deck cannot carry, with why."""
        values, _ = self.values()
        out = {c: f"not for a deck: {why}" for c, why in ACTUATOR_ONLY.items() if c in candidates}
        if "fiber_stiffness" in candidates and "E_fiber" not in values:
            out["fiber_stiffness"] = "the deck has no fibers (no truss elements with *ELASTIC)"
        if "mooney_rivlin" in candidates and "C01" in values:
            out["mooney_rivlin"] = "the deck's material is Mooney-Rivlin already (its C01 is a base-model value)"
        if "gravity" in candidates and "density" in values:
            out["gravity"] = "the deck carries its weight already (*DLOAD GRAV)"
        return out
