"""The user's own model (``--inp DECK``) through the scripts: forward ensemble, synthetic recording,
calibration. The deck is the hand-written two-brick cantilever of ``test_read_inp.py`` (C3D20H,
clamped at x = 0, pressure on its top faces), seen by a camera on +x: the tip face x = 4 mm, 8 nodes.
Reference for the calibration: the exact grid posterior of the same run (quadrature, verified on
closed forms in ``test_assimilation.py``); the truth is the deck's own C10."""
import json

import numpy as np
import pytest
import torch
from helpers import load_script
from test_read_inp import HAND_DECK

from torchfra.actuator.deck import observed_faces, read_deck
from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.forward import run_forward, with_deck
from torchfra.io.abaqus.read import read_inp

forward_uq = load_script("forward_uq")
make_recording = load_script("make_recording")
calibrate = load_script("calibrate")

PRIOR = "C10=lognormal:0.1,0.03"


@pytest.fixture
def deck(tmp_path):
    path = tmp_path / "cantilever.inp"
    path.write_text(HAND_DECK.replace("type=C3D20RH", "type=C3D20H"))
    return path


def test_forward_ensemble_of_a_deck_solves_every_member_like_the_deck_itself(deck, tmp_path):
    """Every member of the ensemble equals a direct solve of the deck read by ``read_inp`` at that
    member's C10 (its other values, D1 and P, the deck's), observed at the tip face's 8 nodes; a
    rerun reuses every member."""
    out = forward_uq.main(["--inp", str(deck), "--param", PRIOR, "--members", "6", "--load-steps", "4",
                           "--frames", "8", "--runs-dir", str(tmp_path / "runs"), "--out", "f", "--quiet"])
    assert out["members_converged"] == 6 and out["elements"] == 2 and out["observation_points"] == 8
    assert out["config"]["pressure"] == 0.001 and out["config"]["inp_digest"]
    with np.load(tmp_path / "runs" / "f" / "forward.npz", allow_pickle=False) as f:
        Y, params, points = f["Y"], f["params"], f["points"]
    assert np.allclose(points[:, 0], 4.0)  # the face the +x camera sees: the tip
    model, values = read_inp(deck)
    from torchfra import fem

    for m in (0, 5):
        p = {**{k: torch.tensor([v]) for k, v in values.items()}, "C10": torch.tensor([params[m, 0]])}
        sol = fem.solve(model, p, (1.0,))
        tip = sol.u[0, -1, :, 1:]  # (nodes, 2): uy, uz at full load
        ids = np.array([int(np.argmin(np.linalg.norm(model.X[: model.n_nodes] - x, axis=1))) for x in points])
        # the reduced-basis member agrees with full Newton to its check tolerance (5e-4 mm, fem.reduced)
        assert np.abs(Y[m, -1] - tip[ids].numpy()).max() < 5e-4
    assert (Y[:, -1, :, 1] < 0).all()  # pressure on the top faces bends the tip down, every member
    again = forward_uq.main(["--inp", str(deck), "--param", PRIOR, "--members", "6", "--load-steps", "4",
                             "--frames", "8", "--runs-dir", str(tmp_path / "runs"), "--out", "f", "--quiet"])
    assert again["newton_iterations_total"] == out["newton_iterations_total"]


