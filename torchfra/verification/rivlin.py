r"""Rivlin's inflation of a thick-walled incompressible Neo-Hookean tube in plane strain.

A tube with reference radii ``A < B`` (mm) is inflated by an internal pressure ``P`` (MPa) with
the axial stretch held at 1 (plane strain) and the outer wall traction-free. Material: Abaqus
Neo-Hookean ``psi = C10 (I1bar - 3) + (J - 1)^2 / D1`` in the incompressible limit ``D1 -> 0``,
shear modulus ``mu = 2 C10``.

Derivation
----------
Incompressibility with ``lambda_z = 1`` keeps the annulus area: a material circle of radius ``R``
moves to ``r`` with

.. math:: r^2 - a^2 = R^2 - A^2 \quad\Longrightarrow\quad r^2 = R^2 + c,\qquad c = a^2 - A^2,

so the outer radius is ``b^2 = B^2 + c``. The principal stretches are
``lambda_r = dr/dR = R/r``, ``lambda_t = r/R``, ``lambda_z = 1``. The Cauchy stress of the
incompressible Neo-Hookean solid is ``sigma = -q I + mu B`` (``B = F F^T``, ``q`` the reaction
pressure), hence

.. math:: \sigma_{\theta\theta} - \sigma_{rr} = \mu (\lambda_\theta^2 - \lambda_r^2)
          = \mu \left(\frac{r^2}{R^2} - \frac{R^2}{r^2}\right).

Radial equilibrium ``d sigma_rr / dr + (sigma_rr - sigma_tt) / r = 0`` with
``sigma_rr(a) = -P`` and ``sigma_rr(b) = 0`` gives

.. math:: P = \int_a^b (\sigma_{\theta\theta} - \sigma_{rr}) \frac{dr}{r}
            = \mu \int_a^b \left(\frac{r}{r^2 - c} - \frac{r^2 - c}{r^3}\right) dr ,

and with ``int r/(r^2 - c) dr = ln(r^2 - c)/2`` (``r^2 - c = R^2``) and
``int (1/r - c/r^3) dr = ln r + c/(2 r^2)``:

.. math:: P = \mu \left[ \ln\frac{B}{A} - \ln\frac{b}{a}
              + \frac{c}{2}\left(\frac{1}{a^2} - \frac{1}{b^2}\right) \right].

``P`` increases monotonically with ``a`` towards ``mu ln(B/A)`` as ``a -> inf`` (no finite limit
point in plane strain), so every ``0 <= P < mu ln(B/A)`` has exactly one inner radius ``a >= A``.
"""
from __future__ import annotations

import math

from scipy.optimize import brentq


def _check_geometry(A: float, B: float, C10: float) -> None:
    if not 0 < A < B:
        raise ValueError(f"need reference radii 0 < A < B (mm), got A={A}, B={B}")
    if not C10 > 0:
        raise ValueError(f"C10 must be positive (MPa), got {C10}")


def pressure_for_inner_radius(a: float, A: float, B: float, C10: float) -> float:
    """Internal pressure (MPa) that inflates the inner radius from ``A`` to ``a`` (mm).

    a: deformed inner radius, a >= A for P >= 0 (a < A gives the suction that contracts it).
    A, B: reference inner and outer radii; C10: Neo-Hookean constant (mu = 2 C10).
    """
    _check_geometry(A, B, C10)
    if not a > 0:
        raise ValueError(f"deformed inner radius must be positive, got a={a}")
    c = a * a - A * A
    b2 = B * B + c  # > 0 for every a > 0 because B > A
    mu = 2.0 * C10
    return mu * (math.log(B / A) - 0.5 * math.log(b2 / (a * a)) + 0.5 * c * (1.0 / (a * a) - 1.0 / b2))


def limit_pressure(A: float, B: float, C10: float) -> float:
    """Supremum ``mu ln(B/A)`` of the pressure (MPa) the tube can carry in plane strain."""
    _check_geometry(A, B, C10)
    return 2.0 * C10 * math.log(B / A)


def inner_radius_for_pressure(P: float, A: float, B: float, C10: float, rtol: float = 1e-14) -> float:
    """Deformed inner radius ``a`` (mm) at internal pressure ``P`` (MPa); inverse of
    :func:`pressure_for_inner_radius` by Brent's method.

    Raises ValueError for ``P >= mu ln(B/A)``: the tube inflates without bound there.
    """
    P_max = limit_pressure(A, B, C10)
    if not P < P_max:
        raise ValueError(
            f"P={P} MPa is not below the limit pressure mu ln(B/A) = {P_max} MPa: no equilibrium exists"
        )
    if P == 0:
        return A

    def f(a):
        return pressure_for_inner_radius(a, A, B, C10) - P

    lo, hi = A, A
    if P > 0:
        while f(hi) < 0:
            lo, hi = hi, 2.0 * hi
    else:
        while f(lo) > 0:  # suction: P -> -inf as a -> 0, so halving brackets the root
            lo, hi = 0.5 * lo, lo
    return brentq(f, lo, hi, xtol=1e-15 * A, rtol=rtol, maxiter=200)
