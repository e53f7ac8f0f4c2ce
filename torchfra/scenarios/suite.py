"""The proof suite's cases, their diagnosis and scoring: one row per recording, tables by effect and
SNR band, and the pooled rates of several runs with exact (Clopper-Pearson) 95 % bounds, judged against
the suite's targets. The command is ``torchfra scenarios`` (:mod:`torchfra.cli.scenarios`)."""
from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchfra import scenarios

NULL_C10 = (0.0048, 0.0062, 0.0075)  # MPa, truths of the null scenarios (the paper's prior range)
BANDS = ((0.0, 10.0, "<10"), (10.0, 25.0, "10-25"), (25.0, float("inf"), ">=25"))


def snr_band(snr: float, kind: str) -> str:
    if kind == "null":
        return "null"
    return next(label for lo, hi, label in BANDS if lo <= snr < hi)


def cases(effects, seeds: int, correlations, quick: bool, sizes=None, generator: str = "torchfra",
          first_seed: int = 0) -> list[dict]:
    """Every (effect, size, truth C10, trace, seed, noise correlation) to run, with a unique name;
    seeds ``first_seed`` .. ``first_seed + seeds - 1``."""
    out = []
    for effect in effects:
        e = scenarios.EFFECTS[effect]
        if effect == "none" and generator != "torchfra":  # a CalculiX recording costs minutes: the effects' null
            variants = [(0, 0.0062, "ramp")]
        elif effect == "none":
            variants = [(0, c, "ramp") for c in NULL_C10] + [(0, 0.0062, "cycle")]  # the lag's trace too
        else:
            every = range(1, len(e.sizes) + 1)
            chosen = every[-1:] if quick else [k for k in every if sizes is None or k in sizes]
            variants = [(k, 0.0062, None) for k in chosen]
        for size, c10, trace in variants:
            for seed in range(first_seed, first_seed + seeds):
                for ell in correlations:
                    name = (f"{effect}_s{size}" + (f"_c{c10:g}_{trace}" if effect == "none" else "")
                            + f"_seed{seed}_" + (f"ell{ell:g}" if ell else "iid")
                            + ("" if generator == "torchfra" else f"_{generator}"))
                    out.append(dict(case=name, effect=effect, size=size, truth_c10=c10, trace=trace, seed=seed,
                                    correlation=ell))
    return out


def noise_seed(case: dict) -> int:
    """The seed of a case's noise: its seed index mixed with everything else that names the case
    (effect, size, truth C10, trace, correlation), so that cases differing only in those draw
    independent noise. With the bare index the four null variants of one seed shared one draw: their
    global tests' p-values came in near-equal fours, 15 independent draws in 60 recordings."""
    text = json.dumps([case["effect"], case["size"], case["truth_c10"], case["trace"], case["correlation"],
                       case["seed"]])
    return int(hashlib.sha256(text.encode()).hexdigest()[:8], 16)


def kept_files(cached: Path, prefix: str) -> int:
    """How many ``<prefix>_*.npz`` results a diagnosis kept in ``cached`` (0 before it ran); a write
    cut short leaves a ``.tmp.npz``, which is no result."""
    if not cached.exists():
        return 0
    return sum(not f.name.endswith(".tmp.npz") for f in cached.glob(f"{prefix}_*.npz"))


def fe_work(cached: Path) -> int:
    """The FE work a diagnosis kept in ``cached``: its elastic solves (``solve_*.npz``) and its marches
    of the FE model with history variables (``history_*.npz``, the creep refit's), one file each
    (``physics.ActuatorPhysics`` and ``physics.HistoryPhysics`` write them)."""
    return kept_files(cached, "solve") + kept_files(cached, "history")


