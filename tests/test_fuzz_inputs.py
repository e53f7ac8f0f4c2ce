"""Fuzzing the deck reader and the parameter-file reader: whatever the bytes, read_inp returns a model
or raises InpError, read_parameter_file returns its entries or raises PriorError, each message naming
the file (never another exception), and what is accepted is what the file says: the deck's material
constants, pressure and node coordinates as a plain reading of its lines gives them, the parameter
file's entries as tomllib (the reference TOML parser) reads them."""
import math
import os
import re
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_fuzz_recordings import _edits
from test_read_inp import HAND_DECK

from torchfra.calibration.priors import PriorError, read_parameter_file
from torchfra.io.abaqus.read import InpError, read_inp

FUZZ = settings(max_examples=int(os.environ.get("FUZZ_N", 40)), deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
# FUZZ_N=1500 hunts longer (measured: every test passes at 1500 examples)
DECK = HAND_DECK.replace("type=C3D20RH", "type=C3D20H").encode()


def _read_deck(path):
    try:
        return read_inp(path, with_ids=True)
    except InpError as exc:
        assert str(path) in str(exc), f"the message does not name the file: {exc}"
        return None  # any other exception fails the test


def _plain_deck(data: bytes):
    """The deck as a person reads it: the node lines under *NODE, the two numbers under *HYPERELASTIC,
    the magnitude of the *DLOAD line; None where the text is not plainly that."""
    try:
        lines = [ln.strip() for ln in data.decode("utf-8").splitlines()]
    except UnicodeDecodeError:
        return None
    nodes, keyword, found = {}, None, {}
    for ln in lines:
        if not ln or ln.startswith("**"):
            continue
        if ln.startswith("*"):
            keyword = ln[1:].split(",")[0].strip().upper()
            continue
        fields = [f.strip() for f in ln.split(",")]
        try:
            if keyword == "NODE":
                nodes[int(fields[0])] = [float(f or 0) for f in fields[1:4]]
            elif keyword == "HYPERELASTIC":
                found.setdefault("material", [float(f) for f in fields if f])
            elif keyword == "DLOAD":
                found.setdefault("P", float(fields[2]))
        except (ValueError, IndexError):
            return None
    return nodes, found


def _check_deck(result, data: bytes):
    model, params, ids = result
    plain = _plain_deck(data)
    assert plain is not None, "accepted a deck whose lines are not plainly nodes and numbers"
    nodes, found = plain
    for i, node in enumerate(ids.nodes[: model.mesh.n_nodes]):
        assert np.allclose(model.X[i], nodes[int(node)], rtol=0, atol=0), f"node {node} moved"
    if "material" in found and len(found["material"]) == 2:
        assert [params["C10"], params["D1"]] == found["material"]
    if "P" in found and "P" in params:
        assert params["P"] == found["P"]


@FUZZ
@given(st.data())
def test_edited_deck_is_refused_or_read_as_written(tmp_path, data):
    edited = data.draw(_edits(DECK))
    path = tmp_path / "edited.inp"
    path.write_bytes(edited)
    result = _read_deck(path)
    if result is not None:
        _check_deck(result, edited)


_DECK_BYTES = st.one_of(st.sampled_from([bytes([c]) for c in b"*,=\n\r 0123456789.-eE"]),
                        st.sampled_from([b"*NODE", b"*ELEMENT, TYPE=C3D20H", b"*INCLUDE, INPUT=", b"*PART, NAME=P",
                                         b"*INSTANCE, NAME=I, PART=P", b"*ASSEMBLY", b"*END ASSEMBLY", b"/dev/zero",
                                         b"../x.inp", b"*MATERIAL, NAME=M", b"*DENSITY", b"\x00", b"\xff\xfe"]),
                        st.binary(min_size=1, max_size=4))


@FUZZ
@given(st.lists(_DECK_BYTES, max_size=40), st.sampled_from([b"", DECK[:2000], DECK]))
def test_random_deck_bytes_are_refused_or_read_as_written(tmp_path, pieces, prefix):
    data = prefix + b"".join(pieces)
    path = tmp_path / "noise.inp"
    path.write_bytes(data)
    result = _read_deck(path)
    if result is not None:
        _check_deck(result, data)


# -- parameter files ---------------------------------------------------------------------------------------

CONFIG = (b'[parameters]\nC10 = "lognormal:0.0062,0.0011"\nE_fiber = "lognormal:31000,6000"\n'
          b"[fixed]\nC01 = 0.0\n[truth]\nC10 = 0.0048\nE_fiber = 25000\n")


def _read_config(path):
    try:
        return read_parameter_file(path)
    except PriorError as exc:
        assert str(exc).startswith(f"{path}"), f"the message does not name the file: {exc}"
        return None


def _check_config(out, data: bytes):
    """What was accepted is what tomllib reads, entry for entry."""
    ref = tomllib.loads(data.decode("utf-8"))
    assert out["parameters"] == [f"{k}={v}" for k, v in ref["parameters"].items()]
    assert out["fixed"] == [f"{k}={v}" for k, v in ref.get("fixed", {}).items()]
    assert out["truth"] == {k: float(v) for k, v in ref.get("truth", {}).items()}
    for k in [*ref["parameters"], *ref.get("fixed", {}), *ref.get("truth", {})]:
        assert re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k)
    assert all(math.isfinite(v) for v in out["truth"].values())


@FUZZ
@given(st.data())
def test_edited_parameter_file_is_refused_or_read_as_written(tmp_path, data):
    edited = data.draw(_edits(CONFIG))
    path = tmp_path / "prior.toml"
    path.write_bytes(edited)
    out = _read_config(path)
    if out is not None:
        _check_config(out, edited)


_TOML_BYTES = st.one_of(st.sampled_from([bytes([c]) for c in b'[]{}=,."\'#\n \t0123456789.eE+-_']),
                        st.sampled_from([b"[parameters]", b"[fixed]", b"[truth]", b"C10", b"E_fiber", b'" C10 "',
                                         b'"lognormal:0.0062,0.0011"', b"[[parameters]]", b"inf", b"nan", b"true",
                                         b"[" * 64, b"{a=" * 64]),
                        st.binary(min_size=1, max_size=4))


@FUZZ
@given(st.lists(_TOML_BYTES, max_size=40), st.sampled_from([b"", CONFIG]))
def test_random_parameter_file_bytes_are_refused_or_read_as_written(tmp_path, pieces, prefix):
    data = prefix + b"".join(pieces)
    path = tmp_path / "noise.toml"
    path.write_bytes(data)
    out = _read_config(path)
    if out is not None:
        _check_config(out, data)


@pytest.mark.parametrize("depth", [1000, 100_000])
def test_deep_nesting_anywhere_is_refused(tmp_path, depth):
    path = tmp_path / "deep.toml"
    path.write_bytes(CONFIG + b"[truth.x]\ny = " + b"[" * depth + b"]" * depth + b"\n")
    assert _read_config(path) is None
