"""Forward propagation of the prior ensemble through the actuator model (paper Eq. 15).

    torchfra forward --members 100 --resolution 2 --seed 0 --name forward
    torchfra forward --param C10=lognormal:0.0062,0.0011 --param C01=uniform:0,0.002 --name fwd_mr

writes runs/<name>/: forward.npz (times, pressure, params, points, Y (N, T, P, 2), status),
summary.json, TensorBoard events, tracked_node.png, mean_deformed.vtu. A killed run resumes from
the member chunks already in runs/<name>/members/.

    torchrun --standalone --nproc-per-node 2 scripts/forward_uq.py --members 100 --name forward

runs the same ensemble on 2 processes (torch.distributed, gloo): members are shared out by rank and
every rank ends with all of them in its run folder; rank 0 writes the outputs. Across machines:
torchrun --nnodes N --node-rank I --nproc-per-node K --rdzv-endpoint HOST:PORT (see the README).
"""
from __future__ import annotations

import json
from pathlib import Path

from torchfra.cli.flags import (
    PEAK_PRESSURE,
    add_method,
    add_peak_pressure,
    add_renamed,
    add_resolution,
    add_run_folder,
    add_threads,
    parser,
)
from torchfra.cli.run import add_deck_flags, check_deck_flags

# ForwardConfig's defaults (tests/test_help.py checks they agree), here so that --help needs no torch
MEMBERS, SEED, LOAD_STEPS, FRAMES, CHUNK, BULK_RATIO = 100, 0, 20, 100, 1, 1000.0
SNAPSHOTS, REDUCED_TOL, NEWTON_BUDGET, NEWTON_SECONDS = 0, 5e-4, 500, 0.0


def build_parser():
    """The flags of ``torchfra forward`` (no torch imported)."""
    p = parser(__doc__)
    p.add_argument("--members", type=int, default=MEMBERS, help="ensemble members (prior draws)")
    add_resolution(p)
    p.add_argument("--seed", type=int, default=SEED, help="seed of the prior draws")
    add_run_folder(p, "forward", "outputs")
    add_renamed(p, "--out", "--name", "name", note=" (--out names a file; a run folder is --name)")
    p.add_argument("--load-steps", type=int, default=LOAD_STEPS, help="FE output load factors 1/n .. 1")
    p.add_argument("--frames", type=int, default=FRAMES, help="frames at t = 1/n .. 1 (interpolated)")
    p.add_argument("--chunk", type=int, default=CHUNK, help="members per batched solve and checkpoint (full Newton)")
    p.add_argument("--bulk-ratio", type=float, default=BULK_RATIO, help="K / mu of every member")
    add_peak_pressure(p, None, f"cavity pressure at t = 1 (MPa; default {PEAK_PRESSURE}, with --inp the deck's)")
    add_threads(p)
    p.add_argument("--integration", choices=["full", "reduced"], default="full",
                   help="Hex20 Gauss rule: full 3x3x3 or the paper's reduced 2x2x2")
    add_method(p)
    p.add_argument("--snapshots", type=int, default=SNAPSHOTS,
                   help="members solved in full for the reduced basis (0: 1 + 2 x varying directions, at least 5)")
    p.add_argument("--reduced-tol", type=float, default=REDUCED_TOL,
                   help="mm: a reduced member whose check estimates a larger error is solved in full")
    p.add_argument("--param", action="append", default=[], metavar="NAME=KIND:A,B",
                   help="an uncertain parameter and its prior (lognormal:MEAN,STD, normal:MEAN,STD, uniform:LOW,HIGH); "
                        "repeatable; default the paper's C10 prior")
    p.add_argument("--fixed", action="append", default=[], metavar="NAME=VALUE", help="a parameter held at a value")
    p.add_argument("--config", default=None, help="a TOML file of priors ([parameters], optional [fixed])")
    p.add_argument("--newton-budget", type=int, default=NEWTON_BUDGET,
                   help="Newton iterations one member may spend (0: no limit); a member that spends them stops, "
                        "flagged as not converged")
    p.add_argument("--newton-seconds", type=float, default=NEWTON_SECONDS,
                   help="wall seconds a full-Newton member may take (0: no limit); a member still solving then "
                        "stops, flagged as not converged (machine-dependent; --newton-budget is not)")
    add_deck_flags(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar (helper processes)")
    return p


def main(argv=None) -> dict:
    a = build_parser().parse_args(argv)
    check_deck_flags(a, "peak_pressure")
    from torchfra.calibration.config import ForwardConfig
    from torchfra.calibration.forward import run_forward, with_deck
    from torchfra.calibration.priors import ParameterSet, read_parameter_file
    from torchfra.cli.flags import resolve_method
    from torchfra.report.forward import write_forward_outputs
    from torchfra.runtime.distributed import finish, ranks

    if a.config is not None:
        if a.param or a.fixed:
            raise ValueError("give the parameters in the --config file or by --param/--fixed, not both")
        f = read_parameter_file(a.config)
        a.param, a.fixed = f["parameters"], f["fixed"]
    if a.fixed and not a.param:
        raise ValueError("--fixed needs the uncertain parameters named with --param")
    ParameterSet.parse(a.param, a.fixed) if a.param else None  # each bad entry named before any work
    method, why = resolve_method(a.method, a.members, len(a.param) or 1, a.snapshots)
    r = ranks()
    if why and r.rank == 0 and not a.quiet:
        print(why, flush=True)
    config = ForwardConfig(members=a.members, resolution=a.resolution, seed=a.seed, load_steps=a.load_steps,
                           frames=a.frames, chunk=a.chunk, bulk_ratio=a.bulk_ratio,
                           pressure=PEAK_PRESSURE if a.peak_pressure is None else a.peak_pressure,
                           inp=a.inp or "", camera=a.camera, face=a.face or "",
                           threads=a.threads, integration=a.integration, method=method, snapshots=a.snapshots,
                           reduced_tol=a.reduced_tol, parameters=list(a.param), fixed=list(a.fixed),
                           newton_budget=a.newton_budget, newton_seconds=a.newton_seconds)
    config = with_deck(config)  # a deck is read and checked before any work
    run_dir = Path(a.runs_dir) / a.name
    out = run_forward(config, run_dir, progress=not a.quiet)
    if r.rank != 0:  # torchrun: every rank holds the ensemble; rank 0 writes the outputs
        finish(r)
        return {}
    summary = write_forward_outputs(out, config, run_dir)
    finish(r)
    print(json.dumps({k: summary[k] for k in ("members", "members_converged", "elements", "fiber_elements",
                                              "dofs", "wall_s", "members_reduced", "tracked_displacement_mean")}))
    return summary


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
