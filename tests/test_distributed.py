"""Forward ensembles under torchrun (torch.distributed, gloo): 2 ranks equal 1 process member for
member, every rank ends with the whole ensemble in its own run folder (no shared file system
assumed), and a rerun solves nothing. Reference: the one-process run of the same ensemble."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.forward import load_chunk, run_forward

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


def scenario_suite(out: Path, torchrun: bool) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    launch = ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"] if torchrun else []
    return subprocess.run([sys.executable, *launch, str(ROOT / "tests" / "torchrun_scenarios.py"),
                           "--effects", "none,gravity", "--seeds", "2", "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=600)


def test_scenario_suite_shares_its_cases_over_ranks_and_resumes(tmp_path):
    """scripts/scenarios.py under torchrun (each case's diagnosis replaced by a deterministic row,
    tests/torchrun_scenarios.py): the 2 ranks run disjoint halves of the cases, rank 0 gathers every
    row into results.json and the same table as one process; a stopped run's per-rank rows are
    reused, not run again."""
    import json

    one = scenario_suite(tmp_path / "one", torchrun=False)
    assert one.returncode == 0, one.stderr[-3000:]
    done = scenario_suite(tmp_path / "two", torchrun=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warn" not in done.stderr.lower(), done.stderr[-3000:]
    rows1 = {r["case"]: r for r in json.loads((tmp_path / "one" / "results.json").read_text())["rows"]}
    rows2 = {r["case"]: r for r in json.loads((tmp_path / "two" / "results.json").read_text())["rows"]}
    assert len(rows1) == (4 + 3) * 2 and rows1.keys() == rows2.keys()
    ran_by = [r.pop("rank") for r in rows2.values()]
    assert sorted(ran_by) == [0] * 7 + [1] * 7  # round robin: each rank half of the cases
    assert all(rows1[c] | {"rank": 0} == rows2[c] | {"rank": 0} for c in rows1)
    assert (tmp_path / "one" / "table.md").read_text() == (tmp_path / "two" / "table.md").read_text()
    assert not list((tmp_path / "two").glob("results.rank*.json"))  # gathered
    # a run stopped with 2 rows saved by rank 1 only: they are reused, the rest is run
    results = json.loads((tmp_path / "two" / "results.json").read_text())
    kept = results["rows"][:2]
    (tmp_path / "two" / "results.json").unlink()
    (tmp_path / "two" / "results.rank1.json").write_text(json.dumps({"settings": {}, "rows": kept}))
    again = scenario_suite(tmp_path / "two", torchrun=True)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "14 cases, 2 reused" in again.stdout
    rows3 = json.loads((tmp_path / "two" / "results.json").read_text())["rows"]
    assert len(rows3) == 14 and {r["case"] for r in rows3} == rows1.keys()


def test_a_damaged_per_rank_rows_file_is_named(tmp_path):
    """A ``results.rank<R>.json`` that is not a stopped run's rows stops the suite with its name and
    the way out, before any case runs."""
    import pytest

    sys.path.insert(0, str(ROOT / "tests"))
    from helpers import load_script

    suite = load_script("scenarios")
    (tmp_path / "results.rank1.json").write_text("{not json")
    ran = []
    with pytest.raises(ValueError, match=r"results.rank1.json: not the rows of a stopped suite run .*delete it"):
        suite.run_cases([{"case": "a"}], {}, tmp_path / "results.json", None, ran.append)
    assert not ran