def run_case(case: dict, a, out: Path, diagnose) -> dict:
    gen = dict(noise=a.noise, seed=noise_seed(case), correlation=case["correlation"], truth_c10=case["truth_c10"],
               trace=case["trace"], cache_dir=out / "clean", generator=a.generator, pressure=a.pressure)
    gen.update(resolution=a.resolution)
    if a.quick:
        gen.update(resolution=1, frames=6)
    rec, clean, meta = scenarios.make_scenario(case["effect"], case["size"], **gen)
    cached = out / "diag" / case["case"] / "solves"
    before = fe_work(cached)
    t0 = time.perf_counter()
    known = not a.estimate_noise  # else the diagnosis estimates sigma and the correlation length itself
    # a recording made on the diagnosis mesh itself (--resolution 1, --quick) has no discretization error
    # for the diagnosis to take out
    d = diagnose(rec, noise=a.noise if known else None, correlation=(case["correlation"] or None) if known else None,
                 run_dir=out / "diag" / case["case"], progress=a.verbose,
                 mesh_error=gen["resolution"] > 1 or a.generator == "calculix")
    seconds = time.perf_counter() - t0
    decision = str(d["decision"])
    # the part of the effect the calibrated base model cannot absorb (C10 refitted): what any
    # diagnosis can see. clean - base fit = (Z - base fit) - noise
    with np.load(out / "diag" / case["case"] / "residuals.npz", allow_pickle=False) as f:
        unabsorbed = f["before"] - (rec.Z - clean)
    snr_after_base = float(np.sqrt(np.nansum(unabsorbed**2))) / a.noise
    return {
        "case": case["case"], "effect": case["effect"], "kind": meta["kind"], "size": case["size"], "noise": a.noise,
        "value": meta["value"], "truth_c10": case["truth_c10"], "trace": meta["trace"]["kind"],
        "snr": meta["snr"], "snr_after_base": snr_after_base, "band": snr_band(snr_after_base, meta["kind"]),
        "band_raw": snr_band(meta["snr"], meta["kind"]), "seed": case["seed"], "noise_seed": noise_seed(case),
        "correlated": bool(case["correlation"]), "correlation_length": case["correlation"],
        "expected": meta["expected"], "decision": decision, "correct": scenarios.is_correct(case["effect"], decision),
        "detected": bool(d["mismatch_detected"]["detected"]),
        "noise_estimated": bool(a.estimate_noise), "sigma_used": float(d["noise"]["sigma"]),
        "correlation_used": float(d["noise"]["correlation_length_mm"]),
        "rms_before": float(d["fit_before"]["rms"]), "rms_after": float(d["fit_after"]["rms"]),
        "solves": fe_work(cached),  # FE solves and history marches of the diagnosis: one file each
        "history_marches": kept_files(cached, "history"),
        "seconds": float(d["cost"].get("seconds", seconds)),
        "solves_reused": before,  # solves found on disk from an earlier run: "seconds" then is not the cost
        "generation": {"generator": a.generator, "pressure_max": a.pressure,
                       "resolution": meta["generation"]["resolution"], "frames": meta["generation"]["frames"],
                       "solves": meta["solves"], "seconds": meta["seconds"]},
    }


def _mean(rows, key) -> str:
    v = [r[key] for r in rows if r[key] is not None and np.isfinite(r[key])]
    return f"{np.mean(v):.3g}" if v else "-"


def grouped(rows, band_of) -> list[tuple[tuple, list]]:
    """Rows grouped by (effect, kind, SNR band), in the library's effect order and then by band; an
    effect the library does not know (a row from another version) sorts last."""
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r["effect"], r["kind"], band_of(r)), []).append(r)
    order = {e: k for k, e in enumerate(scenarios.EFFECTS)}
    bands = {label: k for k, (_, _, label) in enumerate(BANDS)}
    return sorted(groups.items(), key=lambda x: (order.get(x[0][0], len(order)), bands.get(x[0][2], -1)))


