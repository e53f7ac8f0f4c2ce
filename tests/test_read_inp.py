"""torchfra.io.abaqus.read.read_inp: decks that write_inp writes read back into the same model (same
residual at a random state, same parameters), a hand-written Abaqus deck read and solved, and
unsupported or broken decks rejected with the file, line and keyword."""
import re

import numpy as np
import pytest
import torch
from helpers import block_with_cavity

from torchfra import fem
from torchfra.fem.embedding import embedding_weights
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus.read import InpError, read_inp
from torchfra.io.abaqus.write import write_inp

RTOL = 1e-12


def residual(model, params, a, load_factor):
    """Reduced residual (N, n_red) of members ``a`` (N, n_red), every member with the same params."""
    N = a.shape[0]
    p = {k: torch.full((N,), float(v)) for k, v in params.items()}
    return model.evaluate(a, p, torch.full((N,), load_factor)).residual


def assert_round_trip(original, params, tmp_path, name, **kw):
    """write_inp -> read_inp gives the same constraints, parameters and residual (to RTOL)."""
    deck = write_inp(tmp_path / f"{name}.inp", original, params, **kw)
    model, read_params = read_inp(deck)
    assert read_params == {k: params[k] for k in original.param_names()}
    # coordinates to 1e-12 mm: write_inp keeps 14 significant digits where repr() needs more than the
    # 20 characters CalculiX reads
    assert np.allclose(model.X, original.X, rtol=0, atol=1e-12) and model.mesh.n_nodes == original.mesh.n_nodes
    assert np.array_equal(model.mesh.elements, original.mesh.elements)
    assert np.array_equal(model.clamped_dofs, original.clamped_dofs)
    assert model.prescribed_dofs == original.prescribed_dofs
    assert [s.tolist() for s in model.rigid_node_sets] == [s.tolist() for s in original.rigid_node_sets]
    assert model.n_red == original.n_red
    a = 0.02 * torch.randn(2, model.n_red, generator=torch.Generator().manual_seed(1))
    r0 = residual(original, params, a, 0.7)
    r1 = residual(model, read_params, a, 0.7)
    rel = float((r1 - r0).abs().max() / r0.abs().max())
    print(f"{name}: rel = {rel:.2e}, max |r| = {float(r0.abs().max()):.3g}")
    assert rel < RTOL, f"{name}: max |r_read - r_original| / max |r| = {rel:.2e}"
    return model, deck


@pytest.mark.parametrize(
    "formulation, integration, element_type, material",
    [
        ("hybrid", "reduced", "C3D20RH", fem.NeoHookean),
        ("displacement", "reduced", "C3D20R", fem.NeoHookean),
        ("hybrid", "full", "C3D20H", fem.MooneyRivlin),
        ("displacement", "full", "C3D20", fem.MooneyRivlin),
    ],
)
def test_block_round_trip(tmp_path, formulation, integration, element_type, material):
    """Hex20 block clamped at its base, follower pressure on a side, a prescribed top displacement."""
    mesh = box_mesh((2.0, 2.0, 4.0), (1, 2, 2), distortion=0.1)
    original = fem.Model(mesh)
    original.add(fem.Hex20Solid(mesh, material(), formulation, integration=integration))
    original.add(fem.FollowerPressure(mesh, "ymin", pressure="P"))
    original.clamp("zmin")
    original.prescribe("zmax", 2, 0.3)
    params = {"C10": 0.1, "C01": 0.02, "D1": 0.37, "P": 0.013}
    params = {k: params[k] for k in original.param_names()}
    model, _ = assert_round_trip(original, params, tmp_path, element_type, element_type=element_type)
    solid = model.terms[0]
    assert (solid.formulation, solid.integration, type(solid.material)) == (formulation, integration, material)
    assert isinstance(model.terms[1], fem.FollowerPressure)  # an open face: follower, not cavity


