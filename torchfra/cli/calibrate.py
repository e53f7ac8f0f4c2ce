"""Calibrate the actuator's parameters (C10, or any parameter set) from a recording with the
hierarchical master/slave EnKF (paper Eqs. 21-23), its nonlinear-slave variant, the restart EnKF
and the exact grid posterior.

    python scripts/calibrate.py --config seed                  # the paper's experiment (§4.1)
    python scripts/calibrate.py --param C10=lognormal:0.0062,0.0011 --param E_fiber=lognormal:31000,8000 \
        --truth C10=0.0048 --truth E_fiber=25000 --name two_params   # two parameters, synthetic recording
    python scripts/calibrate.py --config my_actuator.toml --recording my_dic.csv --noise 0.5
    python scripts/calibrate.py --recording my_dic.csv --noise 0.5 --name bench_test
    python scripts/calibrate.py --recording vic3d_exports/ --pressure trace.csv --landmarks lm.csv --name test1
    torchrun --standalone --nproc-per-node 2 scripts/calibrate.py --config seed   # forward ensemble on 2 ranks

writes runs/<name>/: summary.json, bands.png, pdfs.png (pairs.png for several parameters), TensorBoard events; the forward ensemble is
cached in runs/forward_cache/<settings>/ (shared by runs with the same prior, mesh and load) and the restart filter checkpoints after every step, so a killed
run resumes without redoing finished FE work.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from torchfra.cli.flags import (
    PEAK_PRESSURE,
    add_method,
    add_peak_pressure,
    add_resolution,
    add_run_folder,
    add_threads,
    parser,
)
from torchfra.cli.run import add_deck_flags, check_deck_flags
from torchfra.io.dic.importer import add_arguments

CONFIGS = ("seed",)  # named configs: torchfra.calibration.config.SEED
EXIT_NO_RESULT = 3  # the recording does not fit the model and prior: no calibration result (a wrong input is 2)


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextmanager
def forward_ranks(config: CalibrationConfig, run_dir: Path, n: int, argv: list[str]):
    """The forward ensemble and the restart filter on ``n`` processes through torch.distributed
    (gloo, this machine): this process becomes rank 0 of the group, and ranks 1..n-1 are this script
    again with the same arguments, which solve their share of the forward members (torchfra.calibration.forward)
    and then of every restart forecast (``calibration.serve_restart``), and leave at rank 0's stop.
    Yields the :class:`RestartRanks` to hand to ``run_calibration`` (None: no other rank; none is
    started when the ensemble is on disk and the restart filter is off). On the way out the stop is
    sent, the group left, the environment restored, and ranks still running when the work did not
    finish are stopped."""
    from torchfra.calibration.forward import forward_config, forward_dir
    from torchfra.calibration.restart import RestartRanks
    from torchfra.runtime.distributed import finish, ranks

    fwd, where = forward_config(config), forward_dir(config, run_dir.parent)
    per_file = 1 if fwd.method == "reduced" else fwd.chunk

    def solved() -> bool:
        return all((where / "members" / f"chunk_{s:05d}.npz").exists() for s in range(0, fwd.members, per_file))

    if n <= 1 or (solved() and not config.restart):
        yield None
        return
    group = {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(_free_port()), "WORLD_SIZE": str(n)}
    names = (*group, "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE")
    saved = {k: os.environ.get(k) for k in names}
    env = dict(os.environ, **group, LOCAL_WORLD_SIZE=str(n), MKL_NUM_THREADS=str(fwd.threads),
               OMP_NUM_THREADS=str(fwd.threads))
    procs = [subprocess.Popen([sys.executable, str(Path(__file__).resolve()), *argv], stdout=subprocess.DEVNULL,
                              env={**env, "RANK": str(i), "LOCAL_RANK": str(i)}) for i in range(1, n)]
    os.environ.update(group, RANK="0", LOCAL_RANK="0", LOCAL_WORLD_SIZE=str(n))
    service = RestartRanks(ranks()) if config.restart else None
    try:
        yield service
    finally:
        if service is not None:
            service.stop()
        finish(ranks(), wait=False)
        done = solved() and (service is None or service.stopped)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        for h in procs:
            stopped = False
            if h.poll() is None and not done:
                h.terminate()  # this process failed or was stopped: do not leave ranks behind
                stopped = True
            if h.wait() != 0 and not stopped:
                print(f"rank process {h.pid} failed (exit status {h.returncode}); the forward members and "
                      "restart steps it had not saved are solved by a rerun", file=sys.stderr)


def _base_config(a) -> tuple[CalibrationConfig, dict]:
    """The named config or the TOML file's, and the parameter set given by flags or file (empty: the
    config's own, the paper's C10 prior)."""
    from torchfra.calibration.config import SEED
    from torchfra.calibration.priors import ParameterSet, read_parameter_file

    prior: dict = {}
    if a.config in CONFIGS:
        base = SEED
    elif a.config.endswith(".toml"):
        base = SEED
        prior = read_parameter_file(a.config)
    else:
        raise ValueError(f"--config {a.config!r}: not a named config ({', '.join(sorted(CONFIGS))}) nor a .toml file "
                         "of priors")
    if a.param or a.fixed:
        if prior:
            raise ValueError("give the parameters in the --config file or by --param/--fixed, not both")
        ParameterSet.parse(a.param or [], a.fixed or [])  # checked here: each bad entry named before any work
        prior = {"parameters": list(a.param or []), "fixed": list(a.fixed or [])}
        if not a.param:
            raise ValueError("--fixed needs the uncertain parameters named with --param")
    return base, prior


def build_parser():
    """The flags of ``torchfra calibrate`` (no torch imported)."""
    p = parser(__doc__)
    p.add_argument("--config", default="seed",
                   help="named settings to start from (seed: the paper's experiment), or a TOML file of priors "
                        "([parameters], optional [fixed] and [truth] tables; see torchfra.calibration.priors)")
    p.add_argument("--param", action="append", default=None, metavar="NAME=KIND:A,B",
                   help="an uncertain parameter and its prior for the parameter itself: lognormal:MEAN,STD, "
                        "normal:MEAN,STD or uniform:LOW,HIGH (repeat for several; default the config's C10 prior)")
    p.add_argument("--fixed", action="append", default=None, metavar="NAME=VALUE",
                   help="a parameter held at a value (repeatable), e.g. E_fiber=31000")
    add_run_folder(p, None, "outputs (default: the --config name, seed)")
    p.add_argument("--recording", default=None,
                   help="CSV/NPZ recording (default: a synthetic one at --c10/--truth), or with --pressure a DIC "
                        "export (a folder of per-frame files or one file), converted into runs/<name>/recording.csv")
    p.add_argument("--c10", type=float, default=None, metavar="MPA",
                   help="C10 of the synthetic recording (the truth; default the config's, 0.0048 for seed)")
    p.add_argument("--truth", action="append", default=None, metavar="[NAME=]VALUE",
                   help="values of the synthetic recording: a number for C10 (MPa, as --c10), or NAME=VALUE per "
                        "uncertain parameter (repeatable; a parameter not given takes its null value)")
    p.add_argument("--noise", type=float, default=None, metavar="MM",
                   help="observation noise std (mm); default: 1.0 for a synthetic recording, for a recording file "
                        "estimated from its frames as the diagnosis does (printed and in summary.json noise)")
    p.add_argument("--members", type=int, default=None, help="ensemble size N_s (default the config's, 100 for seed)")
    add_resolution(p)
    add_peak_pressure(p, None, "largest pressure of the forward ensemble (MPa; default the config's, "
                      f"{PEAK_PRESSURE} for seed; with --inp the deck's); a recording's frames must lie below it",
                      old=("--forward-pressure",))
    add_method(p)
    p.add_argument("--assimilate-every", type=int, default=None, metavar="N",
                   help="the hierarchical filters assimilate every n-th frame (default 1, the paper's); fewer "
                        "updates keep their spread along a weakly constrained direction of several parameters")
    p.add_argument("--no-restart", action="store_true", help="skip the restart filter (the FE-costly baseline)")
    p.add_argument("--restart-every", type=int, default=None, metavar="N",
                   help="the restart filter assimilates every n-th frame (default the config's, 10 for seed)")
    p.add_argument("--coverage-seeds", type=int, default=None, metavar="N",
                   help="noise re-draws for the coverage study of a synthetic recording (default the config's, 20 "
                        "for seed; 0: none)")
    add_threads(p)
    p.add_argument("--workers", type=int, default=2,
                   help="processes sharing the forward ensemble and the restart filter's FE re-solves through "
                        "torch.distributed (one per core; this one is rank 0)")
    add_arguments(p)
    add_deck_flags(p)
    return p


def _noise(config, given: float | None):
    """The noise the filters assume and where it came from: ``--noise``, the synthetic recording's, or,
    for a recording file without ``--noise``, estimated from its frames as the diagnosis does
    (:func:`torchfra.observation.noise.estimate_noise`); said on stdout.

    Returns
    -------
    config : CalibrationConfig
        With ``noise`` set to the estimate when one was made.
    noise : dict
        ``sigma_mm``, ``source`` and, when estimated, the correlation length seen and the frames left out.
    """
    if given is not None:
        print(f"noise: {config.noise:g} mm per component, given by --noise", flush=True)
        return config, {"sigma_mm": config.noise, "source": "given (--noise)"}
    if config.recording is None:
        print(f"noise: {config.noise:g} mm per component, the synthetic recording's", flush=True)
        return config, {"sigma_mm": config.noise, "source": "the synthetic recording's"}
    from torchfra.io.recordings import read_recording
    from torchfra.observation.noise import estimate_noise

    nm = estimate_noise(read_recording(config.recording), give="give --noise SIGMA (mm)")
    noise = {"sigma_mm": nm.sigma, "source": "estimated from the recording's frames (second differences in time, "
             "as torchfra diagnose does)", "correlation_length_mm": nm.ell,
             "frames_left_out": nm.estimated["frames_left_out"]}
    print(f"noise: {nm.sigma:.3g} mm per component, estimated from the recording's frames (give --noise to set it)",
          flush=True)
    if nm.ell > 0:
        print(f"note: the noise looks correlated in space over {nm.ell:.3g} mm; the filters and the exact posterior "
              "assume independent noise, so their spreads may be too narrow", flush=True)
    return replace(config, noise=nm.sigma), noise


def _looks_like_a_number(text) -> bool:
    try:
        float(text)
    except (TypeError, ValueError):
        return False
    return True


def main(argv=None) -> dict | int:
    p = build_parser()
    raw_argv = list(sys.argv[1:] if argv is None else argv)
    a = p.parse_args(argv)
    if a.pressure is not None and _looks_like_a_number(a.pressure) and not Path(a.pressure).exists():
        raise ValueError(f"--pressure {a.pressure}: --pressure names a pressure-trace CSV of a DIC export; "
                         f"{a.pressure} is a peak pressure: give it as --peak-pressure {a.pressure} (MPa)")
    check_deck_flags(a, "peak_pressure")
    if a.c10 is not None:
        if any(t.split("=")[0].strip().upper() == "C10" or "=" not in t for t in a.truth or []):
            raise ValueError("give the truth of C10 once: --c10 or --truth C10=..., not both")
        a.truth = [*(a.truth or []), f"C10={a.c10!r}"]

    import torch

    from torchfra.calibration.config import CalibrationConfig, ForwardConfig
    from torchfra.calibration.experiment import applicable_config, headline, run_calibration
    from torchfra.calibration.forward import forward_config, forward_dir, observed_surface, run_forward
    from torchfra.calibration.frames import validate_recording
    from torchfra.calibration.priors import parse_truth
    from torchfra.calibration.restart import RestartRanks, serve_restart
    from torchfra.cli.flags import resolve_method
    from torchfra.io.dic.importer import recording_path
    from torchfra.report.calibration import write_calibration_outputs
    from torchfra.runtime.distributed import finish, ranks

    torch.set_num_threads(a.threads)
    torch.set_default_dtype(torch.float64)
    base, prior = _base_config(a)
    r = ranks()
    members = a.members if a.members is not None else base.members
    n_params = len(prior.get("parameters", [])) or len(base.parameters) or 1
    method, why = resolve_method(a.method, members, n_params)
    if r.parallel:  # torchrun: the ranks share the forward ensemble and the restart filter's re-solves;
        a.workers = 1  # rank 0 does everything else
        if r.rank != 0:
            fwd_only = {"members": a.members, "resolution": a.resolution, "pressure": a.peak_pressure, "inp": a.inp,
                        "camera": a.camera, "face": a.face}
            config = replace(base, **prior, method=method, **{k: v for k, v in fwd_only.items() if v is not None})
            try:
                run_forward(forward_config(config), forward_dir(config, a.runs_dir), progress=False)
                if config.restart and not a.no_restart:
                    serve_restart(config, r)
            finally:  # leave the group before the interpreter exits: a gloo group still open at exit can
                finish(r, wait=False)  # abort the process ("terminate called without an active exception")
            return {}
    if why:
        print(why, flush=True)
    if a.pressure is not None and a.recording is None:
        raise ValueError("--pressure names the trace of a DIC export: give the export with --recording")
    run_dir = Path(a.runs_dir) / (a.name or Path(a.config).stem)
    if a.recording is not None:
        face = observed_surface(ForwardConfig(inp=a.inp, camera=a.camera, face=a.face or "")) if a.inp else None
        a.recording = str(recording_path(a.recording, a, run_dir, face))
    truth = {**prior.pop("truth", {}), **parse_truth(a.truth)}
    overrides = {"recording": a.recording, "truth_c10": truth.pop("C10", None), "noise": a.noise, "members": a.members,
                 "resolution": a.resolution, "pressure": a.peak_pressure, "restart_every": a.restart_every,
                 "coverage_seeds": a.coverage_seeds, "assimilate_every": a.assimilate_every, "inp": a.inp,
                 "camera": a.camera, "face": a.face}
    config: CalibrationConfig = replace(base, **prior, method=method,
                                        **{k: v for k, v in overrides.items() if v is not None})
    if config.inp:  # the deck is read and checked now; its pressure is the forward ensemble's
        config = replace(config, pressure=forward_config(config).pressure)
    if truth and config.recording is None:
        config = replace(config, truth=truth)
    elif truth:
        raise ValueError("--truth sets the synthetic recording's values; a recording file has its own")
    if config.recording is None and config.parameters:
        from torchfra.calibration.forward import truth_values

        truth_values(config)  # every value checked against its prior before any FE work
    if a.no_restart:
        config = replace(config, restart=False)
    t0 = time.perf_counter()
    validate_recording(config)  # refuse a bad file before any FE work or helper process
    config, noise = _noise(config, a.noise)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the cleanup below when killed politely
    if r.parallel:  # torchrun started the ranks
        service = RestartRanks(r) if config.restart else None
        try:
            out = run_calibration(config, run_dir, restart_threads=a.threads, restart_ranks=service)
        finally:
            if service is not None:
                service.stop()
        finish(r, wait=False)
    else:
        with forward_ranks(config, run_dir, a.workers, raw_argv) as service:
            out = run_calibration(config, run_dir, restart_threads=a.threads if service else max(a.threads, a.workers),
                                  restart_ranks=service)
    summary = write_calibration_outputs(out, run_dir, time.perf_counter() - t0)
    summary["noise"] = noise
    summary["config"] = applicable_config(config, synthetic=config.recording is None)
    summary["headline"] = headline(summary)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    fit = summary.get("data_fit", {"ok": True})
    if not fit["ok"]:  # flagged, never reported as a result
        print("the data do not fit the model/prior; no calibration result:\n- " + "\n- ".join(fit["reasons"])
              + f"\n(the filters' outputs are in {run_dir} for inspection only)", file=sys.stderr)
        return EXIT_NO_RESULT
    for name, row in summary["filters"].items():  # frames the filter's forecasts do not explain
        flags = row.get("innovation_flags", {}).get("frames", [])
        if flags:
            print(f"innovation check, {name}: {len(flags)} of {row['frames_assimilated']} frames outside the 99.99 % "
                  f"band of the normalized innovation, the first at frame index {flags[0]} (summary.json "
                  "innovation_flags): the filter's forecasts, with their spread and the noise, do not explain the "
                  "recording there", file=sys.stderr)
    print(result_lines(summary, run_dir))
    return summary


def result_lines(summary: dict, run_dir) -> str:
    """The posteriors as lines: per parameter (name and unit) each filter's mean +- std, rounded to the
    digits its std supports, with its distance from the exact posterior; the truth; the headline."""
    from torchfra.calibration.experiment import rounded
    from torchfra.report.calibration import LABELS

    lines = []
    comp = summary.get("comparison", {})
    one = len(summary["parameters"]) == 1
    for p in summary["parameters"]:
        unit = summary.get("prior", {}).get(p, {}).get("unit", "")
        lines.append(f"{p}" + (f" ({unit})" if unit else "") + ":")
        for name, row in summary["filters"].items():
            c = comp.get(name, {}) if one else comp.get(name, {}).get(p, {})
            d = c.get("distance_from_exact_mean_in_exact_stds")
            off = "" if name == "exact" or d is None else f"   {d:+.2f} exact stds from the exact mean"
            lines.append(f"  {LABELS.get(name, name):<36} {rounded(row[p]['mean'], row[p]['std'])}{off}")
        truth = (summary.get("truth") or {}).get(p)
        if truth is not None:
            lines.append(f"  {'truth':<36} {truth:g}")
    lines.append(f"headline: {summary['headline']['text']}")
    lines.append(f"run: {run_dir} (summary.json)")
    return "\n".join(lines)


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
