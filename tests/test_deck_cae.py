"""Decks in the layout Abaqus/CAE writes (parts, an assembly of placed instances, instance-qualified
names) read to the same model as the same deck written flat: the same mesh once the instance's
translation and rotation are applied to the flat deck's coordinates, the same constraints and loads,
and the same forward solution. Reference: the flat deck, whose coordinates the test places itself
(a closed-form 90 degree rotation; scipy's Rotation for a general axis)."""
import re
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchfra import fem
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus.read import InpError, InpNote, read_inp

MESH = box_mesh((2.0, 1.0, 4.0), (2, 1, 4))  # the 2x1x4 C3D20H block
PARAMS = {"C10": 0.05, "D1": 0.02, "P": 0.004}


def _nodes(X, first=1):
    return "".join(f"{first + i}, {float(x)!r}, {float(y)!r}, {float(z)!r}\n" for i, (x, y, z) in enumerate(X))


def _elements(conn, node_first=1, first=1):
    out = ""
    for e, row in enumerate(conn):
        ids = [str(n + node_first) for n in row]
        out += f"{first + e}, " + ", ".join(ids[:15]) + ",\n" + ", ".join(ids[15:]) + "\n"
    return out


def _ids(values, first=1):
    values = [str(int(v) + first) for v in values]
    return "".join(", ".join(values[i:i + 16]) + "\n" for i in range(0, len(values), 16))


BASE = np.flatnonzero(np.isclose(MESH.nodes[:, 2], 0.0))
FACES = MESH.face_sets["ymin"]  # (element, face 0-based) of the y = 0 side
LABEL = f"S{int(FACES[0, 1]) + 1}"
assert np.all(FACES[:, 1] == FACES[0, 1])

MATERIAL = "*Material, name=Rubber\n*Hyperelastic, neo hooke\n0.05, 0.02\n"
STEP = "*Step, name=Step-1, nlgeom=YES\n*Static\n0.1, 1., 1e-05, 0.1\n"


def flat_deck(blocks):
    """The blocks (coordinates (n, 3) each) written flat: ids of block k follow those of block k - 1."""
    n, E = MESH.n_nodes, MESH.n_elements
    text = "*Heading\nflat\n*Node\n" + "".join(_nodes(X, 1 + k * n) for k, X in enumerate(blocks))
    text += "*Element, type=C3D20H, elset=All\n" + "".join(_elements(MESH.elements, 1 + k * n, 1 + k * E)
                                                            for k in range(len(blocks)))
    text += "*Nset, nset=Fixed\n" + "".join(_ids(BASE + k * n) for k in range(len(blocks)))
    text += "*Elset, elset=Loaded\n" + "".join(_ids(FACES[:, 0] + k * E) for k in range(len(blocks)))
    text += f"*Surface, type=ELEMENT, name=Load\nLoaded, {LABEL}\n*Solid Section, elset=All, material=Rubber\n,\n"
    text += MATERIAL + STEP + "*Boundary\nFixed, ENCASTRE\n*Dsload\nLoad, P, 0.004\n*End Step\n"
    return text


def cae_deck(placements, orientation=False):
    """The block as one part, instanced once per placement (a list of data lines, possibly empty);
    the base is clamped through the part's qualified node set, the load on an assembly surface."""
    part = ("*Part, name=Block\n*Node\n" + _nodes(MESH.nodes) + "*Element, type=C3D20H\n" + _elements(MESH.elements)
            + "*Nset, nset=Base\n" + _ids(BASE) + "*Elset, elset=Set-1, generate\n"
            + f"1, {MESH.n_elements}, 1\n")
    if orientation:
        part += "*Orientation, name=Ori-1\n1., 0., 0., 0., 1., 0.\n3, 0.\n"
    part += f"** Section: Section-1\n*Solid Section, elset=Set-1, {'orientation=Ori-1, ' if orientation else ''}" \
            "material=Rubber\n,\n*End Part\n"
    text = "*Heading\n** Job name: block Model name: Model-1\n*Preprint, echo=NO, model=NO, history=NO\n** PARTS\n"
    text += part + "** ASSEMBLY\n*Assembly, name=Assembly\n"
    names = [f"Block-{k + 1}" for k in range(len(placements))]
    for name, lines in zip(names, placements):
        text += f"*Instance, name={name}, part=Block\n" + "".join(line + "\n" for line in lines) + "*End Instance\n"
    for name in names:
        text += f"*Elset, elset=_Load_{LABEL}, internal, instance={name}\n" + _ids(FACES[:, 0])
    text += f"*Surface, type=ELEMENT, name=Load\n_Load_{LABEL}, {LABEL}\n*End Assembly\n" + MATERIAL + STEP
    text += "*Boundary\n" + "".join(f"{name}.Base, ENCASTRE\n" for name in names)
    text += "*Dsload\nLoad, P, 0.004\n*Output, field, variable=PRESELECT\n*End Step\n"
    return text


