"""Abaqus/CalculiX input decks of one member of a :class:`torchfra.fem.Model`, and CalculiX results.

``write_inp`` writes the model as it stands (finalized or not) for one parameter set. The load
factor ``lambda`` of torchfra is the step time ``t`` in [0, 1] of one ``*STATIC`` step: loads
and prescribed displacements ramp linearly with ``t``.

What each torchfra object becomes (ids are 1-based: node ``i`` -> ``i + 1``, mesh element
``e`` -> ``e + 1``, truss elements numbered after the mesh elements):

- ``Hex20Solid`` with ``NeoHookean`` -> ``*ELEMENT, TYPE=C3D20R`` or ``C3D20`` (both use Abaqus C3D20 node
  order), ``*SOLID SECTION`` and ``*HYPERELASTIC, NEO HOOKE`` with ``C10, D1`` (the same energy
  ``C10 (I1bar - 3) + (J - 1)^2 / D1``); with ``MooneyRivlin`` ``*HYPERELASTIC, MOONEY-RIVLIN``
  with ``C10, C01, D1`` (energy ``C10 (I1bar - 3) + C01 (I2bar - 3) + (J - 1)^2 / D1``). CalculiX has no hybrid brick: a hybrid body is written
  as ``element_type`` (by default C3D20R or C3D20, following the body's integration, with a
  warning; give ``"C3D20RH"``/``"C3D20H"`` for Abaqus), so only the displacement formulation
  compares one to one.
- ``Truss`` -> ``T3D3`` (Abaqus order end, middle, end) or two ``T3D2`` per Line3
  (``truss_element``), ``*SOLID SECTION`` with the area, ``*ELASTIC`` with ``E`` and
  ``truss_poisson``. Best effort: CalculiX 2.20 expands trusses into volume elements tied by
  MPCs. With T3D3 nodes that are dependent in an ``*EQUATION`` (embedded fibres) it stops
  ("no mean rotation MPC"). A truss node that is also clamped leaves a residual near 1e-4 of
  the average force, which never meets tight tolerances. Where it runs, trusses agree only to
  the truss model (torchfra: Green strain; CalculiX: expanded beam). ``truss_element="SPRINGA"``
  writes each Line3 as two axial springs of stiffness E A / L on its chords instead: ideal two-node
  trusses, not expanded (25x faster on the actuator, and within 1.2e-5 of torchfra's chords).
- ``FollowerPressure`` / ``CavityPressure`` -> ``*SURFACE, TYPE=ELEMENT`` (S1..S6 = face + 1)
  and ``*DLOAD`` lines ``element, P<face + 1>, P``. Abaqus ``P`` pushes on the face like
  torchfra's traction ``-P n`` and follows the face under NLGEOM. Pressures of several terms on
  one face are summed into one line (CalculiX adds repeated face loads within a step, Abaqus
  replaces them). CalculiX integrates C3D20R face loads with 2x2 Gauss points; torchfra uses
  3x3, which is exact for a Quad8 face. On a coarse, strongly bent mesh the two differ by about
  1e-5 of the displacement. ``SensorCavityPressure`` is written at its true pressure
  ``gain P + offset``.
- ``Gravity`` -> ``*DENSITY`` and ``*DLOAD ..., GRAV``; a weight that acts before the load path
  (``Gravity(preload=True)``) gets its own first ``*STEP`` (the reference state), and the load
  path's step holds it (a ``*DLOAD`` persists into the next step); ``ElasticSupport`` -> ``SPRING1`` and
  ``SPRING2`` elements that store its discrete energy exactly (see ``abaqus_candidates``).
- clamped dofs -> ``*BOUNDARY node, dof, dof`` (dof 1, 2, 3 = x, y, z); prescribed dofs ->
  ``*BOUNDARY node, dof, dof, value`` with the value at load factor 1. A clamp wins, as in
  ``Model.finalize``.
- embedded nodes -> one ``*EQUATION`` ``u_node - sum_h w_h u_h = 0`` per component, with the
  embedded node dependent.
- rigid node sets -> ``*RIGID BODY, NSET=..., REF NODE=..., ROT NODE=...`` with two extra nodes
  after the model's: the reference node at the set's centroid (torchfra's reference point) and
  the rotation node. CalculiX enforces the body with nonlinear MPCs and its own rotation
  unknowns. The constrained motion is the same, but the Newton iterations differ.

The step is ``*STATIC, DIRECT`` with ``increments`` equal increments (or, with ``load_factors``, a
load trace through an ``*AMPLITUDE``, ``increments_per_entry`` increments per entry). There is no automatic
cutback, so a failing increment stops the run with an error instead of silently changing the path.
``*CONTROLS, PARAMETERS=FIELD`` tightens the residual and correction tolerances; CalculiX's
defaults of 5e-3 and 1e-2 are far too loose for a cross-check. ``*NODE PRINT`` and ``*NODE FILE``
write ``U`` on the model's nodes (set ``NMODEL``).

Follower pressure needs ``hold_increments`` more increments at the full load. CalculiX evaluates
the pressure on the previous iteration's geometry, and its tangent converges only linearly on a
follower load. Its residual check therefore passes while the solution still moves by about 1e-4
of the displacement, measured on a bent block. Increments at constant load let it settle.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np

from torchfra.fem.gravity import Gravity
from torchfra.fem.materials import MooneyRivlin, NeoHookean
from torchfra.fem.model import Model
from torchfra.fem.pressure import CavityPressure, FollowerPressure
from torchfra.fem.sensor import SensorCavityPressure
from torchfra.fem.solid import Hex20Solid
from torchfra.fem.springs import ElasticSupport
from torchfra.fem.truss import Truss
from torchfra.io.abaqus.candidates import gravity_of_solids, support_springs

_PRESSURES = (FollowerPressure, CavityPressure)


class CalculixError(RuntimeError):
    """CalculiX is missing, failed, or its output is incomplete; the message carries its output tail."""


def _num(x: float) -> str:
    """A float in at most 20 characters (CalculiX reads numeric fields of up to 20 characters)."""
    s = repr(float(x))
    return s if len(s) <= 20 else f"{float(x):.13e}"


def _set_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", name).upper()


def _id_lines(ids, per_line: int = 10) -> list[str]:
    ids = [str(int(i)) for i in ids]
    return [", ".join(ids[k : k + per_line]) + "," for k in range(0, len(ids), per_line)]


def _param_values(model: Model, params: dict) -> dict[str, float]:
    """One float per parameter the model's terms use; raise naming what is missing or not scalar."""
    if model.morph_names:
        raise ValueError(f"write_inp exports the mesh's nodes, but the model morphs them ({model.morph_names}); "
                         "build the model without the morph on a re-meshed geometry to export it")
    values = {}
    for name in model.param_names():
        if name not in params:
            raise KeyError(f"write_inp needs parameter '{name}' (used by the model's terms); got {sorted(params)}")
        v = np.asarray(params[name], dtype=np.float64)
        if v.size != 1:
            raise ValueError(
                f"write_inp exports one member: parameter '{name}' must be a single number, got shape {v.shape}; "
                "pass e.g. {k: float(v[m]) for k, v in params.items()} for member m"
            )
        value = float(v.reshape(()))
        if not np.isfinite(value):
            raise ValueError(f"parameter '{name}' is {value!r}; it must be finite")
        values[name] = value
    return values


