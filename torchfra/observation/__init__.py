"""What a camera and a pressure sensor record, and how the model is seen by them.

- :class:`Recording` (:mod:`~torchfra.observation.recording`): frames x points of in-plane
  displacements ``(uy, uz)`` in mm with the frames' times and pressures (MPa), missing values NaN;
- :class:`ObservationOperator` (:mod:`~torchfra.observation.operator`): the sparse map from the
  model's nodal displacements to displacements at the recording's points on the visible faces;
- :func:`register` (:mod:`~torchfra.observation.registration`): the rigid (or similarity) transform
  that puts a camera's points onto the model's face.

Reading and writing recordings as files is :mod:`torchfra.io.recordings`.
"""
# imported on first use: `torchfra <subcommand> --help` reads the flags without loading torch
_WHERE = {
    "ObservationError": "torchfra.observation.operator",
    "ObservationOperator": "torchfra.observation.operator",
    "regular_grid": "torchfra.observation.operator",
    "visible_faces": "torchfra.observation.operator",
    "Recording": "torchfra.observation.recording",
    "RecordingError": "torchfra.observation.recording",
    "from_table": "torchfra.observation.recording",
    "to_table": "torchfra.observation.recording",
    "Registration": "torchfra.observation.registration",
    "RegistrationError": "torchfra.observation.registration",
    "register": "torchfra.observation.registration",
}

__all__ = ["ObservationError", "ObservationOperator", "Recording", "RecordingError", "Registration",
           "RegistrationError", "from_table", "regular_grid", "register", "to_table", "visible_faces"]


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
