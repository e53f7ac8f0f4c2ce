"""A deck's text as cards: keyword lines with their parameters and data lines, in file order, with
``*INCLUDE``\ d files inserted in place (the reading behind :func:`torchfra.io.abaqus.read_inp`).

Every file is read through :mod:`torchfra.io.files` (a FIFO, a device, a binary or UTF-16 file is
refused naming it). ``*INCLUDE, INPUT=file`` is resolved relative to the including file, links
followed, and must lie under one of the allowed folders (the deck's own and those the caller
names); an included file's text is never quoted in a message, as it may be no deck at all.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from torchfra.io.files import read_text

MAX_DECK_BYTES = 1 << 30  # per deck file (the deck and each included file)


class InpError(ValueError):
    """A deck the reader cannot turn into a model; the message names the file, the line and the keyword."""


@dataclass
class _Line:
    fields: list[str]
    file: str
    number: int
    included: bool = False  # from an *INCLUDEd file: its text is never quoted in a message


@dataclass
class _Card:
    keyword: str  # upper case, single spaces, without the '*'
    params: dict[str, str | None]  # upper-case key -> value (None for a flag)
    file: str
    number: int
    data: list[_Line] = field(default_factory=list)
    included: bool = False

    def error(self, message: str, line: _Line | None = None) -> InpError:
        where = line if line is not None else self
        return InpError(f"{where.file}, line {where.number}: *{self.keyword}: {message}")

    def check_params(self, allowed: set[str], required: tuple[str, ...] | set[str] = ()) -> None:
        for key in self.params:
            if key not in allowed:
                known = ", ".join(sorted(allowed)) or "none"
                raise self.error(f"parameter {key} is not supported by this reader (supported: {known})")
        for key in required:
            if not self.params.get(key):
                raise self.error(f"needs the parameter {key}=...")

    def name(self, key: str) -> str | None:
        value = self.params.get(key)
        return None if value is None else value.upper()

    def no_data(self) -> None:
        if self.data:
            raise self.error("takes no data lines", self.data[0])


def _split_keyword(text: str) -> tuple[str, dict[str, str | None]]:
    parts = [p.strip() for p in text[1:].split(",")]
    keyword = " ".join(parts[0].upper().split())
    params: dict[str, str | None] = {}
    for part in parts[1:]:
        if not part:
            continue
        key, eq, value = part.partition("=")
        params[" ".join(key.upper().split())] = value.strip().strip('"') if eq else None
    return keyword, params


def _include_target(card: _Card, path: Path, roots: list[Path]) -> Path:
    """The file an ``*INCLUDE, INPUT=`` names, resolved (links followed) and confined to ``roots``."""
    value = card.params["INPUT"]
    target = Path(value)
    resolved = (target if target.is_absolute() else path.parent / target).resolve()
    if not any(resolved.is_relative_to(root) for root in roots):
        allowed = ", ".join(str(r) for r in roots)
        raise card.error(f"INPUT={value} is {resolved}, outside the deck's folder ({allowed}); an included file "
                         "must lie in the deck's folder or below it: move it there, or allow its folder with "
                         "read_inp(..., include_dirs=[...])")
    return resolved


def _cards(path: Path, roots: list[Path], cards: list[_Card] | None = None, depth: int = 0,
           via: _Card | None = None) -> list[_Card]:
    """Cards of a deck in file order. ``*INCLUDE`` inserts its file's lines in place, as Abaqus does:
    data lines of an included file go on the card before the ``*INCLUDE`` if the file starts with
    data, and data lines after it go on the included file's last card. Included files must lie under
    one of ``roots``; their text is never quoted in a message (they may not be decks at all)."""
    cards = [] if cards is None else cards
    if depth > 10:
        raise InpError(f"{path}: *INCLUDE nested more than 10 deep")
    included = depth > 0
    try:
        lines = read_text(path, what="deck", max_bytes=MAX_DECK_BYTES, error=InpError).splitlines()
    except InpError as exc:
        if via is None:
            raise
        raise via.error(f"INPUT={via.params['INPUT']}: {exc}") from None
    i = 0
    while i < len(lines):
        number, text = i + 1, lines[i].strip()
        i += 1
        if not text or text.startswith("**"):
            continue
        if text.startswith("*"):
            while text.endswith(",") and i < len(lines):  # keyword line continued on the next line
                nxt = lines[i].strip()
                i += 1
                if nxt.startswith("**") or not nxt:
                    continue
                text += " " + nxt
            keyword, params = _split_keyword(text)
            card = _Card(keyword, params, str(path), number, included=included)
            if keyword == "INCLUDE":
                card.check_params({"INPUT"}, {"INPUT"})
                _cards(_include_target(card, Path(path), roots), roots, cards, depth + 1, card)
            else:
                cards.append(card)
            continue
        if not cards:
            shown = "" if included else f": {text[:60]!r}"
            raise InpError(f"{path}, line {number}: data line before the first keyword{shown}; a deck starts with "
                           "a keyword line (*HEADING, *NODE, ...)")
        fields = [f.strip() for f in text.split(",")]
        while fields and not fields[-1]:
            fields.pop()
        cards[-1].data.append(_Line(fields, str(path), number, included))
    return cards


def _shown(card: _Card, line: _Line | None, text: str) -> str:
    """``text`` quoted for a message, unless it comes from an included file (whose text is not shown)."""
    where = line if line is not None else card
    return "(text of an included file, not shown)" if where.included else repr(text)


def _label(card: _Card, line: _Line | None, name: str) -> str:
    """A name read from a data line, for a message; not shown when the line comes from an included file."""
    where = line if line is not None else card
    return "(a name in an included file, not shown)" if where.included else name


def _int(card: _Card, line: _Line | None, text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise card.error(f"{what} must be an integer, got {_shown(card, line, text)}", line) from None


def _float(card: _Card, line: _Line | None, text: str, what: str) -> float:
    try:
        return float(text.replace("d", "e").replace("D", "e"))
    except ValueError:
        raise card.error(f"{what} must be a number, got {_shown(card, line, text)}", line) from None


def _is_int(text: str) -> bool:
    return re.fullmatch(r"[+-]?\d+", text) is not None
