"""Every subcommand's --help: exit 0, every option explained with its default, the shared flags spelled one
way (torchfra.cli.flags), no torch imported; the old spellings still work and name the new one."""
import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

from torchfra.cli import flags
from torchfra.cli.main import SUBCOMMANDS

ROOT = Path(__file__).resolve().parents[1]
CHECKED = list(SUBCOMMANDS)


def _env():
    return dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")


def _torchfra(args, cwd, timeout=120):
    return subprocess.run([sys.executable, "-m", "torchfra", *args], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _parser(name: str, monkeypatch) -> argparse.ArgumentParser:
    """The subcommand's parser, caught as its main parses ``--help``."""
    import importlib

    seen = []

    def catch(self, args=None, namespace=None):
        seen.append(self)
        raise SystemExit(0)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", catch)
    module = importlib.import_module(f"torchfra.cli.{SUBCOMMANDS[name][0]}")
    with pytest.raises(SystemExit):
        module.main(["--help"])
    monkeypatch.undo()
    return seen[0]


@pytest.mark.parametrize("name", list(SUBCOMMANDS))
def test_help_of_every_subcommand_exits_0_as_a_subprocess(tmp_path, name):
    out = _torchfra([name, "--help"], tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: torchfra {name}") and "Traceback" not in out.stderr


def test_help_imports_no_torch(tmp_path):
    """``torchfra <sub> --help`` reads the flags only: torch (4 s of imports on this machine) stays unloaded."""
    code = ("import sys\nfrom torchfra.cli.main import main\nbad = []\n"
            f"for name in {CHECKED!r}:\n"
            "    try:\n        main([name, '--help'])\n    except SystemExit:\n        pass\n"
            "    if 'torch' in sys.modules:\n        bad.append(name)\n        break\n"
            "print('TORCH', bad, file=sys.stderr)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=_env(), capture_output=True, text=True,
                         timeout=120)
    assert "TORCH []" in out.stderr, out.stderr[-2000:]


@pytest.mark.parametrize("name", CHECKED)
def test_every_option_has_help_and_shows_its_default(name, monkeypatch):
    p = _parser(name, monkeypatch)
    formatter = p._get_formatter()
    for action in p._actions:
        if not action.option_strings or action.help == argparse.SUPPRESS:
            continue
        flag = action.option_strings[-1]
        assert action.help and len(action.help.split()) >= 2, f"{name} {flag}: no help"
        shown = formatter._get_help_string(action)  # what --help prints, before %-expansion
        empty = action.default is None or action.default is False or action.default == []
        if not empty and action.default is not argparse.SUPPRESS:
            assert "default" in shown, f"{name} {flag}: default {action.default!r} not shown"
    assert "needs --param" not in p.format_help() or any("--param" in a.option_strings for a in p._actions), name


def _visible(p):
    return {s: a for a in p._actions if a.help != argparse.SUPPRESS for s in a.option_strings}


def test_the_shared_flags_are_spelled_one_way(monkeypatch):
    parsers = {name: _parser(name, monkeypatch) for name in CHECKED}
    for name, p in parsers.items():
        seen = _visible(p)
        for old in ("--mesh", "--forward-pressure"):
            assert old not in seen, f"{name} still shows {old}"
        if "--resolution" in seen:  # one default, so that the commands share their forward ensembles
            expected = 2 if name == "scenarios" else flags.DEFAULT_RESOLUTION  # scenarios: the recordings' model
            assert seen["--resolution"].type is int and seen["--resolution"].default == expected, name
        if "--pressure" in seen:  # a pressure-trace CSV, never a number
            assert seen["--pressure"].type is None and "trace" in seen["--pressure"].help, name
        if "--peak-pressure" in seen:
            assert seen["--peak-pressure"].type is float and "MPa" in seen["--peak-pressure"].help, name
        if "--out" in seen:  # a file; a run folder is --name
            assert "--name" not in seen or name == "import-dic", name
        if "--name" in seen:
            assert "--runs-dir" in seen, name
    assert {n for n, p in parsers.items() if "--peak-pressure" in _visible(p)} >= {
        "calibrate", "forward", "make-recording", "scenarios", "demo"}
    assert {n for n, p in parsers.items() if "--resolution" in _visible(p)} >= {
        "calibrate", "forward", "make-recording", "scenarios", "diagnose"}
    assert {n for n, p in parsers.items() if "--method" in _visible(p)} == {"calibrate", "forward"}
    assert all(_visible(parsers[n])["--method"].choices == flags.METHODS for n in ("calibrate", "forward"))
    assert all("--c10" in _visible(parsers[n]) for n in ("calibrate", "make-recording", "demo"))


@pytest.mark.parametrize("name, old, value, dest, new", [
    ("forward", "--mesh", "2", "resolution", "--resolution"),
    ("forward", "--pressure", "0.02", "peak_pressure", "--peak-pressure"),
    ("forward", "--out", "fw", "name", "--name"),
    ("calibrate", "--forward-pressure", "0.03", "peak_pressure", "--peak-pressure"),
    ("calibrate", "--mesh", "2", "resolution", "--resolution"),
    ("make-recording", "--pressure", "0.01", "peak_pressure", "--peak-pressure"),
    ("make-recording", "--mesh", "2", "resolution", "--resolution"),
    ("diagnose", "--mesh", "2", "resolution", "--resolution"),
    ("scenarios", "--pressure", "0.01", "peak_pressure", "--peak-pressure"),
    ("demo", "--pressure", "0.0003", "peak_pressure", "--peak-pressure"),
])
def test_old_spellings_still_work_and_say_the_new_name(name, old, value, dest, new, monkeypatch, capsys):
    p = _parser(name, monkeypatch)
    args = ["rec.csv"] if name == "diagnose" else []
    a = p.parse_args([*args, old, value])
    expected = type(p.get_default(dest) or (1.0 if "pressure" in dest else 1 if dest == "resolution" else ""))(value)
    assert getattr(a, dest) == expected
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{old} is an old spelling: use {new}")


def test_a_number_given_as_a_pressure_trace_is_named_a_peak_pressure(tmp_path):
    (tmp_path / "rec.csv").write_text("frame,time,pressure,point_id,X,Y,Z,uy,uz\n0,1.0,0.01,1,8,0,30,0.1,0.2\n")
    out = _torchfra(["calibrate", "--recording", "rec.csv", "--pressure", "0.02"], tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "0.02 is a peak pressure" in out.stderr and "--peak-pressure 0.02" in out.stderr
    out = _torchfra(["forward", "--pressure", "trace.csv"], tmp_path)  # a trace where only a peak fits
    assert out.returncode == 2 and "--peak-pressure" in out.stderr and "Traceback" not in out.stderr


def test_the_constants_behind_help_agree_with_the_library():
    from torchfra.calibration.config import SEED, ForwardConfig
    from torchfra.cli import diagnose, forward, make_recording, scenarios
    from torchfra.diagnosis.pipeline import ALL_CANDIDATES
    from torchfra.scenarios import CALCULIX_EFFECTS, EFFECTS, GENERATORS, PRESSURE_MAX

    d = ForwardConfig()
    assert (forward.MEMBERS, forward.SEED, forward.LOAD_STEPS, forward.FRAMES, forward.CHUNK, forward.BULK_RATIO,
            forward.SNAPSHOTS, forward.REDUCED_TOL, forward.NEWTON_BUDGET, forward.NEWTON_SECONDS) == (
        d.members, d.seed, d.load_steps, d.frames, d.chunk, d.bulk_ratio, d.snapshots, d.reduced_tol,
        d.newton_budget, d.newton_seconds)
    assert flags.PEAK_PRESSURE == d.pressure == SEED.pressure == PRESSURE_MAX
    assert flags.DEFAULT_RESOLUTION == SEED.resolution and make_recording.TRUTH_C10 == SEED.truth_c10
    assert diagnose.CANDIDATES == tuple(ALL_CANDIDATES)
    assert (scenarios.EFFECTS, scenarios.GENERATORS, scenarios.CALCULIX_EFFECTS) == (
        tuple(EFFECTS), tuple(GENERATORS), tuple(CALCULIX_EFFECTS))


def test_method_auto_solves_a_tiny_ensemble_in_full_and_says_so(tmp_path):
    """A reduced ensemble solves max(5, 1 + 2 d) snapshot members in full (fem.reduced.select_snapshots)."""
    from torchfra.fem.reduced import select_snapshots

    import torch

    for d, members in ((1, 30), (3, 40)):
        params = {f"p{j}": torch.exp(torch.randn(members, generator=torch.Generator().manual_seed(j)))
                  for j in range(d)}
        assert flags.snapshot_count(d) == len(select_snapshots(params))
    assert flags.resolve_method("auto", 6, 1)[0] == "full" and "6 members against 5" in flags.resolve_method(
        "auto", 6, 1)[1]
    assert flags.resolve_method("auto", 100, 1) == ("reduced", "")
    assert flags.resolve_method("reduced", 6, 1) == ("reduced", "")
    out = _torchfra(["forward", "--members", "6", "--inp", "missing.inp"], tmp_path)  # stops at the deck, after
    assert "--method auto: 6 members against 5 snapshot members" in out.stdout  # the choice is said
    assert out.returncode == 2 and "missing.inp" in out.stderr
