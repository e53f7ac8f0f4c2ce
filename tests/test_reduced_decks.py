"""Reduced-order ensembles of decks that are not the actuator, against full Newton of every member.

Reference: ``fem.solve`` (full Newton) of the same members of the same deck. Each deck is written as
an Abaqus/CalculiX file and read back (``read_inp``), as ``torchfra forward --inp`` reads it. A
reduced member is accepted by ``solve_ensemble`` only when its full-residual check (one full Newton
step from the reduced answer, ``error_estimate``) is within ``tol`` mm; the tests ask that the true
error against full Newton is within that same ``tol``. The shapes are picked so that a face set's
or an element set's size equals a length of the terms' shared arrays (8 faces: the 8 nodes of a
Quad8 face; 3 faces: the 3 axes of the Levi-Civita symbol), which restricting a term to sampled
blocks must not confuse with its blocks.
"""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchfra import fem
from torchfra.fem.embedding import embedding_weights
from torchfra.fem.reduced import solve_ensemble
from torchfra.fem.structured import box_mesh
from torchfra.io.abaqus.read import read_inp
from torchfra.io.abaqus.write import write_inp

pytestmark = pytest.mark.slow  # minutes of FE work each: python -m pytest -m slow runs them

LOADS = [0.25, 0.5, 0.75, 1.0]
TOL = 1e-4  # mm: the reduced-basis check's tolerance (solve_ensemble tol), on displacements of ~1-15 mm


def block_deck(path, size, cells, fiber=False, pressure=0.004):
    """A clamped C3D20H block (size mm, cells bricks) with a follower pressure (``*DLOAD P3``) on its
    y = 0 faces; ``fiber``: a straight fiber along z at the block's centre line, embedded, written as
    T3D2 trusses. Returns the deck's path."""
    mesh = box_mesh(size, cells)
    model = fem.Model(mesh)
    model.add(fem.Hex20Solid(mesh, fem.NeoHookean()))
    params = {"C10": 0.05, "D1": 0.02, "P": pressure}
    if fiber:
        n = 2 * cells[2] + 1
        X = np.column_stack([np.full(n, size[0] / 2), np.full(n, 0.25 * size[1]),
                             np.linspace(0.0, 0.9 * size[2], n)])
        nodes = model.add_nodes(X)
        model.add(fem.Truss(model.X, np.stack([nodes[0:-1:2], nodes[2::2], nodes[1::2]], axis=1), area=0.05))
        for node, (hosts, w) in zip(nodes, embedding_weights(mesh, X)):
            model.embed(int(node), hosts, w)
        params["E_fiber"] = 50.0
    model.add(fem.FollowerPressure(mesh, "ymin", pressure="P"))
    model.clamp("zmin")
    return write_inp(path, model, params, element_type="C3D20H", truss_element="T3D2")


def members(params, n=8, seed=0):
    """n members: the deck's values, C10 lognormal about it (5 % median, 20 % spread)."""
    g = torch.Generator().manual_seed(seed)
    out = {k: torch.full((n,), float(v), dtype=torch.float64) for k, v in params.items()}
    out["C10"] = out["C10"] * torch.exp(0.2 * torch.randn(n, generator=g, dtype=torch.float64))
    return out


# The fibered block at 0.001 MPa bends 5.6 mm; at 0.004 MPa (15 mm on its 16 mm) the reduced Newton, which takes
# no cutbacks, fails from the unloaded state and every member is solved in full instead (correct, not reduced).
@pytest.mark.parametrize("size, cells, fiber, pressure, faces", [
    ((8.0, 4.0, 16.0), (2, 1, 4), False, 0.004, 8),  # 8 follower faces: as many as a face's nodes
    ((4.0, 4.0, 12.0), (1, 1, 3), False, 0.004, 3),  # 3 follower faces, 3 bricks
    ((4.0, 4.0, 16.0), (1, 1, 4), True, 0.001, 4),  # an embedded T3D2 fiber, 4 bricks
])
def test_reduced_members_of_a_deck_match_full_newton(tmp_path, size, cells, fiber, pressure, faces):
    model, params = read_inp(block_deck(tmp_path / "block.inp", size, cells, fiber, pressure))
    assert model.terms[-1].dofs.shape[0] == faces  # the follower pressure's faces
    if fiber:
        assert isinstance(model.terms[1], fem.Truss) and model.terms[1].conn.shape[0] == 2 * cells[2]
    prm = members(params)
    ref = fem.solve(model, prm, LOADS)
    assert ref.converged.all()
    es = solve_ensemble(model, prm, LOADS, tol=TOL, xtol=1e-6, polish_tol=1e-7)
    reduced = np.flatnonzero(es.method == "reduced")
    assert reduced.size >= 3 and (es.status == "converged").all()
    scale = float(ref.u.abs().max())
    assert scale > 1.0  # a large deformation: the pressure bends the block by millimetres
    err = (es.u[reduced] - ref.u[reduced]).abs().amax(dim=(1, 2, 3)).numpy()
    assert err.max() <= TOL, err  # within the full-residual check's tolerance
    assert np.all(es.error_estimate[reduced] <= TOL)


def test_forward_of_a_block_deck_runs_on_the_reduced_basis(tmp_path):
    """The documented deck command on the 8-face block, as a process: the ensemble goes onto its
    reduced basis (3 of 8 members) and every member converges."""
    deck = block_deck(tmp_path / "block.inp", (8.0, 4.0, 16.0), (2, 1, 4))
    cmd = [sys.executable, "-m", "torchfra", "forward", "--inp", str(deck), "--param", "C10=lognormal:0.05,0.01",
           "--members", "8", "--method", "reduced", "--runs-dir", str(tmp_path / "runs"), "--out", "blk", "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
    summary = json.loads((tmp_path / "runs" / "blk" / "summary.json").read_text())
    assert summary["members_converged"] == 8 and summary["members_reduced"] >= 3
