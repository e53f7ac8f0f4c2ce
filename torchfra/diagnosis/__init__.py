"""Finding the physics the model left out: locate the mismatch, rank the candidates, refit, decide.

The diagnosis of a recording (docs/diagnosis.md), one module per step:

1. **Calibrate** the base model (C10) by Gauss-Newton on the posterior with the exact
   sensitivities (a Laplace posterior: MAP, covariance and log evidence verified against the exact
   posterior by quadrature, one and two parameters, on a nonlinear scaling-law stand-in for the
   actuator in tests/test_discovery.py).
2. **Locate.** Whitened residuals over points x frames with the noise model (i.i.d. or spatially
   correlated with a squared-exponential kernel; sigma and the correlation length are estimated
   from frame-to-frame differences when not given). Global test: the residual sum of squares
   against chi^2 with n - d degrees of freedom. Onset: per-frame chi^2 tests with
   Benjamini-Hochberg control; the onset is the first frame after which the significant frames
   are the majority. Space: per-point chi^2 tests (BH at ``alpha``) grouped into clusters of
   neighbouring points. Below the model's own noise floor (:func:`model_floor`: its
   discretization error alone would set off these tests) that error, estimated by one refinement
   at the base fit (:func:`discretization_error`), is taken out of the recording and C10 refitted
   first (``noise.model_floor.taken_out``).
   **Hysteresis** (model-free, :func:`hysteresis`): a recording that comes back down from its
   largest pressure is tested for path independence, loading against unloading at equal pressure;
   every candidate of the library is hyperelastic and quasi-static, so a loop means
   history-dependent physics (viscoelasticity, a sensor lag, damage, friction, drift) and the
   decision is ``"unexplained"`` with that class named, whatever a candidate explains besides.
   The omnibus half of the level is then shared by the chi^2 total and the hysteresis test.
3. **Rank without refitting.** For each candidate, the whitened sensitivities of the observations
   to its parameters at the calibrated point (candidates at their null values), projected off the
   span of the calibrated parameters' sensitivities; the Lagrange-multiplier (score) statistic
   ``e' U (U'U)^-1 U' e ~ chi^2_q`` under the base model, its p-value, and the fraction of the
   excess residual it can explain. A candidate whose sensitivities lie (almost) in the span of the
   base parameters' is reported ``confounded_with`` them (a pressure gain with C10: the scaling
   law); candidates whose projected sensitivities nearly coincide form a group. The smallest
   effect each candidate could show at this noise (80 % power at the test level) is reported. A
   candidate whose effect changes its shape as it grows (a fiber compliance:
   :data:`torchfra.actuator.candidates.FAR_SECANTS`) is tested along its derivative and the secant to a point two prior
   standard deviations off its null together (two degrees of freedom): the derivative at a nearly
   inextensible fiber carries a quarter of a compliant fiber's effect, the pair more than 98 %.
4. **Refit and decide.** Every significant candidate (in order of their score statistic; at most
   ``max_refits`` when given) is added alone, and the best pair when none passes, and the extended parameters
   refitted by Gauss-Newton, started
   where a coarse scan along the score direction stops falling (``scan_start``: a term that switches
   on far from its null, such as the bulk compliance D1, is invisible to a local fit from there); an
   extension is accepted only if its Laplace log evidence beats the base model's (a pair's: also
   each of its members' refitted alone, :func:`beats_its_members`) by more than
   ``evidence_threshold`` (5: decisive on Jeffreys' scale), every added parameter is more than 3
   posterior standard deviations from its null and inside its range, the residual returns to the
   noise level (global test passes at ``alpha``, RMS within 10 % of the noise), the held-out
   frames are predicted better, and no other candidate's score test is still significant on the
   extended model's residual (a surrogate explains only part of the mismatch; the test projects off
   the extended model's sensitivities at its MAP, one-sided for a one-sided candidate, on the residual
   less the diagnosis mesh's own discretization error, estimated by one refinement at the MAP:
   :func:`discretization_error`; a recording of a body, or of a finer model, carries it, and at the
   suite's noise it alone would fail the test on about one recording in eight). Of the extensions
   that pass, the one with the largest evidence is the decision; any other within
   ``evidence_threshold`` of it explains the recording about as well, and is named beside it
   (``"a|b"``: the data cannot tell them apart). Nothing passes: ``"unexplained"``, with where the
   mismatch sits.

Every FE solve is cached in the run folder (array-only .npz): a resumed diagnosis redoes no solve.


Modules: :mod:`.noise` (the noise model, its estimate, whitening), :mod:`.fit` (Gauss-Newton with a
Laplace posterior, and the refits' starts), :mod:`.locate` (the global, per-frame, per-point and
hysteresis tests), :mod:`.rank` (the score tests), :mod:`.refit` (an extension's refit and its checks),
:mod:`.decide` (the decision), :mod:`.result` (``diagnosis.json`` and its schema), :mod:`.pipeline`
(:func:`diagnose`: the steps in order), :mod:`.model` (the actuator or a deck seen through a recording,
with exact sensitivities).
"""
from torchfra.diagnosis.model import ActuatorPhysics, Evaluation, HistoryPhysics
from torchfra.diagnosis.noise import DiagnosisError, NoiseModel, Whitener, estimate_noise
from torchfra.diagnosis.pipeline import ALL_CANDIDATES, diagnose
from torchfra.diagnosis.refit import NOISE_FLOOR_MM, discretization_error, model_floor
from torchfra.diagnosis.result import Diagnosis

__all__ = ["ALL_CANDIDATES", "ActuatorPhysics", "Diagnosis", "DiagnosisError", "Evaluation", "HistoryPhysics",
           "NOISE_FLOOR_MM", "NoiseModel", "Whitener", "diagnose", "discretization_error", "estimate_noise", "model_floor"]
