"""Read an Abaqus/CalculiX input deck into a :class:`torchfra.fem.Model` (the inverse of ``write_inp``).

``read_inp(path)`` returns ``(model, params)``: the model in torchfra units (mm, MPa, N) and one
float per parameter its terms use, each the value of the deck (a load at load factor 1). Keywords
and parameters are read case-insensitively, names of sets, surfaces, materials and amplitudes are
upper-cased as Abaqus does, ``**`` lines are comments, a keyword line ending with a comma goes on on
the next line, ``*INCLUDE, INPUT=file`` is followed (relative to the including file; the file must
lie in the deck's folder or below it, or under a folder of ``include_dirs``). Every file is read
through :mod:`torchfra.io.files` (a FIFO, a device, a binary or UTF-16 file is refused naming it)
into cards (:mod:`torchfra.io.abaqus.cards`).
Decks in Abaqus/CAE's layout (``*PART`` / ``*ASSEMBLY`` / ``*INSTANCE``, instance-qualified names
``Part-1-1.Set-1``) are flattened into one mesh (:mod:`torchfra.io.abaqus.assembly`).

What each card becomes:

- ``*NODE`` -> model nodes. Node ``i`` of the model is Abaqus id ``i + 1`` when the kept ids are
  ``1..n``; otherwise the kept nodes are numbered in file order (``read_inp(..., with_ids=True)``
  returns the ids). Kept are the nodes of elements and of rigid-body node sets; rigid-body
  reference and rotation nodes (``write_inp`` adds two per body after the model's) and stray nodes
  are left out. The mesh holds the nodes up to the last brick node, later ones (fiber nodes) are
  added with ``Model.add_nodes``, as ``write_inp``'s fiber models are built.
- ``*ELEMENT, TYPE=C3D20R | C3D20RH | C3D20 | C3D20H`` -> Hex20 bricks (Abaqus C3D20 node order,
  20 nodes over as many lines as needed); ``R`` = reduced 2x2x2 integration, ``H`` = hybrid u-p
  formulation. Mesh element ``e`` is brick id ``e + 1`` when the brick ids are ``1..E``, otherwise
  the bricks in file order. ``TYPE=T3D3`` (end, middle, end) -> :class:`Truss` rows (end, end,
  middle). ``TYPE=T3D2`` -> a Line3 truss whose middle node is a new node (appended after the deck's
  nodes) tied to the mean of the two ends: its Green strain is the constant strain of the two-node
  truss, so it stores exactly torchfra's energy of a two-node truss.
- ``*NSET`` / ``*ELSET`` (ids, set names, ``GENERATE``; ``*NSET, ELSET=`` for the nodes of element
  sets) -> sets; node sets of mesh nodes become ``mesh.node_sets``.
- ``*SURFACE, TYPE=ELEMENT`` (``element or elset, S1..S6``) -> ``mesh.face_sets`` (face = S - 1).
- ``*ORIENTATION`` and ``*SOLID SECTION, ORIENTATION=`` are accepted with a note (:class:`InpNote`,
  a warning): every material read here is isotropic, so a local frame has no effect.
- ``*SOLID SECTION, ELSET, MATERIAL`` -> one :class:`Hex20Solid` per section and brick type, with
  ``*HYPERELASTIC, NEO HOOKE`` (or ``REDUCED POLYNOMIAL, N=1``) -> :class:`NeoHookean` (``C10, D1``)
  or ``*HYPERELASTIC, MOONEY-RIVLIN`` (or ``POLYNOMIAL, N=1``) -> :class:`MooneyRivlin`
  (``C10, C01, D1``); one :class:`Truss` per truss section with the section's area (mm^2, its data
  line) and ``*ELASTIC`` ``E`` (MPa; Poisson's ratio does not enter a truss's force). A material
  option belongs to the block its ``*MATERIAL`` opens; any other keyword closes the block, so a
  ``*DENSITY`` after a ``*BOUNDARY`` is an error naming its line.
- ``*BOUNDARY`` (``node or nset, first dof, last dof, value`` or ``ENCASTRE``, ``PINNED``,
  ``XSYMM``...) -> ``Model.clamp`` for value 0, ``Model.prescribe`` (value at load factor 1)
  otherwise; a later card on the same dof replaces an earlier one (Abaqus ``OP=MOD``). Rotational
  dofs 4-6 set to zero are accepted (solid and truss nodes have none).
- ``*RIGID BODY, NSET, REF NODE[, ROT NODE]`` -> ``Model.rigid`` (its reference point is the
  centroid of the set; the motions are the same whatever the reference node). A reference node
  fixed in all six dofs (or with the rotation node in its three) clamps the set instead.
- ``*EQUATION`` ``u_n - sum_h w_h u_h = 0`` in dof 1, 2 and 3 with the same hosts and weights (the
  embedded-node ties ``write_inp`` writes) -> ``Model.embed``. ``*EMBEDDED ELEMENT, HOST ELSET``
  with the embedded elements on its data lines -> every node of those elements that is no brick
  node is located in the host bricks and embedded (``EXTERIOR TOLERANCE``, default 0.05 of the mean
  host size, or ``ABSOLUTE EXTERIOR TOLERANCE`` in mm).
- ``*DLOAD`` ``element or elset, P1..P6, p`` and ``*DSLOAD`` ``surface, P, p`` -> pressure on brick
  faces, one term per distinct magnitude: :class:`CavityPressure` where the loaded faces close a
  cavity (its residual equals the follower's there), :class:`FollowerPressure` otherwise. A face
  loaded twice is an error (Abaqus replaces such a load, CalculiX adds it). ``elset, GRAV, g, dx,
  dy, dz`` -> :class:`Gravity` with the ``*DENSITY`` of the elements' material.
- ``*AMPLITUDE`` referenced by a load or boundary -> that load's value at step time 1; it must
  ramp linearly from 0 at step time 0 to there (torchfra ramps every load with the one load factor).
  Unreferenced amplitudes are ignored.

Parameter names are those the torchfra terms expect: ``C10``, ``C01``, ``D1`` (fixed by the
materials, so every body must share them), ``E_fiber`` for the truss modulus (``E_fiber_<MATERIAL>``
per material when the truss materials differ), ``P`` for the pressure (``P_<SURFACE>`` or ``P_<k>``
per magnitude when several differ) and ``density`` (``density_<MATERIAL>`` when several differ).

Accepted and ignored (output requests, step controls): ``*HEADING``, ``*PREPRINT``, ``*STEP``, ``*STATIC``,
``*CONTROLS``, ``*NODE PRINT``, ``*NODE FILE``, ``*EL PRINT``, ``*EL FILE``, ``*OUTPUT``,
``*NODE OUTPUT``, ``*ELEMENT OUTPUT``, ``*END STEP``; one step only, and ``*STEP, NLGEOM=NO``,
``*STEP, PERTURBATION`` and ``*STATIC, RIKS`` are errors (torchfra solves finite strain along a
proportional load path; a ``*STEP`` without ``NLGEOM``, geometrically linear in Abaqus, is read as
finite strain too). Everything else (another keyword, element type, load label, material
option or keyword parameter) raises :class:`InpError` (a ``ValueError``) naming it, the file and the
line; so do undefined nodes, elements, sets, surfaces, materials and amplitudes.

Not representable, hence errors: springs (``SPRING1``/``SPRING2``, which ``write_inp`` writes for
:class:`ElasticSupport`), concentrated loads, linear elastic bricks, bodies with different
hyperelastic constants (the torchfra materials' parameter names are fixed), partial constraints of
a rigid body's reference node, ``*EQUATION`` ties of single components. What a deck does not carry
is not restored: the original parameter names of trusses and pressures, ``SensorCavityPressure``
(written at its true pressure, read as a cavity pressure), the face quadrature of pressure terms
(``pressure_quadrature`` sets it).
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchfra.fem.elements import hex20_shape
from torchfra.fem.embedding import locate_points
from torchfra.fem.gravity import Gravity
from torchfra.fem.materials import MooneyRivlin, NeoHookean
from torchfra.fem.mesh import Mesh, MeshError
from torchfra.fem.model import Model
from torchfra.fem.pressure import CavityPressure, FollowerPressure, check_closed
from torchfra.fem.solid import Hex20Solid
from torchfra.fem.truss import Truss, two_node_truss
from torchfra.io.abaqus.assembly import Scope, read_cards
from torchfra.io.abaqus.cards import InpError, _Card, _cards, _float, _int, _is_int, _label, _Line

__all__ = ["InpError", "InpIds", "InpNote", "read_inp"]

# element type -> (Hex20Solid formulation, integration)
_BRICKS = {
    "C3D20R": ("displacement", "reduced"),
    "C3D20RH": ("hybrid", "reduced"),
    "C3D20": ("displacement", "full"),
    "C3D20H": ("hybrid", "full"),
}
_TRUSSES = {"T3D3": 3, "T3D2": 2}

_MATERIAL_OPTIONS = {"HYPERELASTIC", "ELASTIC", "DENSITY"}
_IGNORED = {
    "HEADING", "PREPRINT", "STEP", "STATIC", "CONTROLS", "NODE PRINT", "NODE FILE", "EL PRINT", "EL FILE", "OUTPUT",
    "NODE OUTPUT", "ELEMENT OUTPUT", "END STEP",
}

# named boundary conditions -> (displacement components fixed, 0-based)
_NAMED_BOUNDARIES = {
    "ENCASTRE": (0, 1, 2), "PINNED": (0, 1, 2),
    "XSYMM": (0,), "YSYMM": (1,), "ZSYMM": (2,),
    "XASYMM": (1, 2), "YASYMM": (0, 2), "ZASYMM": (0, 1),
}

# *HYPERELASTIC option -> (material class, parameter names of its data line)
_HYPERELASTIC = {
    "NEO HOOKE": (NeoHookean, ("C10", "D1")),
    "REDUCED POLYNOMIAL": (NeoHookean, ("C10", "D1")),
    "MOONEY-RIVLIN": (MooneyRivlin, ("C10", "C01", "D1")),
    "POLYNOMIAL": (MooneyRivlin, ("C10", "C01", "D1")),
}


class InpNote(UserWarning):
    """A card read but without effect on the model (e.g. an orientation of an isotropic material)."""


@dataclass
class InpIds:
    """Abaqus ids of the model's entities.

    nodes: (n_nodes,) id of every model node (-1 for the middle nodes added for T3D2 trusses).
    elements: (n_elements,) id of every mesh element (brick).
    """

    nodes: np.ndarray
    elements: np.ndarray


@dataclass
class _Material:
    card: _Card
    hyperelastic: tuple[type, dict[str, float], _Card] | None = None
    elastic: tuple[float, _Card] | None = None
    density: tuple[float, _Card] | None = None


class _Reader:
    """Collects a deck's cards into plain data, then builds the model (``build``)."""

    def __init__(self, dtype, pressure_quadrature: int):
        self.dtype, self.quadrature = dtype, pressure_quadrature
        self.nodes: dict[int, np.ndarray] = {}
        self.elements: dict[int, tuple[str, tuple[int, ...], _Card, _Line]] = {}
        self.nsets: dict[str, dict[int, None]] = {}
        self.elsets: dict[str, dict[int, None]] = {}
        self.surfaces: dict[str, list[tuple[int, int, _Card, _Line]]] = {}
        self.materials: dict[str, _Material] = {}
        self.material: _Material | None = None
        self.material_end: tuple[str, _Card] | None = None  # the open block's material and the card that closed it
        self.sections: list[tuple[str, str, float | None, _Card]] = []
        self.rigid: list[tuple[list[int], int, int | None, _Card]] = []
        self.equations: list[tuple[list[tuple[int, int, float]], _Card, _Line]] = []
        self.embedded: list[tuple[str, list[int], _Card]] = []
        self.boundaries: list[tuple[int, int, float, str | None, _Card, _Line]] = []
        self.face_loads: list[tuple[int, int, float, str | None, _Card, _Line]] = []
        self.gravity: list[tuple[list[int], float, tuple[float, ...], str | None, _Card, _Line]] = []
        self.amplitudes: dict[str, _Card] = {}
        self.orientations: dict[str, _Card] = {}
        self.oriented: list[tuple[str, str, _Card]] = []  # (material, orientation, section card)
        self.steps = 0
        self._scope: Scope | None = Scope()  # a flat deck: ids and names as written; None: assembly level
        self.assembly: Scope | None = None  # the assembly's own ids are numbered past the instances'
        self.instances: dict[str, Scope] = {}

    # -- parts, instances and qualified names (torchfra.io.abaqus.assembly) ----------------------------
    @property
    def scope(self) -> Scope:
        """The scope of the card being read: an instance's, the assembly's, or a flat deck's."""
        if self._scope is not None:
            return self._scope
        if self.assembly is None:  # fixed at its first use, once the instances before it are defined
            self.assembly = Scope(None, max(self.nodes, default=0), max(self.elements, default=0))
        return self.assembly

    def begin_assembly(self) -> None:
        self._scope = None

    def begin_instance(self, name: str, translation, rotation, axis_point) -> None:
        self._scope = self.instances[name] = Scope(name, max(self.nodes, default=0), max(self.elements, default=0),
                                                   rotation, translation, axis_point)

    def end_instance(self) -> None:
        self._scope = None

    def _in(self, card: _Card) -> Scope:
        """The scope of a card's ids and names: its own, or that of ``INSTANCE=`` at assembly level."""
        name = card.name("INSTANCE")
        if name is None:
            return self.scope
        if self.scope.instance is not None or not self.instances:
            raise card.error("INSTANCE= belongs on a set defined at assembly level")
        if name not in self.instances:
            raise card.error(f"instance {name} is not defined (known: {', '.join(sorted(self.instances)) or 'none'})")
        return self.instances[name]

    def _global(self, card: _Card, text: str, kind: str) -> tuple[int | None, str]:
        """A reference as written -> (global id, "") for an id, (None, global name) for a name; at
        assembly level ``I.5`` and ``I.NAME`` are instance I's id 5 and set or surface NAME."""
        scope = self._in(card)
        head, dot, rest = text.partition(".")
        if dot and scope.instance is None and head.upper() in self.instances:
            scope, text = self.instances[head.upper()], rest
            if not _is_int(text):
                return None, scope.qualify(text.upper())
        if _is_int(text):
            return (scope.node_offset if kind == "node" else scope.element_offset) + int(text), ""
        return None, scope.qualify(text.upper())

    def defined_name(self, card: _Card, key: str) -> str | None:
        """The global name of a set or surface a card defines (an instance's names are qualified)."""
        name = card.name(key)
        return None if name is None else self.scope.qualify(name)

    # -- references ----------------------------------------------------------------------------------
    def node_refs(self, card: _Card, line: _Line | None, text: str) -> list[int]:
        node, name = self._global(card, text, "node")
        if node is not None:
            if node not in self.nodes:
                raise card.error(f"node {text} is not defined", line)
            return [node]
        if name not in self.nsets:
            known = ", ".join(sorted(self.nsets)) or "none"
            raise card.error(f"node set {_label(card, line, name)} is not defined (known: {known})", line)
        return list(self.nsets[name])

    def element_refs(self, card: _Card, line: _Line | None, text: str) -> list[int]:
        element, name = self._global(card, text, "element")
        if element is not None:
            if element not in self.elements:
                raise card.error(f"element {text} is not defined", line)
            return [element]
        if name not in self.elsets:
            known = ", ".join(sorted(self.elsets)) or "none"
            raise card.error(f"element set {_label(card, line, name)} is not defined (known: {known})", line)
        return list(self.elsets[name])

    def amplitude_at_one(self, name: str, card: _Card, line: _Line | None) -> float:
        """Value of amplitude ``name`` at step time 1; raise unless it ramps linearly from 0 there."""
        amp = self.amplitudes.get(name)
        if amp is None:
            raise card.error(f"amplitude {name} is not defined", line)
        amp.check_params({"NAME", "TIME", "DEFINITION", "VALUE"}, {"NAME"})
        for key, ok in (("TIME", ("STEP TIME", "TOTAL TIME")), ("DEFINITION", ("TABULAR",)), ("VALUE", ("RELATIVE",))):
            value = amp.name(key)
            if value is not None and " ".join(value.split()) not in ok:
                raise amp.error(f"{key}={value} is not supported (only {' or '.join(ok)})")
        numbers = [_float(amp, ln, f, "an amplitude entry") for ln in amp.data for f in ln.fields if f]
        if len(numbers) < 2 or len(numbers) % 2:
            raise amp.error("needs pairs 'time, value'")
        t, a = np.array(numbers[0::2]), np.array(numbers[1::2])
        if np.any(np.diff(t) <= 0):
            raise amp.error("times must increase")
        at_one = float(np.interp(1.0, t, a))
        check = np.concatenate([[0.0], t[(t > 0) & (t < 1)]])
        if np.any(np.abs(np.interp(check, t, a) - check * at_one) > 1e-12 * max(1.0, abs(at_one))):
            raise amp.error(
                "does not ramp linearly from 0 at step time 0 to step time 1; torchfra ramps every load and "
                "prescribed displacement with one load factor (the value at step time 1 is the one at load factor 1)"
            )
        return at_one

    # -- cards ---------------------------------------------------------------------------------------
    def read(self, card: _Card) -> None:
        if card.keyword not in _MATERIAL_OPTIONS and self.material is not None:
            self.material_end = (self.material.card.name("NAME"), card)  # any other keyword ends the block
            self.material = None
        handler = getattr(self, "card_" + card.keyword.replace(" ", "_").replace("-", "_"), None)
        if handler is not None:
            handler(card)
        elif card.keyword == "STEP":
            self.steps += 1
            if self.steps > 1:
                raise card.error("a second step; this reader reads one *STATIC step (one load path)")
            if (card.name("NLGEOM") or "YES") == "NO" or "PERTURBATION" in card.params:
                raise card.error("NLGEOM=NO / PERTURBATION: torchfra solves finite strain only")
            if (card.name("AMPLITUDE") or "RAMP") != "RAMP":
                raise card.error("AMPLITUDE=STEP is not supported: loads ramp with the load factor")
        elif card.keyword == "STATIC" and "RIKS" in card.params:
            raise card.error("RIKS (arc length) is not supported: the load factor is prescribed in torchfra")
        elif card.keyword in _IGNORED:
            pass
        else:
            raise card.error("keyword is not supported by torchfra.io.abaqus.read (no torchfra counterpart)")

    def card_NODE(self, card: _Card) -> None:
        card.check_params({"NSET"})
        scope = self.scope
        ids = []
        for line in card.data:
            if not 3 <= len(line.fields) <= 4:
                raise card.error("expects 'id, x, y[, z]'", line)
            label = _int(card, line, line.fields[0], "node id")
            node = scope.node_offset + label
            if node in self.nodes:
                raise card.error(f"node {label} is defined twice", line)
            xyz = [_float(card, line, f or "0", "a coordinate") for f in line.fields[1:]]
            self.nodes[node] = scope.place(np.array(xyz + [0.0] * (3 - len(xyz))))
            ids.append(node)
        if card.name("NSET"):
            self.nsets.setdefault(self.defined_name(card, "NSET"), {}).update(dict.fromkeys(ids))

    def card_ELEMENT(self, card: _Card) -> None:
        card.check_params({"TYPE", "ELSET"}, {"TYPE"})
        kind = card.name("TYPE")
        if kind not in _BRICKS and kind not in _TRUSSES:
            raise card.error(
                f"element type {kind} is not supported (supported: {', '.join(list(_BRICKS) + list(_TRUSSES))})"
            )
        n = 20 if kind in _BRICKS else _TRUSSES[kind]
        ids, fields, first = [], [], None
        for line in card.data:
            first = first or line
            fields += line.fields
            if len(fields) < n + 1:
                continue
            if len(fields) > n + 1:
                raise card.error(f"a {kind} element has an id and {n} nodes; got {len(fields) - 1} nodes", line)
            label = _int(card, first, fields[0], "element id")
            element = self.scope.element_offset + label
            if element in self.elements:
                raise card.error(f"element {label} is defined twice", first)
            nodes = tuple(self.scope.node_offset + _int(card, first, f, "a node id") for f in fields[1:])
            self.elements[element] = (kind, nodes, card, first)
            ids.append(element)
            fields, first = [], None
        if fields:
            raise card.error(f"incomplete {kind} element: an id and {n} nodes expected", first)
        if card.name("ELSET"):
            self.elsets.setdefault(self.defined_name(card, "ELSET"), {}).update(dict.fromkeys(ids))

    def _set_members(self, card: _Card, refs) -> list[int]:
        members = []
        if "GENERATE" in card.params:
            for line in card.data:
                if len(line.fields) not in (2, 3):
                    raise card.error("GENERATE expects 'first, last[, increment]'", line)
                a, b, *step = (_int(card, line, f, "a GENERATE bound") for f in line.fields)
                step = step[0] if step else 1
                if step <= 0 or b < a:
                    raise card.error("GENERATE needs first <= last and a positive increment", line)
                for i in range(a, b + 1, step):
                    members += refs(card, line, str(i))
        else:
            for line in card.data:
                for f in line.fields:
                    if f:
                        members += refs(card, line, f)
        return members

    def card_NSET(self, card: _Card) -> None:
        card.check_params({"NSET", "GENERATE", "ELSET", "UNSORTED", "INTERNAL", "INSTANCE"}, {"NSET"})
        if "ELSET" in card.params:  # nodes of the elements of element sets (named on the card or the data lines)
            names = [card.params["ELSET"]] if card.params["ELSET"] else [f for ln in card.data for f in ln.fields if f]
            elements = [e for name in names for e in self.element_refs(card, card.data[0] if card.data else None, name)]
            members = [n for e in elements for n in self.elements[e][1]]
        else:
            members = self._set_members(card, self.node_refs)
        self.nsets.setdefault(self.defined_name(card, "NSET"), {}).update(dict.fromkeys(members))

    def card_ELSET(self, card: _Card) -> None:
        card.check_params({"ELSET", "GENERATE", "UNSORTED", "INTERNAL", "INSTANCE"}, {"ELSET"})
        members = self._set_members(card, self.element_refs)
        self.elsets.setdefault(self.defined_name(card, "ELSET"), {}).update(dict.fromkeys(members))

    def card_SURFACE(self, card: _Card) -> None:
        card.check_params({"NAME", "TYPE"}, {"NAME"})
        if (card.name("TYPE") or "ELEMENT") != "ELEMENT":
            raise card.error(f"TYPE={card.name('TYPE')} is not supported (only element-based surfaces)")
        faces = self.surfaces.setdefault(self.defined_name(card, "NAME"), [])
        for line in card.data:
            if len(line.fields) != 2 or not re.fullmatch(r"S[1-6]", line.fields[1].upper()):
                raise card.error("expects 'element or element set, S1..S6'", line)
            for e in self.element_refs(card, line, line.fields[0]):
                faces.append((e, int(line.fields[1][1]) - 1, card, line))

    def card_SOLID_SECTION(self, card: _Card) -> None:
        card.check_params({"ELSET", "MATERIAL", "ORIENTATION"}, {"ELSET", "MATERIAL"})
        orientation = card.name("ORIENTATION")
        if orientation is not None:
            if self.scope.qualify(orientation) not in self.orientations:
                known = ", ".join(sorted(self.orientations)) or "none"
                raise card.error(f"orientation {orientation} is not defined (known: {known})")
            # every material this reader builds is isotropic, so a local frame changes nothing
            warnings.warn(f"{card.file}, line {card.number}: *SOLID SECTION: ORIENTATION={orientation} has no "
                          f"effect: material {card.name('MATERIAL')} is isotropic", InpNote, stacklevel=2)
        area = None
        if card.data:
            line = card.data[0]
            if len(card.data) > 1 or len(line.fields) > 1:
                raise card.error("expects at most one data line with the truss cross-section area", line)
            if line.fields:
                area = _float(card, line, line.fields[0], "the cross-section area")
        self.sections.append((self._global(card, card.params["ELSET"], "element")[1] or card.params["ELSET"],
                              card.name("MATERIAL"), area, card))

    def card_ORIENTATION(self, card: _Card) -> None:
        card.check_params({"NAME", "SYSTEM", "DEFINITION"}, {"NAME"})
        self.orientations[self.defined_name(card, "NAME")] = card

    def card_MATERIAL(self, card: _Card) -> None:
        card.check_params({"NAME"}, {"NAME"})
        card.no_data()
        name = card.name("NAME")
        if name in self.materials:
            raise card.error(f"material {name} is defined twice")
        self.material = self.materials[name] = _Material(card)

    def _current_material(self, card: _Card) -> _Material:
        if self.material is None:
            ended = ""
            if self.material_end is not None:
                name, end = self.material_end
                ended = (f" (the block of material {name} ended at line {end.number} of {end.file} with "
                         f"*{end.keyword})")
            raise card.error(f"is a material option outside a *MATERIAL block{ended}; move it into the "
                             "material's block, right after its *MATERIAL line")
        return self.material

    def _one_row(self, card: _Card, n: int, what: str) -> list[float]:
        if len(card.data) != 1 or len(card.data[0].fields) > n:
            line = card.data[1] if len(card.data) > 1 else (card.data[0] if card.data else None)
            raise card.error(f"expects one data line '{what}' (temperature-dependent data is not supported)", line)
        line = card.data[0]
        values = [_float(card, line, f or "0", what) for f in line.fields]
        return values + [0.0] * (n - len(values))

    def card_HYPERELASTIC(self, card: _Card) -> None:
        material = self._current_material(card)
        options = [k for k in card.params if k != "N"]
        if len(options) > 1 or (options and options[0] not in _HYPERELASTIC) or any(card.params[k] for k in options):
            raise card.error(
                f"option {', '.join(options)} is not supported (supported: {', '.join(_HYPERELASTIC)}; "
                "POLYNOMIAL and REDUCED POLYNOMIAL with N=1)"
            )
        option = options[0] if options else "POLYNOMIAL"  # the Abaqus default: POLYNOMIAL, N=1
        if "N" in card.params and (card.params["N"] or "").strip() != "1":
            raise card.error(f"N={card.params['N']} is not supported (only N=1)")
        if "N" in card.params and option not in ("POLYNOMIAL", "REDUCED POLYNOMIAL"):
            raise card.error(f"N= goes with POLYNOMIAL or REDUCED POLYNOMIAL, not {option}")
        cls, names = _HYPERELASTIC[option]
        values = dict(zip(names, self._one_row(card, len(names), ", ".join(names))))
        if not values["D1"] > 0:
            raise card.error(
                f"D1 = {values['D1']!r}: the incompressible limit D1 = 0 is not supported (torchfra needs D1 > 0)"
            )
        material.hyperelastic = (cls, values, card)

    def card_ELASTIC(self, card: _Card) -> None:
        material = self._current_material(card)
        card.check_params({"TYPE"})
        if (card.name("TYPE") or "ISOTROPIC") != "ISOTROPIC":
            raise card.error(f"TYPE={card.name('TYPE')} is not supported (only ISOTROPIC)")
        E, _ = self._one_row(card, 2, "E, nu")
        material.elastic = (E, card)

    def card_DENSITY(self, card: _Card) -> None:
        material = self._current_material(card)
        card.check_params(set())
        material.density = (self._one_row(card, 1, "density")[0], card)

    def card_BOUNDARY(self, card: _Card) -> None:
        card.check_params({"AMPLITUDE", "OP", "TYPE"})
        if (card.name("OP") or "MOD") != "MOD" or (card.name("TYPE") or "DISPLACEMENT") != "DISPLACEMENT":
            raise card.error("only OP=MOD and TYPE=DISPLACEMENT are supported")
        amp = card.name("AMPLITUDE")
        for line in card.data:
            if len(line.fields) < 2 or len(line.fields) > 4:
                raise card.error("expects 'node or node set, first dof[, last dof[, value]]' or a named condition",
                                 line)
            nodes = self.node_refs(card, line, line.fields[0])
            kind = line.fields[1].upper()
            if kind in _NAMED_BOUNDARIES:
                if len(line.fields) > 2:
                    raise card.error(f"{kind} takes no further fields", line)
                dofs = [1, 2, 3, 4, 5, 6] if kind == "ENCASTRE" else [c + 1 for c in _NAMED_BOUNDARIES[kind]]
                value = 0.0
            else:
                first = _int(card, line, kind, "the first dof")
                fields = line.fields + [""] * (4 - len(line.fields))
                last = _int(card, line, fields[2], "the last dof") if fields[2] else first
                if not 1 <= first <= last <= 6:
                    raise card.error(f"dofs {first}..{last}: only displacements (1-3) and rotations (4-6) exist", line)
                value = _float(card, line, fields[3], "the value") if fields[3] else 0.0
                dofs = list(range(first, last + 1))
            for node in nodes:
                for dof in dofs:
                    self.boundaries.append((node, dof, value, amp, card, line))

    def card_RIGID_BODY(self, card: _Card) -> None:
        card.check_params({"NSET", "TIE NSET", "PIN NSET", "REF NODE", "ROT NODE"}, {"REF NODE"})
        card.no_data()
        sets = [card.params[k] for k in ("NSET", "TIE NSET", "PIN NSET") if card.params.get(k)]
        if not sets:
            raise card.error("needs NSET= (node-based rigid body; element-based rigid bodies are not supported)")
        nodes = [n for s in sets for n in self.node_refs(card, None, s)]
        ref, rot = (self._node_param(card, key) for key in ("REF NODE", "ROT NODE"))
        for node in (ref, rot):
            if node is not None and node not in self.nodes:
                raise card.error(f"node {node} is not defined")
        self.rigid.append((list(dict.fromkeys(nodes)), ref, rot, card))

    def _node_param(self, card: _Card, key: str) -> int | None:
        """The node a keyword parameter names: an id, ``I.5``, or a node set of one node."""
        text = card.params.get(key)
        if not text:
            return None
        node, _ = self._global(card, text, "node")
        if node is not None:
            return node
        members = self.node_refs(card, None, text)
        if len(members) != 1:
            raise card.error(f"{key}={text}: node set of {len(members)} nodes; it must name one node")
        return members[0]

    def card_EQUATION(self, card: _Card) -> None:
        card.check_params(set())
        count, terms, first = None, [], None
        for line in card.data:
            if count is None:
                if len(line.fields) != 1:
                    raise card.error("expects the number of terms alone on the line before the terms", line)
                count, first = _int(card, line, line.fields[0], "the number of terms"), line
                if count < 1:
                    raise card.error("an equation needs at least one term", line)
                continue
            if len(line.fields) % 3 or len(line.fields) > 12:
                raise card.error("expects up to four terms 'node, dof, coefficient' per line", line)
            for k in range(0, len(line.fields), 3):
                node = self.node_refs(card, line, line.fields[k])
                if len(node) != 1:
                    raise card.error(f"node set {line.fields[k]} in an equation must hold one node", line)
                terms.append((node[0], _int(card, line, line.fields[k + 1], "a dof"),
                              _float(card, line, line.fields[k + 2], "a coefficient")))
            if len(terms) > count:
                raise card.error(f"{len(terms)} terms given, {count} announced", line)
            if len(terms) == count:
                self.equations.append((terms, card, first))
                count, terms = None, []
        if count is not None:
            raise card.error(f"an equation announced {count} terms and got {len(terms)}", first)

    def card_EMBEDDED_ELEMENT(self, card: _Card) -> None:
        card.check_params({"HOST ELSET", "EXTERIOR TOLERANCE", "ABSOLUTE EXTERIOR TOLERANCE"}, {"HOST ELSET"})
        if not card.data:
            raise card.error("needs data lines naming the embedded elements or element sets")
        embedded = [e for line in card.data for f in line.fields if f for e in self.element_refs(card, line, f)]
        self.element_refs(card, None, card.params["HOST ELSET"])
        self.embedded.append((self._global(card, card.params["HOST ELSET"], "element")[1] or card.params["HOST ELSET"],
                              embedded, card))

    def card_DLOAD(self, card: _Card) -> None:
        card.check_params({"AMPLITUDE", "OP"})
        if (card.name("OP") or "MOD") != "MOD":
            raise card.error("only OP=MOD is supported")
        amp = card.name("AMPLITUDE")
        for line in card.data:
            if len(line.fields) < 3:
                raise card.error("expects 'element or element set, label, magnitude[, ...]'", line)
            label = line.fields[1].upper()
            elements = self.element_refs(card, line, line.fields[0])
            magnitude = _float(card, line, line.fields[2], "the magnitude")
            if re.fullmatch(r"P[1-6]", label):
                if len(line.fields) != 3:
                    raise card.error(f"{label} takes one magnitude", line)
                for e in elements:
                    self.face_loads.append((e, int(label[1]) - 1, magnitude, amp, card, line))
            elif label == "GRAV":
                if len(line.fields) != 6:
                    raise card.error("GRAV expects 'element set, GRAV, g, dx, dy, dz'", line)
                d = tuple(_float(card, line, f or "0", "a direction component") for f in line.fields[3:])
                self.gravity.append((elements, magnitude, d, amp, card, line))
            else:
                shown = _label(card, line, label)
                raise card.error(f"load label {shown} is not supported (supported: P1..P6 on bricks, GRAV)", line)

    def card_DSLOAD(self, card: _Card) -> None:
        card.check_params({"AMPLITUDE", "OP"})
        if (card.name("OP") or "MOD") != "MOD":
            raise card.error("only OP=MOD is supported")
        for line in card.data:
            if len(line.fields) != 3 or line.fields[1].upper() != "P":
                raise card.error("expects 'surface, P, magnitude' (only the pressure label P is supported)", line)
            name = self._global(card, line.fields[0], "element")[1] or line.fields[0].upper()
            if name not in self.surfaces:
                known = ", ".join(sorted(self.surfaces)) or "none"
                raise card.error(f"surface {_label(card, line, name)} is not defined (known: {known})",
                                 line)
            magnitude = _float(card, line, line.fields[2], "the magnitude")
            for e, face, _, _ in self.surfaces[name]:
                self.face_loads.append((e, face, magnitude, card.name("AMPLITUDE"), card, line))

    def card_AMPLITUDE(self, card: _Card) -> None:
        card.check_params({"NAME", "TIME", "DEFINITION", "VALUE", "SMOOTH"}, {"NAME"})
        self.amplitudes[card.name("NAME")] = card

    # -- model ---------------------------------------------------------------------------------------
    def build(self, path: Path) -> tuple[Model, dict[str, float], InpIds]:
        bricks = [e for e, (kind, *_) in self.elements.items() if kind in _BRICKS]
        if not bricks:
            raise InpError(f"{path}: the deck defines no C3D20 bricks; a torchfra model needs a solid body")
        for e, (kind, nodes, card, line) in self.elements.items():
            for n in nodes:
                if n not in self.nodes:
                    raise card.error(f"element {e} refers to node {n}, which is not defined", line)
        # rigid-body reference and rotation nodes and stray nodes are not model nodes
        kept = set(n for _, nodes, _, _ in self.elements.values() for n in nodes)
        kept.update(n for nodes, _, _, _ in self.rigid for n in nodes)
        node_ids = [n for n in self.nodes if n in kept]
        if sorted(node_ids) == list(range(1, len(node_ids) + 1)):
            node_ids = list(range(1, len(node_ids) + 1))
        self.index = {n: i for i, n in enumerate(node_ids)}
        if sorted(bricks) == list(range(1, len(bricks) + 1)):
            bricks = list(range(1, len(bricks) + 1))
        brick_index = {e: i for i, e in enumerate(bricks)}
        X = np.array([self.nodes[n] for n in node_ids]).reshape(-1, 3)
        conn = np.array([[self.index[n] for n in self.elements[e][1]] for e in bricks], dtype=np.int64)
        n_mesh = int(conn.max()) + 1

        node_sets = {
            name: np.array([self.index[n] for n in members])
            for name, members in self.nsets.items()
            if members and all(n in self.index and self.index[n] < n_mesh for n in members)
        }
        face_sets = {}
        for name, faces in self.surfaces.items():
            rows = []
            for e, face, card, line in faces:
                if e not in brick_index:
                    raise card.error(f"surface {name}: element {e} is not a brick", line)
                rows.append((brick_index[e], face))
            face_sets[name] = np.array(rows, dtype=np.int64).reshape(-1, 2)
        pressures = self._pressure_groups(brick_index, face_sets)
        try:
            mesh = Mesh(X[:n_mesh], conn, node_sets, face_sets)
        except MeshError as err:
            message = re.sub(r"element (\d+)", lambda m: f"{m.group(0)} (Abaqus id {bricks[int(m.group(1))]})",
                             str(err), count=1)
            raise InpError(f"{path}: {message}") from err
        model = Model(mesh, dtype=self.dtype)
        model.add_nodes(X[n_mesh:])
        ids = InpIds(np.array(node_ids, dtype=np.int64), np.array(bricks, dtype=np.int64))

        params: dict[str, float] = {}
        owners: dict[str, str] = {}

        def set_param(name: str, value: float, owner: str, card: _Card) -> None:
            if name in params and params[name] != value:
                raise card.error(
                    f"parameter {name} = {value!r} here but {params[name]!r} in {owners[name]}; the torchfra materials "
                    "use fixed parameter names (C10, C01, D1), so every body of one model shares their values"
                )
            params[name], owners[name] = value, owner

        embedded = self._ties(model, ids)
        truss_moduli = {
            mat: self.materials[mat].elastic[0]
            for elset, mat, _, card in self.sections
            if mat in self.materials and self.materials[mat].elastic is not None
            and any(self.elements[e][0] in _TRUSSES for e in self.element_refs(card, None, elset))
        }
        section_of: dict[int, _Card] = {}
        for elset, mat_name, area, card in self.sections:
            elements = self.element_refs(card, None, elset)
            if mat_name not in self.materials:
                known = ", ".join(sorted(self.materials)) or "none"
                raise card.error(f"material {mat_name} is not defined (known: {known})")
            material = self.materials[mat_name]
            for e in elements:
                if e in section_of:
                    raise card.error(f"element {e} already has the section on line {section_of[e].number}")
                section_of[e] = card
            groups: dict[str, list[int]] = {}
            for e in elements:
                groups.setdefault(self.elements[e][0], []).append(e)
            for kind, members in groups.items():
                if kind in _BRICKS:
                    if material.hyperelastic is None:
                        what = "*ELASTIC (torchfra has no linear elastic solid)" if material.elastic else "none"
                        raise card.error(f"material {mat_name} of {kind} bricks needs *HYPERELASTIC, has {what}")
                    cls, values, hcard = material.hyperelastic
                    for k, v in values.items():
                        set_param(k, v, f"material {mat_name}", hcard)
                    formulation, integration = _BRICKS[kind]
                    model.add(Hex20Solid(mesh, cls(), formulation, elements=np.array([brick_index[e] for e in members]),
                                         integration=integration, dtype=self.dtype))
                else:
                    if material.elastic is None or material.hyperelastic is not None:
                        raise card.error(f"material {mat_name} of {kind} trusses needs *ELASTIC (and no *HYPERELASTIC)")
                    if area is None or not area > 0:
                        raise card.error(f"a truss section needs a positive cross-section area (data line), got {area}")
                    name = ("E_fiber" if len(set(truss_moduli.values())) == 1
                            else "E_fiber_" + re.sub(r"[^A-Za-z0-9_]", "_", mat_name))
                    params[name] = truss_moduli[mat_name]
                    model.add(self._truss(model, kind, members, area, name, embedded, ids, card))
        for e, (kind, _, card, line) in self.elements.items():
            if e not in section_of:
                raise card.error(f"{kind} element {e} has no *SOLID SECTION", line)
        self._add_loads(model, mesh, brick_index, pressures, params)
        missing = [k for k in model.param_names() if k not in params]
        if missing:  # every term's parameter is set above; a gap here is a reader bug, never silent
            raise InpError(f"{path}: no value read for parameters {missing}")
        return model, {k: params[k] for k in model.param_names()}, ids

    def _model_node(self, node: int, card: _Card, line: _Line | None) -> int:
        if node not in self.index:
            raise card.error(f"node {node} belongs to no element (rigid-body reference nodes and stray nodes are "
                             "not model nodes)", line)
        return self.index[node]

    def _ties(self, model: Model, ids: InpIds) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Boundary conditions, rigid bodies and embedded nodes onto ``model``; returns the embedded
        ties ``{node: (hosts, weights)}`` (model indices)."""
        # boundary conditions: last card wins per dof; rigid reference / rotation nodes apart
        refs = {ref: (k, 0) for k, (_, ref, _, _) in enumerate(self.rigid)}
        refs.update({rot: (k, 3) for k, (_, _, rot, _) in enumerate(self.rigid) if rot is not None})
        dofs: dict[int, tuple[float, _Card, _Line]] = {}
        body_dofs: dict[int, dict[int, float]] = {}
        for node, dof, value, amp, card, line in self.boundaries:
            value = value * self.amplitude_at_one(amp, card, line) if amp else value
            if node in refs and node not in self.index:
                body, offset = refs[node]
                if offset == 3 and dof > 3:
                    raise card.error(f"dof {dof} of rotation node {node}: a rotation node has dofs 1-3", line)
                body_dofs.setdefault(body, {})[dof + offset] = value
                continue
            index = self._model_node(node, card, line)
            if dof > 3:
                if value != 0.0:
                    raise card.error(f"rotation dof {dof} of node {node} set to {value}: solid and truss nodes have "
                                     "no rotations", line)
                continue
            dofs[3 * index + dof - 1] = (value, card, line)
        clamped_bodies = set()
        for body, fixed in body_dofs.items():
            card = self.rigid[body][3]
            if sorted(fixed) != [1, 2, 3, 4, 5, 6] or any(v != 0.0 for v in fixed.values()):
                raise card.error(
                    f"the reference node of this rigid body is constrained in dofs {sorted(fixed)} (values "
                    f"{sorted(set(fixed.values()))}); only a reference node fixed in all six dofs (a clamped body) is "
                    "supported"
                )
            clamped_bodies.add(body)
        for c in range(3):
            clamp = [d // 3 for d, (v, _, _) in dofs.items() if d % 3 == c and v == 0.0]
            if clamp:
                model.clamp(np.array(clamp), [c])
        for d, (v, _, _) in sorted(dofs.items()):
            if v != 0.0:
                model.prescribe(np.array([d // 3]), d % 3, v)
        for k, (nodes, _, _, card) in enumerate(self.rigid):
            index = np.array([self._model_node(n, card, None) for n in nodes])
            if k in clamped_bodies:
                model.clamp(index)
            else:
                model.rigid(index)

        # embedded nodes: *EQUATION ties (three components with the same hosts and weights) ...
        ties: dict[int, dict[int, tuple[tuple[int, ...], np.ndarray, _Card, _Line]]] = {}
        for terms, card, line in self.equations:
            (node, dof, a), rest = terms[0], terms[1:]
            if not 1 <= dof <= 3 or a == 0.0 or any(d != dof for _, d, _ in rest):
                raise card.error(
                    "only ties 'A u_node - sum_h A_h u_host = 0' of one displacement component (dof 1, 2 or 3, A != 0) "
                    "are supported", line
                )
            hosts = tuple(self._model_node(n, card, line) for n, _, _ in rest)
            weights = np.array([-w / a for _, _, w in rest])
            comps = ties.setdefault(self._model_node(node, card, line), {})
            if dof in comps:
                raise card.error(f"dof {dof} of node {node} is the dependent dof of two equations", line)
            comps[dof] = (hosts, weights, card, line)
        embedded: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for node, comps in ties.items():
            first = next(iter(comps.values()))
            _, _, card, line = first
            if sorted(comps) != [1, 2, 3] or any(
                h != first[0] or not np.allclose(w, first[1], rtol=1e-14, atol=0.0) for h, w, _, _ in comps.values()
            ):
                raise card.error(
                    f"node {ids.nodes[node]} is tied in dofs {sorted(comps)}; torchfra's embedded node ties all three "
                    "displacement components to the same hosts with the same weights", line
                )
            embedded[node] = (np.array(first[0], dtype=np.int64), first[1])
        # ... and *EMBEDDED ELEMENT (nodes located in the host bricks)
        brick_nodes = set(model.mesh.elements.ravel().tolist())
        for host_set, elements, card in self.embedded:
            hosts = self.element_refs(card, None, host_set)
            if any(self.elements[e][0] not in _BRICKS for e in hosts) or any(
                self.elements[e][0] in _BRICKS for e in elements
            ):
                raise card.error("host elements must be C3D20 bricks and embedded elements trusses")
            nodes = [self.index[n] for e in elements for n in self.elements[e][1]]
            nodes = [n for n in dict.fromkeys(nodes) if n not in brick_nodes and n not in embedded]
            if not nodes:
                continue
            host_conn = np.array([[self.index[n] for n in self.elements[e][1]] for e in hosts], dtype=np.int64)
            X = model.X
            if card.params.get("ABSOLUTE EXTERIOR TOLERANCE"):
                tol = _float(card, None, card.params["ABSOLUTE EXTERIOR TOLERANCE"], "ABSOLUTE EXTERIOR TOLERANCE")
            else:
                rel = card.params.get("EXTERIOR TOLERANCE")
                rel = 0.05 if not rel else _float(card, None, rel, "EXTERIOR TOLERANCE")
                extent = X[host_conn].max(1) - X[host_conn].min(1)
                tol = rel * float(np.cbrt(np.prod(extent, axis=1)).mean())
            try:
                host, xi = locate_points(Mesh(X, host_conn, check=False), X[nodes], tol=max(tol, 1e-9))
            except ValueError as err:
                raise card.error(str(err)) from err
            N, _ = hex20_shape(xi)
            for k, node in enumerate(nodes):
                embedded[node] = (host_conn[host[k]], N[k])
        for node, (hosts, weights) in embedded.items():
            model.embed(node, hosts, weights)
        return embedded

    def _truss(self, model: Model, kind: str, members: list[int], area: float, modulus: str, embedded,
               ids: InpIds, card: _Card) -> Truss:
        """A truss term of the elements ``members``; a T3D2 element gets a middle node tied to its ends
        (through their own embedding ties where they are embedded)."""
        rows = np.array([[self.index[n] for n in self.elements[e][1]] for e in members], dtype=np.int64)
        if kind == "T3D3":
            rows = rows[:, [0, 2, 1]]  # Abaqus end, middle, end -> torchfra end, end, middle
        else:
            rigid = {n for nodes, _, _, _ in self.rigid for n in nodes}
            for e, (a, b) in zip(members, rows):
                if ids.nodes[a] in rigid or ids.nodes[b] in rigid:
                    raise card.error(f"T3D2 element {e} ends on a rigid body: its added middle node cannot be tied")
            first = model.n_nodes
            truss = two_node_truss(model, rows, area=area, modulus=modulus, dtype=self.dtype)
            ids.nodes = np.concatenate([ids.nodes, np.full(model.n_nodes - first, -1, dtype=np.int64)])
            return truss
        return Truss(model.X, rows, area=area, modulus=modulus, dtype=self.dtype)

    def _pressure_groups(self, brick_index, face_sets) -> list[tuple[str, str, float]]:
        """Face loads grouped by magnitude at load factor 1: ``(face set, parameter, value)``; adds the
        face sets that no surface already names."""
        loads: dict[tuple[int, int], tuple[float, _Card, _Line]] = {}
        for e, face, magnitude, amp, card, line in self.face_loads:
            if e not in brick_index:
                raise card.error(f"pressure on element {e}, which is not a brick", line)
            key = (brick_index[e], face)
            if key in loads:
                other = loads[key][2]
                raise card.error(
                    f"face S{face + 1} of element {e} is loaded again (first on line {other.number} of {other.file}); "
                    "Abaqus replaces a repeated load and CalculiX adds it, so give one line per face", line
                )
            scale = self.amplitude_at_one(amp, card, line) if amp else 1.0
            loads[key] = (magnitude * scale, card, line)
        groups: dict[float, list[tuple[int, int]]] = {}
        for key, (value, _, _) in loads.items():
            groups.setdefault(value, []).append(key)
        out = []
        named = {frozenset(map(tuple, rows.tolist())): name for name, rows in face_sets.items()}
        for k, (value, faces) in enumerate(groups.items()):
            surface = named.get(frozenset(faces))
            suffix = re.sub(r"[^A-Za-z0-9_]", "_", surface) if surface else str(k + 1)
            param = "P" if len(groups) == 1 else "P_" + suffix
            if surface is None:
                surface = "DLOAD_" + param
                face_sets[surface] = np.array(faces, dtype=np.int64)
            out.append((surface, param, value))
        return out

    def _add_loads(self, model: Model, mesh: Mesh, brick_index, pressures, params) -> None:
        for face_set, param, value in pressures:
            params[param] = value
            try:
                check_closed(mesh, face_set)
                term = CavityPressure
            except ValueError:
                term = FollowerPressure
            model.add(term(mesh, face_set, pressure=param, quadrature=self.quadrature, dtype=self.dtype))
        section = {}
        for elset, mat, _, card in self.sections:
            for e in self.element_refs(card, None, elset):
                section[e] = mat
        groups: dict[tuple, list[int]] = {}
        cards: dict[tuple, tuple[_Card, _Line]] = {}
        for elements, g, d, amp, card, line in self.gravity:
            scale = self.amplitude_at_one(amp, card, line) if amp else 1.0
            for e in elements:
                mat = section.get(e)
                if e not in brick_index or self.materials[mat].density is None:
                    raise card.error(f"GRAV on element {e}: it must be a brick whose material has a *DENSITY", line)
                key = (mat, g * scale, d)
                groups.setdefault(key, []).append(brick_index[e])
                cards.setdefault(key, (card, line))
        densities = {mat: self.materials[mat].density[0] for mat, _, _ in groups}
        for key, elements in groups.items():
            mat, g, d = key
            name = "density" if len(set(densities.values())) == 1 else "density_" + re.sub(r"[^A-Za-z0-9_]", "_", mat)
            params[name] = densities[mat]
            if len(set(elements)) != len(elements):
                card, line = cards[key]
                raise card.error("an element carries the same GRAV load twice", line)
            model.add(Gravity(mesh, density=name, direction=d, g=g, elements=np.array(elements), dtype=self.dtype))


def read_inp(path, *, dtype=torch.float64, pressure_quadrature: int = 3, with_ids: bool = False,
             include_dirs=()):
    """Read an Abaqus/CalculiX input deck into a torchfra model (see the module docstring for the cards).

    path: the ``.inp`` deck (lengths in mm, moduli and pressures in MPa, densities in t/mm^3,
        accelerations in mm/s^2).
    dtype: floating type of the model.
    pressure_quadrature: Gauss points per direction of the pressure terms' face rule (3: exact for a
        Quad8 face; 2: CalculiX's C3D20R face rule).
    with_ids: also return :class:`InpIds`, the Abaqus id of every model node and mesh element.
    include_dirs: folders besides the deck's own (and those below them) that ``*INCLUDE, INPUT=`` may
        read from; an included file anywhere else (an absolute path, ``..`` out of the deck's folder,
        a link pointing out of it) is refused naming the ``*INCLUDE`` line.

    Returns ``(model, params)`` (or ``(model, params, ids)``): an unfinalized :class:`Model` and
    ``{parameter name: float}`` for every parameter of its terms, the deck's values at load factor 1
    (pass ``{k: torch.tensor([v]) for k, v in params.items()}`` to ``fem.solve``).

    Raises :class:`InpError` (a ValueError) naming the file, line and keyword of anything the reader
    does not support or cannot resolve.
    """
    path = Path(path)
    reader = _Reader(dtype, pressure_quadrature)
    roots = [path.parent.resolve()] + [Path(d).resolve() for d in include_dirs]
    read_cards(reader, _cards(path, roots), _float, InpError, path)
    model, params, ids = reader.build(path)
    return (model, params, ids) if with_ids else (model, params)
