"""Forward ensemble: prior sampling, resumable chunked solves, the files other tools read."""
import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.forward import lognormal_parameters, member_parameters, run_forward
from torchfra.report.forward import write_forward_outputs


def test_lognormal_moments():
    """Closed form: E[X] = exp(mu + s^2/2), Var[X] = (exp(s^2) - 1) E[X]^2; and a 2e5-sample check."""
    mean, std = 1.1 * 0.005615, 0.2 * 0.005615
    mu, s = lognormal_parameters(mean, std)
    assert math.exp(mu + s * s / 2) == pytest.approx(mean, rel=1e-14)
    assert math.sqrt(math.expm1(s * s)) * mean == pytest.approx(std, rel=1e-14)
    C10 = member_parameters(ForwardConfig(members=200_000, seed=3))["C10"]
    assert float(C10.mean()) == pytest.approx(mean, rel=3 * std / mean / math.sqrt(2e5) * 2)
    assert float(C10.std()) == pytest.approx(std, rel=0.01)
    with pytest.raises(ValueError, match="mean > 0 and std > 0"):
        lognormal_parameters(-1.0, 0.1)


def test_forward_run_files_and_resume(tmp_path):
    config = ForwardConfig(members=2, resolution=1, load_steps=1, frames=10, chunk=1, pressure=0.002)
    run_dir = tmp_path / "fwd"
    result = run_forward(config, run_dir, progress=False)
    summary = write_forward_outputs(result, config, run_dir)
    for key in ("members", "members_converged", "elements", "fiber_elements", "dofs", "load_steps",
                "newton_iterations_total", "wall_s", "threads", "tracked_point", "tracked_displacement_mean"):
        assert key in summary
    assert summary["members_converged"] == 2
    data = np.load(run_dir / "forward.npz")
    P = data["points"].shape[0]
    assert data["Y"].shape == (2, 10, P, 2) and data["times"].shape == (10,)
    assert np.allclose(data["pressure"], 0.002 * data["times"])
    assert data["params"].shape == (2, 4) and list(data["param_names"]) == ["C10", "D1", "E_fiber", "P"]
    assert np.allclose(data["points"][:, 0], 8.0)  # the front face the camera sees
    # softer member bends more (tracked u_y more negative)
    soft = int(np.argmin(data["params"][:, 0]))
    t = int(data["tracked_point_index"])
    assert data["Y"][soft, -1, t, 0] < data["Y"][1 - soft, -1, t, 0] < 0
    assert json.loads((run_dir / "summary.json").read_text())["members"] == 2
    assert (run_dir / "mean_deformed.vtu").exists() and list(run_dir.glob("events.out.tfevents*"))
    # a rerun loads the finished chunks instead of solving them again
    stamps = {p: p.stat().st_mtime_ns for p in (run_dir / "members").glob("*.npz")}
    again = run_forward(config, run_dir, progress=False)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert np.array_equal(again["Y_fe"], result["Y_fe"])
    # threads and the reduced batch change how members are solved, not what they are: it resumes
    how = run_forward(dataclasses.replace(config, threads=2, reduced_batch=3), run_dir, progress=False)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps and np.array_equal(how["Y_fe"], result["Y_fe"])
    torch.set_num_threads(1)
    with pytest.raises(ValueError, match="other settings"):
        run_forward(ForwardConfig(members=3, resolution=1, load_steps=1, frames=10, chunk=1), run_dir)


