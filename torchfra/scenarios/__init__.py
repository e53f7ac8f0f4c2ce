"""Recordings with one concealed effect switched on: the proof suite of the missing-physics diagnosis.

A scenario is the paper's actuator (Neo-Hookean C10 at ``truth_c10``, D1 = 1/(1000 C10), E_fiber =
31000 MPa, clamped base, rigid top, cavity pressure up to 0.022 MPa) with one effect added, observed
the way a camera and a pressure sensor would (docs/design.md#s6): uy, uz on the camera-visible face x = +8 mm
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
  (``studies/viscoelastic.py``).
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
gravity              density (t/mm^3)    3.5e-11, 1e-10, 4e-10   5.2, 14.0, 50.5
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
the cavity toward the centre (SNR measured by ``studies/cavity_offset.py``).
Gravity acts before the reference image (the recording sees the pressure's displacements from the sagged body): a
silicone's density 1.1e-9 t/mm^3 gives SNR 95.8 (studies/gravity_reference.py): the body is soft.
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

Modules: :mod:`.effects` (the effects and their models), :mod:`.generate` (clean observations, noise,
:func:`make_scenario`), :mod:`.calculix` (recordings made by CalculiX), :mod:`.suite` (cases, scoring,
pooled bounds; the command ``torchfra scenarios``).
"""
from torchfra.scenarios.calculix import CALCULIX_EFFECTS, GENERATORS, check_generator
from torchfra.scenarios.effects import EFFECTS, PRESSURE_MAX, VISCO_TAU1, Effect, is_correct, knob_value
from torchfra.scenarios.generate import (
                                         clean_observations,
                                         dic_grid,
                                         elastic_frames,
                                         face_observer,
                                         make_scenario,
                                         observation_noise,
                                         pressure_trace,
                                         reference_points,
)

__all__ = ["CALCULIX_EFFECTS", "EFFECTS", "Effect", "GENERATORS", "PRESSURE_MAX", "VISCO_TAU1", "check_generator",
           "clean_observations", "dic_grid", "elastic_frames", "face_observer", "reference_points", "is_correct", "knob_value",
           "make_scenario", "observation_noise", "pressure_trace"]
