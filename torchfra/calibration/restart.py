"""The restart EnKF: every analysis restarts the FE solve of every member from its last state at the new
parameters (paper Eq. 23), shared over torchrun ranks (:class:`RestartRanks`), checkpointed per analysis."""
from __future__ import annotations

import json
import pickle
import re
import warnings
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.calibration.config import CalibrationConfig, config_dict, recording_digest
from torchfra.calibration.exact import ExactReference, ensemble_stats
from torchfra.calibration.forward import forward_config
from torchfra.calibration.frames import ActuatorSolver


class RestartForecaster:
    """Forecast observations by re-solving every member at the frame's pressure with its current
    parameters, warm-started from its own previous equilibrium (the state-export variant of the
    paper §3.3). Counts FE solves (member x assimilation step) and Newton iterations.

    ``reduced``: a ``fem.reduced.HyperReducedModel`` of the same model (the forward ensemble's):
    members are then re-solved on its basis (hyper-reduced Newton polished on the full residual,
    ``fem.reduced.solve_reduced``), warm-started from their reduced states; a member whose reduced
    solve fails is solved in full from the unloaded state and continues from its projection.

    ``ranks``: a :class:`RestartRanks` of a torch.distributed group (torchrun, ``calibrate.py
    --workers``): every forecast's members are then shared out round robin over the ranks, each
    re-solves its share (:func:`serve_restart` on ranks 1..), and rank 0 gathers them."""

    def __init__(self, solver: ActuatorSolver, lam: np.ndarray, N: int, frames=None, reduced=None, ranks=None,
                 slots=None):
        self.solver, self.lam = solver, lam
        self.frames = np.arange(len(lam)) if frames is None else np.asarray(frames)
        self.slots = None if slots is None else torch.as_tensor(slots)  # (steps, J): a ragged recording's points
        self.reduced = reduced
        self.ranks = ranks
        pack = fem.newton._Packing(solver.model)
        size = pack.size if reduced is None else reduced.basis.size
        self.x = torch.zeros(N, size, dtype=torch.float64)
        self.lam_now = np.zeros(N)
        self.fe_solves = 0
        self.newton_iterations = 0
        self.full_fallbacks = 0

    def state(self) -> dict:
        return {"x": self.x, "lam_now": torch.as_tensor(self.lam_now), "fe_solves": self.fe_solves,
                "newton_iterations": self.newton_iterations, "reduced": self.reduced is not None}

    def load_state(self, s: dict) -> bool:
        """Take a checkpointed state; False (nothing taken) if it was made by the other kind of solve."""
        if bool(s.get("reduced", False)) != (self.reduced is not None) or tuple(s["x"].shape) != tuple(self.x.shape):
            return False
        self.x, self.lam_now = s["x"], s["lam_now"].numpy()
        self.fe_solves, self.newton_iterations = s["fe_solves"], s["newton_iterations"]
        return True

    def __call__(self, Q: torch.Tensor, k: int) -> torch.Tensor:
        s, N = self.solver, len(Q)
        target = float(self.lam[k])
        if self.reduced is not None and np.ptp(self.lam_now) > 0:
            raise RuntimeError("restart filter: members are at different loads; restart the filter")
        params = s.params_q(Q)
        lam_now = torch.as_tensor(self.lam_now, dtype=torch.float64)
        if self.ranks is not None and self.ranks.r.parallel:
            step = self.ranks.solve(params, self.x, lam_now, target)
        else:
            step = restart_solve(s, self.reduced, params, self.x, lam_now, target)
        u, x, iterations, fallbacks, failed = step
        failed = np.flatnonzero(failed)
        if failed.size:
            raise RuntimeError(f"restart filter: members {failed.tolist()} did not converge at frame {self.frames[k]} "
                               f"({ {n: v[failed].tolist() for n, v in s.pset.natural(Q).items()} }); the run can be "
                               "resumed after a fix")
        self.fe_solves += N
        self.newton_iterations += int(iterations)
        self.full_fallbacks += int(fallbacks)
        self.x, self.lam_now = x, np.full(N, target)
        Y = s.operator(u[:, : s.mesh.n_nodes])  # (N, P, 2) at every point of the recording
        if self.slots is not None:  # this frame's points only; an empty slot forecasts 0 (never observed)
            ids = self.slots[k]
            Y = Y[:, ids.clamp(min=0)] * (ids >= 0)[None, :, None]
        return Y.reshape(N, -1)


