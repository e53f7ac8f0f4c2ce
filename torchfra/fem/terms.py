"""The contract between energy terms and the assembly.

A term is one physics contribution (a material body, fibers, a pressure, a spring...). It sees
element-level tensors only: ``dofs`` lists, for each of its blocks (elements, faces, ...), the global
degrees of freedom ``3 * node + component`` it touches; ``evaluate`` returns block residuals and
block tangents for all members at once. Sparse patterns, scatter and constraints live in
``assembly.py`` and ``constraints.py``.

Every term has parameters with a *null* value at which it vanishes, so extending a model is adding
a term (DESIGN §1.4).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class TermOutput:
    """Block residuals ``fe`` (N, B, D), tangents ``Ke`` (N, B, D, D) or None, energy (N,) or None,
    and ``ok`` (N,): False where the member's state is inadmissible (e.g. det F <= 0).

    Terms with element-local unknowns (hybrid pressure) return ``Ke`` condensed and, when the
    local unknowns are given, ``fe_condensed`` = the right-hand side that goes with it.

    A *global* term (``Term.global_dofs``: couplings that differ from member to member, e.g. fibers
    embedded where each member's own geometry puts them) returns ``fe`` over every dof (N, 3 n_nodes),
    ``Ke`` None and its tangents as one sparse matrix per member in ``K_global``."""

    fe: torch.Tensor
    Ke: torch.Tensor | None
    energy: torch.Tensor | None
    ok: torch.Tensor
    fe_condensed: torch.Tensor | None = None
    K_global: list | None = None


class Term:
    """Base class of energy terms.

    ``kind`` is ``"internal"`` (stored energy) or ``"load"`` (work of external loads, scaled by the
    load factor). ``conservative`` terms have an energy; follower loads on open surfaces do not.
    A ``preload`` load acts in full before the load path starts (the body's weight in the reference
    image of a DIC recording): :func:`torchfra.fem.newton.solve` settles the model under its preloads
    first, and the path's load factor then scales the other loads only (``Model.term_load_factor``).
    """

    kind: str = "internal"
    conservative: bool = True
    n_local: int = 0  # element-local unknowns per block carried by Newton (condensed per block)
    preload: bool = False  # a load that acts in full before the load path (settled first)
    global_dofs: bool = False  # True: no blocks; fe over every dof, tangents per member (TermOutput.K_global)
    param_names: tuple[str, ...] = ()
    dofs: np.ndarray  # (B, D) global dof indices

    def validate(self, params: dict[str, torch.Tensor]) -> None:
        for name in self.param_names:
            if name not in params:
                raise KeyError(f"{type(self).__name__} needs parameter '{name}'; got {sorted(params)}")
            v = params[name]
            if not torch.isfinite(v).all():
                m = int(torch.nonzero(~torch.isfinite(v))[0, 0])
                raise ValueError(f"parameter {name} of member {m} is not finite ({float(v[m])})")

    def morphs_present(self, names: list[str]) -> None:
        """Called by :meth:`Model.finalize` on a global term of a model with morphs ``names``; a global
        term has no blocks to follow them: refuse (the default) or check its members against them."""
        raise ValueError(f"a {type(self).__name__} term does not follow the model's morphs {names}")

    def evaluate(
        self,
        u: torch.Tensor,
        params: dict[str, torch.Tensor],
        load_factor: torch.Tensor,
        tangent: bool = True,
        energy: bool = False,
    ) -> TermOutput:
        """u: (N, n_nodes, 3) displacements; params: name -> (N,); load_factor: (N,)."""
        raise NotImplementedError


def node_dofs(nodes: np.ndarray) -> np.ndarray:
    """(B, A) node indices -> (B, 3A) dof indices, node-major."""
    return (3 * nodes[..., None] + np.arange(3)).reshape(nodes.shape[0], -1)
