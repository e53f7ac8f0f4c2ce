"""Every script in examples/ runs as its docstring says (a subprocess from the repository root, the
calibration and the diagnosis with ``TORCHFRA_EXAMPLE_QUICK=1``), and what it prints and writes is right."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torchfra.io.recordings import read_recording

pytestmark = pytest.mark.slow  # minutes of FE work each: python -m pytest -m slow runs them

ROOT = Path(__file__).resolve().parents[1]


def run_example(name: str, *args, quick: bool = False, cwd=ROOT) -> str:
    env = dict(os.environ, PYTHONPATH=str(ROOT), **({"TORCHFRA_EXAMPLE_QUICK": "1"} if quick else {}))
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_every_example_is_tested_and_documented():
    scripts = sorted(p.name for p in (ROOT / "examples").glob("*.py"))
    tested = sorted(set(re.findall(r'run_example\("(\w+\.py)"', Path(__file__).read_text())))
    assert scripts == tested
    for doc in ("docs/index.md", "docs/api.md"):
        text = (ROOT / doc).read_text()
        assert "examples/" in text and all(s in text for s in scripts), doc


def test_fem_block():
    out = run_example("fem_block.py")
    rows = re.findall(r"member (\d): C10 = ([\d.]+) MPa, (\w+), \d+ Newton iterations, top moved uy = ([\d.]+) mm", out)
    assert len(rows) == 3 and all(r[2] == "converged" for r in rows)
    c10, uy = np.array([float(r[1]) for r in rows]), np.array([float(r[3]) for r in rows])
    # a softer block bends further; linear beam theory gives uy ~ 1/C10, the large rotation (0.5-0.7 rad)
    # stiffens the softer members a little, so the ratio lies between 1 and C10's (reference: Euler-Bernoulli)
    assert np.all(np.diff(uy) < 0)
    assert 1.0 < uy[0] / uy[-1] <= c10[-1] / c10[0] * 1.001


def test_read_dic_export(tmp_path):
    out = run_example("read_dic_export.py", tmp_path)
    assert "5 frames x 60 points, pressure 0..0.02 MPa" in out
    rec = read_recording(tmp_path / "recording.csv")
    # the export's field, written by the script: uy = 0.5 p[kPa] (Z/60)^2, uz = -0.02 p[kPa] Y/8
    kpa = 1000 * rec.pressure[:, None]
    np.testing.assert_allclose(rec.Z[..., 0], 0.5 * kpa * (rec.X[None, :, 2] / 60) ** 2, atol=1e-7)
    np.testing.assert_allclose(rec.Z[..., 1], -0.02 * kpa * rec.X[None, :, 1] / 8, atol=1e-7)
    np.testing.assert_allclose(rec.times, 0.5 * np.arange(5))


def test_own_deck(tmp_path):
    out = run_example("own_deck.py", cwd=tmp_path)
    assert (tmp_path / "runs" / "example_deck" / "block.inp").exists()
    assert "parameters {'C10': 0.0056, 'D1': 0.18, 'P': 0.0002}" in out
    rows = re.findall(r"C10 = ([\d.]+) MPa, (\w+), largest displacement ([\d.]+) mm", out)
    assert [r[1] for r in rows] == ["converged"] * 3
    disp = np.array([float(r[2]) for r in rows])
    assert np.all(np.diff(disp) < 0)  # the stiffer member moves less


def test_calibrate_synthetic(tmp_path):
    run = tmp_path / "cal"
    out = run_example("calibrate_synthetic.py", run, quick=True)
    summary = json.loads((run / "summary.json").read_text())
    exact = summary["filters"]["exact"]["C10"]
    assert any(line.startswith("C10 = ") for line in out.splitlines()) and "exact stds from the exact mean" in out
    # the synthetic recording's truth, 0.0048 MPa at 0.05 mm noise, within 3 exact stds (reference: the truth)
    assert abs(exact["mean"] - 0.0048) < 3 * exact["std"]
    assert summary["members"] == 4 and summary["frames"] == 6
    for f in ("bands.png", "pdfs.png", "bands_again.png", "pdfs_again.png"):
        assert (run / f).stat().st_size > 10_000
