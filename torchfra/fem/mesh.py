"""Hex20 meshes with named node sets and face sets, validated on construction.

A mesh is reference geometry only (mm). Face sets are lists of ``(element, face)`` pairs with the
Abaqus face number ``face`` in 0..5 for S1..S6, so they export to ``*SURFACE, TYPE=ELEMENT`` as is.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from torchfra.fem.elements import HEX20_EDGES, HEX20_FACES, HEX20_NATURAL, gauss_hex, hex20_shape


class MeshError(ValueError):
    """Invalid mesh input; the message names the element, node or set at fault."""


@dataclass
class Mesh:
    """A Hex20 mesh.

    nodes: (n_nodes, 3) reference coordinates in mm.
    elements: (n_elements, 20) node indices in Abaqus C3D20 order (0-based).
    node_sets: name -> (k,) node indices.
    face_sets: name -> (k, 2) rows ``(element, face)``, face 0..5 = Abaqus S1..S6.
    """

    nodes: np.ndarray
    elements: np.ndarray
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    face_sets: dict[str, np.ndarray] = field(default_factory=dict)
    check: bool = True

    def __post_init__(self):
        self.nodes = np.ascontiguousarray(self.nodes, dtype=np.float64)
        self.elements = np.ascontiguousarray(self.elements, dtype=np.int64)
        self.node_sets = {k: np.asarray(v, dtype=np.int64).ravel() for k, v in self.node_sets.items()}
        self.face_sets = {k: np.asarray(v, dtype=np.int64).reshape(-1, 2) for k, v in self.face_sets.items()}
        if self.check:
            self.validate()

    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    @property
    def n_elements(self) -> int:
        return self.elements.shape[0]

    def validate(self) -> None:
        """Check shapes, index ranges, node order and positive Jacobians; raise MeshError otherwise."""
        if self.nodes.ndim != 2 or self.nodes.shape[1] != 3:
            raise MeshError(f"nodes must have shape (n_nodes, 3), got {self.nodes.shape}")
        if not np.all(np.isfinite(self.nodes)):
            bad = int(np.argwhere(~np.isfinite(self.nodes))[0, 0])
            raise MeshError(f"node {bad} has a non-finite coordinate {self.nodes[bad].tolist()}")
        if self.elements.ndim != 2 or self.elements.shape[1] != 20:
            raise MeshError(
                f"Hex20 connectivity must have shape (n_elements, 20), got {self.elements.shape}; "
                "give the 20 nodes of each brick in Abaqus C3D20 order"
            )
        lo, hi = self.elements.min(initial=0), self.elements.max(initial=0)
        if lo < 0 or hi >= self.n_nodes:
            e = int(np.argwhere((self.elements < 0) | (self.elements >= self.n_nodes))[0, 0])
            raise MeshError(f"element {e} refers to a node outside 0..{self.n_nodes - 1}: {self.elements[e].tolist()}")
        for e in np.flatnonzero([len(set(row)) != 20 for row in self.elements]):
            raise MeshError(f"element {e} repeats a node: {self.elements[e].tolist()}")
        self._check_node_order()
        self._check_jacobians()
        for name, idx in self.node_sets.items():
            if idx.size and (idx.min() < 0 or idx.max() >= self.n_nodes):
                raise MeshError(f"node set '{name}' refers to nodes outside 0..{self.n_nodes - 1}")
        for name, ef in self.face_sets.items():
            if ef.size and (ef[:, 0].min() < 0 or ef[:, 0].max() >= self.n_elements):
                raise MeshError(f"face set '{name}' refers to elements outside 0..{self.n_elements - 1}")
            if ef.size and (ef[:, 1].min() < 0 or ef[:, 1].max() > 5):
                raise MeshError(f"face set '{name}' has a face number outside 0..5 (Abaqus S1..S6)")

    def _check_node_order(self) -> None:
        # A mid-edge node must sit near the middle of its two corners; otherwise the order is wrong.
        X = self.nodes[self.elements]
        a, b = X[:, HEX20_EDGES[:, 0]], X[:, HEX20_EDGES[:, 1]]
        mid = X[:, 8:]
        length = np.linalg.norm(b - a, axis=-1)
        off = np.linalg.norm(mid - 0.5 * (a + b), axis=-1)
        bad = off > 0.5 * length
        if bad.any():
            e, k = np.argwhere(bad)[0]
            raise MeshError(
                f"element {e}: node {self.elements[e, 8 + k]} at position {8 + k} is not between corners "
                f"{HEX20_EDGES[k].tolist()}; the connectivity is not in Abaqus C3D20 node order"
            )

    def _check_jacobians(self) -> None:
        pts, _ = gauss_hex(2)
        check_pts = np.concatenate([pts, 0.999 * HEX20_NATURAL[:8]])
        _, dN = hex20_shape(check_pts)
        J = np.einsum("eai,gaj->egij", self.nodes[self.elements], dN)
        det = np.linalg.det(J)
        bad = ~(det > 0)
        if bad.any():
            e, g = np.argwhere(bad)[0]
            where = f"Gauss point {g}" if g < len(pts) else f"corner {g - len(pts)}"
            raise MeshError(
                f"element {e} is inverted or degenerate: det J = {det[e, g]:.3e} <= 0 at {where}; "
                "check its node order (Abaqus C3D20: bottom face counter-clockwise seen from the top) "
                "and the coordinates of its nodes"
            )

    def node_set(self, name: str) -> np.ndarray:
        if name not in self.node_sets:
            raise MeshError(f"node set '{name}' does not exist; known node sets: {sorted(self.node_sets)}")
        return self.node_sets[name]

    def face_set(self, name: str) -> np.ndarray:
        if name not in self.face_sets:
            raise MeshError(f"face set '{name}' does not exist; known face sets: {sorted(self.face_sets)}")
        return self.face_sets[name]

    def face_nodes(self, name: str) -> np.ndarray:
        """Quad8 connectivity (k, 8) of a face set, node order of ``HEX20_FACES``."""
        ef = self.face_set(name)
        return self.elements[ef[:, 0][:, None], HEX20_FACES[ef[:, 1]]]

    def face_set_nodes(self, name: str) -> np.ndarray:
        """Sorted unique nodes of a face set."""
        return np.unique(self.face_nodes(name))
