"""Abaqus/CalculiX input decks of one member of a :class:`torchfra.fem.Model`, and CalculiX results.

``write_inp`` writes the model as it stands (finalized or not) for one parameter set, with the
load factor ``lambda`` of torchfra mapped to the step time ``t`` in [0, 1] of one ``*STATIC``
step (default ramp amplitude: loads and prescribed displacements grow linearly with ``t``).

What each torchfra object becomes (ids are 1-based: node ``i`` -> ``i + 1``, mesh element
``e`` -> ``e + 1``, trusses numbered after the mesh elements):

- ``Hex20Solid`` with ``NeoHookean`` -> ``*ELEMENT, TYPE=C3D20R`` (node order unchanged: both are
  Abaqus C3D20 order), ``*SOLID SECTION`` and ``*HYPERELASTIC, NEO HOOKE`` with ``C10, D1``
  (same energy ``C10 (I1bar - 3) + (J - 1)^2 / D1``). CalculiX has no hybrid brick: a hybrid
  body is written with ``element_type`` (C3D20R by default, with a warning; give ``"C3D20RH"``
  for Abaqus), so only the displacement formulation is comparable one to one.
- ``Truss`` -> ``T3D3`` (Abaqus order end, middle, end), ``*SOLID SECTION`` with the area,
  ``*ELASTIC`` with ``E`` and ``truss_poisson``. Best effort: CalculiX expands T3D3 into
  volumetric beams and uses its own strain measure, so fibres agree only to their (tiny) strain.
- ``FollowerPressure`` and ``CavityPressure`` -> ``*SURFACE, TYPE=ELEMENT`` (S1..S6 = face + 1)
  and ``*DLOAD`` lines ``element, P<face + 1>, P``: Abaqus ``P`` pushes on the face like torchfra's
  traction ``-P n`` and follows the face under NLGEOM. Pressures of several terms on one face are
  summed (CalculiX adds repeated face loads within a step, Abaqus replaces them).
- clamped dofs -> ``*BOUNDARY node, dof, dof`` (dof 1, 2, 3 = x, y, z); prescribed dofs ->
  ``*BOUNDARY node, dof, dof, value`` with the value at load factor 1 (a clamp wins, as in
  ``Model.finalize``).
- embedded nodes -> ``*EQUATION`` ``u_node - sum_h w_h u_h = 0`` per component, node dependent.
- rigid node sets -> ``*RIGID BODY, NSET=..., REF NODE=..., ROT NODE=...`` with two extra nodes
  after the model's: the reference node at the set's centroid (torchfra's reference point) and
  the rotation node. Best effort: CalculiX enforces the body with nonlinear MPCs and its own
  rotation parameters; the constrained motion is the same rigid motion, the iterations differ.

The step is ``*STATIC, DIRECT`` with ``increments`` equal increments (no automatic cutback, so a
failing increment stops the run with an error instead of silently changing the path), tightened
``*CONTROLS, PARAMETERS=FIELD`` residual and correction tolerances (CalculiX defaults, 5e-3 and
1e-2, are far too loose for a cross-check), and ``*NODE PRINT`` / ``*NODE FILE`` of ``U`` on the
model's nodes (set ``NMODEL``).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np

from ..fem.materials import NeoHookean
from ..fem.model import Model
from ..fem.pressure import CavityPressure, FollowerPressure
from ..fem.solid import Hex20Solid
from ..fem.truss import Truss


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
        if not np.isfinite(v):
            raise ValueError(f"parameter '{name}' is {float(v)!r}; it must be finite")
        values[name] = float(v.reshape(()))
    return values


def write_inp(
    path,
    model: Model,
    params: dict,
    *,
    element_type: str = "C3D20R",
    increments: int = 20,
    nlgeom: bool = True,
    title: str = "torchfra model",
    residual_tolerance: float = 1e-10,
    truss_poisson: float = 0.36,
    settle_steps: int = 4,
) -> Path:
    """Write ``model`` for one parameter set as an Abaqus/CalculiX ``.inp`` deck; returns the path.

    path: output file (``.inp``; the CalculiX job name is its stem).
    params: parameter name -> one number (MPa, 1/MPa, ...), the values of a single member; load
        magnitudes (pressures) and prescribed displacements are those reached at load factor 1.
    element_type: element name of the Hex20 bodies (``"C3D20R"`` for CalculiX, ``"C3D20RH"``
        for an Abaqus hybrid analogue).
    increments: number of equal increments of the ``*STATIC, DIRECT`` step.
    nlgeom: geometric nonlinearity (finite strain, follower pressure).
    title: ``*HEADING`` text.
    residual_tolerance: ``*CONTROLS, PARAMETERS=FIELD`` ratio of the largest residual force to the
        average force and of the largest correction to the largest incremental displacement.
    truss_poisson: Poisson's ratio written for truss materials (a truss's axial force ignores it).

    Raises NotImplementedError for terms or materials with no Abaqus counterpart here, KeyError /
    ValueError for missing or non-scalar parameters.
    """
    if int(increments) < 1:
        raise ValueError(f"increments must be a positive integer, got {increments}")
    if not 0 < residual_tolerance < 1:
        raise ValueError(f"residual_tolerance must lie in (0, 1), got {residual_tolerance}")
    values = _param_values(model, params)
    mesh, X = model.mesh, model.X
    n_nodes = X.shape[0]

    model_data: list[str] = [f"*HEADING\n{title}", "** written by torchfra.io.abaqus.write_inp; ids are 0-based index + 1"]
    model_data.append("*NODE, NSET=NMODEL")
    model_data += [f"{i + 1}, {_num(x)}, {_num(y)}, {_num(z)}" for i, (x, y, z) in enumerate(X)]

    sections, materials, loads = [], [], {}
    solid_owner: dict[int, int] = {}
    next_element = mesh.n_elements + 1
    for k, term in enumerate(model.terms):
        if isinstance(term, Hex20Solid):
            if not isinstance(term.material, NeoHookean):
                raise NotImplementedError(
                    f"term {k} ({type(term.material).__name__} material) has no Abaqus export yet; "
                    "write_inp maps only NeoHookean to *HYPERELASTIC, NEO HOOKE"
                )
            for e in term.element_ids:
                if int(e) in solid_owner:
                    raise NotImplementedError(
                        f"element {int(e)} belongs to solid terms {solid_owner[int(e)]} and {k}; an Abaqus element "
                        "carries one material, so superposed bodies cannot be exported"
                    )
                solid_owner[int(e)] = k
            if term.formulation == "hybrid" and not element_type.upper().endswith("H"):
                warnings.warn(
                    f"term {k} is a hybrid (u-p) body but is written as {element_type}, a displacement-only "
                    "element: results agree only where the formulations do (near-compressible D1, fine meshes)",
                    stacklevel=2,
                )
            elset, mat = f"SOLID{k}", f"MAT{k}"
            model_data.append(f"*ELEMENT, TYPE={element_type}, ELSET={elset}")
            for e in term.element_ids:
                nodes = [str(int(n) + 1) for n in mesh.elements[e]]
                model_data.append(f"{int(e) + 1}, " + ", ".join(nodes[:15]) + ",")
                model_data.append(", ".join(nodes[15:]))
            sections.append(f"*SOLID SECTION, ELSET={elset}, MATERIAL={mat}")
            materials += [f"*MATERIAL, NAME={mat}", "*HYPERELASTIC, NEO HOOKE",
                          f"{_num(values['C10'])}, {_num(values['D1'])}"]
        elif isinstance(term, Truss):
            elset, mat = f"TRUSS{k}", f"MAT{k}"
            model_data.append(f"*ELEMENT, TYPE=T3D3, ELSET={elset}")
            for a, b, m in term.conn.numpy():
                model_data.append(f"{next_element}, {a + 1}, {m + 1}, {b + 1}")
                next_element += 1
            sections += [f"*SOLID SECTION, ELSET={elset}, MATERIAL={mat}", _num(term.area)]
            materials += [f"*MATERIAL, NAME={mat}", "*ELASTIC", f"{_num(values[term.modulus])}, {_num(truss_poisson)}"]
        elif isinstance(term, (FollowerPressure, CavityPressure)):
            for e, f in mesh.face_set(term.face_set):
                loads[(int(e), int(f))] = loads.get((int(e), int(f)), 0.0) + values[term.pressure]
        else:
            raise NotImplementedError(
                f"term {k} ({type(term).__name__}) has no Abaqus export; write_inp knows Hex20Solid, Truss, "
                "FollowerPressure and CavityPressure"
            )

    for name, nodes in mesh.node_sets.items():
        model_data.append(f"*NSET, NSET=N_{_set_name(name)}")
        model_data += _id_lines(np.asarray(nodes) + 1)
    pressure_sets = sorted({t.face_set for t in model.terms if isinstance(t, (FollowerPressure, CavityPressure))})
    for name in pressure_sets:
        model_data.append(f"*SURFACE, NAME=S_{_set_name(name)}, TYPE=ELEMENT")
        model_data += [f"{e + 1}, S{f + 1}" for e, f in mesh.face_set(name)]
    model_data += sections + materials
    model_data += _rigid_bodies(model, n_nodes)
    model_data += _equations(model)
    model_data += _clamps(model)

    step = [f"*STEP{', NLGEOM' if nlgeom else ''}, INC={10 * int(increments) + 100}", "*STATIC, DIRECT",
            f"{_num(1.0 / int(increments))}, 1.0"]
    # Iteration limits raised so that no check cuts a DIRECT increment that converges quadratically.
    controls = ["*CONTROLS, PARAMETERS=TIME INCREMENTATION", "20, 30, 40, 50, 40, 4, , 5",
                "*CONTROLS, PARAMETERS=FIELD",
                f"{_num(residual_tolerance)}, {_num(residual_tolerance)}, , , {_num(residual_tolerance)}, 1e-5, "
                f"{_num(residual_tolerance)}, {_num(1e-3 * residual_tolerance)}"]
    step += controls
    clamped = set(model.clamped_dofs.tolist())
    presc = {d: v for d, v in model.prescribed_dofs.items() if d not in clamped}
    if presc:
        step.append("*BOUNDARY")
        step += [f"{d // 3 + 1}, {d % 3 + 1}, {d % 3 + 1}, {_num(v)}" for d, v in sorted(presc.items())]
    if loads:
        step.append("*DLOAD")
        step += [f"{e + 1}, P{f + 1}, {_num(p)}" for (e, f), p in sorted(loads.items())]
    step += ["*NODE PRINT, NSET=NMODEL", "U", "*NODE FILE", "U", "*END STEP"]
    if loads:
        for _ in range(int(settle_steps)):
            step += [f"*STEP{', NLGEOM' if nlgeom else ''}, INC=100", "*STATIC, DIRECT", "1.0, 1.0"]
            step += controls + ["*NODE PRINT, NSET=NMODEL", "U", "*NODE FILE", "U", "*END STEP"]

    path = Path(path)
    path.write_text("\n".join(model_data + step) + "\n")
    return path


def _clamps(model: Model) -> list[str]:
    dofs = model.clamped_dofs
    if dofs.size == 0:
        return []
    lines = ["*BOUNDARY"]
    nodes, comps = dofs // 3, dofs % 3
    for node in np.unique(nodes):
        c = np.sort(comps[nodes == node])
        if c.tolist() == [0, 1, 2]:
            lines.append(f"{node + 1}, 1, 3")
        else:
            lines += [f"{node + 1}, {ci + 1}, {ci + 1}" for ci in c]
    return lines


def _equations(model: Model) -> list[str]:
    lines = []
    for node, hosts, weights in model.embedded_nodes:
        keep = weights != 0.0
        hosts, weights = hosts[keep], weights[keep]
        for c in range(3):
            terms = [(node + 1, c + 1, 1.0)] + [(h + 1, c + 1, -w) for h, w in zip(hosts, weights)]
            lines += ["*EQUATION", str(len(terms))]
            lines += [", ".join(f"{n}, {d}, {_num(w)}" for n, d, w in terms[i : i + 4]) for i in range(0, len(terms), 4)]
    return lines


def _rigid_bodies(model: Model, n_nodes: int) -> list[str]:
    lines = []
    for k, nodes in enumerate(model.rigid_node_sets):
        ref, rot = n_nodes + 2 * k + 1, n_nodes + 2 * k + 2
        c = model.X[nodes].mean(axis=0)
        lines += ["*NODE", f"{ref}, {_num(c[0])}, {_num(c[1])}, {_num(c[2])}",
                  f"{rot}, {_num(c[0])}, {_num(c[1])}, {_num(c[2])}"]
        lines.append(f"*NSET, NSET=RIGID{k}")
        lines += _id_lines(np.asarray(nodes) + 1)
        lines.append(f"*RIGID BODY, NSET=RIGID{k}, REF NODE={ref}, ROT NODE={rot}")
    return lines


# -- CalculiX results ------------------------------------------------------------------------------

_HEADER = re.compile(r"^\s*displacements \(vx,vy,vz\) for set (\S+) and time\s+(\S+)")


def _dat_blocks(path) -> list[tuple[float, dict[int, np.ndarray]]]:
    """Every ``displacements`` block of a CalculiX ``.dat`` file: ``(step time, {node (0-based): u})``."""
    blocks: list[tuple[float, dict[int, np.ndarray]]] = []
    current = None
    for line in Path(path).read_text().splitlines():
        m = _HEADER.match(line)
        if m:
            current = {}
            blocks.append((float(m.group(2)), current))
            continue
        parts = line.split()
        if current is not None and len(parts) == 4 and parts[0].isdigit():
            current[int(parts[0]) - 1] = np.array([float(p) for p in parts[1:]])
        elif current is not None and parts and not (len(parts) == 4 and parts[0].isdigit()):
            current = None  # another kind of output block begins
    return blocks


def read_dat_displacements(path) -> dict[int, np.ndarray]:
    """Nodal displacements (mm) of the last printed increment of a CalculiX ``.dat`` file.

    Returns ``{node index (0-based): (3,) array}`` for the nodes of the last ``*NODE PRINT`` block
    of ``U``. Raises ValueError if the file holds no displacement block.
    """
    blocks = _dat_blocks(path)
    if not blocks:
        raise ValueError(f"{path} holds no 'displacements (vx,vy,vz)' block; did the deck ask for *NODE PRINT of U?")
    return blocks[-1][1]


def run_calculix(inp_path, *, executable: str = "ccx", threads: int = 1, timeout: float | None = 600.0) -> np.ndarray:
    """Run CalculiX on a deck (``ccx -i <stem>`` in the deck's folder) and return its displacements.

    Returns (n, 3) displacements (mm) of the last increment, row = node index (0-based), n the
    largest printed node id (the ``NMODEL`` set of ``write_inp``: all model nodes); rows of nodes
    not printed are NaN. The step must reach time 1 (load factor 1).

    Raises CalculixError (with the tail of CalculiX's output) if ``executable`` is not found, exits
    with an error, times out, prints ``*ERROR``, or stops before the end of the step.
    """
    inp_path = Path(inp_path).resolve()
    if not inp_path.is_file() or inp_path.suffix != ".inp":
        raise FileNotFoundError(f"{inp_path} is not an existing .inp deck")
    exe = shutil.which(executable)
    if exe is None:
        raise CalculixError(
            f"CalculiX executable '{executable}' not found on PATH; install it (Debian: apt-get install calculix-ccx)"
        )
    job = inp_path.stem
    dat = inp_path.with_suffix(".dat")
    dat.unlink(missing_ok=True)  # never read a stale result from an earlier run
    env = dict(os.environ, OMP_NUM_THREADS=str(int(threads)))
    try:
        proc = subprocess.run([exe, "-i", job], cwd=inp_path.parent, env=env, capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired as err:
        out = (err.stdout or b"")
        out = out.decode(errors="replace") if isinstance(out, bytes) else out
        raise CalculixError(f"CalculiX ran past {timeout} s on {inp_path}; output tail:\n{_tail(out)}") from err
    out = proc.stdout + proc.stderr
    if proc.returncode != 0 or "*ERROR" in out:
        raise CalculixError(f"CalculiX failed on {inp_path} (exit code {proc.returncode}); output tail:\n{_tail(out)}")
    if not dat.is_file():
        raise CalculixError(f"CalculiX wrote no {dat.name} for {inp_path}; output tail:\n{_tail(out)}")
    blocks = _dat_blocks(dat)
    if not blocks:
        raise CalculixError(f"{dat} holds no displacement output; output tail:\n{_tail(out)}")
    time, u = blocks[-1]
    if time < 1.0 - 1e-6 or "Job finished" not in out:
        raise CalculixError(f"CalculiX stopped at time {time} before the end of the step on {inp_path}; "
                            f"output tail:\n{_tail(out)}")
    result = np.full((max(u) + 1, 3), np.nan)
    for node, value in u.items():
        result[node] = value
    return result


def _tail(text: str, lines: int = 40) -> str:
    return "\n".join(text.splitlines()[-lines:])
