"""The ``torchfra bench`` command: its flags, the suite it runs (one module of :mod:`torchfra.cli.bench` each),
and the JSON it prints and writes. Torch and the suites are imported after the flags are read, so ``--help``
needs neither."""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
import time
import warnings

from torchfra.cli.flags import Formatter, add_resolution

DESCRIPTION = "Benchmarks of the finite element core on Hex20 box meshes, for one member and for an ensemble."
SUITES = ("device", "ensemble", "fem", "forward", "sensitivity")  # a module of torchfra.cli.bench each


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=DESCRIPTION, formatter_class=Formatter)
    parser.add_argument("--suite", choices=sorted(SUITES), required=True, help="the benchmark suite to run")
    parser.add_argument("--out", help="also write the JSON to this file")
    parser.add_argument("--threads", type=int, default=1, help="torch and MKL (PARDISO) threads (default 1)")
    parser.add_argument("--quick", action="store_true", help="tiny meshes and ensembles: a smoke test, < 1 min")
    parser.add_argument("--meshes", help="divisions to run instead of the suite's, e.g. 8x8x16,16x16x16")
    parser.add_argument("--members", help="fem: member counts instead of the suite's, e.g. 1,100 (1 must come "
                        "first); forward: the ensemble size M (default 100)")
    add_resolution(parser, what="the forward suite's actuator")
    parser.add_argument("--load-steps", type=int, default=None,
                        help="forward: output load factors (default 20; 5 with --quick)")
    parser.add_argument("--old-members", type=int, help="ensemble: members solved by the old path too (default all)")
    parser.add_argument("--vary", action="append", metavar="NAME=S", help="ensemble: also draw NAME per member as "
                        "its value x lognormal(0, S), e.g. E_fiber=0.3 (repeatable)")
    parser.add_argument("--newton-budget-s", type=float, help="run a full Newton solve only if estimated below this")
    parser.add_argument("--chunk-budget-s", type=float, help="time budget of one member-chunked measurement")
    parser.add_argument("--superlu-max-unknowns", type=int, help="skip SuperLU on larger systems")
    args = parser.parse_args(argv)
    args.mesh = args.resolution  # the suites' name for it

    import torch

    from torchfra.cli.bench.common import FULL, QUICK, QUICK_FORWARD_MEMBERS, _START, available_memory_mb, \
        environment, log, rounded, set_mkl_threads
    from torchfra.cli.bench.forward import FORWARD_TARGET_MEMBERS

    warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
    warnings.filterwarnings("ignore", message="Sparse invariant checks")
    torch.set_num_threads(args.threads)
    cfg = dataclasses.replace(QUICK if args.quick else FULL)
    if args.meshes:
        cfg.divisions = [tuple(int(v) for v in m.split("x")) for m in args.meshes.split(",")]
    # --quick: a smoke run of the forward suites too (8 members at 5 load steps, 2 by the old path)
    quick_forward = args.quick and args.suite in ("forward", "ensemble")
    args.forward_members = int(args.members.split(",")[-1]) if args.members else \
        (QUICK_FORWARD_MEMBERS if quick_forward else FORWARD_TARGET_MEMBERS)
    if args.load_steps is None:
        args.load_steps = 5 if quick_forward else 20
    if quick_forward and args.old_members is None:
        args.old_members = 2
    if args.suite in ("forward", "ensemble") and args.forward_members < 1:
        parser.error("--members must be >= 1")
    if args.members and args.suite == "fem":
        cfg.members = [int(v) for v in args.members.split(",")]
    if args.suite == "fem" and cfg.members[0] != 1:
        parser.error("--members must start with 1 (the single-member runs feed the estimates)")
    if args.newton_budget_s is not None:
        cfg.newton_budget_s = args.newton_budget_s
    if args.chunk_budget_s is not None:
        cfg.chunk_budget_s = args.chunk_budget_s
    if args.superlu_max_unknowns is not None:
        cfg.superlu_max_unknowns = args.superlu_max_unknowns

    env = environment(set_mkl_threads(args.threads))
    log(f"suite {args.suite}, {'quick' if args.quick else 'full'}, {torch.get_num_threads()} torch threads, "
        f"{env['mkl_threads']} MKL threads, load average {env['load_average_start']}")
    suite = importlib.import_module(f"torchfra.cli.bench.{args.suite}")
    records = suite.fem_suite(cfg) if args.suite == "fem" else getattr(suite, f"{args.suite}_suite")(cfg, args)
    definitions = getattr(suite, f"{args.suite.upper()}_DEFINITIONS", None)
    if definitions is None:  # the sensitivity suite's JSON has always carried the FE core's definitions
        from torchfra.cli.bench.fem import DEFINITIONS as definitions
    result = {"suite": args.suite, "quick": args.quick, "environment": env, **records, "definitions": definitions}
    env["load_average_end"] = list(os.getloadavg())
    env["memory_available_mb_end"] = available_memory_mb()
    result["total_wall_s"] = time.perf_counter() - _START
    text = json.dumps(rounded(result), indent=1)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            f.write(text + "\n")
    print(text)
    log(f"done in {result['total_wall_s']:.1f} s")
    return result


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
