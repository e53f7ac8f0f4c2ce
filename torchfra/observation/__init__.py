"""What a camera and a pressure sensor record, and how the model is seen by them.

- :class:`Recording` (:mod:`~torchfra.observation.recording`): frames x points of in-plane
  displacements ``(uy, uz)`` in mm with the frames' times and pressures (MPa), missing values NaN;
- :class:`ObservationOperator` (:mod:`~torchfra.observation.operator`): the sparse map from the
  model's nodal displacements to displacements at the recording's points on the visible faces;
- :func:`register` (:mod:`~torchfra.observation.registration`): the rigid (or similarity) transform
  that puts a camera's points onto the model's face.

Reading and writing recordings as files is :mod:`torchfra.io.recordings`.
"""
from torchfra.observation.operator import ObservationError, ObservationOperator, regular_grid, visible_faces
from torchfra.observation.recording import Recording, RecordingError, from_table, to_table
from torchfra.observation.registration import Registration, RegistrationError, register

__all__ = ["ObservationError", "ObservationOperator", "Recording", "RecordingError", "Registration",
           "RegistrationError", "from_table", "regular_grid", "register", "to_table", "visible_faces"]
