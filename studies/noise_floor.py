"""How little noise the diagnosis can take: the base model's own discretization error on a null.

    python studies/noise_floor.py [--c10 0.0062] [--resolution 2]

A proof-suite null (no effect, true C10 ``--c10``) recorded at ``--resolution`` (2: the suite's)
*without noise* is diagnosed by the resolution-1 model. The base fit cannot explain the recording
exactly: what it leaves is the coarse mesh's discretization error (and the load steps' reading of the
frames). Its global chi^2 statistic and each candidate's score statistic are non-centralities, and
they grow as 1/sigma^2 when the noise sigma shrinks; on a noisy null at noise sigma the tests then
fire with the non-central chi^2 probabilities this script reports for a scan of sigma (the
diagnosis' own levels: alpha/2 for the global test, alpha/2 shared by the candidates). Between the
largest single test's probability and the sum over the tests lies the rate at which a null is
flagged as a mismatch (the tests share the residual, so neither is exact).

The same is measured with the error estimated by one refinement (``diagnosis.refit.discretization_error``
at the base fit) taken out of the recording before the fit: how far such a correction would move the
floor. The diagnosis does not do this for the base fit today (README "How little noise").

Writes ``--out`` (studies/results/study_noise_floor.json) and runs/<name>/ (both diagnoses and their cached
FE solves: a rerun solves nothing).
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
from torchfra.diagnosis.refit import discretization_error

NOISE_SCAN = (1.0, 0.5, 0.25, 0.1, 0.05, 0.025)  # mm


def fires(noncentrality: float, dof: int, level: float, one_sided: bool = False, pull_in: bool = True) -> float:
    """P(a chi^2 test with ``dof`` rejects at ``level``) when its statistic is non-central chi^2 with
    ``noncentrality``; a one-sided 1-dof test rejects only a pull into the range (``pull_in``)."""
    lam = max(float(noncentrality), 0.0)
    if one_sided and dof == 1:
        sign = 1.0 if pull_in else -1.0
        return float(stats.norm.sf(stats.norm.isf(level) - sign * math.sqrt(lam)))
    return float(stats.ncx2.sf(stats.chi2.isf(level, dof), dof, lam)) if lam > 0 else level


def scan(d: dict, sigma0: float, alpha: float) -> dict:
    """The tests' firing probabilities on a noisy null at each sigma of NOISE_SCAN, from the
    noise-free diagnosis ``d`` whitened at ``sigma0``."""
    g = d["mismatch_detected"]["global"]
    lam_g = g["statistic"]  # noise-free: the statistic is the non-centrality
    tested = [r for r in d["ranking"] if r["dof"] > 0]
    noise_alone = min(alpha / 2 + sum(r["level"] for r in tested), 1.0)  # the levels' union bound
    out = {}
    for s in NOISE_SCAN:
        f = (sigma0 / s) ** 2
        p_g = fires(lam_g * f, g["dof"], alpha / 2)
        p_c = {r["name"]: fires(r["score"] * f, r["dof"], r["level"], bool(r.get("one_sided")),
                                r["p_value"] <= 0.5) for r in tested}
        p_all = [p_g, *p_c.values()]
        out[f"{s:g}"] = {"global_test": p_g, "largest_score_test": max(p_c.values()),
                         "flagged_at_least": max(p_all), "flagged_at_most": min(sum(p_all), 1.0),
                         "noise_alone_at_most": noise_alone,
                         "score_tests": p_c}
    return out


def floor(table: dict, rate: float = 0.05) -> float | None:
    """The smallest scanned sigma at which a null is flagged at most ``rate`` of the time (upper bound)."""
    ok = [float(s) for s, v in table.items() if v["flagged_at_most"] <= rate]
    return min(ok) if ok else None


def summary(d: dict) -> dict:
    g = d["mismatch_detected"]["global"]
    return {"C10": d["parameters"]["base"]["C10"]["mean"], "global_statistic": g["statistic"], "dof": g["dof"],
            "rms_noise_units": g["rms"],
            "scores": {r["name"]: {"score": r["score"], "dof": r["dof"], "one_sided": bool(r.get("one_sided"))}
                       for r in d["ranking"] if r["dof"] > 0}}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--c10", type=float, default=0.0062, help="the null recording's true C10 (MPa)")
    p.add_argument("--resolution", type=int, default=2, choices=(2, 3), help="mesh of the recording (the diagnosis: 1)")
    p.add_argument("--noise", type=float, default=1.0, help="the noise (mm) the noise-free diagnosis is whitened "
                                                            "with; the scan rescales it")
    p.add_argument("--alpha", type=float, default=0.01, help="the diagnosis' level")
    p.add_argument("--name", default=None, help="run name (default: study_noise_floor_c<c10>_res<r>)")
    p.add_argument("--runs-dir", default="runs")
    p.add_argument("--out", default="studies/results/study_noise_floor.json")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (recorded)")
    a = p.parse_args(argv)
    if not (a.noise > 0 and math.isfinite(a.noise)):
        p.error(f"--noise {a.noise}: give the noise std in mm, a positive number")
    if not (a.c10 > 0 and math.isfinite(a.c10)):
        p.error(f"--c10 {a.c10}: give the true C10 in MPa, a positive number")
    if not 0 < a.alpha < 1:
        p.error(f"--alpha {a.alpha}: give a level between 0 and 1")
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    runs = Path(a.runs_dir)
    rec, clean, meta = scenarios.make_scenario("none", 0, truth_c10=a.c10, noise=a.noise, seed=0,
                                               resolution=a.resolution, cache_dir=runs / "scenarios" / "clean",
                                               progress=True)
    rec = replace(rec, Z=clean.copy())  # noise-free: what the base fit leaves is the model's own error
    run_dir = runs / (a.name or f"study_noise_floor_c{a.c10:g}_res{a.resolution}")
    kw = dict(noise=a.noise, correlation=0.0, alpha=a.alpha, progress=True, max_refits=0)
    as_is = diagnose(rec, run_dir=run_dir / "as_it_is", **kw)
    z = {"C10": as_is["parameters"]["base"]["C10"]["coordinate_mean"]}
    delta, info = discretization_error(rec, (), z, as_is["model"]["resolution"], 10,
                                       cache=run_dir / "as_it_is" / "solves")
    if delta is None:
        raise SystemExit(f"the mesh error could not be estimated: {info['why']}")
    out_fit = diagnose(replace(rec, Z=rec.Z - delta), run_dir=run_dir / "mesh_error_out", **kw)
    t_as, t_out = scan(as_is, a.noise, a.alpha), scan(out_fit, a.noise, a.alpha)
    out = {
        "command": " ".join(["python studies/noise_floor.py", *(sys.argv[1:] if argv is None else argv)]),
        "truth_c10": a.c10, "recording_resolution": a.resolution, "diagnosis_resolution": as_is["model"]["resolution"],
        "observations": as_is["observations"], "whitened_at_mm": a.noise, "alpha": a.alpha,
        "mesh_error": info,
        "noise_free": {"as_it_is": summary(as_is), "mesh_error_out": summary(out_fit)},
        "noisy_null_flagged": {"as_it_is": t_as, "mesh_error_out": t_out},
        "floor_mm_at_5_percent": {"as_it_is": floor(t_as), "mesh_error_out": floor(t_out)},
        "threads": a.threads, "seconds": time.perf_counter() - t0,
        "solves": as_is["cost"]["solves"] + out_fit["cost"]["solves"] + info["solves"],
        "note": "noise-free statistics are non-centralities; the flagged rate lies between flagged_at_least and "
                "flagged_at_most (the tests share the residual)",
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"null at C10 {a.c10:g} recorded at resolution {a.resolution} without noise, fitted at 1: global chi^2 "
          f"{out['noise_free']['as_it_is']['global_statistic']:.3g} at {a.noise:g} mm "
          f"({out['noise_free']['mesh_error_out']['global_statistic']:.3g} with the mesh error out, "
          f"{info['rms_mm']:.3g} mm RMS)")
    for s in NOISE_SCAN:
        u, v = t_as[f"{s:g}"], t_out[f"{s:g}"]
        print(f"  noise {s:g} mm: a null flagged {u['flagged_at_least']:.1%}-{u['flagged_at_most']:.1%} as it is, "
              f"{v['flagged_at_least']:.1%}-{v['flagged_at_most']:.1%} with the mesh error out "
              f"(noise alone <= {u['noise_alone_at_most']:.1%})")
    print(f"-> {a.out}")
    return out


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
