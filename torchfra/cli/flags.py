"""The flags the subcommands share, spelled one way, with their defaults (no torch here: ``--help`` stays fast).

- ``--pressure TRACE.csv`` is always a pressure-trace CSV (of a DIC export); a peak pressure in MPa
  is ``--peak-pressure``. The old spellings of the peak pressure (``--pressure NUMBER`` of
  ``forward``, ``make-recording``, ``scenarios`` and ``demo``, ``--forward-pressure`` of ``calibrate``)
  still work and say the new name on stderr.
- ``--resolution N``: the actuator's mesh resolution, default :data:`DEFAULT_RESOLUTION` in every command
  that builds the actuator for an ensemble or a recording, so their forward ensembles are shared
  (``--mesh`` is its old spelling).
- ``--name NAME`` with ``--runs-dir DIR``: a run folder ``DIR/NAME/``; ``--out PATH``: a file (or, for
  ``scenarios``, the suite's folder).
- ``--method auto|full|reduced``: how an ensemble's members are solved (:func:`resolve_method`).
- ``--c10``: C10 in MPa, the truth of a synthetic recording where one is made.
"""
from __future__ import annotations

import argparse
import sys

DEFAULT_RESOLUTION = 1  # the calibration's, the diagnosis's and make-recording's: one forward cache for all
PEAK_PRESSURE = 0.022  # MPa, the paper's largest pressure (§4); CalibrationConfig.pressure, ForwardConfig.pressure
METHODS = ("auto", "full", "reduced")


class Formatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's layout and ends every option's help with its default, unless the default
    is empty (None, False, an empty list) or the help already says it."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        empty = default is None or default is False or default is argparse.SUPPRESS or default == []
        if "default" in text or empty or not action.option_strings:
            return text
        return text + " (default: %(default)s)"


def parser(doc: str, **kw) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` whose description is the module's ``doc`` and whose help shows defaults."""
    return argparse.ArgumentParser(description=doc, formatter_class=Formatter, **kw)


class Renamed(argparse.Action):
    """An old spelling of a flag: sets the new flag's value and says the new name, once, on stderr."""

    def __init__(self, option_strings, dest, new: str, note: str = "", **kw):
        kw.setdefault("help", argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kw)
        self.new, self.note = new, note

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{option_string} is an old spelling: use {self.new}{self.note}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_renamed(p, old: str, new: str, dest: str, note: str = "", **kw) -> None:
    """Accept ``old`` as a deprecated spelling of ``new`` (same ``dest``, same ``type``)."""
    p.add_argument(old, dest=dest, action=Renamed, new=new, note=note, **kw)


def add_resolution(p, default: int = DEFAULT_RESOLUTION, what: str = "the FE model of the paper's actuator") -> None:
    """``--resolution N`` (old spelling ``--mesh``)."""
    p.add_argument("--resolution", type=int, default=default, metavar="N",
                   help=f"mesh resolution of {what} (1 = coarsest; a deck has its own mesh)")
    add_renamed(p, "--mesh", "--resolution", "resolution", type=int)


def _peak(value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a number: --pressure used to be the peak pressure in "
                                         "MPa here; give it as --peak-pressure (this command reads no pressure "
                                         "trace)") from None


def add_peak_pressure(p, default: float | None, text: str, old: tuple[str, ...] = ("--pressure",)) -> None:
    """``--peak-pressure MPA``; ``old``: its former spellings, still accepted with a note."""
    p.add_argument("--peak-pressure", type=float, default=default, metavar="MPA", help=text)
    for spelling in old:
        add_renamed(p, spelling, "--peak-pressure", "peak_pressure", type=_peak if spelling == "--pressure" else float,
                    note=" (MPa; --pressure names a pressure-trace CSV)" if spelling == "--pressure" else "")


def add_run_folder(p, default: str | None, what: str = "outputs") -> None:
    """``--name NAME`` and ``--runs-dir DIR``: the run folder ``DIR/NAME/``."""
    p.add_argument("--name", default=default, help=f"run name: {what} go to <runs-dir>/<name>/")
    p.add_argument("--runs-dir", default="runs", help="folder holding the run folders")


def add_method(p) -> None:
    """``--method auto|full|reduced``: how an ensemble's members are solved."""
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="full: every member by full Newton; reduced: a few snapshot members by full Newton, the "
                        "others on their reduced basis, each checked and re-solved in full if needed; auto: reduced, "
                        "unless the ensemble is too small for the basis to pay (fewer members than twice the snapshot "
                        "members), then full")


def add_threads(p) -> None:
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (recorded)")


def snapshot_count(n_parameters: int, snapshots: int = 0) -> int:
    """Members a reduced ensemble solves by full Newton for its basis: ``snapshots``, or by default
    ``max(5, 1 + 2 d)`` for ``d`` varying parameters (``torchfra.fem.reduced.select_snapshots``)."""
    return snapshots if snapshots > 0 else max(5, 1 + 2 * max(1, n_parameters))


def resolve_method(method: str, members: int, n_parameters: int, snapshots: int = 0) -> tuple[str, str]:
    """``auto`` made ``full`` or ``reduced``: (the method, one line saying why, empty unless ``auto`` chose full).

    A reduced ensemble solves ``snapshot_count`` members by full Newton, then each other member on the
    basis at about a fifth of a full solve plus one full check step; with fewer than twice as many members
    as snapshots, the basis serves fewer members than it costs, so ``auto`` solves every member in full."""
    if method != "auto":
        return method, ""
    snaps = snapshot_count(n_parameters, snapshots)
    if members < 2 * snaps:
        return "full", (f"--method auto: {members} members against {snaps} snapshot members a reduced basis needs; "
                        "too few for the basis to pay, so every member is solved by full Newton")
    return "reduced", ""
