"""Forward propagation of the prior ensemble through the actuator model (paper Eq. 15).

    python scripts/forward_uq.py --members 100 --mesh 2 --seed 0 --out forward
    python scripts/forward_uq.py --param C10=lognormal:0.0062,0.0011 --param C01=uniform:0,0.002 --out fwd_mr

writes runs/<out>/: forward.npz (times, pressure, params, points, Y (N, T, P, 2), status),
summary.json, TensorBoard events, tracked_node.png, mean_deformed.vtu. A killed run resumes from
the member chunks already in runs/<out>/members/.

    torchrun --standalone --nproc-per-node 2 scripts/forward_uq.py --members 100 --out forward

runs the same ensemble on 2 processes (torch.distributed, gloo): members are shared out by rank and
every rank ends with all of them in its run folder; rank 0 writes the outputs. Across machines:
torchrun --nnodes N --node-rank I --nproc-per-node K --rdzv-endpoint HOST:PORT (see the README).
"""
import argparse
import json
from pathlib import Path

from torchfra.calibration.config import ForwardConfig
from torchfra.calibration.forward import run_forward, with_deck
from torchfra.calibration.priors import ParameterSet, read_parameter_file
from torchfra.cli.run import add_deck_flags, check_deck_flags
from torchfra.report.forward import write_forward_outputs
from torchfra.runtime.distributed import finish, ranks


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = ForwardConfig()
    p.add_argument("--members", type=int, default=d.members, help="ensemble members (prior draws)")
    p.add_argument("--mesh", type=int, default=d.resolution, help="mesh resolution knob (1 = coarsest)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the prior draws")
    p.add_argument("--out", default="forward", help="run name: outputs go to <runs-dir>/<out>/")
    p.add_argument("--runs-dir", default="runs")
    p.add_argument("--load-steps", type=int, default=d.load_steps, help="FE output load factors 1/n .. 1")
    p.add_argument("--frames", type=int, default=d.frames, help="frames at t = 1/n .. 1 (interpolated)")
    p.add_argument("--chunk", type=int, default=d.chunk, help="members per batched solve and checkpoint")
    p.add_argument("--bulk-ratio", type=float, default=d.bulk_ratio, help="K / mu of every member")
    p.add_argument("--pressure", type=float, default=None, help=f"cavity pressure at t = 1 (MPa; default {d.pressure}, "
                   "with --inp the deck's)")
    p.add_argument("--threads", type=int, default=d.threads, help="torch CPU threads (recorded)")
    p.add_argument("--integration", choices=["full", "reduced"], default=d.integration,
                   help="Hex20 Gauss rule: full 3x3x3 (default) or the paper's reduced 2x2x2")
    p.add_argument("--method", choices=["reduced", "full"], default=d.method,
                   help="reduced (default): a few members by full Newton, the others on their reduced basis, each "
                   "checked and re-solved in full if needed; full: full Newton for every member")
    p.add_argument("--snapshots", type=int, default=d.snapshots,
                   help="members solved in full for the reduced basis (0: 1 + 2 x varying directions, at least 3)")
    p.add_argument("--reduced-tol", type=float, default=d.reduced_tol,
                   help="mm: a reduced member whose check estimates a larger error is solved in full")
    p.add_argument("--param", action="append", default=[], metavar="NAME=KIND:A,B",
                   help="an uncertain parameter and its prior (lognormal:MEAN,STD, normal:MEAN,STD, uniform:LOW,HIGH); "
                        "repeatable; default the paper's C10 prior")
    p.add_argument("--fixed", action="append", default=[], metavar="NAME=VALUE", help="a parameter held at a value")
    p.add_argument("--config", default=None, help="a TOML file of priors ([parameters], optional [fixed])")
    p.add_argument("--newton-budget", type=int, default=d.newton_budget,
                   help="Newton iterations one member may spend (0: no limit); a member that spends them stops, "
                        "flagged as not converged")
    p.add_argument("--newton-seconds", type=float, default=d.newton_seconds,
                   help="wall seconds a full-Newton member may take (0: no limit); a member still solving then "
                        "stops, flagged as not converged (machine-dependent; --newton-budget is not)")
    add_deck_flags(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar (helper processes)")
    a = p.parse_args(argv)
    check_deck_flags(a)
    if a.config is not None:
        if a.param or a.fixed:
            raise ValueError("give the parameters in the --config file or by --param/--fixed, not both")
        f = read_parameter_file(a.config)
        a.param, a.fixed = f["parameters"], f["fixed"]
    if a.fixed and not a.param:
        raise ValueError("--fixed needs the uncertain parameters named with --param")
    ParameterSet.parse(a.param, a.fixed) if a.param else None  # each bad entry named before any work
    config = ForwardConfig(members=a.members, resolution=a.mesh, seed=a.seed, load_steps=a.load_steps,
                           frames=a.frames, chunk=a.chunk, bulk_ratio=a.bulk_ratio,
                           pressure=d.pressure if a.pressure is None else a.pressure, inp=a.inp or "",
                           camera=a.camera, face=a.face or "",
                           threads=a.threads, integration=a.integration, method=a.method, snapshots=a.snapshots,
                           reduced_tol=a.reduced_tol, parameters=list(a.param), fixed=list(a.fixed),
                           newton_budget=a.newton_budget, newton_seconds=a.newton_seconds)
    config = with_deck(config)  # a deck is read and checked before any work
    run_dir = Path(a.runs_dir) / a.out
    r = ranks()
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
