"""Scripts end a wrong input with one paragraph on stderr and exit status 2, never a traceback;
--debug shows the traceback; Ctrl-C exits 130 saying how to resume."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from torchfra.cli import run as cli
from torchfra.observation.recording import RecordingError

ROOT = Path(__file__).resolve().parents[1]


def _script(args, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("args, message", [
    (["scripts/calibrate.py", "--recording", "{tmp}/missing.csv"], "missing.csv: no such recording"),
    (["scripts/calibrate.py", "--recording", "{tmp}/folder.csv"], "folder.csv: is a folder, not a recording"),
    (["scripts/calibrate.py", "--recording", "{tmp}/utf16.csv"], "utf16.csv: the file is UTF-16; save it as UTF-8"),
    (["scripts/calibrate.py", "--recording", "{tmp}/kpa.csv"], "pressures in kPa or Pa instead of MPa?"),
    (["scripts/calibrate.py", "--recording", "{tmp}/high.csv"], "calibrate with --forward-pressure 0.03"),
    (["scripts/make_recording.py", "--out", "{tmp}/a_file/r.csv"], "a_file: File exists"),
    (["scripts/forward_uq.py", "--runs-dir", "{tmp}/a_file"], "a_file/forward: Not a directory"),
    (["scripts/fem_demo.py", "--runs-dir", "{tmp}/a_file"], "a_file/fem_demo: Not a directory"),
    (["scripts/calibrate.py", "--param", "C11=lognormal:1,0.1"], "unknown parameter 'C11'; the model's parameters are"),
    (["scripts/calibrate.py", "--param", "C10=lognormal:0.006,0.001", "--truth", "C01=0.001"],
     r"C01'] are not uncertain parameters of this set"),
    (["scripts/calibrate.py", "--param", "C01=uniform:0,0.002", "--truth", "C01=0.005"], "C10 needs a prior"),
    (["scripts/calibrate.py", "--param", "C10=lognormal:0.006,0.001", "--param", "C01=uniform:0,0.002",
      "--truth", "C01=0.005"], "lie outside their prior's support"),
    (["scripts/calibrate.py", "--config", "{tmp}/prior.toml"], "prior.toml: --param 'C10=normal:0.006,0.003': C10 must"),
    (["scripts/forward_uq.py", "--param", "density=normal:0,1e-9"], "density must lie in [0, 2.5e-08]"),
    (["scripts/make_recording.py", "--value", "E_fiber=-1"], "E_fiber must lie in"),
])
def test_scripts_end_a_wrong_input_with_one_paragraph(tmp_path, args, message):
    (tmp_path / "folder.csv").mkdir()
    (tmp_path / "utf16.csv").write_text("frame,time,pressure,point_id,X,Y,Z,uy,uz\n", encoding="utf-16")
    (tmp_path / "a_file").write_text("")
    (tmp_path / "prior.toml").write_text('[parameters]\nC10 = "normal:0.006,0.003"\n')
    for name, p in (("kpa", 22.0), ("high", 0.03)):  # a point of the visible face; the last frame's pressure
        (tmp_path / f"{name}.csv").write_text("frame,time,pressure,point_id,X,Y,Z,uy,uz\n"
                                              f"0,0.5,0.01,1,8,0,30,0.1,0.2\n1,1.0,{p},1,8,0,30,0.2,0.4\n")
    args = [str(ROOT / args[0]), *(a.format(tmp=tmp_path) for a in args[1:])]
    out = _script(args, tmp_path)
    assert not (tmp_path / "runs" / "forward_cache").exists()  # refused before any FE work or helper
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr and "Traceback" not in out.stdout
    assert out.stderr.startswith("error: ") and message in out.stderr
    assert out.stderr.rstrip().endswith("(run with --debug for the traceback)")
    assert "\n\n" not in out.stderr.strip()


def test_every_script_is_a_thin_wrapper_of_its_subcommand_and_ends_through_cli_run():
    """scripts/<name>.py is its subcommand's main (the same flags) run through cli.run, nothing else;
    every subcommand module's own main guard goes through cli.run too."""
    from torchfra.cli.main import SUBCOMMANDS

    scripts = sorted((ROOT / "scripts").glob("*.py"))
    assert len(scripts) == len(SUBCOMMANDS)
    modules = {m for m, _ in SUBCOMMANDS.values()}
    for path in scripts:
        lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
        imports = [line for line in lines if line.startswith("from torchfra.cli.") and line.endswith(" import main")]
        assert len(imports) == 1 and imports[0].split()[1].removeprefix("torchfra.cli.") in modules, path.name
        assert lines[-2:] == ['if __name__ == "__main__":', "run(main)"] and len(lines) <= 6, path.name
    for module in modules:
        source = ROOT / "torchfra" / "cli" / f"{module}.py"
        if not source.exists():  # a subcommand that is a package: its command module guards main
            source = ROOT / "torchfra" / "cli" / module / "command.py"
        tail = source.read_text().rstrip().splitlines()[-3:]
        assert [line.strip() for line in tail] == ["from torchfra.cli.run import run", "", "run(main)"], module


def test_debug_shows_the_traceback(tmp_path):
    out = _script([str(ROOT / "scripts/calibrate.py"), "--recording", str(tmp_path / "missing.csv"), "--debug"], tmp_path)
    assert out.returncode == 1
    assert "Traceback" in out.stderr and "RecordingError: " in out.stderr and "missing.csv: no such recording" in out.stderr


def _main_raising(exc):
    def main():
        raise exc
    return main


@pytest.mark.parametrize("exc, status, text", [
    (RecordingError("r.csv, line 3: bad\n\nsecond paragraph"), 2, "error: r.csv, line 3: bad\nsecond paragraph\n"),
    (FileNotFoundError(2, "No such file or directory", "x.npz"), 2, "error: x.npz: No such file or directory\n"),
    (IsADirectoryError(21, "Is a directory", "runs"), 2, "error: runs: Is a directory\n"),
    (PermissionError(13, "Permission denied", "out.csv"), 2, "error: out.csv: Permission denied\n"),
    (KeyError("C10"), 2, "error: no entry 'C10'\n"),
    (UnicodeDecodeError("utf-8", b"\xff", 0, 1, "invalid start byte"), 2,
     "error: 'utf-8' codec can't decode byte 0xff in position 0: invalid start byte\n"),
    (KeyboardInterrupt(), 130, "interrupted; rerun the same command to resume\n"),
])
def test_run_prints_one_paragraph_and_exits(monkeypatch, capsys, exc, status, text):
    monkeypatch.setattr(sys, "argv", ["script.py"])
    with pytest.raises(SystemExit) as done:
        cli.run(_main_raising(exc))
    assert done.value.code == status
    err = capsys.readouterr().err
    assert text in err and "Traceback" not in err
    if status == 2:
        assert err.endswith("(run with --debug for the traceback)\n")


def test_run_lets_bugs_and_debug_through(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["script.py"])
    with pytest.raises(ZeroDivisionError):  # not a wrong input: a bug keeps its traceback
        cli.run(_main_raising(ZeroDivisionError("bug")))
    seen = []
    monkeypatch.setattr(sys, "argv", ["script.py", "--name", "x", "--debug"])

    def main():
        seen.append(list(sys.argv[1:]))
        raise RecordingError("bad")

    with pytest.raises(RecordingError):
        cli.run(main)
    assert seen == [["--name", "x"]]  # main never sees --debug
    monkeypatch.setattr(sys, "argv", ["script.py"])
    with pytest.raises(SystemExit) as done:
        cli.run(lambda: {"summary": 1})
    assert done.value.code == 0
