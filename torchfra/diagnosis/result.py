"""The diagnosis as written to ``diagnosis.json``: one record, one serializer, the schema written down once.

:class:`Diagnosis` holds the fields below in the order ``diagnosis.json`` has them; :meth:`Diagnosis.to_json`
is the one place they become JSON (NumPy scalars and arrays as plain numbers and lists).

========================  ============================================================================
field                     meaning
========================  ============================================================================
recording                 the recording's source (file path)
frames, points            frames and points of the recording; ``observations``: finite (uy, uz) values
noise                     ``sigma`` (mm), ``correlation_length_mm``, ``estimated`` ({"sigma", "ell": bool,
                          "frames_left_out"}), ``model_floor`` ({"floor_mm", "below", "why", and
                          "taken_out" when the mesh's error was taken out of the recording})
mismatch_detected         ``detected``, ``alpha``, ``global`` (the chi^2 test of the base fit's residual),
                          ``by_score_test``, ``by_hysteresis``, ``frames_significant``, ``points_significant``
location                  ``clusters``: neighbouring points whose residual is significant
onset                     the first frame after which most frames are significant (or None)
hysteresis                the model-free test of path independence (``applicable``, ``detected``, ...)
ranking                   one row per candidate tested, most significant first (below)
not_testable              candidate -> why this recording cannot test it
not_available             candidate -> why the model (a deck) cannot carry it
model                     {"kind": "actuator", "resolution"} or {"kind": "deck", "path", "camera",
                          "face", "digest"}, and "weight": when the gravity candidate's weight acts,
                          "before_reference" (before the reference image) or "with_load"
tried                     one entry per refit (below)
decision                  "none", "unexplained", a candidate, or candidates the data cannot tell apart
                          joined by "|"
missing_physics           {"kind": "candidate", "name"}, a history-dependent verdict, or {"kind": decision}
parameters                ``base``: the base fit's parameters; ``extended``: the accepted refit's (or None)
fit_before, fit_after     fit reports (below) of the base model and of the decision's model
cost                      ``solves`` (FE solves of this run), ``seconds``, ``resolution``, ``load_steps``,
                          ``ranking_solves``, ``mesh_error_solves``
held_out_frames           the frames held out of every fit (their numbers)
========================  ============================================================================

A **ranking row** (:func:`torchfra.diagnosis.rank.rank`): ``name``, ``parameters``, ``score`` (the score
statistic), ``dof``, ``p_value``, ``one_sided``, ``nuisance_parameters``, ``explained_fraction`` (of the
excess residual), ``confounded_with`` / ``confounded_parameters`` / ``untestable_parameters`` (what the
base parameters absorb), ``tested_parameters``, ``tested_directions`` (a secant's column is
``"<parameter>@<coordinate>"``), ``detectable_change`` (the smallest change detectable with 80 % power,
per direction, in the coordinate), ``projected_fraction``, ``group`` (candidates whose projected
sensitivities nearly coincide), ``significant``, ``level`` (Bonferroni over the candidates),
``secant_points``.

A **refit entry**: ``candidates``, ``fit`` (a fit report), ``checks`` (each acceptance check: ``evidence``,
``away_from_null``, ``inside_range``, ``residual_at_noise``, ``held_out_better``,
``no_other_candidate_significant``, and ``beats_its_members`` for a pair), ``accepted``,
``remaining_scores`` (the other candidates' score tests on its residual), and where they apply
``mesh_error`` (the refinement's estimate), ``chosen``, ``rival``, ``partial``, ``loop_left_in_residual``.

A **fit report**: ``rms`` and ``nis_per_observation`` of the whitened residual, ``chi2_p_value``,
``log_evidence`` (Laplace), ``log_likelihood``, ``held_out_log_density``, ``held_out_rms``,
``parameters`` (per parameter: ``mean``, ``std``, ``unit``, ``coordinate``, ``coordinate_mean``,
``coordinate_std``), ``solves``, ``seconds``, and for a refit ``scan`` (its start).
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfra.observation.recording import Recording


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(type(o))


@dataclass
class Diagnosis:
    """A diagnosis's record, field by field as in ``diagnosis.json`` (the module docstring says what each holds)."""

    recording: str
    frames: int
    points: int
    observations: int
    noise: dict
    mismatch_detected: dict
    location: dict
    onset: dict | None
    hysteresis: dict
    ranking: list
    not_testable: dict
    not_available: dict
    model: dict
    tried: list
    decision: str
    missing_physics: dict
    parameters: dict
    fit_before: dict
    fit_after: dict
    cost: dict
    held_out_frames: list

    @classmethod
    def of(cls, rec: Recording, nm, base, where: dict, loop: dict, ranking: list, not_testable: dict,
           not_available: dict, deck, resolution: int, load_steps: int, tried: list, verdict, base_report: dict,
           ranking_solves: int, seconds: float, held: np.ndarray, alpha: float,
           weight: str = "before_reference") -> "Diagnosis":
        """The record of a diagnosis from its steps' outcomes (:mod:`torchfra.diagnosis.pipeline`)."""
        accepted = verdict.accepted
        decision = verdict.decision
        mesh_solves = sum(t["mesh_error"]["solves"] for t in tried if "mesh_error" in t)
        mesh_solves += base.floor["taken_out"]["solves"] if "taken_out" in base.floor else 0
        fe_solves = (base.start_solves + base.solves + ranking_solves + sum(t["fit"]["solves"] for t in tried)
                     + verdict.rival_solves + mesh_solves)
        return cls(
            recording=rec.source,
            frames=int(rec.n_frames), points=int(rec.n_points), observations=int(np.isfinite(rec.Z).sum()),
            noise={"sigma": nm.sigma, "correlation_length_mm": nm.ell, "estimated": nm.estimated,
                   "model_floor": base.floor},
            mismatch_detected={"detected": where["detected"], "alpha": alpha, "global": where["global"],
                               "by_score_test": where["detected_by_score"],
                               "by_hysteresis": where["detected_by_hysteresis"],
                               "frames_significant": where["frames_significant"],
                               "points_significant": where["points_significant"]},
            location={"clusters": where["clusters"]},
            onset=where["onset"],
            hysteresis=loop,
            ranking=ranking,
            not_testable=not_testable,
            not_available=not_available,
            model={**({"kind": "actuator", "resolution": resolution} if deck is None else
                      {"kind": "deck", "path": str(deck.path), "camera": deck.camera, "face": deck.face,
                       "digest": base.phys.deck_digest}), "weight": weight},
            tried=tried,
            decision=decision,
            missing_physics=({"kind": "candidate", "name": decision} if decision not in ("none", "unexplained") else
                             verdict.history_verdict or (loop["physics"] if loop["detected"] else {"kind": decision})),
            parameters={"base": base_report["parameters"], "extended": accepted[2]["parameters"] if accepted else None},
            fit_before=base_report,
            fit_after=accepted[2] if accepted else base_report,
            cost={"solves": fe_solves, "seconds": seconds, "resolution": resolution if deck is None else None,
                  "load_steps": load_steps, "ranking_solves": ranking_solves, "mesh_error_solves": mesh_solves},
            held_out_frames=[int(rec.frames[k]) for k in held],
        )

    def to_json(self) -> dict:
        """The record as ``diagnosis.json`` holds it (a dict in the fields' order)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def write_outputs(run_dir: Path, out: dict, rec: Recording, raw: np.ndarray, where: dict, base_fit, accepted_fit,
                  sigma: float, taken_out: np.ndarray | None) -> None:
    """``diagnosis.json``, ``residuals.npz`` (the residuals before and after, the point RMS, the mesh's
    error taken out) and the figures, into ``run_dir``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "diagnosis.json").write_text(json.dumps(out, indent=1, default=_json_default))
    np.savez(run_dir / "residuals.npz", before=raw, after=(rec.Z - accepted_fit.evaluation.Y) if accepted_fit else raw,
             point_rms_before=where["point_rms"], X=rec.X, point_ids=rec.point_ids,
             mesh_error_taken_out=np.zeros_like(raw) if taken_out is None else taken_out)
    try:
        from torchfra.report.diagnosis import write_figures
    except ImportError:  # figures need matplotlib
        return
    write_figures(run_dir, rec, out, base_fit, accepted_fit, sigma, where)
