"""The actuator calibration experiment (paper §4.1) on top of the forward ensemble: recordings in,
the four posteriors of C10 out (hierarchical, hierarchical with nonlinear slave, restart, exact).

Frames of a recording are tied to the model by their pressure: the body is hyperelastic and loaded
quasi-statically, so its state depends on the current pressure only, and the FE response at a
frame is the forward solution at load factor ``pressure / P_forward`` (interpolated between the
forward's load steps). A loading-unloading trace is therefore served by the same forward ensemble;
a frame whose pressure exceeds the forward's is refused (rerun the forward with a larger
``pressure``). Hysteresis, once modelled, will need the solver to follow the trace instead.
"""
from __future__ import annotations

import hashlib
import json
import math
import pickle
import re
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch

from torchfra import fem
from torchfra.actuator.deck import observed_faces
from torchfra.assimilation.filters import PolynomialSlave
from torchfra.forward import ForwardConfig, forward_model, parameter_set, with_deck
from torchfra.observation.operator import ObservationError, ObservationOperator, frame_times, visible_faces
from torchfra.observation.recording import Recording, RecordingError


@dataclass
class CalibrationConfig:
    """Settings of a calibration run (units mm, MPa). ``recording`` None makes a synthetic one at
    ``truth_c10`` with noise N(0, noise^2) per component (the paper's experiment)."""

    members: int = 100
    resolution: int = 1
    seed: int = 0
    recording: str | None = None
    truth_c10: float = 0.0048
    noise: float = 1.0
    noise_seed: int = 1
    points: str = "nodes"  # synthetic recordings: "nodes" or a DIC grid spacing in mm, e.g. "2.0"
    frames: int = 100
    filter_seed: int = 2
    degree: int | str = "auto"  # polynomial slave: a degree, or "auto" (smallest leave-one-out error)
    restart: bool = True
    restart_every: int = 10
    coverage_seeds: int = 20
    grid: int = 4000
    pressure: float = 0.022  # MPa at t = 1 of the synthetic recording; the forward ensemble's range
    load_steps: int = 20
    # any parameter set (torchfra.priors): prior specs "NAME=KIND:A,B" and fixed "NAME=VALUE" (empty:
    # the paper's prior of C10); ``truth``: values of the synthetic recording's uncertain parameters
    # other than C10 (``truth_c10``), a missing one at its null value
    parameters: list = field(default_factory=list)
    fixed: list = field(default_factory=list)
    truth: dict = field(default_factory=dict)
    # the hierarchical filters assimilate every n-th frame (the last included); 1: every frame, the
    # paper's. Fewer sequential updates keep the ensemble's spread along a weakly constrained
    # direction (scripts/study_assimilation_stride.py); they are compared with the exact posterior
    # on the same frames
    assimilate_every: int = 1
    # the user's own model (torchfra.forward.ForwardConfig): an Abaqus/CalculiX deck, the camera's
    # side and the observed surface; ``pressure`` is then the deck's
    inp: str = ""
    camera: str = "+x"
    face: str = ""


SEED = CalibrationConfig()  # --config seed: the paper's numerical experiment (§4.1)


def forward_dir(config: CalibrationConfig, runs_dir) -> Path:
    """Where the forward ensemble of ``config`` is cached: ``<runs>/forward_cache/<settings>/``, shared by
    every calibration run with the same prior, mesh and load (a new recording needs no new FE work)."""
    f = forward_config(config)
    method = "" if f.method == "full" else f"_{f.method}"
    prior = f"_prior{parameter_set(f).key()}" if f.parameters else ""  # the paper's prior keeps its old name
    model = (f"deck{f.inp_digest[:10]}{f.camera}{f.face}" if f.inp else
             f"mesh{f.resolution}")  # a deck's cache is keyed by what it holds, not by its path
    return Path(runs_dir) / "forward_cache" / (f"{model}_N{f.members}_seed{f.seed}_P{f.pressure:g}"
                                               f"_steps{f.load_steps}{method}{prior}")


