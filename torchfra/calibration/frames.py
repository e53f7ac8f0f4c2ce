"""Frames of a recording tied to the model by their pressure.

The body is hyperelastic and loaded quasi-statically, so its state depends on the current pressure only:
the FE response at a frame is the forward solution at load factor ``pressure / P_forward``, interpolated
between the forward's load steps (:func:`forecast_at_frames`), seen at the recording's points
(:func:`recording_operator`, :func:`point_map`). A frame whose pressure exceeds the forward's is refused."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from torchfra import fem
from torchfra.actuator.deck import observed_faces
from torchfra.calibration.config import CalibrationConfig, ForwardConfig
from torchfra.calibration.forward import forward_config, forward_model, parameter_set, with_deck
from torchfra.observation.operator import ObservationError, ObservationOperator, visible_faces
from torchfra.observation.recording import Recording, RecordingError


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

