"""How long may a time step of the creeping body's march be? The step rule of ``fem.solve_history``.

    python studies/history_steps.py [--tau1 0.005 0.035 0.1 0.3] [--g1 0.3] [--dlam 0.1 0.05 0.025 0.0125]

``fem.viscoelastic`` advances each Prony term's history by the exponential (Simo) recurrence, exact
when the instantaneous stress S0 is linear in time over a step, whatever the step's length against
tau1. What a long step misses is only S0's curvature within it, which a finer step in *load* removes.
So a step need not be shorter than tau1: the march could follow the recording's frames and a load
increment alone. The diagnosis' creep candidate (``physics.HistoryPhysics``) has marched in steps of
at most tau1 / 2, and a sensor lag or a fast creep pulls tau1 towards a few thousandths of the
recording's duration: hundreds of steps per march, minutes each, four marches per evaluation.

This study marches the paper's actuator (resolution 1, C10 0.0062 MPa, 0.022 MPa, the suite's
20-frame load-unload cycle, observed as the suite observes it: uy, uz on the face x = +8 at the
shifted 2 mm DIC grid) with one Prony term for several tau1 at once (one member each), under

- load-step rules without any time limit: at most ``dlam`` in load factor per step, for each
  ``--dlam``; the finest is the reference. A consistent scheme converges to one answer as dlam
  shrinks, at second order (the successive differences fall ~4x per halving);
- the diagnosis' rule so far: at most tau1 / 2 in time and 0.1 in load (one march per tau1).

Reported per tau1 and rule: the largest and the RMS difference to the reference at the observed
points (mm), the norm of the difference over frames, points and components divided by the noise
``--sigma`` (the same unit as the suite's SNRs), the creep effect's own norm / sigma for scale, and
the steps and wall time of each march. Writes studies/results/study_history_steps.json (``--out``).
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
from torchfra.scenarios import PRESSURE_MAX, elastic_frames, face_observer, pressure_trace


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=1)
    ap.add_argument("--tau1", type=float, nargs="+", default=[0.005, 0.035, 0.1, 0.3],
                    help="relaxation times, units of the cycle's duration")
    ap.add_argument("--g1", type=float, default=0.3)
    ap.add_argument("--dlam", type=float, nargs="+", default=[0.1, 0.05, 0.025, 0.0125],
                    help="load-factor limits per step of the time-free rules; the smallest is the reference")
    ap.add_argument("--C10", type=float, default=0.0062)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--sigma", type=float, default=0.25, help="noise std (mm) the differences are measured in")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("TORCHFRA_THREADS", "1")))
    ap.add_argument("--out", default="studies/results/study_history_steps.json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    times, recorded = pressure_trace("cycle", a.frames)
    lam = recorded / PRESSURE_MAX
    taus = np.array(a.tau1, dtype=np.float64)
    n = taus.size
    params = {"C10": a.C10, "D1": 1.0 / (BULK_RATIO * a.C10), "E_fiber": E_FIBER, "P": PRESSURE_MAX}
    params = {k: torch.full((n,), v, dtype=torch.float64) for k, v in params.items()}
    params["g1"] = torch.full((n,), a.g1, dtype=torch.float64)
    params["tau1"] = torch.as_tensor(taus)
    model, _ = build_actuator_model(ActuatorGeometry(resolution=a.resolution))
    fem.with_viscoelasticity(model)
    mesh = model.mesh
    op = face_observer(mesh, 2.0)
    options = fem.NewtonOptions(stagnation_tol=1e-6)

    def march(members, max_dt, max_dlam, label):
        sub = {k: v[members] for k, v in params.items()}
        t0 = time.perf_counter()
        sol = fem.solve_history(model, sub, times, lam, max_dt=max_dt, max_dlam=max_dlam, options=options,
                                progress=label)
        if not sol.converged.all():
            raise RuntimeError(f"{label}: march stopped ({list(sol.status)})")
        Y = np.stack([op(sol.u[i][:, : mesh.n_nodes]).numpy() for i in range(len(members))])
        return Y, time.perf_counter() - t0, sol.increments.tolist()

    everyone = list(range(n))
    elastic = {**{k: v[:1] for k, v in params.items()}, "g1": torch.zeros(1, dtype=torch.float64)}
    base_model, _ = build_actuator_model(ActuatorGeometry(resolution=a.resolution))
    base, base_sol = elastic_frames(base_model, {k: v for k, v in elastic.items() if k not in ("g1", "tau1")}, lam,
                                    options, op)
    if not base_sol.converged.all():
        raise RuntimeError(f"the elastic body did not solve ({list(base_sol.status)})")

    rules = []
    for dlam in sorted(a.dlam, reverse=True):  # coarse first: the progress tells early how it goes
        Y, s, steps = march(everyone, float("inf"), dlam, f"load steps <= {dlam:g}, no time limit, {n} tau1")
        rules.append({"rule": f"dlam {dlam:g}", "dlam": dlam, "max_dt": "none", "Y": Y, "seconds": s,
                      "steps": steps, "members": everyone})
    reference = min(rules, key=lambda r: r["dlam"])
    for i, tau in enumerate(taus):
        Y, s, steps = march([i], 0.5 * tau, 0.1, f"tau1 = {tau:g}: steps <= tau1 / 2 and 0.1 in load")
        rules.append({"rule": "tau1/2 and dlam 0.1", "dlam": 0.1, "max_dt": 0.5 * tau, "Y": Y, "seconds": s,
                      "steps": steps, "members": [i]})

    rows = []
    for r in rules:
        for j, i in enumerate(r["members"]):
            diff = r["Y"][j] - reference["Y"][i]
            rows.append({"tau1": float(taus[i]), "rule": r["rule"], "dlam": r["dlam"], "max_dt": r["max_dt"],
                         "steps": int(r["steps"][j]), "march_seconds": r["seconds"],
                         "members_in_march": len(r["members"]),
                         "max_abs_diff_mm": float(np.abs(diff).max()),
                         "rms_diff_mm": float(np.sqrt(np.mean(diff ** 2))),
                         "diff_norm_over_sigma": float(np.linalg.norm(diff) / a.sigma),
                         "effect_norm_over_sigma": float(np.linalg.norm(reference["Y"][i] - base) / a.sigma)})
            print(json.dumps(rows[-1]), flush=True)
    result = {"command": "python " + " ".join(sys.argv), "resolution": a.resolution, "frames": a.frames,
              "trace": "cycle", "C10": a.C10, "g1": a.g1, "sigma_mm": a.sigma, "threads": a.threads,
              "reference": f"load steps <= {reference['dlam']:g}, no time limit", "rows": rows}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
