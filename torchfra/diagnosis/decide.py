"""Step 4 of the diagnosis: the decision among the extensions that passed every check."""
from __future__ import annotations

from dataclasses import dataclass, replace

from torchfra.actuator.candidates import (
    CANDIDATE_PARAMETERS,
    HISTORY_DEPENDENT_CANDIDATES,
    RIVALS,
)
from torchfra.diagnosis.fit import gauss_newton, load_map_start
from torchfra.diagnosis.locate import _pressure_direction, hysteresis
from torchfra.diagnosis.model import ActuatorPhysics
from torchfra.diagnosis.refit import RefitContext, _fit_report, refit


def decide(tried: list[dict], ranking: list[dict], evidence_threshold: float) -> tuple[str, dict | None]:
    """The decision from the refits ``tried`` (each with ``candidates``, ``accepted`` and
    ``fit["log_evidence"]``): "unexplained" when none was accepted; else the accepted one with the
    largest evidence (a candidate confounded with another at the null, e.g. the pressure sensor's
    group, by its group's names, less the members refitted themselves without passing within the
    margin: the data told those apart), joined by "|" with every other accepted one within ``evidence_threshold`` of it:
    the data cannot tell those apart, so none of them is the winner alone. Marks the chosen entry
    ``chosen`` and the others named ``rival``; returns (decision, chosen entry or None)."""
    passed = [t for t in tried if t["accepted"]]
    if not passed:
        return "unexplained", None
    best = max(passed, key=lambda t: t["fit"]["log_evidence"])
    best["chosen"] = True
    combo = best["candidates"]
    row = next(r for r in ranking if r["name"] == combo[0])
    # the group is confounding at the null (linearized); a member refitted itself and not within the
    # margin was told apart by the data (a compressible bulk beside a compliant fiber, whose secant
    # spans the bulk's direction at the null), so only members never refitted (or a base parameter,
    # C10 for a pressure gain) are named with the winner
    refitted = {c for t in tried for c in t["candidates"]}
    names = (["+".join(combo)] if len(row["group"]) == 1 or len(combo) > 1 else
             [g for g in row["group"] if g == combo[0] or g not in refitted])
    for t in passed:
        if t is not best and best["fit"]["log_evidence"] - t["fit"]["log_evidence"] < evidence_threshold:
            t["rival"] = True
            names.append("+".join(t["candidates"]))
    return "|".join(names), best





@dataclass
class Verdict:
    """Steps 3 and 4's outcome: the ``decision`` ("none", "unexplained", a candidate, or candidates the
    data cannot tell apart joined by "|"), the accepted extension ``(combo, Fit, report)`` or None, the
    verdict on history-dependent physics the library cannot name (None: none), and the FE solves the
    rival's fit spent."""

    decision: str
    accepted: tuple | None
    history_verdict: dict | None
    rival_solves: int


def refit_and_decide(ctx: RefitContext, detected: bool, loop: dict, max_refits: int | None, base_phys,
                     base_z: dict[str, float]) -> Verdict:
    """Refit every significant candidate (at most ``max_refits``; the best pair when no single one
    passes), decide among the extensions that passed, and check the winner against its rival and
    against a load-unload loop left in its residual."""
    if not detected:
        return Verdict("none", None, None, 0)
    order = [r for r in ctx.ranking if r["significant"] and r["dof"] > 0]
    singles = [(r["name"],) for r in order[:max_refits]]  # None: every significant candidate
    pair = [(order[0]["name"], order[1]["name"])] if len(order) >= 2 else []
    # every significant single candidate is refitted, not only the first that passes: the score
    # ranks by the linearization at the null, and two terms that switch on far from it (a bulk
    # compliance, a fiber compliance) can both explain a recording once refitted (measured: a
    # fiber compliance at SNR 13 after the base fit was first explained by D1 alone). The pair
    # is tried only when no single candidate passes.
    for i, combo in enumerate(singles):
        refit(ctx, combo, len(singles) - i + len(pair))
    if not any(t["accepted"] for t in ctx.tried):
        for combo in pair:
            refit(ctx, combo, 1)
    decision, best = decide(ctx.tried, ctx.ranking, ctx.evidence_threshold)
    history_verdict, rival_solves = None, 0
    if best is not None and any(c in RIVALS for c in best["candidates"]):
        decision, best, history_verdict, rival_solves = _against_the_rival(ctx, decision, best)
    if best is not None and loop["detected"] and _loop_left(ctx, best, base_phys, base_z):
        # what the candidate explained is part of the story only
        best["chosen"] = False
        best["partial"] = True
        decision, best = "unexplained", None
    accepted = None if best is None else (tuple(best["candidates"]), *ctx.fits[tuple(best["candidates"])])
    return Verdict(decision, accepted, history_verdict, rival_solves)


