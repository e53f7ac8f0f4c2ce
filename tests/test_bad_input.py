"""Bad input gets a clear error naming the culprit (element, node, set, parameter, member)."""
import numpy as np
import pytest
import torch

from torchfra import fem
from torchfra.fem.structured import box_mesh


@pytest.fixture
def mesh():
    return box_mesh((1.0, 1.0, 2.0), (1, 1, 2))


def test_wrong_connectivity_size(mesh):
    with pytest.raises(fem.MeshError, match=r"\(n_elements, 20\)"):
        fem.Mesh(mesh.nodes, mesh.elements[:, :8])


def test_node_index_out_of_range(mesh):
    el = mesh.elements.copy()
    el[1, 3] = mesh.n_nodes + 5
    with pytest.raises(fem.MeshError, match="element 1 refers to a node outside"):
        fem.Mesh(mesh.nodes, el)


def test_wrong_node_order_is_named(mesh):
    el = mesh.elements.copy()
    el[0, [8, 10]] = el[0, [10, 8]]  # two mid-edge nodes swapped
    with pytest.raises(fem.MeshError, match="element 0: node .* not between corners"):
        fem.Mesh(mesh.nodes, el)


def test_inverted_element_is_named(mesh):
    el = mesh.elements.copy()
    el[1] = el[1][[4, 5, 6, 7, 0, 1, 2, 3, 12, 13, 14, 15, 8, 9, 10, 11, 16, 17, 18, 19]]  # upside down
    with pytest.raises(fem.MeshError, match="element 1 is inverted or degenerate"):
        fem.Mesh(mesh.nodes, el)


def test_degenerate_element_is_named(mesh):
    nodes = mesh.nodes.copy()
    top = mesh.elements[1, 4:8]
    nodes[top, 2] = nodes[mesh.elements[1, 0], 2]  # flatten element 1 (and its mid-edge nodes stay put)
    with pytest.raises(fem.MeshError, match="element 1"):
        fem.Mesh(nodes, mesh.elements)


def test_non_finite_coordinate_is_named(mesh):
    nodes = mesh.nodes.copy()
    nodes[7, 1] = np.nan
    with pytest.raises(fem.MeshError, match="node 7"):
        fem.Mesh(nodes, mesh.elements)


def test_missing_sets_are_named(mesh):
    model = fem.Model(mesh)
    with pytest.raises(fem.MeshError, match="no node set or face set named 'bottom'.*zmin"):
        model.clamp("bottom")
    with pytest.raises(fem.MeshError, match="face set 'side' does not exist"):
        fem.FollowerPressure(mesh, "side")


def test_open_cavity_refused(mesh):
    with pytest.raises(ValueError, match="not closed"):
        fem.CavityPressure(mesh, "xmin")


def _model(mesh):
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.clamp("zmin")
    model.prescribe("zmax", 2, 0.1)
    return model


@pytest.mark.parametrize(
    "name,values,message",
    [
        ("C10", [0.5, float("nan")], "parameter C10 of member 1 is nan"),
        ("C10", [-0.5, 0.5], "parameter C10 of member 0 is -0.5"),
        ("D1", [0.1, 0.0], "parameter D1 of member 1 is 0.0"),
    ],
)
def test_bad_parameters_are_named(mesh, name, values, message):
    params = {"C10": torch.tensor([0.5, 0.5]), "D1": torch.tensor([0.1, 0.1])}
    params[name] = torch.tensor(values)
    with pytest.raises(fem.ParameterError, match=message):
        fem.solve(_model(mesh), params)


def test_missing_parameter_and_ragged_members(mesh):
    with pytest.raises(fem.ParameterError, match="needs parameter 'D1'"):
        fem.solve(_model(mesh), {"C10": torch.tensor([0.5])})
    with pytest.raises(ValueError, match="same members"):
        fem.solve(_model(mesh), {"C10": torch.tensor([0.5, 0.4]), "D1": torch.tensor([0.1])})


def test_bad_load_factors(mesh):
    params = {"C10": torch.tensor([0.5]), "D1": torch.tensor([0.1])}
    with pytest.raises(ValueError, match=r"load factors must lie in \(0, 1\]"):
        fem.solve(_model(mesh), params, [0.5, 1.5])


def test_conflicting_constraints_name_the_node(mesh):
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    model.clamp("xmin")
    model.rigid("zmax")
    with pytest.raises(ValueError, match="node .* of a rigid node set is also clamped"):
        model.finalize()


def test_unknown_integration_rule(mesh):
    with pytest.raises(ValueError, match="integration must be 'reduced'"):
        fem.Hex20Solid(mesh, fem.NeoHookean(), integration="2x2x2")
