from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from torchfra import fem
from torchfra.actuator.candidates import BULK_RATIO, E_FIBER
from torchfra.actuator.geometry import ActuatorGeometry, build_actuator_model
from torchfra.observation.operator import ObservationOperator, frame_times, regular_grid, visible_faces
from torchfra.observation.recording import Recording
from torchfra.scenarios.calculix import _calculix_displacements, check_generator
from torchfra.scenarios.effects import (
    EFFECTS,
    PRESSURE_MAX,
    SENSOR_GAIN,
    VISCO_TAU1,
    _effect,
    build_model,
    knob_value,
    model_parameters,
)

GRID_SHIFT = (0.382, 0.618)  # grid offset along (y, z) as fractions of its spacing


CACHE_VERSION = 1  # bump when the way clean observations are made changes


def pressure_trace(kind: str, frames: int, pressure: float = PRESSURE_MAX) -> tuple[np.ndarray, np.ndarray]:
    """Normalized frame times (K,) and recorded pressures (K,) MPa: ``"ramp"`` rises linearly to
    ``pressure`` at t = 1, ``"cycle"`` rises to it at t = 1/2 and falls back to 0 at t = 1."""
    t = frame_times(frames)
    return t, pressure * _trace_shape(kind, t)


def _trace_shape(kind: str, t):
    if kind == "ramp":
        return np.clip(t, 0.0, 1.0)
    if kind == "cycle":
        return np.clip(1.0 - np.abs(2.0 * np.asarray(t) - 1.0), 0.0, 1.0)
    raise ValueError(f"unknown pressure trace {kind!r}; valid traces: ramp, cycle")


def true_pressure(effect: str, value: float, trace: str, times, pressure: float = PRESSURE_MAX) -> np.ndarray:
    """Pressure in the cavity (K,) MPa at the frames of the recorded ``trace`` (see ``pressure_trace``)."""
    recorded = pressure * _trace_shape(trace, np.asarray(times))
    if effect == "pressure_sensor":
        return SENSOR_GAIN * recorded + value
    if effect == "sensor_lag":
        return pressure * _trace_shape(trace, np.maximum(np.asarray(times) - value, 0.0))
    return recorded  # viscoelasticity: the body creeps under the recorded pressure (``clean_observations``)


def dic_grid(mesh, spacing: float) -> np.ndarray:
    """(P, 3) points on the camera-visible face x = +w_x/2: the regular grid of ``spacing`` mm
    shifted by ``GRID_SHIFT`` of the spacing in y and z; points pushed off the face are dropped."""
    faces = visible_faces(mesh, (1.0, 0.0, 0.0))
    grid = regular_grid(mesh, faces, spacing)
    face_X = mesh.nodes[np.unique(mesh.elements[faces[:, 0]])]
    front = face_X[np.isclose(face_X[:, 0], grid[0, 0])]
    grid[:, 1:] += spacing * np.asarray(GRID_SHIFT)
    lo, hi = front[:, 1:].min(0), front[:, 1:].max(0)
    inside = np.all((grid[:, 1:] > lo + 1e-9) & (grid[:, 1:] < hi - 1e-9), axis=1)
    return grid[inside]


_ARRAYS = ("clean", "points", "times", "recorded", "true", "mesh")


def face_observer(mesh, spacing: float) -> ObservationOperator:
    """The suite's camera (DESIGN §6): uy, uz on the face x = +8 mm at the DIC grid of ``spacing`` mm,
    whose points are not mesh nodes (``dic_grid``)."""
    return ObservationOperator(mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=dic_grid(mesh, spacing))


def reference_points(op: ObservationOperator, u_ref) -> np.ndarray:
    """Where the observer's points lie in the reference image (P, 3) mm: their positions on the body
    settled under its weight, ``X + u_ref`` (``u_ref``: (n_nodes, 3) or None for an unloaded reference)."""
    if u_ref is None:
        return op.points
    return op.points + op.weights @ np.asarray(u_ref)[: op.n_nodes]


