"""The proof suite of the missing-physics diagnosis: recordings with one concealed effect each
(torchfra.scenarios), diagnosed without being told the effect, scored against it.

    python scripts/scenarios.py                               # every effect, 3 noise seeds, sigma 1 mm
    python scripts/scenarios.py --effects gravity,none --seeds 1 --correlation 0,4
    python scripts/scenarios.py --quick                       # smoke run: resolution 1, few frames
    torchrun --standalone --nproc-per-node 2 scripts/scenarios.py   # cases shared out over 2 ranks

writes runs/<name>/: results.json (one row per case), table.md (per effect and SNR band: identification
rate, false attributions on nulls, "unexplained" rate, RMS before/after in noise units, FE solves,
wall time; bands by the SNR left after the base model's C10 refit), summary.json, and the diagnosis' own folders under diag/<case>/. Noise-free observations
are cached under runs/<name>/clean/. Rerunning resumes: cases with a result row are not redone.

    python scripts/scenarios.py --pool studies/results/proof_suite/proof_suite_*.json --name pooled   # no FE work

pools the rows of earlier runs into one table with exact 95 % bounds and the proof suite's targets.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from torchfra.cli.flags import PEAK_PRESSURE, add_peak_pressure, add_renamed, add_run_folder, add_threads, parser

# the names torchfra.scenarios defines (tests/test_help.py checks they agree), here so that --help needs no torch
EFFECTS = ("none", "mooney_rivlin", "compressibility", "fiber_stiffness", "gravity", "compliant_base",
           "pressure_sensor", "cavity_offset", "viscoelasticity", "stiff_base_region", "fiber_debond", "sensor_lag")
GENERATORS = ("torchfra", "calculix")
CALCULIX_EFFECTS = ("none", "mooney_rivlin", "compressibility", "fiber_stiffness", "gravity", "compliant_base",
                    "pressure_sensor")


class _Folder(argparse.Action):
    """``--out FOLDER``, the old spelling: the suite's folder as a path (now ``--name`` under ``--runs-dir``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        import sys

        print(f"{option_string} is an old spelling: use --name NAME (the folder <runs-dir>/<name>/)", file=sys.stderr)
        namespace.out = values


