"""The sensitivity suite: one actuator solve and the exact sensitivities of its states."""
from __future__ import annotations

import numpy as np
import torch

from torchfra import fem
from torchfra.cli.bench.common import Config, clock, log


def sensitivity_suite(cfg: Config, args) -> dict:
    """One actuator solve and the exact sensitivities of its states to d parameters (C10, D1,
    E_fiber, C01, density, c_n, c_t: every candidate term switched on at its null), measured side by
    side; the fraction is what the sensitivities cost relative to the solve they come from."""
    from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
    from torchfra.fem.sensitivity import sensitivities

    model, info = build_actuator_model(ActuatorGeometry(resolution=args.mesh), material=fem.MooneyRivlin(),
                                       base="compliant", gravity=(0.0, -1.0, 0.0))
    model.finalize()
    load = np.arange(1, args.load_steps + 1) / args.load_steps
    theta = {"C10": torch.tensor([0.0062], dtype=torch.float64), "C01": torch.zeros(1, dtype=torch.float64),
             "D1": torch.tensor([1 / 6.2], dtype=torch.float64), "E_fiber": torch.tensor([31000.0], dtype=torch.float64),
             "density": torch.zeros(1, dtype=torch.float64), "c_n": torch.tensor([1e-4], dtype=torch.float64),
             "c_t": torch.tensor([1e-4], dtype=torch.float64)}

    def params_of(th):
        return {**th, "P": torch.full((1,), 0.022, dtype=torch.float64)}

    options = fem.NewtonOptions(stagnation_tol=1e-6)
    log(f"sensitivity: resolution {args.mesh}, {model.n_red} dofs, {args.load_steps} load steps, d = {len(theta)}")
    wall_solve, sol = clock(lambda: fem.solve(model, params_of(theta), load, options))
    wall_sens, S = clock(lambda: sensitivities(model, params_of, theta, sol))
    log(f"  solve {wall_solve:.1f} s ({int(sol.iterations[0])} iterations); sensitivities of {len(theta)} parameters "
        f"at {len(load)} load steps {wall_sens:.1f} s = {wall_sens / wall_solve:.0%} of the solve")
    return {"resolution": args.mesh, "dofs": int(model.n_red), "load_steps": args.load_steps, "parameters": list(theta),
            "solve_s": wall_solve, "newton_iterations": int(sol.iterations[0]), "sensitivities_s": wall_sens,
            "fraction_of_solve": wall_sens / wall_solve, "sensitivity_phases_s": S.timings}
