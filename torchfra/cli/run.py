"""How the commands end: a user's mistake is one paragraph on stderr, not a traceback.

``run(main)`` calls ``main()`` (which parses ``sys.argv``). A wrong input (``ValueError`` and with
it the project's own errors: ``RecordingError``, ``ParameterError``, ``MeshError``,
``GeometryError``, ``ObservationError``, ``CheckpointError``, and ``UnicodeDecodeError``;
``KeyError``; ``OSError``: a missing file, a folder where a file belongs, no permission;
``CalculixError``) is printed as ``error: <message>`` with exit status 2, the status argparse gives
a wrong flag. Ctrl-C exits with 130 and says how to go on: runs resume from what they saved.
``--debug`` anywhere on the command line (removed before ``main`` sees it) lets the exception
through with its traceback; so does any other exception, which is a bug, not a wrong input.
"""
from __future__ import annotations

import sys
from typing import Callable, NoReturn

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what a shell reports for Ctrl-C
DEBUG_FLAG = "--debug"


def user_errors() -> tuple[type[BaseException], ...]:
    errors: tuple[type[BaseException], ...] = (ValueError, KeyError, OSError)
    abaqus = sys.modules.get("torchfra.io.abaqus.write")  # only a script that ran CalculiX can meet its error
    return errors + (abaqus.CalculixError,) if abaqus is not None else errors


def message(exc: BaseException) -> str:
    """The exception as one paragraph: no blank lines, file errors as '<file>: <reason>'."""
    if isinstance(exc, OSError) and exc.strerror:
        files = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        text = f"{' -> '.join(files)}: {exc.strerror}" if files else exc.strerror
    elif isinstance(exc, KeyError) and len(exc.args) == 1:
        text = f"no entry {exc.args[0]!r}"
    else:
        text = str(exc)
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return "\n".join(lines) or type(exc).__name__


def run(main: Callable[[], object]) -> NoReturn:
    """Run a script's ``main`` and exit: 0 (or the exit status ``main`` returns as an int), 2 on a
    wrong input, 130 when interrupted."""
    from torchfra.runtime.allocator import keep_freed_memory

    keep_freed_memory()  # a command's process is torchfra's own: freed blocks are kept for the next Newton step
    debug = DEBUG_FLAG in sys.argv[1:]
    if debug:
        sys.argv[1:] = [a for a in sys.argv[1:] if a != DEBUG_FLAG]
    try:
        result = main()
    except KeyboardInterrupt:
        if debug:
            raise
        print("\ninterrupted; rerun the same command to resume", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except user_errors() as exc:
        if debug:
            raise
        print(f"error: {message(exc)}\n(run with {DEBUG_FLAG} for the traceback)", file=sys.stderr)
        sys.exit(EXIT_USER_ERROR)
    sys.exit(result if isinstance(result, int) and not isinstance(result, bool) else 0)


def add_deck_flags(parser, values: str | None = "needs --param for its uncertain parameters") -> None:
    """``--inp``, ``--camera``, ``--face``: the user's own model from an Abaqus/CalculiX deck.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.
    values : str or None
        What ``--inp``'s help says about the deck's parameters in this command (None: nothing).
    """
    parser.add_argument("--inp", default=None, metavar="DECK.inp",
                        help="the user's own model, an Abaqus/CalculiX input deck (torchfra.io.read_inp), instead of "
                        "the paper's actuator; " + (f"{values}; " if values else "") + "its pressure is the deck's")
    parser.add_argument("--camera", choices=["+x", "-x"], default="+x",
                        help="side the camera looks from (default +x: the actuator's front face); recordings observe "
                        "uy and uz, so a deck is oriented with its camera on the x axis")
    parser.add_argument("--face", default=None, metavar="SURFACE",
                        help="with --inp: the deck's *SURFACE the camera observes (default: every face it sees)")


def check_deck_flags(args, pressure_flag: str = "pressure") -> None:
    """Refuse deck flags that cannot go together, before any work (``pressure_flag``: the flag that
    sets the model's pressure, which a deck sets itself)."""
    if args.inp is None:
        if args.face is not None:
            raise ValueError("--face names a surface of a deck: give the deck with --inp")
        return
    if pressure_flag and getattr(args, pressure_flag, None) is not None:
        flag = "--" + pressure_flag.replace("_", "-")
        raise ValueError(f"--inp {args.inp}: the deck's *DLOAD sets the pressure; drop {flag} (or change the deck)")