def elastic_frames(model, params, lam: np.ndarray, options, op, progress=False):
    """The elastic body observed by ``op`` at the frames' load factors ``lam`` (K,): one FE solve
    through the distinct positive levels, no displacement at a frame whose level is 0. Returns
    (observations (K, P, 2) of the first member, the solve); the caller checks its status.
    A model whose weight acts before the reference image is observed from its settled state
    (``sol.u_reference``), as DIC measures it; its points then lie at :func:`reference_points`."""
    distinct = np.unique(lam[lam > 0])
    sol = fem.solve(model, params, distinct, options, progress=progress)
    u = sol.u[0, :, : model.mesh.n_nodes]
    if sol.u_reference is not None:
        u = u - sol.u_reference[0, : model.mesh.n_nodes]
    Y = op(u).numpy()  # (distinct, P, 2)
    frames = np.zeros((lam.size,) + Y.shape[1:])
    pos = lam > 0
    frames[pos] = Y[np.searchsorted(distinct, lam[pos])]
    return frames, sol


def _clean_key(effect, value, c10, resolution, spacing, frames, trace, pressure, generator="torchfra",
               points=None) -> dict:
    if value == EFFECTS[effect].null:  # an effect at its null is the base model: share its cache
        effect, value = "none", 0.0
    return {"effect": effect, "value": float(value), "c10": float(c10), "resolution": int(resolution),
            "spacing": float(spacing), "frames": int(frames), "trace": trace, "pressure": float(pressure),
            "grid_shift": list(GRID_SHIFT), "bulk_ratio": BULK_RATIO, "E_fiber": E_FIBER,
            "stagnation_tol": 1e-6, "version": CACHE_VERSION,
            **({"history": "fe_prony", "tau1": VISCO_TAU1} if effect == "viscoelasticity" else {}),
            **({"weight": "before_reference"} if effect == "gravity" else {}),
            **({"points": hashlib.sha256(np.ascontiguousarray(points, dtype=np.float64).tobytes()).hexdigest()[:16]}
               if points is not None else {}),
            **({"generator": "calculix", "element": "C3D20R", "fibers": "SPRINGA"} if generator == "calculix" else {})}


