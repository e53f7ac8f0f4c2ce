"""Forward ensembles under torchrun (torch.distributed, gloo): 2 ranks equal 1 process member for
member, every rank ends with the whole ensemble in its own run folder (no shared file system
assumed), and a rerun solves nothing. Reference: the one-process run of the same ensemble."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from torchfra.forward import ForwardConfig, load_chunk, run_forward

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["--members", "6", "--mesh", "1", "--pressure", "0.004", "--load-steps", "2", "--frames", "4",
        "--snapshots", "2", "--out", "ens", "--quiet"]
CONFIG = ForwardConfig(members=6, resolution=1, pressure=0.004, load_steps=2, frames=4, snapshots=2)


def torchrun(base: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           str(ROOT / "tests" / "torchrun_forward.py"), str(base), *ARGS],
                          capture_output=True, text=True, env=env, timeout=600)


def test_two_ranks_equal_one_process_and_every_rank_holds_the_ensemble(tmp_path):
    one = run_forward(CONFIG, tmp_path / "one", progress=False)
    done = torchrun(tmp_path / "two")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Warning" not in done.stderr and "warn" not in done.stderr.lower(), done.stderr[-3000:]
    with np.load(tmp_path / "two" / "rank0" / "ens" / "forward.npz", allow_pickle=False) as f:
        Y, status = f["Y"], f["status"]
    np.testing.assert_array_equal(status, one["status"])
    # member for member: the same algorithm on the same member, whichever rank ran it (the reduced
    # members' batches differ by rank, which changes round-off only: measured 8e-15 mm)
    assert np.abs(Y - one["Y_fe"]).max() < 1e-9, np.abs(Y - one["Y_fe"]).max()
    assert not (tmp_path / "two" / "rank1" / "ens" / "forward.npz").exists()  # rank 0 writes the outputs
    for rank in ("rank0", "rank1"):  # each rank's folder holds every member: a rerun can start from either
        members = tmp_path / "two" / rank / "ens" / "members"
        assert sorted(p.name for p in members.glob("chunk_*.npz")) == [f"chunk_{m:05d}.npz" for m in range(6)]
        for m in range(6):
            np.testing.assert_allclose(load_chunk(members / f"chunk_{m:05d}.npz")["Y"][0], one["Y_steps"][m],
                                       rtol=0, atol=1e-9)  # batches differ by rank: round-off only
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "two").rglob("chunk_*.npz")}
    again = torchrun(tmp_path / "two")
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # resumed: nothing solved or rewritten
