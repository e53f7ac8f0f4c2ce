"""``torchfra``: one command with a subcommand per job.

    torchfra calibrate --config seed              # the paper's experiment: four posteriors of C10
    torchfra forward --members 100 --mesh 1       # a prior ensemble through the actuator model
    torchfra make-recording --truth C10=0.0048 --out runs/recordings/synthetic.csv
    torchfra import-dic exports/ --pressure-trace trace.csv --landmarks corners.csv --out rec.csv
    torchfra diagnose rec.csv                     # find the physics the model leaves out
    torchfra scenarios --quick                    # the diagnosis's proof suite
    torchfra bench --suite fem                    # benchmarks (JSON)
    torchfra demo                                 # the FE core on an ensemble of soft blocks

``torchfra <subcommand> --help`` lists each one's flags with their defaults. The subcommands are
imported only when run: ``--help`` of the command itself needs no torch.
"""
from __future__ import annotations

import importlib
import sys

# subcommand -> (module under torchfra.cli, one line of what it does)
SUBCOMMANDS = {
    "calibrate": ("calibrate", "calibrate parameters from a recording: hierarchical and restart EnKF, exact posterior"),
    "forward": ("forward", "a prior ensemble through the FE model (resumable, torchrun)"),
    "diagnose": ("diagnose", "find the physics the model leaves out of a recording"),
    "import-dic": ("import_dic", "a DIC export and its pressure trace as a recording on the model's face"),
    "virtual-dic": ("virtual_dic", "a virtual DIC experiment: speckle images of the FE actuator correlated by pyvale"),
    "make-recording": ("make_recording", "a synthetic recording of the actuator (or of a deck)"),
    "scenarios": ("scenarios", "the diagnosis's proof suite: recordings with concealed effects, scored"),
    "bench": ("bench", "benchmarks of the FE core, the ensembles and the sensitivities (JSON)"),
    "demo": ("demo", "the FE core on an ensemble of soft blocks bent by pressure"),
}


def usage() -> str:
    width = max(len(k) for k in SUBCOMMANDS)
    rows = "\n".join(f"  {k:<{width}}  {line}" for k, (_, line) in SUBCOMMANDS.items())
    return (f"usage: torchfra <subcommand> [flags]   (torchfra <subcommand> --help for its flags)\n\n"
            f"subcommands:\n{rows}\n\n{__doc__.split(chr(10) + chr(10), 1)[1].split('``torchfra <sub')[0].rstrip()}\n")


def main(argv: list[str] | None = None) -> None:
    """The ``torchfra`` entry point: dispatch to the subcommand's ``main`` and exit as it says."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        sys.exit(0)
    if argv[0] in ("-V", "--version"):
        from torchfra import __version__

        print(f"torchfra {__version__}")
        sys.exit(0)
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        close = [k for k in SUBCOMMANDS if k.startswith(name[:3])] if name else []
        print(f"torchfra: no subcommand {name!r}" + (f" (did you mean {close[0]}?)" if close else "")
              + f"; one of: {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        sys.exit(2)
    from torchfra.cli.run import run

    module = importlib.import_module(f"torchfra.cli.{SUBCOMMANDS[name][0]}")
    sys.argv = [f"torchfra {name}", *rest]
    run(module.main)


if __name__ == "__main__":
    main()