def test_a_changed_deck_is_another_run_and_bad_deck_settings_are_named(deck, tmp_path):
    cfg = ForwardConfig(members=5, load_steps=2, frames=4, inp=str(deck), parameters=[PRIOR])
    run_forward(cfg, tmp_path / "f", progress=False)
    deck.write_text(deck.read_text().replace("0.1, 0.02", "0.1, 0.03"))  # another D1 in the deck
    with pytest.raises(ValueError, match="other settings \\(inp_digest\\)"):
        run_forward(cfg, tmp_path / "f", progress=False)
    with pytest.raises(ValueError, match="has no parameter delta_y \\(its parameters: C10, D1, P\\)"):
        with_deck(ForwardConfig(inp=str(deck), parameters=[PRIOR, "delta_y=normal:0,0.1"]))
    with pytest.raises(ValueError, match="name the uncertain parameters"):
        with_deck(ForwardConfig(inp=str(deck)))
    with pytest.raises(ValueError, match="no such deck file"):
        with_deck(ForwardConfig(inp=str(tmp_path / "nope.inp"), parameters=[PRIOR]))
    with pytest.raises(ValueError, match="no such surface \\(its surfaces: DLOAD_P\\)"):
        observed_faces(read_deck(deck)[0].mesh, "+x", "TOP")
    with pytest.raises(ValueError, match="is a folder"):
        with_deck(ForwardConfig(inp=str(tmp_path), parameters=[PRIOR]))
    nan = tmp_path / "nan.inp"
    nan.write_text(deck.read_text().replace("0.1, 0.03", "nan, 0.03"))
    with pytest.raises(ValueError, match="gives C10 no finite value"):
        with_deck(ForwardConfig(inp=str(nan), parameters=[PRIOR]))
    two = tmp_path / "two_pressures.inp"
    two.write_text(deck.read_text().replace("BEAM, P2, 0.001", "11, P2, 0.001\n12, P2, 0.002"))
    with pytest.raises(ValueError, match="no single pressure load P"):
        with_deck(ForwardConfig(inp=str(two), parameters=[PRIOR]))
    with pytest.raises(ValueError, match="has no parameter delta_y"):
        forward_uq.main(["--inp", str(deck), "--param", PRIOR, "--param", "delta_y=normal:0,0.1",
                         "--runs-dir", str(tmp_path / "runs"), "--out", "bad", "--quiet"])
    assert not (tmp_path / "runs" / "bad").exists()  # refused before any run folder was made


def test_calibration_of_a_deck_from_its_recording(deck, tmp_path):
    """make_recording --inp, then calibrate --inp on that recording: the exact posterior holds the
    deck's C10 (0.1 MPa) within 3 stds, and the nonlinear hierarchical filter agrees with it to half
    an exact std (measured 0.17)."""
    rec = tmp_path / "rec.csv"
    make_recording.main(["--inp", str(deck), "--noise", "0.01", "--seed", "3", "--frames", "20", "--out", str(rec)])
    text = rec.read_text().splitlines()
    assert text[0] == "frame,time,pressure,point_id,X,Y,Z,uy,uz" and len(text) == 1 + 20 * 8
    out = calibrate.main(["--inp", str(deck), "--param", PRIOR, "--recording", str(rec), "--noise", "0.01",
                          "--members", "30", "--no-restart", "--coverage-seeds", "0", "--workers", "1",
                          "--runs-dir", str(tmp_path / "runs"), "--name", "cal"])
    exact, nonlinear = out["filters"]["exact"]["C10"], out["filters"]["hierarchical_nonlinear"]["C10"]
    assert abs(exact["mean"] - 0.1) < 3 * exact["std"]
    assert abs(nonlinear["mean"] - exact["mean"]) < 0.5 * exact["std"]
    assert out["data_fit"]["ok"]
    summary = json.loads((tmp_path / "runs" / "cal" / "summary.json").read_text())
    assert summary["config"]["inp"] == str(deck)
    cache = list((tmp_path / "runs" / "forward_cache").iterdir())
    assert len(cache) == 1 and cache[0].name.startswith("deck")
    with pytest.raises(ValueError, match="drop --peak-pressure"):
        calibrate.main(["--inp", str(deck), "--param", PRIOR, "--recording", str(rec), "--forward-pressure", "0.002"])


