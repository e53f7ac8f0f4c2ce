"""The fiber-pitch candidate: helical fibers wound at another angle than the model's.

Fibers wound by hand or on a worn mandrel come out at another pitch than drawn. A pitch change
moves the fibers relative to the matrix by many turns (2 -> 2.2 deg shifts the end of a 40 mm helix
by ~5 turns), so it is no morph of the reference mesh (a morph carries embedded nodes with the
material they sit in), and every member of an ensemble needs its own fiber embedding.

:class:`FiberPitch` winds, for every member, the same Line3 trusses as the base model (the same
count per helix, nodes on the helix at equal arc length, 2-point Gauss, Green strain: ``fem.Truss``)
at the member's pitch ``alpha``, embeds their nodes in the bricks that host them at that pitch
(``u_node = sum_a N_a(xi) u_a``, ``fem.embedding.locate_points``) and adds

    W_alpha(u) - W_alpha0(u),

the energy of these fibers at ``alpha`` less the same construction at the model's own pitch
``alpha0``. At ``alpha0`` the second is, node by node, the base model's trusses (same nodes, hosts,
weights, rule), so the model with the term is the model re-built with its fibers wound at
``alpha`` (checked to round-off against exactly that model, ``tests/test_fiber_pitch.py``); at
``alpha = alpha0`` both are the same numbers and the term is exactly zero.

The hosts of a member's fiber nodes depend on its pitch, so the couplings the term adds are the
member's own: it is a *global* term (``global_dofs``): it returns the residual over every dof
(N, 3 n_nodes) and, per member, its tangent as a sparse matrix ``T^T K_f T`` (``K_f``: the
trusses' block tangent, ``T``: the embedding map), which :class:`Model` adds after the block
assembly. Hyper-reduction (ECSW samples blocks) does not apply; ensembles with a pitch are solved
by full Newton (``torchfra.calibration.forward``).

The pitch derivative is exact (sensitivities by torch.func, :mod:`torchfra.fem.sensitivity`): each
node's natural coordinates are corrected by one Newton step in torch,
``xi = xi_0 + (dX/dxi)^-1 (X(alpha) - X(xi_0))``, which leaves the value (the lookup converged) and
carries ``dxi/dalpha``. The residual is continuous in ``alpha`` (a node that crosses a brick face
keeps its interpolated displacement) with kinks where one does.
"""
from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import scipy.sparse as sp
import torch

from torchfra.fem.elements import as_tensor, gauss_1d, hex20_shape, hex20_shape_values, line3_shape
from torchfra.fem.mesh import Mesh
from torchfra.fem.params import ParameterInfo, check_parameters
from torchfra.fem.terms import Term, TermOutput

PITCH_RANGE_DEG = (1.0, 4.0)


def pitch_parameter(nominal_deg: float, name: str = "fiber_pitch") -> ParameterInfo:
    """Registry entry of the fiber pitch (deg), null at the model's own pitch."""
    lo, hi = PITCH_RANGE_DEG
    return ParameterInfo(name, "deg", float(nominal_deg), lo, hi,
                         f"angle between the fibers and the circumferential direction (the model's {nominal_deg:g} "
                         "deg): fibers wound off their drawn pitch")


def _plain(t: torch.Tensor) -> bool:
    """True for a tensor no derivative is being taken through (no torch.func transform, no forward-mode
    dual, no autograd history)."""
    import torch.autograd.forward_ad as fwAD

    if t.requires_grad:
        return False
    try:
        t.numpy()
    except RuntimeError:  # a torch.func-wrapped tensor has no storage of its own
        return False
    return fwAD.unpack_dual(t).tangent is None


