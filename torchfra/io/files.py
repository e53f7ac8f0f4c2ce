"""One bounded way in for every file a user hands in: recordings, pressure traces, DIC exports and
landmarks, TOML configs, decks and their ``*INCLUDE`` files.

Each reader names what it reads (``what="deck"``) and the error class it raises; this layer then
refuses, with the file's name and what to do,

- a path that does not exist ("no such deck file");
- a path that exists but is not a regular file: a folder, a FIFO (named pipe), a device such as
  ``/dev/zero``, a socket, or a link to one of them. This is decided from ``os.stat`` before the
  file is opened (opening a FIFO blocks until a writer comes; a device may never end), and checked
  again on the opened descriptor, which is opened non-blocking;
- a file over ``max_bytes`` (the limit is stated in the message, with the keyword that raises it);
- for text: UTF-16 (a byte-order mark), NUL bytes (a binary file), bytes that are not in the expected
  encoding (the line and column are named), more than ``max_lines`` lines.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["InputFileError", "check_regular", "open_binary", "read_bytes", "read_text"]

MAX_TEXT_BYTES = 256 << 20  # a default for text a user hands in; every reader may state its own


class InputFileError(ValueError):
    """A file that cannot be read as the kind of file it was given as; the message names it."""


def _kind(mode: int) -> str | None:
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a plain file"


def check_regular(path, what: str, *, error: type[Exception] = InputFileError) -> Path:
    """Refuse ``path`` unless it names an existing regular file (a link to one is fine).

    Parameters
    ----------
    path : str or Path
        The file a user gave.
    what : str
        What the file should be, in words ("recording", "deck", "parameter"); the messages say
        "no such <what> file" and "name the <what> file".
    error : type
        The exception class raised (the caller's own, e.g. ``RecordingError``); called with the message.

    Returns
    -------
    Path
        ``path`` as a :class:`~pathlib.Path`.

    Raises
    ------
    error
        For a missing path, a folder, a FIFO, a device, a socket, or a link to any of them; decided
        from ``os.stat`` alone, without opening the file.
    """
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        dangling = os.path.islink(path)
        raise error(f"{path}: no such {what} file{' (a link to a path that does not exist)' if dangling else ''}; "
                    "check the path") from None
    except NotADirectoryError:
        raise error(f"{path}: no such {what} file (a part of the path is a file, not a folder); check the path") \
            from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} file ({exc.strerror})") from None
    kind = _kind(mode)
    if kind is not None:
        link = f" (a link to {os.path.realpath(path)})" if os.path.islink(path) else ""
        if kind == "a folder":
            raise error(f"{path}: is a folder{link}, not a {what} file; name the {what} file inside it")
        raise error(f"{path}: is {kind}{link}, not a regular file; name the {what} file "
                    "(save the data to a file first if it comes from a pipe or a device)")
    return path


def _limit_message(path: Path, size_text: str, what: str, max_bytes: int, limit_name: str) -> str:
    return (f"{path}: {size_text}, over the limit of {max_bytes} bytes for a {what} file; is this the right "
            f"file? If it is, raise the limit ({limit_name}=...)")


def open_binary(path, what: str, *, max_bytes: int | None = None, error: type[Exception] = InputFileError,
                limit_name: str = "max_bytes"):
    """Open a regular file for reading bytes, after :func:`check_regular` (and the size limit).

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file should be, in words (see :func:`check_regular`).
    max_bytes : int, optional
        Refuse a file larger than this (from its stat); None: no limit here (the caller bounds what it reads).
    error : type
        The exception class raised.
    limit_name : str
        The keyword that raises ``max_bytes``, as the message names it.

    Returns
    -------
    file object
        Opened in binary mode; the caller closes it (``with open_binary(...) as f``).

    Raises
    ------
    error
        See :func:`check_regular`; also for a file over ``max_bytes`` or one that cannot be opened.
    """
    path = check_regular(path, what, error=error)
    try:
        # non-blocking: should the path have become a FIFO since the stat, opening it does not wait for a writer
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise error(f"{path}: cannot open the {what} file ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        kind = _kind(st.st_mode)
        if kind is not None:
            raise error(f"{path}: is {kind}, not a regular file; name the {what} file")
        if max_bytes is not None and st.st_size > max_bytes:
            raise error(_limit_message(path, f"{st.st_size} bytes", what, max_bytes, limit_name))
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path, what: str, *, max_bytes: int, error: type[Exception] = InputFileError,
               limit_name: str = "max_bytes") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (see :func:`open_binary`).

    Parameters
    ----------
    path, what, max_bytes, error, limit_name
        As for :func:`open_binary`; ``max_bytes`` is required and holds also for a file that grows
        while it is read.

    Returns
    -------
    bytes
        The file's content.
    """
    with open_binary(path, what, max_bytes=max_bytes, error=error, limit_name=limit_name) as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise error(_limit_message(Path(path), f"more than {max_bytes} bytes", what, max_bytes, limit_name))
    return data


def decode_text(data: bytes, path, what: str, *, encoding: str = "utf-8", max_lines: int | None = None,
                error: type[Exception] = InputFileError, errors: str = "strict") -> str:
    """``data`` (a file's bytes) as text, refused with the file's name if it is not text in ``encoding``.

    Parameters
    ----------
    data : bytes
        The file's content.
    path : str or Path
        The file, for the messages.
    what : str
        What the file should be, in words.
    encoding : str
        The encoding expected; a UTF-8 byte-order mark is skipped when it is ``"utf-8"``.
    max_lines : int, optional
        Refuse more lines than this.
    error : type
        The exception class raised.
    errors : str
        ``"strict"``: refuse bytes not in ``encoding``; ``"replace"``: read them as U+FFFD (for formats
        whose readers name what they cannot read further on).

    Returns
    -------
    str
        The text.

    Raises
    ------
    error
        For UTF-16 text (a byte-order mark), NUL bytes, bytes not in ``encoding`` (line and column named),
        more than ``max_lines`` lines.
    """
    path = Path(path)
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise error(f"{path}: the {what} file is UTF-16 text; it is read as {encoding}: save it as {encoding}")
    nul = data.find(b"\0")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise error(f"{path}, line {line}: NUL bytes: a binary file, not {what} text ({encoding} expected); "
                    f"is this the right file?")
    if max_lines is not None:
        n = data.count(b"\n") + (0 if data.endswith(b"\n") or not data else 1)
        if n > max_lines:
            raise error(f"{path}: {n} lines, over the limit of {max_lines} lines for a {what} file; is this the "
                        "right file? If it is, raise the limit (max_lines=...)")
    if encoding.replace("_", "-").lower() in ("utf-8", "utf8") and data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        return data.decode(encoding, errors)
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise error(f"{path}, line {line}: byte 0x{data[exc.start]:02x} at column {column} is not {encoding} text; "
                    f"save the {what} file as {encoding}") from None


def read_text(path, *, what: str, max_bytes: int = MAX_TEXT_BYTES, max_lines: int | None = None,
              encoding: str = "utf-8", error: type[Exception] = InputFileError) -> str:
    """The text of a file a user hands in, read within limits.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file should be, in words ("deck", "parameter", "landmark"): the messages name it.
    max_bytes : int
        Refuse a larger file (the message states the limit).
    max_lines : int, optional
        Refuse a file with more lines.
    encoding : str
        The encoding expected (a UTF-8 byte-order mark is skipped).
    error : type
        The exception class raised (the caller's own); called with the message.

    Returns
    -------
    str
        The file's text.

    Raises
    ------
    error
        For a missing file, one that is not a regular file (folder, FIFO, device, socket, or a link to
        one; decided before opening), one over ``max_bytes`` or ``max_lines``, binary or UTF-16 content,
        or bytes not in ``encoding``.
    """
    data = read_bytes(path, what, max_bytes=max_bytes, error=error)
    return decode_text(data, path, what, encoding=encoding, max_lines=max_lines, error=error)
