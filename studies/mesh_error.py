"""The diagnosis mesh's own discretization error, and what it does to the surrogate test.

    python studies/mesh_error.py [--effect compressibility] [--size 3] [--noise 0.25]

A proof-suite recording of ``effect`` at ``size`` made at ``--resolution`` (2: the suite's) without
noise, diagnosed by the resolution-1 model told the noise ``--noise`` (the right candidate only:
``max_refits=1``). Whatever the right refit leaves in a noise-free residual is the coarse mesh's
discretization error (and the load steps' reading of the frames); its score statistics along the
other candidates' directions are the non-centralities those tests carry on every noisy recording of
this kind. Reported per candidate: the score left by the refit as it is, and after the mesh error,
estimated by one refinement (``diagnosis.refit.discretization_error``), is taken out; and the probability
that at least one of them fails the surrogate test at the diagnosis' level on a noisy recording
(non-central chi^2; one-sided for a one-sided candidate), against the noise alone.
Writes ``--out`` (studies/results/study_mesh_error.json) and runs/<name>/ (the diagnosis, its cached solves:
a rerun solves nothing).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from scipy import stats

from torchfra import scenarios
from torchfra.diagnosis.pipeline import diagnose


def failure(scores: dict, rows: dict, level: float) -> float:
    """P(at least one of the candidates' score tests rejects at ``level``) on a noisy recording whose
    noise-free residual left ``scores`` ({name: {"score", "dof", "p_value"}}): non-central chi^2 with
    the score as non-centrality; a one-sided candidate rejects only a pull into its range (its p-value
    below 1/2 says the noise-free pull is one)."""
    keep = 1.0
    for name, s in scores.items():
        lam, dof = max(float(s["score"]), 0.0), int(s["dof"])
        if rows[name].get("one_sided") and dof == 1:
            sign = 1.0 if s["p_value"] <= 0.5 else -1.0
            p = float(stats.norm.sf(stats.norm.isf(level) - sign * math.sqrt(lam)))
        else:
            p = float(stats.ncx2.sf(stats.chi2.isf(level, dof), dof, lam)) if lam > 0 else level
        keep *= 1.0 - p
    return 1.0 - keep


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--effect", default="compressibility", help="a library effect of the proof suite")
    p.add_argument("--size", type=int, default=3, choices=(1, 2, 3))
    p.add_argument("--noise", type=float, default=0.25, help="the noise (mm) the diagnosis is told, and the scores "
                                                             "are whitened with")
    p.add_argument("--resolution", type=int, default=2, choices=(2, 3), help="mesh of the recording (the diagnosis: 1)")
    p.add_argument("--name", default=None, help="run name (default: study_mesh_error_<effect>_s<size>_res<r>)")
    p.add_argument("--runs-dir", default="runs")
    p.add_argument("--out", default="studies/results/study_mesh_error.json")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (recorded)")
    a = p.parse_args(argv)
    if not (a.noise > 0 and math.isfinite(a.noise)):
        p.error(f"--noise {a.noise}: give the noise std in mm, a positive number")
    if a.effect not in scenarios.EFFECTS or scenarios.EFFECTS[a.effect].kind != "library":
        lib = [n for n, e in scenarios.EFFECTS.items() if e.kind == "library"]
        p.error(f"--effect {a.effect}: choose a library effect: {', '.join(lib)}")
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    runs = Path(a.runs_dir)
    rec, clean, meta = scenarios.make_scenario(a.effect, a.size, noise=a.noise, seed=0, resolution=a.resolution,
                                               cache_dir=runs / "scenarios" / "clean", progress=True)
    rec = replace(rec, Z=clean.copy())  # noise-free: what is left after the right refit is the model's error
    run_dir = runs / (a.name or f"study_mesh_error_{a.effect}_s{a.size}_res{a.resolution}")
    d = diagnose(rec, noise=a.noise, correlation=0.0, run_dir=run_dir, progress=True, max_refits=1)
    right = next((t for t in d["tried"] if t["candidates"] == [a.effect]), None)
    if right is None or "mesh_error" not in right or right["mesh_error"]["why"]:
        raise SystemExit(f"the refit of {a.effect} did not pass the checks before the surrogate test, or its mesh "
                         f"error could not be estimated: {None if right is None else right.get('mesh_error')}; "
                         f"see {run_dir / 'diagnosis.json'}")
    rows = {r["name"]: r for r in d["ranking"]}
    level = d["ranking"][0]["level"]
    before, after = right["mesh_error"]["remaining_scores_uncorrected"], right["remaining_scores"]
    per = {n: {"dof": before[n]["dof"], "one_sided": bool(rows[n].get("one_sided")),
               "score_as_it_is": before[n]["score"], "score_mesh_error_out": after[n]["score"]} for n in before}
    out = {
        "command": " ".join(["python studies/mesh_error.py", *(sys.argv[1:] if argv is None else argv)]),
        "effect": a.effect, "size": a.size, "value": meta["value"], "recording_resolution": a.resolution,
        "diagnosis_resolution": d["model"]["resolution"], "noise_mm": a.noise, "level": level,
        "refit": right["fit"]["parameters"], "rms_noise_units": right["fit"]["rms"],
        "mesh_error": {k: v for k, v in right["mesh_error"].items() if k != "remaining_scores_uncorrected"},
        "scores": per,
        "surrogate_test_fails": {"as_it_is": failure(before, rows, level), "mesh_error_out": failure(after, rows, level),
                                 "noise_alone": 1.0 - (1.0 - level) ** len(before)},
        "threads": a.threads, "seconds": time.perf_counter() - t0,
        "solves": d["cost"]["solves"], "note": "scores are non-centralities: a noisy recording adds chi^2 noise to each",
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    f = out["surrogate_test_fails"]
    as_is = ", ".join(f"{n} {v['score_as_it_is']:.2f}" for n, v in per.items())
    taken_out = ", ".join(f"{n} {v['score_mesh_error_out']:.2f}" for n, v in per.items())
    print(f"{a.effect} size {a.size}, recorded at resolution {a.resolution} without noise, refitted at 1: "
          f"scores left {as_is}; with the mesh error out {taken_out}. At noise {a.noise} mm "
          f"the surrogate test fails {f['as_it_is']:.1%} of such recordings as it is, {f['mesh_error_out']:.1%} with "
          f"the mesh error out ({f['noise_alone']:.1%} for the noise alone) -> {a.out}")
    return out


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