def fiber_model(pressure=fem.CavityPressure):
    """Block with a cavity: hybrid Mooney-Rivlin body, an embedded straight 3-node fiber pair,
    cavity pressure, self-weight, clamped base and rigid top."""
    mesh = block_with_cavity()
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.MooneyRivlin()))
    X = np.column_stack([np.full(5, 1.5), np.full(5, 0.5), np.linspace(0.2, 1.9, 5)])
    nodes = model.add_nodes(X)
    model.add(fem.Truss(model.X, nodes[np.array([[0, 2, 1], [2, 4, 3]])], area=0.01))
    for node, (hosts, w) in zip(nodes, embedding_weights(mesh, X)):
        model.embed(int(node), hosts, w)
    model.add(pressure(mesh, "cavity"))
    model.add(fem.Gravity(mesh, direction=(0.0, -1.0, 0.0)))
    model.clamp("zmin")
    model.rigid("zmax")
    return model


FIBER_PARAMS = {"C10": 0.1, "C01": 0.03, "D1": 0.05, "E_fiber": 300.0, "P": 0.02, "density": 2e-8}


def test_fibers_cavity_gravity_rigid_round_trip(tmp_path):
    """T3D3 fibers tied by *EQUATION, *DLOAD pressure closing a cavity, GRAV, *RIGID BODY."""
    original = fiber_model()
    model, deck = assert_round_trip(original, FIBER_PARAMS, tmp_path, "fibers", element_type="C3D20H")
    text = deck.read_text()
    assert "*RIGID BODY" in text and "*EQUATION" in text and "GRAV" in text and "TYPE=T3D3" in text
    assert len(model.embedded_nodes) == 5
    assert [type(t) for t in model.terms] == [fem.Hex20Solid, fem.Truss, fem.CavityPressure, fem.Gravity]


def test_embedded_element_card_ties_like_the_equations(tmp_path):
    """The same deck with *EMBEDDED ELEMENT instead of the *EQUATION ties reads to the same model."""
    original = fiber_model()
    deck = write_inp(tmp_path / "fibers.inp", original, FIBER_PARAMS, element_type="C3D20H")
    text = re.sub(r"\*EQUATION\n\d+\n[^*]*", "", deck.read_text())
    assert "*EQUATION" not in text
    text = text.replace("*BOUNDARY\n", "*EMBEDDED ELEMENT, HOST ELSET=SOLID0\nTRUSS1\n*BOUNDARY\n", 1)
    (tmp_path / "embedded.inp").write_text(text)
    model, params = read_inp(tmp_path / "embedded.inp")
    a = 0.02 * torch.randn(2, model.n_red, generator=torch.Generator().manual_seed(2))
    r0, r1 = residual(original, FIBER_PARAMS, a, 1.0), residual(model, params, a, 1.0)
    assert float((r1 - r0).abs().max() / r0.abs().max()) < RTOL


def test_t3d2_pair_equals_straight_t3d3_at_an_affine_state(tmp_path):
    """write_inp(truss_element="T3D2") splits each Line3 truss into two T3D2; read back, each T3D2 is
    a Line3 truss with a tied middle node (a constant-strain truss). On a straight fiber under an
    affine displacement both store the same energy, so the residuals agree."""
    original = fiber_model(fem.FollowerPressure)
    deck = write_inp(tmp_path / "t3d2.inp", original, FIBER_PARAMS, element_type="C3D20H", truss_element="T3D2")
    model, params, ids = read_inp(deck, with_ids=True)
    assert params == {k: FIBER_PARAMS[k] for k in original.param_names()}
    assert model.n_nodes == original.n_nodes + 4 and (ids.nodes[-4:] == -1).all()
    assert model.terms[1].conn.shape == (4, 3) and model.n_red == original.n_red
    # affine displacement u = G X with u = 0 on the clamped base z = 0, the rigid top translating
    G = torch.tensor([[0.0, 0.0, 0.02], [0.0, 0.0, -0.03], [0.0, 0.0, 0.05]])
    u = torch.as_tensor(original.X) @ G.T
    T = original.finalize().dofmap.T.toarray()
    a = torch.as_tensor(np.linalg.lstsq(T, u.reshape(-1).numpy(), rcond=None)[0])[None]
    assert np.abs(T @ a[0].numpy() - u.reshape(-1).numpy()).max() < 1e-13  # exact: the field is admissible
    r0, r1 = residual(original, FIBER_PARAMS, a, 1.0), residual(model, params, a, 1.0)
    assert float((r1 - r0).abs().max() / r0.abs().max()) < RTOL


