"""A creeping actuator: the FE model with history variables against the load-level approximation.

    python studies/viscoelastic.py [--resolution 1] [--g1 0.05 0.15 0.4] [--tau1 0.1]

The proof suite's viscoelastic recordings (``scenarios.py``, effect ``viscoelasticity``) and the
diagnosis' candidate (``torchfra.actuator.history``) both describe a creeping body by the correspondence
principle: the relaxed elastic body at an effective load level ``mu(t)``, exact for a linear body.
This study measures what that approximation leaves out at finite strain. For the paper's actuator
(C10 0.0062 MPa, 0.022 MPa, the suite's 20-frame load-unload cycle, body at rest at t = 0, tau1 in
units of the cycle's duration) observed as the suite observes it (uy, uz on the face x = +8 at the
shifted 2 mm DIC grid), three models:

- ``fe``: the body with a Prony term in its element kernel (``fem.viscoelastic``: history variables
  at every Gauss point, marched through the trace by ``solve_history``);
- ``approx``: the relaxed body solved at the load levels of ``history.creep_load``;
- ``base``: the elastic body at the recorded pressures.

Reported per g1: the effect's SNR ``||fe - base||`` and the approximation's error ``||fe - approx||``
(norms over frames, points and components; mm, = SNR at noise 1 mm), the largest difference, and
the wall time of each solve. Writes studies/results/study_viscoelastic_res<r>.json (``--out``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.actuator.history import creep_load
from torchfra.scenarios import PRESSURE_MAX, elastic_frames, face_observer, pressure_trace


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=1)
    ap.add_argument("--g1", type=float, nargs="+", default=[0.05, 0.15, 0.4])
    ap.add_argument("--tau1", type=float, default=0.1, help="relaxation time, units of the cycle's duration")
    ap.add_argument("--C10", type=float, default=0.0062)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--max-dt", type=float, default=None, help="longest time step (default tau1 / 4)")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("TORCHFRA_THREADS", "1")))
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    out = Path(a.out or f"studies/results/study_viscoelastic_res{a.resolution}.json")
    times, recorded = pressure_trace("cycle", a.frames)
    lam = recorded / PRESSURE_MAX
    base_params = {"C10": a.C10, "D1": 1.0 / (BULK_RATIO * a.C10), "E_fiber": E_FIBER, "P": PRESSURE_MAX}
    as_t = lambda d: {k: torch.tensor([v], dtype=torch.float64) for k, v in d.items()}  # noqa: E731

    def elastic_at(levels):
        """The elastic body at load factors ``levels`` (K,), zero where the level is 0."""
        model, _ = build_actuator_model(ActuatorGeometry(resolution=a.resolution))
        t0 = time.perf_counter()
        full, sol = elastic_frames(model, as_t(base_params), levels, fem.NewtonOptions(stagnation_tol=1e-6),
                                   face_observer(model.mesh, 2.0))
        assert sol.converged.all(), sol.status
        return full, time.perf_counter() - t0

    base, base_s = elastic_at(lam)
    rows = []
    for g1 in a.g1:
        t = np.concatenate([[0.0], times])
        mu = creep_load(torch.as_tensor(np.concatenate([[0.0], lam])), t, torch.tensor(g1), torch.tensor(a.tau1))
        approx, approx_s = elastic_at(mu.numpy()[1:])
        model, _ = build_actuator_model(ActuatorGeometry(resolution=a.resolution))
        fem.with_viscoelasticity(model)
        op = face_observer(model.mesh, 2.0)
        t0 = time.perf_counter()
        sol = fem.solve_history(model, as_t({**base_params, "g1": g1, "tau1": a.tau1}), times, lam,
                                max_dt=a.max_dt, options=fem.NewtonOptions(stagnation_tol=1e-6),
                                progress=f"g1 = {g1:g}, FE history")
        assert sol.converged.all(), sol.status
        fe_s = time.perf_counter() - t0
        fe = op(sol.u[0][:, : model.mesh.n_nodes]).numpy()
        row = {"g1": g1, "tau1": a.tau1, "snr_effect": float(np.linalg.norm(fe - base)),
               "snr_approx_error": float(np.linalg.norm(fe - approx)),
               "max_abs_approx_error_mm": float(np.abs(fe - approx).max()),
               "max_abs_effect_mm": float(np.abs(fe - base).max()),
               "relative_approx_error": float(np.linalg.norm(fe - approx) / np.linalg.norm(fe - base)),
               "fe_seconds": fe_s, "fe_increments": int(sol.increments[0]), "fe_iterations": int(sol.iterations[0]),
               "approx_seconds": approx_s}
        rows.append(row)
        print(json.dumps(row), flush=True)
    result = {"command": "python " + " ".join(sys.argv), "resolution": a.resolution, "frames": a.frames,
              "C10": a.C10, "trace": "cycle", "threads": a.threads, "base_seconds": base_s, "rows": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
