"""Files found in a run folder or given as a recording are data, never code: a planted pickle is
refused with a message naming the file, and its payload never runs."""
import pathlib
import pickle
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchfra.assimilation import FilterResult, analysis
from torchfra.calibration import restart
from torchfra.calibration.config import CalibrationConfig
from torchfra.calibration.restart import CheckpointError, read_restart_checkpoint
from torchfra.io.recordings import read_recording
from torchfra.observation.recording import COLUMNS, RecordingError

ROOT = pathlib.Path(__file__).resolve().parents[1]


class Payload:
    """Unpickling this creates the marker file: the proof that code from the file ran."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (pathlib.Path(self.marker),)


def _checkpoint_like(res: FilterResult) -> dict:
    return {"config": {"members": 3}, "recording": "digest", "result": res.to_dict(),
            "generator": torch.Generator().manual_seed(0).get_state(),
            "forecaster": {"x": torch.zeros(3, 4), "lam_now": torch.zeros(3), "fe_solves": 0, "newton_iterations": 0}}


@pytest.mark.parametrize("save", [
    lambda obj, path: torch.save(obj, path),  # torch's zip format, the pickle inside
    lambda obj, path: path.write_bytes(pickle.dumps(obj)),  # a bare pickle, torch's legacy format
])
def test_planted_restart_checkpoint_is_refused_and_never_runs(tmp_path, save):
    marker = tmp_path / "payload_ran"
    path = tmp_path / "run" / "restart_checkpoint.pt"
    path.parent.mkdir()
    res = FilterResult(Q=[torch.zeros(3, 1)])
    save({**_checkpoint_like(res), "result": Payload(marker)}, path)
    with pytest.raises(CheckpointError, match=re.escape(str(path)) + r": not a restart checkpoint .*delete it to start"):
        read_restart_checkpoint(path)
    assert not marker.exists()


def test_restart_filter_refuses_a_planted_checkpoint_in_its_run_folder(tmp_path, monkeypatch):
    """The restart filter of a calibration run reads its checkpoint through the safe reader (the
    FE model is stubbed: the refusal comes before any solve)."""
    monkeypatch.setattr(restart, "ActuatorSolver", lambda *a, **k: None)
    monkeypatch.setattr(restart, "RestartForecaster", lambda *a, **k: None)
    marker = tmp_path / "payload_ran"
    torch.save({"result": Payload(marker)}, tmp_path / "restart_checkpoint.pt")
    config = CalibrationConfig(members=3, frames=4, restart_every=2)
    with pytest.raises(CheckpointError, match="restart_checkpoint.pt: .*delete it to start the restart filter over"):
        restart._restart(config, tmp_path, SimpleNamespace(n_frames=4, frames=np.arange(4)), np.ones(4),
                             torch.zeros(3, 1), None, None, None, False)
    assert not marker.exists()


@pytest.mark.parametrize("content, why", [
    (b"", "empty or damaged"),
    (b"PK\x03\x04" + bytes(30), "empty or damaged"),
])
def test_damaged_restart_checkpoint_is_named(tmp_path, content, why):
    path = tmp_path / "restart_checkpoint.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match=why + ".*delete it to start the restart filter over"):
        read_restart_checkpoint(path)


def test_restart_checkpoint_round_trips_through_weights_only(tmp_path):
    """What the restart filter saves (a FilterResult as plain data, the generator state as a uint8
    tensor) loads with weights_only=True and gives back the same result and random stream."""
    gen = torch.Generator().manual_seed(3)
    Q0 = torch.randn(5, 1, generator=gen)
    Y = torch.randn(5, 4, generator=gen)
    Qa, info = analysis(Q0, Y, torch.zeros(4), torch.ones(4), torch.randn(5, 4, generator=gen))
    res = FilterResult(Q=[Q0, Qa], info=[info], Y_tracked=[Y[:, :2]], fe_solves=5, newton_iterations=17, wall_s=1.5)
    path = tmp_path / "restart_checkpoint.pt"
    torch.save({**_checkpoint_like(res), "generator": gen.get_state()}, path)
    saved = read_restart_checkpoint(path)
    back = FilterResult.from_dict(saved["result"])
    assert all(torch.equal(a, b) for a, b in zip(back.Q, res.Q)) and back.info == res.info
    assert torch.equal(back.Y_tracked[0], res.Y_tracked[0]) and back.log_evidence == res.log_evidence
    assert (back.fe_solves, back.newton_iterations, back.wall_s) == (5, 17, 1.5)
    again = torch.Generator().set_state(saved["generator"])
    assert torch.equal(torch.randn(3, generator=again), torch.randn(3, generator=gen))


def test_recording_with_object_array_is_refused_and_never_runs(tmp_path):
    marker = tmp_path / "payload_ran"
    arrays = {c: np.arange(2.0) for c in COLUMNS}
    arrays["uy"] = np.array([Payload(marker), Payload(marker)], dtype=object)
    np.savez(tmp_path / "r.npz", **arrays)
    with pytest.raises(RecordingError, match=r"r.npz: array uy holds Python objects") as err:
        read_recording(tmp_path / "r.npz")
    assert "allow_pickle" not in str(err.value)
    assert not marker.exists()


def test_no_pickle_loading_in_the_code():
    """torch.load with weights_only=False or numpy loads with allow_pickle=True would run code from
    a file."""
    offenders = []
    for path in sorted([*(ROOT / "torchfra").rglob("*.py"), *(ROOT / "scripts").glob("*.py")]):
        text = path.read_text()
        for pattern in (r"weights_only\s*=\s*False", r"allow_pickle\s*=\s*True", r"pickle\.loads?\(",
                        r"torch\.load\((?![^)]*weights_only\s*=\s*True)"):
            offenders += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in re.finditer(pattern, text)]
    assert not offenders, offenders


def test_planted_reduced_batch_checkpoint_is_refused_and_never_runs(tmp_path, capsys):
    """A ``batch_*.partial.npz`` (a reduced batch's per-load-step state) holding a pickle payload is
    named as unreadable and its batch solved from the start; the payload never runs."""
    from torchfra.calibration.forward import _read_partial

    marker = tmp_path / "payload_ran"
    path = tmp_path / "batch_00002.partial.npz"
    np.savez(path, members=np.arange(2), digest=np.array("d"), load_factors=np.ones(1),
             q_out=np.array([Payload(marker)], dtype=object))
    assert _read_partial(path, [0, 1], "d", np.ones(1)) is None
    assert "batch_00002.partial.npz is not a readable batch checkpoint" in capsys.readouterr().err
    assert not marker.exists()
