"""Ensemble-batched finite-strain finite elements (mm, MPa, N).

Build a :class:`Model` from a :class:`Mesh`, add energy terms (:class:`Hex20Solid` with a
:class:`NeoHookean` material, :class:`Truss`, :class:`CavityPressure`, :class:`FollowerPressure`),
constrain it (``clamp``, ``prescribe``, ``rigid``, ``embed``) and call :func:`solve` with one
tensor per parameter holding every member's value.
"""
from .constraints import rotation_matrix
from .materials import Material, NeoHookean, ParameterError
from .mesh import Mesh, MeshError
from .model import Evaluation, Model
from .newton import NewtonOptions, Solution, WarmStart, solve
from .pressure import CavityPressure, FollowerPressure
from .solid import Hex20Solid
from .terms import Term, TermOutput
from .truss import Truss

__all__ = [
    "CavityPressure", "Evaluation", "FollowerPressure", "Hex20Solid", "Material", "Mesh", "MeshError",
    "Model", "NeoHookean", "NewtonOptions", "ParameterError", "Solution", "Term", "TermOutput", "Truss",
    "rotation_matrix", "solve", "WarmStart",
]