def __getattr__(name: str):
    """The suite's driver functions (torchfra.scenarios.suite) under this module too, imported on first use."""
    from torchfra.scenarios import suite

    if name in ("cases", "pooled", "run_cases", "table"):
        return getattr(suite, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_case(case: dict, a, out: Path, diagnose) -> dict:
    """One case of the suite: :func:`torchfra.scenarios.suite.run_case` (imported when a case runs)."""
    from torchfra.scenarios.suite import run_case as run

    return run(case, a, out, diagnose)


def build_parser():
    """The flags of ``torchfra scenarios`` (no torch imported)."""
    p = parser(__doc__)
    p.add_argument("--effects", default="all", help=f"'all' or a comma list of: {', '.join(EFFECTS)}")
    p.add_argument("--seeds", type=int, default=3, help="noise seeds per scenario")
    p.add_argument("--first-seed", type=int, default=0,
                   help="the first noise seed's index: more seeds of a suite already run, under new names")
    p.add_argument("--noise", type=float, default=1.0, metavar="MM", help="noise std sigma (mm)")
    p.add_argument("--correlation", default="0",
                   help="comma list of noise correlation lengths ell (mm); 0 is i.i.d. noise")
    add_run_folder(p, "scenarios", "results, tables and the diagnoses' folders")
    p.add_argument("--out", action=_Folder, default=None, help=argparse.SUPPRESS)
    p.add_argument("--sizes", default="all", help="'all' or a comma list of effect sizes (1, 2, 3)")
    p.add_argument("--estimate-noise", action="store_true",
                   help="do not tell the diagnosis sigma and the correlation length: it estimates them")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: generation at resolution 1 with 6 frames, largest size only, one seed")
    p.add_argument("--verbose", action="store_true", help="show the diagnosis' own progress")
    add_threads(p)
    p.add_argument("--generator", default="torchfra", choices=GENERATORS,
                   help="the code that makes the recordings: torchfra's own FE model at --resolution, or CalculiX "
                        "(ccx) on the deck torchfra writes (C3D20R bricks, fibers as SPRINGA springs; effects: "
                        f"{', '.join(CALCULIX_EFFECTS)})")
    p.add_argument("--resolution", type=int, default=2, choices=(1, 2, 3),
                   help="mesh resolution of the model that makes the recordings; the diagnosis works at 1, the "
                        "default of every other command, and 2 keeps the recordings off its mesh (no inverse crime)")
    add_renamed(p, "--mesh", "--resolution", "resolution", type=int)
    add_peak_pressure(p, PEAK_PRESSURE, "the largest recorded pressure (MPa); CalculiX's C3D20R stops near 0.013 at "
                      "resolution 2")
    p.add_argument("--pool", nargs="+", default=None, metavar="RESULTS.json",
                   help="no FE work: pool the rows of earlier runs' results.json files (a recording listed twice "
                        "counts once, from the last file) into one table with exact 95 %% bounds of every rate and "
                        "the proof suite's targets judged on them; writes <runs-dir>/<name>/pooled.md and pooled.json")
    return p


def main(argv=None) -> dict:
    p = build_parser()
    a = p.parse_args(argv)
    a.out = a.out or str(Path(a.runs_dir) / a.name)
    a.pressure = a.peak_pressure  # the suite's cases read it under its old name
    from torchfra.scenarios.suite import _write_json, pooled

    if a.pool:
        text, summary = pooled([Path(f) for f in a.pool])
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "pooled.md").write_text(text)
        _write_json(out / "pooled.json", summary)
        print(text + f"{summary['recordings']} recordings from {len(a.pool)} files"
              + (f" ({summary['duplicates_dropped']} listed twice, counted once)" if summary["duplicates_dropped"]
                 else "") + f"; written to {out / 'pooled.md'}")
        return summary
    import torch

    from torchfra import scenarios
    from torchfra.scenarios.suite import cases, run_cases, table

    torch.set_num_threads(a.threads)
    torch.set_default_dtype(torch.float64)
    effects = list(scenarios.EFFECTS) if a.effects == "all" else [e.strip() for e in a.effects.split(",") if e.strip()]
    for e in effects:
        scenarios.knob_value(e, 0)  # unknown names fail here, before any FE work
        scenarios.check_generator(e, a.generator)
    if not 0 < a.pressure <= scenarios.PRESSURE_MAX:
        raise ValueError(f"--peak-pressure must lie in (0, {scenarios.PRESSURE_MAX}] MPa, got {a.pressure}")
    if a.seeds < 1 or a.first_seed < 0 or not a.noise > 0:
        raise ValueError(f"need --seeds >= 1, --first-seed >= 0 and --noise > 0, got {a.seeds}, {a.first_seed} "
                         f"and {a.noise}")
    correlations = [float(x) for x in a.correlation.split(",")]
    if any(c < 0 for c in correlations):
        raise ValueError(f"correlation lengths must be >= 0 mm, got {a.correlation}")
    from torchfra.diagnosis.pipeline import diagnose

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.json"
    rows = {r["case"]: r for r in json.loads(results.read_text())["rows"]} if results.exists() else {}
    sizes = None if a.sizes == "all" else {int(x) for x in a.sizes.split(",")}
    todo = cases(effects, 1 if a.quick else a.seeds, correlations, a.quick, sizes, a.generator, a.first_seed)
    for c in todo:
        c["case"] += (f"_p{a.pressure:g}" if a.pressure != scenarios.PRESSURE_MAX else "") + \
            (f"_res{a.resolution}" if a.resolution != 2 and not a.quick else "")
    if a.estimate_noise:
        for c in todo:
            c["case"] += "_estnoise"
    t0 = time.perf_counter()
    rows, reused = run_cases(todo, rows, results, a, lambda case: run_case(case, a, out, diagnose))
    if rows is None:  # a rank other than 0: its rows went to rank 0
        return {}
    selected = [rows[c["case"]] for c in todo]
    (out / "table.md").write_text(table(selected))
    summary = {"cases": len(selected), "reused": reused, "correct": sum(r["correct"] for r in selected),
               "seconds": time.perf_counter() - t0, "table": str(out / "table.md"), "results": str(results)}
    _write_json(out / "summary.json", summary)
    print(table(selected))
    return summary



if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