def table(rows: list[dict]) -> str:
    """Markdown table per effect and SNR band."""
    head = ("| effect | kind | SNR band (after base fit) | cases | SNR raw | SNR after base fit | correct | "
            "named a candidate | unexplained | RMS before | RMS after | FE solves | wall s |")
    lines = ["Correct: the effect's candidate (library), \"none\" (nulls), \"unexplained\" (outside the library). "
             "\"Named a candidate\" on a null is a false attribution. RMS in noise units. SNR raw: ||effect - base "
             "model at the true C10|| / sigma (the generator's); SNR after base fit: ||effect - base model at the "
             "fitted C10|| / sigma, the part no refit of C10 absorbs, which is what a diagnosis can see; the bands "
             "use it. Wall s: diagnoses that solved everything themselves (1 thread).", "", head,
             "|" + "---|" * (head.count("|") - 1)]
    for (effect, kind, band), g in grouped(rows, lambda r: r["band"]):
        n = len(g)
        named = sum(r["decision"] not in ("none", "unexplained") for r in g)
        unexplained = sum(r["decision"] == "unexplained" for r in g)
        lines.append(f"| {effect} | {kind} | {band} | {n} | {_mean(g, 'snr')} | {_mean(g, 'snr_after_base')} | "
                     f"{sum(r['correct'] for r in g) / n:.0%} | "
                     f"{named / n:.0%} | {unexplained / n:.0%} | {_mean(g, 'rms_before')} | {_mean(g, 'rms_after')} | "
                     f"{_mean(g, 'solves')} | {_mean([r for r in g if not r.get('solves_reused')], 'seconds')} |")
    return "\n".join(lines) + "\n"


POOL_FIELDS = ("case", "effect", "kind", "noise", "snr", "snr_after_base", "decision", "rms_before", "rms_after",
               "solves")
POOL_ALPHA = 0.05  # one-sided exact (Clopper-Pearson) bounds at 95 % confidence


def rate_bound(k: int, n: int, side: str, alpha: float = POOL_ALPHA) -> float:
    """Exact one-sided (Clopper-Pearson) confidence bound of a rate seen k times in n: the lower
    bound (``side="lower"``) is the Beta(k, n - k + 1) quantile alpha, the upper the Beta(k + 1,
    n - k) quantile 1 - alpha (k = n gives alpha^(1/n), k = 0 gives 1 - alpha^(1/n))."""
    from scipy.stats import beta

    if not 0 <= k <= n or n < 1:
        raise ValueError(f"a rate needs 0 <= k <= n and n >= 1, got k = {k}, n = {n}")
    if side == "lower":
        return 0.0 if k == 0 else float(beta.ppf(alpha, k, n - k + 1))
    return 1.0 if k == n else float(beta.ppf(1.0 - alpha, k + 1, n - k))


def recording_key(row: dict) -> tuple:
    """What makes a recording: its case name (effect, size, truth, trace, seed index, noise kind,
    generator), its noise level and its noise draw (a null's name and draw recur at another noise)."""
    generator = (row.get("generation") or {}).get("generator", "torchfra")
    return (row["case"], float(row["noise"]), row.get("noise_seed", row.get("seed")), generator)


def read_rows(path: Path) -> list[dict]:
    """The rows of a suite's results file (``results.json`` of a run, or a copy kept in results/);
    JSON only. A file that is not one, or a row without what the table needs, is named."""
    try:
        data = json.loads(Path(path).read_text())
    except ValueError as err:
        raise ValueError(f"{path}: not JSON ({err}); --pool takes the results.json files of suite runs") from err
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{path}: no 'rows' list of cases; --pool takes the results.json files of suite runs")
    for i, row in enumerate(rows):
        missing = [f for f in POOL_FIELDS if not isinstance(row, dict) or f not in row]
        if missing:
            name = row.get("case", f"row {i}") if isinstance(row, dict) else f"row {i}"
            raise ValueError(f"{path}: case {name!r} lacks {', '.join(missing)} (a row of an older suite version?); "
                             "leave the file out of --pool")
        for f in ("noise", "snr", "snr_after_base"):  # what the table keys and bands on
            v = row[f]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or \
                    (f == "noise" and v <= 0):
                raise ValueError(f"{path}: case {row['case']!r} has {f} = {v!r}, not a finite number"
                                 f"{' > 0' if f == 'noise' else ''}; mend or drop the row")
    return rows