def clean_observations(effect: str, value: float, c10: float, resolution: int, spacing: float, frames: int,
                       trace: str, pressure: float = PRESSURE_MAX, cache_dir=None,
                       progress: bool = False, generator: str = "torchfra",
                       points=None) -> tuple[dict[str, np.ndarray], int]:
    """Noise-free observations of the scenario and what made them: arrays ``clean`` (K, P, 2) mm,
    ``points`` (P, 3) mm (in the reference image: on the body settled under its weight when the
    scenario has one), ``times``, ``recorded``, ``true`` (K,) MPa and ``mesh`` (elements, nodes,
    dofs of the generating model); returns ``(arrays, solves)`` with
    ``solves`` the FE solves made (0 when read from ``cache_dir``). ``generator``: ``"torchfra"`` or
    ``"calculix"`` (see the module's docstring). ``points``: observe at these (P, 3) mm instead of the
    DIC grid (located on the face without a tolerance: e.g. another scenario's settled points, for an SNR)."""
    check_generator(effect, generator)
    key = _clean_key(effect, value, c10, resolution, spacing, frames, trace, pressure, generator, points)
    text = json.dumps(key, sort_keys=True)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"{key['effect']}_{digest}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as f:
                if str(f["key"]) == text:
                    return {k: f[k] for k in _ARRAYS}, 0
    effect, value = key["effect"], key["value"]
    times, recorded = pressure_trace(trace, frames, pressure)
    p_true = true_pressure(effect, value, trace, times, pressure)
    if np.any(p_true < 0):
        raise ValueError(f"effect {effect!r} at {value:g} makes negative true pressures; choose a smaller size")
    # CalculiX has no hybrid brick: its scenarios are C3D20R, displacement bricks with 2x2x2 points
    model_kw = dict(formulation="displacement", integration="reduced") if generator == "calculix" else {}
    model, info = (build_actuator_model(ActuatorGeometry(resolution=resolution), **model_kw) if effect == "none"
                   else build_model(effect, value, resolution, **model_kw))
    mesh = info["mesh"]
    op = face_observer(mesh, spacing) if points is None else ObservationOperator(
        mesh, visible_faces(mesh, (1.0, 0.0, 0.0)), points=points, tol=np.inf)
    seen_at = op.points
    P_load = float(p_true.max())
    params = {k: torch.tensor([v], dtype=torch.float64)
              for k, v in {**model_parameters(effect, value, c10), "P": P_load}.items()}
    lam = p_true / P_load
    options = fem.NewtonOptions(stagnation_tol=key["stagnation_tol"])
    if effect == "viscoelasticity":  # history variables: march through the frames' times from rest at t = 0
        params.update({"g1": torch.tensor([value], dtype=torch.float64),
                       "tau1": torch.tensor([VISCO_TAU1], dtype=torch.float64)})
        hist = fem.solve_history(model, params, times, lam, options=options,
                                 progress="creeping body, FE history" if progress else False)
        if hist.status[0] != "converged":
            raise RuntimeError(f"scenario {effect} at {value:g} did not converge (C10 = {c10}, resolution "
                               f"{resolution}, reached t = {hist.time_reached[0]:.3f} of the trace); choose a "
                               "smaller size")
        clean = op(hist.u[0, :, : mesh.n_nodes]).numpy()
    elif generator == "calculix":
        # without a cache the deck goes to a temporary folder, removed once solved (kept when CalculiX
        # fails: the error names it)
        scratch = None if cache_dir is not None else Path(tempfile.mkdtemp(prefix="torchfra_calculix_"))
        deck_dir = (Path(cache_dir) if scratch is None else scratch) / "calculix" / f"{key['effect']}_{digest}"
        values = {k: float(v[0]) for k, v in params.items()}
        U, U_ref = _calculix_displacements(model, values, lam, mesh.n_nodes, deck_dir,
                                           f"torchfra scenario {effect} = {value:g}, C10 = {c10:g} MPa, "
                                           f"resolution {resolution}")
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
        clean = op(torch.as_tensor(U if U_ref is None else U - U_ref)).numpy()
        if points is None:
            seen_at = reference_points(op, U_ref)
    else:
        clean, sol = elastic_frames(model, params, lam, options, op, progress)
        if sol.status[0] != "converged":
            raise RuntimeError(f"scenario {effect} at {value:g} did not converge (C10 = {c10}, resolution "
                               f"{resolution}, reached {sol.load_reached[0]:.3f} of {P_load:g} MPa); choose a "
                               "smaller size")
        if points is None:
            seen_at = reference_points(op, None if sol.u_reference is None else sol.u_reference[0].numpy())
    arrays = {"clean": clean, "points": seen_at, "times": times, "recorded": recorded, "true": p_true,
              "mesh": np.array([mesh.n_elements, mesh.n_nodes, info["dofs"]])}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")  # ranks of a torchrun suite may write at once
        np.savez(tmp, key=np.array(text), **arrays)
        tmp.replace(path)
    return arrays, 1


def correlation_factor(points: np.ndarray, length: float) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor L (P, P) of the squared-exponential correlation
    ``exp(-|X_i - X_j|^2 / (2 length^2))`` between points, and the diagonal jitter it needed (the
    matrix is numerically singular for lengths above the spacing)."""
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    C = np.exp(-d2 / (2.0 * length**2))
    for jitter in 10.0 ** np.arange(-12, -1):
        try:
            return np.linalg.cholesky(C + jitter * np.eye(len(C))), float(jitter)
        except np.linalg.LinAlgError:
            continue
    raise ValueError(f"the correlation matrix of length {length} mm has no Cholesky factor even with jitter")


def observation_noise(points: np.ndarray, frames: int, sigma: float, length: float,
                      rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Noise (K, P, 2) mm: N(0, sigma^2) i.i.d. when ``length`` is 0, else correlated between points
    with the squared-exponential correlation of ``length`` mm (same std), independent across frames
    and components. Returns the noise and the jitter of the correlation factor (0 if i.i.d.)."""
    e = rng.standard_normal((frames, 2, len(points)))
    if length == 0:
        return sigma * e.transpose(0, 2, 1), 0.0
    L, jitter = correlation_factor(points, length)
    return sigma * np.einsum("pq,kcq->kpc", L, e) / math.sqrt(1.0 + jitter), jitter


DEFAULT_CACHE = Path("runs") / "scenarios" / "clean"


