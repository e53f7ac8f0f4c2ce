"""A TOML parameter file (``--config FILE.toml``) is read within bounds: nesting that would exhaust the
parser's recursion, keys that are no parameter names, entries of the wrong kind and a truth outside
its prior are refused naming the file and the entry, before any FE work."""
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from torchfra.calibration.priors import TAIL, PriorError, lognormal_parameters, read_parameter_file

ROOT = Path(__file__).resolve().parents[1]
PRIOR = '[parameters]\nC10 = "lognormal:0.0062,0.0011"\n'


@pytest.mark.parametrize("text, match", [
    ("a = " + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deep to read"),
    ("a = " + "{b=" * 50_000 + "1" + "}" * 50_000 + "\n", "nested too deep to read"),
    ('[parameters]\n" C10 " = "lognormal:0.0062,0.0011"\n', "\\[parameters\\] ' C10 ' is not a parameter name"),
    ('[parameters]\n"C10.x" = "lognormal:0.0062,0.0011"\n', "'C10.x' is not a parameter name"),
    (PRIOR + '[fixed]\n" E_fiber" = 31000\n', "\\[fixed\\] ' E_fiber' is not a parameter name"),
    ("fixed = 5\n" + PRIOR, "fixed must be a table \\[fixed\\]"),
    ("[parameters]\nC10 = 5\n", "C10 = 5 is not a prior string"),
    (PRIOR + "[fixed]\nC01 = true\n", "C01 = True is not a number"),
    (PRIOR + '[truth]\nC10 = "0.005"\n', "C10 = '0.005' is not a number"),
    # reach of lognormal(0.0062, 0.0011) at mean +- 4 stds in log C10: exp(mu +- 4 s), from lognormal_parameters
    (PRIOR + "[truth]\nC10 = 5.0\n", "C10 = 5 lies outside its prior .*reaches \\[0.003019, 0.01234\\]"),
    ('[parameters]\nC10 = "normal:0.006,0.001"\n[truth]\nC10 = 0.0101\n', "reaches \\[0.002, 0.01\\]"),
    ('[parameters]\nC10 = "uniform:0.003,0.009"\n[truth]\nC10 = 0.0091\n', "outside their prior's support"),
], ids=["arrays-100000", "tables-50000", "key-spaces", "key-dot", "fixed-key", "fixed-scalar", "prior-number",
        "fixed-bool", "truth-string", "truth-lognormal", "truth-normal", "truth-uniform"])
def test_a_bad_parameter_file_is_refused_naming_the_file(tmp_path, text, match):
    path = tmp_path / "prior.toml"
    path.write_text(text)
    with pytest.raises(PriorError, match=match) as info:
        read_parameter_file(path)
    assert str(info.value).startswith(f"{path}: ")


def test_the_reach_quoted_is_the_priors_mean_plus_minus_tail_stds():
    mu, s = lognormal_parameters(0.0062, 0.0011)
    assert f"{math.exp(mu - TAIL * s):.4g}" == "0.003019" and f"{math.exp(mu + TAIL * s):.4g}" == "0.01234"


def test_a_good_parameter_file_reads_as_before(tmp_path):
    path = tmp_path / "prior.toml"
    path.write_text(PRIOR + 'E_fiber = "lognormal:31000,6000"\n[fixed]\nC01 = 0.0\n[truth]\nC10 = 0.0048\n'
                    'E_fiber = 25000\n')
    assert read_parameter_file(path) == {"parameters": ["C10=lognormal:0.0062,0.0011", "E_fiber=lognormal:31000,6000"],
                                         "fixed": ["C01=0.0"], "truth": {"C10": 0.0048, "E_fiber": 25000.0}}
    path.write_text('[parameters]\nC10 = "uniform:0.003,0.009"\n[truth]\nC10 = 0.00899\n')  # inside the bounds
    assert read_parameter_file(path)["truth"] == {"C10": 0.00899}


def test_calibrate_refuses_a_truth_outside_its_prior_with_a_recording_before_any_fe_work(tmp_path):
    """As documented (docs/calibration.md): a truth outside its prior is refused before any FE work,
    also when the file is given with --recording."""
    (tmp_path / "prior.toml").write_text(PRIOR + "[truth]\nC10 = 5.0\n")
    (tmp_path / "r.csv").write_text("frame,time,pressure,point_id,X,Y,Z,uy,uz\n0,0.5,0.01,1,8,0,30,0.1,0.2\n"
                                    "1,1.0,0.02,1,8,0,30,0.2,0.4\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "torchfra", "calibrate", "--config", "prior.toml", "--recording",
                          "r.csv", "--members", "5"], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2, out.stderr
    assert "prior.toml: [truth]: C10 = 5 lies outside its prior" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "runs" / "forward_cache").exists()
