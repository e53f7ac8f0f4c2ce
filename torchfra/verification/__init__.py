"""Closed-form reference solutions used to verify the finite element model (mm, MPa, N).

- :mod:`.rivlin`: thick-walled incompressible Neo-Hookean tube under internal pressure, plane strain.
"""
from torchfra.verification.rivlin import inner_radius_for_pressure, limit_pressure, pressure_for_inner_radius

__all__ = ["inner_radius_for_pressure", "limit_pressure", "pressure_for_inner_radius"]