def restart_solve(solver: ActuatorSolver, reduced, params: dict, x: torch.Tensor, lam_now: torch.Tensor,
                  target: float):
    """One restart step of the members ``params`` (name -> (n,)) from their states ``x`` at load
    factors ``lam_now`` to ``target``: -> displacements (n, nodes, 3), new states, Newton
    iterations, full-Newton fallbacks, failed (n,) bool. Every member is solved on its own (a
    batch, or its share of one on a rank, gives each member the same answer)."""
    n = x.shape[0]
    if n == 0:
        return (torch.zeros(0, solver.model.n_nodes, 3, dtype=torch.float64), x.clone(), 0, 0,
                np.zeros(0, dtype=bool))
    if reduced is None:
        sol = fem.solve(solver.model, params, [1.0], solver.options(initial_increment=1.0),
                        start=fem.WarmStart(x, lam_now.numpy(), np.full(n, target)))
        return sol.u[:, -1], sol.x_last, int(sol.iterations.sum()), 0, sol.status != "converged"
    from torchfra.fem.reduced import solve_reduced

    rs = solve_reduced(reduced, params, [target], start=(x, float(lam_now[0])), check=False)
    u = rs.u[:, -1].clone()
    q = rs.a[:, -1] @ reduced.basis.V
    iterations = int(rs.iterations.sum() + rs.polish.sum())
    failed = np.flatnonzero(rs.status != "converged")
    bad = np.zeros(n, dtype=bool)
    if failed.size:  # Newton on the full model from the unloaded state, then on the basis again
        sol = fem.solve(solver.model, {k: v[failed] for k, v in params.items()}, [target], solver.options())
        bad[failed[sol.status != "converged"]] = True
        u[failed] = sol.u[:, -1]
        q[failed] = sol.a[:, -1] @ reduced.basis.V
        iterations += int(sol.iterations.sum())
    return u, q, iterations, int(failed.size), bad


class RestartRanks:
    """Rank 0's side of the restart filter on a torch.distributed group: :meth:`start` (the reduced
    model and the parameter names to every rank), :meth:`solve` per forecast, :meth:`stop`. Ranks
    1.. run :func:`serve_restart` after the forward ensemble and leave at the stop. Only tensors
    travel (float64 and the bytes of the array-only ``reduced_model.npz``); nothing is pickled."""

    STOP, START, SOLVE = 0.0, 1.0, 2.0

    def __init__(self, r):
        self.r = r
        self.ready = False  # set once the forward ensemble is done: the other ranks then wait for a header
        self.busy = False  # inside a solve: a stop now would not match what the other ranks wait for
        self.stopped = False
        self.names: list[str] = []
        self.solver, self.reduced = None, None  # rank 0's own share is solved with these (set by start)

    def _header(self, cmd: float, value: float = 0.0) -> None:
        from torchfra.runtime.distributed import broadcast_tensor

        broadcast_tensor(torch.tensor([cmd, value], dtype=torch.float64), self.r)

    def start(self, solver: ActuatorSolver, reduced, reduced_file: Path | None, names: list[str]) -> None:
        from torchfra.runtime.distributed import broadcast_tensor

        self.solver, self.reduced = solver, reduced
        self._header(self.START)
        data = reduced_file.read_bytes() if reduced_file is not None and reduced_file.exists() else b""
        broadcast_tensor(torch.frombuffer(bytearray(data), dtype=torch.uint8) if data else torch.zeros(0, dtype=torch.uint8),
                         self.r, dtype=torch.uint8)
        meta = json.dumps({"names": list(names)}).encode()
        broadcast_tensor(torch.frombuffer(bytearray(meta), dtype=torch.uint8), self.r, dtype=torch.uint8)
        self.names = list(names)

    def solve(self, params: dict, x: torch.Tensor, lam_now: torch.Tensor, target: float):
        from torchfra.runtime.distributed import broadcast_tensor, recv_tensors

        self.busy = True
        self._header(self.SOLVE, target)
        P = torch.stack([params[n] for n in self.names], dim=1)
        for t in (P, x, lam_now):
            broadcast_tensor(t, self.r)
        parts = {0: _restart_share(self.solver, self.reduced, self.names, P, x, lam_now, target, self.r)}
        for src in range(1, self.r.size):
            parts[src] = recv_tensors(5, src)
        n = x.shape[0]
        u = torch.empty(n, *parts[0][0].shape[1:], dtype=torch.float64)
        x_new = torch.empty_like(x)
        failed = np.zeros(n, dtype=bool)
        iterations = fallbacks = 0
        for src, (u_s, x_s, it, fb, bad) in parts.items():
            rows = torch.arange(src, n, self.r.size)
            u[rows], x_new[rows], failed[rows.numpy()] = u_s, x_s, bad.numpy() > 0
            iterations += int(it)
            fallbacks += int(fb)
        self.busy = False
        return u, x_new, iterations, fallbacks, failed

    def stop(self) -> None:
        """The stop to the other ranks, once, when they wait for it (the forward ensemble done, no
        exchange cut short: otherwise the group is ended by the launcher or the caller)."""
        if self.r.parallel and self.ready and not self.busy and not self.stopped:
            self._header(self.STOP)
            self.stopped = True


