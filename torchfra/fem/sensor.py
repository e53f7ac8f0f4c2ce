"""Cavity pressure read by a sensor with gain and offset (pressure-sensor candidate).

The sensor records ``P_rec``; the cavity holds the true pressure

    P_true = gain * P_rec + offset      (gain dimensionless, offset in MPa),

and the term is the conservative cavity potential of :class:`CavityPressure` at the true pressure,

    W(u) = -lambda (gain P + offset) (V(u) - V0),

with ``P`` the recorded pressure at load factor 1. The load path is linear in the true pressure
from rest (lambda = 0, true pressure 0) to ``gain P + offset`` (lambda = 1), so a frame recorded
at ``P_rec`` lies at ``lambda = (gain P_rec + offset) / (gain P + offset)``
(``SensorCavityPressure.load_factor_of``); with ``offset = 0`` that is ``P_rec / P``, as for the
plain cavity pressure. Nulls: gain 1, offset 0 (exactly :class:`CavityPressure`).

For an incompressible Neo-Hookean body (or K proportional to C10) with rigid fibers (or fiber
moduli proportional to C10) the displacements depend on ``P_true / C10`` only, so the gain is
confounded with C10: ``u(gain, C10) = u(1, C10 / gain)``.
"""
from __future__ import annotations

import math

import torch

from torchfra.fem.mesh import Mesh
from torchfra.fem.params import ParameterInfo, check_parameters
from torchfra.fem.pressure import CavityPressure


class SensorCavityPressure(CavityPressure):
    """Conservative cavity pressure at the true pressure ``gain * P + offset`` (MPa).

    pressure, gain, offset: parameter names of the recorded pressure at load factor 1 (MPa), the
    sensor gain (1) and offset (MPa).
    """

    parameters = {
        "pressure_gain": ParameterInfo("pressure_gain", "1", 1.0, 0.0, math.inf,
                                       "true / recorded pressure slope of the sensor", low_inclusive=False),
        "pressure_offset": ParameterInfo("pressure_offset", "MPa", 0.0, -math.inf, math.inf,
                                         "true pressure when the sensor reads 0"),
    }

    def __init__(self, mesh: Mesh, face_set: str, pressure: str = "P", gain: str = "pressure_gain",
                 offset: str = "pressure_offset", quadrature: int = 3, dtype=torch.float64):
        super().__init__(mesh, face_set, pressure, quadrature, dtype)
        self.gain, self.offset = gain, offset
        self.param_names = (pressure, gain, offset)
        self.parameters = {gain: SensorCavityPressure.parameters["pressure_gain"].renamed(gain),
                           offset: SensorCavityPressure.parameters["pressure_offset"].renamed(offset)}

    def validate(self, params):
        super().validate(params)
        check_parameters(self.parameters, params, "SensorCavityPressure")

    def true_pressure(self, params) -> torch.Tensor:
        """``gain * P + offset`` at load factor 1, (N,) MPa."""
        return params[self.gain] * params[self.pressure] + params[self.offset]

    def load_factor_of(self, recorded, params) -> torch.Tensor:
        """Load factor of frames recorded at pressure ``recorded`` (..., N) MPa: ``(gain P_rec + offset) /
        (gain P + offset)``."""
        recorded = torch.as_tensor(recorded, dtype=params[self.pressure].dtype)
        return (params[self.gain] * recorded + params[self.offset]) / self.true_pressure(params)

    def _scale(self, params, load_factor):
        return load_factor * self.true_pressure(params)