def _solve(model, params):
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, (0.5, 1.0))
    assert sol.converged.all(), sol.status
    return sol.u[0]


def _same_model(tmp_path, flat_text, cae_text, solve=True):
    (tmp_path / "flat.inp").write_text(flat_text)
    (tmp_path / "cae.inp").write_text(cae_text)
    flat, flat_params = read_inp(tmp_path / "flat.inp")
    cae, cae_params, ids = read_inp(tmp_path / "cae.inp", with_ids=True)
    assert cae_params == flat_params == PARAMS
    assert np.allclose(cae.X, flat.X, rtol=0, atol=1e-12)
    assert np.array_equal(cae.mesh.elements, flat.mesh.elements)
    assert np.array_equal(cae.clamped_dofs, flat.clamped_dofs)
    assert cae.mesh.face_sets["LOAD"].tolist() == flat.mesh.face_sets["LOAD"].tolist()
    if solve:
        u_flat, u_cae = _solve(flat, flat_params), _solve(cae, cae_params)
        assert float(u_flat.abs().max()) > 1e-3  # the load moves the block
        assert torch.allclose(u_cae, u_flat, rtol=0, atol=1e-10 * float(u_flat.abs().max()))
    return cae, ids


def test_a_translated_and_rotated_instance_is_the_flat_deck_placed_alike(tmp_path):
    """Translation (10, -3, 2) first, then 90 degrees about the vertical axis through (1, 2, 0):
    x -> a + Rz (x + t - a), Rz = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]."""
    t, a = np.array([10.0, -3.0, 2.0]), np.array([1.0, 2.0, 0.0])
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    placed = a + (MESH.nodes + t - a) @ Rz.T
    cae, ids = _same_model(tmp_path, flat_deck([placed]), cae_deck([["10., -3., 2.", "1., 2., 0., 1., 2., 5., 90."]]))
    assert ids.nodes.tolist() == list(range(1, MESH.n_nodes + 1))  # one instance keeps the part's ids
    assert "BLOCK-1.BASE" in cae.mesh.node_sets


def test_a_rotation_about_a_general_axis_matches_scipy(tmp_path):
    a, b, angle = np.array([0.5, -1.0, 2.0]), np.array([1.5, 0.0, 3.0]), 30.0
    R = Rotation.from_rotvec(np.radians(angle) * (b - a) / np.linalg.norm(b - a)).as_matrix()
    placed = a + (MESH.nodes - a) @ R.T
    line = ", ".join(f"{float(v)!r}" for v in [*a, *b, angle])
    _same_model(tmp_path, flat_deck([placed]), cae_deck([["0., 0., 0.", line]]), solve=False)


def test_two_instances_of_one_part_are_two_bodies_with_shifted_ids(tmp_path):
    """The second instance's ids follow the first's (node id + n, element id + E), as the flat deck writes them."""
    second = MESH.nodes + np.array([5.0, 0.0, 0.0])
    cae, ids = _same_model(tmp_path, flat_deck([MESH.nodes, second]), cae_deck([[], ["5., 0., 0."]]))
    assert cae.mesh.n_elements == 2 * MESH.n_elements and ids.elements[-1] == 2 * MESH.n_elements