def _restart_share(solver, reduced, names, P, x, lam_now, target, r) -> list[torch.Tensor]:
    rows = torch.arange(r.rank, x.shape[0], r.size)
    params = {n: P[rows, j] for j, n in enumerate(names)}
    u, x_new, it, fb, bad = restart_solve(solver, reduced, params, x[rows], lam_now[rows], target)
    return [u, x_new, torch.tensor(float(it)), torch.tensor(float(fb)), torch.as_tensor(bad, dtype=torch.float64)]


def serve_restart(config, r) -> int:
    """Ranks 1..: after the forward ensemble, re-solve this rank's share of every restart forecast
    rank 0 sends, until its stop. Returns the number of forecasts served."""
    import io

    from torchfra.fem.reduced import HyperReducedModel
    from torchfra.runtime.distributed import broadcast_tensor, send_tensors

    solver, reduced, names, served = None, None, [], 0
    while True:
        cmd, value = broadcast_tensor(None, r).tolist()
        if cmd == RestartRanks.STOP:
            return served
        if cmd == RestartRanks.START:
            data = broadcast_tensor(None, r, dtype=torch.uint8).numpy().tobytes()
            names = json.loads(broadcast_tensor(None, r, dtype=torch.uint8).numpy().tobytes())["names"]
            solver = ActuatorSolver(config.resolution, None, forward_config(config))
            reduced = None
            if data:
                with np.load(io.BytesIO(data), allow_pickle=False) as f:
                    reduced = HyperReducedModel.from_arrays(solver.model, {k: f[k] for k in f.files})
            continue
        P, x, lam_now = (broadcast_tensor(None, r) for _ in range(3))
        send_tensors(_restart_share(solver, reduced, names, P, x, lam_now, value, r), 0)
        served += 1


class CheckpointError(ValueError):
    """A restart checkpoint that cannot be read safely; the message names the file and the way out."""


def read_restart_checkpoint(path: Path) -> dict:
    """The restart filter's checkpoint, read with ``weights_only=True``: it holds tensors, numbers,
    strings and plain containers only, so a file holding anything else (a planted pickle, a
    checkpoint of an older version) is refused before any of it runs."""
    why = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch warns about pickle protocols before refusing
            saved = torch.load(path, weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"Unsupported [^.\n]*", str(exc))
        why = f"it holds more than tensors and plain data: {found.group(0) if found else 'not a torch checkpoint'}"
    except (RuntimeError, EOFError, ValueError) as exc:
        why = f"it is empty or damaged: {type(exc).__name__}"
    else:
        if (not isinstance(saved, dict) or not {"config", "recording", "result", "generator", "forecaster"} <= set(saved)
                or not isinstance(saved["config"], dict) or not isinstance(saved["result"], dict)):
            why = "it lacks the restart filter's entries"
    if why is not None:
        raise CheckpointError(f"{path}: not a restart checkpoint this version reads safely ({why}); delete it to "
                              "start the restart filter over")
    return saved


RESTART_KEYS = ("members", "resolution", "seed", "recording", "truth_c10", "noise", "noise_seed", "points", "frames",
                "filter_seed", "restart_every", "pressure", "load_steps", "parameters", "fixed",
                "truth")  # what shapes the restart filter


def _forward_reduction(solver: ActuatorSolver, fwd_dir):
    """The forward ensemble's reduced model (``reduced_model.npz``) for the restart filter, or None."""
    from torchfra.fem.reduced import HyperReducedModel

    path = None if fwd_dir is None else Path(fwd_dir) / "reduced_model.npz"
    if path is None or not path.exists():
        return None
    with np.load(path, allow_pickle=False) as f:
        return HyperReducedModel.from_arrays(solver.model, {k: f[k] for k in f.files})


