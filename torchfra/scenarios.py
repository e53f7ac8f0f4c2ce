"""Recordings with one concealed effect switched on: the proof suite of the missing-physics diagnosis.

A scenario is the paper's actuator (Neo-Hookean C10 at ``truth_c10``, D1 = 1/(1000 C10), E_fiber =
31000 MPa, clamped base, rigid top, cavity pressure up to 0.022 MPa) with one effect added, observed
the way a camera and a pressure sensor would (DESIGN §6): uy, uz on the camera-visible face x = +8 mm
at the points of a DIC-like grid, plus noise. The diagnosis is told nothing about the effect.

Effects (``EFFECTS``; size k = 1, 2, 3 picks the tabled value of the knob, size 0 its null):

- null: ``none``, the base model itself (several truth C10 values make several nulls).
- in the candidate library (``actuator.candidates``): ``mooney_rivlin`` (knob C01, MPa), ``compressibility``
  (bulk ratio k, D1 = 1/(k C10); null 1000), ``fiber_stiffness`` (E_fiber, MPa; null 31000), ``gravity``
  (density, t/mm^3, direction -y; the weight ramps with the load factor like every load term of the
  library, full weight at the largest pressure), ``compliant_base`` (c_n = c_t = c, mm^3/N, springs
  under the base), ``pressure_sensor`` (the sensor reads ``p_rec``, the cavity holds ``p_true = gain
  p_rec + offset``; knob the offset in MPa, gain 1: a gain alone is confounded with C10, see
  ``fem.sensor``). The recording is made at the true pressures and stores the recorded ones.
  ``cavity_offset`` (delta_y, mm: the cavity sits off its nominal axis, a harmonic morph of the
  generating mesh; negative toward the body's centre, thickening the 1 mm wall on the +y side).
  ``viscoelasticity`` (g1, a loading-unloading trace: the body's shear stress relaxes with one
  Prony term, tau1 = ``VISCO_TAU1`` of the trace's duration, the body at rest at t = 0, before the
  first frame; the diagnosis takes it at rest at the first frame and measures tau1 from there: the
  time maps differ). The generation marches the FE model with history variables at every Gauss
  point through the trace (``fem.viscoelastic``, steps of tau1 / 4 at most), not the candidate's
  load-level approximation (``history.creep_load``): that would be an inverse crime in the
  constitutive model. At resolution 1 the approximation misses 7 % of the g1 = 0.15 effect
  (``scripts/study_viscoelastic.py``).
- outside the library (the right answer is "unexplained"): ``stiff_base_region`` (C10 times the knob
  in the elements whose centroid lies below z = 10 mm, the base endcap: a second body whose material
  carries its own parameter names, ``RenamedMaterial``), ``fiber_debond`` (a stretch of both helices
  of the knob's length in mm, centred at z = 30 mm, carries a modulus of 31 MPa, 1/1000 of the
  rest), ``sensor_lag`` (a loading-unloading trace; the true pressure is the recorded trace delayed by
  the knob tau in normalized time, so the recording shows hysteresis).

The knob values were chosen so that the signal-to-noise ratio SNR = ||clean_effect - clean_null||
/ noise (one norm over all frames, points and components; null = base model at the same C10 and
trace) spans about 5 .. 50 at noise 1 mm. Measured at resolution 1, 20 frames, grid spacing 2 mm,
C10 = 0.0062 MPa (``make_scenario`` measures it again for every generated case: ``meta["snr"]``):

===================  ==================  ======================  =================
effect               knob (unit)         sizes 1, 2, 3           SNR at res 1
===================  ==================  ======================  =================
mooney_rivlin        C01 (MPa)           7e-05, 2e-04, 7e-04     5.3, 14.8, 47.4
compressibility      k = 1/(D1 C10)      30, 8, 3                5.7, 17.5, 27.3
fiber_stiffness      E_fiber (MPa)       250, 60, 25             4.8, 19.4, 50.4
gravity              density (t/mm^3)    1.2e-11, 3e-11, 1e-10   5.6, 13.9, 46.1
compliant_base       c (mm^3/N)          1000, 2500, 25000       2.0, 2.6, 3.0
pressure_sensor      offset (MPa)        1.5e-4, 5e-4, 1.5e-3    4.9, 16.5, 50.0
cavity_offset        delta_y (mm)        -0.25, -0.5, -1.0       6.8, 14.6, 33.2
viscoelasticity      g1 (1)              0.05, 0.15, 0.4         6.6, 21.2, 69.6
stiff_base_region    C10 factor          1.2, 2, 6               5.9, 18.4, 34.7
fiber_debond         length (mm)         12, 20, 28              6.1, 11.1, 21.2
sensor_lag           tau (1)             0.004, 0.012, 0.035     5.7, 17.1, 49.9
===================  ==================  ======================  =================

What the measurements showed: the SNR saturates for four effects. ``compliant_base`` stays below 3
however soft the springs: a closed-cavity pressure is self-equilibrated, so the base carries no net
force or moment and springs under it only relax the clamp's hold on the base face's own deformation
(its SNR is ~30 at noise 0.1 mm). ``compressibility`` peaks near k = 3 (k = 1 gave 16.9).
``stiff_base_region`` tends to a rigid base endcap (factor 3 gave 25.7). ``fiber_debond`` stays
below ~21 while the stretch is local (12 mm gave 6.1, 4 mm 0.14); a debonded modulus of 0.31 MPa
instead of 31 MPa ballooned the cavity (no convergence past 49 % load).
``cavity_offset`` is capped by the wall: +0.5 mm (half the 1 mm wall) gave 12.7, so the sizes move
the cavity toward the centre (SNR measured by ``scripts/study_cavity_offset.py``).
Gravity matters far below a silicone's density (1.1e-9 t/mm^3 would give SNR ~200): the body is soft.
Spot checks at the generation resolution 2 (15.7k dofs, ~75 s per solve): gravity size 2 gave 14.1,
fiber_debond size 3 gave 20.9.

No inverse crime: recordings are made at resolution 2 (the diagnosis works at 1), at grid points
that are not mesh nodes (a regular grid shifted by a fraction of its spacing: a camera's grid has
no reason to line up with the mesh), with noise i.i.d. N(0, sigma^2) or spatially correlated
(squared-exponential correlation of length ell mm between points, independent across frames and
components). The noise-free observations are expensive (one FE solve through all frame pressures)
and are cached as array-only ``.npz`` files keyed by everything that determines them; noise seeds
are drawn on top, so more seeds cost no solve.

``generator="calculix"`` makes the noise-free observations with another code altogether: the
scenario's model is written as a CalculiX deck (``io.abaqus.write_inp``: C3D20R bricks, each fiber
as two SPRINGA axial springs tied to its host bricks, the rigid top as ``*RIGID BODY``, the cavity
pressure as ``*DLOAD`` through an ``*AMPLITUDE`` of the frames' true pressures, one increment per
frame) and solved by ``ccx``; the diagnosis model (hybrid 3x3x3 bricks, curved Line3 fibers) then
differs from the recording's in element formulation, integration and fiber element as well
(+0.6 % at the tracked node on the same mesh, README "CalculiX, the actuator"). The decks stay in
the cache folder. CalculiX has no hybrid brick and its C3D20R stops near 60 % of the paper's pressure
on the resolution-2 mesh (a reduced-integration mode in the fiber-free ring by the cavity), so its
scenarios run at lower pressures. Effects it can carry: ``CALCULIX_EFFECTS``.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.fem.materials import Material, ParameterError
from torchfra.observation.operator import ObservationOperator, frame_times, regular_grid, visible_faces
from torchfra.observation.recording import Recording

PRESSURE_MAX = 0.022  # MPa, the largest recorded pressure (paper §4)
VISCO_TAU1 = 0.1  # relaxation time of the viscoelastic scenarios, in units of the trace's duration
BASE_REGION_HEIGHT = 10.0  # mm: stiff_base_region covers the elements with centroid z below this
DEBOND_CENTRE = 30.0  # mm: z of the middle of the debonded fiber stretch
DEBOND_MODULUS = 31.0  # MPa, what the debonded stretch still carries
SENSOR_GAIN = 1.0  # pressure_sensor: true = SENSOR_GAIN * recorded + offset
GRID_SHIFT = (0.382, 0.618)  # grid offset along (y, z) as fractions of its spacing
CACHE_VERSION = 1  # bump when the way clean observations are made changes
GENERATORS = ("torchfra", "calculix")
# effects a CalculiX deck of write_inp carries (no history variables, morphs, renamed materials,
# per-segment fiber moduli, or delayed pressures)
CALCULIX_EFFECTS = ("none", "mooney_rivlin", "compressibility", "fiber_stiffness", "gravity", "compliant_base",
                    "pressure_sensor")
CALCULIX_TIMEOUT_S = 7200.0
CALCULIX_DP = 4e-4  # MPa: the largest pressure change of one CalculiX increment


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


EFFECTS = {e.name: e for e in (
    Effect("none", "null", "-", "-", 0.0, 0.0, 0.0, (), ()),
    Effect("mooney_rivlin", "library", "C01", "MPa", 0.0, 0.0, math.inf,
           (7e-05, 0.0002, 0.0007), (5.3, 14.77, 47.35)),
    Effect("compressibility", "library", "bulk_ratio", "1", BULK_RATIO, 1e-3, math.inf,
           (30.0, 8.0, 3.0), (5.65, 17.48, 27.27)),
    Effect("fiber_stiffness", "library", "E_fiber", "MPa", E_FIBER, 1e-3, math.inf,
           (250.0, 60.0, 25.0), (4.78, 19.38, 50.43)),
    Effect("gravity", "library", "density", "t/mm^3", 0.0, 0.0, 2.5e-8, (1.2e-11, 3e-11, 1e-10), (5.57, 13.91, 46.1)),
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


# -- a material under other parameter names --------------------------------------------------------------

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


# -- the model of a scenario -------------------------------------------------------------------------------

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


def pressure_trace(kind: str, frames: int, pressure: float = PRESSURE_MAX) -> tuple[np.ndarray, np.ndarray]:
    """Normalized frame times (K,) and recorded pressures (K,) MPa: ``"ramp"`` rises linearly to
    ``pressure`` at t = 1, ``"cycle"`` rises to it at t = 1/2 and falls back to 0 at t = 1."""
    t = frame_times(frames)
    return t, pressure * _trace_shape(kind, t)


def _trace_shape(kind: str, t):
    if kind == "ramp":
        return np.clip(t, 0.0, 1.0)
    if kind == "cycle":
        return np.clip(1.0 - np.abs(2.0 * np.asarray(t) - 1.0), 0.0, 1.0)
    raise ValueError(f"unknown pressure trace {kind!r}; valid traces: ramp, cycle")


def true_pressure(effect: str, value: float, trace: str, times, pressure: float = PRESSURE_MAX) -> np.ndarray:
    """Pressure in the cavity (K,) MPa at the frames of the recorded ``trace`` (see ``pressure_trace``)."""
    recorded = pressure * _trace_shape(trace, np.asarray(times))
    if effect == "pressure_sensor":
        return SENSOR_GAIN * recorded + value
    if effect == "sensor_lag":
        return pressure * _trace_shape(trace, np.maximum(np.asarray(times) - value, 0.0))
    return recorded  # viscoelasticity: the body creeps under the recorded pressure (``clean_observations``)


def dic_grid(mesh, spacing: float) -> np.ndarray:
    """(P, 3) points on the camera-visible face x = +w_x/2: the regular grid of ``spacing`` mm
    shifted by ``GRID_SHIFT`` of the spacing in y and z; points pushed off the face are dropped."""
    faces = visible_faces(mesh, (1.0, 0.0, 0.0))
    grid = regular_grid(mesh, faces, spacing)
    face_X = mesh.nodes[np.unique(mesh.elements[faces[:, 0]])]
    front = face_X[np.isclose(face_X[:, 0], grid[0, 0])]
    grid[:, 1:] += spacing * np.asarray(GRID_SHIFT)
    lo, hi = front[:, 1:].min(0), front[:, 1:].max(0)
    inside = np.all((grid[:, 1:] > lo + 1e-9) & (grid[:, 1:] < hi - 1e-9), axis=1)
    return grid[inside]


# -- noise-free observations (cached) --------------------------------------------------------------------

_ARRAYS = ("clean", "points", "times", "recorded", "true", "mesh")


def face_observer(mesh, spacing: float) -> ObservationOperator:
    """The suite's camera (DESIGN §6): uy, uz on the face x = +8 mm at the DIC grid of ``spacing`` mm,
    whose points are not mesh nodes (``dic_grid``)."""
    return ObservationOperator(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=dic_grid(mesh, spacing))


def elastic_frames(model, params, lam: np.ndarray, options, op, progress=False):
    """The elastic body observed by ``op`` at the frames' load factors ``lam`` (K,): one FE solve
    through the distinct positive levels, no displacement at a frame whose level is 0. Returns
    (observations (K, P, 2) of the first member, the solve); the caller checks its status."""
    distinct = np.unique(lam[lam > 0])
    sol = fem.solve(model, params, distinct, options, progress=progress)
    Y = op(sol.u[0, :, : model.mesh.n_nodes]).numpy()  # (distinct, P, 2)
    frames = np.zeros((lam.size,) + Y.shape[1:])
    pos = lam > 0
    frames[pos] = Y[np.searchsorted(distinct, lam[pos])]
    return frames, sol


def _clean_key(effect, value, c10, resolution, spacing, frames, trace, pressure, generator="torchfra") -> dict:
    if value == EFFECTS[effect].null:  # an effect at its null is the base model: share its cache
        effect, value = "none", 0.0
    return {"effect": effect, "value": float(value), "c10": float(c10), "resolution": int(resolution),
            "spacing": float(spacing), "frames": int(frames), "trace": trace, "pressure": float(pressure),
            "grid_shift": list(GRID_SHIFT), "bulk_ratio": BULK_RATIO, "E_fiber": E_FIBER,
            "stagnation_tol": 1e-6, "version": CACHE_VERSION,
            **({"history": "fe_prony", "tau1": VISCO_TAU1} if effect == "viscoelasticity" else {}),
            **({"generator": "calculix", "element": "C3D20R", "fibers": "SPRINGA"} if generator == "calculix" else {})}


def check_generator(effect: str, generator: str) -> None:
    """Refuse, by name, a generator that does not exist or cannot carry ``effect``."""
    if generator not in GENERATORS:
        raise ValueError(f"unknown generator {generator!r}; generators: {', '.join(GENERATORS)}")
    if generator == "calculix" and effect not in CALCULIX_EFFECTS:
        raise ValueError(f"effect {effect!r} has no CalculiX deck here (write_inp carries "
                         f"{', '.join(CALCULIX_EFFECTS)}); generate it with torchfra")


def _calculix_displacements(model, values: dict, lam: np.ndarray, n_nodes: int, deck_dir: Path, title: str
                            ) -> np.ndarray:
    """CalculiX's displacements (K, n_nodes, 3) of the deck of ``model`` at ``values`` (name -> number)
    through the load factors ``lam`` (K,), one increment each, written and run in ``deck_dir``."""
    from torchfra.io.abaqus.write import CalculixError, _dat_blocks, run_calculix, write_inp

    deck_dir.mkdir(parents=True, exist_ok=True)
    # increments of at most CALCULIX_DP MPa: its Newton on the rigid top's MPC and the follower
    # pressure fails on larger ones (2-2.5 % of 0.022 MPa converged, README "CalculiX, the actuator")
    steps = np.abs(np.diff(np.concatenate([[0.0], lam]))) * values["P"]
    per_entry = max(1, int(math.ceil(steps.max() / CALCULIX_DP - 1e-9)))
    deck = write_inp(deck_dir / "scenario.inp", model, values, element_type="C3D20R", truss_element="SPRINGA",
                     load_factors=lam, increments_per_entry=per_entry, title=title)
    try:
        run_calculix(deck, threads=torch.get_num_threads(), timeout=CALCULIX_TIMEOUT_S)
    except CalculixError as exc:  # a CalculixError (a RuntimeError): scripts end it in one paragraph
        raise CalculixError(f"CalculiX did not solve the scenario's deck {deck} ({str(exc).splitlines()[0]}); "
                            "choose a lower --pressure (its C3D20R bricks stop near 60 % of 0.022 MPa at "
                            "resolution 2)") from exc
    blocks = _dat_blocks(deck.with_suffix(".dat"))
    times = np.array([t for t, _ in blocks])
    K = lam.size
    U = np.full((K, n_nodes, 3), np.nan)
    for k in range(K):
        j = int(np.argmin(np.abs(times - (k + 1) / K)))
        if abs(times[j] - (k + 1) / K) > 1e-6:
            raise CalculixError(f"CalculiX printed no displacements at step time {(k + 1) / K:g} (frame {k}) of {deck}")
        block = blocks[j][1]
        U[k] = np.stack([block[i] for i in range(n_nodes)])
    return U


def clean_observations(effect: str, value: float, c10: float, resolution: int, spacing: float, frames: int,
                       trace: str, pressure: float = PRESSURE_MAX, cache_dir=None,
                       progress: bool = False, generator: str = "torchfra") -> tuple[dict[str, np.ndarray], int]:
    """Noise-free observations of the scenario and what made them: arrays ``clean`` (K, P, 2) mm,
    ``points`` (P, 3) mm, ``times``, ``recorded``, ``true`` (K,) MPa and ``mesh`` (elements, nodes,
    dofs of the generating model); returns ``(arrays, solves)`` with
    ``solves`` the FE solves made (0 when read from ``cache_dir``). ``generator``: ``"torchfra"`` or
    ``"calculix"`` (see the module's docstring)."""
    check_generator(effect, generator)
    key = _clean_key(effect, value, c10, resolution, spacing, frames, trace, pressure, generator)
    text = json.dumps(key, sort_keys=True)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{key['effect']}_{digest}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as f:
                if str(f["key"]) == text:
                    return {k: f[k] for k in _ARRAYS}, 0
    effect, value = key["effect"], key["value"]
    times, recorded = pressure_trace(trace, frames, pressure)
    p_true = true_pressure(effect, value, trace, times, pressure)
    if np.any(p_true < 0):
        raise ValueError(f"effect {effect!r} at {value:g} makes negative true pressures; choose a smaller size")
    # CalculiX has no hybrid brick: its scenarios are C3D20R, displacement bricks with 2x2x2 points
    model_kw = dict(formulation="displacement", integration="reduced") if generator == "calculix" else {}
    model, info = (build_actuator_model(ActuatorGeometry(resolution=resolution), **model_kw) if effect == "none"
                   else build_model(effect, value, resolution, **model_kw))
    mesh = info["mesh"]
    op = face_observer(mesh, spacing)
    P_load = float(p_true.max())
    params = {k: torch.tensor([v], dtype=torch.float64)
              for k, v in {**model_parameters(effect, value, c10), "P": P_load}.items()}
    lam = p_true / P_load
    options = fem.NewtonOptions(stagnation_tol=key["stagnation_tol"])
    if effect == "viscoelasticity":  # history variables: march through the frames' times from rest at t = 0
        params.update({"g1": torch.tensor([value], dtype=torch.float64),
                       "tau1": torch.tensor([VISCO_TAU1], dtype=torch.float64)})
        hist = fem.solve_history(model, params, times, lam, options=options,
                                 progress="creeping body, FE history" if progress else False)
        if hist.status[0] != "converged":
            raise RuntimeError(f"scenario {effect} at {value:g} did not converge (C10 = {c10}, resolution "
                               f"{resolution}, reached t = {hist.time_reached[0]:.3f} of the trace); choose a "
                               "smaller size")
        clean = op(hist.u[0, :, : mesh.n_nodes]).numpy()
    elif generator == "calculix":
        # without a cache the deck goes to a temporary folder, removed once solved (kept when CalculiX
        # fails: the error names it)
        scratch = None if cache_dir is not None else Path(tempfile.mkdtemp(prefix="torchfra_calculix_"))
        deck_dir = (Path(cache_dir) if scratch is None else scratch) / "calculix" / f"{key['effect']}_{digest}"
        values = {k: float(v[0]) for k, v in params.items()}
        U = _calculix_displacements(model, values, lam, mesh.n_nodes, deck_dir,
                                    f"torchfra scenario {effect} = {value:g}, C10 = {c10:g} MPa, resolution {resolution}")
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        clean = op(torch.as_tensor(U)).numpy()
    else:
        clean, sol = elastic_frames(model, params, lam, options, op, progress)
        if sol.status[0] != "converged":
            raise RuntimeError(f"scenario {effect} at {value:g} did not converge (C10 = {c10}, resolution "
                               f"{resolution}, reached {sol.load_reached[0]:.3f} of {P_load:g} MPa); choose a "
                               "smaller size")
    arrays = {"clean": clean, "points": op.points, "times": times, "recorded": recorded, "true": p_true,
              "mesh": np.array([mesh.n_elements, mesh.n_nodes, info["dofs"]])}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")  # ranks of a torchrun suite may write at once
        np.savez(tmp, key=np.array(text), **arrays)
        tmp.replace(path)
    return arrays, 1


# -- noise ----------------------------------------------------------------------------------------------

def correlation_factor(points: np.ndarray, length: float) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor L (P, P) of the squared-exponential correlation
    ``exp(-|X_i - X_j|^2 / (2 length^2))`` between points, and the diagonal jitter it needed (the
    matrix is numerically singular for lengths above the spacing)."""
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    C = np.exp(-d2 / (2.0 * length**2))
    for jitter in 10.0 ** np.arange(-12, -1):
        try:
            return np.linalg.cholesky(C + jitter * np.eye(len(C))), float(jitter)
        except np.linalg.LinAlgError:
            continue
    raise ValueError(f"the correlation matrix of length {length} mm has no Cholesky factor even with jitter")


def observation_noise(points: np.ndarray, frames: int, sigma: float, length: float,
                      rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Noise (K, P, 2) mm: N(0, sigma^2) i.i.d. when ``length`` is 0, else correlated between points
    with the squared-exponential correlation of ``length`` mm (same std), independent across frames
    and components. Returns the noise and the jitter of the correlation factor (0 if i.i.d.)."""
    e = rng.standard_normal((frames, 2, len(points)))
    if length == 0:
        return sigma * e.transpose(0, 2, 1), 0.0
    L, jitter = correlation_factor(points, length)
    return sigma * np.einsum("pq,kcq->kpc", L, e) / math.sqrt(1.0 + jitter), jitter


# -- scenarios --------------------------------------------------------------------------------------------

DEFAULT_CACHE = Path("runs") / "scenarios" / "clean"


def make_scenario(effect: str, size, truth_c10: float = 0.0062, noise: float = 1.0, seed: int = 0,
                  resolution: int = 2, spacing: float = 2.0, correlation: float = 0.0, frames: int = 20,
                  trace: str | None = None, pressure: float = PRESSURE_MAX, cache_dir=DEFAULT_CACHE,
                  progress: bool = False, generator: str = "torchfra") -> tuple[Recording, np.ndarray, dict]:
    """A recording of the actuator with ``effect`` at ``size`` (see ``knob_value``) concealed in it.

    truth_c10 (MPa), noise: sigma (mm), seed: of the noise, resolution: of the generating mesh,
    spacing: of the DIC grid (mm), correlation: length ell (mm) of the noise's correlation (0:
    i.i.d.), frames: K, trace: the recorded pressure trace, "ramp" or "cycle" (default: the effect's,
    a cycle for sensor_lag, else a ramp; see ``pressure_trace``), pressure: the largest recorded
    pressure (MPa), cache_dir: where noise-free observations are kept (None: nowhere), generator: the code that
    solves the scenario, ``"torchfra"`` or ``"calculix"`` (see the module's docstring).
    Returns ``(recording, clean (K, P, 2), meta)``; ``meta`` holds the effect, its parameter values,
    the SNR measured against the base model at the same C10 and trace, the generation mesh, the
    trace, the noise model and the FE solves this call made.
    """
    e = _effect(effect)
    value = knob_value(effect, size)
    if not (noise > 0 and correlation >= 0 and truth_c10 > 0 and frames >= 1 and spacing > 0):
        raise ValueError(f"need noise > 0, correlation >= 0, truth_c10 > 0, frames >= 1 and spacing > 0; got "
                         f"noise={noise}, correlation={correlation}, truth_c10={truth_c10}, frames={frames}, "
                         f"spacing={spacing}")
    trace = e.trace if trace is None else trace
    _trace_shape(trace, 0.0)
    t0 = time.perf_counter()
    check_generator(effect, generator)
    setting = dict(c10=truth_c10, resolution=resolution, spacing=spacing, frames=frames, trace=trace,
                   pressure=pressure, cache_dir=cache_dir, progress=progress, generator=generator)
    arrays, solves = clean_observations(effect, value, **setting)
    if value == e.null:
        snr = 0.0
    else:
        null, more = clean_observations("none", 0.0, **setting)
        solves += more
        snr = float(np.linalg.norm(arrays["clean"] - null["clean"]) / noise)
    clean, points = arrays["clean"], arrays["points"]
    err, jitter = observation_noise(points, frames, noise, correlation, np.random.default_rng(seed))
    rec = Recording(np.arange(frames), arrays["times"], arrays["recorded"], np.arange(len(points)), points,
                    clean + err, "synthetic scenario")  # the source must not tell the diagnosis the effect
    parameters = model_parameters(effect if value != e.null else "none", value, truth_c10)
    if effect in ("pressure_sensor", "sensor_lag"):
        parameters.update({"pressure_gain": SENSOR_GAIN, "pressure_offset": value} if effect == "pressure_sensor"
                          else {"tau": value})
    if effect == "viscoelasticity":
        parameters.update({"g1": value, "tau1": VISCO_TAU1})
    meta = {
        "effect": effect, "kind": e.kind, "expected": e.expected, "size": size, "knob": e.parameter,
        "value": value, "unit": e.unit, "parameters": parameters, "truth_c10": truth_c10, "snr": snr,
        "snr_res1_table": dict(zip(range(1, len(e.snr) + 1), e.snr)),
        "generation": {"generator": generator, "resolution": resolution, "elements": int(arrays["mesh"][0]),
                       "nodes": int(arrays["mesh"][1]),
                       "dofs": int(arrays["mesh"][2]), "spacing_mm": spacing, "grid_shift": list(GRID_SHIFT),
                       "points": len(points), "frames": frames},
        "trace": {"kind": trace, "pressure_max": pressure, "times": arrays["times"].tolist(),
                  "recorded": arrays["recorded"].tolist(), "true": arrays["true"].tolist()},
        "noise": {"sigma": noise, "seed": seed, "correlation_length": correlation, "jitter": jitter,
                  "model": "iid normal" if correlation == 0 else "squared-exponential correlation between points"},
        "solves": solves, "seconds": time.perf_counter() - t0,
    }
    return rec, clean, meta
