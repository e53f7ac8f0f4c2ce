"""The library of candidate physics (DESIGN §1.4): what each adds, its parameters, how to switch it on.

Every candidate is a term or a material with named parameters (``ParameterInfo``: unit, null,
admissible range); at the null values the model is exactly the base model. Switching one on is
adding a term or swapping a term of an unfinalized model, never editing the solver:

====================  ===========================  ==============================================
candidate             parameters (null)            switched on by
====================  ===========================  ==============================================
mooney_rivlin         C01 (0) MPa                  ``with_material(model, MooneyRivlin())``
compressibility       D1 (0: incompressible) 1/MPa D1 as a free parameter, not 1/(bulk_ratio C10)
gravity               density (0) t/mm^3           ``model.add(Gravity(mesh, direction=...))``
compliant_base        c_n, c_t (0: clamp) mm^3/N   ``support_face(model, face, compliant=True)``
                                                   in place of ``model.clamp(face)``
pressure_sensor       pressure_gain (1),           ``with_pressure_sensor(model)``
                      pressure_offset (0) MPa
cavity_offset         delta_y (0) mm               ``model.morph("delta_y", field, info)`` (e.g.
                                                   ``build_actuator_model(cavity_offset=True)``)
fiber_pitch           fiber_pitch (drawn) deg          ``build_actuator_model(fiber_pitch=True)``
                                                   (``FiberPitch``: the trusses wound at each
                                                   member's pitch, embedded where they fall)
viscoelasticity       g1 (0), tau1 s [g2, tau2]    ``with_viscoelasticity(model)``, solved along a
                                                   time trace by ``solve_history`` (history
                                                   variables; ``fem.viscoelastic``)
====================  ===========================  ==============================================

Fiber stiffness ``E_fiber`` (MPa) is a parameter of the base model's ``Truss`` (``fiber_stiffness``
below, no null: the rigid-fiber limit is ``E_fiber -> infinity``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from torchfra.actuator.geometry import CAVITY_OFFSET, ActuatorGeometry
from torchfra.fem.gravity import Gravity
from torchfra.fem.helix import pitch_parameter
from torchfra.fem.materials import MooneyRivlin, NeoHookean
from torchfra.fem.params import ParameterInfo
from torchfra.fem.sensor import SensorCavityPressure
from torchfra.fem.springs import ElasticSupport


def fiber_pitch_parameter() -> ParameterInfo:
    """The pitch candidate's registry entry, null at the actuator geometry's drawn pitch."""
    return pitch_parameter(ActuatorGeometry().pitch_deg)


def _cavity_offset_parameter() -> ParameterInfo:
    return CAVITY_OFFSET


@dataclass(frozen=True)
class Candidate:
    """One candidate extension: ``name``, what physics it adds, its parameters (registry entries)."""

    name: str
    description: str
    parameters: tuple[ParameterInfo, ...]

    def null_values(self) -> dict[str, float]:
        """Parameter values at which the candidate vanishes (base-model parameters have none)."""
        return {p.name: p.null for p in self.parameters if p.null is not None}


CANDIDATES = {
    c.name: c
    for c in (
        Candidate("mooney_rivlin", "second invariant of the body's strain energy (Mooney-Rivlin)",
                  (MooneyRivlin.parameters["C01"],)),
        Candidate("compressibility", "finite bulk modulus of the body, D1 free", (NeoHookean.parameters["D1"],)),
        Candidate("gravity", "self-weight of the body", (Gravity.parameters["density"],)),
        Candidate("compliant_base", "distributed springs under the base instead of a clamp",
                  (ElasticSupport.parameters["c_n"], ElasticSupport.parameters["c_t"])),
        Candidate("fiber_stiffness", "Young's modulus of the fibers (a base-model parameter, refitted)",
                  (ParameterInfo("E_fiber", "MPa", None, 0.0, math.inf,
                                 "fiber Young's modulus (31 GPa in the paper); rigid fibers as E_fiber -> inf",
                                 low_inclusive=False),)),
        Candidate("pressure_sensor", "gain and offset of the pressure sensor",
                  (SensorCavityPressure.parameters["pressure_gain"], SensorCavityPressure.parameters["pressure_offset"])),
        Candidate("cavity_offset", "the cavity sits off its nominal axis along y (a misplaced mould core; a morph "
                  "of the reference mesh)", (_cavity_offset_parameter(),)),
        Candidate("fiber_pitch", "the fibers are wound at another pitch than drawn (each member's fibers embedded "
                  "where they fall)", (fiber_pitch_parameter(),)),
    )
}
