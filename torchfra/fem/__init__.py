"""Ensemble-batched finite-strain finite elements (mm, MPa, N).

Build a :class:`Model` from a :class:`Mesh`, add energy terms (:class:`Hex20Solid` with a
:class:`NeoHookean` or :class:`MooneyRivlin` material, :class:`Truss`, :class:`CavityPressure`,
:class:`FollowerPressure`, and the candidate terms :class:`Gravity`, :class:`ElasticSupport`,
:class:`SensorCavityPressure`, :class:`FiberPitch`, and :class:`ViscousOverstress` with
:func:`solve_history` for a time trace with history variables),
constrain it (``clamp``, ``prescribe``, ``rigid``, ``embed``) and call :func:`solve` with one
tensor per parameter holding every member's value.
"""
from torchfra.fem.constraints import rotation_matrix
from torchfra.fem.gravity import Gravity
from torchfra.fem.helix import FiberPitch
from torchfra.fem.materials import Material, MooneyRivlin, NeoHookean, ParameterError
from torchfra.fem.mesh import Mesh, MeshError
from torchfra.fem.model import Evaluation, Model
from torchfra.fem.newton import NewtonOptions, Solution, WarmStart, solve
from torchfra.fem.pressure import CavityPressure, FollowerPressure
from torchfra.fem.sensor import SensorCavityPressure
from torchfra.fem.solid import Hex20Solid
from torchfra.fem.springs import ElasticSupport, support_face
from torchfra.fem.terms import Term, TermOutput
from torchfra.fem.transforms import with_material, with_pressure_sensor
from torchfra.fem.truss import Truss, two_node_truss
from torchfra.fem.viscoelastic import HistorySolution, ViscousOverstress, solve_history, with_viscoelasticity

__all__ = [
    "CavityPressure", "ElasticSupport", "FiberPitch", "Evaluation", "FollowerPressure", "Gravity", "Hex20Solid", "Material",
    "Mesh", "MeshError", "Model", "MooneyRivlin", "NeoHookean", "NewtonOptions", "ParameterError",
    "SensorCavityPressure", "Solution", "Term", "TermOutput", "Truss", "rotation_matrix", "solve", "two_node_truss",
    "support_face", "WarmStart", "HistorySolution", "ViscousOverstress", "solve_history", "with_viscoelasticity",
    "with_material", "with_pressure_sensor",
]