def write_inp(
    path,
    model: Model,
    params: dict,
    *,
    element_type: str | None = None,
    increments: int = 10,
    nlgeom: bool = True,
    title: str = "torchfra model",
    residual_tolerance: float = 1e-10,
    hold_increments: int = 10,
    truss_element: str = "T3D3",
    truss_poisson: float = 0.36,
    load_factors=None,
    increments_per_entry: int = 1,
) -> Path:
    """Write ``model`` for one parameter set as an Abaqus/CalculiX ``.inp`` deck; returns the path.

    path: output file (``.inp``; the CalculiX job name is its stem).
    params: parameter name -> one number (MPa, 1/MPa, ...), the values of a single member; pressures
        and prescribed displacements are those reached at load factor 1.
    element_type: element name of the Hex20 bodies; None (default): ``C3D20R`` for a body with
        reduced 2x2x2 integration, ``C3D20`` for full 3x3x3 (CalculiX has no hybrid brick); give
        ``"C3D20RH"``/``"C3D20H"`` for an Abaqus hybrid analogue. A name whose integration differs
        from the body's is refused.
    increments: number of equal increments from load factor 0 to 1 (``*STATIC, DIRECT``).
    nlgeom: geometric nonlinearity (finite strain, follower pressure).
    title: ``*HEADING`` text.
    residual_tolerance: ``*CONTROLS, PARAMETERS=FIELD`` bound on the largest residual force relative
        to the average force and on the largest correction relative to the largest incremental
        displacement.
    hold_increments: increments of the same size at the full load after the ramp (only when
        pressure loads are present; see the module docstring). The step then ends at time
        ``1 + hold_increments / increments``.
    truss_element: ``"T3D3"`` (one per torchfra truss), ``"T3D2"`` (two per truss, end-middle
        and middle-end) or ``"SPRINGA"`` (the same two as axial springs of stiffness E A / L: ideal
        two-node trusses, which CalculiX does not expand into volume elements).
    truss_poisson: Poisson's ratio written for truss materials (a truss's axial force ignores it).
    load_factors: a load trace instead of the ramp: one increment per entry, increment k ending at
        step time (k + 1) / len(load_factors) with the loads at ``load_factors[k]`` of their value
        (an ``*AMPLITUDE`` through them from 0 at time 0; loading and unloading alike, no hold), so
        CalculiX prints the displacements at every entry. Overrides ``increments``.
    increments_per_entry: with ``load_factors``, equal increments from one entry to the next (the
        load follows the trace linearly in between); entry k ends increment (k + 1) x this.

    Raises NotImplementedError for terms or materials with no Abaqus counterpart here, KeyError /
    ValueError for missing or non-scalar parameters and bad options.
    """
    if truss_element not in ("T3D3", "T3D2", "SPRINGA"):
        raise ValueError(f"truss_element must be 'T3D3', 'T3D2' or 'SPRINGA', got {truss_element!r}")
    if int(increments) < 1 or int(hold_increments) < 0:
        raise ValueError(f"need increments >= 1 and hold_increments >= 0, got {increments}, {hold_increments}")
    if not 0 < residual_tolerance < 1:
        raise ValueError(f"residual_tolerance must lie in (0, 1), got {residual_tolerance}")
    values = _param_values(model, params)
    mesh = model.mesh

    lines = [f"*HEADING\n{title}", "** written by torchfra.io.abaqus.write_inp; ids are 0-based index + 1",
             "*NODE, NSET=NMODEL"]
    lines += [f"{i + 1}, {_num(x)}, {_num(y)}, {_num(z)}" for i, (x, y, z) in enumerate(model.X)]
    properties, loads, gravity = _elements(model, values, element_type, truss_element, truss_poisson, lines)
    for name, nodes in mesh.node_sets.items():
        lines.append(f"*NSET, NSET=N_{_set_name(name)}")
        lines += _id_lines(np.asarray(nodes) + 1)
    for name in sorted({t.face_set for t in model.terms if isinstance(t, _PRESSURES)}):
        lines.append(f"*SURFACE, NAME=S_{_set_name(name)}, TYPE=ELEMENT")
        lines += [f"{e + 1}, S{f + 1}" for e, f in mesh.face_set(name)]
    lines += properties + _rigid_bodies(model) + _equations(model) + _clamps(model)

    trace = None if load_factors is None else np.asarray(load_factors, dtype=np.float64).reshape(-1)
    if trace is not None and (trace.size == 0 or not np.all(np.isfinite(trace)) or np.abs(trace).max() > 1 + 1e-12):
        raise ValueError("load_factors must be a non-empty sequence of finite load factors in [-1, 1]")
    if int(increments_per_entry) < 1:
        raise ValueError(f"increments_per_entry must be >= 1, got {increments_per_entry}")
    n_inc = int(increments) if trace is None else trace.size * int(increments_per_entry)
    dt = 1.0 / n_inc
    hold = int(hold_increments) if loads and trace is None else 0
    period = 1.0 + hold * dt
    amplitude = ""
    if hold:
        lines += ["*AMPLITUDE, NAME=RAMP_HOLD", f"0.0, 0.0, 1.0, 1.0, {_num(period)}, 1.0"]
        amplitude = ", AMPLITUDE=RAMP_HOLD"
    if trace is not None:
        points = [f"{_num(k / trace.size)}, {_num(v)}" for k, v in enumerate(np.concatenate([[0.0], trace]))]
        lines += ["*AMPLITUDE, NAME=TRACE"] + [", ".join(points[i:i + 4]) for i in range(0, len(points), 4)]
        amplitude = ", AMPLITUDE=TRACE"
    # Iteration limits raised so that no divergence or logarithmic-rate check cuts a DIRECT increment.
    tol = _num(residual_tolerance)
    controls = ["*CONTROLS, PARAMETERS=TIME INCREMENTATION", "20, 30, 40, 50, 40, 4, , 5",
                "*CONTROLS, PARAMETERS=FIELD", f"{tol}, {tol}, , , {tol}, 1e-5, {tol}, {_num(1e-3 * residual_tolerance)}"]
    preloads = {bool(getattr(t, "preload", False)) for t in model.terms if isinstance(t, Gravity)}
    if len(preloads) > 1:
        raise NotImplementedError("gravity terms that act before the load path and others that ramp with it: "
                                  "write them as separate models")
    settle = bool(gravity) and preloads == {True}
    if settle:  # the weight first, in its own step (the reference state); the next step holds it
        lines += ["** step 1: the body settles under its weight (the reference state of a DIC recording)",
                  f"*STEP{', NLGEOM' if nlgeom else ''}, INC={10 * int(increments) + 100}", "*STATIC, DIRECT",
                  f"{_num(1.0 / int(increments))}, 1.0"] + controls
        lines += ["*DLOAD"] + gravity + ["*NODE PRINT, NSET=NMODEL", "U", "*END STEP",
                                         "** step 2: the load path, the weight held"]
    lines += [f"*STEP{', NLGEOM' if nlgeom else ''}, INC={10 * (n_inc + hold) + 100}", "*STATIC, DIRECT",
              f"{_num(dt)}, {_num(period)}"] + controls
    clamped = set(model.clamped_dofs.tolist())
    presc = {d: v for d, v in model.prescribed_dofs.items() if d not in clamped}
    if presc:
        lines.append(f"*BOUNDARY{amplitude}")
        lines += [f"{d // 3 + 1}, {d % 3 + 1}, {d % 3 + 1}, {_num(v)}" for d, v in sorted(presc.items())]
    if loads:
        lines.append(f"*DLOAD{amplitude}")
        lines += [f"{e + 1}, P{f + 1}, {_num(p)}" for (e, f), p in sorted(loads.items())]
    if gravity and not settle:
        lines.append(f"*DLOAD{amplitude}")
        lines += gravity
    lines += ["*NODE PRINT, NSET=NMODEL", "U", "*NODE FILE", "U", "*END STEP"]

    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def _elements(model, values, element_type, truss_element, truss_poisson, lines):
    """Append ``*ELEMENT`` blocks to ``lines``; return (section + material lines, face loads,
    gravity ``*DLOAD`` lines)."""
    mesh = model.mesh
    properties, loads, owner, gravity_lines = [], {}, {}, []
    gravity = gravity_of_solids(model, values)
    next_element = mesh.n_elements + 1
    for k, term in enumerate(model.terms):
        if isinstance(term, Hex20Solid):
            if not isinstance(term.material, (NeoHookean, MooneyRivlin)):
                raise NotImplementedError(
                    f"term {k} ({type(term.material).__name__} material) has no Abaqus export yet; "
                    "write_inp maps NeoHookean and MooneyRivlin to *HYPERELASTIC"
                )
            for e in term.element_ids.tolist():
                if e in owner:
                    raise NotImplementedError(
                        f"element {e} belongs to solid terms {owner[e]} and {k}; an Abaqus element carries one "
                        "material, so superposed bodies cannot be exported"
                    )
                owner[e] = k
            reduced = term.integration == "reduced"
            name = element_type or ("C3D20R" if reduced else "C3D20")
            if ("R" in name.upper()[5:]) != reduced:
                raise ValueError(
                    f"term {k} integrates with {'2x2x2 (reduced)' if reduced else '3x3x3 (full)'} Gauss points but "
                    f"element_type={name} is the other rule: give {'C3D20R' if reduced else 'C3D20'}"
                    f"{'H' if name.upper().endswith('H') else ''}, or element_type=None to follow the body"
                )
            if term.formulation == "hybrid" and not name.upper().endswith("H"):
                warnings.warn(
                    f"term {k} is a hybrid (u-p) body but is written as {name}, a displacement-only "
                    "element: results agree only where the formulations do (compressible D1, fine meshes)",
                    stacklevel=3,
                )
            lines.append(f"*ELEMENT, TYPE={name}, ELSET=SOLID{k}")
            for e in term.element_ids.tolist():
                nodes = [str(n + 1) for n in mesh.elements[e].tolist()]
                lines += [f"{e + 1}, " + ", ".join(nodes[:15]) + ",", ", ".join(nodes[15:])]
            properties += [f"*SOLID SECTION, ELSET=SOLID{k}, MATERIAL=MAT{k}", f"*MATERIAL, NAME=MAT{k}"]
            if isinstance(term.material, MooneyRivlin):
                properties += ["*HYPERELASTIC, MOONEY-RIVLIN",
                               ", ".join(_num(values[p]) for p in ("C10", "C01", "D1"))]
            else:
                properties += ["*HYPERELASTIC, NEO HOOKE", f"{_num(values['C10'])}, {_num(values['D1'])}"]
            if k in gravity:
                rho, g, d = gravity[k]
                properties += ["*DENSITY", _num(rho)]
                gravity_lines.append(f"SOLID{k}, GRAV, {_num(g)}, " + ", ".join(_num(v) for v in d))
        elif isinstance(term, Truss) and truss_element == "SPRINGA":
            # each Line3 (a, b, m) as the axial springs a-m and m-b of stiffness E A / L (L: the chord's
            # reference length), one *SPRING per stiffness value
            conn = term.conn.numpy()
            chords = np.stack([conn[:, [0, 2]], conn[:, [2, 1]]], axis=1).reshape(-1, 2)
            stiffness = values[term.modulus] * term.area / np.linalg.norm(model.X[chords[:, 0]] - model.X[chords[:, 1]], axis=1)
            groups: dict[str, list] = {}
            for e, kk in enumerate(stiffness):
                groups.setdefault(_num(float(f"{kk:.12e}")), []).append(e)
            for g, (kk, members) in enumerate(sorted(groups.items())):
                lines.append(f"*ELEMENT, TYPE=SPRINGA, ELSET=TRUSS{k}_{g}")
                for e in members:
                    lines.append(f"{next_element}, {chords[e, 0] + 1}, {chords[e, 1] + 1}")
                    next_element += 1
                properties += [f"*SPRING, ELSET=TRUSS{k}_{g}", "", kk]
        elif isinstance(term, Truss):
            lines.append(f"*ELEMENT, TYPE={truss_element}, ELSET=TRUSS{k}")
            for a, b, m in (term.conn.numpy() + 1).tolist():
                if truss_element == "T3D3":
                    lines.append(f"{next_element}, {a}, {m}, {b}")
                else:
                    lines += [f"{next_element}, {a}, {m}", f"{next_element + 1}, {m}, {b}"]
                next_element += 1 if truss_element == "T3D3" else 2
            properties += [f"*SOLID SECTION, ELSET=TRUSS{k}, MATERIAL=MAT{k}", _num(term.area),
                           f"*MATERIAL, NAME=MAT{k}", "*ELASTIC",
                           f"{_num(values[term.modulus])}, {_num(truss_poisson)}"]
        elif isinstance(term, _PRESSURES):
            p = values[term.pressure]
            if isinstance(term, SensorCavityPressure):
                p = values[term.gain] * p + values[term.offset]
            for e, f in mesh.face_set(term.face_set).tolist():
                loads[(e, f)] = loads.get((e, f), 0.0) + p
        elif isinstance(term, ElasticSupport):
            grounded, pairs = support_springs(term, values)
            groups: dict[tuple, list] = {}
            for node, comp, stiffness in grounded:
                groups.setdefault(("SPRING1", f"{comp + 1}", _num(stiffness)), []).append(f"{node + 1}")
            for a, b, comp, stiffness in pairs:
                groups.setdefault(("SPRING2", f"{comp + 1}, {comp + 1}", _num(stiffness)), []).append(f"{a + 1}, {b + 1}")
            for g, ((kind, dofs, stiffness), members) in enumerate(sorted(groups.items())):
                lines.append(f"*ELEMENT, TYPE={kind}, ELSET=SUPPORT{k}_{g}")
                for nodes in members:
                    lines.append(f"{next_element}, {nodes}")
                    next_element += 1
                properties += [f"*SPRING, ELSET=SUPPORT{k}_{g}", dofs, stiffness]
        elif not isinstance(term, Gravity):
            raise NotImplementedError(
                f"term {k} ({type(term).__name__}) has no Abaqus export; write_inp knows Hex20Solid, Truss, "
                "FollowerPressure, CavityPressure, SensorCavityPressure, Gravity and ElasticSupport"
            )
    return properties, loads, gravity_lines