# A 4 x 1 x 1 mm cantilever of two C3D20RH bricks along x, written by hand: node ids encode their
# place (plane x = 0, 2, 4 -> 1xx, 2xx, 3xx; mid-edge nodes at x = 1, 3 -> 15x, 25x), elements 11, 12.
HAND_DECK = """\
*Heading
 two bricks, clamped at x = 0, pressure on top
** nodes of the three cross-sections: corners, then mid-edge nodes
*NODE, NSET=ALL
101, 0., 0., 0.
102, 0., 1., 0.
103, 0., 1., 1.
104, 0., 0., 1.
105, 0., 0.5, 0.
106, 0., 1., 0.5
107, 0., 0.5, 1.
108, 0., 0., 0.5
201, 2., 0., 0.
202, 2., 1., 0.
203, 2., 1., 1.
204, 2., 0., 1.
205, 2., 0.5, 0.
206, 2., 1., 0.5
207, 2., 0.5, 1.
208, 2., 0., 0.5
301, 4., 0., 0.
302, 4., 1., 0.
303, 4., 1., 1.
304, 4., 0., 1.
305, 4., 0.5, 0.
306, 4., 1., 0.5
307, 4., 0.5, 1.
308, 4., 0., 0.5
*node
151, 1., 0., 0.
152, 1., 1., 0.
153, 1., 1., 1.
154, 1., 0., 1.
251, 3., 0., 0.
252, 3., 1., 0.
253, 3., 1., 1.
254, 3., 0., 1.
*Element, type=C3D20RH, elset=BEAM
11, 101, 201, 202, 102, 104, 204, 203, 103, 151, 205, 152, 105, 154, 207, 153, 107,
108, 208, 206, 106
12, 201, 301, 302, 202, 204, 304, 303, 203, 251, 305, 252, 205,
254, 307, 253, 207, 208, 308, 306, 206
*Nset, nset=Root, generate
101, 108, 1
*Nset, nset=Tip, generate
301, 308
*Elset, elset=Both, generate
11, 12, 1
*Solid Section, elset=Both, material=Silicone
*Material, name=SILICONE
*Hyperelastic, neo hooke
0.1, 0.02
*Boundary
Root, 1, 3
*Step, nlgeom
*Static
0.1, 1.0
*Dload
BEAM, P2, 0.001
*Node Print, nset=Tip
U
*End Step
"""


def test_hand_written_deck_reads(tmp_path):
    """Ids from 101 and 11, GENERATE sets, lower-case keywords, comments and element lines split
    anywhere. With 2x2x2 Gauss points and a cross-section one brick wide this mesh has two
    zero-energy modes (the cross-sections at x = 2 and x = 4 distort in their plane), so the tangent
    of this C3D20RH deck is singular; ``test_hand_written_deck_solves`` solves it as C3D20H."""
    (tmp_path / "hand.inp").write_text(HAND_DECK)
    model, params, ids = read_inp(tmp_path / "hand.inp", with_ids=True)
    assert params == {"C10": 0.1, "D1": 0.02, "P": 0.001}
    assert model.n_nodes == 32 and model.mesh.n_elements == 2 and ids.elements.tolist() == [11, 12]
    assert ids.nodes[:3].tolist() == [101, 102, 103]  # file order: the ids are not 1..n
    assert (model.terms[0].formulation, model.terms[0].integration) == ("hybrid", "reduced")
    assert isinstance(model.terms[1], fem.FollowerPressure)
    assert model.mesh.face_sets["DLOAD_P"].tolist() == [[0, 1], [1, 1]]  # face S2 of both bricks
    assert model.clamped_dofs.size == 3 * 8
    tip = model.mesh.node_sets["TIP"]
    assert np.allclose(model.X[tip, 0], 4.0) and tip.size == 8
    p = {k: torch.tensor([v]) for k, v in params.items()}
    K = model.evaluate(torch.zeros(1, model.n_red), p, torch.zeros(1), tangent=True).tangents[0].toarray()
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert np.abs(eig[:2]).max() < 1e-12 * eig[-1] < eig[2]  # exactly two zero-energy modes