def make_scenario(effect: str, size, truth_c10: float = 0.0062, noise: float = 1.0, seed: int = 0,
                  resolution: int = 2, spacing: float = 2.0, correlation: float = 0.0, frames: int = 20,
                  trace: str | None = None, pressure: float = PRESSURE_MAX, cache_dir=DEFAULT_CACHE,
                  progress: bool = False, generator: str = "torchfra") -> tuple[Recording, np.ndarray, dict]:
    """A recording of the actuator with ``effect`` at ``size`` (see ``knob_value``) concealed in it.

    truth_c10 (MPa), noise: sigma (mm), seed: of the noise, resolution: of the generating mesh,
    spacing: of the DIC grid (mm), correlation: length ell (mm) of the noise's correlation (0:
    i.i.d.), frames: K, trace: the recorded pressure trace, "ramp" or "cycle" (default: the effect's,
    a cycle for sensor_lag, else a ramp; see ``pressure_trace``), pressure: the largest recorded
    pressure (MPa), cache_dir: where noise-free observations are kept (None: nowhere), generator: the code that
    solves the scenario, ``"torchfra"`` or ``"calculix"`` (see the module's docstring).
    Returns ``(recording, clean (K, P, 2), meta)``; ``meta`` holds the effect, its parameter values,
    the SNR measured against the base model at the same C10 and trace, the generation mesh, the
    trace, the noise model and the FE solves this call made.
    """
    e = _effect(effect)
    value = knob_value(effect, size)
    if not (noise > 0 and correlation >= 0 and truth_c10 > 0 and frames >= 1 and spacing > 0):
        raise ValueError(f"need noise > 0, correlation >= 0, truth_c10 > 0, frames >= 1 and spacing > 0; got "
                         f"noise={noise}, correlation={correlation}, truth_c10={truth_c10}, frames={frames}, "
                         f"spacing={spacing}")
    trace = e.trace if trace is None else trace
    _trace_shape(trace, 0.0)
    t0 = time.perf_counter()
    check_generator(effect, generator)
    setting = dict(c10=truth_c10, resolution=resolution, spacing=spacing, frames=frames, trace=trace,
                   pressure=pressure, cache_dir=cache_dir, progress=progress, generator=generator)
    arrays, solves = clean_observations(effect, value, **setting)
    if value == e.null:
        snr = 0.0
    else:
        # the base model seen where the recording's points are (a weight's settled points need not be the grid's)
        null, more = clean_observations("none", 0.0, **setting,
                                        points=None if effect != "gravity" else arrays["points"])
        solves += more
        snr = float(np.linalg.norm(arrays["clean"] - null["clean"]) / noise)
    clean, points = arrays["clean"], arrays["points"]
    err, jitter = observation_noise(points, frames, noise, correlation, np.random.default_rng(seed))
    rec = Recording(np.arange(frames), arrays["times"], arrays["recorded"], np.arange(len(points)), points,
                    clean + err, "synthetic scenario")  # the source must not tell the diagnosis the effect
    parameters = model_parameters(effect if value != e.null else "none", value, truth_c10)
    if effect in ("pressure_sensor", "sensor_lag"):
        parameters.update({"pressure_gain": SENSOR_GAIN, "pressure_offset": value} if effect == "pressure_sensor"
                          else {"tau": value})
    if effect == "viscoelasticity":
        parameters.update({"g1": value, "tau1": VISCO_TAU1})
    meta = {
        "effect": effect, "kind": e.kind, "expected": e.expected, "size": size, "knob": e.parameter,
        "value": value, "unit": e.unit, "parameters": parameters, "truth_c10": truth_c10, "snr": snr,
        "snr_res1_table": dict(zip(range(1, len(e.snr) + 1), e.snr)),
        "generation": {"generator": generator, "resolution": resolution, "elements": int(arrays["mesh"][0]),
                       "nodes": int(arrays["mesh"][1]),
                       "dofs": int(arrays["mesh"][2]), "spacing_mm": spacing, "grid_shift": list(GRID_SHIFT),
                       "points": len(points), "frames": frames},
        "trace": {"kind": trace, "pressure_max": pressure, "times": arrays["times"].tolist(),
                  "recorded": arrays["recorded"].tolist(), "true": arrays["true"].tolist()},
        "noise": {"sigma": noise, "seed": seed, "correlation_length": correlation, "jitter": jitter,
                  "model": "iid normal" if correlation == 0 else "squared-exponential correlation between points"},
        "solves": solves, "seconds": time.perf_counter() - t0,
    }
    return rec, clean, meta

