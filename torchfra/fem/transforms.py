"""Changes to an unfinalized model that swap one of its terms for another: the way a candidate
physics that is not a term of its own (a second invariant, a pressure sensor) is switched on."""
from __future__ import annotations

from torchfra.fem.materials import Material
from torchfra.fem.model import Model
from torchfra.fem.pressure import CavityPressure
from torchfra.fem.sensor import SensorCavityPressure
from torchfra.fem.solid import Hex20Solid


def _unfinalized(model: Model) -> None:
    if model.dofmap is not None:
        raise RuntimeError("the model is finalized; swap terms before the first solve or evaluation")


def with_material(model: Model, material: Material) -> Model:
    """Give every solid body of an unfinalized model ``material`` (same elements, formulation and
    integration); returns the model."""
    _unfinalized(model)
    for k, t in enumerate(model.terms):
        if isinstance(t, Hex20Solid):
            model.terms[k] = Hex20Solid(model.mesh, material, t.formulation, t.element_ids, t.integration,
                                        dtype=model.dtype)
    return model


def with_pressure_sensor(model: Model, gain: str = "pressure_gain", offset: str = "pressure_offset") -> Model:
    """Replace every ``CavityPressure`` of an unfinalized model by a ``SensorCavityPressure`` on the same
    cavity, recorded-pressure parameter and face rule; returns the model."""
    _unfinalized(model)
    for k, t in enumerate(model.terms):
        if type(t) is CavityPressure:
            rule = round(t.w.numel() ** 0.5)
            model.terms[k] = SensorCavityPressure(model.mesh, t.face_set, t.pressure, gain, offset, rule,
                                                  dtype=model.dtype)
    return model
