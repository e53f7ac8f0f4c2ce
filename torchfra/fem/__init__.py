"""Ensemble-batched finite-strain finite elements (mm, MPa, N).

Build a :class:`Model` from a :class:`Mesh`, add energy terms (:class:`Hex20Solid` with a
:class:`NeoHookean` or :class:`MooneyRivlin` material, :class:`Truss`, :class:`CavityPressure`,
:class:`FollowerPressure`, and the candidate terms :class:`Gravity`, :class:`ElasticSupport`,
:class:`SensorCavityPressure`, :class:`FiberPitch`, and :class:`ViscousOverstress` with
:func:`solve_history` for a time trace with history variables),
constrain it (``clamp``, ``prescribe``, ``rigid``, ``embed``) and call :func:`solve` with one
tensor per parameter holding every member's value.
"""
from .constraints import rotation_matrix
from .gravity import Gravity
from .helix import FiberPitch
from .materials import Material, MooneyRivlin, NeoHookean, ParameterError
from .mesh import Mesh, MeshError
from .model import Evaluation, Model
from .newton import NewtonOptions, Solution, WarmStart, solve
from .pressure import CavityPressure, FollowerPressure
from .sensor import SensorCavityPressure
from .solid import Hex20Solid
from .springs import ElasticSupport, support_face
from .terms import Term, TermOutput
from .truss import Truss, two_node_truss
from .viscoelastic import HistorySolution, ViscousOverstress, solve_history, with_viscoelasticity

__all__ = [
    "CavityPressure", "ElasticSupport", "FiberPitch", "Evaluation", "FollowerPressure", "Gravity", "Hex20Solid", "Material",
    "Mesh", "MeshError", "Model", "MooneyRivlin", "NeoHookean", "NewtonOptions", "ParameterError",
    "SensorCavityPressure", "Solution", "Term", "TermOutput", "Truss", "rotation_matrix", "solve", "two_node_truss",
    "support_face", "WarmStart", "HistorySolution", "ViscousOverstress", "solve_history", "with_viscoelasticity",
]