def _clamps(model: Model) -> list[str]:
    dofs = model.clamped_dofs
    if dofs.size == 0:
        return []
    lines = ["*BOUNDARY"]
    nodes, comps = dofs // 3, dofs % 3
    for node in np.unique(nodes).tolist():
        c = np.sort(comps[nodes == node]).tolist()
        lines += [f"{node + 1}, 1, 3"] if c == [0, 1, 2] else [f"{node + 1}, {ci + 1}, {ci + 1}" for ci in c]
    return lines


def _equations(model: Model) -> list[str]:
    lines = []
    for node, hosts, weights in model.embedded_nodes:
        keep = weights != 0.0
        pairs = list(zip((hosts[keep] + 1).tolist(), weights[keep].tolist()))
        for c in range(1, 4):
            terms = [(node + 1, c, 1.0)] + [(h, c, -w) for h, w in pairs]
            lines += ["*EQUATION", str(len(terms))]
            for i in range(0, len(terms), 4):  # at most four terms per line
                lines.append(", ".join(f"{n}, {d}, {_num(w)}" for n, d, w in terms[i : i + 4]))
    return lines


def _rigid_bodies(model: Model) -> list[str]:
    lines = []
    for k, nodes in enumerate(model.rigid_node_sets):
        ref, rot = model.n_nodes + 2 * k + 1, model.n_nodes + 2 * k + 2
        c = ", ".join(_num(v) for v in model.X[nodes].mean(axis=0))
        lines += ["*NODE", f"{ref}, {c}", f"{rot}, {c}", f"*NSET, NSET=RIGID{k}"]
        lines += _id_lines(np.asarray(nodes) + 1)
        lines.append(f"*RIGID BODY, NSET=RIGID{k}, REF NODE={ref}, ROT NODE={rot}")
    return lines


