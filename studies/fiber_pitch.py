"""The fiber-pitch candidate on the actuator: what it is against re-built models, what a pitch change
shows on the DIC grid, and why the diagnosis sees it through a secant.

    python studies/fiber_pitch.py [--pitches 1.5 2.5 3 4] [--resolutions 1 2]

Observations: the proof suite's DIC grid (``scenarios.dic_grid``, 2 mm, off-node) over its 20-frame
ramp to 0.022 MPa. Per resolution:

- ``rebuilt``: the model with the candidate at each pitch against the actuator built with its Line3
  fibers wound at that pitch (the same count per helix, ``build_actuator_model(fibers=...)``): the
  two must agree to round-off (this is what the term claims to be);
- ``remeshed``: against the actuator re-meshed at that pitch the default way (8 truss elements per
  turn at resolution 1, so another count): the fibers' own discretization;
- ``effect``: the candidate at each pitch against the base model (the signal-to-noise ratio at 1 mm
  i.i.d. noise is this norm);
- ``ripple``: the exact derivative dY/d(pitch) at the drawn pitch (implicit differentiation) against
  central secants over +-h: a pitch change slides the fiber nodes through the bricks, so the
  discrete response carries a ripple whose exact slope dwarfs the physical one;
- ``cost``: wall seconds of one solve with and without the candidate (same run, same threads).

Writes studies/results/study_fiber_pitch.json (``--out``) and TensorBoard scalars under runs/<name>/.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model, helix_points
from torchfra.fem.sensitivity import sensitivities
from torchfra.observation.operator import ObservationOperator, visible_faces
from torchfra.report.tensorboard import open_writer
from torchfra.scenarios import PRESSURE_MAX, dic_grid, pressure_trace

OPTIONS = fem.NewtonOptions(rtol=1e-10, stagnation_tol=1e-8)


class Observer:
    """Solves of one resolution's models observed on the grid: (K, P, 2) uy, uz at the load factors."""

    def __init__(self, mesh, points, loads, params):
        self.n = mesh.n_nodes
        self.op = ObservationOperator(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=points, tol=0.05)
        self.loads, self.params = loads, params

    def tensors(self, **extra):
        return {k: torch.tensor([v], dtype=torch.float64) for k, v in {**self.params, **extra}.items()}

    def solve(self, model, **extra):
        t0 = time.perf_counter()
        sol = fem.solve(model, self.tensors(**extra), self.loads, OPTIONS)
        if not sol.converged.all():
            raise RuntimeError(f"solve did not converge ({extra}; reached {sol.load_reached[0]:.3f} of the load)")
        return sol, self.op(sol.u[0, :, : self.n]).numpy(), time.perf_counter() - t0


