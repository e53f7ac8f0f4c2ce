"""Self-weight of a body (gravity candidate): a dead body load, scaled by the load factor.

    W(u) = -lambda rho g int_V0 d . u dV = -lambda rho g sum_e sum_a m_a (d . u_a),
    m_a = int_Ve N_a dV     (consistent nodal loads f_a = lambda rho g m_a d),

over the reference volume (mass is conserved, so the load per reference volume is rho g whatever
the deformation: a dead load, no load stiffness). Units: density rho in t/mm^3 (tonne per cubic
millimetre, so that rho g is in N/mm^3 with g in mm/s^2): silicone rubber ~1.1e-9 t/mm^3
(1.1 g/cm^3); g = 9.81e3 mm/s^2; W in mJ (N mm). Null: rho = 0.

Reference state. A DIC recording measures displacements from its reference image, taken with the
body already under its weight. ``preload=True`` (what such a recording needs) makes the weight act
in full before the load path: :func:`torchfra.fem.newton.solve` settles the body under its weight
first (``Solution.u_reference``), and the path's load factor then ramps the other loads only, so the
recording's displacements are ``u - u_reference``. ``preload=False`` (the default of this FE term)
ramps the weight with the load factor, together with the pressure, from the unloaded body.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.func import grad, vmap

from torchfra.fem.elements import as_tensor, gauss_hex, hex20_shape
from torchfra.fem.mesh import Mesh
from torchfra.fem.morph import Morphable
from torchfra.fem.params import ParameterInfo, check_parameters
from torchfra.fem.terms import Term, TermOutput, node_dofs

STANDARD_GRAVITY = 9.81e3  # mm/s^2


class Gravity(Morphable, Term):
    """Weight ``rho g d`` per unit reference volume on (a subset of) the Hex20 elements of a mesh.

    density: name of the density parameter (t/mm^3); direction: (3,) direction of gravity (normalized
    here); g: acceleration (mm/s^2); elements: element ids (default: all); quadrature: Gauss points
    per direction (3, the default, integrates ``N_a det J`` exactly on straight-edged bricks);
    preload: the weight acts in full before the load path (see the module docstring).
    """

    kind = "load"
    parameters = {
        "density": ParameterInfo(
            "density", "t/mm^3", 0.0, 0.0, 2.5e-8,
            "mass density (silicone ~1.1e-9 t/mm^3); bounded by the densest element, osmium 2.26e-8 t/mm^3",
        ),
    }

    def __init__(self, mesh: Mesh, density: str = "density", direction=(0.0, 0.0, -1.0), g: float = STANDARD_GRAVITY,
                 elements=None, quadrature: int = 3, dtype=torch.float64, preload: bool = False):
        d = np.asarray(direction, dtype=np.float64).reshape(-1)
        if d.shape != (3,) or not np.linalg.norm(d) > 0 or not np.all(np.isfinite(d)):
            raise ValueError(f"gravity direction must be a non-zero finite 3-vector, got {direction!r}")
        if not (np.isfinite(g) and g > 0):
            raise ValueError(f"gravitational acceleration g must be positive (mm/s^2), got {g!r}")
        self.density, self.g = density, float(g)
        self.preload = bool(preload)
        self.direction = d / np.linalg.norm(d)
        self.param_names = (density,)
        self.parameters = {density: Gravity.parameters["density"].renamed(density)}
        self.element_ids = np.arange(mesh.n_elements) if elements is None else np.asarray(elements, dtype=np.int64)
        conn = mesh.elements[self.element_ids]
        self.conn = torch.as_tensor(conn)
        self.dofs = node_dofs(conn)
        pts, wts = gauss_hex(quadrature)
        N, dN = hex20_shape(pts)
        det = np.linalg.det(np.einsum("eai,gaj->egij", mesh.nodes[conn], dN))
        self.nodal_volume = as_tensor(np.einsum("g,eg,ga->ea", wts, det, N), dtype)  # m_a (E, 20), mm^3
        self._shape = (as_tensor(wts[None], dtype), as_tensor(N[None], dtype), as_tensor(dN[None], dtype))
        self.volume = float(self.nodal_volume.sum())
        self._d = as_tensor(self.direction, dtype)
        # W is linear in u, so its gradient per unit rho g is a constant: derived once by torch.func
        zeros = torch.zeros(conn.shape[0], 20, 3, dtype=dtype)
        self._unit_force = vmap(grad(self._unit_energy))(zeros, self.nodal_volume).reshape(conn.shape[0], 60)

    def _unit_energy(self, u_e: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        """Energy of one element per unit ``lambda rho g``: ``-sum_a m_a (d . u_a)``. u_e: (20, 3)."""
        return -(m * (u_e @ self._d)).sum()

    def validate(self, params):
        check_parameters(self.parameters, params, "Gravity")

    def _morph_nodes(self):
        return self.conn.numpy()

    def _nodal_volume(self, params) -> torch.Tensor:
        """m_a of every member (N, E, 20) under the morphs, or (E, 20) without one."""
        if not self.morph_names:
            return self.nodal_volume
        wts, N, dN = (t[0] for t in self._shape)
        det = torch.linalg.det(torch.einsum("neai,gaj->negij", self.morphed_reference(params), dN))
        return torch.einsum("g,neg,ga->nea", wts, det, N)

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        """Residual ``-lambda rho g m_a d`` per element node; the tangent is zero (``Ke = None``)."""
        N = u.shape[0]
        scale = load_factor * params[self.density] * self.g  # (N,) N/mm^3
        if self.morph_names:
            m = self._nodal_volume(params)
            fe = -(scale[:, None, None, None] * m[..., None] * self._d).reshape(N, m.shape[1], 60)
        else:
            m = self.nodal_volume.expand(N, -1, -1)
            fe = scale[:, None, None] * self._unit_force
        W = None
        if energy:
            W = scale * torch.einsum("nea,neai,i->n", m, u[:, self.conn], -self._d)
        return TermOutput(fe, None, W, torch.ones(N, dtype=torch.bool, device=u.device))