def forward_config(config: CalibrationConfig) -> ForwardConfig:
    """The forward ensemble's settings (a deck read: its digest and pressure, see ``with_deck``)."""
    return with_deck(ForwardConfig(members=config.members, resolution=config.resolution, seed=config.seed,
                                   pressure=config.pressure, load_steps=config.load_steps,
                                   parameters=list(config.parameters), fixed=list(config.fixed),
                                   inp=config.inp, camera=config.camera, face=config.face))


def truth_values(config: CalibrationConfig) -> dict[str, float]:
    """The synthetic recording's value of every uncertain parameter (C10 from ``truth_c10``, the
    others from ``truth`` or their null value)."""
    pset = parameter_set(forward_config(config))
    given = {"C10": config.truth_c10, **config.truth} if "C10" in pset.names else dict(config.truth)
    Q = pset.values(given, where="truth of the synthetic recording")  # checks every value against its prior
    return {n: float(given[n]) if n in given else float(p.natural(Q[:, j])[0]) for j, (n, p) in
            enumerate(zip(pset.names, pset.priors))}


def recording_operator(mesh, rec: Recording, tol: float = 1e-3, faces=None) -> ObservationOperator:
    """Match the recording's points to the camera-visible face (or ``faces``) by reference
    coordinates; a point off the face raises an error naming its id."""
    faces = visible_faces(mesh, (1.0, 0.0, 0.0)) if faces is None else faces
    try:
        return ObservationOperator(mesh, faces, points=rec.X, point_ids=rec.point_ids, tol=tol)
    except ObservationError as exc:
        raise RecordingError(f"{rec.source}: {exc}") from exc


def load_factors(rec: Recording, pressure_max: float) -> np.ndarray:
    lam = rec.pressure / pressure_max
    bad = np.flatnonzero((lam < -1e-12) | (lam > 1 + 1e-9))
    if bad.size:
        k = int(bad[0])
        p = float(rec.pressure[k])
        advice = ("the soft actuator balloons far below 0.5 MPa: pressures in kPa or Pa instead of MPa?" if p > 0.5
                  else "a negative pressure is not a load of this model" if p < 0 else
                  f"calibrate with --forward-pressure {float(np.max(rec.pressure)):g} (a forward ensemble up to the "
                  "recording's largest pressure)")
        raise RecordingError(f"{rec.source}: frame {rec.frames[k]} has pressure {p:g} MPa, outside the forward "
                             f"ensemble's range [0, {pressure_max:g}] MPa; {advice}")
    return np.clip(lam, 0.0, 1.0)


def validate_recording(config: CalibrationConfig) -> None:
    """Refuse a recording file that cannot be calibrated (unreadable, pressures outside the forward
    ensemble's range, points off the visible face) before any FE work or helper process starts."""
    if config.recording is None:
        return
    from torchfra.io.recordings import read_recording

    rec = read_recording(config.recording)
    fwd_cfg = forward_config(config)
    load_factors(rec, fwd_cfg.pressure)
    ActuatorSolver(config.resolution, rec, fwd_cfg)


def forecast_at_frames(Y_steps: np.ndarray, steps: np.ndarray, lam: np.ndarray, W, slots=None) -> np.ndarray:
    """Y_steps (N, S, P_fwd, 2) at load factors ``steps`` (S,) -> (N, K, P_rec, 2) at the frames'
    load factors ``lam`` (K,) and the recording's points (W: (P_rec, P_fwd) face interpolation).

    ``slots`` (K, J) (a ragged recording's layout, :func:`observation_layout`): frame k's entries
    are the points ``slots[k]`` (-1: an empty slot, forecast 0) -> (N, K, J, 2), computed a block of
    frames at a time, so memory follows the observations, not frames x points."""
    s = np.concatenate([[0.0], steps])
    Ys = np.concatenate([np.zeros_like(Y_steps[:, :1]), Y_steps], axis=1)
    i = np.clip(np.searchsorted(s, lam, side="right") - 1, 0, s.size - 2)
    w = ((lam - s[i]) / (s[i + 1] - s[i]))[None, :, None, None]
    if slots is not None:
        return _forecast_slots(Ys, i, w, W, slots)
    Yk = (1 - w) * Ys[:, i] + w * Ys[:, i + 1]  # (N, K, P_fwd, 2)
    N, K, P, C = Yk.shape
    flat = np.moveaxis(Yk, 2, 0).reshape(P, -1)
    return np.moveaxis((W @ flat).reshape(W.shape[0], N, K, C), 0, 2)