def pooled(paths) -> tuple[str, dict]:
    """One table over the rows of several suite runs: per effect and SNR band (after the base fit),
    the correct rate with its exact one-sided 95 % bound, and the issue's targets judged on the
    pooled counts. A recording listed in several files counts once, from the last file listing it
    (a re-decision on the same solves replaces the first)."""
    rows: dict[tuple, dict] = {}
    sources: dict[tuple, str] = {}
    listed = 0
    for path in paths:
        for row in read_rows(path):
            listed += 1
            key = recording_key(row)
            rows[key], sources[key] = row, str(path)
    head = ("| effect | kind | SNR band (after base fit) | recordings | SNR after base fit | correct | "
            "exact 95 % bound of the correct rate | named a candidate | unexplained | RMS before | RMS after | "
            "FE solves |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for (effect, kind, band), g in grouped(rows.values(), lambda r: snr_band(float(r["snr_after_base"]), r["kind"])):
        n, k = len(g), sum(scenarios.is_correct(r["effect"], str(r["decision"])) for r in g)
        named = sum(str(r["decision"]) not in ("none", "unexplained") for r in g)
        unexplained = sum(str(r["decision"]) == "unexplained" for r in g)
        snr = [float(r["snr_after_base"]) for r in g]
        lines.append(f"| {effect} | {kind} | {band} | {n} | {min(snr):.3g}-{max(snr):.3g} | {k} of {n} | "
                     f">= {rate_bound(k, n, 'lower'):.0%} | {named} | {unexplained} | {_mean(g, 'rms_before')} | "
                     f"{_mean(g, 'rms_after')} | {_mean(g, 'solves')} |")

    def count(select, good):
        g = [r for r in rows.values() if select(r)]
        return sum(bool(good(r)) for r in g), len(g)

    def correct(r):
        return scenarios.is_correct(r["effect"], str(r["decision"]))

    def strong(r):
        return float(r["snr_after_base"]) >= 25.0

    targets = {}
    for name, select, good, side, target in (
            ("top-1 correct, library effects, SNR >= 25 after the base fit",
             lambda r: r["kind"] == "library" and strong(r), correct, "lower", 0.95),
            ("attributed to a candidate, nulls", lambda r: r["kind"] == "null",
             lambda r: str(r["decision"]) not in ("none", "unexplained"), "upper", 0.05),
            ("\"unexplained\", effects outside the library, SNR >= 25 after the base fit",
             lambda r: r["kind"] == "outside" and strong(r), lambda r: str(r["decision"]) == "unexplained", "lower",
             0.80),
            ("\"unexplained\", effects outside the library, every SNR", lambda r: r["kind"] == "outside",
             lambda r: str(r["decision"]) == "unexplained", "lower", 0.80),
            ("residual within 10 % of the noise after the refit, library effects named right",
             lambda r: r["kind"] == "library" and correct(r), lambda r: float(r["rms_after"]) <= 1.10, "lower",
             1.0)):
        k, n = count(select, good)
        if not n:
            targets[name] = {"k": 0, "n": 0, "rate": None, "bound": None, "target": target, "met": None}
            continue
        bound = rate_bound(k, n, side)
        if target >= 1.0:  # "every one": no bound to judge
            verdict = "yes" if k == n else "no"
        elif (bound <= target) if side == "upper" else (bound >= target):
            verdict = "yes"
        elif (k / n <= target) if side == "upper" else (k / n >= target):
            verdict = "not shown: too few recordings for the bound"
        else:
            verdict = "no: the rate seen misses it"
        targets[name] = {"k": k, "n": n, "rate": k / n, "bound": bound, "side": side, "target": target,
                         "met": verdict}
    lines += ["", "| target | seen | exact 95 % bound | issue's target | met at 95 % confidence |",
              "|---|---|---|---|---|"]
    for name, t in targets.items():
        if not t["n"]:
            lines.append(f"| {name} | no recording | - | {t['target']:.0%} | - |")
            continue
        sign = ">=" if t["side"] == "lower" else "<="
        want = f"{'<=' if t['side'] == 'upper' else '>='} {t['target']:.0%}" if t["target"] < 1.0 else "every one"
        lines.append(f"| {name} | {t['k']} of {t['n']} | {sign} {t['bound']:.1%} | {want} | {t['met']} |")
    summary = {"files": [str(p) for p in paths], "rows_listed": listed, "recordings": len(rows),
               "duplicates_dropped": listed - len(rows), "targets": targets,
               "confidence": f"exact one-sided (Clopper-Pearson), alpha = {POOL_ALPHA}"}
    return "\n".join(lines) + "\n", summary


def _write_json(path: Path, obj) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(obj, indent=1))
    tmp.replace(path)


