"""The actuator calibration experiment (paper §4.1) on top of the forward ensemble: recordings in,
the four posteriors of C10 out (hierarchical, hierarchical with nonlinear slave, restart, exact).

The pieces: :mod:`.config` (settings), :mod:`.frames` (frames tied to the model by their pressure),
:mod:`.synthetic` (recordings of the paper's experiment), :mod:`.exact` (the reference posterior),
:mod:`.restart` (the restart filter on torchrun ranks), :mod:`.coverage` (repeated noise draws).

Frames of a recording are tied to the model by their pressure: the body is hyperelastic and loaded
quasi-statically, so its state depends on the current pressure only, and the FE response at a
frame is the forward solution at load factor ``pressure / P_forward`` (interpolated between the
forward's load steps). A loading-unloading trace is therefore served by the same forward ensemble;
a frame whose pressure exceeds the forward's is refused (rerun the forward with a larger
``pressure``). Hysteresis, once modelled, will need the solver to follow the trace instead.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.assimilation.filters import PolynomialSlave
from torchfra.calibration.config import CalibrationConfig, config_dict
from torchfra.calibration.coverage import coverage_study
from torchfra.calibration.exact import ExactReference
from torchfra.calibration.forward import forward_config, forward_dir, parameter_set
from torchfra.calibration.frames import (
    ActuatorSolver,
    forecast_at_frames,
    load_factors,
    observation_layout,
    point_map,
    recording_operator,
)
from torchfra.calibration.restart import RestartRanks, _restart, restart_spline_check
from torchfra.calibration.synthetic import _load_recording
from torchfra.observation.recording import Recording


def run_calibration(config: CalibrationConfig, run_dir, progress: bool = True, runs_dir=None,
                    restart_threads: int | None = None, restart_ranks: RestartRanks | None = None) -> dict:
    """Run every filter on the recording; return everything the report needs (see scripts/calibrate.py).
    The forward ensemble is cached under ``runs_dir`` (default: the run folder's parent).
    ``restart_threads``: torch threads of the restart filter's FE re-solves (default: as set): when
    they run in this process alone, after the forward ensemble, the cores the other processes used
    are free for them (measured: a 20-member reduced re-solve at resolution 1 took 16.6 s on 1
    thread, 9.9 s on 2). ``restart_ranks``: a :class:`RestartRanks` whose ranks share those
    re-solves instead (faster: 231 s against 286 s on 2 threads for the main job's restart filter)."""
    from torchfra.assimilation import hierarchical_filter
    from torchfra.calibration.forward import run_forward

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    fwd_cfg = forward_config(config)
    pset = parameter_set(fwd_cfg)
    if pset.d > 6:
        raise ValueError(f"{pset.d} uncertain parameters ({pset.names}): calibrate at most 6 at once")
    # the recording first: a bad file is refused before any FE work on the forward ensemble
    rec, clean, truth = _load_recording(config, run_dir, progress)
    load_factors(rec, fwd_cfg.pressure)
    faces = ActuatorSolver(config.resolution, rec, fwd_cfg).faces
    fwd = run_forward(fwd_cfg, forward_dir(config, run_dir.parent if runs_dir is None else runs_dir), progress=progress)
    if restart_ranks is not None:  # the other ranks are past the forward ensemble: they wait for the restart filter
        restart_ranks.ready = True
    ok = fwd["status"] == "converged"
    if not ok.all():  # flagged, never silently replaced: the filters run on the converged members
        print(f"forward members {np.flatnonzero(~ok).tolist()} did not converge; they are left out of the filters")
    mesh = fwd["model"].mesh
    rec_op = recording_operator(mesh, rec, faces=faces)
    W = point_map(rec_op, fwd["operator"])
    lam = load_factors(rec, fwd_cfg.pressure)
    # the paper's tracked node; on a deck's model the point the forward ensemble moves most
    if not config.inp:
        point = rec_op.nearest_point(0.0, 40.0)
    elif rec.ragged:  # its frames see different points: the point that moves most at full load
        final = (W @ np.moveaxis(fwd["Y_steps"][ok][:, -1], 1, 0).reshape(W.shape[1], -1)).reshape(W.shape[0], -1, 2)
        point = int(np.argmax(np.linalg.norm(final, axis=-1).mean(axis=1)))
    slots, Z_obs = observation_layout(rec, point if rec.ragged else -1)  # ragged: each frame's own points + tracked
    Y_fe = forecast_at_frames(fwd["Y_steps"][ok], fwd["load_factors"], lam, W, slots)  # (N, K, P, 2)
    N, K, P, _ = Y_fe.shape
    if config.inp and not rec.ragged:  # the point the ensemble moves most in the last frame
        point = int(np.argmax(np.linalg.norm(Y_fe[:, -1], axis=-1).mean(axis=0)))
    Yt = torch.as_tensor(Y_fe.reshape(N, K, -1))
    # the members' coordinates (log C10 for the paper's prior); all of them for the restart filter
    Q0_all = (torch.log(fwd["params"]["C10"])[:, None] if not fwd_cfg.parameters
              else pset.coordinates({n: fwd["params"][n] for n in pset.names}))
    Q0 = Q0_all[torch.as_tensor(ok)]
    Z = torch.as_tensor(Z_obs.reshape(K, -1))
    r = torch.full((Z.shape[1],), config.noise ** 2, dtype=torch.float64)
    row = point if slots is None else P - 1  # the tracked point's column in Y_fe and Z
    tracked = [2 * row, 2 * row + 1]

    out: dict = {"config": config, "forward": fwd, "recording": rec, "clean": clean, "truth": truth,
                 "Y_fe": Y_fe, "observed": Z_obs, "Q0": Q0, "Q0_all": Q0_all, "parameter_set": pset,
                 "tracked_row": row, "tracked_point": rec_op.points[point].tolist(), "filters": {}}
    if not 1 <= config.assimilate_every <= K:
        raise ValueError(f"assimilate_every must lie in [1, {K}] (the recording's frames), got {config.assimilate_every}")
    hier = np.arange(config.assimilate_every - 1, K, config.assimilate_every)  # the hierarchical filters' frames
    for name, slave in (("hierarchical", "linear"), ("hierarchical_nonlinear", "polynomial")):
        res, s = hierarchical_filter(Q0, Yt[:, hier], Z[hier], r, torch.Generator().manual_seed(config.filter_seed),
                                     slave=slave, degree=config.degree, tracked=tracked)
        out["filters"][name] = {"result": res, "frames": hier}
        if slave == "polynomial":
            out["slave_degree"], out["slave_loo_rms_mm"] = s.degree, s.loo_rms
    t0 = time.perf_counter()
    ref = ExactReference(pset, Q0, Y_fe.reshape(N, K, -1), config.grid)
    Zn = Z.numpy()
    exact = ref.posterior(Zn, config.noise ** 2)
    out["filters"]["exact"] = {"posterior": exact, "frames": np.arange(K), "wall_s": time.perf_counter() - t0}
    out["data_fit"] = ref.data_fit(exact, Zn, config.noise ** 2)
    if hier.size != K:
        out["exact_hierarchical_frames"] = ref.posterior(Zn, config.noise ** 2, frames=hier)
    out["sweep_loo_error"] = ref.loo_error
    out["sweep_loo_error_rms"] = ref.loo_error_rms
    out["sweep"] = ref
    if config.restart:
        # The restart filter solves FE from the unloaded state itself, so its prior is every draw,
        # including forward members that did not converge (the forward's path, not the draw, failed).
        threads = torch.get_num_threads()
        out["restart_threads"] = restart_threads or threads
        torch.set_num_threads(out["restart_threads"])
        try:
            res, idx = _restart(config, run_dir, rec, lam, Q0_all, Z, r, tracked, progress,
                                fwd_dir=forward_dir(config, run_dir.parent if runs_dir is None else runs_dir),
                                ranks=restart_ranks, slots=slots)
        finally:
            torch.set_num_threads(threads)
            if restart_ranks is not None:
                restart_ranks.stop()
        if restart_ranks is not None and restart_ranks.r.parallel:
            out["restart_ranks"] = restart_ranks.r.size
        out["filters"]["restart"] = {"result": res, "frames": idx}
        out["exact_restart_frames"] = ref.posterior(Zn, config.noise ** 2, frames=idx)
        out["restart_spline_check"] = restart_spline_check(config, res, idx, ref, Q0_all, Z, r, tracked)
    # How far each hierarchical slave's forecast is from the FE map (the exact reference's map through
    # the FE members) at the ensemble it forecast for: the slave's linearization error along the way.
    for name in ("hierarchical", "hierarchical_nonlinear"):
        res = out["filters"][name]["result"]
        err = []
        for j, k in enumerate(hier):
            fe = ref.predict(res.Q[j].numpy())[:, k, :][:, tracked]  # (N, 2)
            err.append(np.sqrt(((res.Y_tracked[j].numpy() - fe) ** 2).mean(0)))
        out["filters"][name]["slave_error_tracked"] = np.asarray(err)  # (K, 2) RMS over members, mm
    out["direct_fe_check"] = _direct_fe_check(config, run_dir, out, rec, lam, tracked, point)
    if clean is not None and config.coverage_seeds > 0:
        restart = (Q0_all, out["filters"]["restart"]["frames"]) if config.restart else None
        out["coverage"] = coverage_study(config, Q0, Yt, ref, clean.reshape(K, -1), truth, out["slave_degree"], restart,
                                         hier)
    return out


def _direct_fe_check(config, run_dir: Path, out: dict, rec: Recording, lam, tracked, row) -> dict:
    """One FE solve at each hierarchical filter's final posterior mean (of the coordinates), observed
    at the last frame, against that filter's forecast (its slave's map at the same point) and the
    exact reference's map through the FE members: checks both maps directly, not only through the
    members. Cached in the run folder."""
    names = ("hierarchical", "hierarchical_nonlinear")
    k_top = int(np.argmax(lam))  # the frame of highest pressure (a cycled trace ends unloaded)
    pset = out["parameter_set"]
    q = np.stack([out["filters"][n]["result"].Q[-1].mean(0).numpy() for n in names])  # (2, d)
    if pset.d == 1:
        q = q[:, 0]  # the one-parameter record keeps its shape
    path = run_dir / "direct_fe_check.npz"
    saved = dict(np.load(path, allow_pickle=False)) if path.exists() else None
    if (saved is not None and saved["q"].shape == q.shape and np.allclose(saved["q"], q, rtol=0, atol=1e-12)
            and int(saved["k"]) == k_top):
        fe = saved["fe"]
    else:
        solver = ActuatorSolver(config.resolution, rec, forward_config(config))
        Qm = torch.as_tensor(q.reshape(len(names), -1))
        sol = fem.solve(solver.model, solver.params_q(Qm), [float(lam[k_top])], solver.options())
        if not sol.converged.all():
            return {"skipped": f"the direct FE solve did not converge ({ {n: v.tolist() for n, v in pset.natural(Qm).items()} })"}
        fe = solver.operator(sol.u[:, -1, : solver.mesh.n_nodes]).numpy()[:, row]  # (2, 2)
        np.savez(path, q=q, fe=fe, k=k_top)
    res = {}
    Yfe = torch.as_tensor(out["Y_fe"].reshape(*out["Y_fe"].shape[:2], -1))
    for j, n in enumerate(names):
        Qm = torch.as_tensor(np.asarray(q[j], dtype=np.float64).reshape(1, -1))
        # the slave's map at q without any member's own residual: the affine least-squares fit of
        # Eq. 23 (= degree 1, R_q = 0) or the polynomial of the nonlinear slave
        slave = PolynomialSlave(out["Q0"], Yfe, 1 if n == "hierarchical" else out["slave_degree"])
        pred = slave.map(Qm, k_top)[0, tracked].numpy()
        spline = out["sweep"].predict(Qm.numpy())[0, k_top, tracked]
        at = {p: float(v[0]) for p, v in pset.natural(Qm).items()} if pset.d > 1 else {"C10": float(np.exp(q[j]))}
        res[n] = {**at, "fe_tracked_mm": fe[j].tolist(), "slave_map_tracked_mm": pred.tolist(),
                  "spline_tracked_mm": spline.tolist(), "slave_minus_fe_mm": (pred - fe[j]).tolist(),
                  "spline_minus_fe_mm": (spline - fe[j]).tolist(), "frame": int(rec.frames[k_top])}
    return res



# --- the headline of a calibration's summary.json -------------------------------------------------------------

# below these, the filters' answers are not to be trusted, whatever they say (see docs/calibration.md#the-headline)
TRUSTED_MEMBERS = 20  # ensemble members: the sample covariances of Eqs. 21-23 need tens of them
PRIOR_OUTSIDE_GRID = 0.01  # prior mass outside the members' span, where the exact posterior's map extrapolates
EXACT_STDS_OFF = 3.0  # a filter's mean this many exact posterior stds from the exact mean disagrees with it
HIERARCHICAL = ("hierarchical", "hierarchical_nonlinear", "restart")


def rounded(mean: float, std: float) -> str:
    """``mean +- std`` with the std to two significant digits and the mean to the same decimal place.

    Examples
    --------
    >>> rounded(0.00480012, 1.234e-5)
    '0.004800 +- 0.000012'
    """
    if not (math.isfinite(mean) and math.isfinite(std)) or std <= 0:
        return f"{mean:.6g} +- {std:.2g}"
    place = max(0, 1 - math.floor(math.log10(std)))  # decimals that keep two significant digits of std
    if place > 12:
        return f"{mean:.3e} +- {std:.2e}"
    return f"{mean:.{place}f} +- {std:.{place}f}"


def headline(summary: dict) -> dict:
    """How sure a calibration is, in one line and its parts: each parameter's exact posterior (mean +- std
    in its unit), the filter to report (the one nearest the exact posterior on its frames) with its
    distance from it in exact stds, and the reasons not to trust the filters (too few members, prior mass
    outside the exact posterior's grid, every filter more than 3 exact stds off, a data-fit refusal).

    Parameters
    ----------
    summary : dict
        A calibration's ``summary.json`` as :func:`torchfra.report.calibration.write_calibration_outputs`
        writes it.

    Returns
    -------
    dict
        ``text`` (the line), ``exact`` (per parameter: mean, std, unit), ``report`` (a filter's name or None),
        ``agreement_in_exact_stds`` (per filter: the largest distance over the parameters), ``trusted``,
        ``warnings`` (why the run is not to be trusted) and ``notes`` (filters too far off to report).
    """
    names = summary["parameters"]
    rows, comp = summary["filters"], summary.get("comparison", {})
    units = {p: summary.get("prior", {}).get(p, {}).get("unit", "") for p in names}
    exact = {p: {"mean": rows["exact"][p]["mean"], "std": rows["exact"][p]["std"], "unit": units[p]} for p in names}

    def distance(name):
        c = comp.get(name, {})
        per = [c] if len(names) == 1 else [c.get(p, {}) for p in names]
        d = [abs(x["distance_from_exact_mean_in_exact_stds"]) for x in per
             if x.get("distance_from_exact_mean_in_exact_stds") is not None]
        return max(d) if d else None

    agree = {n: distance(n) for n in HIERARCHICAL if n in rows and distance(n) is not None}
    report = min(agree, key=agree.get) if agree else None
    warnings = []
    fit = summary.get("data_fit", {"ok": True})
    if not fit.get("ok", True):
        warnings.append("no calibration result: the data do not fit the model and prior (" + "; ".join(
            fit.get("reasons", [])) + ")")
    members = summary.get("members_in_hierarchical_filters", summary.get("members", 0))
    outside = rows["exact"].get("prior_mass_outside_grid", 0.0) or 0.0
    if members < TRUSTED_MEMBERS:
        warnings.append(f"{members} members are too few for the filters to be trusted (at least {TRUSTED_MEMBERS}: "
                        "their sample covariances need tens of members); rerun with --members 100")
    if outside > PRIOR_OUTSIDE_GRID:
        warnings.append(f"{100 * outside:.1f} % of the prior lies outside the members' span, where the exact "
                        "posterior extrapolates the FE map; use more --members")
    off = {n: d for n, d in agree.items() if d > EXACT_STDS_OFF}
    notes = []
    if agree and len(off) == len(agree):
        warnings.append("every filter is more than 3 exact stds from the exact posterior ("
                        + ", ".join(f"{n} {d:.1f}" for n, d in off.items()) + "): report the exact posterior")
    elif off:
        notes.append(", ".join(f"{n} {d:.1f}" for n, d in off.items()) + " exact stds off: not to be reported")
    parts = [f"{p} = {rounded(e['mean'], e['std'])} {e['unit']}".rstrip() for p, e in exact.items()]
    text = "; ".join(parts) + " (exact posterior)"
    if report is not None:
        text += f"; filter to report: {report}, {agree[report]:.2f} exact stds from it"
    text += "".join(f"; {n}" for n in notes)
    if warnings:
        text += "; NOT TRUSTED: " + "; ".join(warnings)
    return {"text": text, "exact": exact, "report": report, "agreement_in_exact_stds": agree,
            "trusted": not warnings, "warnings": warnings, "notes": notes}


def applicable_config(config: CalibrationConfig, synthetic: bool, fibers: bool = True) -> dict:
    """The settings a run used, without those that do not apply to it: a recording file's run has no
    synthetic-recording settings (truth, noise seed, points, frames, coverage study), a deck's no actuator
    settings, a model without fibers no fiber stiffness.

    Parameters
    ----------
    config : CalibrationConfig
        The run's settings.
    synthetic : bool
        Whether the recording was made by the run (``config.recording`` None).
    fibers : bool
        Whether the model has fibers (a deck may not).

    Returns
    -------
    dict
        The JSON-ready settings.
    """
    out = config_dict(config)
    if not synthetic:
        for k in ("truth_c10", "truth", "noise_seed", "points", "frames", "coverage_seeds"):
            out.pop(k, None)
    if not config.inp:
        for k in ("inp", "camera", "face"):
            out.pop(k, None)
    if not fibers:
        out["fixed"] = [f for f in out.get("fixed", []) if not f.split("=")[0].strip().startswith("E_fiber")]
    return out
