"""VTU export for ParaView, and per-element result fields of a solved state.

The bricks are written as VTK quadratic hexahedra (meshio ``"hexahedron20"``), whose node order is
the Abaqus C3D20 order used throughout torchfra, so connectivity goes out unchanged. Truss terms of a
:class:`~torchfra.fem.Model` (fibers) go out as quadratic lines (``"line3"``: ends, then middle, as
T3D3). In ParaView, *Warp By Vector* with ``U`` shows the deformed shape (mm).

Field names follow Abaqus output variables where one exists: ``U`` (displacement, mm), ``S``
(Cauchy stress, MPa), ``MISES``, ``PRESS`` (hydrostatic pressure, positive in compression),
``EVOL_RATIO`` (current / reference element volume).
"""
from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import torch

from torchfra.fem.kinematics import deformation_gradient, det3
from torchfra.fem.mesh import Mesh
from torchfra.fem.model import Model
from torchfra.fem.solid import Hex20Solid
from torchfra.fem.truss import Truss

# Order of the 6 components of a symmetric tensor as ParaView reads them (XX, YY, ZZ, XY, YZ, XZ).
_VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2))


def element_fields(solid: Hex20Solid, u: torch.Tensor, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    r"""Element averages of the stress of a solved state, for every member.

    solid: the body term (its Gauss data ``dN_dX``, ``wdet``, ``conn`` and material are used);
    u: (N, n_nodes, 3) displacements (mm); params: name -> (N,) the members' parameters.

    At each Gauss point the condensed pressure ``p`` is the one the solver used (the hybrid brick's
    linear element field, or the per-point value for the displacement brick), ``P = dpsi/dF`` and
    the Cauchy stress is :math:`\sigma = P F^T / J`. Averages are over the *current* volume,
    :math:`\bar\sigma = \sum_g w_g J_g \sigma_g / \sum_g w_g J_g = \sum_g w_g P_g F_g^T / \sum_g w_g J_g`.

    Returns (E = elements of the term):

    - ``S``: (N, E, 3, 3) mean Cauchy stress (MPa);
    - ``MISES``: (N, E) current-volume mean of the Gauss-point von Mises stress (MPa);
    - ``PRESS``: (N, E) mean hydrostatic pressure ``-tr(sigma) / 3`` (MPa, positive in compression);
    - ``EVOL_RATIO``: (N, E) current / reference element volume (1 for an incompressible body).

    A member with NaN displacements (it did not reach that load) gets NaN fields.
    """
    parts = {"S": [], "MISES": [], "PRESS": [], "EVOL_RATIO": []}
    with torch.no_grad():
        p_all = solid.gauss_point_pressure(u, params)
        for members, dN, w in solid._geometries(params, u.shape[0]):  # one entry unless the mesh is morphed
            prm = {k: params[k][members, None, None] for k in solid.material.param_names}
            F = deformation_gradient(u[members][:, solid.conn], dN)  # (N, E, G, 3, 3)
            P = solid.material.derivatives(F, p_all[members], prm).P
            tau = P @ F.transpose(-1, -2)  # Kirchhoff stress J sigma
            J = det3(F)
            sigma = tau / J[..., None, None]
            v = w * J  # current volume weights (w: reference volume weights (E, G))
            volume = v.sum(-1)
            S = torch.einsum("eg,negij->neij", w, tau) / volume[..., None, None]
            dev = sigma - torch.diagonal(sigma, dim1=-2, dim2=-1).mean(-1)[..., None, None] * torch.eye(3, dtype=F.dtype)
            mises_gp = torch.sqrt(1.5 * (dev * dev).sum((-1, -2)))
            parts["S"].append(S)
            parts["MISES"].append((v * mises_gp).sum(-1) / volume)
            parts["PRESS"].append(-torch.diagonal(S, dim1=-2, dim2=-1).mean(-1))
            parts["EVOL_RATIO"].append(volume / w.sum(-1))
    return {k: torch.cat(v) for k, v in parts.items()}


def write_vtu(
    path: str | Path,
    mesh_or_model: Mesh | Model,
    u=None,
    point_data: dict | None = None,
    cell_data: dict | None = None,
) -> Path:
    """Write one state of one member as a VTU file (ParaView) and return its path.

    mesh_or_model: a :class:`Mesh` (bricks only) or a :class:`Model` (its nodes include extra nodes,
        e.g. fiber nodes, and its :class:`Truss` terms are written as ``line3`` cells).
    u: (n_points, 3) displacements in mm (numpy or torch), written as point field ``U``.
    point_data: name -> (n_points,) or (n_points, k) arrays.
    cell_data: name -> (n_elements, ...) arrays for the *bricks*, in mesh element order; a (3, 3)
        tensor per cell is written as 6 components (XX, YY, ZZ, XY, YZ, XZ). Line cells get NaN.
    """
    if isinstance(mesh_or_model, Model):
        mesh, points = mesh_or_model.mesh, mesh_or_model.X
        lines = [t.conn.numpy() for t in mesh_or_model.terms if isinstance(t, Truss)]
    elif isinstance(mesh_or_model, Mesh):
        mesh, points, lines = mesh_or_model, mesh_or_model.nodes, []
    else:
        raise TypeError(f"write_vtu needs a Mesh or a Model, got {type(mesh_or_model).__name__}")
    n_points, n_el = points.shape[0], mesh.n_elements
    cells = [("hexahedron20", mesh.elements)]
    if lines:
        cells.append(("line3", np.concatenate(lines)))

    pdata = {}
    if u is not None:
        pdata["U"] = _point_array("U", u, n_points)
        if pdata["U"].shape != (n_points, 3):
            raise ValueError(f"u must have shape ({n_points}, 3) (one displacement per point), got {pdata['U'].shape}")
    for name, values in (point_data or {}).items():
        pdata[name] = _point_array(name, values, n_points)

    cdata = {}
    for name, values in (cell_data or {}).items():
        arr = _numpy(values)
        if arr.shape[:1] != (n_el,):
            raise ValueError(f"cell field '{name}' has shape {arr.shape}; it needs one row per brick ({n_el})")
        if arr.shape[1:] == (3, 3):
            arr = np.stack([arr[:, i, j] for i, j in _VOIGT], axis=1)
        blocks = [arr]
        if lines:
            blocks.append(np.full((cells[1][1].shape[0], *arr.shape[1:]), np.nan))
        cdata[name] = blocks

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.Mesh(points, cells, point_data=pdata, cell_data=cdata).write(path, file_format="vtu")
    return path


def _numpy(values) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().numpy()
    return np.asarray(values, dtype=np.float64)


def _point_array(name: str, values, n_points: int) -> np.ndarray:
    arr = _numpy(values)
    if arr.shape[:1] != (n_points,):
        raise ValueError(f"point field '{name}' has shape {arr.shape}; it needs one row per point ({n_points})")
    return arr
