"""Structured Hex20 meshes of mapped blocks: boxes, distorted boxes, ring sectors.

A block is the image of the unit cube under a smooth map; nodes (mid-edge nodes included) are
placed by the map itself, so curved boundaries are represented isoparametrically.
Named sets of every block: node sets and face sets ``xmin, xmax, ymin, ymax, zmin, zmax`` on the
six sides of the parameter cube (for a ring sector: x = radius, y = angle, z = axial).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from torchfra.fem.elements import HEX20_EDGES, HEX20_NATURAL
from torchfra.fem.mesh import Mesh

# Abaqus face number (0-based) of each side of the parameter cube.
_SIDE_FACE = {"zmin": 0, "zmax": 1, "ymin": 2, "xmax": 3, "ymax": 4, "xmin": 5}


def structured_hex20(
    divisions: tuple[int, int, int], mapping: Callable[[np.ndarray], np.ndarray]
) -> Mesh:
    """Hex20 mesh of the unit cube mapped by ``mapping``.

    divisions: elements along the three parameter directions.
    mapping: (P, 3) points of [0, 1]^3 -> (P, 3) reference coordinates (mm).
    """
    nx, ny, nz = divisions
    if min(divisions) < 1:
        raise ValueError(f"divisions must be >= 1 in every direction, got {divisions}")
    shape = (2 * nx + 1, 2 * ny + 1, 2 * nz + 1)
    I, J, K = np.meshgrid(*(np.arange(s) for s in shape), indexing="ij")
    used = ((I % 2) + (J % 2) + (K % 2)) <= 1  # Hex20 has no face- or body-centre nodes
    lattice_id = -np.ones(shape, dtype=np.int64)
    lattice_id[used] = np.arange(int(used.sum()))
    ijk = np.stack([I[used], J[used], K[used]], axis=1)
    nodes = mapping(ijk / np.array([2 * nx, 2 * ny, 2 * nz], dtype=np.float64))

    ei, ej, ek = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    base = np.stack([2 * ei.ravel() + 1, 2 * ej.ravel() + 1, 2 * ek.ravel() + 1], axis=1)
    local = base[:, None, :] + HEX20_NATURAL.astype(np.int64)[None]
    elements = lattice_id[local[..., 0], local[..., 1], local[..., 2]]

    eidx = np.stack([ei.ravel(), ej.ravel(), ek.ravel()], axis=1)
    last = np.array([nx - 1, ny - 1, nz - 1])
    face_sets, node_sets = {}, {}
    for axis, name in enumerate("xyz"):
        for side, at_elem, at_node in (("min", 0, 0), ("max", last[axis], shape[axis] - 1)):
            key = f"{name}{side}"
            el = np.flatnonzero(eidx[:, axis] == at_elem)
            face_sets[key] = np.stack([el, np.full_like(el, _SIDE_FACE[key])], axis=1)
            node_sets[key] = lattice_id[used][ijk[:, axis] == at_node]
    node_sets["all"] = np.arange(nodes.shape[0])
    return Mesh(nodes, elements, node_sets, face_sets)


def box_mesh(
    size: tuple[float, float, float],
    divisions: tuple[int, int, int],
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    distortion: float = 0.0,
    seed: int = 0,
) -> Mesh:
    """Box ``origin + [0, size]`` meshed with Hex20 bricks.

    distortion: interior element corners are moved by up to this fraction of the local element
    size (a smooth random map keeps the mesh valid); mid-edge nodes stay at the middle of their
    straight edges, as in the standard (MacNeal-Harder) patch test meshes.
    """
    size_arr, origin_arr = np.asarray(size, dtype=np.float64), np.asarray(origin, dtype=np.float64)
    if np.any(size_arr <= 0):
        raise ValueError(f"box size must be positive, got {size}")
    div = np.asarray(divisions)
    rng = np.random.default_rng(seed)
    amp = rng.uniform(-1, 1, size=(3, 3))

    def mapping(s: np.ndarray) -> np.ndarray:
        if distortion:
            bubble = np.prod(np.sin(np.pi * s), axis=1, keepdims=True)
            waves = np.sin(2 * np.pi * s @ amp.T + amp.sum(axis=0))
            s = s + distortion / div * bubble * waves
        return origin_arr + s * size_arr

    mesh = structured_hex20(tuple(divisions), mapping)
    if distortion:
        corners = mesh.nodes[mesh.elements[:, HEX20_EDGES]]  # (E, 12, 2, 3)
        mesh.nodes[mesh.elements[:, 8:]] = corners.mean(axis=2)
        mesh.validate()
    return mesh


def ring_sector_mesh(
    inner_radius: float,
    outer_radius: float,
    angle_deg: float,
    thickness: float,
    divisions: tuple[int, int, int],
    radial_grading: float = 1.0,
) -> Mesh:
    """Sector of a thick-walled tube: radius along parameter x, angle along y (from the +x axis),
    axis z in [0, thickness]. Node sets/face sets ``xmin`` (inner wall), ``xmax`` (outer wall),
    ``ymin`` (plane y = 0), ``ymax`` (plane at ``angle_deg``), ``zmin``, ``zmax``.

    radial_grading: ratio of the outermost to the innermost radial element size (geometric).
    """
    if not 0 < inner_radius < outer_radius:
        raise ValueError(f"need 0 < inner_radius < outer_radius, got {inner_radius}, {outer_radius}")
    if not 0 < angle_deg <= 180 or thickness <= 0:
        raise ValueError(f"need 0 < angle_deg <= 180 and thickness > 0, got {angle_deg}, {thickness}")
    q = radial_grading ** (1.0 / max(divisions[0] - 1, 1))

    def radial(s: np.ndarray) -> np.ndarray:
        if abs(q - 1) < 1e-14:
            return s
        return (q ** (s * divisions[0]) - 1) / (q ** divisions[0] - 1)

    def mapping(s: np.ndarray) -> np.ndarray:
        r = inner_radius + (outer_radius - inner_radius) * radial(s[:, 0])
        t = np.deg2rad(angle_deg) * s[:, 1]
        return np.stack([r * np.cos(t), r * np.sin(t), thickness * s[:, 2]], axis=1)

    return structured_hex20(tuple(divisions), mapping)
