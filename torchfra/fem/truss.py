"""Three-node quadratic trusses (Abaqus T3D3 analogue) for fibers.

Energy of one element, 2-point Gauss along the reference arc (as T3D3):

    W = sum_q w_q |X_s|_q  (E A / 2) eps_q^2,   eps = (|x_s|^2 / |X_s|^2 - 1) / 2   (Green strain),

E in MPa, A in mm^2, W in mJ. Fibers are nearly inextensible, so strains stay far below 1e-2 and
the choice of strain measure is immaterial; Poisson's ratio does not enter a truss's axial force.
Residual and tangent are W's derivatives in closed form, pinned to torch.func's by tests.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.func import vmap

from torchfra.fem.elements import as_tensor, gauss_1d, line3_shape
from torchfra.fem.morph import Morphable
from torchfra.fem.terms import Term, TermOutput, node_dofs


class Truss(Morphable, Term):
    """Line3 trusses between model nodes.

    X: (n_model_nodes, 3) reference coordinates of the model; conn: (B, 3) node indices (ends, middle);
    area: cross-section (mm^2); modulus: name of the Young's modulus parameter (MPa).
    """

    kind = "internal"

    def __init__(self, X: np.ndarray, conn: np.ndarray, area: float, modulus: str = "E_fiber", dtype=torch.float64):
        conn = np.asarray(conn, dtype=np.int64)
        if conn.ndim != 2 or conn.shape[1] != 3:
            raise ValueError(f"truss connectivity must have shape (n_elements, 3), got {conn.shape}")
        if not area > 0:
            raise ValueError(f"truss cross-section area must be positive, got {area}")
        self.param_names = (modulus,)
        self.modulus, self.area = modulus, float(area)
        self.conn = torch.as_tensor(conn)
        self.dofs = node_dofs(conn)
        pts, wts = gauss_1d(2)
        _, dN = line3_shape(pts)
        self.dN, self.w = as_tensor(dN, dtype), as_tensor(wts, dtype)
        self.X = as_tensor(np.asarray(X)[conn], dtype)  # (B, 3, 3)
        L0 = torch.linalg.norm(torch.einsum("qa,bai->bqi", self.dN, self.X), dim=-1)
        if not (L0 > 0).all():
            b = int(torch.nonzero(~(L0 > 0).all(1))[0, 0])
            raise ValueError(f"truss element {b} has zero length: nodes {conn[b].tolist()}")
        self.jac0 = L0  # (B, Q) = |X_s|

    def validate(self, params):
        super().validate(params)
        v = params[self.modulus]
        if (v <= 0).any():
            m = int(torch.nonzero(v <= 0)[0, 0])
            raise ValueError(f"parameter {self.modulus} of member {m} must be positive, got {float(v[m])}")

    def _morph_nodes(self):
        return self.conn.numpy()

    def _reference(self, params, N: int):
        """Reference nodes (N, B, 3, 3) and Gauss-point lengths ``|X_s|`` (N, B, Q) of every member."""
        if not self.morph_names:
            return self.X.expand(N, -1, -1, -1), self.jac0.expand(N, -1, -1)
        X = self.morphed_reference(params)
        return X, torch.linalg.norm(torch.einsum("qa,nbai->nbqi", self.dN, X), dim=-1)

    def _element_energy(self, x: torch.Tensor, jac0: torch.Tensor, EA: torch.Tensor) -> torch.Tensor:
        xs = torch.einsum("qa,ai->qi", self.dN, x)
        eps = 0.5 * ((xs * xs).sum(-1) / jac0**2 - 1.0)
        return 0.5 * EA * (self.w * jac0 * eps**2).sum()

    def axial_strain(self, u: torch.Tensor, params: dict | None = None) -> torch.Tensor:
        """Green strain at the Gauss points, (N, B, 2) (``params`` carry the morphs, if any)."""
        X, jac0 = self._reference(params, u.shape[0])
        xs = torch.einsum("qa,nbai->nbqi", self.dN, X + u[:, self.conn])
        return 0.5 * ((xs * xs).sum(-1) / jac0**2 - 1.0)

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        N, B = u.shape[0], self.conn.shape[0]
        X, jac0 = self._reference(params, N)
        x = (X + u[:, self.conn]).reshape(N * B, 3, 3)
        jac0 = jac0.reshape(N * B, -1)
        EA = (params[self.modulus] * self.area).repeat_interleave(B)
        # closed form of the derivatives of _element_energy (pinned to torch.func by tests):
        # r_ai = EA sum_q w_q eps_q / L_q dN_qa xs_qi,
        # K_ai,bk = EA sum_q w_q / L_q dN_qa dN_qb (xs_qi xs_qk / L_q^2 + eps_q delta_ik)
        xs = torch.einsum("qa,mai->mqi", self.dN, x)  # (NB, Q, 3)
        eps = 0.5 * ((xs * xs).sum(-1) / jac0**2 - 1.0)
        c = EA[:, None] * self.w / jac0  # (NB, Q)
        fe = torch.einsum("mq,qa,mqi->mai", c * eps, self.dN, xs).reshape(N, B, 9)
        Ke = None
        if tangent:
            outer = xs[..., :, None] * xs[..., None, :] / (jac0**2)[..., None, None] + \
                eps[..., None, None] * torch.eye(3, dtype=x.dtype)  # (NB, Q, 3, 3)
            Ke = torch.einsum("mq,qa,qb,mqik->maibk", c, self.dN, self.dN, outer).reshape(N, B, 9, 9)
        W = vmap(self._element_energy)(x, jac0, EA).reshape(N, B).sum(1) if energy else None
        return TermOutput(fe, Ke, W, torch.ones(N, dtype=torch.bool, device=u.device))


def two_node_truss(model, conn, area: float, modulus: str = "E_fiber", dtype=torch.float64) -> Truss:
    """Straight two-node trusses (Abaqus T3D2) between model nodes ``conn`` (B, 2), as a
    :class:`Truss` term to ``model.add``: each gets a middle node at its chord midpoint (appended with
    ``model.add_nodes``) tied to the mean of its ends, through the ends' own ties where they are
    embedded (``model.embed`` them first), so its displacement is linear along the chord and its
    Green strain is the constant strain of the two-node truss. The ends must not be rigid-body or
    prescribed nodes (a tie's hosts must be free or clamped)."""
    conn = np.asarray(conn, dtype=np.int64).reshape(-1, 2)
    if conn.size and (conn.min() < 0 or conn.max() >= model.n_nodes):
        raise ValueError(f"two_node_truss: node indices must lie in [0, {model.n_nodes}), got {conn.min()}..{conn.max()}")
    ties = {node: (hosts, weights) for node, hosts, weights in model.embedded_nodes}
    middle = model.add_nodes(0.5 * (model.X[conn[:, 0]] + model.X[conn[:, 1]]))
    for m, (a, b) in zip(middle, conn):
        parts = [ties.get(int(n), (np.array([n]), np.array([1.0]))) for n in (a, b)]
        hosts, inverse = np.unique(np.concatenate([h for h, _ in parts]), return_inverse=True)
        model.embed(int(m), hosts, np.bincount(inverse, weights=0.5 * np.concatenate([w for _, w in parts])))
    return Truss(model.X, np.column_stack([conn, middle]), area=area, modulus=modulus, dtype=dtype)