# -- CalculiX results ------------------------------------------------------------------------------

_HEADER = re.compile(r"^\s*displacements \(vx,vy,vz\) for set (\S+) and time\s+(\S+)")


def _fortran_float(text: str) -> float:
    """Parse a number that Fortran may print without its ``E`` (``1.234567-100``)."""
    try:
        return float(text)
    except ValueError:
        return float(re.sub(r"(?<=\d)([+-]\d+)$", r"E\1", text))


def dat_blocks(path) -> list[tuple[float, dict[int, np.ndarray]]]:
    """Every displacement block of a CalculiX ``.dat`` file: ``(total time, {node (0-based): u})``."""
    blocks: list[tuple[float, dict[int, np.ndarray]]] = []
    current = None
    for line in Path(path).read_text().splitlines():
        header = _HEADER.match(line)
        if header:
            current = {}
            blocks.append((_fortran_float(header.group(2)), current))
            continue
        parts = line.split()
        if not parts or current is None:
            continue
        if len(parts) == 4 and parts[0].isdigit():
            current[int(parts[0]) - 1] = np.array([_fortran_float(p) for p in parts[1:]])
        else:
            current = None  # another kind of output block begins
    return blocks


def read_dat_displacements(path) -> dict[int, np.ndarray]:
    """Nodal displacements (mm) of the last printed increment of a CalculiX ``.dat`` file.

    Returns ``{node index (0-based): (3,) array}`` for the nodes of the last ``*NODE PRINT`` block
    of ``U``. Raises ValueError if the file holds no displacement block.
    """
    blocks = dat_blocks(path)
    if not blocks:
        raise ValueError(
            f"{path} holds no 'displacements (vx,vy,vz)' block; did the deck ask for *NODE PRINT of U?"
        )
    return blocks[-1][1]


