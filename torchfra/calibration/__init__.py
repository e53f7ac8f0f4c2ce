"""Calibration from recordings: prior ensembles through the FE model, and the four posteriors.

- :mod:`~torchfra.calibration.priors`: uncertain parameters as data (:class:`ParameterSet`, priors
  ``NAME=KIND:A,B``, TOML files);
- :mod:`~torchfra.calibration.forward`: the prior ensemble through the model (:func:`run_forward`,
  resumable per member, shared over torchrun ranks; reduced-basis members by default);
- :mod:`~torchfra.calibration.experiment`: the calibration experiment (:func:`run_calibration`): the
  hierarchical filter with linear and polynomial slaves, the restart filter, the exact posterior.
"""
from torchfra.calibration.config import SEED, CalibrationConfig, ForwardConfig
from torchfra.calibration.experiment import run_calibration
from torchfra.calibration.forward import run_forward
from torchfra.calibration.priors import ParameterSet, Prior, PriorError, read_parameter_file
from torchfra.calibration.synthetic import synthetic_recording

__all__ = ["SEED", "CalibrationConfig", "ForwardConfig", "ParameterSet", "Prior", "PriorError", "read_parameter_file",
           "run_calibration", "run_forward", "synthetic_recording"]