def _restart(config, run_dir, rec, lam, Q0, Z, r, tracked, progress, fwd_dir=None, ranks=None, slots=None):
    """Restart filter on every ``restart_every``-th frame, checkpointed after each step; its FE
    re-solves shared out over the ranks of ``ranks`` (a :class:`RestartRanks`) when given."""
    from torchfra.assimilation import FilterResult, sequential_filter

    idx = np.arange(config.restart_every - 1, rec.n_frames, config.restart_every)
    ckpt = run_dir / "restart_checkpoint.pt"
    solver = ActuatorSolver(config.resolution, rec, forward_config(config))
    fc = RestartForecaster(solver, lam[idx], Q0.shape[0], rec.frames[idx], reduced=_forward_reduction(solver, fwd_dir),
                           ranks=ranks, slots=None if slots is None else slots[idx])
    if ranks is not None and ranks.r.parallel:
        ranks.start(solver, fc.reduced, None if fwd_dir is None else Path(fwd_dir) / "reduced_model.npz",
                    list(solver.params_q(Q0[:1]).keys()))
    gen = torch.Generator().manual_seed(config.filter_seed + 100)
    result = None
    if ckpt.exists():
        saved = read_restart_checkpoint(ckpt)
        now = config_dict(config)
        default = config_dict(CalibrationConfig())
        if (all(saved["config"].get(k, default[k]) == now[k] for k in RESTART_KEYS) and saved.get("recording") == recording_digest(rec)
                and torch.equal(saved["result"]["Q"][0], Q0)):
            if fc.load_state(saved["forecaster"]):
                result = FilterResult.from_dict(saved["result"])
                gen.set_state(saved["generator"])

    def checkpoint(res: FilterResult, g: torch.Generator) -> None:
        res.fe_solves, res.newton_iterations = fc.fe_solves, fc.newton_iterations
        tmp = ckpt.with_suffix(".tmp")
        torch.save({"config": config_dict(config), "recording": recording_digest(rec), "result": res.to_dict(),
                    "generator": g.get_state(),
                    "forecaster": fc.state()}, tmp)
        tmp.replace(ckpt)

    res = sequential_filter(Q0, fc, Z[idx], r, gen, tracked=tracked, result=result, checkpoint=checkpoint,
                            progress="restart filter (FE solves)" if progress else None)
    res.fe_solves, res.newton_iterations = fc.fe_solves, fc.newton_iterations
    return res, idx


def restart_spline_check(config, res, idx, ref: ExactReference, Q0, Z, r, tracked) -> dict:
    """How well the exact reference's map through the FE members (the spline of a one-parameter
    sweep) stands in for the restart filter's FE solves: its prediction at every ensemble the FE
    restart filter forecast for (the tracked entries, all members, all steps) against the FE
    forecasts, and the same filter (same prior, same generator seed) rerun with the map in place of
    the FE solves against the FE run's posterior (per parameter)."""
    from torchfra.assimilation import sequential_filter

    pset = ref.pset
    err = max(float(np.abs(ref.predict(res.Q[k].numpy())[:, idx[k]][:, tracked] - res.Y_tracked[k].numpy()).max())
              for k in range(res.steps))
    twin = sequential_filter(Q0, ref.forecaster(idx), Z[idx], r, torch.Generator().manual_seed(config.filter_seed + 100))
    fe, spl = ensemble_stats(pset, res.Q[-1]), ensemble_stats(pset, twin.Q[-1])
    out = {"max_forecast_error_tracked_mm": err, "steps": res.steps,
           "log_evidence_difference": twin.log_evidence - res.log_evidence, "by_parameter": {}}
    for n in pset.names:
        out["by_parameter"][n] = {"spline_restart": spl[n], "fe_restart": fe[n],
                                  "mean_difference_in_fe_stds": (spl[n]["mean"] - fe[n]["mean"]) / fe[n]["std"],
                                  "std_ratio": spl[n]["std"] / fe[n]["std"]}
    if pset.d == 1:  # the one-parameter record keeps its keys
        n = pset.names[0]
        b = out["by_parameter"][n]
        out.update({f"spline_restart_{n}": b["spline_restart"], f"fe_restart_{n}": b["fe_restart"],
                    "mean_difference_in_fe_stds": b["mean_difference_in_fe_stds"], "std_ratio": b["std_ratio"]})
    return out