def test_forward_flags_a_member_that_does_not_converge(tmp_path, monkeypatch):
    """A member whose solve fails is flagged in status, summary and forward.npz, keeps NaN (never zeros
    or a neighbour's values) beyond the load it reached, and is left out of the summary's statistics,
    while the other member of its chunk finishes."""
    from torchfra.calibration import forward

    def params_with_a_hopeless_member(config, base=None):
        p = member_parameters(config, base)
        p["C10"][1] = 1e-5  # P / C10 = 200 at full load: far beyond what the increments allow here
        p["D1"][1] = 1.0 / (config.bulk_ratio * p["C10"][1])
        return p

    monkeypatch.setattr(forward, "member_parameters", params_with_a_hopeless_member)
    config = ForwardConfig(members=2, resolution=1, load_steps=2, frames=10, chunk=2, pressure=0.002,
                           newton={"stagnation_tol": 1e-6, "max_iterations": 8, "min_increment": 0.02})
    run_dir = tmp_path / "fwd"
    result = run_forward(config, run_dir, progress=False)
    assert list(result["status"]) == ["converged", "diverged"]
    assert result["load_reached"][1] < 1.0 and result["cutbacks"][1] > 0
    summary = write_forward_outputs(result, config, run_dir)
    assert summary["members_converged"] == 1 and summary["members_failed"] == [1]
    data = np.load(run_dir / "forward.npz")
    assert list(data["status"]) == ["converged", "diverged"]
    t = data["times"]
    beyond = t > result["load_reached"][1] + 1e-12
    assert beyond.any() and np.isnan(data["Y"][1, beyond]).all()
    assert np.isfinite(data["Y"][0]).all()
    # the summary's ensemble statistics are those of the converged member alone
    track = int(data["tracked_point_index"])
    assert np.allclose(summary["tracked_displacement_mean"], data["Y"][0, -1, track])
    # TensorBoard: a point per member, and the status table lists the failed member
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir), size_guidance={"tensors": 0}).Reload()
    assert [e.value for e in events.Scalars("newton/cutbacks")][1] == result["cutbacks"][1]
    assert events.Scalars("newton/members_converged")[0].value == 1
    table = events.Tensors("newton/status/text_summary")[0].tensor_proto.string_val[0].decode()
    assert "| 1 | diverged |" in table