def _against_the_rival(ctx: RefitContext, decision: str, best: dict) -> tuple[str, dict | None, dict | None, int]:
    """A creeping body and a cavity pressure lagging its sensor make the same loop once the lag is
    shorter than the frame spacing: the body's physics is named only if it beats the lag decisively.
    Returns (decision, best or None, the history verdict or None, the rival fit's FE solves)."""
    rival = [RIVALS[c] for c in best["candidates"] if c in RIVALS]
    bar, white, fit_frames = ctx.bar, ctx.white, ctx.fit_frames
    bar.phase(f"fitting the rival of {' + '.join(best['candidates'])}: {rival[0]}", bar.FIT_SOLVES + 2)
    phys = ActuatorPhysics(ctx.rec, (rival[0],), ctx.resolution, ctx.load_steps, ctx.cache, deck=ctx.deck,
                           weight=ctx.weight)
    free = ["C10"] + list(CANDIDATE_PARAMETERS[rival[0]])
    z0, _, _ = load_map_start(phys, white, free, free[1:], phys.null_point(ctx.c10), fit_frames)
    rfit = gauss_newton(phys, white, free, z0, fit_frames, progress=bar.tick)
    rrep = _fit_report(rfit, white, fit_frames, ctx.held, len(free))
    margin = best["fit"]["log_evidence"] - rrep["log_evidence"]
    best["rival"] = {"name": rival[0], "fit": rrep, "evidence_margin": margin}
    if margin > ctx.evidence_threshold:
        return decision, best, None, rfit.solves
    best["chosen"] = False
    best["partial"] = True
    threshold = ctx.evidence_threshold
    verdict = {
        "kind": "history-dependent",
        "meaning": ("a creeping body (viscoelasticity) or a cavity pressure lagging its sensor: the "
                    f"recording cannot tell them apart (log evidence {margin:+.1f} for the creep); a hold "
                    "at constant pressure would (a body creeps on, a lagging pressure settles)")
        if margin > -threshold else
        ("the cavity's pressure lags the recorded one (by "
         f"{rfit.z['pressure_lag']:.3g} of the recording's duration), which explains the recording "
         f"better than a creeping body (log evidence {-margin:+.1f})"),
        "possible_causes": ["viscoelasticity", "a time lag between the pressure sensor and the cavity"]
        if margin > -threshold else ["a time lag between the pressure sensor and the cavity"]}
    return "unexplained", None, verdict, rfit.solves


def _loop_left(ctx: RefitContext, best: dict, base_phys, base_z: dict[str, float]) -> bool:
    """Whether a load-unload loop of the recording is left unexplained by the winner ``best``: a loop
    is explained only by history-dependent physics, and only if none is left in the extended model's
    residual (the same path-independence test on recording - model)."""
    history = set(best["candidates"]) & set(HISTORY_DEPENDENT_CANDIDATES)
    ext = ctx.fits[tuple(best["candidates"])][0]
    left = (hysteresis(replace(ctx.rec, Z=ctx.rec.Z - ext.evaluation.Y), ctx.white, ctx.alpha / 4,
                       _pressure_direction(base_phys, base_z)) if history else None)
    best["loop_left_in_residual"] = left
    return not history or left["detected"]