class FiberPitch(Term):
    """Helical Line3 fibers at pitch ``params[name]`` (deg) in place of the model's ``nominal_deg``
    (module docstring). Energy of the fibers at pitch ``alpha``, as ``fem.Truss`` (T3D3, 2 Gauss points
    per element, Green strain; E in MPa, A in mm^2, W in mJ):

        W_alpha = sum_e sum_q w_q |X_s| (E A / 2) eps_q^2,   eps = (|x_s|^2 / |X_s|^2 - 1) / 2,
        x_b = X_b(alpha) + sum_a N_a(xi_b(alpha)) u_a   (node b embedded in its host brick's nodes a).

    mesh: the Hex20 mesh the fibers are embedded in; ``center`` (x, y) of the helix axis (along z),
    ``radius``, ``z_range`` (z0, z1); ``start_deg``: both helices' angle at z0 about the axis from +x
    (helix 0 winds counter-clockwise seen from +z as z grows, helix 1 clockwise, as
    ``actuator.geometry.helix_points``); ``elements_per_helix``: the base model's Line3 count per
    helix; ``area`` (mm^2) and ``modulus`` (the fibers' Young's modulus parameter) as its trusses'."""

    kind = "internal"
    global_dofs = True

    def __init__(self, mesh: Mesh, center, radius: float, z_range, nominal_deg: float, start_deg: float,
                 elements_per_helix: int, area: float, modulus: str = "E_fiber", name: str = "fiber_pitch",
                 dtype=torch.float64, cache_size: int = 512):
        lo, hi = PITCH_RANGE_DEG
        if not lo <= nominal_deg <= hi:
            raise ValueError(f"the model's fiber pitch {nominal_deg!r} deg lies outside the candidate's range "
                             f"[{lo:g}, {hi:g}] deg")
        if not (radius > 0 and area > 0 and z_range[1] > z_range[0] and elements_per_helix >= 1):
            raise ValueError(f"helix radius, fiber area, z range and elements per helix must be positive, got "
                             f"{radius}, {area}, {z_range}, {elements_per_helix}")
        self.mesh, self.name, self.modulus, self.area = mesh, name, modulus, float(area)
        self.center, self.radius = (float(center[0]), float(center[1])), float(radius)
        self.z0, self.z1 = float(z_range[0]), float(z_range[1])
        self.nominal, self.start = float(nominal_deg), math.radians(start_deg)
        self.param_names = (name, modulus)
        self.parameters = {name: pitch_parameter(nominal_deg, name)}
        self.dtype = dtype
        n_el = int(elements_per_helix)
        self.s = np.linspace(0.0, 1.0, 2 * n_el + 1)  # node arc parameters of one helix
        k = np.arange(n_el)
        one = np.stack([2 * k, 2 * k + 2, 2 * k + 1], 1)  # (end, end, middle) as line3_shape
        self.conn = torch.as_tensor(np.concatenate([one, one + 2 * n_el + 1]))
        pts, wts = gauss_1d(2)
        _, dN = line3_shape(pts)
        self.dN, self.w = as_tensor(dN, dtype), as_tensor(wts, dtype)
        self.dofs = np.zeros((0, 3), dtype=np.int64)  # no blocks: the couplings are each member's own
        # the truss tangent's sparsity over fiber-node dofs, shared by every member and pitch
        nd = (3 * self.conn[:, :, None] + torch.arange(3)).reshape(-1, 9).numpy()
        self._rows, self._cols = np.repeat(nd, 9, axis=1).ravel(), np.tile(nd, (1, 9)).ravel()
        self._cache: OrderedDict = OrderedDict()
        self._cache_size = int(cache_size)

    def morphs_present(self, names: list[str]) -> None:
        """The fibers here do not follow a morph: a member may move its pitch or the morphs, not both
        (at either null the model is exact: the term vanishes at its own, and the morphs move the
        base model's trusses with their hosts)."""
        self.exclusive = tuple(names)

    def validate(self, params):
        super().validate(params)
        check_parameters(self.parameters, params, "FiberPitch")
        off = params[self.name] != self.nominal
        for morph in (m for m in getattr(self, "exclusive", ()) if m in params):
            both = off & (params[morph] != 0)
            if both.any():
                m = int(torch.nonzero(both)[0, 0])
                raise ValueError(f"member {m} moves both {self.name} ({float(params[self.name][m]):g} deg, drawn "
                                 f"{self.nominal:g}) and the morph {morph} ({float(params[morph][m]):g}): the pitch's "
                                 "fibers do not follow a morph; fit one of them at a time")
        v = params[self.modulus]
        if (v <= 0).any():
            m = int(torch.nonzero(v <= 0)[0, 0])
            raise ValueError(f"parameter {self.modulus} of member {m} must be positive, got {float(v[m])}")

    # -- geometry -----------------------------------------------------------------------------------
    def _nodes_numpy(self, alpha: float) -> np.ndarray:
        """Fiber nodes of both helices at pitch ``alpha`` (deg), (n, 3), in numpy (a torch op here would be
        traced by a surrounding torch.func transform)."""
        rate = 1.0 / (self.radius * math.tan(math.radians(alpha)))
        z = self.z0 + self.s * (self.z1 - self.z0)
        th = np.concatenate([self.start + (z - self.z0) * rate, self.start - (z - self.z0) * rate])
        return np.stack([self.center[0] + self.radius * np.cos(th), self.center[1] + self.radius * np.sin(th),
                         np.concatenate([z, z])], 1)

    def nodes(self, alpha: torch.Tensor) -> torch.Tensor:
        """Fiber nodes at pitch ``alpha`` (a 0-d tensor in deg, differentiable), (n, 3)."""
        rate = 1.0 / (self.radius * torch.tan(alpha * (math.pi / 180.0)))
        z = as_tensor(self.z0 + self.s * (self.z1 - self.z0), self.dtype)
        th = torch.cat([self.start + (z - self.z0) * rate, self.start - (z - self.z0) * rate])
        zz = torch.cat([z, z])
        return torch.stack([self.center[0] + self.radius * torch.cos(th),
                            self.center[1] + self.radius * torch.sin(th), zz], -1)

    def _located(self, alpha: float):
        """Host element (mesh id), natural coordinates, their image and the inverse Jacobian there of every
        fiber node at pitch ``alpha`` (numpy; cached per value)."""
        if alpha in self._cache:
            self._cache.move_to_end(alpha)
            return self._cache[alpha]
        from torchfra.fem.embedding import locate_points

        X = self._nodes_numpy(alpha)
        host, xi = locate_points(self.mesh, X)
        N, dN = hex20_shape(xi)
        corners = self.mesh.nodes[self.mesh.elements[host]]
        entry = (host, xi, np.einsum("pa,pai->pi", N, corners), np.linalg.inv(np.einsum("pai,paj->pij", corners, dN)))
        self._cache[alpha] = entry
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return entry

    # -- evaluation ---------------------------------------------------------------------------------
    def _fibers(self, u_m: torch.Tensor, alpha: torch.Tensor, EA: torch.Tensor, tangent: bool, energy: bool):
        """One member's fibers at pitch ``alpha``: residual over every dof (3 n,), sparse tangent (or
        None) and energy (or None)."""
        host, xi0, image, jinv = self._located(float(alpha.detach().tolist()))
        dt = self.dtype
        X = self.nodes(alpha)
        xi = as_tensor(xi0, dt) + torch.einsum("pij,pj->pi", as_tensor(jinv, dt), X - as_tensor(image, dt))
        weights = hex20_shape_values(xi)  # (n_f, 20)
        hosts = torch.as_tensor(self.mesh.elements[host])  # (n_f, 20) mesh node ids
        x = X + torch.einsum("pa,pai->pi", weights, u_m[hosts])  # deformed fiber nodes
        Xe, xe = X[self.conn], x[self.conn]  # (B, 3, 3)
        Xs = torch.einsum("qa,bai->bqi", self.dN, Xe)
        L = torch.linalg.norm(Xs, dim=-1)  # (B, Q) = |X_s|
        xs = torch.einsum("qa,bai->bqi", self.dN, xe)
        eps = 0.5 * ((xs * xs).sum(-1) / L**2 - 1.0)
        c = EA * self.w / L  # as fem.Truss: r_ai = EA sum_q w eps / L dN_qa xs_qi
        f_el = torch.einsum("bq,qa,bqi->bai", c * eps, self.dN, xs)  # (B, 3, 3)
        n_f = X.shape[0]
        f_nodes = torch.zeros(n_f, 3, dtype=dt).index_add(0, self.conn.reshape(-1), f_el.reshape(-1, 3))
        f = torch.zeros(u_m.shape[0], 3, dtype=dt).index_add(
            0, hosts.reshape(-1), (weights[..., None] * f_nodes[:, None, :]).reshape(-1, 3))
        W = 0.5 * EA * (self.w * L * eps**2).sum() if energy else None
        K = None
        if tangent:
            with torch.no_grad():
                outer = xs[..., :, None] * xs[..., None, :] / (L**2)[..., None, None] + \
                    eps[..., None, None] * torch.eye(3, dtype=dt)
                Ke = torch.einsum("mq,qa,qc,mqik->maick", c, self.dN, self.dN, outer).reshape(-1, 9, 9)
                Kf = sp.csr_matrix((Ke.reshape(-1).numpy(), (self._rows, self._cols)), shape=(3 * n_f, 3 * n_f))
                wts = weights.detach().numpy()
                rows = (3 * np.arange(n_f)[:, None, None] + np.arange(3)[None, None, :]).repeat(20, 1).ravel()
                cols = (3 * np.asarray(self.mesh.elements[host])[:, :, None] + np.arange(3)).ravel()
                T = sp.csr_matrix((np.repeat(wts.ravel(), 3), (rows, cols)), shape=(3 * n_f, 3 * u_m.shape[0]))
                K = (T.T @ Kf @ T).tocsr()
        return f.reshape(-1), K, W

    def evaluate(self, u, params, load_factor, tangent=True, energy=False):
        """Residual (N, 3 n_nodes) over every dof; the tangent as one sparse matrix per member in
        ``TermOutput.K_global`` (``Ke`` is None)."""
        N = u.shape[0]
        alpha, EA = params[self.name], params[self.modulus] * self.area
        nominal = torch.tensor(self.nominal, dtype=self.dtype)
        fes, Ks, Ws = [], [], []
        n = 3 * u.shape[1]
        # at the drawn pitch both fields are the same numbers: exactly zero, skipped unless differentiated
        null = (alpha == self.nominal).tolist() if _plain(alpha) else [False] * N
        for m in range(N):
            if null[m]:
                fes.append(torch.zeros(n, dtype=u.dtype, device=u.device))
                Ks.append(sp.csr_matrix((n, n)) if tangent else None)
                Ws.append(torch.zeros((), dtype=u.dtype) if energy else None)
                continue
            fp, Kp, Wp = self._fibers(u[m], alpha[m], EA[m], tangent, energy)
            f0, K0, W0 = self._fibers(u[m], nominal, EA[m], tangent, energy)
            fes.append(fp - f0)
            Ks.append((Kp - K0).tocsr() if tangent else None)
            Ws.append(Wp - W0 if energy else None)
        return TermOutput(torch.stack(fes), None, torch.stack(Ws) if energy else None,
                          torch.ones(N, dtype=torch.bool, device=u.device), K_global=Ks if tangent else None)