def run_calculix(inp_path, *, executable: str = "ccx", threads: int = 1, timeout: float | None = 600.0) -> np.ndarray:
    """Run CalculiX on a deck (``ccx -i <stem>`` in the deck's folder) and return its displacements.

    Returns (n, 3) displacements (mm) of the last printed increment, row = node index (0-based),
    n = the largest printed node id (for a ``write_inp`` deck the set ``NMODEL``: all model
    nodes); rows of nodes not printed are NaN. Runs with ``OMP_NUM_THREADS=threads``; an old
    ``<stem>.dat`` is deleted first so a stale result is never read.

    Raises CalculixError with the tail of CalculiX's output if ``executable`` is not on PATH,
    exits non-zero, prints ``*ERROR``, runs past ``timeout`` seconds, writes no displacements, or
    stops before time 1 (load factor 1).
    """
    inp_path = Path(inp_path).resolve()
    if not inp_path.is_file() or inp_path.suffix != ".inp":
        raise FileNotFoundError(f"{inp_path} is not an existing .inp deck")
    exe = shutil.which(executable)
    if exe is None:
        raise CalculixError(
            f"CalculiX executable '{executable}' not found on PATH; install it (Debian: apt-get install calculix-ccx)"
        )
    dat = inp_path.with_suffix(".dat")
    dat.unlink(missing_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS=str(int(threads)))
    try:
        proc = subprocess.run([exe, "-i", inp_path.stem], cwd=inp_path.parent, env=env, capture_output=True,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired as err:
        out = err.stdout.decode(errors="replace") if isinstance(err.stdout, bytes) else (err.stdout or "")
        raise CalculixError(f"CalculiX ran past {timeout} s on {inp_path}; output tail:\n{_tail(out)}") from err
    out = proc.stdout + proc.stderr
    if proc.returncode != 0 or "*ERROR" in out:
        raise CalculixError(f"CalculiX failed on {inp_path} (exit code {proc.returncode}); output tail:\n{_tail(out)}")
    blocks = dat_blocks(dat) if dat.is_file() else []
    if not blocks:
        raise CalculixError(f"CalculiX printed no displacements to {dat}; output tail:\n{_tail(out)}")
    time, u = blocks[-1]
    if time < 1.0 - 1e-6 or "Job finished" not in out:
        raise CalculixError(
            f"CalculiX stopped at time {time}, before load factor 1, on {inp_path}; output tail:\n{_tail(out)}"
        )
    result = np.full((max(u) + 1, 3), np.nan)
    for node, value in u.items():
        result[node] = value
    return result


def _tail(text: str, lines: int = 40) -> str:
    return "\n".join(text.splitlines()[-lines:])
