"""``*INCLUDE, INPUT=`` reads only below the deck's folder (or folders the caller allows with
``include_dirs=``), through the bounded reading layer, and never quotes an included file's text."""
import os
import re
import threading

import pytest
from test_read_inp import HAND_DECK

from torchfra.io.abaqus.read import InpError, read_inp

def _deck(folder, include: str):
    """The hand-written deck with its material block moved to the file ``include`` names."""
    head, tail = HAND_DECK.split("*Material, name=SILICONE\n*Hyperelastic, neo hooke\n0.1, 0.02\n")
    deck = folder / "deck.inp"
    deck.write_text(head + f"*Include, input={include}\n" + tail)
    line = deck.read_text().splitlines().index(f"*Include, input={include}") + 1
    return deck, line


MATERIAL = "*Material, name=SILICONE\n*Hyperelastic, neo hooke\n0.1, 0.02\n"


def test_an_include_below_the_deck_reads_and_one_outside_it_is_refused(tmp_path):
    (tmp_path / "model" / "parts").mkdir(parents=True)
    (tmp_path / "model" / "parts" / "material.inp").write_text(MATERIAL)
    (tmp_path / "outside.inp").write_text(MATERIAL)
    deck, _ = _deck(tmp_path / "model", "parts/material.inp")
    assert read_inp(deck)[1] == {"C10": 0.1, "D1": 0.02, "P": 0.001}
    for include in ("../outside.inp", str(tmp_path / "outside.inp"), "parts/../../outside.inp"):
        deck, line = _deck(tmp_path / "model", include)
        with pytest.raises(InpError, match=re.escape(f"{deck}, line {line}: *INCLUDE: INPUT={include} is "
                                                     f"{tmp_path / 'outside.inp'}, outside the deck's folder")):
            read_inp(deck)
        assert read_inp(deck, include_dirs=[tmp_path])[1]["C10"] == 0.1  # allowed explicitly


def test_a_link_out_of_the_deck_folder_is_refused(tmp_path):
    (tmp_path / "model").mkdir()
    (tmp_path / "elsewhere.inp").write_text(MATERIAL)
    (tmp_path / "model" / "material.inp").symlink_to(tmp_path / "elsewhere.inp")
    deck, line = _deck(tmp_path / "model", "material.inp")
    with pytest.raises(InpError, match=f"line {line}: \\*INCLUDE: INPUT=material.inp is .*elsewhere.inp, outside"):
        read_inp(deck)


def _fifo(path):
    os.mkfifo(path)

    def writer():  # comes anyway, so that a reader that opens the FIFO blocking fails instead of hanging
        try:
            os.close(os.open(path, os.O_WRONLY))
        except OSError:
            pass

    threading.Thread(target=writer, daemon=True).start()


def test_devices_and_fifos_are_refused_by_the_reading_layer(tmp_path):
    deck, line = _deck(tmp_path, "/dev/zero")
    with pytest.raises(InpError, match=f"line {line}: \\*INCLUDE: INPUT=/dev/zero is /dev/zero, outside"):
        read_inp(deck)
    with pytest.raises(InpError, match="/dev/zero: is a device, not a regular file"):
        read_inp(deck, include_dirs=["/dev"])
    _fifo(tmp_path / "pipe.inp")
    deck, _ = _deck(tmp_path, "pipe.inp")
    with pytest.raises(InpError, match="pipe.inp: is a FIFO \\(named pipe\\), not a regular file"):
        read_inp(deck)


@pytest.mark.parametrize("content, match", [
    (b"SECRET-1234, x, y\n", "must be an integer, got \\(text of an included file, not shown\\)"),
    ("*Material, name=SILICONE\n*Hyperelastic, neo hooke\nSECRET-1234, 0.02\n".encode(),
     "must be a number, got \\(text of an included file, not shown\\)"),
    ("SECRET-1234\n".encode("utf-16"), "UTF-16 text"),
    (b"SECRET-1234\x00\x00", "NUL bytes: a binary file, not deck text"),
    ("SECRET-\xb5\n".encode("latin-1"), "byte 0xb5 at column 8 is not utf-8 text"),
    (b"SECRET-1234\n", "node set \\(a name in an included file, not shown\\) is not defined"),
], ids=["integer", "number", "utf16", "binary", "latin1", "set-name"])
def test_an_included_files_text_is_never_quoted(tmp_path, content, match):
    """The included file may be no deck at all (a key, a password file): a message names it and its
    line, never its text."""
    (tmp_path / "inc.txt").write_bytes(content)
    text = HAND_DECK
    if content == b"SECRET-1234\n":  # a data line of the *NSET card before the *INCLUDE: a set name
        text = text.replace("*Nset, nset=Tip, generate\n301, 308\n", "*Nset, nset=Tip\n*Include, input=inc.txt\n")
    elif b"Material" in content:
        text = text.replace(MATERIAL, "*Include, input=inc.txt\n")
    else:  # data lines of an included file go on the card before the *INCLUDE (a *NODE here)
        text = text.replace("*node\n", "*node\n*Include, input=inc.txt\n", 1)
    (tmp_path / "deck.inp").write_text(text)
    with pytest.raises(InpError, match=match) as info:
        read_inp(tmp_path / "deck.inp")
    assert "SECRET" not in str(info.value) and str(tmp_path / "inc.txt") in str(info.value)


def test_a_deck_that_starts_with_an_included_non_deck_names_the_line_only(tmp_path):
    (tmp_path / "inc.txt").write_text("SECRET-1234\n")
    (tmp_path / "deck.inp").write_text("*Include, input=inc.txt\n" + HAND_DECK)
    with pytest.raises(InpError, match="inc.txt, line 1: data line before the first keyword; a deck starts") as info:
        read_inp(tmp_path / "deck.inp")
    assert "SECRET" not in str(info.value)
