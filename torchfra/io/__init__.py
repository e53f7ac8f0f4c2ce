"""Files a user hands in or gets out: recordings, DIC exports, pressure traces, Abaqus/CalculiX decks, VTU.

- :func:`read_recording`, :func:`write_recording` (:mod:`~torchfra.io.recordings`): the recording
  CSV/NPZ format, read defensively;
- :mod:`torchfra.io.dic`: MatchID, VIC-3D, DICe and generic point-cloud exports, turned into a
  recording on the model's face (:func:`~torchfra.io.dic.import_export`);
- :func:`read_pressure_trace` (:mod:`~torchfra.io.pressure_trace`): the pressure sensor's log;
- :mod:`torchfra.io.abaqus`: :func:`~torchfra.io.abaqus.read_inp` (a deck into a model),
  :func:`~torchfra.io.abaqus.write_inp` (a model into a deck), :func:`~torchfra.io.abaqus.run_calculix`;
- :func:`write_vtu` (:mod:`~torchfra.io.vtu`): solutions for ParaView.
"""
# imported on first use: `torchfra <subcommand> --help` reads the flags without loading torch
_WHERE = {
    "read_inp": "torchfra.io.abaqus",
    "write_inp": "torchfra.io.abaqus",
    "read_pressure_trace": "torchfra.io.pressure_trace",
    "read_recording": "torchfra.io.recordings",
    "write_recording": "torchfra.io.recordings",
    "write_vtu": "torchfra.io.vtu",
}

__all__ = ["read_inp", "read_pressure_trace", "read_recording", "write_inp", "write_recording", "write_vtu"]


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
