"""A second actuator, from a deck written as an Abaqus user writes one (``tests/channel_deck.py``: a
fiber-reinforced bending actuator with a square channel, C3D20H bricks, embedded T3D2 fibers, a
rigid top, pressure on a ``*SURFACE``), read, solved, run as a forward ensemble and calibrated
through the scripts with ``--inp``.

References: the symmetry of the body without its fibers (no bending, to round-off), the
strain-limiting layer's kinematics (the fibers stretch far less than the opposite face), a direct
solve of the deck for every ensemble member, and the exact grid posterior of the calibration
(quadrature, verified on closed forms in ``test_assimilation.py``) around the deck's own C10."""
import json

import numpy as np
import pytest
import torch
from channel_deck import channel_deck
from helpers import load_script

from torchfra import fem
from torchfra.io.abaqus.read import read_inp

forward_uq = load_script("forward_uq")
make_recording = load_script("make_recording")
calibrate = load_script("calibrate")

PRIOR = "C10=lognormal:0.05,0.012"


@pytest.fixture(scope="module")
def deck(tmp_path_factory):
    path = tmp_path_factory.mktemp("deck") / "channel.inp"
    path.write_text(channel_deck())
    return path


def solve_deck(path, **overrides):
    model, values = read_inp(path)
    params = {k: torch.tensor([overrides.get(k, v)], dtype=torch.float64) for k, v in values.items()}
    return model, values, fem.solve(model, params, (0.5, 1.0))


def test_the_channel_deck_reads_and_bends_towards_its_fibers(deck):
    model, values, sol = solve_deck(deck)
    assert values == {"C10": 0.05, "D1": 0.02, "E_fiber": 31000.0, "P": 0.04}
    assert model.mesh.n_elements == 41 and sol.converged.all(), sol.status
    X = np.asarray(model.X)
    top = model.mesh.node_sets["TOP"]
    u = sol.u[0, -1].numpy()
    # the rigid top: every top node moves with one rigid motion (distances kept to round-off)
    x_top = X[top] + u[top]
    d0 = np.linalg.norm(X[top][:, None] - X[top][None], axis=-1)
    d1 = np.linalg.norm(x_top[:, None] - x_top[None], axis=-1)
    assert np.abs(d1 - d0).max() < 1e-8
    # the channel pressure lengthens the free (+y) side; the fibers on the -y side hold theirs:
    # the top tilts towards -y, and the actuator bends that way
    y_side = top[np.isclose(X[top, 1], 12.0)]
    fiber_side = top[np.isclose(X[top, 1], 0.0)]
    assert u[y_side, 2].mean() > 0.2 and abs(u[fiber_side, 2].mean()) < 0.3 * u[y_side, 2].mean()
    assert u[top, 1].mean() < -0.5
    fibers = np.arange(model.mesh.n_nodes, model.n_nodes)  # appended nodes: fiber nodes (and T3D2 middles)
    z = X[fibers, 2]
    ends = fibers[np.isclose(z, 30.0)]
    assert np.abs(u[ends, 2]).max() < 0.05 * u[y_side, 2].mean()  # the fibers barely stretch


def test_without_fibers_the_symmetric_body_does_not_bend(deck):
    """The body is symmetric about y = 6 mm without its fibers: the channel pressure only lengthens
    it; the top's mean y displacement is zero to round-off, against millimetres with the fibers."""
    model, values, sol = solve_deck(deck, E_fiber=1e-9)
    assert sol.converged.all()
    top = model.mesh.node_sets["TOP"]
    u = sol.u[0, -1].numpy()
    assert u[top, 2].mean() > 0.05
    assert abs(u[top, 1].mean()) < 1e-8 * u[top, 2].mean()


def test_forward_ensemble_and_calibration_of_the_channel_deck(deck, tmp_path):
    """forward_uq --inp: every member equals a direct solve of the deck at its C10 (round-off
    through the reduced basis' check tolerance); make_recording --inp, then calibrate --inp: the
    exact posterior holds the deck's C10 (its recording's truth) within 4 stds, the nonlinear
    hierarchical filter lies within 3 exact stds of it and the restart filter's ensemble covers it."""
    out = forward_uq.main(["--inp", str(deck), "--camera", "+x", "--param", PRIOR, "--members", "8",
                           "--load-steps", "4", "--frames", "8", "--out", "ens", "--runs-dir", str(tmp_path),
                           "--quiet"])
    assert out["members_converged"] == 8
    with np.load(tmp_path / "ens" / "forward.npz", allow_pickle=False) as f:
        c10, Y, points = f["params"][:, list(f["param_names"]).index("C10")], f["Y"], f["points"]
    assert np.allclose(points[:, 0], 12.0)  # the face the +x camera sees
    model, values = read_inp(deck)
    ids = np.array([int(np.argmin(np.linalg.norm(np.asarray(model.X)[: model.mesh.n_nodes] - x, axis=1)))
                    for x in points])
    for m in range(8):
        sol = fem.solve(model, {k: torch.tensor([c10[m] if k == "C10" else v], dtype=torch.float64)
                                for k, v in values.items()}, (1.0,))
        assert sol.converged.all()
        # reduced-basis members agree with full Newton to the check tolerance (5e-4 mm, fem.reduced)
        assert np.abs(Y[m, -1] - sol.u[0, -1, ids, 1:].numpy()).max() < 5e-4, m
    assert (Y[:, -1, :, 0].mean(axis=1) < 0).all()  # every member bends towards its fibers (-y)
    rec = tmp_path / "rec.csv"
    make_recording.main(["--inp", str(deck), "--camera", "+x", "--noise", "0.02", "--seed", "5", "--frames", "10",
                         "--out", str(rec)])
    summary = calibrate.main(["--inp", str(deck), "--camera", "+x", "--param", PRIOR, "--recording", str(rec),
                              "--noise", "0.02", "--members", "16", "--coverage-seeds", "0", "--workers", "1",
                              "--name", "cal", "--runs-dir", str(tmp_path / "runs")])
    exact = summary["filters"]["exact"]["C10"]
    assert abs(exact["mean"] - 0.05) < 4 * exact["std"], exact
    nonlinear = summary["filters"]["hierarchical_nonlinear"]["C10"]
    assert abs(nonlinear["mean"] - exact["mean"]) < 3 * exact["std"], nonlinear
    # the restart filter assimilates one frame here (every 10th) with 16 members: its ensemble, not
    # the exact std, is the yardstick of its sampling error
    restart = summary["filters"]["restart"]["C10"]
    assert abs(restart["mean"] - exact["mean"]) < 2 * restart["std"] < 0.02, restart
    saved = json.loads((tmp_path / "runs" / "cal" / "summary.json").read_text())
    assert saved["config"]["inp"] == str(deck)
