"""CalculiX cross-check of the actuator model at a partial cavity pressure.

    OMP_NUM_THREADS=1 TORCHFRA_THREADS=1 python studies/calculix_actuator.py \\
        --resolution 1 --pressure 0.0044 --c10 0.0048 --increments 10 --out calculix_actuator_p0044

Builds the actuator (``build_actuator_model``; C10, D1 = 1 / (bulk_ratio C10), E_fiber, cavity
pressure P), writes it for CalculiX and runs ``ccx`` (one thread) on up to two decks in
``runs/<out>/``:

- ``t3d2`` (``actuator.inp``): the deck ``torchfra.io.abaqus.write_inp`` exports. C3D20R bricks,
  each Line3 fiber as two T3D2 trusses, fiber nodes tied to the host bricks by ``*EQUATION``,
  rigid top as ``*RIGID BODY``, cavity pressure as ``*DLOAD``. CalculiX expands every T3D2 into a
  small volume element tied to the truss nodes by its own MPCs: at resolution 1, 52,918 equations
  instead of 4,218, ~20 s per Newton iteration, and a residual that stalls near 1e-6 N at a fiber
  host node, so increments need more and more iterations beyond ~20 % of full pressure.
- ``springa`` (``actuator_springa.inp``): the same deck with each T3D2 replaced by a SPRINGA axial
  spring of stiffness E A / L between the same two nodes: an ideal two-node truss (force
  k (l - L) instead of torchfra's Green strain; the fibers strain < 1e-3), not expanded, 25x faster.

and solves the same problem with torchfra in several formulations:

- ``twin``: displacement-only Hex20 with 2x2x2 Gauss points (C3D20R), cavity pressure as a follower
  load with 2x2 face points (CalculiX's C3D20R face rule), each Line3 fiber as the two straight
  trusses of the deck (``chordify``): the discretization of the decks, the like-for-like check.
- ``displacement_reduced_line3``: the same with torchfra's curved Line3 fibers (fiber element).
- ``displacement_reduced``: the same with the model's exact 3x3 cavity pressure (face rule).
- ``hybrid_reduced``: hybrid u/p, 2x2x2 (the paper's C3D20RH; CalculiX has no hybrid brick).
- ``hybrid_full``: hybrid u/p, 3x3x3: the actuator model torchfra uses (C3D20H analogue).
- ``displacement_full``: displacement-only, 3x3x3 (C3D20: volumetric locking, for contrast).

``--fiber-resolutions`` adds a torchfra-only check: hybrid_full with Line3 fibers against the same
with chords at other resolutions (how the fiber-element difference changes with the mesh).

CalculiX prints the displacements of every increment, so each case is compared at every load
factor k / increments (torchfra outputs at the same factors) and at the end. CalculiX's Newton
iterations converge only linearly here (the rigid body's nonlinear MPC, the follower pressure),
and it accepts an increment once the residual is small while the last correction can still be
~5e-5 of max |u| (recorded as ``last_correction_rel``). A hold increment at the full load
(``--hold-increments``) made this worse, not better, with the SPRINGA deck at 0.0044 MPa: its
predictor extrapolates the last increment's motion, and the iterations back stopped with a last
correction of 2e-4 of max |u| (the twin moved from 7e-5 to 2.5e-4 away). Hence no hold by default.
``runs/<out>/summary.json`` holds the model size, each CalculiX run (version, wall time, equations,
increments, Newton iterations per increment, final time, change over the hold increments), each
torchfra case (wall time, Newton iterations, increments, tracked displacement) and, per deck and
case: tracked-node (y, z) displacements, the relative difference of their magnitudes, the vector
difference relative to the CalculiX magnitude, and max over all model nodes of
|u_torchfra - u_ccx| / max |u_ccx| (Euclidean norms per node), at the end and along the load path;
``torchfra_vs_twin`` gives the same measures between torchfra cases. A CalculiX run that stops
early is recorded with its last converged time and the tail of its output, and is compared along
the load path it reached. ``--reuse-ccx`` reads the results of decks already run in ``runs/<out>/``.
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.io.abaqus.write import dat_blocks, write_inp

# name: (formulation, integration, cavity pressure, fiber element)
#   cavity pressure "follower2": FollowerPressure on the cavity faces with 2x2 face points (CalculiX's
#   C3D20R face rule); "cavity3": the model's CavityPressure with the exact 3x3 rule.
#   fiber element "chords": each Line3 fiber as two straight trusses (the deck's T3D2, ``chordify``);
#   "line3": the model's curved Line3 trusses.
CASES = {
    "twin": ("displacement", "reduced", "follower2", "chords"),
    "displacement_reduced_line3": ("displacement", "reduced", "follower2", "line3"),
    "displacement_reduced": ("displacement", "reduced", "cavity3", "line3"),
    "hybrid_reduced": ("hybrid", "reduced", "cavity3", "line3"),
    "hybrid_full": ("hybrid", "full", "cavity3", "line3"),
    "displacement_full": ("displacement", "full", "cavity3", "line3"),
}
TWIN = "twin"
DECKS = {"t3d2": "actuator.inp", "springa": "actuator_springa.inp"}


# -- models ------------------------------------------------------------------------------------------
def chordify(model) -> None:
    """Replace every Line3 fiber (a, b, m) by the two straight trusses a-m and m-b of the deck's T3D2
    pair: each becomes a Line3 whose middle node sits at the chord midpoint, tied to the mean of its
    ends (through the ends' host weights), so its displacement is linear along the chord and its
    Green strain is that of a two-node truss."""
    k, truss = next((k, t) for k, t in enumerate(model.terms) if isinstance(t, fem.Truss))
    conn = truss.conn.numpy()
    pairs = np.concatenate([conn[:, [0, 2]], conn[:, [2, 1]]])
    model.terms[k] = fem.two_node_truss(model, pairs, area=truss.area, modulus=truss.modulus)


def build(geom: ActuatorGeometry, formulation: str, integration: str, pressure: str, fibers: str):
    """The actuator model (``build_actuator_model``) with the cavity pressure and fiber element of a case."""
    model, info = build_actuator_model(geom, formulation=formulation, integration=integration)
    if pressure == "follower2":
        k, term = next((k, t) for k, t in enumerate(model.terms) if isinstance(t, fem.CavityPressure))
        model.terms[k] = fem.FollowerPressure(model.mesh, term.face_set, pressure=term.pressure, quadrature=2)
    if fibers == "chords":
        chordify(model)
    return model, info


def solve_torchfra(geom, case, params, load_factors) -> tuple[dict, np.ndarray]:
    model, info = build(geom, *CASES[case])
    t0 = time.perf_counter()
    sol = fem.solve(model, {k: torch.tensor([v]) for k, v in params.items()}, load_factors,
                    fem.NewtonOptions(stagnation_tol=1e-6))
    wall = time.perf_counter() - t0
    u = sol.u[0, :, : info["mesh"].n_nodes + info["fiber_nodes_count"]].numpy()  # (T, model nodes, 3)
    row = dict(zip(("formulation", "integration", "cavity_pressure", "fibers"), CASES[case]))
    row.update(status=str(sol.status[0]), load_reached=float(sol.load_reached[0]),
               iterations=int(sol.iterations[0]), increments=int(sol.increments[0]),
               cutbacks=int(sol.cutbacks[0]), wall_s=wall, tracked_u_yz_mm=u[-1, info["tracked_node"], 1:].tolist())
    return row, u


# -- decks ---------------------------------------------------------------------------------------------
def write_decks(run_dir: Path, geom, params, increments: int, hold: int, decks) -> tuple[dict, object, dict]:
    """Write the requested decks from the model with Line3 fibers; returns (paths, model, info)."""
    model, info = build(geom, *CASES["displacement_reduced_line3"])
    title = f"torchfra actuator, resolution {geom.resolution}, P = {params['P']} MPa, C10 = {params['C10']} MPa"
    options = dict(element_type="C3D20R", truss_element="T3D2", increments=increments, hold_increments=hold)
    paths = {}
    if "t3d2" in decks:
        paths["t3d2"] = write_inp(run_dir / DECKS["t3d2"], model, params, title=title, **options)
    if "springa" in decks:
        path = write_inp(run_dir / DECKS["springa"], model, params, title=title + ", fibers as SPRINGA",
                         **{**options, "truss_element": "SPRINGA"})
        paths["springa"] = path
    return paths, model, info


# -- CalculiX --------------------------------------------------------------------------------------------
def ccx_version(exe: str) -> str:
    out = subprocess.run([exe, "-v"], capture_output=True, text=True).stdout
    m = re.search(r"Version\s+(\S+)", out)
    return m.group(1) if m else out.strip()


def parse_sta(path: Path) -> list[dict]:
    rows = []
    if path.is_file():
        for line in path.read_text().splitlines():
            p = line.split()
            if len(p) == 7 and p[0].isdigit():  # an attempt that did not converge reads e.g. "1U"
                rows.append({"inc": int(p[1]), "attempt": p[2], "converged": not p[2].endswith("U"),
                             "iterations": int(p[3]), "total_time": float(p[4])})
    return rows


def run_ccx(deck: Path, timeout: float, reuse: dict | None) -> tuple[dict, list]:
    """Run ``ccx -i <stem>`` with one thread in the deck's folder, output to ``<stem>.log``; with
    ``reuse`` (the earlier summary row, possibly empty), read the earlier run's files instead."""
    exe = shutil.which("ccx")
    if exe is None:
        raise SystemExit("CalculiX (ccx) is not on PATH; install it (Debian: apt-get install calculix-ccx)")
    log = deck.with_suffix(".log")
    if reuse is None:
        for suffix in (".dat", ".sta", ".frd", ".cvg", ".12d"):
            deck.with_suffix(suffix).unlink(missing_ok=True)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        t0 = time.perf_counter()
        with log.open("w") as fh:
            try:
                proc = subprocess.run([exe, "-i", deck.stem], cwd=deck.parent, env=env, stdout=fh,
                                      stderr=subprocess.STDOUT, timeout=timeout)
                code, timed_out = proc.returncode, False
            except subprocess.TimeoutExpired:
                code, timed_out = None, True
        wall = time.perf_counter() - t0
    else:
        code, timed_out, wall = reuse.get("exit_code", 0), reuse.get("timed_out", False), reuse.get("wall_s")
    text = log.read_text(errors="replace") if log.is_file() else ""
    sta = parse_sta(deck.with_suffix(".sta"))
    eq = re.search(r"number of equations\s+(\d+)", text)
    dat = deck.with_suffix(".dat")
    blocks = dat_blocks(dat) if dat.is_file() else []
    finished = "Job finished" in text and code == 0 and "*ERROR" not in text
    corrections = last_corrections(text)
    return {
        "deck": str(deck), "version": ccx_version(exe), "threads": 1, "wall_s": wall, "exit_code": code,
        "timed_out": timed_out, "finished": finished, "equations": int(eq.group(1)) if eq else None,
        "increments_done": sum(r["converged"] for r in sta), "iterations": sum(r["iterations"] for r in sta),
        "iterations_per_increment": [r["iterations"] for r in sta if r["converged"]],
        "failed_attempts": [{k: r[k] for k in ("inc", "iterations", "total_time")} for r in sta if not r["converged"]],
        "final_time": blocks[-1][0] if blocks else 0.0,
        "last_correction_per_increment_mm": [r["correction_mm"] for r in corrections],
        "last_correction_node": corrections[-1]["node"] if corrections else None,
        "output_tail": None if finished else "\n".join(text.splitlines()[-30:]),
    }, blocks


def last_corrections(log_text: str) -> list[dict]:
    """Per converged CalculiX increment: the last Newton correction and the increment's displacement
    (largest components, mm) and the node of that correction, from the ``ccx`` output."""
    rows, current = [], {}
    for line in log_text.splitlines():
        m = re.match(r"\s*largest increment of disp=\s*(\S+)", line)
        if m:
            current["increment_mm"] = float(m.group(1))
        m = re.match(r"\s*largest correction to disp=\s*(\S+) in node (\d+)", line)
        if m:
            current.update(correction_mm=float(m.group(1)), node=int(m.group(2)))
        if line.strip() == "convergence" and current:
            rows.append(current)
            current = {}
    return rows


def to_array(block: dict, n: int) -> np.ndarray:
    u = np.full((n, 3), np.nan)
    for node, value in block.items():
        if node < n:
            u[node] = value
    return u


def compare(u: np.ndarray, ref: np.ndarray, tracked: int) -> dict:
    """u, ref: (n, 3) displacements (torchfra, reference) at one load factor."""
    ty, ry = u[tracked, 1:], ref[tracked, 1:]
    scale = np.linalg.norm(ref, axis=1).max()
    return {
        "tracked_ref_yz_mm": ry.tolist(), "tracked_torchfra_yz_mm": ty.tolist(),
        "tracked_rel_diff_magnitude": float((np.linalg.norm(ty) - np.linalg.norm(ry)) / np.linalg.norm(ry)),
        "tracked_rel_diff_vector": float(np.linalg.norm(ty - ry) / np.linalg.norm(ry)),
        "max_node_diff_rel": float(np.linalg.norm(u - ref, axis=1).max() / scale),
        "max_u_ref_mm": float(scale),
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=1, help="actuator mesh resolution (1: 288 bricks)")
    p.add_argument("--pressure", type=float, default=0.0044, help="cavity pressure at load factor 1 (MPa)")
    p.add_argument("--c10", type=float, default=0.0048, help="Neo-Hookean C10 (MPa)")
    p.add_argument("--bulk-ratio", type=float, default=1000.0, help="D1 = 1 / (bulk_ratio C10)")
    p.add_argument("--e-fiber", type=float, default=31000.0, help="fiber Young's modulus (MPa)")
    p.add_argument("--increments", type=int, default=10, help="equal CalculiX increments from 0 to P")
    p.add_argument("--hold-increments", type=int, default=0,
                   help="CalculiX increments held at P (0: see the module docstring)")
    p.add_argument("--decks", nargs="+", default=list(DECKS), choices=list(DECKS), help="CalculiX decks to run")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES), help="torchfra formulations")
    p.add_argument("--fiber-resolutions", type=int, nargs="*", default=[],
                   help="resolutions of the torchfra-only Line3-vs-chords check (hybrid_full)")
    p.add_argument("--ccx-timeout", type=float, default=1800.0, help="seconds before CalculiX is stopped")
    p.add_argument("--reuse-ccx", action="store_true",
                   help="read the CalculiX results of decks already run in runs/<out>/ instead of running them again")
    p.add_argument("--out", default="calculix_actuator")
    p.add_argument("--runs-dir", default="runs")
    a = p.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("TORCHFRA_THREADS", "1")))
    run_dir = Path(a.runs_dir) / a.out
    run_dir.mkdir(parents=True, exist_ok=True)
    summary_path = run_dir / "summary.json"
    earlier = json.loads(summary_path.read_text()).get("calculix", {}) if a.reuse_ccx and summary_path.is_file() else {}
    geom = ActuatorGeometry(resolution=a.resolution)
    params = {"C10": a.c10, "D1": 1.0 / (a.bulk_ratio * a.c10), "E_fiber": a.e_fiber, "P": a.pressure}
    factors = [(k + 1) / a.increments for k in range(a.increments)]
    cases = [TWIN] + [c for c in a.cases if c != TWIN]

    reused = {d for d in a.decks if a.reuse_ccx and (run_dir / DECKS[d]).with_suffix(".dat").is_file()}
    paths, model, info = write_decks(run_dir, geom, params, a.increments, a.hold_increments,
                                     [d for d in a.decks if d not in reused])
    paths = {d: paths.get(d, run_dir / DECKS[d]) for d in a.decks}
    n, tracked = model.n_nodes, info["tracked_node"]
    summary = {
        "command": "python studies/calculix_actuator.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "resolution": a.resolution, "pressure_MPa": a.pressure, "params": params, "bulk_ratio": a.bulk_ratio,
        "model": {k: int(info[k]) for k in ("elements", "nodes", "fiber_elements", "fiber_nodes_count", "dofs")},
        "tracked_node": tracked, "tracked_node_X_mm": model.X[tracked].tolist(), "load_factors": factors,
        "calculix": {}, "torchfra": {}, "comparison": {},
    }

    ccx = {}  # deck -> (results by load factor, result at the end, complete)
    for deck, path in paths.items():
        print(f"CalculiX on {path} ...", flush=True)
        row, blocks = run_ccx(path, a.ccx_timeout, earlier.get(deck, {}) if deck in reused else None)
        row.update(element="C3D20R", fibers="T3D2" if deck == "t3d2" else "SPRINGA", increments=a.increments,
                   hold_increments=a.hold_increments)
        summary["calculix"][deck] = row
        if blocks:
            by_time = {round(t, 9): to_array(b, n) for t, b in blocks}  # the last block of a time wins
            end = to_array(blocks[-1][1], n)
            row["tracked_u_yz_mm"] = end[tracked, 1:].tolist()
            if row["last_correction_per_increment_mm"]:  # the size of CalculiX's unfinished Newton iteration
                row["last_correction_rel"] = (row["last_correction_per_increment_mm"][-1]
                                              / float(np.linalg.norm(end, axis=1).max()))
            if 1.0 in by_time:
                row["hold_change_rel"] = float(np.linalg.norm(end - by_time[1.0], axis=1).max()
                                               / np.linalg.norm(end, axis=1).max())
            ccx[deck] = (by_time, end, row["final_time"] >= 1.0 - 1e-9)
        print(json.dumps({k: v for k, v in row.items() if k != "output_tail"}), flush=True)
        summary_path.write_text(json.dumps(summary, indent=1))
    if not ccx:
        raise SystemExit(f"CalculiX printed no displacements; see the .log files in {run_dir}")

    solutions = {}
    for case in cases:
        row, u = solve_torchfra(geom, case, params, factors)
        solutions[case] = u
        summary["torchfra"][case] = row
        print(case, json.dumps(row), flush=True)
        if row["status"] != "converged":
            continue
        for deck, (by_time, end, complete) in ccx.items():
            path = [dict(load_factor=f, **compare(u[k], by_time[round(f, 9)], tracked))
                    for k, f in enumerate(factors) if round(f, 9) in by_time]
            summary["comparison"].setdefault(deck, {})[case] = {
                "at_end": compare(u[-1], end, tracked) if complete else None, "load_path": path}
        summary_path.write_text(json.dumps(summary, indent=1))
    # element effects within torchfra at load factor 1, against the C3D20R twin
    ref = solutions[TWIN][-1]
    summary["torchfra_vs_twin"] = {
        case: {k: v for k, v in compare(u[-1], ref, tracked).items() if k.startswith(("tracked_rel", "max_node"))}
        for case, u in solutions.items() if case != TWIN and np.isfinite(u[-1]).all()
    }
    summary_path.write_text(json.dumps(summary, indent=1))

    summary["fiber_element_check"] = []
    for r in a.fiber_resolutions:
        u_r = {}
        for fibers in ("line3", "chords"):
            m, i = build(ActuatorGeometry(resolution=r), "hybrid", "full", "cavity3", fibers)
            sol = fem.solve(m, {k: torch.tensor([v]) for k, v in params.items()}, (1.0,),
                            fem.NewtonOptions(stagnation_tol=1e-6))
            u_r[fibers] = sol.u[0, -1, : i["mesh"].n_nodes].numpy()
        d = compare(u_r["line3"], u_r["chords"], i["tracked_node"])
        summary["fiber_element_check"].append({
            "resolution": r, "fiber_elements": int(i["fiber_elements"]),
            "tracked_line3_yz_mm": d["tracked_torchfra_yz_mm"], "tracked_chords_yz_mm": d["tracked_ref_yz_mm"],
            "tracked_rel_diff_magnitude": d["tracked_rel_diff_magnitude"],
            "tracked_rel_diff_vector": d["tracked_rel_diff_vector"], "max_node_diff_rel": d["max_node_diff_rel"]})
        print("fiber element check", json.dumps(summary["fiber_element_check"][-1]), flush=True)
        summary_path.write_text(json.dumps(summary, indent=1))

    for deck, rows in summary["comparison"].items():
        for case, c in rows.items():
            e = c["at_end"] or c["load_path"][-1]
            print(f"{deck:8s} {case:28s} tracked (y, z) {np.round(e['tracked_torchfra_yz_mm'], 5)} vs ccx "
                  f"{np.round(e['tracked_ref_yz_mm'], 5)}: |u| {100 * e['tracked_rel_diff_magnitude']:+.3f} %, "
                  f"vector {100 * e['tracked_rel_diff_vector']:.3f} %, max node {100 * e['max_node_diff_rel']:.3f} %")
    return summary


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
