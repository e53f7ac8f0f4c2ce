"""The library of candidate physics: the one registry every list of candidates and parameters derives from.

A candidate is a piece of physics the base model (the paper's actuator, or a user's deck) may leave
out. Each entry of :data:`REGISTRY` says what it adds, its parameters (each a :class:`Coordinate`:
unit, admissible range, null value at which the model is exactly the base model, and the prior the
diagnosis and the filters work with), and how it is switched on in a model (:func:`actuator_model`).
Switching one on is adding a term or swapping a term of an unfinalized model, never editing the solver:

====================  ===========================  ==============================================
candidate             parameters (null)            switched on by
====================  ===========================  ==============================================
mooney_rivlin         C01 (0) MPa                  ``fem.with_material(model, MooneyRivlin())``
compressibility       D1 (1/(1000 C10)) 1/MPa      D1 free instead of 1/(bulk_ratio C10)
fiber_stiffness       E_fiber (31000) MPa          E_fiber free (a parameter of the base model)
gravity               density (0) t/mm^3           ``model.add(Gravity(mesh, direction=...))``
compliant_base        c_n, c_t (0: clamp) mm^3/N   ``support_face(model, face, compliant=True)``
                                                   in place of ``model.clamp(face)``
pressure_sensor       pressure_gain (1),           the frames' load factors (the true pressure is
                      pressure_offset (0) MPa      ``gain * recorded + offset``)
cavity_offset         delta_y (0) mm               a morph of the reference mesh
                                                   (``build_actuator_model(cavity_offset=True)``)
fiber_pitch           fiber_pitch (2 deg drawn)    ``build_actuator_model(fiber_pitch=True)``
viscoelasticity       g1 (0), tau1                 the frames' load factors (load-level creep,
                                                   :mod:`torchfra.actuator.history`); in the FE
                                                   kernel ``fem.with_viscoelasticity``
pressure_lag          pressure_lag (0)             not physics of the body: viscoelasticity's rival
====================  ===========================  ==============================================

Parameter coordinates and priors (Gaussian in the coordinate, truncated to the admissible range):

=================  ========  ===============================  ======================  =============
parameter          coord.    prior                            null                    candidate
=================  ========  ===============================  ======================  =============
C10 (MPa)          log       log C10 ~ N(log 0.0068, 0.5^2)   (base)                  base model
C01 (MPa)          linear    N(0, 0.003^2)                    0                       mooney_rivlin
D1 (1/MPa)         log       N(log 1/(1000 C10), 2^2)         1/(1000 C10)            compressibility
E_fiber (MPa)      log       N(log 31000, 2.5^2)              31000                   fiber_stiffness
density (t/mm^3)   linear    N(0, (2e-9)^2), >= 0             0                       gravity
c_n, c_t (mm^3/N)  linear    N(0, 2^2), >= 0                  0 (clamp)               compliant_base
pressure_gain      linear    N(1, 0.2^2), > 0                 1                       pressure_sensor
pressure_offset    linear    N(0, 0.003^2) MPa                0                       pressure_sensor
delta_y (mm)       linear    N(0, 0.4^2), in [-1, 0.5]        0                       cavity_offset
fiber_pitch (deg)  linear    N(2, 0.5^2), in [1, 4]           2 (the drawn pitch)     fiber_pitch
g1 (1)             linear    N(0, 0.3^2), in [0, 0.95]        0                       viscoelasticity
tau1 (duration)    log       log tau1 ~ N(log 0.1, 1.5^2)     (none: see below)       viscoelasticity
pressure_lag       linear    N(0, 0.05^2), in [-0.2, 0.2]     0                       pressure_lag
=================  ========  ===============================  ======================  =============

``tau1`` has no null: at ``g1 = 0`` it has no effect, so the score test of the candidate is the one of
``g1`` at the prior's ``tau1`` (:data:`NUISANCE`), and a refit frees both. A compliant base is
evaluated at c = 1e-4 mm^3/N in place of its null (the clamp has no spring dofs): the base then moves
by ~1e-6 mm, far below any DIC noise.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchfra import fem
from torchfra.actuator.geometry import CAVITY_OFFSET, ActuatorGeometry, build_actuator_model
from torchfra.actuator.history import G1, LAG, TAU1
from torchfra.fem.gravity import Gravity
from torchfra.fem.helix import pitch_parameter
from torchfra.fem.materials import MooneyRivlin, NeoHookean
from torchfra.fem.params import ParameterInfo
from torchfra.fem.sensor import SensorCavityPressure
from torchfra.fem.springs import ElasticSupport

BULK_RATIO = 1000.0  # K / mu of the base model's body: D1 = 1 / (BULK_RATIO C10)
E_FIBER = 31000.0  # MPa, the cotton fibers' Young's modulus in the paper
KAPPA_T = 0.005615  # MPa, the paper's reference value of C10
C10_PRIOR_MEAN = 0.0068  # MPa, the centre of the diagnosis's prior on C10
SPRING_NULL = 1e-4  # mm^3/N: the clamp's stand-in when a compliant base is switched on
GRAVITY_DIRECTION = (0.0, -1.0, 0.0)  # the actuator lies on its side, bending in the camera's plane
FIBER_PITCH = pitch_parameter(ActuatorGeometry().pitch_deg)


@dataclass(frozen=True)
class Coordinate:
    """A free parameter: natural ``name``, coordinate ``transform`` ("log" or "linear"), Gaussian
    prior (mean, std) in the coordinate, admissible natural range, null (natural; None for the base
    model's own parameters), the candidate it belongs to.

    How the diagnosis tests it: ``secant_step`` (its sensitivity is a central secant over this step
    in the coordinate, not the exact derivative), ``far_secant`` (also tested along the secant to a
    point this many prior stds from its null: its effect changes shape as it grows), ``nuisance_of``
    (identified only away from that parameter's null: never score-tested, freed in a refit)."""

    name: str
    unit: str
    transform: str
    prior_mean: float
    prior_std: float
    low: float
    high: float
    null: float | None
    candidate: str
    secant_step: float | None = None
    far_secant: float | None = None
    nuisance_of: str | None = None

    def natural(self, z):
        return torch.exp(z) if self.transform == "log" else z

    def coordinate(self, x: float) -> float:
        return math.log(x) if self.transform == "log" else float(x)

    def clip(self, z: float) -> float:
        lo = self.coordinate(self.low) if not (self.transform == "log" and self.low <= 0) else -math.inf
        hi = self.coordinate(self.high) if math.isfinite(self.high) else math.inf
        return float(min(max(z, lo), hi))

    def log_prior_normalizer(self) -> float:
        """log of the prior mass inside the admissible range (the truncation's normalization)."""
        from scipy.stats import norm

        lo = self.coordinate(self.low) if not (self.transform == "log" and self.low <= 0) else -math.inf
        hi = self.coordinate(self.high) if math.isfinite(self.high) else math.inf
        mass = norm.cdf(hi, self.prior_mean, self.prior_std) - norm.cdf(lo, self.prior_mean, self.prior_std)
        return math.log(max(mass, 1e-300))


@dataclass(frozen=True)
class Candidate:
    """One candidate: ``name``, what physics it adds, its parameters (:class:`Coordinate`), and how it
    enters a model.

    ``build``: keyword arguments of :func:`build_actuator_model` that switch it on ({} when it needs
    no change of the model: a base-model parameter set free, or the frames' load factors);
    ``base_parameter``: its parameters are the base model's own (D1, E_fiber), given values anyway;
    ``fe_free``: its parameters act on the frames' load factors only, no FE solve depends on them;
    ``sensor``: it acts on the recorded pressure, so a forward ensemble cannot carry it (estimated by
    the diagnosis only); ``history_dependent``: it leaves a load-unload loop; ``rival_of``: not physics
    of the body but the candidate it mimics, fitted beside that one and never named;
    ``actuator_only``: why a deck cannot carry it (None: a deck can)."""

    name: str
    description: str
    parameters: tuple[Coordinate, ...]
    build: dict = field(default_factory=dict)
    base_parameter: bool = False
    fe_free: bool = False
    sensor: bool = False
    history_dependent: bool = False
    rival_of: str | None = None
    actuator_only: str | None = None

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def null_values(self) -> dict[str, float]:
        """Parameter values at which the candidate vanishes (base-model parameters have none)."""
        return {p.name: p.null for p in self.parameters if p.null is not None}


C10 = Coordinate("C10", "MPa", "log", math.log(C10_PRIOR_MEAN), 0.5, 0.0, math.inf, None, "base")

REGISTRY: dict[str, Candidate] = {c.name: c for c in (
    Candidate("mooney_rivlin", "second invariant of the body's strain energy (Mooney-Rivlin)",
              (Coordinate("C01", "MPa", "linear", 0.0, 0.003, -0.003, 0.05, 0.0, "mooney_rivlin"),),
              build={"material": "mooney_rivlin"}),
    Candidate("compressibility", "finite bulk modulus of the body, D1 free",
              (Coordinate("D1", "1/MPa", "log", math.log(1 / (BULK_RATIO * C10_PRIOR_MEAN)), 2.0, 0.0, 1e4, None,
                          "compressibility"),), base_parameter=True),
    Candidate("fiber_stiffness", "Young's modulus of the fibers (a base-model parameter, refitted)",
              # a fiber near inextensible (31 GPa) stretches where a compliant one would, but not in
              # proportion: on the actuator (resolution 1, 6 frames to 0.02 MPa, C10 projected out) the
              # derivative captures 0.27 of a 60 MPa fiber's effect and 0.23 of a 20 MPa one's, derivative
              # and secant (to 209 MPa) together 0.998 and 0.991
              # (tests/test_discovery.py::test_a_compliant_fibers_effect_lies_in_its_derivative_and_secant).
              # A bulk's compliance keeps its shape: the derivative in log D1 captures 0.96-0.99 of K/mu from
              # 100 down to 1.5, so D1 needs no secant
              (Coordinate("E_fiber", "MPa", "log", math.log(E_FIBER), 2.5, 0.0, 1e6, E_FIBER, "fiber_stiffness",
                          far_secant=-2.0),), base_parameter=True),
    Candidate("gravity", "self-weight of the body",
              (Coordinate("density", "t/mm^3", "linear", 0.0, 2e-9, 0.0, 2.5e-8, 0.0, "gravity"),),
              build={"gravity": GRAVITY_DIRECTION}),
    Candidate("compliant_base", "distributed springs under the base instead of a clamp",
              (Coordinate("c_n", "mm^3/N", "linear", 0.0, 2.0, SPRING_NULL, 1e3, 0.0, "compliant_base"),
               Coordinate("c_t", "mm^3/N", "linear", 0.0, 2.0, SPRING_NULL, 1e3, 0.0, "compliant_base")),
              build={"base": "compliant"},
              actuator_only="it puts springs under the actuator's base face instead of its clamp"),
    Candidate("pressure_sensor", "gain and offset of the pressure sensor",
              (Coordinate("pressure_gain", "1", "linear", 1.0, 0.2, 0.2, 5.0, 1.0, "pressure_sensor"),
               Coordinate("pressure_offset", "MPa", "linear", 0.0, 0.003, -0.02, 0.02, 0.0, "pressure_sensor")),
              sensor=True),
    Candidate("cavity_offset", "the cavity sits off its nominal axis along y (a misplaced mould core; a morph "
              "of the reference mesh)",
              (Coordinate("delta_y", "mm", "linear", 0.0, 0.4, CAVITY_OFFSET.low, CAVITY_OFFSET.high, 0.0,
                          "cavity_offset"),),
              build={"cavity_offset": True}, actuator_only="it moves the actuator's cavity by a morph of its mesh"),
    Candidate("fiber_pitch", "the fibers are wound at another pitch than drawn (each member's fibers embedded "
              "where they fall)",
              # a pitch change slides the fiber nodes through the bricks (~100 mm per deg at the helices'
              # ends), so the discrete model's response carries a ripple whose exact slope dwarfs the
              # physical one (on the proof suite's grid and ramp, studies/results/study_fiber_pitch.json:
              # |dY/d pitch| 1935 exact at the null against 3.8-4.3 as secants over +-0.05 to +-0.25 deg at
              # resolution 1, 249 against 2.0 at resolution 2); the secant over half the prior's std sees
              # the physics
              (Coordinate("fiber_pitch", FIBER_PITCH.unit, "linear", FIBER_PITCH.null, 0.5, FIBER_PITCH.low,
                          FIBER_PITCH.high, FIBER_PITCH.null, "fiber_pitch", secant_step=0.25),),
              build={"fiber_pitch": True}, actuator_only="it winds the actuator's fiber helices at another pitch"),
    Candidate("viscoelasticity", "the body creeps (one Prony term on the shear stress)",
              (Coordinate("g1", G1.unit, "linear", 0.0, 0.3, G1.low, G1.high, 0.0, "viscoelasticity"),
               Coordinate("tau1", TAU1.unit, "log", math.log(0.1), 1.5, TAU1.low, TAU1.high, 0.1, "viscoelasticity",
                          nuisance_of="g1")),
              fe_free=True, sensor=True, history_dependent=True),
    Candidate("pressure_lag", "the cavity's pressure lags the recorded one",
              (Coordinate("pressure_lag", LAG.unit, "linear", 0.0, 0.05, LAG.low, LAG.high, 0.0, "pressure_lag"),),
              fe_free=True, sensor=True, history_dependent=True, rival_of="viscoelasticity"),
)}

# -- what the rest of the package reads, derived from REGISTRY -----------------------------------------
COORDINATES: dict[str, Coordinate] = {"C10": C10, **{p.name: p for c in REGISTRY.values() for p in c.parameters}}
CANDIDATE_PARAMETERS: dict[str, tuple[str, ...]] = {c.name: c.parameter_names for c in REGISTRY.values()}
SECANT_STEPS = {p.name: p.secant_step for p in COORDINATES.values() if p.secant_step is not None}
FAR_SECANTS = {p.name: p.far_secant for p in COORDINATES.values() if p.far_secant is not None}
NUISANCE = {p.name: p.nuisance_of for p in COORDINATES.values() if p.nuisance_of is not None}
LOAD_MAP_ONLY = tuple(n for c in REGISTRY.values() if c.fe_free for n in c.parameter_names)
HISTORY_DEPENDENT_CANDIDATES = tuple(c.name for c in REGISTRY.values() if c.history_dependent)
RIVALS = {c.rival_of: c.name for c in REGISTRY.values() if c.rival_of is not None}
ACTUATOR_ONLY = {c.name: c.actuator_only for c in REGISTRY.values() if c.actuator_only is not None}
# the candidates a diagnosis can name (a rival is fitted beside its candidate, never named)
DIAGNOSIS_CANDIDATES = tuple(sorted(c.name for c in REGISTRY.values() if c.rival_of is None))
# parameters on the recorded pressure (the frames' load factors): a forward ensemble cannot carry them
SENSOR_PARAMETERS = {n: (c.name if c.rival_of is None else f"{c.rival_of}'s rival")
                     for c in REGISTRY.values() if c.sensor for n in c.parameter_names}
# FE model parameters a candidate adds to the base model's C10, D1, E_fiber, P
ADDED_MODEL_PARAMETERS = tuple(n for c in REGISTRY.values() if c.build for n in c.parameter_names)


def null_coordinate(name: str, c10: float) -> float:
    """The coordinate at which parameter ``name`` switches its candidate off (base-model value)."""
    if name == "D1":
        return math.log(1.0 / (BULK_RATIO * c10))
    if name in ("c_n", "c_t"):
        return SPRING_NULL
    return COORDINATES[name].coordinate(COORDINATES[name].null)


def candidates_of(names) -> tuple[str, ...]:
    """The candidates a model must switch on to carry parameters ``names`` (base-model parameters such
    as D1 and E_fiber need none)."""
    names = set(names)
    return tuple(sorted(c.name for c in REGISTRY.values() if names & set(c.parameter_names) and c.build))


def build_flags(candidates) -> dict:
    """Keyword arguments of :func:`build_actuator_model` that switch ``candidates`` on."""
    unknown = sorted(set(candidates) - set(REGISTRY))
    if unknown:
        raise ValueError(f"unknown candidate physics {unknown}; known: {sorted(REGISTRY)}")
    flags = {k: v for c in sorted(candidates) for k, v in REGISTRY[c].build.items()}
    if flags.get("material") == "mooney_rivlin":
        flags["material"] = fem.MooneyRivlin()
    return flags


def actuator_model(candidates=(), resolution: int = 1, integration: str = "full",
                   weight: str = "before_reference", **geometry):
    """The paper's actuator at ``resolution`` with ``candidates`` switched on (each at its null exactly
    the base model), unfinalized, and its info (:func:`build_actuator_model`). ``weight``: when the
    ``gravity`` candidate's weight acts (:data:`torchfra.actuator.geometry.WEIGHT`)."""
    return build_actuator_model(ActuatorGeometry(resolution=resolution, **geometry), integration=integration,
                                weight=weight, **build_flags(candidates))


# The FE library's own parameter records (fem ParameterInfo: unit, null, admissible range) of each
# candidate term, against which the tests check every term's null and derivatives
CANDIDATES = {
    "mooney_rivlin": (MooneyRivlin.parameters["C01"],),
    "compressibility": (NeoHookean.parameters["D1"],),
    "gravity": (Gravity.parameters["density"],),
    "compliant_base": (ElasticSupport.parameters["c_n"], ElasticSupport.parameters["c_t"]),
    "fiber_stiffness": (ParameterInfo("E_fiber", "MPa", None, 0.0, math.inf,
                                      "fiber Young's modulus (31 GPa in the paper); rigid fibers as E_fiber -> inf",
                                      low_inclusive=False),),
    "pressure_sensor": (SensorCavityPressure.parameters["pressure_gain"],
                        SensorCavityPressure.parameters["pressure_offset"]),
    "cavity_offset": (CAVITY_OFFSET,),
    "fiber_pitch": (FIBER_PITCH,),
}


def fe_null_values(name: str) -> dict[str, float]:
    """The FE terms' own null values of candidate ``name`` (:data:`CANDIDATES`)."""
    return {p.name: p.null for p in CANDIDATES[name] if p.null is not None}
