"""Study: the hierarchical filter (polynomial slave) assimilating every n-th frame, against the exact
posterior on the same frames, for a parameter set (default C10 with Mooney-Rivlin C01).

    python studies/assimilation_stride.py --out studies/results/study_assimilation_stride_C10_C01.json

Reuses the forward ensemble and recording of the calibration run with the same settings (runs
`calibrate.py`'s experiment without the restart filter and coverage if they are not cached), then
reruns the filter on frames n-1, 2n-1, ... for each stride and seed: no FE solve. Prints and writes
JSON: per stride and seed, each parameter's distance from the exact mean (exact stds) and std ratio.
"""
import argparse
import json
from pathlib import Path

import numpy as np
import torch

from torchfra.assimilation import hierarchical_filter
from torchfra.calibration.config import CalibrationConfig
from torchfra.calibration.exact import ensemble_stats
from torchfra.calibration.experiment import run_calibration
from torchfra.calibration.priors import parse_truth


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", action="append", default=None, metavar="NAME=KIND:A,B",
                   help="priors (default C10=lognormal:0.0061765,0.001123 and C01=uniform:0,0.003)")
    p.add_argument("--truth", action="append", default=None, metavar="NAME=VALUE",
                   help="the synthetic recording's values (default C10=0.0048, C01=0.001)")
    p.add_argument("--strides", default="1,5,10,20", help="comma-separated strides n (every n-th frame)")
    p.add_argument("--seeds", type=int, default=3, help="filter seeds per stride")
    p.add_argument("--runs-dir", default="runs")
    p.add_argument("--name", default="stride_study", help="run folder for the calibration it reuses")
    p.add_argument("--out", default=None, help="JSON file to write")
    a = p.parse_args(argv)
    params = a.param or ["C10=lognormal:0.0061765,0.001123", "C01=uniform:0,0.003"]
    truth = parse_truth(a.truth or ["C10=0.0048", "C01=0.001"])
    strides = [int(s) for s in a.strides.split(",")]
    cfg = CalibrationConfig(parameters=params, truth={k: v for k, v in truth.items() if k != "C10"},
                            truth_c10=truth.get("C10", 0.0048), restart=False, coverage_seeds=0)
    out = run_calibration(cfg, Path(a.runs_dir) / a.name, progress=True, runs_dir=a.runs_dir)
    pset, Q0, Y = out["parameter_set"], out["Q0"], out["Y_fe"]
    N, K = Y.shape[:2]
    Yt = torch.as_tensor(Y.reshape(N, K, -1))
    Zn = out["recording"].Z.reshape(K, -1)
    Z, r = torch.as_tensor(Zn), torch.full((Zn.shape[1],), cfg.noise ** 2, dtype=torch.float64)
    rows = []
    for n in strides:
        idx = np.arange(n - 1, K, n)
        exact = out["sweep"].posterior(Zn, cfg.noise ** 2, frames=idx).stats()
        for seed in range(a.seeds):
            res, slave = hierarchical_filter(Q0, Yt[:, idx], Z[idx], r, torch.Generator().manual_seed(cfg.filter_seed + seed),
                                             slave="polynomial", degree="auto")
            st = ensemble_stats(pset, res.Q[-1])
            rows.append({"stride": n, "frames": int(idx.size), "seed": seed, "slave_degree": slave.degree,
                         **{q: {"distance_in_exact_stds": (st[q]["mean"] - exact[q]["mean"]) / exact[q]["std"],
                                "std_ratio": st[q]["std"] / exact[q]["std"], "exact_std": exact[q]["std"]}
                            for q in pset.names}})
    result = {"parameters": params, "truth": truth, "members": N, "frames": K, "rows": rows}
    if a.out:
        Path(a.out).write_text(json.dumps(result, indent=1))
    for row in rows:
        print(row["stride"], row["seed"], {q: (round(row[q]["distance_in_exact_stds"], 2), round(row[q]["std_ratio"], 2))
                                           for q in pset.names})
    return result


if __name__ == "__main__":
    from torchfra.cli.run import run

    run(main)
