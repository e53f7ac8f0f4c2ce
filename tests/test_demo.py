"""The FEM demo script end to end on a tiny ensemble, and the exporters it relies on."""
from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
import torch
from helpers import load_script

from torchfra import fem
from torchfra.fem.structured import box_mesh
from torchfra.io.vtu import element_fields, write_vtu
from torchfra.report.tensorboard import boundary_triangles


def _load_demo():
    return load_script("fem_demo")


def test_demo_writes_a_sane_run(tmp_path):
    demo = _load_demo()
    # 8 bricks, 2 members, a tenth of the default pressure: a few seconds, same code path.
    summary = demo.main([
        "--name", "tiny", "--runs-dir", str(tmp_path), "--members", "2", "--divisions", "2,2,2",
        "--pressure", "2e-5", "--load-steps", "2", "--threads", "1",
    ])
    run = tmp_path / "tiny"
    assert json.loads((run / "summary.json").read_text()) == json.loads(json.dumps(summary))
    for key in ("members", "members_converged", "elements", "dofs", "load_steps", "newton_iterations_total",
                "wall_s", "threads", "tip_displacement_mean_mm", "member_results"):
        assert key in summary, key
    assert summary["members"] == 2 and len(summary["member_results"]) == 2
    assert summary["members_converged"] == 2, summary["member_results"]
    assert summary["elements"] == 8 and summary["load_steps"] == 2 and summary["threads"] == 1
    assert summary["newton_iterations_total"] > 0 and summary["wall_s"] > 0
    for member in summary["member_results"]:
        ux, uy, uz = member["tip_displacement_mm"]
        # pressure on y = 0 bends the block towards +y, shortens it along z, nothing happens along x
        assert uy > 0.1 and uz < 0 and abs(ux) < 1e-8 * uy
        assert member["tip_uy_path_mm"][0] < member["tip_uy_path_mm"][1]

    mesh = box_mesh((16.0, 16.0, 60.0), (2, 2, 2))
    vtu = meshio.read(run / "deformed.vtu")
    assert vtu.points.shape == (mesh.n_nodes, 3)
    assert vtu.cells[0].type == "hexahedron20" and np.array_equal(vtu.cells[0].data, mesh.elements)
    U = vtu.point_data["U"]
    rep = summary["member_results"][summary["vtu_member"]]
    np.testing.assert_allclose(U[mesh.node_set("zmax")].mean(0), rep["tip_displacement_mm"], rtol=1e-10)
    np.testing.assert_allclose(vtu.cell_data["EVOL_RATIO"][0], 1.0, atol=5e-3)  # K / mu = 1000
    assert vtu.cell_data["S"][0].shape == (8, 6) and np.all(vtu.cell_data["MISES"][0] >= 0)

    assert (run / "tip_displacement.png").stat().st_size > 0
    events = list(run.glob("events.out.tfevents.*"))
    assert events and all(e.stat().st_size > 0 for e in events)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run)).Reload()
    tags = acc.Tags()["scalars"]
    assert {"newton/iterations", "newton/members_converged", "newton/residual/member_0"} <= set(tags)
    assert [e.value for e in acc.Scalars("newton/members_converged")] == [2.0]


def test_element_fields_of_an_isochoric_stretch():
    """Homogeneous u = (F - I) X with F = diag(l^-1/2, l^-1/2, l): J = 1, so the condensed pressure
    is 0 and Neo-Hookean gives sigma = 2 C10 dev(b); Mises = 2 C10 (l^2 - 1/l) (closed form)."""
    mesh = box_mesh((2.0, 3.0, 4.0), (1, 1, 2), distortion=0.2)
    solid = fem.Hex20Solid(mesh, fem.NeoHookean())
    stretch, C10 = 1.3, torch.tensor([0.0056, 0.01])
    F = torch.diag(torch.tensor([stretch**-0.5, stretch**-0.5, stretch]))
    X = torch.as_tensor(mesh.nodes)
    u = ((X @ (F - torch.eye(3)).T)[None]).expand(2, -1, -1)
    out = element_fields(solid, u, {"C10": C10, "D1": torch.tensor([1e-3, 1e-3])})
    mises = 2 * C10 * (stretch**2 - 1 / stretch)
    torch.testing.assert_close(out["MISES"], mises[:, None].expand(2, mesh.n_elements), rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(out["PRESS"], torch.zeros(2, mesh.n_elements), rtol=0, atol=1e-12)
    torch.testing.assert_close(out["EVOL_RATIO"], torch.ones(2, mesh.n_elements), rtol=1e-12, atol=0)
    s_zz = 2 * C10 * (stretch**2 - (stretch**2 + 2 / stretch) / 3)
    torch.testing.assert_close(out["S"][..., 2, 2], s_zz[:, None].expand(2, mesh.n_elements), rtol=1e-10, atol=1e-14)


def test_boundary_triangles_close_the_box_outwards():
    mesh = box_mesh((16.0, 16.0, 60.0), (2, 2, 3))
    tri = mesh.nodes[boundary_triangles(mesh)]  # (F, 3, 3)
    # divergence theorem: sum over outward triangles of x . n dA / 3 is the enclosed volume
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    volume = np.einsum("fi,fi->", tri.mean(axis=1), cross) / 6.0
    assert volume == pytest.approx(16.0 * 16.0 * 60.0, rel=1e-12)
    n_outer_faces = 2 * (2 * 2 + 2 * 3 + 2 * 3)
    assert tri.shape[0] == 6 * n_outer_faces


def test_write_vtu_rejects_a_wrong_field(tmp_path):
    mesh = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    with pytest.raises(ValueError, match="one row per point"):
        write_vtu(tmp_path / "bad.vtu", mesh, point_data={"T": np.zeros(3)})
    path = write_vtu(tmp_path / "ok.vtu", mesh, u=np.zeros((mesh.n_nodes, 3)), cell_data={"S": np.zeros((1, 3, 3))})
    assert meshio.read(path).cell_data["S"][0].shape == (1, 6)


def test_write_vtu_of_a_model_adds_its_trusses_as_line3(tmp_path):
    mesh = box_mesh((1.0, 1.0, 2.0), (1, 1, 2))
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    fiber = model.add_nodes([[0.5, 0.5, 0.2], [0.5, 0.5, 1.8], [0.5, 0.5, 1.0]])
    model.add(fem.Truss(model.X, fiber[None], area=0.01))
    path = write_vtu(tmp_path / "m.vtu", model, u=np.zeros((model.n_nodes, 3)), cell_data={"MISES": np.ones(2)})
    back = meshio.read(path)
    assert [c.type for c in back.cells] == ["hexahedron20", "line3"]
    assert back.points.shape == (mesh.n_nodes + 3, 3) and np.array_equal(back.cells[1].data, fiber[None])
    assert np.all(back.cell_data["MISES"][0] == 1) and np.isnan(back.cell_data["MISES"][1]).all()
