"""How the candidate terms (gravity, elastic support) become Abaqus/CalculiX cards: the numbers.

``write_inp`` formats them; this module only decides what they are.

- ``Gravity`` -> ``*DENSITY`` in the material of every solid body it covers and a ``*DLOAD``
  line ``ELSET, GRAV, g, d_x, d_y, d_z`` (a dead load per reference volume, as torchfra's). A
  gravity term must cover whole solid bodies: an Abaqus density belongs to a material.
- ``ElasticSupport`` -> scalar springs that store exactly the term's discrete energy
  ``1/2 u^T K u``, ``K = sum_faces (k_n K_n + k_t K_t)`` (consistent, not lumped): for every
  coupled pair of dofs ``a < b`` a ``SPRING2`` of stiffness ``-K_ab`` between them, and at every
  dof a ``SPRING1`` to ground of stiffness ``sum_b K_ab``. Then
  ``sum_{a<b} -K_ab (u_a - u_b)^2 / 2 + sum_a (sum_b K_ab) u_a^2 / 2 = u^T K u / 2``. Some of
  these stiffnesses are negative (the corner weights ``int N_a dA`` of a Quad8 face are), the
  sum is the positive semi-definite K. Scalar springs act along fixed global axes, so the face
  normals must lie along a coordinate axis (then K couples only equal components).
"""
from __future__ import annotations

import numpy as np

from torchfra.fem.gravity import Gravity
from torchfra.fem.solid import Hex20Solid
from torchfra.fem.springs import ElasticSupport


def gravity_of_solids(model, values: dict[str, float]) -> dict[int, tuple[float, float, np.ndarray]]:
    """``{solid term index: (density, g, direction)}`` for the solid bodies the gravity terms cover."""
    solids = {k: set(t.element_ids.tolist()) for k, t in enumerate(model.terms) if isinstance(t, Hex20Solid)}
    out: dict[int, tuple[float, float, np.ndarray]] = {}
    for j, term in enumerate(model.terms):
        if not isinstance(term, Gravity):
            continue
        covered = set(term.element_ids.tolist())
        for k, elements in solids.items():
            if not (elements & covered):
                continue
            if not elements <= covered:
                raise NotImplementedError(
                    f"gravity term {j} covers part of solid term {k}; an Abaqus density belongs to a whole material, "
                    "so give Gravity the elements of whole solid bodies"
                )
            if k in out:
                raise NotImplementedError(f"solid term {k} is covered by more than one gravity term")
            out[k] = (values[term.density], term.g, term.direction)
            covered -= elements
        if covered:
            raise NotImplementedError(
                f"gravity term {j} acts on elements without a solid body (e.g. {sorted(covered)[0]}); nothing to export"
            )
    return out


def support_springs(term: ElasticSupport, values: dict[str, float], rtol: float = 1e-12):
    """Scalar springs storing the support's energy: ``(grounded, pairs)`` with grounded rows
    ``(node, component, stiffness)`` (SPRING1) and pair rows ``(node_a, node_b, component, stiffness)``
    (SPRING2); nodes 0-based, components 0..2, stiffness in N/mm."""
    K = 0.0
    if term.normal is not None:
        K = K + term.K_n.numpy() / values[term.normal]
    if term.tangential is not None:
        K = K + term.K_t.numpy() / values[term.tangential]
    dofs = term.dofs  # (B, 24)
    n = int(dofs.max()) + 1
    rows = np.repeat(dofs, 24, axis=1).ravel()
    cols = np.tile(dofs, (1, 24)).ravel()
    keys, inverse = np.unique(rows * n + cols, return_inverse=True)
    vals = np.bincount(inverse, weights=K.ravel())
    r, c = np.divmod(keys, n)
    scale = np.abs(vals).max()
    keep = np.abs(vals) > rtol * scale
    r, c, vals = r[keep], c[keep], vals[keep]
    if np.any(r % 3 != c % 3):
        raise NotImplementedError(
            f"ElasticSupport on '{term.face_set}' couples different displacement components (a face normal not "
            "along a coordinate axis); scalar springs act along the global axes only"
        )
    row_sum = np.bincount(r, weights=vals, minlength=n)
    grounded = [(d // 3, d % 3, row_sum[d]) for d in np.unique(r) if abs(row_sum[d]) > rtol * scale]
    upper = r < c
    pairs = [(a // 3, b // 3, a % 3, -v) for a, b, v in zip(r[upper], c[upper], vals[upper])]
    return grounded, pairs
