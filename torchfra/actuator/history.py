"""History-dependent physics on the frame-to-load map: viscoelastic creep of the whole body.

A soft silicone relaxes: under a pressure that rises and falls, its displacements lag the pressure
and come back down along a higher path (a hysteresis loop, dissipation). The candidate here is a
quasi-linear viscoelastic body (Fung) with one Prony term, in the Abaqus convention
(``*VISCOELASTIC, TIME=PRONY``): every modulus relaxes by the same normalized function

    g_R(t) = 1 - g1 (1 - exp(-t / tau1)),          g1 in [0, 1), tau1 > 0,

and the model's hyperelastic coefficients (``C10``, ...) are the **long-term** (relaxed) ones, so
the instantaneous response is stiffer by 1 / (1 - g1). By the correspondence principle, a body whose
moduli all relax alike and that is loaded by ``lambda(t) f`` responds as the relaxed (elastic) body
at the effective load level

    mu(t) = int_0^t J(t - s) dlambda(s),           J(t) = 1 - g1 exp(-t / tau_c),
    tau_c = tau1 / (1 - g1)                        (retardation time),

J being the creep compliance normalized by its long-term value (the inverse, in Laplace space, of
``s G(s)`` with ``G / G_inf = 1 + g1 / (1 - g1) exp(-t / tau1)``). So the viscoelastic response is
the elastic one read at ``mu(t)`` in place of ``lambda(t)``: the FE model is solved once, as for
every other candidate, and only the frames' load factors change. This is exact for a linear body
(small strain, same relaxation in every modulus); at finite strain it is the quasi-linear response
restricted to the elastic equilibrium path (a one-parameter approximation: the shape of the
deformation along the path is the elastic one). A full history-variable formulation in the element
kernel is not needed for the candidate's job, detecting and sizing a creeping body, and would change
the solver (time stepping along the recording's own time trace) for every member.

Properties that make the candidate physical, not a free time warp:
- ``mu <= lambda`` while loading, and at equal load unloading passes through a larger ``mu`` than
  loading: the body always lags its load, so the loop is run clockwise in (pressure, displacement);
  a pressure sensor that lags the pressure (the body *leads* the recorded pressure) needs
  ``g1 < 0`` and is not explained;
- ``g1 = 0`` gives ``mu = lambda`` exactly (the null);
- on a constant-rate ramp, ``mu = lambda - g1 tau_c lambda' (1 - exp(-t / tau_c))``: once
  ``t >> tau_c`` a shift of the load, nearly confounded with a pressure offset; rate changes (holds,
  unloading) are what identify it.

Time: ``tau1`` is measured in units of the recording's duration (first to last frame), whatever the
recording's time unit; the body is taken at rest (fully relaxed) at the first frame's pressure. The
load is piecewise linear in time between frames, and the convolution is integrated exactly on it.
"""
from __future__ import annotations

import numpy as np
import torch

from torchfra.fem.params import ParameterInfo

G1 = ParameterInfo("g1", "1", 0.0, 0.0, 0.95,
                   "Prony relaxation fraction g1 (Abaqus *VISCOELASTIC, TIME=PRONY): the instantaneous moduli "
                   "are the long-term ones / (1 - g1)")
TAU1 = ParameterInfo("tau1", "duration", None, 1e-3, 1e2,
                     "Prony relaxation time tau1 in units of the recording's duration (first to last frame)")


def normalized_time(times) -> np.ndarray:
    """Frame times (K,) -> (t - t_0) / (t_K-1 - t_0); a single frame -> [0]."""
    t = np.asarray(times, dtype=np.float64)
    span = t[-1] - t[0]
    return (t - t[0]) / span if span > 0 else np.zeros_like(t)


def creep_load(lam: torch.Tensor, t: np.ndarray, g1: torch.Tensor, tau1: torch.Tensor) -> torch.Tensor:
    """Effective load level ``mu`` (K,) of the viscoelastic body under the load history ``lam`` (K,)
    at normalized times ``t`` (K,), strictly increasing: ``mu_k = lam_k - g1 h_k`` with the memory

        h_0 = 0,   h_k+1 = exp(-dt / tau_c) h_k + (dlam / dt) tau_c (1 - exp(-dt / tau_c)),

    exact for ``lam`` linear between frames. ``g1``, ``tau1``: 0-d or (1,) tensors (forward-mode
    derivatives pass through)."""
    t = np.asarray(t, dtype=np.float64)
    if t.shape != tuple(lam.shape) or (t.size > 1 and not np.all(np.diff(t) > 0)):
        raise ValueError("creep_load needs one strictly increasing time per load level")
    g1 = torch.as_tensor(g1).to(lam.dtype).reshape(())
    tau1 = torch.as_tensor(tau1).to(lam.dtype).reshape(())
    if not (0.0 <= float(g1.detach()) < 1.0 and float(tau1.detach()) > 0.0):
        raise ValueError(f"creep_load needs 0 <= g1 < 1 and tau1 > 0, got g1 = {float(g1.detach())!r}, tau1 = {float(tau1.detach())!r}")
    tau_c = tau1 / (1.0 - g1)
    dt = torch.as_tensor(np.diff(t), dtype=lam.dtype)
    decay = torch.exp(-dt / tau_c)
    gain = -torch.expm1(-dt / tau_c) * tau_c / dt  # tau_c (1 - exp(-dt / tau_c)) / dt
    dlam = lam[1:] - lam[:-1]
    h = [torch.zeros((), dtype=lam.dtype)]
    for k in range(dt.numel()):
        h.append(decay[k] * h[-1] + gain[k] * dlam[k])
    return lam - g1 * torch.stack(h)


LAG = ParameterInfo("pressure_lag", "duration", 0.0, -0.2, 0.2,
                    "time by which the cavity's pressure lags the recorded one (a pneumatic line between sensor "
                    "and cavity; negative: the sensor lags), in units of the recording's duration")


def delayed_load(lam: torch.Tensor, t: np.ndarray, lag: torch.Tensor) -> torch.Tensor:
    """The load the body feels when it lags the recorded load ``lam`` (K,) by ``lag``: ``lam`` linear
    between the normalized frame times ``t`` (K,), read at ``t - lag`` (held at its first and last
    values outside them). At ``lag = 0`` exactly ``lam``; its derivative there is the slope of the
    segment before each frame (a positive lag reads into the past).

    A first-order lag of the load (``tau mu' + mu = lambda``) is ``creep_load`` with ``g1 -> 1``; a
    pure delay is this. A creeping body and a lagging cavity pressure make the same loop once the
    lag is shorter than the frame spacing; the diagnosis fits this as the rival of viscoelasticity."""
    t_ = torch.as_tensor(np.asarray(t, dtype=np.float64), dtype=lam.dtype)
    s = torch.clamp(t_ - torch.as_tensor(lag).to(lam.dtype).reshape(()), t_[0], t_[-1])
    i = torch.clamp(torch.searchsorted(t_, s.detach(), side="left") - 1, 0, t_.numel() - 2)
    w = (s - t_[i]) / (t_[i + 1] - t_[i])
    return (1 - w) * lam[i] + w * lam[i + 1]