def run_cases(todo: list[dict], rows: dict, results: Path, a, run) -> tuple[dict | None, int]:
    """Run every case of ``todo`` without a row in ``rows`` (``run(case) -> row``), saving rows as
    they come. Under torchrun the ranks share the cases out round robin (as rank 0's rows list what
    is left, so all agree); each rank keeps its rows in ``results.rank<R>.json`` beside
    ``results`` until rank 0 has gathered them (as JSON text, never pickled) into ``results``.
    Returns (every row, cases reused) on rank 0, (None, 0) on the others."""
    from torchfra.runtime.distributed import broadcast_ints, finish, gather_bytes, ranks

    r = ranks()
    parts = sorted(results.parent.glob("results.rank*.json")) if r.rank == 0 else []
    for part in parts:  # a stopped parallel run's rows: into results.json before any rank writes again
        try:
            rows.update({row["case"]: row for row in json.loads(part.read_text())["rows"]})
        except (ValueError, KeyError, TypeError) as err:
            raise ValueError(f"{part}: not the rows of a stopped suite run ({type(err).__name__}: {err}); delete it "
                             "to run its cases again") from err
    if parts:
        _write_json(results, {"settings": vars(a), "rows": list(rows.values())})
        for part in parts:
            part.unlink()
    left = broadcast_ints([i for i, c in enumerate(todo) if c["case"] not in rows] if r.rank == 0 else None, r)
    reused = len(todo) - len(left)
    if r.rank == 0:
        print((f"{len(todo)} cases, {reused} reused from {results}" if reused else f"{len(todo)} cases")
              + (f", shared out over {r.size} ranks" if r.parallel else ""))
    mine = r.share(left)
    own: dict = {}
    bar = tqdm([todo[i] for i in mine], desc=f"scenarios (rank {r.rank} of {r.size}: its share)" if r.parallel
               else "scenarios", unit="case", disable=r.rank != 0)
    partial = results.with_name(f"results.rank{r.rank}.json")
    for case in bar:
        bar.set_postfix_str(case["case"])
        own[case["case"]] = run(case)
        if r.parallel:
            _write_json(partial, {"settings": vars(a), "rows": list(own.values())})
        else:
            rows[case["case"]] = own[case["case"]]
            _write_json(results, {"settings": vars(a), "rows": list(rows.values())})
    if not r.parallel:
        return rows, reused
    gathered = gather_bytes(json.dumps(list(own.values())).encode(), r)
    if r.rank != 0:
        finish(r, wait=False)
        return None, 0
    for data in gathered:
        rows.update({row["case"]: row for row in json.loads(data.decode())})
    _write_json(results, {"settings": vars(a), "rows": list(rows.values())})
    for part in results.parent.glob("results.rank*.json"):  # gathered: results.json holds them now
        part.unlink()
    finish(r, wait=False)
    return rows, reused