def test_calibrate_workers_share_the_forward_ensemble_through_torch_distributed(deck, tmp_path):
    """``calibrate.py --workers 2``: this process becomes rank 0 of a gloo group and a second process
    (the script again, rank 1) solves its share of the forward members and of every restart
    forecast; every member equals the one-process run's (round-off), every filter gives the same
    posterior (the restart filter's to 1e-9 after 4 steps of FE re-solves split over the ranks),
    and the process leaves the group and its environment as it found them."""
    import os

    import torch.distributed as dist

    rec = tmp_path / "rec.csv"
    make_recording.main(["--inp", str(deck), "--noise", "0.01", "--seed", "3", "--frames", "12", "--out", str(rec)])
    args = ["--inp", str(deck), "--param", PRIOR, "--recording", str(rec), "--noise", "0.01", "--members", "16",
            "--coverage-seeds", "0", "--name", "cal"]
    one = calibrate.main([*args, "--workers", "1", "--runs-dir", str(tmp_path / "one")])
    two = calibrate.main([*args, "--workers", "2", "--runs-dir", str(tmp_path / "two")])
    assert "WORLD_SIZE" not in os.environ and "MASTER_PORT" not in os.environ and not dist.is_initialized()

    def members(root):
        files = sorted((root / "forward_cache").glob("*/members/chunk_*.npz"))
        with_y = [np.load(f, allow_pickle=False) for f in files]
        return np.concatenate([f["Y"] for f in with_y]), [str(f["method"][0]) for f in with_y]

    (Y1, m1), (Y2, m2) = members(tmp_path / "one"), members(tmp_path / "two")
    assert Y1.shape == (16, 20, 8, 2) and m1 == m2
    assert np.abs(Y1 - Y2).max() < 1e-10
    for name in ("hierarchical", "hierarchical_nonlinear", "exact", "restart"):
        assert abs(one["filters"][name]["C10"]["mean"] - two["filters"][name]["C10"]["mean"]) < 1e-9
        assert abs(one["filters"][name]["C10"]["std"] - two["filters"][name]["C10"]["std"]) < 1e-9
    assert one["restart_ranks"] == 1 and two["restart_ranks"] == 2
    assert two["filters"]["restart"]["fe_solves"] == one["filters"]["restart"]["fe_solves"] > 0
    # a rerun finds the forward ensemble and the restart filter done: its ranks start, find nothing to
    # solve and leave at the stop
    again = calibrate.main([*args, "--workers", "2", "--runs-dir", str(tmp_path / "two")])
    assert again["filters"]["restart"]["C10"] == two["filters"]["restart"]["C10"]
    assert "WORLD_SIZE" not in os.environ and not dist.is_initialized()


def test_calibrate_under_torchrun_shares_the_restart_filter(deck, tmp_path):
    """``torchrun --standalone --nproc-per-node 2 scripts/calibrate.py``: rank 1 solves its share of
    the forward members and of every restart forecast, rank 0 the rest and everything else; every
    filter equals the one-process run's (reference) to 1e-9, and nothing is printed as a warning."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    rec = tmp_path / "rec.csv"
    make_recording.main(["--inp", str(deck), "--noise", "0.01", "--seed", "3", "--frames", "12", "--out", str(rec)])
    args = ["--inp", str(deck), "--param", PRIOR, "--recording", str(rec), "--noise", "0.01", "--members", "16",
            "--coverage-seeds", "0", "--name", "cal"]
    one = calibrate.main([*args, "--workers", "1", "--runs-dir", str(tmp_path / "one")])
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(root))
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           str(root / "scripts" / "calibrate.py"), *args, "--runs-dir", str(tmp_path / "two")],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warn" not in done.stderr.lower(), done.stderr[-3000:]
    two = json.loads((tmp_path / "two" / "cal" / "summary.json").read_text())
    assert two["restart_ranks"] == 2 and two["filters"]["restart"]["fe_solves"] == one["filters"]["restart"]["fe_solves"]
    for name in ("hierarchical", "hierarchical_nonlinear", "exact", "restart"):
        for stat in ("mean", "std"):
            assert abs(one["filters"][name]["C10"][stat] - two["filters"][name]["C10"][stat]) < 1e-9