def same_trusses(geom: ActuatorGeometry, n_el: int, pitch: float):
    """Line3 fibers of both helices at ``pitch`` with ``n_el`` elements per helix (the base's count)."""
    X = helix_points(ActuatorGeometry(resolution=geom.resolution, pitch_deg=pitch),
                     np.linspace(0.0, 1.0, 2 * n_el + 1)).reshape(-1, 3)
    k = np.arange(n_el)
    one = np.stack([2 * k, 2 * k + 2, 2 * k + 1], 1)
    return X, np.concatenate([one, one + 2 * n_el + 1])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pitches", type=float, nargs="+", default=[1.5, 2.5, 3.0, 4.0], help="pitch angles (deg)")
    ap.add_argument("--resolutions", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--secants", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2, 0.05, 0.25],
                    help="half-steps of the central secants against the exact derivative (deg)")
    ap.add_argument("--C10", type=float, default=0.0062)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--threads", type=int, default=int(os.environ.get("TORCHFRA_THREADS", "1")))
    ap.add_argument("--name", default="study_fiber_pitch")
    ap.add_argument("--out", default="studies/results/study_fiber_pitch.json")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.set_default_dtype(torch.float64)
    _, recorded = pressure_trace("ramp", a.frames)
    loads = recorded[recorded > 0] / PRESSURE_MAX
    params = {"C10": a.C10, "D1": 1.0 / (BULK_RATIO * a.C10), "E_fiber": E_FIBER, "P": PRESSURE_MAX}
    nominal = ActuatorGeometry().pitch_deg
    writer = open_writer(Path("runs") / a.name)
    per_res = 2 + 3 * len(a.pitches) + 2 * len(a.secants)
    bar = tqdm(total=len(a.resolutions) * per_res, desc="fiber pitch study: FE solves", unit="solve",
               bar_format="{l_bar}{bar}| {n}/{total} [{elapsed} elapsed, ~{remaining} left]")
    out = {"command": "python studies/fiber_pitch.py " + " ".join(argv if argv is not None else os.sys.argv[1:]),
           "threads": a.threads, "C10": a.C10, "frames": a.frames, "nominal_pitch_deg": nominal,
           "note": "norms over frames, points and (uy, uz) in mm: the signal-to-noise ratio at 1 mm i.i.d. noise",
           "resolutions": []}
    for res in a.resolutions:
        geom = ActuatorGeometry(resolution=res)
        base, info = build_actuator_model(geom)
        pitched, _ = build_actuator_model(geom, fiber_pitch=True)
        n_el = info["fiber_elements"] // 2
        obs = Observer(info["mesh"], dic_grid(info["mesh"], 2.0), loads, params)
        _, Y0, t_base = obs.solve(base)
        bar.update()
        sol_null, Y_null, t_null = obs.solve(pitched, fiber_pitch=nominal)
        bar.update()
        row = {"resolution": res, "truss_elements_per_helix": n_el, "observations": int(Y0.size),
               "null_minus_base_max_mm": float(np.abs(Y_null - Y0).max()), "pitches": []}
        for p in a.pitches:
            rebuilt, _ = build_actuator_model(geom, fibers=same_trusses(geom, n_el, p))
            remeshed, info_r = build_actuator_model(ActuatorGeometry(resolution=res, pitch_deg=p))
            _, Yp, t_pitch = obs.solve(pitched, fiber_pitch=p)
            bar.update()
            _, Yb, _ = obs.solve(rebuilt)
            bar.update()
            _, Yr, _ = obs.solve(remeshed)
            bar.update()
            r = {"pitch_deg": p, "effect_norm_mm": float(np.linalg.norm(Yp - Y0)),
                 "effect_max_mm": float(np.abs(Yp - Y0).max()),
                 "minus_rebuilt_same_trusses_max_mm": float(np.abs(Yp - Yb).max()),
                 "remeshed_truss_elements_per_helix": info_r["fiber_elements"] // 2,
                 "minus_remeshed_default_norm_mm": float(np.linalg.norm(Yp - Yr)),
                 "remeshed_effect_norm_mm": float(np.linalg.norm(Yr - Y0)), "solve_s": round(t_pitch, 2)}
            row["pitches"].append(r)
            writer.add_scalar(f"fiber_pitch/res{res}/effect_norm_mm", r["effect_norm_mm"], int(round(100 * p)))
            writer.add_scalar(f"fiber_pitch/res{res}/minus_remeshed_norm_mm", r["minus_remeshed_default_norm_mm"],
                              int(round(100 * p)))

        def params_of(th):
            return {**{k: torch.full_like(th["fiber_pitch"], v) for k, v in params.items()}, **th}

        S = sensitivities(pitched, params_of, {"fiber_pitch": torch.tensor([nominal])}, sol_null)
        exact = obs.op(S.du[0, :, : obs.n, :, 0]).numpy()
        row["ripple"] = {"exact_norm_mm_per_deg": float(np.linalg.norm(exact)), "secants": []}
        for h in a.secants:
            _, Yu, _ = obs.solve(pitched, fiber_pitch=nominal + h)
            bar.update()
            _, Yd, _ = obs.solve(pitched, fiber_pitch=nominal - h)
            bar.update()
            sec = (Yu - Yd) / (2 * h)
            row["ripple"]["secants"].append({"half_step_deg": h, "secant_norm_mm_per_deg": float(np.linalg.norm(sec)),
                                             "exact_minus_secant_rel": float(np.linalg.norm(exact - sec)
                                                                             / np.linalg.norm(sec))})
        row["cost"] = {"base_solve_s": round(t_base, 2), "with_candidate_at_null_s": round(t_null, 2),
                       "with_candidate_off_null_mean_s": round(float(np.mean([r["solve_s"] for r in row["pitches"]])), 2)}
        out["resolutions"].append(row)
    bar.close()
    writer.close()
    for row in out["resolutions"]:
        print(f"resolution {row['resolution']} ({row['truss_elements_per_helix']} trusses per helix):")
        for r in row["pitches"]:
            print(f"  {r['pitch_deg']:g} deg: effect {r['effect_norm_mm']:.3f} mm (max {r['effect_max_mm']:.4f}); "
                  f"vs the same trusses re-built {r['minus_rebuilt_same_trusses_max_mm']:.1e} mm; vs the default "
                  f"re-mesh ({r['remeshed_truss_elements_per_helix']} per helix) {r['minus_remeshed_default_norm_mm']:.3f} mm")
        print(f"  exact |dY/dpitch| at the drawn pitch {row['ripple']['exact_norm_mm_per_deg']:.1f} mm/deg; secants: "
              + ", ".join(f"+-{s['half_step_deg']:g}: {s['secant_norm_mm_per_deg']:.2f}" for s in row["ripple"]["secants"]))
        print(f"  cost: {row['cost']}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
