"""``fem.two_node_truss`` through the public API: straight two-node trusses (Abaqus T3D2) embedded
in a brick store exactly the closed-form energy of a two-node truss under an affine deformation,
E A L / 2 * eps^2 with the chord's Green strain eps = (|F d|^2 / |d|^2 - 1) / 2 (the brick's Hex20
interpolation reproduces an affine field, so the embedded ends follow it exactly)."""
import numpy as np
import pytest
import torch

from torchfra import fem
from torchfra.fem.elements import hex20_shape
from torchfra.fem.embedding import locate_points
from torchfra.fem.structured import box_mesh


def test_embedded_two_node_trusses_store_the_closed_form_energy():
    mesh = box_mesh((2.0, 2.0, 4.0), (1, 1, 2))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    ends = np.array([[0.3, 0.4, 0.2], [1.5, 1.1, 1.9], [0.7, 1.6, 3.7]])  # a kinked fiber, 2 segments
    nodes = model.add_nodes(ends)
    host, xi = locate_points(mesh, ends)
    N, _ = hex20_shape(xi)
    for k, node in enumerate(nodes):
        model.embed(int(node), mesh.elements[host[k]], N[k])
    conn = np.array([[nodes[0], nodes[1]], [nodes[1], nodes[2]]])
    truss = model.add(fem.two_node_truss(model, conn, area=0.02, modulus="E_fiber"))
    assert model.n_nodes == mesh.n_nodes + 3 + 2  # the three ends and one middle node per truss
    F = np.array([[1.02, 0.01, 0.0], [0.0, 0.99, 0.015], [0.005, 0.0, 1.03]])
    u = torch.as_tensor(model.X @ (F - np.eye(3)).T)[None]  # affine: every node, embedded ones included
    model.finalize()
    out = truss.evaluate(u, {"E_fiber": torch.tensor([31000.0])}, torch.ones(1), tangent=False, energy=True)
    d = ends[1:] - ends[:-1]
    L = np.linalg.norm(d, axis=1)
    eps = (np.linalg.norm(d @ F.T, axis=1) ** 2 / L**2 - 1) / 2
    assert float(out.energy[0]) == pytest.approx(float(np.sum(31000.0 * 0.02 * L / 2 * eps**2)), rel=1e-12)
    # the middle nodes are tied to the mean of the ends' own hosts: the model's ties reproduce them
    tied = {n: (h, w) for n, h, w in model.embedded_nodes}
    for m in truss.conn[:, 2].tolist():
        hosts, weights = tied[m]
        assert np.allclose(weights @ model.X[hosts], model.X[m]) and weights.sum() == pytest.approx(1.0)


def test_two_node_truss_refuses_unknown_nodes():
    mesh = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    model = fem.Model(mesh)
    with pytest.raises(ValueError, match="node indices must lie in"):
        fem.two_node_truss(model, [[0, mesh.n_nodes + 5]], area=0.1)