class _Payload:
    """Unpickling this object would create a marker file: proof of code execution."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (str(self.marker), "w"))


def test_planted_pickle_chunk_is_refused_not_executed(tmp_path):
    """A crafted member chunk (copied run, shared cache) holding a pickle payload is refused by name,
    and the payload never runs: chunks are read with allow_pickle=False."""
    config = ForwardConfig(members=1, resolution=1, load_steps=1, frames=10, pressure=0.002)
    run_dir = tmp_path / "fwd"
    (run_dir / "members").mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(__import__("dataclasses").asdict(config)))
    marker = tmp_path / "executed"
    np.savez(run_dir / "members" / "chunk_00000.npz", Y=np.array([_Payload(marker)], dtype=object))
    with pytest.raises(ValueError, match=r"chunk_00000\.npz is not a forward-ensemble chunk.*delete it"):
        run_forward(config, run_dir, progress=False)
    assert not marker.exists()


def test_lock_of_a_recycled_pid_is_taken_over(tmp_path, capsys):
    """A chunk lock naming a live PID that now belongs to another process (or a dead one) does not
    make the run wait forever: it is taken over with a message, and the member is solved."""
    import os
    import socket

    config = ForwardConfig(members=1, resolution=1, load_steps=1, frames=10, pressure=0.002)
    run_dir = tmp_path / "fwd"
    (run_dir / "members").mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(__import__("dataclasses").asdict(config)))
    lock = run_dir / "members" / "chunk_00000.lock"
    lock.write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "start": "-1", "time": 0.0}))
    result = run_forward(config, run_dir, progress=True)
    assert result["status"].tolist() == ["converged"] and not lock.exists()
    assert "now belongs to another process" in capsys.readouterr().err


def test_chunks_are_per_member_and_carry_arrays_only(tmp_path):
    """Default checkpoints hold one member each (a stop loses at most one member's work) and load
    with allow_pickle=False, residual histories intact."""
    from torchfra.calibration.forward import load_chunk

    config = ForwardConfig(members=2, resolution=1, load_steps=1, frames=10, pressure=0.002)
    assert config.chunk == 1
    result = run_forward(config, tmp_path / "fwd", progress=False)
    chunks = sorted((tmp_path / "fwd" / "members").glob("chunk_*.npz"))
    assert [c.name for c in chunks] == ["chunk_00000.npz", "chunk_00001.npz"]
    for m, c in enumerate(chunks):
        with np.load(c, allow_pickle=False) as data:
            assert all(data[k].dtype != object for k in data.files)
        rec = load_chunk(c)
        assert rec["history"] == [list(result["history"][m])] and rec["Y"].shape[0] == 1


def test_reduced_forward_matches_full_newton_for_every_member_and_frame(tmp_path):
    """Reference: the same ensemble by full Newton for every member (method "full"). The issue's
    accuracy bound: max |Delta Y| <= 1e-3 mm for every member and frame (DIC noise is 1 mm)."""
    kw = dict(members=6, resolution=1, load_steps=4, frames=10, pressure=0.011, snapshots=3)
    full = run_forward(ForwardConfig(method="full", **kw), tmp_path / "full", progress=False)
    config = ForwardConfig(method="reduced", **kw)
    red = run_forward(config, tmp_path / "red", progress=False)
    assert list(red["method"]).count("reduced") == 3  # 3 snapshots (--snapshots 3), 3 reduced
    assert (red["status"] == "converged").all()
    assert np.abs(red["Y_fe"] - full["Y_fe"]).max() <= 1e-3
    is_red = red["method"] == "reduced"
    assert (red["error_estimate"][is_red] <= config.reduced_tol).all()
    assert np.array_equal(red["Y_fe"][~is_red], full["Y_fe"][~is_red])  # snapshots are full solves
    assert (tmp_path / "red" / "reduced_model.npz").exists()
    # resume: every member is loaded, none solved again
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "red" / "members").glob("*.npz")}
    again = run_forward(config, tmp_path / "red", progress=False)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert np.array_equal(again["Y_fe"], red["Y_fe"])


def test_a_reduced_batch_killed_mid_solve_resumes_after_its_last_load_step(tmp_path, monkeypatch, capsys):
    """A reduced batch checkpoints its state after every load step (``batch_*.partial.npz``, arrays
    only): a run killed inside the batch resumes it from there, says so, and ends bit-identical to an
    uninterrupted run (reference: the same ensemble solved without a kill); no checkpoint is left."""
    from torchfra.calibration import forward

    config = ForwardConfig(members=6, resolution=1, load_steps=3, frames=4, pressure=0.004, snapshots=2,
                           reduced_batch=4)
    whole = run_forward(config, tmp_path / "whole", progress=False)
    written = []
    original = forward._write_partial

    def killed_after_one_step(path, batch, digest, state):
        original(path, batch, digest, state)
        written.append(int(state["step"]))
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(forward, "_write_partial", killed_after_one_step)
    with pytest.raises(KeyboardInterrupt):
        run_forward(config, tmp_path / "killed", progress=False)
    assert written == [0] and len(list((tmp_path / "killed" / "members").glob("batch_*.partial.npz"))) == 1
    monkeypatch.setattr(forward, "_write_partial", original)
    resumed = run_forward(config, tmp_path / "killed", progress=True)
    said = capsys.readouterr()
    assert "resuming reduced members" in said.out + said.err, said
    assert np.array_equal(resumed["Y_fe"], whole["Y_fe"]) and np.array_equal(resumed["status"], whole["status"])
    assert not list((tmp_path / "killed" / "members").glob("batch_*"))
    # a checkpoint of a batch that an earlier stopped run shared out otherwise (other ranks) is removed
    # once every member is saved, and nothing is solved again
    orphan = tmp_path / "killed" / "members" / "batch_00003.partial.npz"
    np.savez(orphan, members=np.array([3, 4]), digest=np.array("other"))
    again = run_forward(config, tmp_path / "killed", progress=False)
    assert not orphan.exists() and np.array_equal(again["Y_fe"], whole["Y_fe"])
