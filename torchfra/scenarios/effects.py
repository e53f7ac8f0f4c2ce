"""The proof suite's concealed effects: each effect's knob, null, admissible range and tabled sizes, the
right answer a diagnosis must give, and the model that carries it (a library candidate of
:mod:`torchfra.actuator.candidates`, or physics outside the library)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.fem.materials import Material, ParameterError

PRESSURE_MAX = 0.022  # MPa, the largest recorded pressure (paper §4)


VISCO_TAU1 = 0.1  # relaxation time of the viscoelastic scenarios, in units of the trace's duration


BASE_REGION_HEIGHT = 10.0  # mm: stiff_base_region covers the elements with centroid z below this


DEBOND_CENTRE = 30.0  # mm: z of the middle of the debonded fiber stretch


DEBOND_MODULUS = 31.0  # MPa, what the debonded stretch still carries


SENSOR_GAIN = 1.0  # pressure_sensor: true = SENSOR_GAIN * recorded + offset


@dataclass(frozen=True)
class Effect:
    """One concealed effect: its knob (``parameter`` in ``unit``), the knob's ``null`` (the base model),
    the admissible range ``[low, high]``, the tabled ``sizes`` 1..n and their SNR at resolution 1."""

    name: str
    kind: str  # "null", "library" or "outside"
    parameter: str
    unit: str
    null: float
    low: float
    high: float
    sizes: tuple[float, ...]
    snr: tuple[float, ...]
    trace: str = "ramp"

    @property
    def expected(self) -> str:
        """The diagnosis' right answer: "none", the candidate's name, or "unexplained"."""
        return {"null": "none", "outside": "unexplained"}.get(self.kind, self.name)


# gravity's SNR at resolution 1 with the weight before the reference image, against the base model seen
# at the recording's points (studies/gravity_reference.py, studies/results/study_gravity_reference.json)
SNR_GRAVITY = (5.17, 14.04, 50.52)

EFFECTS = {e.name: e for e in (
    Effect("none", "null", "-", "-", 0.0, 0.0, 0.0, (), ()),
    Effect("mooney_rivlin", "library", "C01", "MPa", 0.0, 0.0, math.inf,
           (7e-05, 0.0002, 0.0007), (5.3, 14.77, 47.35)),
    Effect("compressibility", "library", "bulk_ratio", "1", BULK_RATIO, 1e-3, math.inf,
           (30.0, 8.0, 3.0), (5.65, 17.48, 27.27)),
    Effect("fiber_stiffness", "library", "E_fiber", "MPa", E_FIBER, 1e-3, math.inf,
           (250.0, 60.0, 25.0), (4.78, 19.38, 50.43)),
    Effect("gravity", "library", "density", "t/mm^3", 0.0, 0.0, 2.5e-8, (3.5e-11, 1e-10, 4e-10), SNR_GRAVITY),
    Effect("compliant_base", "library", "c", "mm^3/N", 0.0, 0.0, math.inf,
           (1000.0, 2500.0, 25000.0), (2.04, 2.55, 2.98)),
    Effect("pressure_sensor", "library", "pressure_offset", "MPa", 0.0, 0.0, PRESSURE_MAX,
           (0.00015, 0.0005, 0.0015), (4.93, 16.49, 49.99)),
    Effect("cavity_offset", "library", "delta_y", "mm", 0.0, -1.0, 0.5, (-0.25, -0.5, -1.0), (6.84, 14.55, 33.19)),
    Effect("viscoelasticity", "library", "g1", "1", 0.0, 0.0, 0.95, (0.05, 0.15, 0.4), (6.55, 21.19, 69.6),
           trace="cycle"),
    Effect("stiff_base_region", "outside", "C10_factor", "1", 1.0, 1.0, math.inf,
           (1.2, 2.0, 6.0), (5.87, 18.4, 34.72)),
    Effect("fiber_debond", "outside", "length", "mm", 0.0, 0.0, 40.0, (12.0, 20.0, 28.0), (6.13, 11.09, 21.19)),
    Effect("sensor_lag", "outside", "tau", "1", 0.0, 0.0, 0.5,
           (0.004, 0.012, 0.035), (5.71, 17.12, 49.91), trace="cycle"),
)}


def is_correct(effect: str, decision: str) -> bool:
    """Whether a diagnosis ``decision`` names ``effect`` right: the candidate's name (or, for the
    pressure sensor, a group holding it, since its gain is confounded with C10), "none" on a null,
    "unexplained" on an effect outside the library."""
    expected = _effect(effect).expected
    if effect == "pressure_sensor":
        return expected in decision.split("|")
    return decision == expected


class RenamedMaterial(Material):
    """``material`` with some parameters under other names (``names``: own name -> new name), so that
    two bodies of one model carry distinct values, e.g. ``C10`` and ``C10_base``. Same energy,
    stress and tangent (every call is passed through with the parameters renamed back)."""

    def __init__(self, material: Material, names: dict[str, str]):
        self.material, self.names = material, dict(names)
        self.param_names = tuple(self.names.get(n, n) for n in material.param_names)

    def _own(self, prm):
        return {n: prm[self.names.get(n, n)] for n in self.material.param_names}

    def validate(self, params):
        missing = [n for n in self.param_names if n not in params]
        if missing:
            raise ParameterError(f"material {type(self.material).__name__} (renamed) needs parameters {missing}; "
                                 f"got {sorted(params)}")
        try:
            self.material.validate(self._own(params))
        except ParameterError as exc:
            raise ParameterError(f"{exc} (named {self.names} in this body)") from exc

    def psi(self, F, p, prm):
        return self.material.psi(F, p, self._own(prm))

    def derivatives(self, F, p, prm, with_energy: bool = False, tangent: bool = True):
        return self.material.derivatives(F, p, self._own(prm), with_energy, tangent)

    def pressure_coefficients(self, F, prm):
        return self.material.pressure_coefficients(F, self._own(prm))

    def pressure_gradient(self, F, p, prm):
        return self.material.pressure_gradient(F, p, self._own(prm))


def _effect(name: str) -> Effect:
    if name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; valid effects: {', '.join(EFFECTS)}")
    return EFFECTS[name]


def knob_value(effect: str, size) -> float:
    """The knob's value of ``size``: an int k picks the tabled size (0: the null), a float is the value
    itself (in the effect's unit); anything else raises ValueError listing the valid sizes."""
    e = _effect(effect)
    tabled = "".join(f", {k + 1} ({v:g} {e.unit})" for k, v in enumerate(e.sizes))
    valid = f"valid sizes of {effect!r}: 0 (null){tabled}, or a value in [{e.low:g}, {e.high:g}] {e.unit}"
    if isinstance(size, (bool, np.bool_)) or not isinstance(size, (int, float, np.integer, np.floating)):
        raise ValueError(f"size {size!r} of effect {effect!r} is neither a size number nor a value; {valid}")
    if isinstance(size, (int, np.integer)):
        if not 0 <= size <= len(e.sizes):
            raise ValueError(f"unknown size {size} of effect {effect!r}; {valid}")
        return e.null if size == 0 else e.sizes[size - 1]
    if effect == "none" and size != 0:
        raise ValueError(f"the null effect 'none' has no knob, got size {size!r}; {valid}")
    if not (math.isfinite(size) and e.low <= size <= e.high):
        raise ValueError(f"size {size!r} of effect {effect!r} is outside its admissible range "
                         f"[{e.low:g}, {e.high:g}] {e.unit}; {valid}")
    return float(size)


def model_parameters(effect: str, value: float, c10: float) -> dict[str, float]:
    """FE parameters (name -> value) of the scenario's model, without the pressure ``P``."""
    p = {"C10": c10, "D1": 1.0 / (BULK_RATIO * c10), "E_fiber": E_FIBER}
    if effect == "mooney_rivlin":
        p["C01"] = value
    elif effect == "compressibility":
        p["D1"] = 1.0 / (value * c10)
    elif effect == "fiber_stiffness":
        p["E_fiber"] = value
    elif effect == "gravity":
        p["density"] = value
    elif effect == "compliant_base":
        p["c_n"] = p["c_t"] = value
    elif effect == "cavity_offset":
        p["delta_y"] = value
    elif effect == "stiff_base_region":
        p["C10_base"] = value * c10
        p["D1_base"] = 1.0 / (BULK_RATIO * value * c10)
    elif effect == "fiber_debond":
        p["E_fiber_debond"] = DEBOND_MODULUS
    return p


def build_model(effect: str, value: float, resolution: int, **model_kw):
    """The actuator at ``resolution`` with ``effect`` switched on (the effect is not null); returns
    ``(model, info)`` unfinalized, as ``build_actuator_model`` (``model_kw``: its ``formulation`` and
    ``integration``)."""
    geom = ActuatorGeometry(resolution=resolution)
    kw = dict(model_kw)
    if effect == "mooney_rivlin":
        kw["material"] = fem.MooneyRivlin()
    elif effect == "gravity":
        kw["gravity"] = (0.0, -1.0, 0.0)
    elif effect == "compliant_base":
        kw["base"] = "compliant"
    elif effect == "cavity_offset":
        kw["cavity_offset"] = True
    elif effect == "fiber_debond":
        lo, hi = DEBOND_CENTRE - value / 2, DEBOND_CENTRE + value / 2
        kw["fiber_modulus"] = lambda c: np.where((c[:, 2] > lo) & (c[:, 2] < hi), "E_fiber_debond", "E_fiber")
    model, info = build_actuator_model(geom, **kw)
    if effect == "viscoelasticity":
        fem.with_viscoelasticity(model)
    if effect == "stiff_base_region":
        centroid_z = info["mesh"].nodes[info["mesh"].elements[:, :8]].mean(1)[:, 2]
        stiff = centroid_z < BASE_REGION_HEIGHT
        k = next(k for k, t in enumerate(model.terms) if isinstance(t, fem.Hex20Solid))
        body = model.terms[k]
        model.terms[k] = fem.Hex20Solid(model.mesh, body.material, body.formulation, np.flatnonzero(~stiff),
                                        body.integration)
        model.terms.insert(k + 1, fem.Hex20Solid(
            model.mesh, RenamedMaterial(body.material, {"C10": "C10_base", "D1": "D1_base"}), body.formulation,
            np.flatnonzero(stiff), body.integration))
    return model, info

