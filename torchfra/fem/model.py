"""A finite element model: mesh, energy terms, constraints; evaluated for N members at once."""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from torchfra.fem.assembly import SparsePattern
from torchfra.fem.constraints import DofMap
from torchfra.fem.mesh import Mesh, MeshError
from torchfra.fem.morph import MorphError
from torchfra.fem.terms import Term


@dataclass
class Evaluation:
    """Model state of N members: reduced residual (N, n_red), its scale (N,) for relative
    convergence tests, admissibility (N,), total potential (N,) if asked, reduced tangents if asked."""

    residual: torch.Tensor
    force_scale: torch.Tensor
    ok: torch.Tensor
    energy: torch.Tensor | None = None
    tangents: list[sp.csr_matrix] | None = None
    rhs: torch.Tensor | None = None  # condensed residual that goes with the tangents (local unknowns)


class Model:
    """Mesh + terms + constraints.

    >>> model = Model(mesh)
    >>> model.add(Hex20Solid(mesh, NeoHookean()))
    >>> model.clamp("zmin"); model.rigid("zmax")
    >>> model.add(FollowerPressure(mesh, "ymax", pressure="P"))
    """

    def __init__(self, mesh: Mesh, dtype=torch.float64, memory_budget_mb: float = 1024.0):
        self.mesh, self.dtype = mesh, dtype
        self.X = mesh.nodes.copy()
        self.terms: list[Term] = []
        self._clamped: list[np.ndarray] = []
        self._prescribed: dict[int, float] = {}
        self._rigid: list[np.ndarray] = []
        self._embedded: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._morphs: dict[str, tuple[np.ndarray, object]] = {}
        self.memory_budget_mb = memory_budget_mb
        self.dofmap: DofMap | None = None

    @property
    def n_nodes(self) -> int:
        return self.X.shape[0]

    @property
    def symmetric_tangent(self) -> bool:
        """True when every term is conservative: the tangent is then the Hessian of the total
        potential (through the constraints too), hence symmetric, and Newton may factorize it as such."""
        return all(t.conservative for t in self.terms)

    # -- read-only description (exporters, reports) ---------------------------------------------------
    @property
    def clamped_dofs(self) -> np.ndarray:
        """Sorted global dofs ``3 * node + component`` fixed at zero."""
        return np.unique(np.concatenate(self._clamped)) if self._clamped else np.zeros(0, dtype=np.int64)

    @property
    def prescribed_dofs(self) -> dict[int, float]:
        """Global dof -> displacement (mm) reached at load factor 1."""
        return dict(self._prescribed)

    @property
    def rigid_node_sets(self) -> list[np.ndarray]:
        """Node sets moving as rigid bodies (reference point: their centroid)."""
        return list(self._rigid)

    @property
    def embedded_nodes(self) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """``(node, host nodes, weights)`` ties of embedded nodes."""
        return list(self._embedded)

    # -- building ----------------------------------------------------------------------------------
    def add_nodes(self, X: np.ndarray) -> np.ndarray:
        """Append extra nodes (e.g. fiber nodes); returns their indices."""
        self._editable()
        first = self.n_nodes
        self.X = np.concatenate([self.X, np.asarray(X, dtype=np.float64).reshape(-1, 3)])
        return np.arange(first, self.n_nodes)

    def add(self, term: Term) -> Term:
        self._editable()
        self.terms.append(term)
        return term

    def _nodes(self, name_or_nodes) -> np.ndarray:
        if isinstance(name_or_nodes, str):
            if name_or_nodes in self.mesh.node_sets:
                return self.mesh.node_sets[name_or_nodes]
            if name_or_nodes in self.mesh.face_sets:
                return self.mesh.face_set_nodes(name_or_nodes)
            raise MeshError(
                f"no node set or face set named '{name_or_nodes}'; node sets: {sorted(self.mesh.node_sets)}, "
                f"face sets: {sorted(self.mesh.face_sets)}"
            )
        return np.asarray(name_or_nodes, dtype=np.int64).ravel()

    def clamp(self, nodes, components=(0, 1, 2)) -> None:
        """Fix the given displacement components (0=x, 1=y, 2=z) of a node set / face set to zero."""
        self._editable()
        n = self._nodes(nodes)
        self._clamped.append((3 * n[:, None] + np.asarray(components)).ravel())

    def prescribe(self, nodes, component: int, value) -> None:
        """Displacement ``component`` of the nodes equals ``load_factor * value`` (mm); ``value`` is
        one number or one per node."""
        self._editable()
        n = self._nodes(nodes)
        values = np.broadcast_to(np.asarray(value, dtype=np.float64), n.shape)
        for node, v in zip(n, values):
            self._prescribed[int(3 * node + component)] = float(v)

    def rigid_motion(self, a, body: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """Motion of rigid body ``body`` (in the order of :meth:`rigid` calls) from reduced unknowns
        ``a`` (..., n_red), e.g. ``Solution.a``: the translation of its reference point (the centroid
        of its nodes, mm) and its rotation vector (axis times angle, rad; ``fem.rotation_matrix``
        turns it into R), each (..., 3). These are the last 6 entries per body of ``a``; a rigid
        node X moves by ``translation + (R - I) (X - centroid)``."""
        self.finalize()
        if not 0 <= body < len(self.dofmap.bodies):
            raise ValueError(f"rigid body {body} does not exist; the model has {len(self.dofmap.bodies)}")
        cols = torch.as_tensor(self.dofmap.bodies[body].columns)
        a = torch.as_tensor(a)
        return a[..., cols[:3]], a[..., cols[3:]]

    def rigid(self, nodes) -> None:
        """The nodes move as one rigid body (finite rotation): a face that stays flat and undeformed."""
        self._editable()
        self._rigid.append(np.unique(self._nodes(nodes)))

    def embed(self, node: int, hosts: np.ndarray, weights: np.ndarray) -> None:
        """Tie ``node`` to host nodes: u_node = sum weights * u_hosts (embedded-element constraint)."""
        self._editable()
        self._embedded.append((int(node), np.asarray(hosts, dtype=np.int64), np.asarray(weights, dtype=np.float64)))

    def morph(self, name: str, field: np.ndarray, info=None) -> None:
        """Reference coordinates ``X + s field`` with ``s`` the member's parameter ``name`` (mm): a
        geometric imperfection every member may carry with its own size (``fem.morph``). ``field``:
        (n_mesh_nodes, 3) or (n_nodes, 3); embedded nodes follow their hosts. ``info``: the
        parameter's ``ParameterInfo`` (range checked at every solve). The morph must vanish on
        clamped, prescribed and rigid nodes and on terms that cannot follow it."""
        self._editable()
        field = np.asarray(field, dtype=np.float64)
        if field.ndim != 2 or field.shape[1] != 3 or field.shape[0] not in (self.mesh.n_nodes, self.n_nodes):
            raise MorphError(f"morph '{name}': field must have shape ({self.mesh.n_nodes}, 3) or ({self.n_nodes}, 3), "
                             f"got {field.shape}")
        if not np.all(np.isfinite(field)):
            raise MorphError(f"morph '{name}': field has non-finite entries at nodes "
                             f"{np.flatnonzero(~np.isfinite(field).all(1))[:5].tolist()}")
        if name in self._morphs:
            raise MorphError(f"morph '{name}' is already defined")
        self._morphs[name] = (field, info)

    @property
    def morph_names(self) -> list[str]:
        """Parameters that move the reference geometry (empty: every member shares the mesh)."""
        return list(self._morphs)

    def morph_fields(self) -> np.ndarray:
        """Every morph's nodal field on every model node (n_nodes, 3, K); embedded nodes follow their hosts."""
        out = np.zeros((self.n_nodes, 3, len(self._morphs)))
        for k, (field, _) in enumerate(self._morphs.values()):
            out[: field.shape[0], :, k] = field
            for node, hosts, weights in self._embedded:
                out[node, :, k] = weights @ out[hosts, :, k]
        return out

    def _attach_morphs(self) -> None:
        if not self._morphs:
            return
        fields = self.morph_fields()
        moving = np.abs(fields).max(axis=(1, 2)) > 0
        names = list(self._morphs)
        for t in self.terms:
            if t.global_dofs:  # no blocks to follow a morph: the term says what it allows
                t.morphs_present(names)
        pinned = {"clamped": self.clamped_dofs // 3, "prescribed": np.asarray(sorted(self._prescribed), dtype=np.int64) // 3}
        for k, nodes in enumerate(self._rigid):
            pinned[f"rigid body {k}"] = nodes
        for what, nodes in pinned.items():
            bad = nodes[moving[nodes]] if nodes.size else nodes
            if bad.size:
                raise MorphError(f"morphs {names} move {bad.size} {what} nodes (first: node {int(bad[0])}); a morph "
                                 "must vanish where the model is constrained")
        for t in self.terms:
            nodes = np.unique(t.dofs // 3)
            if not moving[nodes].any():
                continue
            if not hasattr(t, "set_morph"):
                raise MorphError(f"morphs {names} move nodes of a {type(t).__name__} term (first: node "
                                 f"{int(nodes[moving[nodes]][0])}), which cannot follow a morph; keep the morph zero there")
            t.set_morph(names, self.X, fields, self.dtype)

    def _editable(self):
        if self.dofmap is not None:
            raise RuntimeError("the model is finalized; build a new Model to change it")

    def finalize(self) -> "Model":
        if self.dofmap is not None:
            return self
        if not self.terms:
            raise ValueError("the model has no terms; add at least a solid body")
        self._attach_morphs()
        clamped = self.clamped_dofs
        presc = {d: v for d, v in self._prescribed.items() if d not in set(clamped.tolist())}
        self.dofmap = DofMap(self.n_nodes, clamped, presc, self._rigid, self._embedded, self.X, self.dtype)
        n = 3 * self.n_nodes
        self.pattern = SparsePattern(n, [t.dofs for t in self.terms])
        self._dofs = [torch.arange(n) if t.global_dofs else torch.as_tensor(t.dofs).ravel() for t in self.terms]
        self._free_nodes_check()
        return self

    def _free_nodes_check(self):
        used = np.zeros(3 * self.n_nodes, dtype=bool)
        for t in self.terms:
            used[t.dofs.ravel()] = True
        col_used = np.asarray(abs(self.dofmap.T).T @ used.astype(float)).ravel() > 0
        for b in self.dofmap.bodies:  # rotations act through the nonlinear part of the map
            col_used[b.columns[3:]] = True
        if not col_used.all():
            raise ValueError(
                f"{int((~col_used).sum())} unknowns touch no element (orphan nodes?); the stiffness would be singular"
            )

    @property
    def n_red(self) -> int:
        return self.finalize().dofmap.n_red

    def param_names(self) -> list[str]:
        return sorted({k for t in self.terms for k in t.param_names} | set(self._morphs))

    def validate(self, params: dict[str, torch.Tensor]) -> int:
        """Check parameters (every member); returns the number of members."""
        sizes = {k: v.shape for k, v in params.items()}
        n = {s[0] for s in sizes.values() if len(s) == 1}
        if len(n) != 1 or any(len(s) != 1 for s in sizes.values()):
            raise ValueError(f"every parameter must be a 1-D tensor over the same members, got shapes {sizes}")
        for t in self.terms:
            t.validate(params)
        infos = {name: info for name, (_, info) in self._morphs.items() if info is not None}
        if infos:
            from torchfra.fem.params import check_parameters

            check_parameters(infos, params, "the model's morph")
        return n.pop()

    # -- reference state ---------------------------------------------------------------------------
    @property
    def has_preload(self) -> bool:
        """True when a load term acts before the load path (``Term.preload``, e.g. the weight in a
        DIC recording's reference image): :func:`torchfra.fem.newton.solve` settles it first."""
        return any(t.kind == "load" and getattr(t, "preload", False) for t in self.terms)

    @property
    def is_settling(self) -> bool:
        return getattr(self, "_settling", False)

    @contextmanager
    def settling(self):
        """Within this context the load factor scales the preloads alone (the other loads and the
        prescribed displacements are off): the path from the unloaded body to its reference state."""
        before = self.is_settling
        self._settling = True
        try:
            yield self
        finally:
            self._settling = before

    def term_load_factor(self, term: Term, load_factor: torch.Tensor) -> torch.Tensor:
        """The load factor ``term`` sees at the path's ``load_factor``: a preload acts in full (1) on
        the load path and ramps while settling; the other loads ramp on the path and are off while settling."""
        if term.kind != "load":
            return load_factor
        if getattr(term, "preload", False):
            return load_factor if self.is_settling else torch.ones_like(load_factor)
        return torch.zeros_like(load_factor) if self.is_settling else load_factor

    def prescribed_factor(self, load_factor: torch.Tensor) -> torch.Tensor:
        """The factor on the prescribed displacements: the load factor, zero while settling."""
        return torch.zeros_like(load_factor) if self.is_settling else load_factor

    # -- evaluation --------------------------------------------------------------------------------
    def displacement(self, a: torch.Tensor, load_factor: torch.Tensor) -> torch.Tensor:
        """a: (N, n_red) -> nodal displacements (N, n_nodes, 3)."""
        a, load_factor = torch.as_tensor(a, dtype=self.dtype), torch.as_tensor(load_factor, dtype=self.dtype)
        return self.finalize().dofmap.expand(a, self.prescribed_factor(load_factor)).reshape(a.shape[0], -1, 3)

    def initial_local(self, N: int) -> list[torch.Tensor | None]:
        """Element-local unknowns of every term at the unloaded state (zeros), (N, B, L) or None."""
        return [torch.zeros(N, t.dofs.shape[0], t.n_local, dtype=self.dtype) if t.n_local else None for t in self.terms]

    def evaluate(self, a, params, load_factor, tangent=False, energy=False, local=None) -> Evaluation:
        """Reduced residual (and tangents, energy) of members ``a: (N, n_red)``.

        local: per term, its element-local unknowns (N, B, L) carried by Newton, or None to use
        their stationary values for ``a``.
        """
        self.finalize()
        a, load_factor = torch.as_tensor(a, dtype=self.dtype), torch.as_tensor(load_factor, dtype=self.dtype)
        params = {k: torch.as_tensor(v, dtype=self.dtype) for k, v in params.items()}
        N = a.shape[0]
        local = local or [None] * len(self.terms)
        if tangent:
            chunk = self._chunk_size()
            if N > chunk:
                parts = [
                    self.evaluate(a[i : i + chunk], {k: v[i : i + chunk] for k, v in params.items()},
                                  load_factor[i : i + chunk], tangent, energy,
                                  [None if l is None else l[i : i + chunk] for l in local])
                    for i in range(0, N, chunk)
                ]
                return Evaluation(
                    torch.cat([p.residual for p in parts]), torch.cat([p.force_scale for p in parts]),
                    torch.cat([p.ok for p in parts]),
                    torch.cat([p.energy for p in parts]) if energy else None,
                    [K for p in parts for K in p.tangents],
                    torch.cat([p.rhs for p in parts]),
                )
        u = self.displacement(a, load_factor)
        n = 3 * self.n_nodes
        r_full = torch.zeros(N, n, dtype=a.dtype)
        rhs_full = torch.zeros(N, n, dtype=a.dtype)
        scale = torch.zeros(N, dtype=a.dtype)
        ok = torch.ones(N, dtype=torch.bool)
        W = torch.zeros(N, dtype=a.dtype) if energy else None
        blocks, extra = [], []
        for t, dofs, loc in zip(self.terms, self._dofs, local):
            kw = {"local": loc} if t.n_local else {}
            out = t.evaluate(u, params, self.term_load_factor(t, load_factor), tangent=tangent, energy=energy, **kw)
            r_t = torch.zeros(N, n, dtype=a.dtype).index_add_(1, dofs, out.fe.reshape(N, -1))
            r_full += r_t
            fe_c = out.fe if out.fe_condensed is None else out.fe_condensed
            rhs_full.index_add_(1, dofs, fe_c.reshape(N, -1))
            scale = torch.maximum(scale, torch.linalg.norm(r_t, dim=1))
            ok &= out.ok
            if energy:
                if out.energy is None:
                    raise ValueError(f"{type(t).__name__} is not conservative: the model has no total potential")
                W += out.energy
            blocks.append(out.Ke)
            if tangent and out.K_global is not None:
                extra.append(out.K_global)
        r = self.dofmap.reduce(r_full, a)
        rhs = self.dofmap.reduce(rhs_full, a)
        Ks = self._reduced_tangents(a, r_full, blocks, extra) if tangent else None
        return Evaluation(r, scale, ok, W, Ks, rhs)

    def local_update(self, a, da, params, load_factor, local) -> list[torch.Tensor | None]:
        """Newton update of the element-local unknowns that goes with the step ``a -> a + da``."""
        u = self.displacement(a, load_factor)
        du = self.displacement(a + da, load_factor) - u
        return [
            None if loc is None else loc + t.local_update(u, params, loc, du)
            for t, loc in zip(self.terms, local)
        ]

    def nodal_forces(self, u: torch.Tensor, params, load_factor, kinds=("internal",)) -> torch.Tensor:
        """Sum of the nodal forces of the terms of the given kinds, (N, n_nodes, 3) in N.

        At equilibrium the internal forces at constrained nodes are the reactions (Abaqus RF).
        """
        self.finalize()
        N, n = u.shape[0], 3 * self.n_nodes
        r = torch.zeros(N, n, dtype=u.dtype)
        for t, dofs in zip(self.terms, self._dofs):
            if t.kind in kinds:
                r.index_add_(1, dofs, t.evaluate(u, params, self.term_load_factor(t, load_factor),
                                                 tangent=False).fe.reshape(N, -1))
        return r.reshape(N, -1, 3)

    def _reduced_tangents(self, a, r_full, blocks, extra=()) -> list[sp.csr_matrix]:
        """``J^T K J`` (+ the constraints' geometric stiffness) per member; ``extra``: per global term, one
        sparse full-dof tangent per member, added to the block assembly."""
        data = self.pattern.assemble(blocks).numpy()
        Js, JTs = self.dofmap.jacobian(a), self.dofmap.jacobian(a, transposed=True)
        geo = self.dofmap.geometric_stiffness(a, r_full)
        Ks = []
        for m in range(a.shape[0]):
            K = self.pattern.to_scipy(data[m])
            for per_member in extra:
                K = K + per_member[m]
            Kr = JTs[m] @ (K @ Js[m])
            if geo:
                rows = np.concatenate([np.repeat(cols, 3) for cols, _ in geo])
                cols_ = np.concatenate([np.tile(cols, 3) for cols, _ in geo])
                vals = np.concatenate([H[m].ravel() for _, H in geo])
                Kr = Kr + sp.csr_matrix((vals, (rows, cols_)), shape=Kr.shape)
            Kr = Kr.tocsr()
            Ks.append(Kr)
        return Ks

    def _chunk_size(self) -> int:
        per_member = sum(t.dofs.shape[0] * t.dofs.shape[1] ** 2 for t in self.terms) * 8 * 3  # Ke + temporaries
        return max(1, int(self.memory_budget_mb * 2**20 // per_member))
