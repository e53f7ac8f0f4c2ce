"""Coverage of the filters' posteriors over repeated noise draws of one recording."""
from __future__ import annotations

import numpy as np
import torch

from torchfra.calibration.exact import ExactReference, ensemble_stats


def coverage_study(config, Q0, Yt, ref: ExactReference, clean, truth: dict, out_degree, restart=None,
                   hier=None) -> dict:
    """Re-draw the recording's noise ``coverage_seeds`` times (no FE solve) and count, per parameter,
    how often each filter's 10-90 % interval holds the truth (expected 80 %; binomial std 9 % at 20
    seeds).

    ``restart = (Q0_all, frames)`` adds the restart filter on those frames, its FE solves replaced by
    the exact reference's map (checked against the FE restart run by :func:`restart_spline_check`),
    and the exact posterior on the same frames. ``hier``: the hierarchical filters' frames (default
    all; otherwise the exact posterior on those frames is added)."""
    from torchfra.assimilation import hierarchical_filter, sequential_filter

    pset = ref.pset
    r = torch.full((clean.shape[1],), config.noise ** 2, dtype=torch.float64)
    names = ["hierarchical", "hierarchical_nonlinear", "exact"]
    K = clean.shape[0]
    hier = np.arange(K) if hier is None else np.asarray(hier)
    if hier.size != K:
        names += ["exact_hierarchical_frames"]
    if restart is not None:
        names += ["restart", "exact_restart_frames"]
    rows = {k: [] for k in names}
    for s in range(config.coverage_seeds):
        rng = np.random.default_rng(10_000 + s)
        Zs = clean + config.noise * rng.standard_normal(clean.shape)
        Zt = torch.as_tensor(Zs)
        for name, slave in (("hierarchical", "linear"), ("hierarchical_nonlinear", "polynomial")):
            res, _ = hierarchical_filter(Q0, Yt[:, hier], Zt[hier], r, torch.Generator().manual_seed(config.filter_seed + s),
                                         slave=slave, degree=out_degree)
            rows[name].append(ensemble_stats(pset, res.Q[-1]))
        rows["exact"].append(ref.posterior(Zs, config.noise ** 2).stats())
        if hier.size != K:
            rows["exact_hierarchical_frames"].append(ref.posterior(Zs, config.noise ** 2, frames=hier).stats())
        if restart is not None:
            Q0_all, idx = restart
            res = sequential_filter(Q0_all, ref.forecaster(idx), Zt[idx], r,
                                    torch.Generator().manual_seed(config.filter_seed + 100 + s))
            rows["restart"].append(ensemble_stats(pset, res.Q[-1]))
            rows["exact_restart_frames"].append(ref.posterior(Zs, config.noise ** 2, frames=idx).stats())
    out = {}
    for name, st in rows.items():
        per = {}
        for p in pset.names:
            inside = [x[p]["p10"] <= truth[p] <= x[p]["p90"] for x in st]
            per[p] = {"coverage_80": float(np.mean(inside)), "seeds": len(st), "inside": inside,
                      "mean_of_means": float(np.mean([x[p]["mean"] for x in st])),
                      "mean_std": float(np.mean([x[p]["std"] for x in st]))}
        # one parameter: its entries at the top (the record's keys); several: one entry per parameter
        out[name] = per[pset.names[0]] if pset.d == 1 else {"seeds": len(st), **per}
    return out

