"""torchfra: ensemble finite element models of soft fiber-reinforced actuators, calibrated from DIC recordings.

The wings, each importing only those below it (``torchfra/LAYERS.txt``): :mod:`torchfra.cli` (the
``torchfra`` command), :mod:`torchfra.scenarios` (the diagnosis's proof suite), :mod:`torchfra.diagnosis`
(missing physics), :mod:`torchfra.report` (figures, TensorBoard), :mod:`torchfra.calibration` (prior
ensembles and posteriors), :mod:`torchfra.actuator` (the paper's actuator, the candidate registry, a
user's deck), :mod:`torchfra.io` (files in and out), :mod:`torchfra.observation` (recordings, the
camera's view), :mod:`torchfra.verification`, :mod:`torchfra.fem` (ensemble-batched finite elements);
:mod:`torchfra.assimilation` (ensemble Kalman analysis and filters) and :mod:`torchfra.runtime` stand alone.
:func:`torchfra.calibrate` and :func:`torchfra.diagnose` (:mod:`torchfra.api`) are the estimators a Python
user calls. Importing torchfra changes nothing in the host process; the commands tune its allocator
(:mod:`torchfra.runtime.allocator`).
"""
__version__ = "0.1.0"

__all__ = ["calibrate", "diagnose"]


def __getattr__(name: str):
    # the estimators (torchfra.api) load torch and the wings on first use, not on ``import torchfra``
    if name in ("calibrate", "diagnose", "CalibrationResult", "DiagnosisResult", "ParameterPosterior"):
        from torchfra import api

        return getattr(api, name)
    raise AttributeError(f"module 'torchfra' has no attribute {name!r}")
