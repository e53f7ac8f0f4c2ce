"""Finite element side of the Rivlin tube benchmark: a plane-strain quarter tube under internal
follower pressure, solved on a sequence of meshes and compared with :mod:`.rivlin`.

Model (mm, MPa): ring sector ``A <= R <= B``, 90 degrees, one Hex20 layer of thickness
``thickness`` along z. Symmetry ``u_y = 0`` on the plane y = 0 (``ymin``) and ``u_x = 0`` on the
plane x = 0 (``ymax``); plane strain ``u_z = 0`` on every node; hybrid Neo-Hookean body;
``FollowerPressure`` on the inner wall (``xmin``).

Incompressible limit. The closed form is for ``D1 = 0``; the hybrid brick needs ``D1 > 0``. The
error of a nearly incompressible solution is linear in ``D1`` for small ``D1`` (first-order
perturbation in ``mu / K``), so each mesh is solved for two members with ``K / mu = r`` and
``10 r`` in one batch and extrapolated to ``D1 = 0``:

    a_0 = (D1_1 a_2 - D1_2 a_1) / (D1_1 - D1_2),

which leaves an ``O(D1^2)`` remainder. The raw values of both members are reported as well, so
the ``D1`` sensitivity is visible. Default ``K / mu = 1e3, 1e4``: the remainder is ~1e-9 relative
(the extrapolations from (1e3, 1e4) and (1e4, 1e5) agree to 1.2e-9), and the stiffer member stays
well clear of the round-off floor of the condensed residual. That floor (relative to the force
scale) grows like ``K / mu`` and with refinement -- measured ~6e-12 (2,4,1), 2e-11 (4,8,1),
6e-11 (8,16,1), 1.2e-10 (16,32,1) at ``K / mu = 1e4`` and ten times that per decade of ``K`` --
so ``K / mu >= 1e6`` cannot meet the force criterion ``rtol = 1e-9`` on these meshes (Newton then
accepts them only through its round-off stagnation test).

Inner radius measure. The mesher places every inner-wall node exactly on ``R = A``; the exact
solution maps that circle to ``r = a``. So the deformed radius ``sqrt(x^2 + y^2)`` of each
inner-wall node is a *nodal* value whose error is the FE nodal displacement error (no geometric
interpolation error of the curved boundary enters). We report the mean over those nodes (the
figure the order study uses) and the largest nodal deviation (which also catches a loss of
axisymmetry).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from torchfra import fem
from torchfra.fem.structured import ring_sector_mesh
from torchfra.verification.rivlin import inner_radius_for_pressure


@dataclass
class TubeResult:
    """One mesh of the study. Radii in mm; errors relative to ``a_exact``."""

    divisions: tuple[int, int, int]
    dofs: int
    K_over_mu: tuple[float, float]
    a_fe_members: tuple[float, float]  # mean inner-wall radius of the two D1 members
    a_fe: float  # extrapolated to D1 = 0
    a_exact: float
    rel_error: float  # (a_fe - a_exact) / a_exact, signed
    max_nodal_rel_error: float  # max over inner-wall nodes of |r_i - a_exact| / a_exact (D1 -> 0)
    d1_sensitivity: float  # (a_fe_members[1] - a_fe_members[0]) / a_exact
    status: tuple[str, str]
    newton_iterations: tuple[int, int]
    increments: tuple[int, int]
    wall_s: float
    order: float | None = None  # observed order vs the previous (twice coarser) mesh


def quarter_tube_model(A: float, B: float, divisions, thickness: float = 1.0) -> fem.Model:
    """Plane-strain quarter tube (see the module docstring); pressure parameter ``"P"``."""
    mesh = ring_sector_mesh(A, B, 90.0, thickness, divisions=tuple(divisions))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), integration="reduced"))
    model.add(fem.FollowerPressure(mesh, "xmin", pressure="P"))
    model.clamp("ymin", (1,))
    model.clamp("ymax", (0,))
    model.clamp("all", (2,))
    return model


def inner_wall_radii(model: fem.Model, u: torch.Tensor) -> torch.Tensor:
    """Deformed radius of every inner-wall node. u: (N, n_nodes, 3) -> (N, k)."""
    inner = model.mesh.node_sets["xmin"]
    x = torch.as_tensor(model.X[inner], dtype=u.dtype) + u[:, inner]
    return torch.sqrt(x[..., 0] ** 2 + x[..., 1] ** 2)


def solve_tube(
    A: float,
    B: float,
    C10: float,
    P: float,
    divisions,
    K_over_mu: tuple[float, float] = (1e3, 1e4),
    thickness: float = 1.0,
    options: fem.NewtonOptions | None = None,
) -> TubeResult:
    """Solve one mesh for the two ``D1`` members ``D1 = 2 / (K_over_mu * 2 C10)`` and compare with
    the closed form. Raises RuntimeError naming the member if Newton did not converge."""
    model = quarter_tube_model(A, B, divisions, thickness)
    mu = 2.0 * C10
    D1 = torch.tensor([2.0 / (r * mu) for r in K_over_mu], dtype=torch.float64)
    n = D1.shape[0]
    t0 = time.perf_counter()
    sol = fem.solve(
        model, {"C10": torch.full((n,), C10), "D1": D1, "P": torch.full((n,), P)}, (1.0,), options
    )
    wall = time.perf_counter() - t0
    if not sol.converged.all():
        bad = int(np.flatnonzero(~sol.converged)[0])
        raise RuntimeError(
            f"quarter tube {tuple(divisions)}: member {bad} (K/mu = {K_over_mu[bad]:g}) {sol.status[bad]} at load "
            f"factor {sol.load_reached[bad]:.4f}, last relative residual {sol.last_residual[bad]:.3e}"
        )
    radii = inner_wall_radii(model, sol.u[:, -1])  # (2, k)
    d1 = D1.numpy()
    radii0 = (d1[0] * radii[1] - d1[1] * radii[0]) / (d1[0] - d1[1])
    members = radii.mean(dim=1).numpy()
    a_fe = float(radii0.mean())
    a_exact = inner_radius_for_pressure(P, A, B, C10)
    return TubeResult(
        divisions=tuple(int(v) for v in divisions),
        dofs=model.n_red,
        K_over_mu=tuple(float(r) for r in K_over_mu),
        a_fe_members=tuple(float(v) for v in members),
        a_fe=a_fe,
        a_exact=a_exact,
        rel_error=(a_fe - a_exact) / a_exact,
        max_nodal_rel_error=float((radii0 - a_exact).abs().max()) / a_exact,
        d1_sensitivity=float(members[1] - members[0]) / a_exact,
        status=tuple(str(s) for s in sol.status),
        newton_iterations=tuple(int(v) for v in sol.iterations),
        increments=tuple(int(v) for v in sol.increments),
        wall_s=wall,
    )


def refinement_study(A, B, C10, P, meshes, **kwargs) -> list[TubeResult]:
    """Solve each mesh (uniform refinements: element size h ~ 1 / angular divisions) and fill in
    the observed order ``log(|e_(k-1)| / |e_k|) / log(h_(k-1) / h_k)`` of the mean inner-radius
    error."""
    results = []
    for divisions in meshes:
        res = solve_tube(A, B, C10, P, divisions, **kwargs)
        if results:
            prev = results[-1]
            refine = res.divisions[1] / prev.divisions[1]
            res.order = math.log(abs(prev.rel_error) / abs(res.rel_error)) / math.log(refine)
        results.append(res)
    return results