def test_hand_written_deck_solves(tmp_path):
    """The same deck with C3D20H (hybrid, full integration): pressure on the top faces (S2) bends
    the cantilever down, by about the Euler-Bernoulli deflection."""
    (tmp_path / "hand.inp").write_text(HAND_DECK.replace("type=C3D20RH", "type=C3D20H"))
    model, params = read_inp(tmp_path / "hand.inp")
    assert (model.terms[0].formulation, model.terms[0].integration) == ("hybrid", "full")
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, (0.5, 1.0))
    assert sol.converged.all(), sol.status
    tip = model.mesh.node_sets["TIP"]
    w = sol.u[0, :, tip, 2].mean(-1)  # mean vertical tip displacement at half and full load
    assert w[1] < w[0] < 0  # pressure on the top face pushes the tip down, more at full load
    # cantilever under q = P b: w = q L^4 / (8 E I), E = 3 mu = 6 C10 (incompressible), I = b h^3 / 12
    beam = 0.001 * 1.0 * 4.0**4 / (8 * 6 * 0.1 / 12)
    assert 0.8 * beam < -float(w[1]) < 1.2 * beam  # measured 0.675 mm against 0.64 mm


VARIANTS = {
    "include, surface, dsload, encastre": [
        ("*NODE, NSET=ALL\n", "*Include, input=nodes.inp\n*NODE, NSET=ALL\n"),
        ("Root, 1, 3", "Root, ENCASTRE"),
        ("*Step, nlgeom", "*Surface, name=Top,\n   type=ELEMENT\nBoth, S2\n*Step, nlgeom"),
        ("*Dload\nBEAM, P2, 0.001", "*Dsload\nTop, P, 0.001"),
    ],
    "clamped rigid body, nset from elset, amplitude": [
        ("*Boundary\nRoot, 1, 3", "*Node\n9001, 0., 0.5, 0.5\n*Rigid body, nset=Root, ref node=9001\n"
                                   "*Boundary\n9001, 1, 6"),
        ("*Nset, nset=Tip, generate\n301, 308", "*Elset, elset=E12\n12\n*Nset, nset=E12, elset=E12\n"
                                                 "*Nset, nset=Tip, generate\n301, 308"),
        ("*Dload\n", "*Amplitude, name=Ramp\n0., 0., 1., 1.\n*Dload, amplitude=Ramp\n"),
    ],
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_hand_written_variants_read_to_the_same_model(tmp_path, variant):
    """Variants of the hand-written deck that describe the same model give the same residual."""
    (tmp_path / "hand.inp").write_text(HAND_DECK)
    reference, params = read_inp(tmp_path / "hand.inp")
    text = HAND_DECK
    for old, new in VARIANTS[variant]:
        assert old in text
        text = text.replace(old, new, 1)
    if "*Include" in text:  # 16 nodes move to an included file; the 8 node lines after *Include go on
        # the included file's *NODE card, since Abaqus inserts the file's lines in place
        lines = text.splitlines()
        first = lines.index("*NODE, NSET=ALL") + 1
        (tmp_path / "nodes.inp").write_text("*NODE, NSET=ALL\n" + "\n".join(lines[first : first + 16]) + "\n")
        text = "\n".join(lines[:first - 1] + lines[first + 16 :]) + "\n"
    (tmp_path / "variant.inp").write_text(text)
    model, variant_params = read_inp(tmp_path / "variant.inp")
    assert variant_params == params and model.n_red == reference.n_red
    assert np.array_equal(model.clamped_dofs, reference.clamped_dofs) and not model.rigid_node_sets
    a = 0.02 * torch.randn(2, model.n_red, generator=torch.Generator().manual_seed(3))
    r0, r1 = residual(reference, params, a, 0.8), residual(model, params, a, 0.8)
    assert float((r1 - r0).abs().max() / r0.abs().max()) < RTOL


def _bad(tmp_path, old, new):
    assert old in HAND_DECK
    (tmp_path / "bad.inp").write_text(HAND_DECK.replace(old, new))
    return tmp_path / "bad.inp"


@pytest.mark.parametrize(
    "old, new, at, message",
    [
        ("*Boundary\n", "*Cload\nTip, 3, -0.1\n*Boundary\n", "*Cload", "*CLOAD: keyword is not supported"),
        ("type=C3D20RH", "type=C3D8", "*Element, type=C3D8, elset=BEAM",
         "*ELEMENT: element type C3D8 is not supported"),
        ("Root, 1, 3", "Base, 1, 3", "Base, 1, 3", "*BOUNDARY: node set BASE is not defined"),
        ("BEAM, P2, 0.001", "BEAM, BX, 0.001", "BEAM, BX, 0.001", "*DLOAD: load label BX is not supported"),
        ("BEAM, P2", "BEEM, P2", "BEEM, P2, 0.001", "*DLOAD: element set BEEM is not defined"),
        ("*Hyperelastic, neo hooke", "*Hyperelastic, ogden", "*Hyperelastic, ogden", "*HYPERELASTIC: option OGDEN"),
        ("*Hyperelastic, neo hooke\n0.1, 0.02", "*Plastic\n1.0, 0.0", "*Plastic", "*PLASTIC: keyword is not supported"),
    ],
    ids=["keyword", "element-type", "node-set", "load-label", "element-set", "hyperelastic-option", "material-option"],
)
def test_bad_decks_name_keyword_and_line(tmp_path, old, new, at, message):
    """Unknown keywords, element types, load labels and material options, and undefined sets, are
    errors naming the file, the line and the keyword."""
    deck = _bad(tmp_path, old, new)
    line = deck.read_text().splitlines().index(at) + 1
    with pytest.raises(InpError, match=re.escape(f"{deck}, line {line}: {message}")):
        read_inp(deck)


def test_amplitudes_and_other_errors(tmp_path):
    """A linear amplitude scales a load to its value at step time 1; a non-linear one, a second step,
    a face loaded twice and undefined materials are errors; InpError is a ValueError."""
    deck = _bad(tmp_path, "*Dload\n", "*Dload, amplitude=Ramp2\n").read_text()
    (tmp_path / "amp.inp").write_text(deck.replace("*Step", "*Amplitude, name=RAMP2\n0., 0., 1., 2., 3., 2.\n*Step"))
    assert read_inp(tmp_path / "amp.inp")[1]["P"] == 0.002
    (tmp_path / "amp.inp").write_text(deck.replace("*Step", "*Amplitude, name=RAMP2\n0., 0., 0.5, 2., 1., 2.\n*Step"))
    with pytest.raises(InpError, match=r"\*AMPLITUDE: does not ramp linearly"):
        read_inp(tmp_path / "amp.inp")
    deck = _bad(tmp_path, "*End Step\n", "*End Step\n*Step, nlgeom\n*Static\n*End Step\n")
    second = deck.read_text().splitlines().index("*Step, nlgeom", 60) + 1
    with pytest.raises(ValueError, match=rf"line {second}: \*STEP: a second step"):
        read_inp(deck)
    with pytest.raises(InpError, match=r"face S2 of element 11 is loaded again"):
        read_inp(_bad(tmp_path, "BEAM, P2, 0.001\n", "BEAM, P2, 0.001\n11, P2, 0.002\n"))
    with pytest.raises(InpError, match=r"material SILICONE is not defined"):
        read_inp(_bad(tmp_path, "name=SILICONE", "name=RUBBER"))
    with pytest.raises(InpError, match=r"element 12 refers to node 399, which is not defined"):
        read_inp(_bad(tmp_path, "254, 307,", "254, 399,"))


def test_support_springs_are_rejected(tmp_path):
    """write_inp writes ElasticSupport as SPRING1/SPRING2 elements, which have no torchfra term."""
    mesh = box_mesh((2.0, 2.0, 4.0), (1, 1, 2))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean(), "displacement"))
    model.add(fem.ElasticSupport(mesh, "zmin"))
    deck = write_inp(tmp_path / "springs.inp", model, {"C10": 0.1, "D1": 0.5, "c_n": 1.0, "c_t": 2.0})
    line = next(k + 1 for k, ln in enumerate(deck.read_text().splitlines()) if "TYPE=SPRING" in ln)
    with pytest.raises(InpError, match=rf"line {line}: \*ELEMENT: element type SPRING[12] is not supported"):
        read_inp(deck)


def test_the_actuator_deck_round_trips(tmp_path):
    """The paper's actuator (resolution 1: hybrid full-integration bricks, embedded 3-node fiber
    helices tied by *EQUATION, closed-cavity pressure, clamped base, rigid top) written by write_inp
    and read back: same parameters and the same residual at a random state (measured 3e-16)."""
    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model

    model, _ = build_actuator_model(ActuatorGeometry(resolution=1))
    params = {"C10": 0.0048, "D1": 1 / (1000 * 0.0048), "E_fiber": 31000.0, "P": 0.022}
    assert_round_trip(model, params, tmp_path, "actuator", element_type="C3D20H")