def _forecast_slots(Ys, i, w, W, slots, block_bytes: float = 64e6) -> np.ndarray:
    """:func:`forecast_at_frames` for a ragged layout: each slot's point from its few face nodes
    (the rows of W, padded to the longest), a block of frames at a time."""
    W = sp.csr_matrix(W)
    nnz = np.diff(W.indptr)
    T = max(int(nnz.max(initial=0)), 1)
    cols, vals = np.zeros((W.shape[0], T), dtype=np.int64), np.zeros((W.shape[0], T))
    filled = np.arange(T) < nnz[:, None]
    cols[filled], vals[filled] = W.indices, W.data  # CSR order is row by row: the same as the mask's
    N, P_fwd, C = Ys.shape[0], Ys.shape[2], Ys.shape[3]
    K, J = slots.shape
    out = np.zeros((N, K, J, C))
    per_frame = 8.0 * N * C * (P_fwd + 2 * J * T)
    step = max(1, int(block_bytes // per_frame))
    for k0 in range(0, K, step):
        k = np.arange(k0, min(K, k0 + step))
        Yk = (1 - w[:, k]) * Ys[:, i[k]] + w[:, k] * Ys[:, i[k] + 1]  # (N, b, P_fwd, C)
        ids = slots[k]
        c = cols[np.maximum(ids, 0)]  # (b, J, T)
        v = vals[np.maximum(ids, 0)] * (ids >= 0)[..., None]
        g = Yk[:, np.arange(len(k))[:, None, None], c]  # (N, b, J, T, C)
        out[:, k] = np.einsum("bjt,nbjtc->nbjc", v, g)
    return out


def observation_layout(rec: Recording, row: int):
    """The observed entries the filters see, frame by frame: ``(slots, Z)``. A recording that follows
    its points: ``slots`` None and Z its (K, P, 2). A ragged one: each frame's observed points in
    its slots, and one more slot, never observed (NaN), for the tracked point ``row`` so the filters
    forecast it in every frame for the figures without it weighing on any analysis."""
    if not rec.ragged:
        return None, rec.Z
    K = rec.n_frames
    slots = np.concatenate([rec.slots, np.full((K, 1), row, dtype=np.int64)], axis=1)
    Z = np.concatenate([rec.Z, np.full((K, 1, 2), np.nan)], axis=1)
    return slots, Z


def point_map(rec_op: ObservationOperator, fwd_op: ObservationOperator) -> sp.csr_matrix:
    """(P_rec, P_fwd) weights: recording points from the forward's observed face nodes."""
    W = rec_op.weights.tocsc()[:, fwd_op.point_ids]
    lost = np.asarray(rec_op.weights.sum(axis=1)).ravel() - np.asarray(W.sum(axis=1)).ravel()
    if np.abs(lost).max(initial=0) > 1e-9:
        raise ObservationError("recording points use face nodes the forward ensemble did not observe")
    return W.tocsr()


# -- the FE model at given parameters ----------------------------------------------------------------

class ActuatorSolver:
    """The actuator at resolution ``resolution`` with the parameter set of ``fwd``, observed at a
    recording's points."""

    def __init__(self, resolution: int, rec: Recording | None = None, fwd: ForwardConfig | None = None):
        self.fwd = with_deck(fwd or ForwardConfig(resolution=resolution))
        self.pset = parameter_set(self.fwd)
        self.model, self.info, self.deck_values = forward_model(self.fwd)
        self.model.finalize()
        self.mesh = self.model.mesh
        self.faces = observed_faces(self.mesh, self.fwd.camera, self.fwd.face)
        self.operator = None if rec is None else recording_operator(self.mesh, rec, faces=self.faces)

    def params(self, c10) -> dict[str, torch.Tensor]:
        c10 = torch.as_tensor(c10, dtype=torch.float64).reshape(-1)
        N = c10.shape[0]
        return {"C10": c10, "D1": 1.0 / (self.fwd.bulk_ratio * c10),
                "E_fiber": torch.full((N,), self.fwd.E_fiber, dtype=torch.float64),
                "P": torch.full((N,), self.fwd.pressure, dtype=torch.float64)}

    def params_q(self, Q: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every model parameter of the filters' coordinates Q (N, d) of the parameter set."""
        if self.pset.d == 1 and not self.fwd.parameters:  # the paper's prior: exactly as the C10 path
            return self.params(torch.exp(Q[:, 0]))
        return self.pset.model_parameters(Q, self.fwd.pressure, self.fwd.bulk_ratio, self.fwd.E_fiber,
                                          base=self.deck_values)

    def options(self, **kw) -> fem.NewtonOptions:
        return fem.NewtonOptions(**{**self.fwd.newton, **kw})


def synthetic_recording(c10, resolution: int = 1, points="nodes", noise: float = 1.0, seed: int = 0,
                        times=None, pressure=None, progress: bool = False, parameters=(), fixed=(), deck=None
                        ) -> tuple[Recording, np.ndarray]:
    """A recording made by the model itself at C10 = ``c10`` (or, with a parameter set ``parameters``
    / ``fixed`` as in :class:`ForwardConfig`, at the values ``c10 = {name: value}`` of its uncertain
    parameters): the FE model is solved at every frame's pressure (no interpolation in time),
    observed at ``points`` ("nodes" of the visible face, or a DIC-like grid spacing in mm), and
    perturbed with N(0, noise^2) per component. Returns the recording and its noise-free
    observations (K, P, 2). ``deck``: ``{"inp", "camera", "face"}`` of the user's own model (see
    :class:`ForwardConfig`); its ``pressure`` at load factor 1 is the deck's, ``pressure`` a trace
    up to it."""
    from torchfra.observation.operator import regular_grid

    times = frame_times(100) if times is None else np.asarray(times, dtype=np.float64)
    deck = with_deck(ForwardConfig(resolution=resolution, parameters=list(parameters), **deck)) if deck else None
    fwd = deck or ForwardConfig(resolution=resolution)
    pressure = fwd.pressure * times if pressure is None else np.asarray(pressure, dtype=np.float64)
    if deck is not None and np.max(pressure) > deck.pressure * (1 + 1e-9):
        raise ValueError(f"the pressure trace reaches {np.max(pressure):g} MPa, above the deck's {deck.pressure:g} MPa")
    solver = ActuatorSolver(resolution, fwd=ForwardConfig(resolution=resolution, pressure=float(np.max(pressure)),
                                                          parameters=list(parameters), fixed=list(fixed))
                            if deck is None else replace(deck, fixed=list(fixed)))
    mesh = solver.mesh
    faces = solver.faces
    if isinstance(points, str) and points == "nodes":
        op = ObservationOperator(mesh, faces, points="nodes")
    else:
        op = ObservationOperator(mesh, faces, points=regular_grid(mesh, faces, float(points)))
    lam = pressure / solver.fwd.pressure
    distinct = np.unique(lam[lam > 0])
    if isinstance(c10, dict):
        params = solver.params_q(solver.pset.values(c10))
        where = ", ".join(f"{k} = {v:g}" for k, v in c10.items())
    else:
        params, where = solver.params([c10]), f"C10 = {c10:g} MPa"
    sol = fem.solve(solver.model, params, distinct, solver.options(),
                    progress=f"synthetic recording: FE solve at {where}" if progress else False)
    if sol.status[0] != "converged":
        raise RuntimeError(f"the model did not converge at {where} (reached load {sol.load_reached[0]:.3f})")
    Y = op(sol.u[0, :, : mesh.n_nodes]).numpy()  # (distinct, P, 2)
    clean = np.zeros((len(times), op.n_points, 2))
    pos = lam > 0
    clean[pos] = Y[np.searchsorted(distinct, lam[pos])]
    rng = np.random.default_rng(seed)
    Z = clean + noise * rng.standard_normal(clean.shape)
    rec = Recording(np.arange(len(times)), times, pressure, np.asarray(op.point_ids), op.points, Z, "synthetic")
    return rec, clean


# -- restart filter: FE solves of the current ensemble ------------------------------------------------

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


def recording_digest(rec: Recording) -> str:
    """Fingerprint of a recording's content (checkpoints must not resume against other data)."""
    h = hashlib.sha256()
    for a in (rec.frames, rec.times, rec.pressure, rec.point_ids, rec.X, rec.Z):
        h.update(np.ascontiguousarray(a).tobytes())
    if rec.ragged:
        h.update(b"slots" + np.ascontiguousarray(rec.slots).tobytes())
    return h.hexdigest()


def config_dict(config: CalibrationConfig) -> dict:
    return json.loads(json.dumps(asdict(config)))


# -- the experiment ----------------------------------------------------------------------------------

FILTERS = ("hierarchical", "hierarchical_nonlinear", "restart", "exact")


def _stats(c10) -> dict[str, float]:
    from torchfra.assimilation import summarize

    return summarize(np.asarray(c10).reshape(-1))


def ensemble_stats(pset, Q: torch.Tensor) -> dict[str, dict[str, float]]:
    """Per parameter: mean, std, p10, p90 of an ensemble of coordinates Q (N, d)."""
    if pset.d == 1 and pset.priors[0].kind == "lognormal":
        return {pset.names[0]: _stats(torch.exp(Q[:, 0]))}  # the paper's path, to the last digit
    return {n: _stats(v) for n, v in pset.natural(Q).items()}


def natural_of(prior):
    """q -> parameter value on numpy arrays (exp for a lognormal prior)."""
    if prior.kind == "lognormal":
        return np.exp
    return lambda q: prior.natural(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


@dataclass
class ExactPosterior:
    """The exact posterior of a parameter set: ``raw`` the grid (1-D :class:`GridPosterior` or
    :class:`TensorPosterior`), per-parameter ``stats()`` in natural units."""

    raw: object
    names: list
    naturals: list

    @property
    def d(self) -> int:
        return len(self.names)

    def stats(self, step: int = -1) -> dict:
        if self.d == 1:
            return {self.names[0]: self.raw.stats(step, natural=self.naturals[0])}
        if step != -1:
            raise ValueError("the tensor-grid posterior is kept after the last frame only")
        return self.raw.stats()

    @property
    def log_evidence(self) -> float:
        return float(self.raw.log_evidence[-1]) if self.d == 1 else float(self.raw.log_evidence)

    def edge_mass(self) -> float:
        return self.raw.edge_mass() if self.d == 1 else float(self.raw.edge_mass)

    @property
    def prior_mass_outside(self) -> float:
        return float(self.raw.prior_mass_outside)

    def density(self, j: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(x, marginal pdf of parameter j)."""
        if self.d == 1:
            return self.raw.density(natural=self.naturals[0])
        q, dens = self.raw.marginal(j)
        x = np.asarray(self.naturals[j](q))
        jac = x if self.naturals[j] is np.exp else np.abs(np.gradient(x, q))  # dx/dq
        return x, dens / jac


class ExactReference:
    """The exact posterior's map through the forward members: for one parameter the cubic spline
    through them (a sweep, :class:`SweepMap`), for two or three the tensor-product Legendre map
    (:class:`~torchfra.assimilation.exact_nd.TensorMap`); each with its leave-one-out error."""

    def __init__(self, pset, Q0: torch.Tensor, Y: np.ndarray, grid: int = 4000):
        from torchfra.assimilation import SweepMap
        from torchfra.assimilation.exact_nd import TensorMap

        if pset.d > 6:
            raise ValueError(f"{pset.d} uncertain parameters: calibrate at most 6 at once")
        self.pset, self.d, self.grid = pset, pset.d, grid
        self.names = pset.names
        self.naturals = [natural_of(p) for p in pset.priors]
        m, sd = pset.gaussian()
        self.prior_mean, self.prior_std = m.numpy(), sd.numpy()
        if self.d == 1:
            self.map = SweepMap(Q0[:, 0].numpy(), Y)
            self.loo_error_rms = None
            self.kind = f"cubic spline through the {len(Q0)} forward members (a parameter sweep)"
        else:
            self.map = TensorMap(Q0.numpy(), Y)
            self.loo_error_rms = self.map.loo_error_rms
            basis = "per parameter" if self.map.basis == "tensor" else "in total"
            self.kind = (f"Legendre polynomial map of degree {self.map.degree} {basis}, least squares through the "
                         f"{len(Q0)} forward members; posterior "
                         + ("on a tensor grid along its principal axes" if self.d <= 3 else
                            "by importance sampling (t proposal at the Laplace point)"))

    @property
    def loo_error(self) -> float:
        """Largest leave-one-out error of the map through the members (units of Y)."""
        if self.d == 1:
            if not hasattr(self, "_loo"):
                self._loo = self.map.leave_one_out_error()
            return self._loo
        return self.map.loo_error

    def predict(self, Q) -> np.ndarray:
        """(N, d) coordinates -> (N, K, m) observations."""
        Q = np.asarray(Q, dtype=np.float64)
        return self.map(Q[:, 0]) if self.d == 1 else self.map(Q)

    def forecaster(self, frames):
        return self.map.forecaster(frames)

    def posterior(self, Z, r, frames=None) -> ExactPosterior:
        from torchfra.assimilation import grid_posterior
        from torchfra.assimilation.exact_nd import sampled_posterior, tensor_posterior

        if self.d > 3:
            raw = sampled_posterior(self.map, Z, r, self.prior_mean, self.prior_std, self.names, self.naturals,
                                    frames=frames)
        elif self.d == 1:
            raw = grid_posterior(self.map, Z, r, float(self.prior_mean[0]), float(self.prior_std[0]), self.grid,
                                 frames=frames)
        else:
            raw = tensor_posterior(self.map, Z, r, self.prior_mean, self.prior_std, self.names, self.naturals,
                                   frames=frames)
        return ExactPosterior(raw, list(self.names), self.naturals)

    def data_fit(self, post: ExactPosterior, Z, r) -> dict:
        from torchfra.assimilation import data_fit
        from torchfra.assimilation.exact_nd import data_fit_nd

        if self.d == 1:
            f = self.naturals[0]
            return data_fit(post.raw, self.map, Z, r, natural=math.exp if f is np.exp else lambda q: float(f(q)))
        return data_fit_nd(post.raw, self.map, Z, r)


def _load_recording(config: CalibrationConfig, run_dir: Path, progress: bool):
    """The recording to calibrate on, and its noise-free observations and truth when synthetic."""
    from torchfra.io.recordings import read_recording, write_recording

    if config.recording is not None:
        return read_recording(config.recording), None, None
    path, clean_path = run_dir / "recording.csv", run_dir / "recording_clean.npz"
    made_by = {k: getattr(config, k) for k in ("truth_c10", "noise", "noise_seed", "points", "frames", "pressure",
                                               "resolution")}
    if config.parameters:  # recordings of the paper's prior keep their old record
        made_by.update(parameters=config.parameters, fixed=config.fixed, truth=truth_values(config))
    truth = truth_values(config)
    if path.exists() and clean_path.exists():
        saved = json.loads(str(np.load(clean_path, allow_pickle=False)["made_by"]))
        if saved != json.loads(json.dumps(made_by)):
            raise RecordingError(f"{path} was made with other settings ({saved}); choose another --name, or "
                                 "delete the run folder's recording files to make a new one")
        return read_recording(path), np.load(clean_path, allow_pickle=False)["clean"], truth
    times = frame_times(config.frames)
    deck = {"inp": config.inp, "camera": config.camera, "face": config.face} if config.inp else None
    rec, clean = synthetic_recording(truth if config.parameters else config.truth_c10, config.resolution,
                                     config.points, config.noise, config.noise_seed, times, config.pressure * times,
                                     progress=progress, parameters=config.parameters, fixed=config.fixed, deck=deck)
    write_recording(path, rec)
    np.savez(clean_path.with_suffix(".tmp.npz"), clean=clean, made_by=json.dumps(made_by))
    clean_path.with_suffix(".tmp.npz").replace(clean_path)  # written last: marks the pair complete
    return read_recording(path), clean, truth


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
    from torchfra.forward import run_forward

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
