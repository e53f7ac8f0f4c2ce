"""Decks as Abaqus/CAE writes them: parts, an assembly of their instances, instance-qualified names.

A CAE deck defines each mesh once in a ``*PART, NAME=P`` ... ``*END PART`` block and places it with
``*INSTANCE, NAME=I, PART=P`` ... ``*END INSTANCE`` inside ``*ASSEMBLY`` ... ``*END ASSEMBLY``. The
reader flattens this into one mesh, as if the deck had been written flat:

- every instance gets the part's nodes, elements, sets, surfaces and sections; its node and element
  ids are the part's shifted past every id defined before it (the first instance keeps the part's
  ids), its set and surface names are qualified, ``I.NAME`` (upper-cased, as Abaqus does);
- the instance's data lines place it: an optional translation ``tx, ty, tz``, then an optional
  rotation ``ax, ay, az, bx, by, bz, angle`` about the axis from point a to point b by ``angle``
  degrees (right-hand rule); the translation is applied first, then the rotation, both in the
  assembly's coordinates;
- at assembly level (and in the model and history data after ``*END ASSEMBLY``) a name or id is
  the assembly's own unless qualified: ``I.NAME`` is the set or surface NAME of instance I, ``I.5``
  its node or element 5; ``*NSET`` / ``*ELSET, INSTANCE=I`` define assembly sets from instance I's
  ids and sets. Nodes defined at assembly level (reference points) are numbered past the instances'.

Inside a part (and an instance block) the reader accepts the cards that describe a mesh and its
sections (:data:`PART_CARDS`); a part that is never instanced is not part of the model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

PART_CARDS = {"NODE", "ELEMENT", "NSET", "ELSET", "SURFACE", "SOLID SECTION", "ORIENTATION"}


@dataclass
class Scope:
    """Where a card stands: the instance it belongs to (None: the assembly or a flat deck), the shift
    of its node and element ids, and the placement of its nodes (x -> a + R (x + t - a))."""

    instance: str | None = None
    node_offset: int = 0
    element_offset: int = 0
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    axis_point: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def qualify(self, name: str) -> str:
        """A set or surface name defined in this scope, as the flat deck knows it."""
        return name if self.instance is None else f"{self.instance}.{name}"

    def place(self, xyz: np.ndarray) -> np.ndarray:
        """Coordinates (3,) of a node of this scope in the assembly."""
        if self.instance is None:
            return xyz
        return self.axis_point + self.rotation @ (xyz + self.translation - self.axis_point)


def rotation_matrix(axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rotation (3, 3) by ``degrees`` about the unit vector along ``axis`` (right-hand rule; Rodrigues'
    formula R = I + sin(t) K + (1 - cos(t)) K^2, K the cross-product matrix of the unit axis)."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    t = math.radians(degrees)
    return np.eye(3) + math.sin(t) * K + (1.0 - math.cos(t)) * (K @ K)


def placement(card, number) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translation (3,), rotation (3, 3), axis point a (3,)) of an ``*INSTANCE`` card's data lines;
    ``number(card, line, text, what)`` reads a field."""
    if len(card.data) > 2:
        raise card.error("expects at most two data lines: a translation 'tx, ty, tz' and a rotation "
                         "'ax, ay, az, bx, by, bz, angle'", card.data[2])
    t, R, a = np.zeros(3), np.eye(3), np.zeros(3)
    if card.data:
        line = card.data[0]
        if len(line.fields) > 3:
            raise card.error("the first data line is the translation 'tx, ty, tz'", line)
        values = [number(card, line, f or "0", "a translation") for f in line.fields]
        t = np.array(values + [0.0] * (3 - len(values)))
    if len(card.data) == 2:
        line = card.data[1]
        if len(line.fields) != 7:
            raise card.error("the rotation line is 'ax, ay, az, bx, by, bz, angle' (the axis from point a to "
                             "point b, the angle in degrees)", line)
        v = [number(card, line, f or "0", "a rotation entry") for f in line.fields]
        a, b = np.array(v[:3]), np.array(v[3:6])
        if not np.linalg.norm(b - a) > 0:
            raise card.error("the rotation axis needs two distinct points a and b", line)
        R = rotation_matrix(b - a, v[6])
    return t, R, a


def read_cards(reader, cards, number, error, path) -> None:
    """Feed ``cards`` to ``reader`` (its ``read(card)``, ``begin_assembly``, ``begin_instance``,
    ``end_instance`` and ``instances``), expanding each part at its instances; ``number`` reads a
    field, ``error`` is the exception class of a structure error in deck ``path``."""
    parts: dict[str, list] = {}
    part = instance = None
    in_assembly = assembled = False
    for card in cards:
        kw = card.keyword
        if part is not None:
            if kw == "END PART":
                card.check_params(set())
                part = None
            elif kw in PART_CARDS:
                parts[part].append(card)
            else:
                raise card.error(f"is not supported inside *PART {part} (a part holds {', '.join(sorted(PART_CARDS))}"
                                 "; loads, boundaries and steps go after *END ASSEMBLY)")
            continue
        if kw == "PART":
            card.check_params({"NAME"}, {"NAME"})
            card.no_data()
            if in_assembly:
                raise card.error("a part is defined before *ASSEMBLY, not inside it")
            part = card.name("NAME")
            if part in parts:
                raise card.error(f"part {part} is defined twice")
            parts[part] = []
        elif kw == "ASSEMBLY":
            card.check_params({"NAME"})
            card.no_data()
            if assembled:
                raise card.error("a second *ASSEMBLY; a deck has one")
            in_assembly = assembled = True
            reader.begin_assembly()
        elif kw == "INSTANCE":
            card.check_params({"NAME", "PART"}, {"NAME", "PART"})
            if not in_assembly or instance is not None:
                raise card.error("an instance goes inside *ASSEMBLY ... *END ASSEMBLY, one at a time (close the "
                                 "previous one with *END INSTANCE)")
            name, of = card.name("NAME"), card.name("PART")
            if of not in parts:
                raise card.error(f"part {of} is not defined (known: {', '.join(sorted(parts)) or 'none'}); define it "
                                 "with *PART before the assembly")
            if name in reader.instances:
                raise card.error(f"instance {name} is defined twice")
            reader.begin_instance(name, *placement(card, number))
            instance = name
            for c in parts[of]:
                reader.read(c)
        elif kw == "END INSTANCE":
            card.check_params(set())
            if instance is None:
                raise card.error("*END INSTANCE without an *INSTANCE")
            instance = None
            reader.end_instance()
        elif kw == "END ASSEMBLY":
            card.check_params(set())
            if not in_assembly or instance is not None:
                raise card.error("*END ASSEMBLY without an open *ASSEMBLY (or with an *INSTANCE not closed)")
            in_assembly = False
        elif kw == "END PART":
            raise card.error("*END PART without a *PART")
        elif instance is not None and kw not in PART_CARDS:
            raise card.error(f"is not supported inside *INSTANCE {instance} (an instance block holds "
                             f"{', '.join(sorted(PART_CARDS))})")
        else:
            reader.read(card)
    if part is not None:
        raise error(f"{path}: *PART {part} is never closed with *END PART")
    if in_assembly:
        raise error(f"{path}: *ASSEMBLY is never closed with *END ASSEMBLY")
    if parts and not assembled:
        raise error(f"{path}: the deck defines parts ({', '.join(sorted(parts))}) but no *ASSEMBLY placing them; "
                         "a part is in the model through an *INSTANCE")
