"""Every file a user hands in goes through one reading layer (torchfra.io.files): a missing path, a
folder, a FIFO, a device (or a link to one), an oversized, binary or UTF-16 file is refused with the
file's name and what to do, before anything is parsed. A FIFO must be refused from its stat: opening
it would block until a writer comes; /dev/zero would be read forever."""
import os
import re
import threading

import pytest

from torchfra.calibration.priors import PriorError, read_parameter_file
from torchfra.io.abaqus import InpError, read_inp
from torchfra.io.dic.exports import read_frame, read_landmarks
from torchfra.io.files import InputFileError, check_regular, read_bytes, read_text
from torchfra.io.pressure_trace import read_pressure_trace
from torchfra.io.recordings import read_recording
from torchfra.io.tables import DicError, read_lines
from torchfra.observation.recording import RecordingError


def _fifo(path):
    """A named pipe with a writer thread that comes anyway, so that a reader that opens it blocking
    fails the test instead of hanging it."""
    os.mkfifo(path)

    def writer():
        try:
            fd = os.open(path, os.O_WRONLY)
            os.close(fd)
        except OSError:
            pass

    threading.Thread(target=writer, daemon=True).start()


HOSTILE = [
    ("missing", lambda p: None, "no such parameter file"),
    ("folder", lambda p: p.mkdir(), "is a folder, not a parameter file"),
    ("fifo", _fifo, "is a FIFO \\(named pipe\\), not a regular file"),
    ("zero", lambda p: p.symlink_to("/dev/zero"), "is a device \\(a link to /dev/zero\\), not a regular file"),
    ("dangling", lambda p: p.symlink_to(p.parent / "gone"), "no such parameter file \\(a link to a path that"),
    ("utf16", lambda p: p.write_bytes("[parameters]\n".encode("utf-16")), "UTF-16 text; it is read as utf-8"),
    ("binary", lambda p: p.write_bytes(b"[parameters]\n\x00\x01\x02"), "line 2: NUL bytes: a binary file, not "
                                                                        "parameter text \\(utf-8 expected\\)"),
    ("latin1", lambda p: p.write_bytes("C10 = 1 # µ\n".encode("latin-1")), "line 1: byte 0xb5 at column 11 is not "
                                                                            "utf-8 text"),
    ("big", lambda p: p.write_bytes(b"#" * 101), "101 bytes, over the limit of 100 bytes"),
]


@pytest.mark.parametrize("name, make, match", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_the_layer_refuses_what_is_not_a_bounded_text_file(tmp_path, name, make, match):
    path = tmp_path / name
    make(path)
    with pytest.raises(InputFileError, match=match) as info:
        read_text(path, what="parameter", max_bytes=100)
    assert str(path) in str(info.value)


def test_the_layer_reads_a_regular_file_and_a_link_to_one_and_counts_lines(tmp_path):
    path = tmp_path / "a.txt"
    path.write_bytes(b"\xef\xbb\xbfone\ntwo\n")  # a UTF-8 byte-order mark is skipped
    (tmp_path / "link.txt").symlink_to(path)
    assert read_text(tmp_path / "link.txt", what="x", max_bytes=100) == "one\ntwo\n"
    assert check_regular(path, "x") == path
    assert read_bytes(path, "x", max_bytes=100) == b"\xef\xbb\xbfone\ntwo\n"
    with pytest.raises(InputFileError, match="3 lines, over the limit of 2 lines"):
        path.write_text("a\nb\nc")
        read_text(path, what="x", max_lines=2)


@pytest.mark.parametrize("make, match", [
    (lambda p: None, "no such {what} file"),
    (_fifo, "FIFO \\(named pipe\\), not a regular file"),
    (lambda p: p.symlink_to("/dev/zero"), "a device .*not a regular file"),
    (lambda p: p.mkdir(), "is a folder"),
    (lambda p: p.write_bytes("x".encode("utf-16")), "UTF-16"),
    (lambda p: p.write_bytes(b"\x00\x00*NODE\n"), "NUL bytes"),
], ids=["missing", "fifo", "device", "folder", "utf16", "binary"])
@pytest.mark.parametrize("reader, error, what, suffix", [
    (read_recording, RecordingError, "recording", ".csv"),
    (read_pressure_trace, DicError, "pressure trace", ".csv"),
    (read_lines, DicError, "DIC export", ".csv"),
    (read_parameter_file, PriorError, "parameter", ".toml"),
    (read_inp, InpError, "deck", ".inp"),
], ids=["recording", "trace", "dic", "toml", "deck"])
def test_every_reader_goes_through_the_layer(tmp_path, make, match, reader, error, what, suffix):
    """Each reader raises its own error type, naming the file, for each hostile kind of path."""
    path = tmp_path / ("f" + suffix)
    make(path)
    if reader is read_recording and "UTF-16" in match:
        match = "UTF-16"
    if reader is read_recording and "NUL" in match:
        match = "NUL bytes"
    with pytest.raises(error, match=match.format(what=what)) as info:
        reader(path)
    assert str(path) in str(info.value)


def test_a_deck_named_on_the_command_line_that_is_a_device_is_not_called_missing(tmp_path):
    from torchfra.actuator.deck import read_deck

    with pytest.raises(ValueError, match="--inp /dev/zero: is a device, not a regular file"):
        read_deck("/dev/zero")
    with pytest.raises(ValueError, match="no such deck file"):
        read_deck(tmp_path / "nope.inp")


@pytest.mark.parametrize("reader, what", [
    (lambda p: read_frame(p), "DIC frame"),
    (lambda p: read_landmarks(p, None), "landmark"),  # refused before the series is looked at
], ids=["frame", "landmarks"])
def test_dic_frames_and_landmark_files_are_opened_through_the_layer(tmp_path, reader, what):
    _fifo(tmp_path / "pipe.csv")
    with pytest.raises(DicError, match="pipe.csv: is a FIFO \\(named pipe\\), not a regular file"):
        reader(tmp_path / "pipe.csv")
    with pytest.raises(DicError, match=f"gone.csv: no such {what} file"):
        reader(tmp_path / "gone.csv")
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    with pytest.raises(DicError, match="zero.csv: is a device \\(a link to /dev/zero\\), not a regular file"):
        reader(tmp_path / "zero.csv")


@pytest.mark.parametrize("command", ["forward", "calibrate"])
def test_inp_that_is_a_device_or_fifo_is_refused_by_the_command(tmp_path, command):
    """``torchfra <command> --inp /dev/zero`` (or a FIFO) as a user runs it: exit 2, "not a regular
    file" (not "no such deck file"), no run folder."""
    import subprocess
    import sys
    from pathlib import Path

    _fifo(tmp_path / "pipe.inp")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), OMP_NUM_THREADS="1")
    for deck, kind in (("/dev/zero", "a device"), ("pipe.inp", "a FIFO \\(named pipe\\)")):
        out = subprocess.run([sys.executable, "-m", "torchfra", command, "--inp", deck, "--param",
                              "C10=lognormal:0.1,0.03"], cwd=tmp_path, env=env, capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 2, out.stderr
        assert re.search(f"error: --inp {deck}: is {kind}, not a regular file", out.stderr), out.stderr
        assert "Traceback" not in out.stderr and not (tmp_path / "runs" / "forward_cache").exists()