def test_an_orientation_on_an_isotropic_material_is_accepted_with_a_note(tmp_path):
    (tmp_path / "cae.inp").write_text(cae_deck([[]], orientation=True))
    (tmp_path / "flat.inp").write_text(flat_deck([MESH.nodes]))
    with pytest.warns(InpNote, match="ORIENTATION=ORI-1 has no effect: material RUBBER is isotropic"):
        cae, params = read_inp(tmp_path / "cae.inp")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the flat deck has no orientation: no note
        flat, _ = read_inp(tmp_path / "flat.inp")
    p = {k: torch.tensor([v]) for k, v in params.items()}
    a = 0.01 * torch.randn(1, cae.n_red, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    r0 = flat.evaluate(a, p, torch.ones(1)).residual
    assert torch.allclose(cae.evaluate(a, p, torch.ones(1)).residual, r0, rtol=0, atol=1e-12 * float(r0.abs().max()))


def _line(text, start):
    return next(k + 1 for k, ln in enumerate(text.splitlines()) if ln.startswith(start))


@pytest.mark.parametrize("edit, at, message", [
    (lambda t: t.replace("*Static\n", "*Static\n*Density\n1e-9\n", 1), "*Density",
     "*DENSITY: is a material option outside a *MATERIAL block (the block of material RUBBER ended at line {m}"),
    (lambda t: t.replace("*Boundary\n", "*Boundary\nBlock-1.Base, ENCASTRE\n*Density\n1e-9\n", 1), "*Density",
     "*DENSITY: is a material option outside a *MATERIAL block"),
    (lambda t: t.replace("*End Part", "*Boundary\nBase, ENCASTRE\n*End Part"), "*Boundary",
     "*BOUNDARY: is not supported inside *PART BLOCK"),
    (lambda t: t.replace("part=Block", "part=Brick"), "*Instance", "*INSTANCE: part BRICK is not defined"),
    (lambda t: t.replace("instance=Block-1", "instance=Block-9"), "*Elset, elset=_Load",
     "*ELSET: instance BLOCK-9 is not defined"),
    (lambda t: t.replace("Block-1.Base, ENCASTRE", "Block-1.Top, ENCASTRE"), "Block-1.Top",
     "*BOUNDARY: node set BLOCK-1.TOP is not defined"),
    (lambda t: t.replace("*End Instance\n", "*End Instance\n*End Instance\n"), "*End Instance\n*End Instance",
     "*END INSTANCE: *END INSTANCE without an *INSTANCE"),
], ids=["density-in-step", "density-after-boundary", "boundary-in-part", "no-part", "no-instance", "no-set",
        "end-instance"])
def test_bad_cae_decks_name_the_line(tmp_path, edit, at, message):
    text = edit(cae_deck([["1., 0., 0."]]))
    (tmp_path / "bad.inp").write_text(text)
    lines = text.splitlines()
    if at == "*End Instance\n*End Instance":
        line = next(k + 2 for k in range(len(lines) - 1) if lines[k] == lines[k + 1] == "*End Instance")
    else:
        line = _line(text, at)
    message = message.format(m=_line(text, "*Step"))
    with pytest.raises(InpError, match=re.escape(f"{tmp_path / 'bad.inp'}, line {line}: {message}")):
        read_inp(tmp_path / "bad.inp")


def test_an_unclosed_part_and_parts_without_an_assembly_are_named(tmp_path):
    text = cae_deck([[]])
    (tmp_path / "a.inp").write_text(text.split("*End Part")[0])
    with pytest.raises(InpError, match="a.inp: \\*PART BLOCK is never closed with \\*END PART"):
        read_inp(tmp_path / "a.inp")
    (tmp_path / "b.inp").write_text(text.split("** ASSEMBLY")[0] + MATERIAL)
    with pytest.raises(InpError, match="b.inp: the deck defines parts \\(BLOCK\\) but no \\*ASSEMBLY"):
        read_inp(tmp_path / "b.inp")


TOP = np.flatnonzero(np.isclose(MESH.nodes[:, 2], 4.0))


def test_an_assembly_reference_point_is_numbered_after_the_instances(tmp_path):
    """A rigid body CAE writes at assembly level: its reference point is assembly node 1 (a set
    ``RP-1``), tied to the instance's top; fixed in all six dofs it clamps the top, as the flat deck
    with the reference node numbered after the block's does."""
    n = MESH.n_nodes
    rigid_flat = (f"*Node\n{n + 1}, 1., 0.5, 4.\n*Nset, nset=Top\n" + _ids(TOP)
                  + f"*Rigid Body, ref node={n + 1}, tie nset=Top\n")
    flat = flat_deck([MESH.nodes]).replace("*Material", rigid_flat + "*Material", 1)
    flat = flat.replace("Fixed, ENCASTRE\n", f"Fixed, ENCASTRE\n{n + 1}, ENCASTRE\n")
    rigid_cae = ("*Node\n1, 1., 0.5, 4.\n*Nset, nset=RP-1, internal\n1,\n*Nset, nset=_T, internal, instance=Block-1\n"
                 + _ids(TOP) + "*Rigid Body, ref node=RP-1, tie nset=_T\n")
    cae = cae_deck([[]]).replace("*End Assembly", rigid_cae + "*End Assembly")
    cae = cae.replace("Block-1.Base, ENCASTRE\n", "Block-1.Base, ENCASTRE\nRP-1, ENCASTRE\n")
    model, ids = _same_model(tmp_path, flat, cae, solve=False)
    assert model.clamped_dofs.size == 3 * (BASE.size + TOP.size) and model.n_nodes == n  # the point is no model node
